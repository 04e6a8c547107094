"""Does any refinement make the displacement worse than none? (issue 19, point 5)

Run from the repository root::

    python3 benchmarks/bench_pure_cosine.py

An independent ray-traced pair, made by the project's own forward model: two
crossed pure cosines (``forward.CrossedCosines``: no square-wave harmonics,
no mixing terms), 8 px period in the image both ways, rotated 9 deg; Bessel-J0
ring waves (``forward.RingWaves``) 7 mm long on the surface (40 px = 5
carrier periods along the rows), up to 1.8 px displacement (carrier phase
1.4 rad).  Printed: the full-grid relative RMS displacement error per method
(interior, 8 % and 15 % margins: the accuracy table's rule is 8 %), 8-bit and
float frames; then where the error is (float frames): by distance from the
frame's edge in carrier periods (8 px) and by component, each band's RMS
error over the RMS displacement of the 8 % interior.  About 20 s.

``--interpolation lanczos`` runs the full grid with cv2's Lanczos4 resize
(before issue 19's spline) for comparison; ``--size 512`` a 512^2 frame (the 8 %
margin is then 5 carrier periods: the border bands of docs/processing.md
section 6 fall outside). The last two columns are the height error (the
accuracy table's measure: interior, 8 % margin, null space removed), which is
what image matching fits: its displacement is the height's (``u = a h + B grad
h``), so it can be the best height with a larger displacement error.
"""

from __future__ import annotations

import math
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from benchmarks.bench_processing import rel_height_error  # noqa: E402
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


#: Bands of distance from the frame's edge, in carrier periods (8 px); the 8 % margin is 2.56 periods.
BANDS = ((0, 1), (1, 2), (2, 2.56), (2.56, 3), (3, 4), (4, 6), (6, 99))
PERIOD_PX = 8.0


def band_errors(u, u_true, period_px, valid=None):
    """``(interior, by band, (row, col))`` of a square frame's displacement ``u`` (2, n, n): the
    RMS error over the 8 % interior, per band of distance from the edge (:data:`BANDS`, in
    carrier periods of ``period_px``) and per component (8 % interior), each over the RMS
    displacement of the 8 % interior, %; ``valid`` (n, n): the samples that count (None: all)."""
    n = u.shape[1]
    valid = np.ones(u.shape[1:], bool) if valid is None else valid
    r = np.arange(n)
    edge = np.minimum.outer(np.minimum(r, n - 1 - r), np.minimum(r, n - 1 - r)) / period_px
    R, C = np.meshgrid(r, r, indexing="ij")
    inner = valid & (R > 0.08 * n) & (R < 0.92 * n) & (C > 0.08 * n) & (C < 0.92 * n)
    norm = np.sqrt(np.mean(u_true[:, inner] ** 2))
    e = u - u_true
    interior = 100 * np.sqrt(np.mean(e[:, inner] ** 2)) / norm
    bands = [100 * np.sqrt(np.mean(e[:, valid & (edge >= lo) & (edge < hi)] ** 2)) / norm for lo, hi in BANDS]
    parts = [100 * np.sqrt(np.mean(e[i][inner] ** 2)) / norm for i in range(2)]
    return interior, bands, parts


def where_the_error_is(res, u_true):
    """``(by band, (row, col))`` of :func:`band_errors` for a full-grid result."""
    _, bands, parts = band_errors(res.displacement, u_true, PERIOD_PX, res.valid)
    return bands, parts


def main(argv=None):
    import argparse

    global N

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--interpolation", default="spline", choices=("spline", "lanczos"),
                    help="full-grid interpolation (full_interpolation)")
    ap.add_argument("--size", type=int, default=256, help="frame side, pixels (default 256)")
    args = ap.parse_args(argv)
    N = args.size
    ref, _ = F.render_tir(F.FlatSurface(), GEOMETRY, (N, N), PATTERN, supersample=2)
    img, _ = F.render_tir(RINGS, GEOMETRY, (N, N), PATTERN, supersample=2)
    u_true, _ = F.true_displacement(RINGS, GEOMETRY, (N, N))
    print(f"pure cosines 8 px, rotated 9 deg; J0 ring waves: max |u| {np.hypot(*u_true).max():.2f} px")
    print(f"{N}^2; full-grid relative RMS displacement error (%), interior; height error (%)")
    print(f"{'method':44s} {'8-bit 8%':>9s} {'8-bit 15%':>10s} {'float 8%':>9s} {'float 15%':>10s}"
          f" {'h 8-bit':>8s} {'h float':>8s}")
    pairs = ((F.quantize(ref, bits=8), F.quantize(img, bits=8)), (ref, img))
    rows = METHODS + [("decimated grid (live)", dict(grid="decimated"))]
    where = []
    for label, kw in rows:
        cells, heights = [], []
        for r, i in pairs:
            res = Reconstructor(r, GEOMETRY, full_interpolation=args.interpolation, **kw)(i)
            cells += [displacement_error(res, u_true, 0.08), displacement_error(res, u_true, 0.15)]
            heights.append(rel_height_error(res, RINGS, GEOMETRY))
        if res.grid == "full" and kw:
            where.append((label, where_the_error_is(res, u_true)))
        print(f"{label:44s} {cells[0]:9.2f} {cells[1]:10.2f} {cells[2]:9.2f} {cells[3]:10.2f}"
              f" {heights[0]:8.2f} {heights[1]:8.2f}", flush=True)
    print("where the error is, float frames: RMS error (% of the interior's RMS u) by distance from the edge")
    print(f"{'(carrier periods; the 8 % margin is 2.56)':44s}" + "".join(f"{f'{lo}-{hi}':>7s}" for lo, hi in BANDS)
          + "    u_row  u_col")
    for label, (bands, parts) in where:
        print(f"{label:44s}" + "".join(f"{b:7.2f}" for b in bands) + f"  {parts[0]:7.2f} {parts[1]:6.2f}")


if __name__ == "__main__":
    main()
