"""Per-frame outcome of a batch run: a bad frame is marked invalid with its reason, never silent.

One frame is measured by :func:`measure_frame`, which never raises for a
fault of the frame itself (black, no pattern, another pattern, unreadable...):
it returns ``(None, FrameOutcome(status, reason))`` instead, and the writer
stores that frame as all-NaN heights with ``valid = 0`` and its status (see
docs/output-format.md, ``/frame_status``). :class:`FrameTally` counts the
outcomes and the recorder's flags for the summary line. The serial engine
(:mod:`app.batch.engine`) and any parallel one call these same pieces.
"""

from __future__ import annotations

import dataclasses
import enum
import logging
import math
import zlib
from typing import Optional

import numpy as np

from processing.errors import (
    AllInvalidError,
    NoCarrierError,
    PatternMismatchError,
    SampleRangeError,
    ShapeMismatchError,
    TirdeflectError,
)
from processing.live_view import SATURATION_MAX_PCT, saturation_pct
from processing.banding import LightBands, bands_of, evened_frame
from processing.turn import TURN_MAX_MRAD, TurnCheck

__all__ = ["FrameStatus", "FrameOutcome", "FrameTally", "measure_frame", "outcome_of_error", "coverage",
           "unmeasured_cause", "PARTLY_MEASURED_PCT", "UNMEASURED_NOTE_PCT", "frame_digest"]

log = logging.getLogger(__name__)


class FrameStatus(enum.IntEnum):
    """Why a frame has no heights (``/frame_status`` in OUT.h5; 0 = measured)."""

    OK = 0
    #: every pixel has the same value, e.g. all zero (packets lost, no light)
    BLANK = 1
    #: no checkerboard in the frame (noise, out of focus, pattern not in view)
    NO_PATTERN = 2
    #: the pattern is there but no pixel could be measured (contrast lost)
    NO_CONTRAST = 3
    #: the frame shows another pattern (period / rotation) than the reference
    PATTERN_MISMATCH = 4
    #: the frame could not be read (truncated, undecodable, NaN/Inf samples or beyond 32 bits)
    UNREADABLE = 5
    #: the frame's size differs from the reference's
    SHAPE_MISMATCH = 6
    #: any other fault of the frame the numerics reported (see the reason)
    OTHER = 7

    @property
    def label(self) -> str:
        """Lower-case words for messages, e.g. ``pattern mismatch``."""
        return self.name.lower().replace("_", " ")


@dataclasses.dataclass(frozen=True)
class FrameOutcome:
    """What became of one frame: ``status`` and a one-line ``reason`` (empty when OK)."""

    status: FrameStatus = FrameStatus.OK
    reason: str = ""
    #: of a measured frame: the percentage of its pixels at its bit depth's top code
    #: (:func:`processing.live_view.saturation_pct`)
    saturated_pct: float = 0.0
    #: of a measured frame: its own isolated pixels brighter than anything the reference's pattern
    #: shows, repaired before measuring (:attr:`processing.result.Result.hot_pixels`)
    hot_pixels: int = 0
    #: of a measured frame: how far its pattern turned since the reference (camera or board moved;
    #: :attr:`processing.result.Result.turn`); None where not judged
    turn: Optional[TurnCheck] = None
    #: of a measured frame: its light along the rows against the reference's
    #: (:func:`processing.banding.light_bands`: a rolling shutter under flickering light); None where not judged
    light_bands: Optional[LightBands] = None
    #: of a measured frame: the percentage of the area its reference covers that it measured (:func:`coverage`)
    measured_pct: float = 100.0
    #: of a frame measured on less than :data:`PARTLY_MEASURED_PCT`: why the rest was not (:func:`unmeasured_cause`)
    unmeasured_cause: str = ""
    #: of a measured frame: its samples' CRC-32 (:func:`frame_digest`), -1 where not taken: :class:`FrameTally`
    #: counts the frames identical to the one before them (a camera that sent a frame twice)
    digest: int = -1

    @property
    def ok(self) -> bool:
        return self.status == FrameStatus.OK


