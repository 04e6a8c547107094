"""What sets the board's scale in the image, and what the reference says of it: the words of the board-period
check (:func:`processing.carriers.check_board_period`) and of the perspective check
(:func:`processing.keystone.keystone_check`).

The carriers measure the board's period in pixels; through the geometry that is a period in mm
(:meth:`processing.camera_model.CameraModel.board_period_mm`), set by ``pixel_mm`` and ``theta_deg`` and, for
a camera at a finite distance ``D``, by ``D`` and ``depth_mm`` too: the camera sees the board
``depth_mm / cos(theta)`` beyond the surface, smaller than the surface by ``D / (D + depth_mm / cos theta)``
(a telecentric lens: not at all). So a period that disagrees with ``pattern_period_mm`` may come from any of
those keys; :func:`scale_alternatives` solves for each in turn, the others kept. The keystone the reference
shows (:mod:`processing.keystone`) does not depend on ``depth_mm``: it measures ``pixel_mm / D``, which tells
the camera's distance apart from the board's depth.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Optional

import numpy as np
import scipy.optimize

from .camera_model import nearest_camera_distance_mm
from .errors import GeometryError
from .keystone import KEYSTONE_MIN_MISMATCH, Keystone, predicted_keystone

__all__ = ["cell_shape_words", "root_two_hint", "setup_words", "scale_keys", "scale_alternatives", "keystone_words",
           "keystone_message", "heights_off_pct", "far_limit_mm", "seen_distance_mm"]


def setup_words(geometry) -> str:
    """The keys that set the board's scale and shape in the image, with their values: "pixel_mm = 0.1, theta_deg
    = 55, telecentric"."""
    distance = geometry.camera_distance_mm if geometry.setup == "tir" else geometry.fsss_camera_distance_mm
    camera = "telecentric" if distance is None else f"camera {distance:g} mm away"
    angle = f", theta_deg = {geometry.theta_deg:g}" if geometry.setup == "tir" else ""
    return f"pixel_mm = {geometry.pixel_mm:g}{angle}, {camera}"


def root_two_hint(period_mm: float, printed_mm: float, band: float) -> str:
    """Where a board period is sqrt(2) off the printed one (within ``band``): the pattern is a grid of crossed
    lines or cosines along x and y (its period P shows as a checkerboard of period P sqrt(2) turned by 45 deg),
    or the reverse (by-hand trial of 7 Dec 2026: crossed cosines of 2 mm were told "pixel_mm should be
    0.07071")."""
    for factor, what in ((math.sqrt(2.0), "crossed lines or cosines along x and y"),
                         (1.0 / math.sqrt(2.0), "a checkerboard where crossed lines or cosines are described")):
        if abs(period_mm / (printed_mm * factor) - 1.0) <= band:
            return (f". The two are sqrt(2) apart: if the pattern is {what}, keep pixel_mm and set "
                    f"pattern_period_mm = {period_mm:.4g} (the checkerboard it is equivalent to)")
    return ""


def cell_shape_words(aspect: float, stretch: float, setup: str, theta: float) -> str:
    """Words on a reference whose board's cells are ``aspect`` times as long along y as along x through the
    geometry (``setup``: its keys, in words), where ``pattern_stretch_y = stretch`` says otherwise; ``theta``:
    the theta_deg that a board of the declared shape implies (NaN: not said)."""
    def cells(a):
        return "square" if abs(a - 1.0) < 0.005 else f"{a:.3g} times as long along y as along x"

    shape = cells(stretch)
    text = (f"the reference's checkerboard is not the board the geometry describes: through this geometry "
            f"({setup}) its cells are {cells(aspect)}, where pattern_stretch_y = {stretch:g} says {shape}. If "
            f"the board's cells are so, set pattern_stretch_y = {aspect:.3g} (pattern_period_mm is its period "
            f"along x)")
    if math.isfinite(theta):
        text += f"; if they are {shape}, theta_deg is wrong: the carriers give {theta:.1f} deg"
    return text


def heights_off_pct(ratio: float) -> float:
    """How far (%) every height is off where the board's scale in the image is off by ``ratio``: heights
    scale as the square of the scale (``pixel_mm`` squared; measured, by-hand trial of 7 Dec 2026: pixel_mm
    4.5-5 % high, heights 9-10 % off)."""
    return 100.0 * abs(ratio ** 2 - 1.0)


