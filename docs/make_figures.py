"""Make docs/needle.png: the real FS-SS needle pair processed by tirdeflect.

Rerun from the repository root::

    python3 docs/make_figures.py            # writes docs/needle.png, prints figures

Input: tests/data/fsss-needle-waves, the copy the repository carries (or
$TIRDEFLECT_DATA/fsss-needle-waves):
``reference_2.png`` (flat water) and ``202406_1457001661.bmp`` (ring waves from
a needle, upper right). Geometry from that folder's README (classic FS-SS, the
pattern seen through the water from above): checkerboard square 2.2 mm; layers
from the pattern up: 5.7 cm air (n 1.0003), 1.2 cm glass (n 1.48899), 4.3 cm
water (n 1.34); 80 cm air to the camera; 0.207 mm per pixel.

The figure has three panels: reference, frame, height map (micrometres, colour
bar, NaN = masked shown grey). Only OpenCV draws it (no matplotlib).
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

DATA = Path(os.environ.get("TIRDEFLECT_DATA", ROOT / "tests" / "data"))
NEEDLE = DATA / "fsss-needle-waves"

#: FS-SS geometry of the needle data set, from its README.
NEEDLE_GEOMETRY = {
    "setup": "fsss",
    "pixel_mm": 0.207,
    "fsss_layers": [[57.0, 1.0003], [12.0, 1.48899], [43.0, 1.34]],
    "n_water": 1.34,
    "n_air": 1.0003,
    "fsss_camera_distance_mm": 800.0,
}

PANEL = 512          # pixels per panel side in the figure
TITLE_H = 44
FONT = cv2.FONT_HERSHEY_SIMPLEX


def needle_geometry():
    """The FS-SS :class:`processing.Geometry` of the needle images."""
    from processing import Geometry

    return Geometry.from_dict(dict(NEEDLE_GEOMETRY))


# ----------------------------------------------------------------- drawing helpers


def _grey_panel(image: np.ndarray) -> np.ndarray:
    img = image.astype(np.float32)
    lo, hi = np.percentile(img, [0.5, 99.5])
    img = np.clip((img - lo) / max(hi - lo, 1e-9) * 255.0, 0, 255).astype(np.uint8)
    img = cv2.resize(img, (PANEL, PANEL), interpolation=cv2.INTER_AREA)
    return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)


def _diverging_lut() -> np.ndarray:
    """256-entry BGR lookup table: dark blue - white - dark red (heights, signed)."""
    stops = np.array([0.0, 0.25, 0.5, 0.75, 1.0])
    rgb = np.array([[5, 48, 97], [67, 147, 195], [247, 247, 247], [214, 96, 77], [103, 0, 31]], float)
    x = np.linspace(0.0, 1.0, 256)
    lut = np.stack([np.interp(x, stops, rgb[:, i]) for i in (2, 1, 0)], axis=-1)  # BGR
    return np.round(lut).astype(np.uint8).reshape(256, 1, 3)


def _apply_lut(img8: np.ndarray) -> np.ndarray:
    return cv2.LUT(cv2.cvtColor(img8, cv2.COLOR_GRAY2BGR), _diverging_lut())


def _height_panel(height_um: np.ndarray, limit_um: float) -> np.ndarray:
    valid = np.isfinite(height_um)
    norm = np.zeros(height_um.shape, np.float32)
    norm[valid] = (height_um[valid] + limit_um) / (2 * limit_um)
    img8 = np.clip(norm * 255.0, 0, 255).astype(np.uint8)
    colour = _apply_lut(img8)
    colour[~valid] = (128, 128, 128)
    return cv2.resize(colour, (PANEL, PANEL), interpolation=cv2.INTER_AREA)


def _colour_bar(limit_um: float, height: int) -> np.ndarray:
    width = 110
    bar = np.full((height, width, 3), 255, np.uint8)
    top, bottom = 20, height - 20
    ramp = np.linspace(255, 0, bottom - top).astype(np.uint8)[:, None]
    ramp = _apply_lut(np.ascontiguousarray(np.repeat(ramp, 22, axis=1)))
    bar[top:bottom, 8:30] = ramp
    cv2.rectangle(bar, (8, top), (29, bottom - 1), (0, 0, 0), 1)
    for frac in (0.0, 0.25, 0.5, 0.75, 1.0):
        y = int(round(top + frac * (bottom - top - 1)))
        value = limit_um * (1 - 2 * frac)
        cv2.line(bar, (30, y), (36, y), (0, 0, 0), 1)
        cv2.putText(bar, f"{value:+.0f}", (39, y + 5), FONT, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(bar, "um", (39, top - 6), FONT, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return bar


def _titled(panel: np.ndarray, title: str) -> np.ndarray:
    head = np.full((TITLE_H, panel.shape[1], 3), 255, np.uint8)
    cv2.putText(head, title, (8, 29), FONT, 0.62, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([head, panel])


def _scale_bar(panel: np.ndarray, mm_per_px_panel: float, length_mm: float = 50.0) -> None:
    n = int(round(length_mm / mm_per_px_panel))
    y = panel.shape[0] - 14
    cv2.line(panel, (12, y), (12 + n, y), (255, 255, 255), 3)
    cv2.putText(panel, f"{length_mm:.0f} mm", (12, y - 8), FONT, 0.5, (255, 255, 255), 1, cv2.LINE_AA)


def compose(reference, frame, height_mm, *, pixel_mm: float, caption: str,
            height_title: str = "height h (um), grey = masked", marker=None) -> np.ndarray:
    """Three panels side by side with titles, a colour bar and a caption line.

    Parameters
    ----------
    reference, frame : ndarray (rows, cols)
        Input images (any dtype).
    height_mm : ndarray (rows, cols) float
        Height in mm, NaN where invalid; shown in micrometres.
    pixel_mm : float
        Input pixel size in mm (for the scale bar).
    caption : str
        Printed under the panels.

    height_title : str
        Title of the height panel.
    marker : (row, col) or None
        Input-pixel position to mark with a cross on the height panel.

    Returns
    -------
    ndarray (H, W, 3) uint8, BGR
    """
    height_um = np.asarray(height_mm, dtype=np.float64) * 1e3
    finite = height_um[np.isfinite(height_um)]
    limit = float(np.percentile(np.abs(finite), 99.5)) if finite.size else 1.0
    step = 20.0 if limit >= 40 else 4.0 if limit >= 4 else 0.4  # ticks at quarters stay round
    limit = float(np.ceil(max(limit, 1e-3) / step) * step)
    mm_per_panel_px = pixel_mm * reference.shape[1] / PANEL
    p_ref = _grey_panel(reference)
    p_frame = _grey_panel(frame)
    p_h = _height_panel(height_um, limit)
    for p in (p_ref, p_frame, p_h):
        _scale_bar(p, mm_per_panel_px)
    if marker is not None:
        f = PANEL / reference.shape[1]
        centre = (int(round(marker[1] * f)), int(round(marker[0] * f)))
        cv2.drawMarker(p_h, centre, (0, 0, 0), cv2.MARKER_CROSS, 22, 2)
        cv2.drawMarker(p_frame, centre, (0, 0, 255), cv2.MARKER_CROSS, 22, 2)
    gap = np.full((PANEL + TITLE_H, 10, 3), 255, np.uint8)
    row = np.hstack([
        _titled(p_ref, "reference (flat water)"), gap,
        _titled(p_frame, "frame: needle ring waves"), gap,
        _titled(p_h, height_title),
        np.vstack([np.full((TITLE_H, 110, 3), 255, np.uint8), _colour_bar(limit, PANEL)]),
    ])
    foot = np.full((34, row.shape[1], 3), 255, np.uint8)
    cv2.putText(foot, caption, (8, 23), FONT, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([row, foot])


# ----------------------------------------------------------------- main


def process_needle(*, grid: str = "full"):
    """Process the needle pair; returns (reference, frame, result, seconds)."""
    from app.files import imageio
    from processing import Reconstructor

    reference = imageio.read_image(NEEDLE / "reference_2.png")
    frame = imageio.read_image(NEEDLE / "202406_1457001661.bmp")
    geometry = needle_geometry()
    t0 = time.perf_counter()
    reconstruct = Reconstructor(reference, geometry)
    result = reconstruct(frame, grid=grid)
    seconds = time.perf_counter() - t0
    return reference, frame, reconstruct, result, seconds


def remove_plane(height_mm: np.ndarray) -> tuple:
    """Subtract the least-squares plane ``a + b*row + c*col`` over the finite samples.

    Returns (height without plane, (a, b, c)) with b, c in mm per pixel.
    """
    h = np.asarray(height_mm, dtype=np.float64)
    rr, cc = np.indices(h.shape, dtype=np.float64)
    ok = np.isfinite(h)
    A = np.c_[np.ones(ok.sum()), rr[ok], cc[ok]]
    coef, *_ = np.linalg.lstsq(A, h[ok], rcond=None)
    return h - (coef[0] + coef[1] * rr + coef[2] * cc), tuple(coef)


def ring_centre(height_mm: np.ndarray, *, step: int = 4, border: int = 64) -> tuple:
    """Row, col (pixels) of the centre of a ring-wave pattern.

    For axisymmetric waves the height gradient points along the radius, so the
    centre is the point closest, in least squares, to all the lines through
    each sample along its gradient (weighted by the squared gradient).
    """
    h = np.asarray(height_mm, dtype=np.float64)
    ok = np.isfinite(h)
    hs = cv2.GaussianBlur(np.where(ok, h, 0.0), (0, 0), 3)
    gr, gc = np.gradient(hs)
    rr, cc = np.indices(h.shape, dtype=np.float64)
    sel = np.zeros_like(ok)
    sel[border:-border:step, border:-border:step] = True
    sel &= cv2.erode(ok.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
    g = np.stack([gr[sel], gc[sel]], axis=1)
    w = np.sum(g * g, axis=1)
    n = g / np.sqrt(np.maximum(w, 1e-30))[:, None]
    p = np.stack([rr[sel], cc[sel]], axis=1)
    # minimise sum w |(I - n n^T)(x - p)|^2
    M = np.zeros((2, 2))
    v = np.zeros(2)
    for i in range(len(w)):
        P = np.eye(2) - np.outer(n[i], n[i])
        M += w[i] * P
        v += w[i] * P @ p[i]
    r, c = np.linalg.solve(M, v)
    return float(r), float(c)


def main(argv=None) -> int:
    out = ROOT / "docs" / "needle.png"
    reference, frame, reconstruct, result, seconds = process_needle()
    height = np.asarray(result.height, dtype=np.float64)
    valid = np.asarray(result.valid, dtype=bool)
    flat, (a, b, c) = remove_plane(height)
    pixel_mm = NEEDLE_GEOMETRY["pixel_mm"]
    finite = flat[np.isfinite(flat)]
    r0, c0 = ring_centre(flat)
    carriers = getattr(reconstruct, "carriers", None)
    desc = carriers.describe() if hasattr(carriers, "describe") else ""
    shift = np.nanmedian(np.asarray(result.displacement).reshape(2, -1), axis=1)
    print(f"needle pair: {reference.shape} px, carriers: {desc}")
    print(f"median displacement (u_row, u_col) = ({shift[0]:+.2f}, {shift[1]:+.2f}) px")
    print(f"best-fit plane removed: slope {b / pixel_mm * 1e3:+.2f} um/mm along rows, "
          f"{c / pixel_mm * 1e3:+.2f} um/mm along cols (a global frame shift reads as a tilt)")
    print(f"valid fraction {valid.mean():.3f}; height after plane removal p1..p99 "
          f"{np.percentile(finite, 1) * 1e3:+.1f} .. {np.percentile(finite, 99) * 1e3:+.1f} um; "
          f"RMS {np.std(finite) * 1e3:.1f} um")
    side = lambda r, c: (f"{'upper' if r < reference.shape[0] / 2 else 'lower'} "
                         f"{'right' if c > reference.shape[1] / 2 else 'left'}")
    print(f"ring centre (radial-gradient fit) at row {r0:.0f}, col {c0:.0f} ({side(r0, c0)})")
    print(f"processing time (reference analysis + one full-grid frame): {seconds:.2f} s")
    caption = (f"FS-SS needle waves, 0.207 mm/px, full grid; best-fit plane removed; valid "
               f"{valid.mean() * 100:.0f} %; h p1..p99 {np.percentile(finite, 1) * 1e3:+.0f}.."
               f"{np.percentile(finite, 99) * 1e3:+.0f} um; + = fitted ring centre; "
               f"made by docs/make_figures.py")
    figure = compose(reference, frame, flat, pixel_mm=pixel_mm, caption=caption,
                     height_title="height h (um), plane removed; grey = masked", marker=(r0, c0))
    cv2.imwrite(str(out), figure)
    print(f"wrote {out.relative_to(ROOT)} ({figure.shape[1]} x {figure.shape[0]} px)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