#: error type -> status; the first match wins (PatternMismatchError before its base)
_STATUS_OF_ERROR = (
    (PatternMismatchError, FrameStatus.PATTERN_MISMATCH),
    (NoCarrierError, FrameStatus.NO_PATTERN),
    (AllInvalidError, FrameStatus.NO_CONTRAST),
    (ShapeMismatchError, FrameStatus.SHAPE_MISMATCH),
    (SampleRangeError, FrameStatus.UNREADABLE),
)


def outcome_of_error(exc: BaseException) -> FrameOutcome | None:
    """The outcome of a frame whose reading or measuring raised ``exc``;
    None when ``exc`` is not the frame's fault (a full disk, a bug): the run
    must stop then."""
    from app.files.h5safe import DiskFullError
    from app.files.imageio import ImageReadError

    if isinstance(exc, DiskFullError):
        return None  # no room for the output: the run's fault, every later frame would fail too
    message = " ".join(str(exc).split())
    if isinstance(exc, ImageReadError):
        return FrameOutcome(FrameStatus.UNREADABLE, message)
    for kind, status in _STATUS_OF_ERROR:
        if isinstance(exc, kind):
            return FrameOutcome(status, message)
    if isinstance(exc, TirdeflectError):
        return FrameOutcome(FrameStatus.OTHER, message)
    return None


def frame_digest(image: np.ndarray) -> int:
    """CRC-32 of a frame's samples (0.6 ms a 1024^2 16-bit frame): equal for a frame sent twice."""
    return zlib.crc32(memoryview(np.ascontiguousarray(image)).cast("B"))


def measure_frame(reconstruct, image: np.ndarray, ref_shape, grid: str):
    """Reconstruct one frame: ``(Result, OK)`` or ``(None, FrameOutcome)`` for a bad frame.

    Raises only what is not the frame's fault.
    """
    image = np.asarray(image)
    if image.shape != tuple(ref_shape):
        return None, FrameOutcome(
            FrameStatus.SHAPE_MISMATCH,
            f"frame has shape {image.shape} (rows, cols) but the reference has {tuple(ref_shape)}; "
            f"use frames and reference from the same camera and region")
    lo, hi = (image.min(), image.max()) if image.size else (0, 0)
    if lo == hi:
        return None, FrameOutcome(
            FrameStatus.BLANK,
            f"every pixel of the frame is {lo:g} (a {'black' if hi == 0 else 'uniform'} frame: "
            f"lost packets, no light or a saturated exposure)")
    saturated = saturation_pct(image)
    bands = bands_of(reconstruct, image, saturated)
    try:  # bands of light along the rows are evened out first (processing.banding.even_rows)
        result = reconstruct(evened_frame(image, bands), grid=grid)
    except TirdeflectError as exc:
        outcome = outcome_of_error(exc)
        if outcome is None:
            raise
        return None, outcome
    if not np.asarray(result.valid, dtype=bool).any():
        return None, FrameOutcome(
            FrameStatus.NO_CONTRAST,
            "no pixel of the frame could be measured (no pattern contrast: black, saturated or "
            "fully blurred frame); check exposure and that the pattern is in view")
    measured_pct, contrast = coverage(result, reconstruct.reference_valid, reconstruct.pattern == "checkerboard")
    cause = unmeasured_cause(contrast, reconstruct.min_amplitude) if measured_pct < PARTLY_MEASURED_PCT else ""
    return result, FrameOutcome(saturated_pct=saturated, hot_pixels=result.hot_pixels, turn=result.turn,
                                light_bands=bands, measured_pct=measured_pct, unmeasured_cause=cause,
                                digest=frame_digest(image))