def scale_keys(geometry) -> str:
    """The keys that set the board's scale in the image for this geometry, in words."""
    if geometry.setup == "tir":
        shrink = "D / (D + depth_mm / cos(theta_deg))"
        if geometry.camera_distance_mm is not None:
            return (f"pixel_mm, pattern_period_mm, theta_deg, camera_distance_mm and depth_mm (a camera D mm "
                    f"away sees the board, depth_mm / cos(theta_deg) beyond the surface, smaller by {shrink})")
        return (f"pixel_mm, pattern_period_mm and theta_deg; and a camera at a finite distance D, which this "
                f"geometry does not declare (no camera_distance_mm: a telecentric lens), sees the board smaller "
                f"by {shrink}")
    if geometry.fsss_camera_distance_mm is not None:
        return ("pixel_mm, pattern_period_mm, fsss_camera_distance_mm and fsss_layers (the board's apparent "
                "depth below the surface)")
    return ("pixel_mm and pattern_period_mm; and a camera at a finite distance, which this geometry does not "
            "declare (no fsss_camera_distance_mm: a telecentric lens), sees the board smaller through the layers")


def _solve(geometry, key: str, carrier_freq, frame_shape, printed_mm: float, lo: float, hi: float):
    """The value of ``key`` in ``[lo, hi]`` (geometric search) that makes the board period printed_mm, the
    other keys kept; None where none does (or the geometry refuses the values)."""
    def off(log_value):
        try:
            g = dataclasses.replace(geometry, **{key: math.exp(log_value)})
        except GeometryError:
            return math.nan
        return g.board_period_mm(carrier_freq, frame_shape) / printed_mm - 1.0

    grid = np.linspace(math.log(lo), math.log(hi), 41)
    values = np.array([off(v) for v in grid])
    for i in range(len(grid) - 1):
        a, b = values[i], values[i + 1]
        if np.isfinite(a) and np.isfinite(b) and a * b <= 0:
            return math.exp(scipy.optimize.brentq(off, grid[i], grid[i + 1], xtol=1e-6))
    return None


def scale_alternatives(geometry, carrier_freq, frame_shape, printed_mm: float, implied_pixel_mm: float,
                       keystone: Optional[Keystone]) -> str:
    """The values that would each bring the board period to ``printed_mm``, in words: ``pixel_mm`` (always),
    and for TIR the camera distance and ``depth_mm``; where the reference's keystone tells the camera's
    distance (:func:`keystone_words`), that distance and the ``depth_mm`` it needs, ``pixel_mm`` kept."""
    text = f"If the board is the one printed with that period: pixel_mm = {implied_pixel_mm:.4g} (the rest kept)"
    if geometry.setup != "tir":
        return text + "; otherwise correct pattern_period_mm or " + (
            "fsss_camera_distance_mm or fsss_layers" if geometry.fsss_camera_distance_mm is not None
            else "declare the camera's distance, fsss_camera_distance_mm")
    near = nearest_camera_distance_mm(geometry.pixel_mm, frame_shape)
    distance = _solve(geometry, "camera_distance_mm", carrier_freq, frame_shape, printed_mm, near, 1e6)
    if distance is not None:
        text += f", or camera_distance_mm = {distance:.4g} (pixel_mm and depth_mm kept)"
    if geometry.camera_distance_mm is not None:
        depth = _solve(geometry, "depth_mm", carrier_freq, frame_shape, printed_mm, 1e-3 * geometry.depth_mm,
                       1e3 * geometry.depth_mm)
        if depth is not None:
            text += f", or depth_mm = {depth:.4g} (the rest kept)"
    if keystone is not None and keystone.implied is not None:
        seen = seen_distance_mm(geometry, keystone, carrier_freq, frame_shape)
        text += ". " + keystone_words(geometry, keystone, frame_shape, carrier_freq)
        if seen is None and geometry.camera_distance_mm is not None:
            tele = dataclasses.replace(geometry, camera_distance_mm=None).board_period_mm(carrier_freq, frame_shape)
            text += f": through a telecentric lens (camera_distance_mm omitted) the period is {tele:.4g} mm"
        if seen is not None:
            fixed = dataclasses.replace(geometry, camera_distance_mm=seen)
            depth = _solve(fixed, "depth_mm", carrier_freq, frame_shape, printed_mm, 1e-3 * geometry.depth_mm,
                           1e3 * geometry.depth_mm)
            if depth is not None:
                text += (f": with pixel_mm = {geometry.pixel_mm:g} kept, camera_distance_mm = {seen:.4g} and "
                         f"depth_mm = {depth:.4g} give the printed period")
    return text


