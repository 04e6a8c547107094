"""The series memory of a Reconstructor, one value: :class:`SeriesState`.

A frame of a series is unwrapped in time against the last one
(:func:`unwrap_phase`) and checked for continuity with it
(:func:`check_series`); what one frame passes to the next is a
:class:`SeriesState`, which these functions take and return (they never
change the one given).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Optional

import numpy as np

from .pin import PIN_MIN_PIECE_SAMPLES
from .regions import connected_regions
from .result import SeriesCheck
from .unwrap import TWO_PI, has_wraps, jumps_only_at_residues, median_turn, unwrap_spatial, unwrap_temporal, wrap

__all__ = ["SeriesState", "SERIES_MAX_SLIP_FRACTION", "SERIES_MAX_PIN_SHIFT", "EMPTY", "unwrap_phase",
           "after_unwrap", "check_series", "series_slip", "copy_check"]

#: Series check: a frame is flagged when its phase changed by more than pi
#: since the previous frame and temporal unwrapping's count of 2 pi disagrees
#: with the frame's own spatial unwrapping on more than this fraction of the
#: samples valid in both (a fast surface whose two answers agree is no slip:
#: on clean ray-traced series the old test, change > pi alone, flagged 38 of 40).
SERIES_MAX_SLIP_FRACTION = 0.01
#: ... or when its height offset, measured on the previous frame's pin
#: samples, moved by more than this fraction of the frame's rms height (the
#: method's accuracy is 2-4 % of the height, notes.md) and more than 4 times
#: its own noise.
SERIES_MAX_PIN_SHIFT = 0.02


@dataclasses.dataclass
class SeriesState:
    """Temporal-unwrapping memory of a :class:`Reconstructor` after a frame.

    Attributes
    ----------
    phase : ndarray, shape (2, m_rows, m_cols), or None
        Unwrapped carrier phases of the last frame on the decimated grid,
        radians, NaN where invalid (None: the next frame is unwrapped in
        space; what :data:`EMPTY` holds).
    valid : ndarray, bool, shape (m_rows, m_cols), or None
        Its valid samples.
    all_valid : bool
        Every sample was valid.
    check : tuple or None
        What the series check (:class:`SeriesCheck`) compares the next frame
        with: the last frame's phase, valid samples, decimated height and
        pin samples.
    """

    phase: Optional[np.ndarray]
    valid: Optional[np.ndarray]
    all_valid: bool
    check: Optional[tuple] = None

    def agrees_with(self, other: Optional["SeriesState"], *, tol_rad: float = 0.5) -> bool:
        """Same valid samples and the same unwrapped phase there.

        Two unwrappings of one wrapped phase differ by whole multiples of
        2 pi; anything below ``tol_rad`` (default 0.5 rad) is rounding (the
        same frame through different FFT plans differs by about 1e-6 rad).
        """
        if other is None:
            return False
        if self.phase.shape != other.phase.shape or self.all_valid != other.all_valid:
            return False
        if not np.array_equal(self.valid, other.valid):
            return False
        if not self.valid.any():
            return True
        diff = np.abs(self.phase[:, self.valid].astype(np.float64) - other.phase[:, other.valid])
        return bool(diff.max() < tol_rad)


#: No memory: the first frame of a series.
EMPTY = SeriesState(None, None, False, None)


def copy_check(check):
    """A copy of a :attr:`SeriesState.check` tuple (None stays None)."""
    return None if check is None else tuple(None if a is None else np.array(a, copy=True) for a in check)


def unwrap_phase(wrapped, valid, all_valid, state: SeriesState, *, unwrap: bool, temporal: bool,
                 ref_mask, ref_idx):
    """Unwrapped carrier phases (2, m_rows, m_cols) of ``wrapped`` with mask
    ``valid``: against ``state`` (temporal) when it holds a frame, else in
    space, the reference region's (``ref_mask``, flat ``ref_idx``) median
    nearest 0; NaN-free where ``all_valid``.  Where the series' count then
    slips (:func:`series_slip`), the chain unwraps the frame again against
    :data:`EMPTY` (:meth:`processing.chain_checkerboard.CheckerboardChain.unwrapped`)."""
    if not unwrap:
        return np.where(valid, wrapped, np.nan)
    prev = state.phase
    if not (temporal and prev is not None):
        return _unwrap_spatial_both(wrapped, valid, ref_mask)
    out = None
    if all_valid and state.all_valid:
        out = _unwrap_temporal_all_valid(wrapped, prev, ref_idx)
    if out is None:
        out = np.empty_like(wrapped)
        for s in range(2):
            out[s] = unwrap_temporal(wrapped[s], prev[s], valid, state.valid, ref_mask=ref_mask)
    for s in range(2):
        _heal_specks(out[s], wrapped[s], valid, ref_mask)
    return out


def _unwrap_spatial_both(wrapped, valid, ref_mask):
    """Both carriers' phases unwrapped in space (:func:`processing.unwrap.unwrap_spatial`)."""
    out = np.empty_like(wrapped)
    for s in range(2):
        out[s] = unwrap_spatial(wrapped[s], valid, ref_mask=ref_mask)
    return out


