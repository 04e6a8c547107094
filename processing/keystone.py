"""The perspective a reference shows against the camera the geometry declares (:func:`keystone_check`).

A camera at a finite distance sees the board's near edge larger than its far edge (a keystone): for a TIR
view at 55 deg from 1500 mm, a 256 px field 0.1 mm a pixel shows its carrier periods 3 % apart from the top
rows to the bottom ones; a telecentric lens shows none. The geometry predicts that change: the flat-surface
map pixel -> pattern plane (:meth:`processing.camera_model.CameraModel.flat_pattern_point`) has the Jacobian
``J(r)`` (mm per pixel) at each pixel, and the board's fixed frequency ``f`` (cycles per mm) shows as the
carrier ``J(r)^T f`` there. So the carriers found in the image's top and bottom thirds, and in its left and
right thirds (:func:`band_carriers`), are set against ``J^T f`` at those bands' centres, ``f`` taken from the
whole reference's carriers through ``J`` at the image centre. Only the differences top -> bottom and left ->
right are compared (a lens's own distortion is symmetric about the centre and cancels there), relative to
the carriers' length: :class:`Keystone`.

The camera that the reference implies is the one whose predicted differences come nearest the measured
ones: ``q = +-1 / camera_distance_mm`` (0: telecentric; the sign: ``rows_toward_camera``) searched over
every distance :meth:`~processing.camera_model.CameraModel.check_frame` accepts (:func:`implied_camera`).
A clear mismatch is named (:func:`processing.carriers.check_board_period`'s note, not a refusal: a water
surface not flat at the reference, frames averaged over waves, changes the period across the image as a camera
does, read as a camera 3565 mm away); every one the bounds let through costs heights several % at least
(by-hand trial of 7 Dec 2026: 3.3-4.2 % with rows_toward_camera reversed, 26 % with a camera 1500 mm away
declared telecentric, 232 % with its distance typed in cm; measured on its 256^2 bump: 6.6 % with 1200 mm
declared, 5.1 % with 1875 mm), while right geometries stay at a sixth of the bound (ray traced) and under half
of it (real references, :data:`KEYSTONE_MIN_MISMATCH`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple, Optional

import numpy as np
import scipy.fft

from .camera_model import field_half_diagonal_mm, pixel_jacobian
from .carrier_peaks import Carriers, as_float_image, hann
from .errors import GeometryError

__all__ = ["Keystone", "KEYSTONE_MIN_MISMATCH", "KEYSTONE_MIN_RELATIVE", "DECLARED_FITS", "band_carriers",
           "band_centres_px", "predicted_keystone", "implied_camera", "keystone_check", "camera_of",
           "peak_near"]

#: Smallest mismatch (:attr:`Keystone.mismatch`, relative to the carriers' length) that is named. Measured
#: on still-water references of right geometries: ray-traced 128^2-1024^2, telecentric and at 400-3000 mm,
#: either rows_toward_camera, boards of 1.2 and 2 mm, square and turned by 20 deg: at most 0.0018 (128^2); the
#: two real FS-SS references of tests/data and the trapped-modes run's (real lenses, a camera tilted by a few
#: degrees, which no key describes) seen as TIR views: their keystones along a camera distance's, at most
#: 0.0058. A camera 1500 mm away shows 0.021 on 128^2 at 0.1 mm a pixel, 0.043 on 256^2.
KEYSTONE_MIN_MISMATCH = 0.012
#: ... and at least this fraction of the larger of the two keystones (declared, fitted): a camera distance
#: declared more than 1.25 times or less than 0.8 times the one the reference shows is named (measured
#: relative noise: 4.5 % on 128^2, 13 % for the real references' tilt on 256^2 at 1500 mm).
KEYSTONE_MIN_RELATIVE = 0.2
#: Where the measured differences lie within this fraction of :data:`KEYSTONE_MIN_MISMATCH` of the declared
#: camera's, the declared camera is taken as the one the reference implies without a search
#: (:func:`keystone_check`): the best camera is then at most twice as far from the declared one, inside the bound.
DECLARED_FITS = 0.4
#: Boards finer than this (px, either carrier) are not judged: near the Nyquist limit a band's carrier may be
#: an alias, whose change runs the other way (a 1.2 mm board at 400 mm on 128^2: 2.5 px).
MIN_PERIOD_PX = 3.0
#: Fraction of the frame's height (width) that the top and bottom (left and right) bands span.
BAND_FRACTION = 1.0 / 3.0
#: The band's peak is searched within this fraction of the carriers' spacing (:attr:`Carriers.min_spacing`)
#: of the whole image's carrier: a keystone moves it by up to 16 % of its length (256^2 at 400 mm, 0.1 mm a pixel).
PEAK_SEARCH_RADIUS = 0.3
#: Zero-padding of the bands (finer bins for the parabola): 3 gives the real references the numbers of 4 (2 moved
#: the trapped-modes reference's from 0.0055 to 0.0071) in two thirds of the time (0.35 s on 1024^2).
PAD = 3


class Keystone(NamedTuple):
    """A reference's perspective against its geometry's (:func:`keystone_check`)."""

    #: The measured differences top -> bottom and left -> right, (2 bands pairs, 2 carriers, row/col),
    #: relative to the carriers' mean length.
    measured: np.ndarray
    #: What the declared geometry predicts for them.
    predicted: np.ndarray
    #: How far the declared camera's differences lie from those of the camera that fits the measured ones best
    #: (:func:`implied_camera`; Frobenius norm): the measured differences along the keystone a distance makes.
    mismatch: float
    #: The camera the reference implies: ``(camera_distance_mm or None for telecentric, rows_toward_camera)``;
    #: None where it cannot be told (FS-SS, whose camera looks straight down: no keystone at any distance).
    implied: Optional[tuple]
    #: Whether the mismatch is clear (:data:`KEYSTONE_MIN_MISMATCH`, :data:`KEYSTONE_MIN_RELATIVE`).
    wrong: bool


def band_centres_px(frame_shape) -> np.ndarray:
    """``(4, 2)`` pixel centres (row, col) of the top, bottom, left and right bands."""
    rows, cols = frame_shape
    h, w = _band_px(rows), _band_px(cols)
    mid_r, mid_c = (rows - 1) / 2.0, (cols - 1) / 2.0
    return np.array([[(h - 1) / 2.0, mid_c], [rows - 1 - (h - 1) / 2.0, mid_c],
                     [mid_r, (w - 1) / 2.0], [mid_r, cols - 1 - (w - 1) / 2.0]])


def _band_px(n: int) -> int:
    return max(1, int(round(n * BAND_FRACTION)))


def band_carriers(reference, carriers: Carriers) -> Optional[np.ndarray]:
    """``(4, 2, 2)``: the carriers (cycles per pixel) of the top, bottom, left and right bands of ``reference``
    (:func:`band_centres_px`), each the peak of the band's spectrum nearest the whole image's carrier
    (:func:`peak_near`), in its order and sign; None where a band shows no peak there."""
    img = as_float_image(reference, "reference")
    rows, cols = img.shape
    h, w = _band_px(rows), _band_px(cols)
    bands = (img[:h], img[rows - h:], img[:, :w], img[:, cols - w:])
    whole = np.asarray(carriers.freq, np.float64)
    radius = PEAK_SEARCH_RADIUS * carriers.min_spacing
    out = np.empty((4, 2, 2))
    for b, band in enumerate(bands):
        spectrum, fr, fc = _padded_spectrum(band)
        for s in range(2):
            found = peak_near(spectrum, fr, fc, whole[s], radius)
            if found is None:
                return None
            out[b, s] = found
    return out


def _padded_spectrum(band):
    """The band's Hann-windowed spectrum, zero-padded to :data:`PAD` times its size (finer bins), with its
    frequencies (cycles per pixel) along rows and columns."""
    rows, cols = band.shape
    n_r, n_c = scipy.fft.next_fast_len(PAD * rows), scipy.fft.next_fast_len(PAD * cols)
    windowed = (band - band.mean()) * (hann(rows)[:, None] * hann(cols)[None, :])
    return np.abs(scipy.fft.fft2(windowed, s=(n_r, n_c), workers=2)), scipy.fft.fftfreq(n_r), scipy.fft.fftfreq(n_c)


def peak_near(spectrum, fr, fc, freq, radius) -> Optional[np.ndarray]:
    """``(f_row, f_col)``: the highest bin of ``spectrum`` (a full 2-D magnitude, frequencies ``fr`` along rows
    and ``fc`` along columns) within ``radius`` (cycles per pixel) of ``freq``, refined by a parabola through
    the logarithms of its neighbours along each axis; None where that bin lies on the disc's edge (no peak
    inside)."""
    near_r = np.flatnonzero(np.abs(fr - freq[0]) <= radius)
    near_c = np.flatnonzero(np.abs(fc - freq[1]) <= radius)
    if near_r.size < 3 or near_c.size < 3:
        return None
    patch = spectrum[np.ix_(near_r, near_c)]
    inside = np.hypot(fr[near_r][:, None] - freq[0], fc[near_c][None, :] - freq[1]) <= radius
    i, j = np.unravel_index(int(np.argmax(np.where(inside, patch, -1.0))), patch.shape)
    if i in (0, patch.shape[0] - 1) or j in (0, patch.shape[1] - 1):
        return None
    logs = np.log(np.maximum(patch.astype(np.float64), 1e-300))
    d_r = _vertex(logs[i - 1, j], logs[i, j], logs[i + 1, j])
    d_c = _vertex(logs[i, j - 1], logs[i, j], logs[i, j + 1])
    step_r, step_c = fr[1] - fr[0], fc[1] - fc[0]
    return np.array([fr[near_r[i]] + d_r * step_r, fc[near_c[j]] + d_c * step_c])


def _vertex(left: float, centre: float, right: float) -> float:
    """Offset (bins, within +-0.5) of the vertex of the parabola through three equally spaced values."""
    curvature = left - 2.0 * centre + right
    return 0.0 if curvature >= 0 else float(np.clip(0.5 * (left - right) / curvature, -0.5, 0.5))


def _jacobians(geometry, points_px, frame_shape, step_px: float = 1.0) -> Optional[np.ndarray]:
    """``(n, 2, 2)``: ``d(pattern x, y) / d(row, col)`` (mm per pixel) at ``points_px`` (n, 2), central
    differences of :meth:`flat_pattern_point`; None where not finite (a camera ``check_frame`` refuses)."""
    with np.errstate(all="ignore"):
        jac = pixel_jacobian(lambda r, c: np.stack(geometry.flat_pattern_point(r, c, frame_shape), -1),
                             points_px[:, 0], points_px[:, 1], eps=step_px)
    return jac if np.all(np.isfinite(jac)) else None


def predicted_keystone(geometry, carrier_freq, frame_shape) -> Optional[np.ndarray]:
    """``(2, 2, 2)``: the differences of the carriers top -> bottom and left -> right (per carrier, (row, col))
    relative to their mean length that ``geometry`` predicts for a board whose whole-image carriers are
    ``carrier_freq``; None where its map is degenerate."""
    rows, cols = frame_shape
    points = np.vstack([[[(rows - 1) / 2.0, (cols - 1) / 2.0]], band_centres_px(frame_shape)])
    jac = _jacobians(geometry, points, frame_shape)
    if jac is None or abs(np.linalg.det(jac[0])) < 1e-300:
        return None
    k = np.asarray(carrier_freq, np.float64)
    f_pattern = np.linalg.solve(jac[0].T, k.T)  # (2 pattern axes, 2 carriers)
    local = np.einsum("bij,is->bsj", jac[1:], f_pattern)  # (4 bands, 2 carriers, row/col)
    return _differences(local, k)


def _differences(local, whole) -> np.ndarray:
    """``(2, 2, 2)``: bottom - top and right - left of ``local`` (4, 2, 2), over the mean carrier length."""
    scale = float(np.mean(np.hypot(whole[:, 0], whole[:, 1])))
    return np.stack([local[1] - local[0], local[3] - local[2]]) / scale


def implied_camera(geometry, measured, carrier_freq, frame_shape, n_steps: int = 121) -> Optional[tuple]:
    """``(q, predicted)``: the TIR camera whose predicted differences come nearest ``measured``, the other keys
    kept, as ``q = +-1 / camera_distance_mm`` (0: telecentric; below 0: ``rows_toward_camera`` the other way
    than declared), and its predicted differences. ``q`` is searched from about the nearest distance
    :meth:`check_frame` accepts, on both sides of telecentric, then on three finer grids (each a tenth: 0.2 %
    at 1500 mm on 256^2). None for FS-SS (its camera looks straight down: no keystone at any distance)."""
    if geometry.setup != "tir":
        return None
    # from a little beyond the nearest distance check_frame accepts (55 of its 60 deg off the axis)
    q_max = math.tan(math.radians(55.0)) / field_half_diagonal_mm(geometry.pixel_mm, frame_shape)
    best = (math.inf, 0.0, None)
    grid = np.linspace(-q_max, q_max, n_steps)
    for _ in range(4):
        for q in grid:
            predicted = _predicted_at(geometry, q, carrier_freq, frame_shape)
            if predicted is not None:
                mismatch = float(np.linalg.norm(measured - predicted))
                if mismatch < best[0]:
                    best = (mismatch, float(q), predicted)
        step = (grid[1] - grid[0])
        grid = np.linspace(best[1] - step, best[1] + step, 21)
    return None if best[2] is None else (best[1], best[2])


def _predicted_at(geometry, q, carrier_freq, frame_shape) -> Optional[np.ndarray]:
    """:func:`predicted_keystone` of a camera at ``1 / |q|`` (telecentric at 0), rows flipped where ``q < 0``;
    None where the geometry refuses that camera."""
    changes = {"camera_distance_mm": None if q == 0 else 1.0 / abs(q)}
    if q < 0:
        changes["rows_toward_camera"] = not geometry.rows_toward_camera
    try:
        g = dataclasses.replace(geometry, **changes)
        g.check_frame(frame_shape)
    except GeometryError:
        return None
    return predicted_keystone(g, carrier_freq, frame_shape)


def camera_of(geometry, q: float) -> tuple:
    """``(camera_distance_mm or None, rows_toward_camera)`` of :func:`implied_camera`'s ``q``."""
    if q == 0:
        return None, bool(geometry.rows_toward_camera)
    return 1.0 / abs(q), bool((q < 0) != bool(geometry.rows_toward_camera))