def far_limit_mm(geometry, carrier_freq, frame_shape) -> float:
    """The camera distance beyond which its keystone stays below :data:`KEYSTONE_MIN_MISMATCH` over this frame
    (indistinguishable from a telecentric lens); inf where no keystone is predicted."""
    probe_mm = 10.0 * nearest_camera_distance_mm(geometry.pixel_mm, frame_shape)
    try:
        g = dataclasses.replace(geometry, camera_distance_mm=probe_mm)
    except GeometryError:
        return math.inf
    predicted = predicted_keystone(g, carrier_freq, frame_shape)
    size = 0.0 if predicted is None else float(np.linalg.norm(predicted))
    return math.inf if size == 0 else probe_mm * size / KEYSTONE_MIN_MISMATCH


def seen_distance_mm(geometry, keystone: Keystone, carrier_freq, frame_shape) -> Optional[float]:
    """The camera distance the reference's keystone shows (TIR), mm; None where it shows none that can be told
    from a telecentric lens (farther than :func:`far_limit_mm`)."""
    seen = keystone.implied[0] if keystone.implied is not None else None
    if seen is None or seen > far_limit_mm(geometry, carrier_freq, frame_shape):
        return None
    return seen


def keystone_words(geometry, keystone: Keystone, frame_shape, carrier_freq) -> str:
    """What the reference's keystone shows, in words (TIR)."""
    seen, rows_toward = seen_distance_mm(geometry, keystone, carrier_freq, frame_shape), keystone.implied[1]
    if seen is None:
        return (f"The reference shows no keystone: a telecentric lens, or a camera farther than about "
                f"{far_limit_mm(geometry, carrier_freq, frame_shape):.4g} mm")
    side = "" if rows_toward == bool(geometry.rows_toward_camera) else (
        f", with rows_toward_camera = {'true' if rows_toward else 'false'}")
    return (f"The reference's keystone (the board's period {_row_change(keystone.measured, carrier_freq)}) shows "
            f"a camera about {seen:.4g} mm away{side} at "
            f"pixel_mm = {geometry.pixel_mm:g} (it measures pixel_mm / camera_distance_mm; depth_mm does not "
            f"change it)")


def _row_change(differences, carrier_freq) -> str:
    """How the board's period changes from the top third of the image to the bottom third (``differences``
    of :mod:`processing.keystone`), in words: "2.9 % shorter in the bottom third ... than in the top third"."""
    k = np.asarray(carrier_freq, np.float64)
    length = np.hypot(k[:, 0], k[:, 1])
    change = -100.0 * float(np.mean(np.sum(k * differences[0], axis=1) * np.mean(length) / length ** 2))
    if abs(change) < 0.05:
        return "the same in the bottom third of the image as in the top third"
    return (f"{abs(change):.1f} % {'longer' if change > 0 else 'shorter'} in the bottom third of the image than "
            f"in the top third")


def keystone_message(geometry, keystone: Keystone, carrier_freq, frame_shape) -> str:
    """The note on a reference whose keystone is not the declared camera's (TIR): the camera it implies, and that
    a water surface not flat when it was taken does the same."""
    declared = ("a telecentric lens (no camera_distance_mm)" if geometry.camera_distance_mm is None
                else f"camera_distance_mm = {geometry.camera_distance_mm:g}")
    side = "true" if geometry.rows_toward_camera else "false"
    seen, rows_toward = seen_distance_mm(geometry, keystone, carrier_freq, frame_shape), keystone.implied[1]
    if seen is None:
        fix = "omit camera_distance_mm (a telecentric lens)"
    else:
        fix = f"set camera_distance_mm = {seen:.4g}"
        if rows_toward != bool(geometry.rows_toward_camera):
            fix += (f" and rows_toward_camera = {'true' if rows_toward else 'false'} (the image's first rows "
                    f"{'farther from' if rows_toward else 'nearer to'} the camera)")
    return (f"the reference's perspective is not the declared camera's: the geometry ({declared}, "
            f"rows_toward_camera = {side}, theta_deg = {geometry.theta_deg:g}, pixel_mm = {geometry.pixel_mm:g}) "
            f"predicts the board's period {_row_change(keystone.predicted, carrier_freq)}; the reference shows "
            f"it {_row_change(keystone.measured, carrier_freq)}. "
            f"{keystone_words(geometry, keystone, frame_shape, carrier_freq)}. A camera at the wrong distance "
            f"or the rows the wrong way round puts every height off (by-hand trial of 7 Dec 2026: 3-4 % with "
            f"rows_toward_camera reversed, 26 % with a camera 1500 mm away declared telecentric, 232 % with "
            f"its distance typed in cm). Measure the distance from the lens to the centre of the surface in mm "
            f"and {fix}, or check pixel_mm (the keystone measures pixel_mm / camera_distance_mm); where the "
            f"camera is as declared, the water was not flat when the reference was taken (still moving, or "
            f"curved: a meniscus, a slow slosh), which changes the board's period across the image as a camera "
            f"does: take the reference again on still water")