def series_slip(phase, valid, prev_phase, prev_valid, ref_mask) -> float:
    """The share of the samples valid in this and the previous frame where, the unwrapped ``phase``
    having changed by more than pi since ``prev_phase``, its count of 2 pi differs from this
    frame's own spatial unwrapping (:func:`_disagrees_with_spatial`); 0.0 where the change stays
    within pi everywhere (temporal unwrapping then adds nothing the images do not say) or no sample
    is valid in both."""
    both = valid & prev_valid
    n = int(np.count_nonzero(both))
    if n == 0 or float(np.nanmax(np.abs(phase - prev_phase), initial=0.0)) <= np.pi:
        return 0.0
    return float(np.count_nonzero(_disagrees_with_spatial(phase, valid, ref_mask) & both)) / n


def _heal_specks(phase, wrapped, valid, ref_mask):
    """Give back to this frame's own spatial unwrapping the few samples on
    which the temporally unwrapped ``phase`` (2-D, changed in place) counts
    other periods than it does.

    A jump of more than pi between two valid neighbours of ``phase`` that is
    not a side of a residue is a slope of more than half a carrier period
    per decimated sample: beyond what the demodulation resolves, so not a
    surface the method can measure.  Such jumps come from samples newly
    valid at the frame's edge or a mask's rim, grown from a neighbour whose
    change was near pi, and temporal unwrapping would carry them on through
    every later frame.  On each connected valid region whose disagreement
    with the frame's own unwrapping is at most
    :data:`SERIES_MAX_SLIP_FRACTION` of its samples, those samples take the
    frame's count; a larger disagreement is left for the series check to
    report (a slip of the whole series, or a surface too fast for the frame
    rate).  Nothing is done (nor unwrapped) when ``phase`` has no such jump.
    """
    work = np.where(valid, phase, 0.0)
    if not has_wraps(work, valid) or jumps_only_at_residues(wrap(work), valid, work):
        return
    from scipy import ndimage

    own = unwrap_spatial(np.where(valid, wrapped, 0.0), valid, ref_mask=ref_mask)
    turns = np.where(valid, np.round((work - np.where(valid, own, 0.0)) / TWO_PI), 0.0)
    labels, _ = connected_regions(valid)
    for lab, box in enumerate(ndimage.find_objects(labels), start=1):
        region = labels[box] == lab
        t = turns[box][region]
        t -= np.median(t)  # one common offset per region is no slip
        bad = t != 0
        n_bad = int(np.count_nonzero(bad))
        if 0 < n_bad <= SERIES_MAX_SLIP_FRACTION * t.size:
            piece = phase[box]
            piece[region] = piece[region] - TWO_PI * t


def _unwrap_temporal_all_valid(wrapped, prev, ref_idx):
    """unwrap_temporal for both carriers when this and the previous frame
    are valid everywhere (most live frames): the same arithmetic without
    masks; None when the change since the previous frame has a 2 pi jump
    (the general path unwraps it in space)."""
    pi = np.pi
    delta = wrap(wrapped - prev)
    # a change spanning <= pi cannot hold a neighbour jump > pi (the usual
    # case: two reductions instead of the difference test)
    if float(delta.max()) - float(delta.min()) > pi:
        if (np.abs(np.diff(delta, axis=1)).max(initial=0.0) > pi
                or np.abs(np.diff(delta, axis=2)).max(initial=0.0) > pi):
            return None
    out = prev + delta
    if ref_idx.size:
        vals = out.reshape(2, -1)[:, ref_idx]
        for s in range(2):
            out[s] -= median_turn(vals[s])
    return out


def after_unwrap(state: SeriesState, phase, valid, all_valid: bool) -> SeriesState:
    """``state`` continued by a frame's unwrapped ``phase`` and ``valid``
    samples (the series check's memory kept)."""
    kept = phase.copy() if all_valid else np.where(valid, phase, np.nan)
    return dataclasses.replace(state, phase=kept, valid=valid.copy(), all_valid=all_valid)


