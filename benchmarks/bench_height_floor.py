"""The floor of the displacement-to-height step, and what second-order optics would take off it.

Run from the repository root::

    python3 benchmarks/bench_height_floor.py

The exact displacement of ray-traced dimples (``forward.true_displacement``, no
images, no demodulation) on the decimated grid of a 2 mm board at 256^2 is
solved for the heights by the Reconstructor's own height solver
(``processing.height.solver_for``): the error left (the accuracy table's
measure: interior, null space removed) is what no better displacement can
take off.  It grows with the displacement (the linear model ``u = a h + B
grad h`` of notes.md is first order).  Then the same solve after removing two
second-order terms, each computed from the first solve's heights (a
measurement of what ``processing.second_order.SecondOrderOptics`` does):

* the reflection's nonlinearity in the slope: the exact trace of the surface
  taken as a plane at each sample (its height and gradient), less its linear
  part (the same trace of the heights scaled by 1e-3, divided by 1e-3);
* the hit point's move with the height: pixel ``r``'s ray meets the raised
  surface at ``X0 + t h`` (``t = d_xy / d_z`` of the camera ray), so the
  heights seen on the pixel grid, ``H(X0) = h(X0 + t H)``, have the gradient
  ``grad h (1 + t . grad h)`` to second order: the displacement's slope part
  scaled by ``1 + t . grad h``.

The two have opposite signs, so the linear model's floor is what is left of
their difference: either alone is no better (the nonlinearity 0.190 -> 0.139 %
on the accuracy table's deep dimple, 15 um, sigma 9 mm, telecentric, but worse
with the camera at 1.5 m; the hit point alone worse everywhere); both together
take off 95-98 % in every geometry here: 0.190 -> 0.003 %, 60 um 1.509 ->
0.083 % (5 Dec 2026).  About 20 s.  Image matching's final solve now does this
(``processing.second_order``) where the slopes make it count.
"""

from __future__ import annotations

import dataclasses
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from benchmarks.bench_processing import rel_height_error  # noqa: E402
from processing import forward as F  # noqa: E402
from processing.geometry import Geometry  # noqa: E402
from processing.height import solver_for  # noqa: E402
from processing.reconstruct import Reconstructor  # noqa: E402
from processing.second_order import SecondOrderOptics  # noqa: E402

N = 256
GEOMETRIES = {
    "theta 55, telecentric": Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False),
    "theta 55, rows towards the camera": Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=True),
    "theta 60, camera at 1.5 m": Geometry(theta_deg=60, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False,
                                          camera_distance_mm=1500.0),
}
DIMPLES = ((0.001, 9.0), (0.005, 4.0), (0.015, 9.0), (0.03, 4.0), (0.06, 4.0))


class Grid:
    """A decimated grid of the Reconstructor, its height solver and second-order optics."""

    def __init__(self, geometry):
        board = F.Checkerboard(period_mm=2.0, edge_softness_mm=0.1)
        ref, _ = F.render_tir(F.FlatSurface(), geometry, (N, N), board, supersample=1)
        self.template = Reconstructor(ref, geometry)(ref, grid="decimated")
        self.g = geometry
        rows_px, cols_px = self.template.rows_px, self.template.cols_px
        self.solver = solver_for(geometry, rows_px, cols_px, (N, N))
        self.optics = SecondOrderOptics(geometry, rows_px, cols_px, (N, N), self.solver.x_mm, self.solver.y_mm)
        self.valid = np.ones((rows_px.size, cols_px.size), bool)

    def solve(self, u):
        return np.asarray(self.solver.solve(np.asarray(u, np.float32), self.valid).height_mm, np.float64)

    def error(self, h, surface):
        res = dataclasses.replace(self.template, height=h.astype(np.float32), valid=self.valid)
        return rel_height_error(res, surface, self.g)


def main() -> int:
    print("height error (%) of the exact displacement solved for the heights; 256^2, 2 mm board's decimated grid")
    print(f"{'geometry':36s} {'dimple':>16s} {'max |u| px':>10s} {'linear':>8s} {'-nonlin.':>9s} "
          f"{'hit pt':>7s} {'both':>7s}")
    for name, geometry in GEOMETRIES.items():
        grid = Grid(geometry)
        for depth_mm, sigma_mm in DIMPLES:
            surface = F.Dimple(depth_mm, sigma_mm)
            u = F.true_displacement(surface, geometry, (N, N), rows_px=grid.template.rows_px,
                                    cols_px=grid.template.cols_px)[0]
            h1 = grid.solve(u)
            nonlinear = grid.optics.nonlinear_part(h1, grid.valid)
            spacing = grid.optics.spacing_scale(h1, grid.valid)
            cells = [grid.error(h1, surface), grid.error(grid.solve(u - nonlinear), surface),
                     grid.error(grid.solve(u * spacing), surface),
                     grid.error(grid.solve((u - nonlinear) * spacing), surface)]
            print(f"{name:36s} {1e3 * depth_mm:6.0f} um s{sigma_mm:3.0f} mm {np.nanmax(np.abs(u)):10.1f} "
                  + "".join(f"{c:8.3f}" for c in cells))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
