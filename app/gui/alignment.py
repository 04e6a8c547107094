"""Alignment metrics of a live frame *before* any reference exists.

While the physicist sets up the pattern and theta there is no reference yet,
so :meth:`processing.Reconstructor.alignment` cannot be used. This falls back
on :func:`processing.carriers.find_carriers` applied to the live frame itself
(carrier periods, rotation, theta from the pattern's aspect, peak sharpness as
focus metric) plus a display spectrum. Once a reference exists the worker
uses the Reconstructor's own ``alignment``/``spectrum``.

Random dots (``Geometry.pattern == "dots"``) have no carriers: the metrics are
:func:`processing.piv.dot_alignment`'s (dot size, dots per interrogation
window, contrast, focus), judged against PIV practice (docs/gui.md).
"""

from __future__ import annotations

import collections
from typing import Optional

import numpy as np

from processing.geometry import grazing_view_note
from processing.live_view import SATURATION_MAX_PCT
from processing.piv import DOTS_PER_WINDOW_MIN  # the one bound: `process` names a dots run below it too
from processing.reference_average import (PHASE_BOUND_RAD, grey_change, half_spectrum_baseband, phase_change_rad,
                                          worst_tile_rms)

__all__ = ["frame_alignment", "display_spectrum", "modulation_map", "assess", "DOT_WINDOW_PX", "periodic_pattern",
           "theta_mismatch", "FrameMotion", "MOTION_MEMORY"]

#: Final interrogation window (px) of the live random-dot Reconstructor; its
#: dots per window are counted in windows of this size.
DOT_WINDOW_PX = 16


def display_spectrum(frame: np.ndarray, *, size: int = 256, max_freq: float = 0.25, half_spectrum=None) -> dict:
    """Centred log-magnitude spectrum of ``frame`` for display.

    Parameters
    ----------
    frame : ndarray, shape (rows, cols)
        Raw frame.
    size : int
        At most about this many samples per axis (block maxima keep the peaks).
    max_freq : float
        Show frequencies up to this many cycles per pixel (0.25: periods >= 4 px).
    half_spectrum : ndarray, optional
        The frame's :func:`processing.carriers.windowed_spectrum`, where it was computed already.

    Returns
    -------
    dict
        ``log_magnitude`` float32 (n_rows, n_cols): log10 |FFT| (Hann window);
        ``freq_x`` (n_cols,), ``freq_y`` (n_rows,): cycles per pixel, increasing
        (see :func:`processing.carriers.display_spectrum`).
    """
    from processing.carriers import frame_spectrum

    return frame_spectrum(frame, size=size, max_freq=max_freq, half_spectrum=half_spectrum)


