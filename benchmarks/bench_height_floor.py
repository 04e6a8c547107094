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
measurement, not yet what the Reconstructor does):

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
0.083 % (5 Dec 2026).  About 20 s.
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

N = 256
EPS = 1e-3  # scale of the linear part's trace
GEOMETRIES = {
    "theta 55, telecentric": Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False),
    "theta 55, rows towards the camera": Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=True),
    "theta 60, camera at 1.5 m": Geometry(theta_deg=60, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False,
                                          camera_distance_mm=1500.0),
}
DIMPLES = ((0.001, 9.0), (0.005, 4.0), (0.015, 9.0), (0.03, 4.0), (0.06, 4.0))


class _LocalPlanes:
    """The surface as a plane at each ray: height ``h`` and gradient ``(gx, gy)`` (image frame) through
    the ray's point on the flat surface ``(x0, y0)`` (arrays of the rays' shape)."""

    def __init__(self, h, gx, gy, x0, y0):
        self.h, self.gx, self.gy, self.x0, self.y0 = h, gx, gy, x0, y0

    def height_and_gradient(self, x, y):
        return self.h + self.gx * (x - self.x0) + self.gy * (y - self.y0), self.gx, self.gy


class Grid:
    """A decimated grid of the Reconstructor, its height solver and camera rays."""

    def __init__(self, geometry):
        board = F.Checkerboard(period_mm=2.0, edge_softness_mm=0.1)
        ref, _ = F.render_tir(F.FlatSurface(), geometry, (N, N), board, supersample=1)
        self.template = Reconstructor(ref, geometry)(ref, grid="decimated")
        self.g = geometry
        self.rows, self.cols = np.meshgrid(self.template.rows_px, self.template.cols_px, indexing="ij")
        self.solver = solver_for(geometry, self.template.rows_px, self.template.cols_px, (N, N))
        origin, d = geometry.camera_rays(self.rows, self.cols, (N, N))
        self.x0, self.y0 = geometry.surface_point(self.rows, self.cols, (N, N))
        # hit point's move per mm of height, image frame (x along the columns, y = row_sign * canonical y)
        self.t = np.stack([d[..., 0] / d[..., 2], geometry.row_sign * d[..., 1] / d[..., 2]])
        self.valid = np.ones(self.rows.shape, bool)

    def gradient(self, h):
        gy, gx = np.gradient(h, self.solver.y_mm, self.solver.x_mm)
        return gx, gy

    def trace(self, h):
        """Exact displacement (px) of the local planes of heights ``h``."""
        gx, gy = self.gradient(h)
        pat, _, _, _, _ = F.trace_tir(_LocalPlanes(h, gx, gy, self.x0, self.y0), self.g, self.rows, self.cols, (N, N))
        r0, c0 = self.g.pixel_of_pattern_point(pat[..., 0], pat[..., 1], (N, N))
        return np.stack([self.rows - r0, self.cols - c0])

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
            nonlinear = grid.trace(h1) - grid.trace(EPS * h1) / EPS
            gx, gy = grid.gradient(h1)
            spacing = 1.0 + grid.t[0] * gx + grid.t[1] * gy
            cells = [grid.error(h1, surface), grid.error(grid.solve(u - nonlinear), surface),
                     grid.error(grid.solve(u * spacing), surface),
                     grid.error(grid.solve((u - nonlinear) * spacing), surface)]
            print(f"{name:36s} {1e3 * depth_mm:6.0f} um s{sigma_mm:3.0f} mm {np.nanmax(np.abs(u)):10.1f} "
                  + "".join(f"{c:8.3f}" for c in cells))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