#: A measured frame whose valid samples cover less than this percentage of the area its reference covers is
#: named in the run's summary, with why (:func:`unmeasured_cause`): a blurred or hidden frame keeps a few
#: specks that pass the contrast test, pinned on whatever is nearest (by-hand trial of 7 Dec 2026: a frame
#: blurred by a Gaussian of 2.5 px, 0.4 % of it measured and 82 % off there, was stored as measured, and
#: the only words were the pin's fallback and a jump).
PARTLY_MEASURED_PCT = 50.0
#: From this percentage of the reference's area unmeasured (NaN) up to :data:`PARTLY_MEASURED_PCT`, a measured
#: frame is counted in a note: by-hand trial of 7 Dec 2026, the impact's centre was NaN in 63 frames (up to 11 %
#: of the field, where its depth lies) and the export said "every frame measured, none flagged".
UNMEASURED_NOTE_PCT = 1.0


def coverage(result, reference_valid, judge_contrast: bool):
    """``(measured_pct, contrast_unmeasured)`` of a frame's ``result``: the percentage of the area the
    reference covers (``reference_valid``, bool on the decimated grid) that the frame measured, and, where
    ``judge_contrast`` (checkerboards: ``result.amplitude`` is the pattern's contrast against the
    reference's) and the frame is named for it (under :data:`PARTLY_MEASURED_PCT`), the median of that
    contrast on the samples of that area it did not measure (else NaN: not needed, not computed)."""
    valid = np.asarray(result.valid, bool)
    covered = np.asarray(reference_valid, bool)
    if covered.shape != valid.shape:  # the full grid: the decimated samples' own pixels (cv2.resize's centres)
        import cv2

        covered = cv2.resize(covered.view(np.uint8), valid.shape[::-1], interpolation=cv2.INTER_NEAREST) > 0
    n_covered = int(np.count_nonzero(covered))
    if n_covered == 0:
        return 100.0, float("nan")
    measured_pct = min(100.0, 100.0 * np.count_nonzero(valid & covered) / n_covered)
    contrast = float("nan")
    unmeasured = covered & ~valid if judge_contrast and measured_pct < PARTLY_MEASURED_PCT else None
    if unmeasured is not None and unmeasured.any():
        amplitude = np.asarray(result.amplitude, np.float64)[unmeasured]
        amplitude = amplitude[np.isfinite(amplitude)]
        contrast = float(np.median(amplitude)) if amplitude.size else float("nan")
    return float(measured_pct), contrast


def unmeasured_cause(contrast: float, min_contrast: float) -> str:
    """Why a frame was not measured on part of its reference's area, from the pattern's ``contrast`` there
    (:func:`coverage`; NaN: not judged) against the quality mask's ``min_contrast``."""
    if not np.isfinite(contrast):
        return "the pattern could not be matched there"
    if contrast < min_contrast:
        return (f"the pattern's contrast there is {contrast:.2f} of the reference's (median; the mask needs "
                f"{min_contrast:.2f}): blurred (focus, motion blur), dimmed or washed out there, or hidden "
                f"(a splash, a shadow, a drop or dirt on the glass)")
    return (f"the pattern kept its contrast there ({contrast:.2f} of the reference's, median): it folded "
            f"(caustics of steep slopes) or broke into islands too small to join the rest")