def modulation_map(frame: np.ndarray, *, window_px: int = 32, step_px: int = 16):
    """Local pattern contrast: local standard deviation over local mean.

    For a square wave between ``m - a`` and ``m + a`` this is the Michelson
    contrast ``a / m`` when the window spans whole pattern periods.

    Parameters
    ----------
    frame : ndarray, shape (rows, cols)
        Raw frame.
    window_px : int
        Side of the averaging window in pixels (a few pattern periods).
    step_px : int
        Sampling step of the returned map in pixels.

    Returns
    -------
    (ndarray, ndarray, ndarray)
        Map float32 (n_rows, n_cols), 0 (no pattern) .. about 1 (full-scale
        black and white squares), and the pixel rows (n_rows,) and columns
        (n_cols,) where it is sampled.
    """
    import cv2

    img = np.asarray(frame, np.float32)
    k = int(max(3, window_px))
    mean = cv2.blur(img, (k, k), borderType=cv2.BORDER_REFLECT)
    mean2 = cv2.blur(img * img, (k, k), borderType=cv2.BORDER_REFLECT)
    std = np.sqrt(np.maximum(mean2 - mean * mean, 0.0))
    rows = np.arange(step_px // 2, img.shape[0], step_px)
    cols = np.arange(step_px // 2, img.shape[1], step_px)
    mod = std[np.ix_(rows, cols)] / np.maximum(mean[np.ix_(rows, cols)], 1e-6)
    return mod.astype(np.float32), rows, cols


def periodic_pattern(image: np.ndarray) -> Optional[str]:
    """Why ``image`` is not random dots, if it shows a periodic pattern; None when it does not.

    :func:`processing.carriers.find_carriers` finds two compact, isolated carrier peaks standing at
    least 40x above the spectrum's level at their radius only in a periodic pattern: on the synthetic
    checkerboard they stand about 7400x above it, on random dots the strongest peak 6-16x.
    """
    from processing.carriers import find_carriers
    from processing.errors import NoCarrierError

    try:
        c = find_carriers(image)
    except (NoCarrierError, ValueError):
        return None
    return (f"the camera sees a periodic pattern, not random dots (carrier peaks at periods "
            f"{', '.join(f'{p:.2f}' for p in np.ravel(c.periods_px))} px stand {float(np.min(c.contrast)):.0f}x "
            "above the spectrum; random dots give no such peak): choose \"checkerboard\" in Controls ▸ "
            "Reference & geometry ▸ Pattern, or put the dot pattern in view")


def _looks_like_dots(frame: np.ndarray) -> bool:
    """Enough dots of a usable size in the windows of the live dots chain (a checkerboard was chosen on dots?)."""
    from processing.piv import dot_alignment

    try:
        a = dot_alignment(frame, window_px=DOT_WINDOW_PX)
    except Exception:  # noqa: BLE001 - a hint only
        return False
    size = np.asarray(a.get("dot_size_px", (np.nan, np.nan)), float).ravel()
    return bool(np.all(np.isfinite(size)) and size.max() < 4 * DOT_LARGE_PX
                and float(a.get("dots_per_window") or 0.0) >= DOTS_PER_WINDOW_MIN)


#: Alignment updates (about 10 a second) whose frame-to-frame change :class:`FrameMotion` reports the
#: largest of: moving water that looks still for one update is not READY for that instant.
MOTION_MEMORY = 5


class FrameMotion:
    """How much the live image changes from one alignment update to the next, before a reference.

    One frame of small waves shows the carriers of still water (the tank's waves at 256^2: READY TO
    MEASURE, by-hand trial 7 Dec 2026), but two frames apart in time differ: for a checkerboard, the
    carrier phase of each update's frame against the previous one's
    (:func:`processing.reference_average.phase_change_rad`, rad; the bands taken from the windowed
    spectrum the carriers' search made), at the carriers of the first frame of the run, so that an
    estimate near a bin's edge does not restart it; for random dots, the grey-level change over the
    contrast (:func:`processing.reference_average.grey_change`).  Beyond
    :data:`~processing.reference_average.PHASE_BOUND_RAD`, what a reference capture refuses, it is
    moving.  Carriers more than a bin away from the run's (the pattern or camera turned, another
    period) or another frame size start a new run.  Qt-free: the window keeps one and
    :func:`frame_alignment` feeds it, on the worker's thread alone."""

    def __init__(self):
        self.reset()

    def reset(self) -> None:
        """Forget the frames seen: the next update starts a run."""
        self._freq = None
        self._shape = None
        self._last = None
        self._recent = collections.deque(maxlen=MOTION_MEMORY)

    def _changed(self, change: float) -> float:
        self._recent.append(float(change))
        return max(self._recent)

    def carriers(self, half_spectrum, shape, freq) -> Optional[float]:
        """The largest carrier phase change (rad) over the last :data:`MOTION_MEMORY` updates, this
        frame's (``half_spectrum``: its windowed ``rfft2``; ``freq``: its carriers) included; None on
        the first frame of a run."""
        freq = np.asarray(freq, float)
        if self._shape != tuple(shape) or self._freq is None or not _same_carriers(freq, self._freq, shape):
            self.reset()
            self._freq, self._shape = freq, tuple(shape)
            self._last = [half_spectrum_baseband(half_spectrum, shape, f) for f in freq]
            return None
        bases = [half_spectrum_baseband(half_spectrum, shape, f) for f in self._freq]
        change = phase_change_rad(bases, self._last)
        self._last = bases
        return self._changed(change)

    def phases(self, phase, valid, run) -> Optional[float]:
        """Once a reference exists: the largest change of the measured carrier phase (rad; ``phase``
        (2, m, n), a live result's unwrapped phase against the reference, ``valid`` its samples) over the
        last :data:`MOTION_MEMORY` updates, per carrier the RMS over the samples valid in both in the worst
        tile (:func:`processing.reference_average.worst_tile_rms`), the larger carrier; None on the first result of a run (``run``: another reference or grid starts one). The
        same figure as :meth:`carriers` before the reference: the "frame to frame" row went with the
        reference (by-hand trial, 7 Dec 2026), though the water may still settle."""
        phase = np.asarray(phase, np.float32)
        valid = np.asarray(valid, bool)
        last = self._last
        if self._freq is not None or self._shape != (run, phase.shape) or last is None:
            self.reset()
            self._shape, self._last = (run, phase.shape), (phase, valid)
            return None
        both = valid & last[1]
        self._last = (phase, valid)
        if not both.any():
            return None
        # per carrier over the samples valid in both, in the worst tile (as a reference capture judges)
        return self._changed(max(worst_tile_rms(np.where(both, phase[c] - last[0][c], 0.0), both)
                                 for c in range(phase.shape[0])))

    def dots(self, frame) -> Optional[float]:
        """Random dots: the largest grey-level change over the contrast (every other pixel) over the
        last :data:`MOTION_MEMORY` updates, this frame's included; None on the first frame of a run."""
        sample = np.asarray(frame, np.float32)[::2, ::2]
        if self._freq is not None or self._last is None or self._last.shape != sample.shape:
            self.reset()
            self._last = sample
            return None
        change = grey_change(sample, self._last)
        self._last = sample
        return self._changed(change)


def _same_carriers(freq, run_freq, shape) -> bool:
    """Whether every carrier of the run (``run_freq``, (2, 2) cycles/px) lies within a bin of one of
    ``freq``'s (either sign: a carrier and its mirror are one)."""
    scale = np.asarray(shape, float)
    for f in run_freq:
        off = min(np.abs((g - s * f) * scale).max() for g in freq for s in (1.0, -1.0))
        if off > 1.0:
            return False
    return True


def frame_alignment(frame: np.ndarray, theta_configured_deg: Optional[float] = None,
                    pattern: str = "checkerboard", geometry=None, motion: Optional[FrameMotion] = None):
    """``(alignment_dict, spectrum_dict)`` of a live frame without reference.

    ``pattern="dots"``: :func:`processing.piv.dot_alignment` of the frame
    (``dot_size_px``, ``dots_per_window``, ``contrast``, ``focus``) with
    ``window_px`` and the ``modulation`` map over windows of that size.
    Otherwise (checkerboard):

    The dict has ``periods_px`` (2,), ``rotation_deg``, ``theta_estimate_deg``,
    ``theta_configured_deg``, ``focus`` (carrier peak sharpness, 0..1), ``modulation``
    (map, see :func:`modulation_map`), ``contrast`` (its median) and ``disturbed``
    (the pattern is distorted by a moving surface: carriers from local tiles,
    :func:`processing.carriers.find_carriers_live`), with a ``geometry`` also
    ``board_period_mm`` (the printed board's period that the carriers show
    through it) -- or ``error`` with the message of
    :class:`processing.errors.NoCarrierError`.

    With a ``motion`` (:class:`FrameMotion`, fed this frame) also ``frame_change_rad`` (checkerboard)
    or ``frame_change_contrast`` (dots): how much the image changed over the last updates (None on
    the first).
    """
    from processing.alignment import carriers_without_reference
    from processing.carriers import windowed_spectrum

    if pattern == "dots":
        spectrum = display_spectrum(frame)
        from processing.piv import dot_alignment

        a = dot_alignment(frame, window_px=DOT_WINDOW_PX)
        mod, rows, cols = modulation_map(frame, window_px=DOT_WINDOW_PX, step_px=DOT_WINDOW_PX // 2)
        a.update(window_px=DOT_WINDOW_PX, modulation=mod, modulation_rows_px=rows, modulation_cols_px=cols,
                 periodic=periodic_pattern(frame))
        if motion is not None:
            a["frame_change_contrast"] = motion.dots(frame)
        return a, spectrum
    # one transform of the frame for the display and the carriers' search (the same window)
    half = windowed_spectrum(frame)
    spectrum = display_spectrum(frame, half_spectrum=half)
    try:
        # a disturbed surface smears the whole image's carrier peaks: then local carriers (tiles,
        # searched together near what a few of them show: find_carriers_live's numbers)
        c, disturbed = carriers_without_reference(frame, half_spectrum=half)
    except ValueError as exc:  # NoCarrierError
        mod, rows, cols = modulation_map(frame)
        error = str(exc)
        if _looks_like_dots(frame):
            error = ("the camera sees random dots, not a checkerboard: choose \"random dots\" in Controls ▸ "
                     "Reference & geometry ▸ Pattern (" + error + ")")
        return {"error": error, "modulation": mod, "modulation_rows_px": rows,
                "modulation_cols_px": cols}, spectrum
    # a window of two periods along both image axes averages the squares out
    axis_period = float(np.max(c.periods_px)) * np.sqrt(2.0)
    window = int(round(2 * axis_period))
    mod, rows, cols = modulation_map(frame, window_px=window, step_px=max(4, window // 4))
    carriers = [(float(f[1]), float(f[0])) for f in np.asarray(c.freq)]  # (f_col, f_row), f_col >= 0
    spectrum["carriers"] = carriers + [(-fx, -fy) for fx, fy in carriers]
    a = {
        "periods_px": np.asarray(c.periods_px, float),
        "rotation_deg": float(c.rotation_deg),
        "theta_estimate_deg": float(c.theta_deg),
        "focus": float(np.min(c.sharpness)),
        "modulation": mod,
        "modulation_rows_px": rows,
        "modulation_cols_px": cols,
        "contrast": float(np.median(mod)),
        "disturbed": bool(disturbed),
    }
    if motion is not None:
        a["frame_change_rad"] = motion.carriers(half, frame.shape, c.freq)
    if theta_configured_deg is not None:
        a["theta_configured_deg"] = float(theta_configured_deg)
    if geometry is not None:
        a["board_period_mm"] = geometry.board_period_mm(c.freq, frame.shape)
    return a, spectrum


PERIOD_TOL = 0.015  # relative period change since the reference that means "pattern or camera moved"
ROTATION_TOL_DEG = 0.5  # rotation change since the reference, same meaning
THETA_TOL_DEG = 1.0  # theta from the pattern vs the configured theta


def theta_mismatch(carriers, geometry) -> str:
    """What the Live tab must say when the reference's pattern shows another theta than the geometry's ("" when
    within :data:`THETA_TOL_DEG`, or not judged: FS-SS, a camera at a finite distance, random dots): the maps'
    y scale and slope along y follow the geometry's theta (by-hand trial of 7 Dec 2026: theta typed as 80 deg on
    a 55 deg view, the y axis spanned +-115 instead of +-35 mm and dh/dy read 3.3x too small, flagged on the
    Alignment tab only, the Live tab's maps and "vs truth" looking right)."""
    from processing.carriers import theta_from_carriers

    if carriers is None or getattr(geometry, "setup", "") != "tir" or geometry.camera_distance_mm is not None:
        return ""
    theta = theta_from_carriers(carriers.freq, float(geometry.pattern_stretch_y or 1.0))
    if not np.isfinite(theta) or abs(theta - geometry.theta_deg) <= THETA_TOL_DEG:
        return ""
    return (f"θ from the pattern is {theta:.1f}°, the geometry says {geometry.theta_deg:g}°: the maps' y scale and "
            f"∂h/∂y follow the geometry's θ; check θ (Controls ▸ Reference & geometry) or the board's "
            f"pattern_stretch_y")


def _nz(value, digits: int = 2) -> float:
    """Round for display without showing "-0.00"."""
    v = round(float(value), digits)
    return 0.0 if v == 0 else v


#: Random dots (PIV practice, docs/gui.md): below this dot size (FWHM, px, either axis) peak locking
#: pulls the displacements towards whole pixels.
DOT_MIN_PX = 2.0
#: Above this (either axis) fewer dots fit a window: a note, not a stop.
DOT_LARGE_PX = 6.0
#: (p99 - p1) / (p99 + p1) of the grey levels below this: dots barely above the ground.
DOT_CONTRAST_MIN = 0.2
#: 1 - autocorrelation at 1 px below this: the image hardly changes from one pixel to the next
#: (a Gaussian blob of 4 px FWHM gives 0.08): blurred.
DOT_FOCUS_MIN = 0.08


NO_GEOMETRY = "no geometry: enter θ and H (Controls ▸ Reference & geometry)"


def _check_saturation(saturation_pct: float, reasons: list, lines: list) -> None:
    """The saturation row of the metrics table, and a reason when above :data:`SATURATION_MAX_PCT`."""
    sat = float(saturation_pct)
    lines.append(("saturation", f"{sat:.2f} %"))
    if sat > SATURATION_MAX_PCT:
        reasons.append(f"{sat:.1f} % of pixels saturated: lower exposure or gain")


def _assess_dots(a: dict, saturation_pct: float, geometry, has_reference: bool, pattern_problem=None):
    """:func:`assess` for a random-dot pattern (``a`` from :func:`processing.piv.dot_alignment`)."""
    reasons, lines, notes = [], [], []
    for problem in dict.fromkeys(p for p in (a.get("periodic"), pattern_problem) if p):
        reasons.append(problem)  # dots chosen on a periodic pattern: every height would be wrong
    ref = a.get("reference") if isinstance(a.get("reference"), dict) else None
    window = int(a.get("window_px") or DOT_WINDOW_PX)
    lines.append(("pattern", "random dots (PIV)"))
    if a.get("error"):
        reasons.append(a["error"])
    size = np.asarray(a.get("dot_size_px", (np.nan, np.nan)), float).ravel()
    per_window = float(a.get("dots_per_window") or 0.0)
    if not np.all(np.isfinite(size)) or per_window <= 0:
        reasons.append("no dots found: light the pattern, check TIR and that the dots are in view")
    else:
        text = f"{size[0]:.2f} × {size[1]:.2f} px (vertical × horizontal)"
        if ref is not None and ref.get("dot_size_px") is not None:
            r = np.ravel(ref["dot_size_px"])
            text += f" (reference {float(r[0]):.2f} × {float(r[1]):.2f})"
        lines.append(("dot size (FWHM)", text))
        small = [axis for value, axis in zip(size, ("vertically", "horizontally")) if value < DOT_MIN_PX]
        if small:
            reasons.append(f"dots {size.min():.1f} px across ({' and '.join(small)}), below {DOT_MIN_PX:g} px: "
                           "peak locking pulls displacements to whole pixels: defocus slightly or zoom in "
                           "(or print larger dots)")
        if size.max() > DOT_LARGE_PX:
            notes.append(f"dots up to {size.max():.1f} px: fewer fit a window; smaller dots or zooming out "
                         "give finer displacements")
        text = f"{per_window:.1f} per {window}×{window} px window"
        if ref is not None and ref.get("dots_per_window") is not None:
            text += f" (reference {float(ref['dots_per_window']):.1f})"
        lines.append(("dots per window", text))
        if per_window < DOTS_PER_WINDOW_MIN:
            reasons.append(f"{per_window:.1f} dots per {window}×{window} px window, PIV needs about "
                           f"{DOTS_PER_WINDOW_MIN:g} or more: use a denser dot pattern or larger windows")
    contrast = a.get("contrast")
    if contrast is not None:
        lines.append(("contrast", f"{float(contrast):.2f}"))
        if float(contrast) < DOT_CONTRAST_MIN:
            reasons.append(f"low contrast ({float(contrast):.2f}): light the pattern, check TIR, focus")
    focus = a.get("focus")
    if focus is not None:
        text = f"{float(focus):.3f}"
        if ref is not None and ref.get("focus") is not None:
            text += f" (reference {float(ref['focus']):.3f})"
        lines.append(("focus (1 − autocorrelation at 1 px)", text))
        if float(focus) < DOT_FOCUS_MIN:
            reasons.append(f"out of focus (focus {float(focus):.3f}, below {DOT_FOCUS_MIN:g}: the image hardly "
                           "changes from pixel to pixel): focus the camera on the dots; if they are sharp, "
                           "use smaller dots or zoom out")
    _check_saturation(saturation_pct, reasons, lines)
    if geometry is None:
        reasons.append(NO_GEOMETRY)
    _judge_motion(a, has_reference, reasons, lines, notes)
    return (not reasons), reasons, lines, notes


def _check_board_period(period_mm, geometry, reasons, lines) -> None:
    """The board's period through the scale (a line) and, where the geometry names the printed
    one (``pattern_period_mm``), a reason not to measure when they disagree
    (:func:`processing.carriers.board_period_check`: a wrong scale multiplies every height by its
    square)."""
    from processing.carriers import board_period_check

    if period_mm is None or not np.isfinite(period_mm) or geometry is None:
        return
    c = board_period_check(geometry, period_mm)
    if c.printed_mm is None:
        lines.append(("board period", f"{period_mm:.4g} mm through the scale (printed: not given)"))
        return
    lines.append(("board period", f"{period_mm:.4g} mm through the scale vs {c.printed_mm:g} mm printed "
                                  f"(Δ {100 * c.off:+.1f} %)"))
    if c.wrong:
        reasons.append(f"the board's period through the scale ({period_mm:.4g} mm) is {100 * c.off:+.0f} % off the "
                       f"printed {c.printed_mm:g} mm: the scale (pixel_mm {geometry.pixel_mm:g}) should be about "
                       f"{c.implied_pixel_mm:.4g} mm/px, or the board period or θ is wrong "
                       "(Controls ▸ Reference & geometry)")


def assess(a: dict, saturation_pct: float, geometry=None, has_reference: bool = False,
           pattern_problem: Optional[str] = None):
    """Decide "ready to measure" from alignment metrics.

    Parameters
    ----------
    a : dict
        :func:`frame_alignment` or :meth:`processing.Reconstructor.alignment` output
        (random dots: ``dot_size_px`` etc., judged by the ``DOT_*`` thresholds).
    saturation_pct : float
        Saturated pixels of the frame (%).
    geometry : processing.Geometry or None
        The geometry in use (its theta is the configured one).
    has_reference : bool
        A reference exists (a disturbed surface is then what is measured, not a problem).
    pattern_problem : str, optional
        Why the reference does not show the chosen pattern (:func:`periodic_pattern` of the reference):
        a reason not to measure.

    Returns
    -------
    (ready, reasons, lines, notes)
        ``reasons``: why not ready; ``lines``: (name, value) rows of the metrics table;
        ``notes``: warnings that do not stop measuring.
    """
    if "dot_size_px" in a or getattr(geometry, "pattern", "checkerboard") == "dots":
        return _assess_dots(a, saturation_pct, geometry, has_reference, pattern_problem)
    reasons, lines, notes = [], [], []
    if pattern_problem:
        reasons.append(pattern_problem)
    if a.get("error") and a.get("periods_px") is None:
        return False, [a["error"]], [("problem", a["error"])], notes
    if a.get("error"):
        reasons.append(a["error"])

    def num(*keys):
        for k in keys:
            v = a.get(k)
            if v is not None:
                return v
        return None

    periods = num("periods_px", "periods")
    if periods is not None and not np.all(np.isfinite(np.ravel(periods))):
        periods = None
    ref_periods = a.get("reference_periods_px")
    if periods is not None:
        text = ", ".join(f"{float(v):.2f} px" for v in np.ravel(periods))
        if ref_periods is not None:
            text += " (reference " + ", ".join(f"{float(v):.2f}" for v in np.ravel(ref_periods)) + ")"
        lines.append(("pattern periods", text))
        if min(np.ravel(periods)) < 4:
            reasons.append("pattern period below 4 px: use a coarser pattern or zoom in")
        if ref_periods is not None:
            rel = np.max(np.abs(np.sort(np.ravel(periods)) / np.sort(np.ravel(ref_periods)) - 1.0))
            if rel > PERIOD_TOL:
                reasons.append(f"pattern periods differ by {100 * rel:.1f} % from the reference's: the pattern "
                               "or the camera moved since: capture a new reference on still water")
    rot = num("rotation_deg", "rotation")
    if rot is not None and np.isfinite(rot):
        ref_rot = a.get("reference_rotation_deg")
        text = f"{_nz(rot):.2f}°" + (f" (reference {_nz(ref_rot):.2f}°)" if ref_rot is not None else "")
        lines.append(("pattern rotation", text))
        if ref_rot is not None and abs(float(rot) - float(ref_rot)) > ROTATION_TOL_DEG:
            reasons.append(f"pattern rotated by {float(rot) - float(ref_rot):+.2f}° since the reference: the "
                           "pattern or the camera moved: capture a new reference on still water")
    th_est = num("theta_estimate_deg", "theta_est_deg", "theta_deg_estimate")
    if th_est is not None and not np.isfinite(th_est):
        th_est = None
    th_cfg = a.get("theta_configured_deg")
    fsss = getattr(geometry, "setup", "tir") == "fsss"
    if th_cfg is None and geometry is not None and not fsss:
        th_cfg = getattr(geometry, "theta_deg", None)
    if fsss:  # FS-SS looks straight down: theta is not part of its alignment
        th_est = None
        lines.append(("setup", "FS-SS (no θ to check)"))
    if th_est is not None:
        th_text = f"{float(th_est):.2f}° from the pattern"
        if th_cfg is not None:
            diff = float(th_est) - float(th_cfg)
            th_text += f" vs {float(th_cfg):.2f}° configured (Δ {_nz(diff):+.2f}°)"
            if abs(diff) > THETA_TOL_DEG:
                reasons.append(f"θ from the pattern differs by {diff:+.1f}° from the geometry's: check θ "
                               "(Controls ▸ Reference & geometry) or the camera's tilt")
        lines.append(("θ", th_text))
    grazing = grazing_view_note(geometry) if geometry is not None else ""
    if grazing:  # said while θ is set, not only when a run reports it (a note: it may be what the tank allows)
        notes.append(grazing)
    _check_board_period(a.get("board_period_mm"), geometry, reasons, lines)
    mod = a.get("modulation")
    contrast = num("contrast", "modulation_median")
    if contrast is None and mod is not None:
        contrast = float(np.nanmedian(mod))
    if contrast is not None:
        # two measures, named apart (by-hand trial, 7 Dec 2026: 0.67 before the reference and 0.61 after, on the
        # same still water, read as the alignment getting worse): before a reference the frame's local std/mean
        # over two periods (every harmonic), after it the carriers' band against the reference (what the mask uses)
        measure = "carrier band" if "reference_periods_px" in a else "local std/mean"
        lines.append((f"contrast ({measure}, median)", f"{float(contrast):.2f}"))
        if float(contrast) < 0.2:
            reasons.append("low contrast: light the pattern, focus, check TIR")
    focus = num("focus", "focus_metric")
    if focus is not None:
        lines.append(("focus (carrier peak sharpness)", f"{float(focus):.3f}"))
    _check_saturation(saturation_pct, reasons, lines)
    if periods is None and th_est is None and not a.get("error"):
        reasons.append("no carriers found")
    if geometry is None:
        reasons.append(NO_GEOMETRY)
    _judge_motion(a, has_reference, reasons, lines, notes)
    return (not reasons), reasons, lines, notes


def _judge_motion(a: dict, has_reference: bool, reasons: list, lines: list, notes: list) -> None:
    """The surface's rows of the metrics table: carriers smeared over the frame (``disturbed``), or the
    image changing between updates (:class:`FrameMotion`'s ``frame_change_rad`` / ``_contrast`` beyond
    :data:`~processing.reference_average.PHASE_BOUND_RAD`); before a reference either is a reason."""
    change = a.get("frame_change_rad")
    unit = "rad of carrier phase"
    if change is None:
        change, unit = a.get("frame_change_contrast"), "of the contrast (RMS grey-level change)"
    shifting = change is not None and float(change) > PHASE_BOUND_RAD
    if change is not None:
        lines.append(("frame to frame", f"{float(change):.3f} {unit}"))
    if a.get("disturbed"):
        lines.append(("surface", "moving: carriers from local patches"))
    elif shifting:
        lines.append(("surface", "moving: the pattern shifts between frames"))
    if a.get("disturbed") or shifting:
        if has_reference:
            notes.append("the surface is moving (as it should while measuring)")
        else:
            figure = (f" (the image changes by {float(change):.2f} {unit} between frames; a reference allows "
                      f"{PHASE_BOUND_RAD:g}: water moving, or the camera or pattern)" if shifting else "")
            reasons.append("the surface is moving: a reference needs still water; wait until it settles" + figure)
    elif not has_reference:
        notes.append("capture the reference on still water")
