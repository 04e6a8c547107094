"""What pins the height's null space in one frame (:mod:`processing.height`'s
module docstring says why): :func:`choose_pin_samples` and its :class:`PinStatus`."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from .errors import GeometryError, TirdeflectError
from .pin_kernels import gather_samples, scale_fit

__all__ = ["PIN_MIN_SAMPLES", "PIN_MIN_FRACTION", "PIN_MIN_PIECE_SAMPLES", "PIN_FALLBACKS", "PinStatus",
           "STILL_REGION_MAX_MOTION_PX", "BAND_MAX_MOTION_PX", "USER_REGION_PREFIX", "band_moved",
           "choose_pin_samples", "null_mode_offset", "pattern_moved",
           "pin_samples_needed", "region_motion_px", "STILL_REGION_MAX_SPREAD_PX", "SHIFT_MIN_PX", "SHIFT_TOL_PX",
           "SHIFT_MIN_SHARE",
           "frame_motion", "frame_motion_step", "FRAME_MOTION_SAMPLES", "shift_tolerance_px", "steady_shift",
           "STEADY_SHIFT_MIN_PX", "STEADY_SHIFT_MIN_RATIO", "STEADY_SHIFT_MIN_FRAMES", "pattern_shifted",
           "level_of_shift_um", "shift_judged", "region_motion", "region_scale", "pattern_scaled", "motion_of",
           "scale_of", "SCALE_MIN_PX", "SCALE_MIN_EXPLAINED", "shift_alias_text"]


#: Fewest valid samples the pin of the null space needs (see the module docstring).
PIN_MIN_SAMPLES = 16
#: Smallest fraction of the reference region that must be valid for the pin.
PIN_MIN_FRACTION = 0.25
#: A connected piece of valid samples needs this many pin samples to be pinned
#: (one independent filter footprint); smaller pieces are reported invalid.
PIN_MIN_PIECE_SAMPLES = 4
PIN_FALLBACKS = ("nearest", "refuse")


#: Largest median displacement (pixels) of the pin samples of the user's ``reference_region`` for
#: which its surface counts as at rest and the camera and board as where the reference saw them
#: (:attr:`PinStatus.region_motion_px`, :attr:`PinStatus.still`).  Where the surface is at rest
#: ``u = a h + B grad h = 0`` exactly: ray-traced frames give at most 0.004 px there (8 and 12 bit,
#: 20 DN noise).  A board moved 3 um on the tank bottom (0.03 px) gives 0.031 px and a 4 um bump 3.2 %
#: off (a tilt); 10 um, 0.100 px and 10.4 %; 30 um, 0.300 px and 31 %.  Only the user's region is held
#: to it: the default border band sees the slopes of whatever reaches it through the 2H lever arm
#: (a centred 4 um bump: median 0 but 0.6 px at the 90th percentile; waves filling the frame, medians
#: of 0.2-0.7 px), so there this bound is not applied (:data:`BAND_MAX_MOTION_PX` is).
STILL_REGION_MAX_MOTION_PX = 0.03
#: The looser bound of the default border band (:func:`band_moved`):
#: features inside the frame leave its median displacement at 0 (``tirdeflect simulate``'s bump,
#: dimple and deep dimple at 512^2: 0.000 px in every frame) while waves that fill the frame move it
#: (its travelling waves: 0.26-0.52 px at 256^2, 0.06-0.65 px, median 0.42, over 80 frames at
#: 1024^2); there the TIR heights' null mode ``exp(-T y/H)`` is set by the band's motion: at 1024^2
#: up to 2.7 % of their RMS (0.10-0.20 % with that mode pinned alike, ``tirdeflect compare``).
BAND_MAX_MOTION_PX = 0.1
#: The user's ``reference_region`` also counts as moving where the median *length* of its samples'
#: displacement exceeds this (px), whatever their median vector: a region laid on a feature centred in
#: it (a bump's top) sees slopes of both signs whose median vector is nearly 0 (by-hand sweep, 7 Dec
#: 2026: ``tirdeflect simulate``'s 2 um bump at 256^2, region [100, 156, 100, 156] on it, median
#: vector 0.015 px, sample lengths' median 2.9-3.1 px; the heights pinned 1.5 um low, in silence).  At
#: rest the lengths' median is the noise's: 0.0002-0.0006 px (8 / 12 bit, 1-2 DN), 0.019 px at 6 DN
#: in 8 bit, 0.007 px on random dots.
STILL_REGION_MAX_SPREAD_PX = 0.1
#: How the name of the user's ``reference_region`` starts (:func:`processing.mask.choose_reference_region`).
USER_REGION_PREFIX = "reference_region"


def region_motion_px(displacement_px, samples) -> float:
    """Length of the median displacement vector (pixels; componentwise medians) of
    ``displacement_px`` (2, n_rows, n_cols) over the pin ``samples`` (bool, its
    finite samples only); NaN when none is finite."""
    return _median_length(_finite_on(displacement_px, samples)[0])


def _finite_on(displacement_px, samples):
    """``(u, sel)``: the displacement (2, m) on the ``samples`` (bool) where both components are
    finite, and that selection (n_rows, n_cols)."""
    u = np.asarray(displacement_px)
    sel = np.asarray(samples, bool) & np.isfinite(u[0]) & np.isfinite(u[1])
    return np.stack([u[0][sel], u[1][sel]]), sel


def _median_length(u_samples) -> float:
    """Length of the componentwise median of ``u_samples`` (2, m); NaN for none."""
    u = np.asarray(u_samples)
    return float(math.hypot(float(np.median(u[0])), float(np.median(u[1])))) if u.shape[1] else float("nan")


def _pin_samples(displacement_px, samples, rows_px, cols_px):
    """``(u, p)``: the displacement (2, m; px) on the finite ``samples`` and their positions (2, m; px)
    on the grid ``rows_px`` x ``cols_px`` (:func:`processing.pin_kernels.gather_samples`)."""
    u = np.asarray(displacement_px)
    if u.dtype not in (np.float32, np.float64):
        u = u.astype(np.float64)
    return gather_samples(u, np.asarray(samples, bool), np.asarray(rows_px, np.float64),
                          np.asarray(cols_px, np.float64))


#: The image's scale changed since the reference (:func:`pattern_scaled`): the pin samples'
#: displacement fits ``u = t + s (p - p_mean)`` with ``s`` moving their farthest (from their centre)
#: by at least this much (px; the band's bound, :data:`BAND_MAX_MOTION_PX`, where waves reach it) ...
SCALE_MIN_PX = 0.1
#: ... and that fit explains at least this share of their displacement's spread about its mean, counted
#: as far as their outward motion grows in proportion to their distance from the centre as a scale
#: change's does (a feature centred in the frame sends its slopes' tail outward too, falling off with the
#: distance: a deep dimple in FS-SS read -0.14 % at 0.6 of its band's motion before that was asked).
#: Measured (7 Dec 2026, ``tirdeflect simulate``'s bump, dimple and waves at 512^2, the synthetic tank's
#: scenes, the real needle frame; the default border band, full and live grid): with nothing changed
#: 0.00-0.09 (the reach 0.000-0.34 px); the frames 0.1 / 0.2 % larger or 0.2 % smaller (a refocus after
#: the reference, or the camera moved along its axis) 0.96-1.00 beside the bump and the dimple, with a
#: reach of 0.42-0.74 px, their heights 120 % off at 0.2 % (the bump): a magnification reads as a curved
#: surface (``u`` linear in position is the gradient of a paraboloid), in silence before; under waves
#: that fill the frame 0.00 (there the band's own note speaks).
SCALE_MIN_EXPLAINED = 0.5


def region_scale(displacement_px, samples, rows_px, cols_px):
    """``(s, reach_px, explained)``: the least-squares scale change ``s`` (a fraction: 0.002 is the
    image 0.2 % larger than at the reference) of ``u = t + s (p - p_mean)`` fitted to the displacement
    (2, n_rows, n_cols; px) on ``samples`` (bool, finite ones only) at pixel positions ``p`` (rows_px x
    cols_px), how far it moves the samples farthest from their centre (px), and the share of the
    displacement's spread about its mean that it explains, counted as far as the samples' outward motion
    grows with their distance as a scale change's does (:data:`SCALE_MIN_EXPLAINED`); NaNs with fewer
    than 16 samples (:func:`scale_of`)."""
    return scale_of(*_pin_samples(displacement_px, samples, rows_px, cols_px))


def scale_of(u_samples, p_samples):
    """:func:`region_scale` of the displacement ``u_samples`` (2, m; px) at positions ``p_samples``
    (2, m; px), finite ones."""
    if np.shape(u_samples)[1] < 16:
        return float("nan"), float("nan"), float("nan")
    # a scale change moves each sample outward in proportion to its distance from the centre; the slopes'
    # tail of a feature centred in the frame points outward too but falls off with the distance (a deep
    # dimple in FS-SS read -0.14 % so): the share counts as far as the outward motion's growth with the
    # distance matches a scale change's (its slope times the mean distance over the mean outward motion,
    # ``grows``: 1 for a scale change, 0 or less for such a tail); one compiled pass (pin_kernels)
    u, p = np.asarray(u_samples), np.asarray(p_samples)
    scale, reach, explained, grows = scale_fit(u if u.dtype in (np.float32, np.float64) else u.astype(np.float64),
                                               p if p.dtype == np.float64 else p.astype(np.float64))
    if math.isnan(scale):
        return float("nan"), float("nan"), float("nan")
    return float(scale), float(reach), float(explained) * min(1.0, max(0.0, float(grows)))


def pattern_scaled(reach_px: float, explained: float) -> bool:
    """Did the image's scale change since the reference (:func:`region_scale` on the pin samples)?  True
    where it moves them by :data:`SCALE_MIN_PX` or more and explains :data:`SCALE_MIN_EXPLAINED` of
    their motion (NaN: not measured)."""
    return bool(reach_px >= SCALE_MIN_PX and explained >= SCALE_MIN_EXPLAINED)


def region_motion(displacement_px, samples, rows_px, cols_px, *, user_region: bool = False) -> dict:
    """The :class:`PinStatus` fields of how the pattern moved on the pin ``samples``: ``region_motion_px``
    (:func:`region_motion_px`; for the user's region ``user_region`` at least the median length of the
    samples' displacement where that exceeds :data:`STILL_REGION_MAX_SPREAD_PX`) and ``region_scale``,
    ``region_scale_reach_px``, ``region_scale_explained`` (:func:`region_scale`)."""
    return motion_of(*_pin_samples(displacement_px, samples, rows_px, cols_px), user_region=user_region)


def motion_of(u_samples, p_samples, *, user_region: bool = False) -> dict:
    """:func:`region_motion` of the pin samples' displacement ``u_samples`` (2, m; px, finite) at
    positions ``p_samples`` (2, m; px)."""
    scale, reach, explained = scale_of(u_samples, p_samples)
    motion = _median_length(u_samples)
    u = np.asarray(u_samples)
    if user_region and u.shape[1]:
        spread = float(np.median(np.hypot(u[0], u[1])))
        if spread > STILL_REGION_MAX_SPREAD_PX:  # slopes of both signs: a feature inside the region
            motion = max(motion, spread)
    return dict(region_motion_px=motion, region_scale=scale, region_scale_reach_px=reach,
                region_scale_explained=explained)


def pattern_moved(region: str, rule: str, motion_px: float) -> bool:
    """Did the pattern move where the user says the surface is at rest?  ``region``: the pin
    region's name (the user's starts with :data:`USER_REGION_PREFIX`), ``rule``: the frame's pin
    rule (only "region" measured on the region itself), ``motion_px``: :func:`region_motion_px`
    (NaN: not measured).  True above :data:`STILL_REGION_MAX_MOTION_PX`; a default region is not
    judged (:attr:`PinStatus.still`, ``/pin_status`` read back by the GUI's export)."""
    judged = rule == "region" and region.startswith(USER_REGION_PREFIX)
    return bool(judged and motion_px > STILL_REGION_MAX_MOTION_PX)


def null_mode_offset(height, null, samples) -> float:
    """``alpha`` of the least squares of ``alpha * null`` to ``height`` on ``samples`` (bool): what
    the pin takes out of one connected piece (``height - alpha * null`` has its ``null``-weighted
    mean 0 there; :class:`processing.height.HeightSolver`, and ``tirdeflect compare`` on both maps)."""
    nr = null[samples]
    return float(np.dot(height[samples], nr) / np.dot(nr, nr))


def band_moved(region: str, rule: str, motion_px: float, setup: str) -> bool:
    """Did the pattern move on the default border band the heights were pinned on (waves reaching
    it, or the camera or the board moved: there the two cannot be told apart)?  True above
    :data:`BAND_MAX_MOTION_PX` of :func:`region_motion_px` where the region is not the user's
    (:func:`pattern_moved` judges that one), the pin was measured on it and ``setup`` (the
    geometry's) is "tir": FS-SS's null mode is a constant, which the band's motion only offsets."""
    judged = setup == "tir" and rule == "region" and not region.startswith(USER_REGION_PREFIX)
    return bool(judged and motion_px > BAND_MAX_MOTION_PX)


#: The whole pattern moved alike since the reference (:func:`pattern_shifted`): its median
#: displacement over the frame's valid samples is at least this long (px; the user's region's bound,
#: :data:`STILL_REGION_MAX_MOTION_PX`) ...
SHIFT_MIN_PX = 0.03
#: ... and at least :data:`SHIFT_MIN_SHARE` of them lie within this (px), or half the median's length
#: where that is more, of it: a large part of the frame moved by the same amount, as it does when the
#: camera or the board moved, or (TIR) the water level changed, while the surface there is at rest (at
#: rest and with nothing moved, ``u`` is 0 there), or (the half length) the whole frame moved more than
#: its parts move about it.  Measured (6 Dec 2026): with nothing moved the share stays 0.61-0.71
#: around a median of 0.000 px beside ``tirdeflect simulate``'s bump (512^2), 0.81-1.0 on the synthetic
#: tank's impact, 0.25-0.60 on its drop, 0.27 beside a 4 um bump of sigma 5 mm in a 25.6 mm frame,
#: 0.000-0.004 on waves filling the frame (simulate's, issue 22's held-out ones, the tank's; their
#: medians 0.001-0.11 px); the board shifted by 0.05-1.0 px beside the bump: the median 0.07-1.0 px,
#: the share 0.67-0.82.  The real FS-SS needle frame (tests/data), shifted by (0.8, 1.7) px against its
#: reference with ring waves filling it: median 1.89 px, 0.010 within 0.05 px but 0.565 within half of
#: it; simulate's waves with the frame shifted by 0.5 / 1.0 px 0.015 / 0.065, not named (there the pin
#: band's motion, :func:`band_moved`, says it).
SHIFT_TOL_PX = 0.05
SHIFT_MIN_SHARE = 0.2


#: About how many samples :func:`frame_motion` reads (every k-th row and column, :func:`frame_motion_step`):
#: the median of a still part's noise to a thirtieth of it, the share to 1.5 %; 0.06 ms a live 1024^2
#: frame's grid (4,096: 0.20 ms).
FRAME_MOTION_SAMPLES = 1024


def frame_motion_step(n_samples: int) -> int:
    """The k of :func:`frame_motion`'s every k-th row and column on a grid of ``n_samples``."""
    return max(1, int(math.sqrt(n_samples / FRAME_MOTION_SAMPLES)))


def frame_motion(displacement_px, valid):
    """``(median, share)`` of a frame's displacement (px, (2, n_rows, n_cols)) on its ``valid``
    finite samples (every k-th row and column, about :data:`FRAME_MOTION_SAMPLES`): the componentwise
    median vector (2,) and the share of the samples within :data:`SHIFT_TOL_PX` of it, or half its
    length where that is more; NaNs where no sample is valid."""
    u = np.asarray(displacement_px)
    k = frame_motion_step(u[0].size)
    ur, uc, v = u[0, ::k, ::k], u[1, ::k, ::k], np.asarray(valid, bool)[::k, ::k]
    sel = v & np.isfinite(ur) & np.isfinite(uc)
    if not sel.any():
        return np.full(2, np.nan), float("nan")
    ur, uc = ur[sel], uc[sel]
    median = np.array([np.median(ur), np.median(uc)], np.float64)
    share = float(np.mean(np.hypot(ur - median[0], uc - median[1]) <= shift_tolerance_px(median)))
    return median, share


def shift_tolerance_px(median_px) -> float:
    """How near a sample must lie to the frame's median displacement ``median_px`` (2,) to count as
    moved alike (:func:`frame_motion`): :data:`SHIFT_TOL_PX`, or half the median's length."""
    return max(SHIFT_TOL_PX, 0.5 * float(np.hypot(*median_px)))


def pattern_shifted(motion_px: float, share: float) -> bool:
    """Did the whole pattern move alike since the reference (:func:`frame_motion`'s median of
    length ``motion_px`` on at least :data:`SHIFT_MIN_SHARE` of the frame, ``share``)?  NaN: no."""
    return bool(motion_px >= SHIFT_MIN_PX and share >= SHIFT_MIN_SHARE)


#: A recording whose frames' median displacements (:func:`frame_motion`) sit, on average, at least
#: this far (px) from 0 ...
STEADY_SHIFT_MIN_PX = 0.2
#: ... by at least this many standard errors (the larger component's spread from frame to frame over
#: the square root of the frames), over at least :data:`STEADY_SHIFT_MIN_FRAMES` frames, was shifted
#: for its whole length: waves filling the frame hide a shift from the per-frame test
#: (:func:`pattern_shifted`), but move the frame's median about 0 (simulate's and the tank's waves:
#: 0.001-0.13 px either way, issue 22's held-out waves up to 0.11), while a camera, a board or a level
#: that moved keeps it at the shift (simulate's waves, 10 frames shifted by 0.5 px: 0.41-0.64 px, mean
#: 0.50, 22 standard errors; 8 frames of 6-12 mm waves on a 19 mm field, the board moved 0.5 px:
#: 0.37-0.78 px, 12).  :func:`steady_shift`.
STEADY_SHIFT_MIN_RATIO = 5.0
STEADY_SHIFT_MIN_FRAMES = 8


def steady_shift(medians_px):
    """``(mean (2,), spread)`` (px; ``spread`` the larger component's standard deviation) of the frames'
    median displacements ``medians_px`` (n, 2) where they sit away from 0 for the whole recording
    (:data:`STEADY_SHIFT_MIN_PX`, :data:`STEADY_SHIFT_MIN_RATIO` standard errors,
    :data:`STEADY_SHIFT_MIN_FRAMES`), else None."""
    m = np.asarray(medians_px, np.float64).reshape(-1, 2)
    m = m[np.all(np.isfinite(m), axis=1)]
    if len(m) < STEADY_SHIFT_MIN_FRAMES:
        return None
    mean = m.mean(axis=0)
    spread = float(m.std(axis=0).max())
    length = float(np.hypot(*mean))
    if length < STEADY_SHIFT_MIN_PX or length < STEADY_SHIFT_MIN_RATIO * spread / math.sqrt(len(m)):
        return None
    return mean, spread


def shift_judged(displacement_px, valid, judge_shift: bool, shift_removal: bool):
    """``(u to solve, motion)``: ``motion`` the frame's :func:`frame_motion` where ``judge_shift``
    (else None), ``u`` the displacement less its median where ``shift_removal`` and the whole pattern
    shifted (:func:`pattern_shifted`; as a reference taken then would see it), else as given."""
    u = displacement_px
    if not judge_shift:
        return u, None
    motion = frame_motion(u, valid)
    if shift_removal and pattern_shifted(float(np.hypot(*motion[0])), motion[1]):
        u = u - motion[0].astype(np.asarray(u).dtype)[:, None, None]
    return u, motion


def shift_alias_text(median_px, carrier_freq, level_um: float = float("nan")) -> str:
    """What a uniform shift ``median_px`` (2,; row, col px) cannot tell: carrier phases repeat every period, so
    a shift is measured only up to whole periods of the pattern along it, about ``max_s 1 / |f_s . d|`` px
    (``carrier_freq`` (2, 2) cycles/px, ``d`` the shift's direction), and its water level ``level_um`` (NaN:
    none) up to that many px of it. By-hand trial of 7 Dec 2026: a level 1 mm higher moved the pattern
    16.3 px, one 11.5 px period more than the 4.9 px said, and the warning read "300 um higher", the
    words of a real 0.3 mm rise. "" where no carriers (random dots) or no shift."""
    m = np.asarray(median_px, np.float64)
    length = float(np.hypot(*m))
    if carrier_freq is None or not (length > 0 and np.all(np.isfinite(m))):
        return ""
    along = np.abs(np.asarray(carrier_freq, np.float64) @ (m / length))
    if not np.any(along > 0):
        return ""
    # a carrier (nearly) across the shift hardly moves with it: the others set the period
    period_px = max(float(1.0 / a) for a in along if a >= 0.25 * along.max())
    step = (f", the level by steps of about {period_px * abs(level_um) / length:.3g} um"
            if math.isfinite(level_um) else "")
    return (f"a uniform shift is measured only up to whole periods of the pattern, about {period_px:.3g} px along "
            f"this one{step}: a move that much larger reads the same")


def level_of_shift_um(median_px, a_px_per_mm) -> float:
    """The change of water level (um, positive up) that moves a still surface's pattern by the
    uniform displacement ``median_px`` (2,): TIR's ``u = a h`` of a height ``h`` the same
    everywhere, ``a_px_per_mm`` (2,) the grid's mean ``a``.  NaN where no level change moves it so
    (FS-SS: ``a`` = 0; or the shift is more than a quarter of its length off ``a``'s direction)."""
    a = np.asarray(a_px_per_mm, np.float64)
    m = np.asarray(median_px, np.float64)
    aa = float(a @ a)
    if not aa > 0 or not np.all(np.isfinite(m)):
        return float("nan")
    level_mm = float(m @ a) / aa
    if np.hypot(*(m - level_mm * a)) > 0.25 * np.hypot(*m):
        return float("nan")
    return 1e3 * level_mm


def pin_samples_needed(region_samples: int) -> int:
    """How many valid samples the pin needs in a region of ``region_samples`` samples."""
    return max(PIN_MIN_SAMPLES, math.ceil(PIN_MIN_FRACTION * int(region_samples)))


@dataclass(frozen=True)
class PinStatus:
    """Where the null space of one frame was pinned (one per reconstructed frame).

    Attributes
    ----------
    rule : {"region", "nearest"}
        "region": on the valid samples of the reference region;
        "nearest": too few of them were valid, so the fallback took the valid
        samples nearest the region.
    region : str
        Which region: ``"reference_region [r0, r1, c0, c1]"`` or the default.
    region_samples : int
        Samples of the grid in the region.
    valid_samples : int
        Of those, valid in this frame.
    needed : int
        Valid samples the pin needs (:func:`pin_samples_needed`).
    used_samples : int
        Samples the offset was measured on.
    unpinned_fraction : float
        Fraction of the frame's valid samples dropped (NaN) because their
        connected piece held fewer than :data:`PIN_MIN_PIECE_SAMPLES` pin samples.
    pieces : int
        Connected pieces of valid samples pinned each on its own pin samples: their heights' offsets
        are set apart, by what the surface does where each is pinned.
    region_motion_px : float
        :func:`region_motion_px` of the displacement on the samples the
        offset was measured on: how far the pattern moved there since the
        reference (NaN: not measured).  In the user's ``reference_region``
        (where the user says the surface is at rest), above
        :data:`STILL_REGION_MAX_MOTION_PX` the surface there is not at rest,
        or the camera or the board moved (a shift of the whole image reads as
        a tilt): :attr:`still` is False.
    frame_motion_px, frame_shift_share : float
        :func:`frame_motion` of the whole frame: the length of its median
        displacement (px) and the share of it that moved alike; both above
        their bounds (:func:`pattern_shifted`), :attr:`shifted` is True.
    frame_motion_row_px, frame_motion_col_px : float
        That median's components (px; a recording's frames together:
        :func:`steady_shift`).
    shift_effect_um : float
        Where :attr:`shifted`: the RMS (um) of the heights that the uniform
        displacement alone gives, solved and pinned as the frame: the tilt
        the shift puts into the heights (NaN: not shifted, or not measured).
    shift_level_um : float
        Where :attr:`shifted`: the change of water level (um, up) that moves
        the pattern so (:func:`level_of_shift_um`; NaN: none does).
    shift_removed : bool
        The shift was taken out of the displacement before the heights were
        solved (the option ``shift_removal``): :attr:`shift_effect_um` is then
        what it would have put into them.
    region_scale, region_scale_reach_px, region_scale_explained : float
        :func:`region_scale` of the displacement on the pin samples: the
        image's scale change since the reference (a fraction), how far it
        moves the farthest of them (px) and the share of their motion it
        explains; both above their bounds, :attr:`scaled` is True.
    """

    rule: str
    region: str
    region_samples: int
    valid_samples: int
    needed: int
    used_samples: int
    unpinned_fraction: float = 0.0
    pieces: int = 1
    region_motion_px: float = float("nan")
    frame_motion_px: float = float("nan")
    frame_shift_share: float = float("nan")
    frame_motion_row_px: float = float("nan")
    frame_motion_col_px: float = float("nan")
    shift_effect_um: float = float("nan")
    shift_level_um: float = float("nan")
    shift_removed: bool = False
    region_scale: float = float("nan")
    region_scale_reach_px: float = float("nan")
    region_scale_explained: float = float("nan")

    @property
    def scaled(self) -> bool:
        """The image's scale changed since the reference on the pin samples (:func:`pattern_scaled`): a
        refocus, or the camera moved along its axis; the heights carry a curved surface that is not there."""
        return pattern_scaled(self.region_scale_reach_px, self.region_scale_explained)

    def scale_text(self) -> str:
        """What a :attr:`scaled` frame's heights carry, one sentence ("" when not)."""
        if not self.scaled:
            return ""
        return (f"the image's SCALE changed by {100 * self.region_scale:+.2g} % since the reference on the "
                f"{self.region} (its samples moved {self.region_scale_reach_px:.2g} px "
                f"{'outward' if self.region_scale > 0 else 'inward'} at the farthest, "
                f"{100 * self.region_scale_explained:.0f} % of their motion alike): the lens refocused or "
                "zoomed, or the camera moved along its axis, and the heights carry a curved surface that is not "
                "there (a paraboloid: 0.2 % over a 512^2 frame put 120 % of a 4 um bump's heights into them; "
                "take the reference again), unless a wave far longer than the frame curves all of it")

    @property
    def shifted(self) -> bool:
        """The whole pattern moved alike since the reference (:func:`pattern_shifted`): the camera or
        the board moved, or (TIR) the water level changed; the heights carry :attr:`shift_effect_um`."""
        return pattern_shifted(self.frame_motion_px, self.frame_shift_share)

    def shift_text(self) -> str:
        """What a shifted frame's heights carry, one sentence ("" when not :attr:`shifted`)."""
        if not self.shifted:
            return ""
        up = "higher" if self.shift_level_um > 0 else "lower"
        level = ("" if not math.isfinite(self.shift_level_um) else
                 f"the water level is {abs(self.shift_level_um):.3g} um {up} than at the reference (evaporation, "
                 f"filling, displaced water), or ")
        if self.shift_removed:
            effect = "; taken out of the heights"
            if math.isfinite(self.shift_effect_um):
                effect += f" (left in, it put {self.shift_effect_um:.3g} um RMS there, a tilt)"
            return (f"the whole pattern SHIFTED by {self.frame_motion_px:.2g} px since the reference "
                    f"({100 * self.frame_shift_share:.0f} % of the frame alike): {level}the camera or the board "
                    f"moved{effect}")
        effect = ("" if not math.isfinite(self.shift_effect_um) else
                  f"; the heights carry {self.shift_effect_um:.3g} um RMS from it (a tilt, not the surface)")
        return (f"the whole pattern SHIFTED by {self.frame_motion_px:.2g} px since the reference "
                f"({100 * self.frame_shift_share:.0f} % of the frame alike): {level}the camera or the board "
                f"moved{effect}; take the reference again")

    @property
    def ok(self) -> bool:
        """Pinned on the region itself, with as many samples as it needs."""
        return self.rule == "region"

    @property
    def still(self) -> bool:
        """False when the pattern moved on the pin samples of the user's ``reference_region``
        (:func:`pattern_moved`)."""
        return not pattern_moved(self.region, self.rule, self.region_motion_px)

    def describe(self) -> str:
        """One line for logs and summaries."""
        if self.region_samples == 0:
            where = f"{self.region}: no sample where the reference shows the pattern"
        else:
            where = (f"{self.region}: {self.valid_samples} of {self.region_samples} samples valid"
                     f" (needs {self.needed})")
        if self.rule == "region":
            text = f"pinned on {where}"
        else:
            text = f"FALLBACK: {where}, pinned on the {self.used_samples} valid samples nearest it"
        if self.unpinned_fraction > 0:
            text += f"; {100 * self.unpinned_fraction:.1f} % of valid samples dropped (no pin sample in their piece)"
        if self.shifted:
            text += "; " + self.shift_text()
        elif not self.still:
            text += (f"; the pattern moved there by {self.region_motion_px:.3g} px since the reference (the surface "
                     "there is not at rest, or the camera or the board moved: the heights carry a tilt)")
        if self.scaled:
            text += "; " + self.scale_text()
        return text


def choose_pin_samples(region: np.ndarray, valid: np.ndarray, *, fallback: str = "nearest",
                       region_name: str = "reference region", near: np.ndarray | None = None):
    """Pin samples of one frame and their :class:`PinStatus`.

    Parameters
    ----------
    region : ndarray bool (n_rows, n_cols)
        The reference region on the sample grid (the same for every frame).
    valid : ndarray bool (n_rows, n_cols)
        Valid samples of this frame.
    fallback : {"nearest", "refuse"}
        What to do when the region holds fewer valid samples than
        :func:`pin_samples_needed`: pin on the valid samples nearest the
        region, or raise GeometryError.
    region_name : str
        How the status names the region.
    near : ndarray bool or None
        Where "nearest" measures from (default: ``region``; e.g. the user's box
        when none of it is valid in the reference).

    Returns
    -------
    samples : ndarray bool (n_rows, n_cols)
    status : PinStatus (``unpinned_fraction`` still 0)
    """
    if fallback not in PIN_FALLBACKS:
        raise TirdeflectError(f"pin fallback must be one of {PIN_FALLBACKS}, got {fallback!r}")
    n_region = int(np.count_nonzero(region))
    inside = region & valid
    n_valid = int(np.count_nonzero(inside))
    needed = pin_samples_needed(n_region)
    if n_valid >= needed:
        return inside, PinStatus("region", region_name, n_region, n_valid, needed, n_valid)
    if fallback == "refuse":
        raise GeometryError(
            f"{region_name} has {n_valid} valid samples in this frame (of {n_region}); the height offset "
            f"needs {needed} to be measured; choose a reference_region where the surface is at rest and the "
            f"pattern is visible, or allow the 'nearest' fallback"
        )
    n_all = int(np.count_nonzero(valid))
    if n_all == 0:
        from .errors import AllInvalidError

        raise AllInvalidError("no valid sample to pin the height offset on; check the mask and the frame")
    anchor = region if near is None else near
    if anchor.any():
        dist = ndimage.distance_transform_edt(~anchor)
    else:  # nothing to measure from: every valid sample is as near
        dist = np.zeros(region.shape)
    d = dist[valid]
    k = min(needed, n_all)
    cut = np.partition(d, k - 1)[k - 1]
    samples = valid & (dist <= cut)
    return samples, PinStatus("nearest", region_name, n_region, n_valid, needed, int(np.count_nonzero(samples)))