class FrameTally:
    """Counts the outcomes of the processed frames and the recorder's flags (never silent).
    ``reference_digest``: the reference's :func:`frame_digest`, so that a frame that is the reference
    itself is named (-1: not known)."""

    #: invalid frames logged one by one; the rest are counted in the summary
    LOG_FIRST = 10

    def __init__(self, reference_digest: int = -1):
        from drivers.base import FrameFlags

        self._incomplete_flag = int(FrameFlags.INCOMPLETE)
        self._loss_flags = int(FrameFlags.ID_GAP_BEFORE | FrameFlags.TIME_GAP_BEFORE
                               | FrameFlags.RING_OVERRUN_BEFORE)
        self.frames = 0
        self.valid = 0
        self.invalid: dict = {}  # FrameStatus -> list of (sequence_index, label, reason)
        self.incomplete = []
        self.gaps = []
        self.saturated = []  # (sequence index, % of pixels saturated) above SATURATION_MAX_PCT
        self.hot = []  # (sequence index, hot pixels repaired) of frames with any
        self.turned = []  # (sequence index, |turn| mrad, TurnCheck) of frames whose pattern turned
        self.banded = []  # (sequence index, LightBands.depth, LightBands) of frames with bands of light along rows
        self.vignetted = []  # (sequence index, darkest corner's light, LightBands) of frames darkened to the corners
        self.partial = []  # (sequence index, % measured, why not all) of frames measured on < PARTLY_MEASURED_PCT
        self.holed = []  # (sequence index, % not measured) of the others with UNMEASURED_NOTE_PCT or more unmeasured
        self.repeated = []  # (sequence index, the one before's) of measured frames identical to the frame before them
        self._last_digest, self._last_index = -1, -1  # of the frame added last (digest -1: not measured)
        self.reference_digest = reference_digest
        # (sequence index, time before, time, file before, file) where /time_s went back; (time, file) of the last
        self.time_back, self._last_time = [], (math.nan, "")
        self.as_reference = []  # (sequence index, 0) of measured frames that are the reference, sample for sample

    def add(self, item, outcome: FrameOutcome) -> None:
        self.frames += 1
        t = float(item.time_s)
        if math.isfinite(t):  # (by-hand trial of 7 Dec 2026: files given out of order, said by `probe` alone)
            before, file_before = self._last_time
            if t < before:
                self.time_back.append((item.sequence_index, before, t, file_before, item.source))
            self._last_time = (t, item.source)
        if outcome.ok and outcome.digest != -1 and outcome.digest == self.reference_digest:
            _add_row(self.as_reference, item, 0, "the reference image itself, sample for sample: its heights are "
                                                 "%d by definition")
        if outcome.ok and outcome.digest != -1 and outcome.digest == self._last_digest:
            _add_row(self.repeated, item, self._last_index,
                     "identical to the frame before it (%d), sample for sample: the camera sent a frame twice")
        self._last_digest, self._last_index = (outcome.digest if outcome.ok else -1), item.sequence_index
        if outcome.ok:
            self.valid += 1
            if outcome.saturated_pct > SATURATION_MAX_PCT:
                _add_row(self.saturated, item, outcome.saturated_pct, "%.1f %% of its pixels saturated")
            if outcome.hot_pixels:
                _add_row(self.hot, item, outcome.hot_pixels,
                         "%d isolated pixel(s) brighter than anything the reference's pattern shows repaired")
            if outcome.light_bands is not None and outcome.light_bands.flagged:
                _add_row(self.banded, item, 100 * outcome.light_bands.depth,
                         "bands of light along the rows, %.2g %% RMS alike across the whole width, that the reference "
                         "does not show (a rolling shutter under flickering light, or a shadow's edge along the rows)",
                         outcome.light_bands)
            if outcome.light_bands is not None and outcome.light_bands.vignetted and not outcome.light_bands.flagged:
                _add_row(self.vignetted, item, outcome.light_bands.vignette.corner,
                         "vignetting: its darkest corner at %.2g of the light of its brightest part", outcome.light_bands)
            if outcome.measured_pct < PARTLY_MEASURED_PCT:
                _add_row(self.partial, item, outcome.measured_pct, "only %.1f %% of the area its reference covers "
                         "could be measured: " + outcome.unmeasured_cause.replace("%", "%%"), outcome.unmeasured_cause)
            elif 100.0 - outcome.measured_pct >= UNMEASURED_NOTE_PCT:
                self.holed.append((item.sequence_index, 100.0 - outcome.measured_pct))
            if outcome.turn is not None and outcome.turn.flagged:
                _add_row(self.turned, item, abs(outcome.turn.turn_mrad),
                         "the pattern turned by %.2f mrad since the reference (the camera or the board moved)",
                         outcome.turn)
        else:
            self.invalid.setdefault(outcome.status, []).append(
                (item.sequence_index, item.label, outcome.reason))
            if self.n_invalid <= self.LOG_FIRST:
                log.warning("frame %d (%s) is invalid (%s): %s%s", item.sequence_index, item.label,
                            outcome.status.label, outcome.reason,
                            "; further invalid frames are only counted" if self.n_invalid == self.LOG_FIRST
                            else "")
        if item.flags & self._incomplete_flag:
            self.incomplete.append(item.sequence_index)
            if len(self.incomplete) <= self.LOG_FIRST:
                log.warning("frame %d (%s) was flagged INCOMPLETE by the camera: its heights may be wrong%s",
                            item.sequence_index, item.label,
                            "; further INCOMPLETE frames are only counted"
                            if len(self.incomplete) == self.LOG_FIRST else "")
        if item.flags & self._loss_flags:
            self.gaps.append(item.sequence_index)

    @property
    def n_invalid(self) -> int:
        return self.frames - self.valid

    def first_invalid(self):
        """(sequence_index, label, reason) of the earliest invalid frame, or None."""
        rows = [row for rows in self.invalid.values() for row in rows]
        return min(rows) if rows else None

    def invalid_summary(self) -> str:
        """e.g. ``9 blank, 3 pattern mismatch (first: frame 4 (a.tif): every pixel ...)``."""
        if not self.invalid:
            return ""
        parts = ", ".join(f"{len(rows)} {status.label}" for status, rows in sorted(self.invalid.items()))
        k, label, reason = self.first_invalid()
        return f"{parts} (first: frame {k} ({label}): {reason})"

    def attrs(self) -> dict:
        counts = {f"frames_{status.name.lower()}": len(self.invalid.get(status, ()))
                  for status in FrameStatus if status != FrameStatus.OK}
        return {"frames_valid": self.valid, "frames_invalid": self.n_invalid, **counts,
                "frames_flagged_incomplete": len(self.incomplete),
                "frames_with_loss_before": len(self.gaps), "frames_saturated": len(self.saturated),
                "saturated_pct_max": _worst(self.saturated, 0.0)[1],
                "frames_with_hot_pixels": len(self.hot), "hot_pixels_max": _worst(self.hot, 0)[1],
                "frames_turned": len(self.turned), "turn_mrad_max": _worst(self.turned, 0.0)[1],
                "frames_light_banded": len(self.banded), "light_bands_pct_max": _worst(self.banded, 0.0)[1],
                "frames_vignetted": len(self.vignetted),
                "frames_partly_measured": len(self.partial), "measured_pct_min": _least(self.partial, 100.0)[1],
                "frames_repeated": len(self.repeated), "frames_as_reference": len(self.as_reference),
                "frames_partly_unmeasured": len(self.holed), "unmeasured_pct_max": _worst(self.holed, 0.0)[1],
                "frames_time_back": len(self.time_back)}

    def notes(self) -> list:
        out = []
        if self.incomplete:
            out.append(f"{len(self.incomplete)} processed frame(s) were recorded INCOMPLETE "
                       f"(missing packets), e.g. frame {self.incomplete[0]}: their heights may be wrong; "
                       f"see /frame_flags in the output")
        if self.gaps:
            out.append(f"the recording lost frames before {len(self.gaps)} processed frame(s), "
                       f"e.g. before frame {self.gaps[0]}: time steps are not uniform; "
                       f"see /frame_flags and /device_timestamp_ns")
        if self.saturated:
            k, pct = _worst(self.saturated, 0.0)
            out.append(f"{len(self.saturated)} frame(s) have more than {SATURATION_MAX_PCT:g} % of their pixels "
                       f"saturated (up to {pct:.1f} %, frame {k}): clipped bright squares cost accuracy "
                       f"(ray-traced, 40 % clipped: 3x the rms height error); lower the exposure or gain "
                       f"for the next recording")
        if self.hot:
            k, n = _worst(self.hot, 0)
            out.append(f"{len(self.hot)} frame(s) had isolated pixels brighter than anything the reference's "
                       f"pattern shows (up to {n}, frame {k}): repaired before measuring (cosmic rays, or hot "
                       f"pixels the reference does not have: take the reference at the frames' exposure); "
                       f"see /hot_pixels in the output")
        if self.banded:
            k, pct, bands = _worst(self.banded, 0.0)
            out.append(f"{len(self.banded)} frame(s) show {bands.describe()} (the most at frame {k}, "
                       f"{pct:.2g} %)")
        if self.vignetted:
            k, _, bands = _least(self.vignetted, 1.0)
            out.append(f"{len(self.vignetted)} frame(s) show {bands.describe()} (the darkest corners at frame {k})")
        if self.partial:
            k, pct, cause = _least(self.partial, 100.0)
            out.append(f"{len(self.partial)} frame(s) were measured on less than {PARTLY_MEASURED_PCT:g} % of the area "
                       f"their reference covers (the least {pct:.1f} %, frame {k}: {cause}); their heights are "
                       f"measured there only, and their pin may be a fallback; see /valid and /pin_status in the "
                       f"output")
        if self.holed:
            k, pct = _worst(self.holed, 0.0)[:2]
            out.append(f"{len(self.holed)} measured frame(s) were not measured on part of their area (up to "
                       f"{pct:.1f} %, frame {k}; from frame {self.holed[0][0]} to {self.holed[-1][0]}): their heights "
                       f"are NaN there (/valid), where the surface was too steep, the pattern folded or was hidden; "
                       f"what lies there, an impact's depth or a crest, is not in the heights")
        if self.repeated:
            k, before = self.repeated[0]
            out.append(f"{len(self.repeated)} frame(s) identical to the one before, sample for sample (first frame "
                       f"{k}, as frame {before}): the camera repeated a frame (one dropped and filled in by the driver "
                       f"or the grabber, or a trigger faster than the camera's frame rate), so their heights repeat "
                       f"the frame's before and their time steps are not real; check the camera's frame rate, "
                       f"exposure and trigger, and /frame_flags where the recording has them")
        if self.time_back:
            k, before, t, file_before, file = self.time_back[0]
            where = f"{file} after {file_before}" if file != file_before else f"within {file}"
            out.append(f"the frames' time (/time_s) goes back at {len(self.time_back)} place(s), first at frame {k} "
                       f"({before:.9g} s, then {t:.9g} s: {where}): files given out of order or twice, or each "
                       f"counting its times from its own start or trigger; plot against /frame_index (/source "
                       f"names each frame's file)")
        if self.as_reference:
            out.append(f"{len(self.as_reference)} frame(s) are the reference image itself, sample for sample (first "
                       f"frame {self.as_reference[0][0]}): their heights are 0 by definition, not a measurement of "
                       f"the surface; was the reference file given among the frames?")
        if self.turned:
            k, mrad, turn = _worst(self.turned, 0.0)
            first = self.turned[0][0]  # when it happened: a knock turns every frame after it
            out.append(f"{len(self.turned)} frame(s) flagged above {TURN_MAX_MRAD:g} mrad of turn, from frame {first}, "
                       f"the most at frame {k}: {turn.describe()}; see /turn_mrad in the output")
        return out


def _add_row(rows: list, item, value, what: str, *more) -> None:
    """Append ``(item.sequence_index, value, *more)`` to ``rows``; log the first such frame as a warning
    (``what`` % ``value`` after the frame's name), the later ones at debug level (counted in the summary)."""
    rows.append((item.sequence_index, value, *more))
    (log.warning if len(rows) == 1 else log.debug)(f"frame %d (%s): {what}", item.sequence_index, item.label, value)


def _least(rows: list, nothing):
    """The row ``(sequence index, value, ...)`` of ``rows`` with the smallest value (the first of equals);
    ``(None, nothing, "")`` when there is none."""
    return min(rows, key=lambda row: row[1], default=(None, nothing, ""))


def _worst(rows: list, nothing):
    """The row ``(sequence index, value, ...)`` of ``rows`` with the largest value (the first of equals);
    ``(None, nothing)`` when there is none."""
    return max(rows, key=lambda row: row[1], default=(None, nothing))
