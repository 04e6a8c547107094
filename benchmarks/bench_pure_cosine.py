"""Does any refinement make the displacement worse than none? (issue 19, point 5)

Run from the repository root::

    python3 benchmarks/bench_pure_cosine.py

An independent ray-traced pair, made by the project's own forward model: two
crossed pure cosines (``forward.CrossedCosines``: no square-wave harmonics,
no mixing terms), 8 px period in the image both ways, rotated 9 deg; Bessel-J0
ring waves (``forward.RingWaves``) 7 mm long on the surface (40 px = 5
carrier periods along the rows), up to 1.8 px displacement (carrier phase
1.4 rad).  Printed: the full-grid relative RMS displacement error per method
(interior, 8 % and 15 % margins), 8-bit and float frames.  About 20 s.
"""

from __future__ import annotations

import math
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from processing import forward as F  # noqa: E402
from processing.geometry import Geometry  # noqa: E402
from processing.reconstruct import Reconstructor  # noqa: E402

GEOMETRY = Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False)
N = 256
PATTERN = F.CrossedCosines(period_mm=0.8, rotation_deg=9.0, stretch_y=1.0 / math.cos(math.radians(55.0)))
RINGS = F.RingWaves(amplitude_mm=0.00033, wavelength_mm=7.0)
METHODS = [
    ("no refinement (refine_iterations=0)", dict(refine_iterations=0)),
    ("FD refinement, 1 iteration", dict(refine_method="fd")),
    ("FD refinement, 2 iterations", dict(refine_method="fd", refine_iterations=2)),
    ("image matching (refine_method='image')", dict(refine_method="image")),
    ("default: Reconstructor(reference, geometry)", {}),
]


def displacement_error(res, u_true, margin):
    R, C = np.meshgrid(res.rows_px, res.cols_px, indexing="ij")
    inner = res.valid & (R > margin * N) & (R < (1 - margin) * N) & (C > margin * N) & (C < (1 - margin) * N)
    if res.grid != "full":
        u_true = F.true_displacement(RINGS, GEOMETRY, (N, N), rows_px=res.rows_px, cols_px=res.cols_px)[0]
    d = (res.displacement - u_true)[:, inner]
    return 100.0 * float(np.sqrt(np.mean(d**2)) / np.sqrt(np.mean(u_true[:, inner] ** 2)))


def main():
    ref, _ = F.render_tir(F.FlatSurface(), GEOMETRY, (N, N), PATTERN, supersample=2)
    img, _ = F.render_tir(RINGS, GEOMETRY, (N, N), PATTERN, supersample=2)
    u_true, _ = F.true_displacement(RINGS, GEOMETRY, (N, N))
    print(f"pure cosines 8 px, rotated 9 deg; J0 ring waves: max |u| {np.hypot(*u_true).max():.2f} px")
    print("full-grid relative RMS displacement error (%), interior")
    print(f"{'method':44s} {'8-bit 8%':>9s} {'8-bit 15%':>10s} {'float 8%':>9s} {'float 15%':>10s}")
    pairs = ((F.quantize(ref, bits=8), F.quantize(img, bits=8)), (ref, img))
    rows = METHODS + [("decimated grid (live)", dict(grid="decimated"))]
    for label, kw in rows:
        cells = []
        for r, i in pairs:
            res = Reconstructor(r, GEOMETRY, **kw)(i)
            cells += [displacement_error(res, u_true, 0.08), displacement_error(res, u_true, 0.15)]
        print(f"{label:44s} {cells[0]:9.2f} {cells[1]:10.2f} {cells[2]:9.2f} {cells[3]:10.2f}", flush=True)


if __name__ == "__main__":
    main()