def check_series(phase, valid, surf, state: SeriesState, ref_mask, slip: Optional[float] = None):
    """``(SeriesCheck or None, state)``: this frame compared with the previous
    one (see :class:`SeriesCheck`; None for the first frame of a series), and
    ``state`` with this frame as what the next is compared with.  ``slip``:
    the series' slip the chain measured (:func:`series_slip`; above 0 it
    unwrapped the frame alone, as a series' first), None: measured here
    (the GPU chain's frames), flagged above :data:`SERIES_MAX_SLIP_FRACTION`."""
    prev = state.check
    height = np.asarray(surf.height_mm)
    pin_samples = surf.pin_samples
    state = dataclasses.replace(state, check=(phase, valid, height, pin_samples))
    if prev is None:
        return None, state
    p_phase, p_valid, p_height, p_pin = prev
    both = valid & p_valid
    n = int(np.count_nonzero(both))
    if n == 0:
        return SeriesCheck(True, "no sample is valid in both this and the previous frame: "
                           "its heights cannot be compared with the previous frame's", float("nan"),
                           float("nan"), 0), state
    # Where the change since the previous frame stays within pi, temporal
    # unwrapping added nothing the images do not say.  Where it exceeds pi
    # (a fast surface), it is a slip only where the series' 2 pi count
    # disagrees with this frame's own spatial unwrapping; NaN compares False.
    slip_fraction = series_slip(phase, valid, p_phase, p_valid, ref_mask) if slip is None else float(slip)
    alone = slip is not None and slip_fraction > 0.0
    reasons = []
    if slip_fraction > SERIES_MAX_SLIP_FRACTION and not alone:
        reasons.append(
            f"the unwrapped phase changed by more than half a carrier period since the previous frame, and on "
            f"{100 * slip_fraction:.1f} % of the samples the series counts other periods than this frame's "
            f"own spatial unwrapping (temporal unwrapping slipped, or the surface moved too fast for the "
            f"frame rate)")
    shift = _pin_shift(height, valid, pin_samples, p_height, p_pin, both, reasons)
    return SeriesCheck(bool(reasons), "; ".join(reasons), slip_fraction, shift, n, unwrapped_alone=alone), state


def _pin_shift(height, valid, pin_samples, p_height, p_pin, both, reasons):
    """Change of the height offset on the previous frame's pin samples (mm; a
    reason appended to ``reasons`` when it is more than noise)."""
    shift = 0.0
    same = p_pin is not None and pin_samples is not None and np.array_equal(p_pin, pin_samples)
    if not same and p_pin is not None:
        common = p_pin & both
        m = int(np.count_nonzero(common))
        if m < PIN_MIN_PIECE_SAMPLES:
            shift = float("nan")
            reasons.append(f"the height offset was pinned on other samples than in the previous frame "
                           f"({m} in common): the offsets of the two frames are not comparable")
        else:
            dh = (height[common] - p_height[common]).astype(np.float64)
            shift = float(dh.mean())
            noise = float(dh.std()) / math.sqrt(max(1.0, m / 4.0))  # ~4 samples per filter footprint
            scale = float(np.sqrt(np.mean(np.square(height[valid], dtype=np.float64))))
            if abs(shift) > max(SERIES_MAX_PIN_SHIFT * scale, 4.0 * noise):
                reasons.append(
                    f"the height offset moved by {1e3 * shift:+.3g} um ({100 * abs(shift) / scale:.1f} % of the "
                    f"rms height) on the previous frame's pin samples: the pin changed under this frame")
    return shift


def _disagrees_with_spatial(phase, valid, ref_mask):
    """Samples where the unwrapped ``phase`` (2, m_rows, m_cols) differs by a
    multiple of 2 pi from this frame's own spatial unwrapping, on the valid
    islands that reach the reference region (elsewhere the frame alone
    cannot fix an island's 2 pi offset: the series is the only witness)."""
    labels, count = connected_regions(valid)
    anchored = np.unique(labels[valid & ref_mask]) if ref_mask is not None else np.array([], int)
    anchored = anchored[anchored > 0]
    if not anchored.size and count:
        anchored = np.array([1 + int(np.argmax(np.bincount(labels[valid])[1:]))])
    judged = labels == anchored[0] if anchored.size == 1 else np.isin(labels, anchored)
    out = np.zeros(valid.shape, bool)
    for s in range(2):
        # One judged region on which the series' phase has no jump over pi between valid neighbours
        # except on the sides of residues (2 x 2 cells whose wrapped differences do not sum to 0, where
        # every unwrapping of this frame must put a jump): it is itself an unwrapping of this frame, as
        # good as any spatial unwrapper's (without residues a consistent unwrapping is unique up to one
        # 2 pi multiple per region; with them the frame alone cannot say on which side of a residue the
        # 2 pi goes), so the frame's own unwrapping is no witness against it: no slip.  Its spatial
        # unwrapping (most of the live chain's time on fast waves) is then not needed.
        if anchored.size == 1:
            masked = np.where(judged, phase[s], 0.0)
            if not has_wraps(masked, judged) or jumps_only_at_residues(wrap(masked), judged, masked):
                continue
        masked = np.where(valid, phase[s], 0.0)
        own = unwrap_spatial(wrap(masked), valid, ref_mask=ref_mask)
        turns = np.round((np.where(judged, phase[s], 0.0) - np.where(judged, own, 0.0)) / TWO_PI)
        if judged.any():
            turns -= np.median(turns[judged])  # one common offset is no slip
        out |= judged & (turns != 0)
    return out