def keystone_check(geometry, reference, carriers: Carriers) -> Optional[Keystone]:
    """The reference's perspective against the declared camera; None where it cannot be measured (a band
    without a clear peak, a board finer than :data:`MIN_PERIOD_PX`, a map :meth:`check_frame` refuses).
    Judged along the keystone a camera distance makes (:func:`implied_camera`): what else the differences
    hold (a real camera's small tilt, that no key describes) is not. Pure: says, never raises."""
    img = as_float_image(reference, "reference")
    whole = np.asarray(carriers.freq, np.float64)
    if np.min(carriers.periods_px) < MIN_PERIOD_PX:
        return None
    local = band_carriers(img, carriers)
    predicted = predicted_keystone(geometry, whole, img.shape)
    if local is None or predicted is None:
        return None
    measured = _differences(local, whole)
    if geometry.setup == "tir" and float(np.linalg.norm(measured - predicted)) <= DECLARED_FITS * KEYSTONE_MIN_MISMATCH:
        # the declared camera explains the reference: the camera that fits best lies at most twice as far from it,
        # within the bound, so the search is not needed (it cost 0.1 s of a 256^2 reconstructor's 0.13 s build)
        declared = (geometry.camera_distance_mm, bool(geometry.rows_toward_camera))
        return Keystone(measured, predicted, float(np.linalg.norm(measured - predicted)), declared, False)
    fit = implied_camera(geometry, measured, whole, img.shape)
    if fit is None:  # FS-SS: nothing in the geometry makes a keystone
        return Keystone(measured, predicted, 0.0, None, False)
    q, best = fit
    mismatch = float(np.linalg.norm(best - predicted))
    larger = max(float(np.linalg.norm(best)), float(np.linalg.norm(predicted)))
    wrong = mismatch > max(KEYSTONE_MIN_MISMATCH, KEYSTONE_MIN_RELATIVE * larger)
    return Keystone(measured, predicted, mismatch, camera_of(geometry, q), bool(wrong))
