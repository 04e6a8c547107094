"""Bands of light along a frame's rows that its reference does not show: a
rolling shutter under light that flickers within a frame (PWM-dimmed LEDs), or
a shadow's edge along the rows.  Each row is exposed at its own moment, so the
light, and with it the frame's grey levels, steps from row to row alike across
the whole width; where the steps are sharp they read as surface, as a shadow's
edge does (docs/processing.md section 10): ``tirdeflect simulate``'s bump and
waves under bands 30 % darker every 32 rows 0.05 -> 1.9-2.1 % and 0.20 -> 1.9-2.0 %
rel. RMS height error, with exit 0 and no word (7 Dec 2026).

:func:`row_profile` low-passes an image along its rows only (a 31 px box, about
a board's period; the bands' edges kept) and samples it; :func:`light_bands` compares a
frame's profile with the reference's: each quarter of the width gets its own
row gain (the median over its columns of frame over reference) and that gain's
departure from its smooth trend; per row the smallest of the four departures
where all four agree in sign, else 0: what every part of the width shares, as
bands do and an object in part of the view (a floating ring, a needle) does not.
:func:`even_rows` divides a named frame's rows by their gains (the batch's frame
check, :mod:`app.batch.frame_status`, and the live window's,
:mod:`app.capture.live_measure`, do so before measuring).  Not taken for bands:
what a frame's own response does to the board (a gamma other than the
reference's: the row frequencies of the board's harmonics are left out of the
judgement, :func:`board_row_frequencies`), and a clipped frame or reference
(not judged, :func:`clipped`).  Nor is vignetting (:func:`vignette_of`): a frame darkened towards its edges and
corners against its reference (the lens opened up, the light moved) makes each quarter's row gains bend alike,
and the 64-row trend cannot follow the bend near the top and bottom rows, where the outer quarters also fall
under :data:`LIT_MIN_GAIN`: simulate's board at 256^2 and 512^2 with corners at 50 / 20 / 5 % of the middle's
light (falling as cos^4 or a Gaussian) read as bands 0.02-0.05 / 0.05-0.13 / 0.24-0.33 deep at 0.5-0.98 of
agreement, and most were named and evened as banded.  A smooth fall-off towards every side is now
named as what it is (:class:`Vignette`), bands are judged on the frame's light over it, and it is not evened.
"""

from __future__ import annotations

import dataclasses
import functools
import warnings
from typing import Optional

import cv2
import numpy as np
from scipy.ndimage import uniform_filter1d

from .live_view import SATURATION_MAX_PCT, saturation_pct

__all__ = ["BANDS_MIN_DEPTH", "BANDS_MIN_AGREEMENT", "BOARD_HARMONIC_ORDER", "BOARD_NOTCH_BINS",
           "MIN_CYCLES_PER_QUARTER", "VIGNETTE_DEGREE", "VIGNETTE_BLOCKS", "VIGNETTE_MAX_MISFIT", "VIGNETTE_MAX_EDGE",
           "VIGNETTE_NAMED_CORNER",
           "LightBands", "RowLight", "Vignette", "board_row_frequencies", "clipped", "even_rows", "bands_of",
           "evened_frame", "frame_light_bands", "light_bands", "reference_light", "row_profile", "vignette_of"]

#: Box along the rows (px) of :func:`row_profile`; it samples every ``cols // COLUMNS_PER_STEP`` columns
#: (2 to 16 px: 64 samples or more across, 16 to a quarter; at 256^2 every 16 px left bands 10 % deep at
#: 0.51 of agreement, every 4 px 0.70).
ROW_BOX_PX = 31
COLUMNS_PER_STEP = 64
#: The row gains' smooth trend (a Gaussian of this many rows): slow changes of light (vignetting, a
#: dimmer frame) are not bands.
TREND_ROWS = 64.0
#: A row whose gain against the reference is under this in any quarter is not lit: lost packets (rows of
#: 0), a black object across the frame; it is neither judged nor evened.
LIT_MIN_GAIN = 0.1
#: Bands are named where the shared departure's RMS reaches this fraction ...
#: (measured at 512^2: bands 30 / 10 / 3 % deep, 0.15-0.17 / 0.041-0.049 / 0.008-0.013; a horizontal
#: shadow edge at half the light 0.11; at most 0.0096 on simulate's bump and waves, the synthetic
#: tank's scenes, random dots and the real needle and trapped-mode frames, 0.0035 / 0.0175 on the real
#: floating ring and ellipse frames, where the objects move the quarters' gains one by one)
BANDS_MIN_DEPTH = 0.02
#: ... and the four quarters agree in sign on at least this share of the rows (bands 10-30 % deep
#: 0.95-1.00, every scene without them at most 0.24, vignetting along the columns 0.51 at 0.0065).
#: Smooth bands (200 rows long, 20 %: mains flicker) are named too (0.043-0.051, 0.91-0.95) though they
#: cost nothing measurable: only sharp edges read as surface.
BANDS_MIN_AGREEMENT = 0.6


#: A frame's light against its reference's is taken for vignetting (:func:`vignette_of`), not bands, where a
#: smooth surface, a polynomial of this degree in x and y fitted to the log of their ratio over blocks of the
#: row profiles (this many rows and columns of blocks) ...
VIGNETTE_DEGREE = 4
VIGNETTE_BLOCKS = (32, 16)
#: ... fits it within this RMS (of the log, after what whole rows of blocks share: bands on top of it) ...
#: (measured 7 Dec 2026 on simulate's board, bump and waves, 256^2 / 512^2: vignettes falling like cos^4 or a
#: Gaussian to 50-2 % at the corners 0.033-0.050 / 0.005-0.046, the same frames without them 0.033-0.042 /
#: 0.005-0.009; a dark disc in the middle 0.23-0.28, a shadow over half of every row 0.09-0.11, the real needle
#: frame 0.16, the real floating ring and ellipse 0.66-0.84)
VIGNETTE_MAX_MISFIT = 0.07
#: ... and falls towards all four sides: the mean of the fitted light along each side at most this fraction of
#: its brightest row's and column's (or, the reference the darker, the same of the inverse).  Measured (the same
#: frames): vignettes to 70 / 50 / 20 / 5 % at the corners 0.91-0.96 / 0.83-0.92 / 0.62-0.84 / 0.36-0.72; bands
#: along the rows, smooth or sharp, a shadow's edge along them, light falling off along the columns, 0.99-1.00
#: (what does not change along the rows leaves the columns' means flat).  Vignettes to 80 % and more at the
#: corners (0.94-0.99) are not named, nor were they taken for bands.
VIGNETTE_MAX_EDGE = 0.97
#: A vignette is named (:attr:`Vignette.named`) where its darkest corner's light is at most this fraction of the
#: brightest part's: where the light falls under about a third, the pattern's contrast is too low to be measured
#: (ray traced, simulate's board, a 4 um bump and waves at 256^2 and 512^2: light under 0.2 of the brightest
#: never measured, 0.2-0.35 in 5-69 %, above it all; vignettes to 5 % at the corners left 40-63 % of the frame
#: measured). A milder one costs nothing: only its bands are judged over it, in silence.
VIGNETTE_NAMED_CORNER = 0.35


@dataclasses.dataclass(frozen=True)
class Vignette:
    """A frame's light against its reference's falling off smoothly from the middle towards every side and
    corner (:func:`vignette_of`): vignetting in one of them, not bands along the rows."""

    #: the darkest corner's light over the brightest part's: the frame's against the reference's, or (where
    #: :attr:`in_reference`) the reference's against the frame's
    corner: float
    #: whether the reference is the one darker towards its corners
    in_reference: bool = False
    #: the fitted fall-off (frame over reference) on the grid of the row profiles (:func:`row_profile`)
    model: np.ndarray = dataclasses.field(default=None, compare=False, repr=False)

    @property
    def named(self) -> bool:
        """Dark enough at a corner to cost part of the frame (:data:`VIGNETTE_NAMED_CORNER`)."""
        return bool(self.corner <= VIGNETTE_NAMED_CORNER)

    def describe(self) -> str:
        pct = f"{100 * self.corner:.2g} %"
        if self.in_reference:
            return (f"the reference darkens towards its edges and corners against this frame (vignetting when the "
                    f"reference was taken: its darkest corner at about {pct} of the light of its brightest part, as "
                    f"this frame is lit), a smooth fall-off, not bands along the rows, and not evened out. Where the "
                    f"reference is darker than about a third of its brightest light, nothing is measured (masked). "
                    f"Capture the reference again under the light of these frames")
        return (f"the image darkens towards its edges and corners against the reference (vignetting: its darkest "
                f"corner at about {pct} of the light of its brightest part, as the reference is lit), a smooth "
                f"fall-off, not bands along the rows, and not evened out. Where the light falls under about a third "
                f"of the brightest, the pattern's contrast is too low and the corners are not measured (masked); "
                f"the heights elsewhere are as without it, a little noisier beside the masked corners (ray traced). "
                f"The light changed since the reference: the lens was opened up (wide open, a lens darkens its "
                f"corners), or the light moved or narrowed. Stop the lens down, or centre and widen the light on the "
                f"board; a new reference under this light does not bring the corners back")


def vignette_of(ratio) -> Optional[Vignette]:
    """The :class:`Vignette` of ``ratio`` (rows, samples: a frame's :func:`row_profile` over its reference's, NaN
    where the reference is dark), or None where its light does not fall off smoothly towards every side: the log
    of its block means (:data:`VIGNETTE_BLOCKS`) fitted by a polynomial in x and y (:data:`VIGNETTE_DEGREE`),
    within :data:`VIGNETTE_MAX_MISFIT` but for what whole rows of blocks share, and its means along each side at
    most :data:`VIGNETTE_MAX_EDGE` of its brightest row's and column's (or of the inverse's: the reference the
    darker).  0.3-1 ms a 1024^2 frame's profile, most of it the block means."""
    ratio = np.asarray(ratio, np.float64)
    rows, cols = ratio.shape
    nr, nc = min(VIGNETTE_BLOCKS[0], rows // 4), min(VIGNETTE_BLOCKS[1], cols // 2)
    if nr < 8 or nc < 6:
        return None
    blocks, y, x = _block_means(ratio[::max(1, rows // 256)], nr, nc)  # (every k-th row: as good, 4x faster)
    ok = np.isfinite(blocks) & (blocks > 1e-3)
    if ok.mean() < 0.5 or not (_falls_to_every_side(np.where(ok, blocks, np.nan), 0.99)
                               or _falls_to_every_side(np.where(ok, 1.0 / np.where(ok, blocks, 1.0), np.nan), 0.99)):
        return None  # (most frames: no fit)
    terms = [(i, j) for i in range(VIGNETTE_DEGREE + 1) for j in range(VIGNETTE_DEGREE + 1 - i)]
    grid_y, grid_x = np.meshgrid(y, x, indexing="ij")
    basis = np.stack([grid_y[ok] ** i * grid_x[ok] ** j for i, j in terms], axis=1)
    logs = np.log(blocks[ok])
    coef = np.linalg.lstsq(basis, logs, rcond=None)[0]
    misfit = np.full(blocks.shape, np.nan)
    misfit[ok] = logs - basis @ coef
    misfit -= _nanmedian_of_rows(misfit)[:, None]  # what whole rows share: bands on top of it
    if not np.sqrt(np.nanmean(misfit ** 2)) <= VIGNETTE_MAX_MISFIT:
        return None
    power = np.zeros((VIGNETTE_DEGREE + 1, VIGNETTE_DEGREE + 1))
    for (i, j), c in zip(terms, coef):
        power[i, j] = c
    fitted = np.exp(_powers(y) @ power @ _powers(x).T)  # on the blocks
    in_reference = not _falls_to_every_side(fitted, VIGNETTE_MAX_EDGE)
    if in_reference and not _falls_to_every_side(1.0 / fitted, VIGNETTE_MAX_EDGE):
        return None
    model = np.exp(_powers(np.linspace(-1.0, 1.0, rows)) @ power @ _powers(np.linspace(-1.0, 1.0, cols)).T)
    light = 1.0 / model if in_reference else model
    corner = float(np.min(light[[0, 0, -1, -1], [0, -1, 0, -1]]) / np.max(light))
    return Vignette(corner, in_reference, model)


def _block_means(a, nr: int, nc: int):
    """Means of the finite values of ``a`` (2-D) over ``nr`` x ``nc`` blocks (NaN where fewer than half are),
    the blocks' centres in -1 .. 1 along the rows and along the columns."""
    rows, cols = a.shape
    hr, hc = rows // nr, cols // nc
    r0, c0 = (rows - hr * nr) // 2, (cols - hc * nc) // 2
    part = a[r0:r0 + hr * nr, c0:c0 + hc * nc]
    finite = np.isfinite(part)
    # (summed along the rows first, then the columns: a sum over two strided axes at once took 5x as long)
    count, total = (np.add.reduceat(np.add.reduceat(v, np.arange(0, hc * nc, hc), axis=1), np.arange(0, hr * nr, hr),
                                    axis=0) for v in (finite.astype(np.float64), np.where(finite, part, 0.0)))
    means = np.where(count > hr * hc / 2, total / np.maximum(count, 1), np.nan)
    centres = [(2 * (start + size * (np.arange(n) + 0.5) - 0.5) - (length - 1)) / (length - 1)
               for start, size, n, length in ((r0, hr, nr, rows), (c0, hc, nc, cols))]
    return means, centres[0], centres[1]


def _nanmedian_of_rows(a):
    """``np.nanmedian(a, axis=1)`` of a 2-D float array, 0 for a row without a finite value (NumPy's took 0.6 ms
    on 32 x 16 blocks, through masked arrays)."""
    s = np.sort(a, axis=1)  # NaN last
    k = np.isfinite(a).sum(axis=1)
    at = np.arange(a.shape[0])
    return np.where(k > 0, (s[at, np.maximum(k - 1, 0) // 2] + s[at, np.minimum(k // 2, a.shape[1] - 1)]) / 2, 0.0)


def _powers(u):
    """``u`` to the powers 0 .. :data:`VIGNETTE_DEGREE`, one per column."""
    return np.stack([np.asarray(u, np.float64) ** k for k in range(VIGNETTE_DEGREE + 1)], axis=-1)


def _falls_to_every_side(light, most: float) -> bool:
    """Is the mean of ``light`` (2-D, NaN where unknown) along each of its four sides at most ``most`` of its
    brightest row's mean (top and bottom) and column's (left and right)?"""
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a side with no known block (an incomplete frame's)
        along_rows, along_cols = np.nanmean(light, axis=1), np.nanmean(light, axis=0)
        return bool(max(along_rows[0], along_rows[-1]) <= most * np.nanmax(along_rows)
                    and max(along_cols[0], along_cols[-1]) <= most * np.nanmax(along_cols))


@dataclasses.dataclass(frozen=True)
class LightBands:
    """How a frame's light varies along its rows against the reference's (:func:`light_bands`)."""

    #: RMS of the row gain's departure shared by the whole width (a fraction of the light)
    depth: float
    #: share of the rows whose four quarters depart to the same side
    agreement: float
    #: (rows,) each row's gain against the reference about the smooth trend: the middle of its four
    #: quarters' (what :func:`even_rows` divides by)
    row_gain: np.ndarray = dataclasses.field(default=None, compare=False, repr=False)
    #: whether the row gains are the light's alone (False where the board's stripes run along the rows,
    #: :data:`MIN_CYCLES_PER_QUARTER`: there they hold the pattern's own motion, and are not divided by)
    evenable: bool = True
    #: the frame darkened towards its edges and corners against the reference, or the reference against the
    #: frame (:func:`vignette_of`); the other fields then judge the frame's light over that fall-off
    vignette: Optional[Vignette] = None

    @property
    def flagged(self) -> bool:
        """Bands of light along the rows (on top of a vignette, where there is one)."""
        return bool(self.depth >= BANDS_MIN_DEPTH and self.agreement >= BANDS_MIN_AGREEMENT)

    @property
    def evened(self) -> bool:
        """Named and evened out before measuring (:func:`even_rows`)."""
        return self.flagged and self.evenable

    @property
    def vignetted(self) -> bool:
        """Darkened towards the corners enough to say so (:attr:`Vignette.named`)."""
        return self.vignette is not None and self.vignette.named

    @property
    def named(self) -> bool:
        """Bands, or a vignette worth naming: something to say of the frame's light (:meth:`describe`)."""
        return self.flagged or self.vignetted

    def describe(self) -> str:
        if self.vignetted and not self.flagged:
            return self.vignette.describe()
        return self._bands_text() + (f". Besides, {self.vignette.describe()}" if self.vignetted else "")

    def _bands_text(self) -> str:
        what = (f"bands of light along the rows, {100 * self.depth:.2g} % RMS alike across the whole width, that "
                f"the reference does not show: a rolling shutter under light that flickers within a frame "
                f"(PWM-dimmed LEDs), or a shadow's edge along the rows; ")
        done = ("evened out before measuring (each row divided by its gain against the reference: bands 30 % deep "
                "had cost about 2 % of the heights' RMS, evened 0.08 %, ray traced)" if self.evenable else
                "NOT evened out: the board's stripes run along the rows (a board turned about 45 deg against the "
                "image), where a row's light cannot be told from the pattern's own motion; bands 30 % deep cost "
                "about 5 % of the heights' RMS there (ray traced). Turn the board 20-30 deg off the rows")
        return f"{what}{done}. Better DC-driven light, a global shutter or an exposure of whole PWM periods"


def even_rows(image, bands: LightBands) -> np.ndarray:
    """``image`` (2-D) with each row divided by its gain (:attr:`LightBands.row_gain`), float32: the bands
    evened out, as a frame taken under the reference's light.  Measured (512^2 ray traced, bands 30 / 10 %
    deep every 32 rows): a 4 um bump 3.29 / 0.98 -> 0.081 / 0.080 % (0.076 without bands), waves 1.30 /
    0.51 -> 0.226 / 0.221 % (0.240)."""
    out = np.array(image, dtype=np.float32)
    out /= np.asarray(bands.row_gain, np.float32)[:, None]
    return out


def row_profile(image) -> np.ndarray:
    """``image`` (2-D) low-passed along its rows only (a box of :data:`ROW_BOX_PX`: blocks of 8 px
    averaged, then 4 blocks) and sampled every 2-16 columns (:data:`COLUMNS_PER_STEP`): float32 (rows,
    samples).  0.5 ms a 1024^2 frame (:func:`light_bands` 0.9 ms)."""
    a = np.asarray(image)
    if a.dtype not in (np.uint8, np.uint16, np.float32, np.float64):
        a = a.astype(np.float32)
    rows, cols = a.shape
    block = 8 if cols >= 8 * ROW_BOX_PX // 4 * 2 else 1
    small = cv2.resize(a, (cols // block, rows), interpolation=cv2.INTER_AREA) if block > 1 else a
    box = max(1, ROW_BOX_PX // block)
    lp = cv2.blur(np.asarray(small, np.float32), (box, 1), borderType=cv2.BORDER_REFLECT)
    step = max(1, max(2, min(16, cols // COLUMNS_PER_STEP)) // block)
    return np.ascontiguousarray(lp[:, box // 2::step])


#: A frame's row gains are divided out (:func:`even_rows`) only where each of the board's carriers runs
#: at least this many cycles along a quarter of the width (the quarter's median then averages the
#: pattern out of its rows' gains).  Measured (6 Dec 2026, 256^2, a 2 um bump of sigma 3.2 mm under
#: bands 30 % deep, 2 x 2 rays; heights' rel. RMS error banded / evened, %), the board turned so that its
#: slower carrier runs 3.2 / 1.17 / 0.79 / 0.55 / 0.47 / 0.39 / 0.32 / 0.24 / 0.16 / 0 cycles a quarter:
#: 4.00 / 0.13, 4.49 / 0.25, 4.54 / 0.76, 4.76 / 0.66, 4.76 / 1.12, 4.80 / 2.90, 4.83 / 4.26, 4.93 / 11.9,
#: 5.02 / 21.9, 5.02 / 31.2 (0.10-0.14 without bands): evened, a board seen as diamonds lost its pattern.
MIN_CYCLES_PER_QUARTER = 0.35

#: Harmonics ``i k1 + j k2`` of the board, ``|i|, |j|`` up to this, whose row frequencies
#: :func:`board_row_frequencies` lists ...
BOARD_HARMONIC_ORDER = 5
#: ... and the half width (FFT bins of the rows) of the notch :func:`light_bands` puts at each.
BOARD_NOTCH_BINS = 2


def board_row_frequencies(carriers_freq, cols: int) -> tuple:
    """Row frequencies (cycles/row, folded into (0, 0.5]) of the board's harmonics ``i k1 + j k2``
    (``carriers_freq``: (2, 2) cycles/px, rows and columns; :data:`BOARD_HARMONIC_ORDER`) that stay alike
    across a frame of ``cols`` columns (less than one cycle over its width): where a frame whose response
    is not the reference's (a gamma, clipping: the board's bright and dark parts scaled apart) changes
    each row's mean with the row's place on the board, alike across the width, as bands of light do.
    On the square board seen square (carriers on the diagonals) ``k1 - k2`` and its multiples; on a board
    turned by a few degrees none (there such changes vary along the rows, and the quarters disagree)."""
    return _board_row_frequencies(tuple(np.round(np.asarray(carriers_freq, np.float64).ravel(), 9)), int(cols))


@functools.lru_cache(maxsize=8)
def _board_row_frequencies(freq: tuple, cols: int) -> tuple:
    k1, k2 = np.reshape(freq, (2, 2))
    found = set()
    for i in range(-BOARD_HARMONIC_ORDER, BOARD_HARMONIC_ORDER + 1):
        for j in range(-BOARD_HARMONIC_ORDER, BOARD_HARMONIC_ORDER + 1):
            if (i or j) and abs(i * k1[1] + j * k2[1]) * cols < 1.0:
                f = abs(i * k1[0] + j * k2[0]) % 1.0
                f = min(f, 1.0 - f)
                if f > 0.0:
                    found.add(round(float(f), 6))
    return tuple(sorted(found))


def light_bands(frame_profile, reference_profile, notch=()) -> LightBands:
    """:class:`LightBands` of a frame's :func:`row_profile` against its reference's (same shape).
    ``notch``: row frequencies (cycles/row, :func:`board_row_frequencies`) taken out of each quarter's
    departure (:data:`BOARD_NOTCH_BINS` either side) before it is judged.  Measured (6 Dec 2026,
    ``tirdeflect simulate``'s board at 256^2 and 512^2, bump and waves): frames at gamma 0.6 / 1.5 against
    a linear reference read as bands 0.017-0.042 deep at 0.58-0.79 of agreement (named at 512^2 and,
    evened out, the bump's error 0.11 -> 0.52 / 1.38 %), notched 0.003-0.014 at 0.07-0.79 (none named);
    bands of light 3-30 % deep (periods 20-200 rows, a gamma on top) within 0.006 of their depth either
    way.  Harmonics to the 4th left 0.017 at 0.82 (the 5th-7th carry the rest), to the 8th took half the
    depth of bands 20 rows apart at 256^2 (the 6th lies on their fundamental).  A board seen as diamonds
    (carriers along the rows and columns) keeps 0.027-0.040 at gamma 1.5 / 0.6 (named): its fundamental
    runs along the rows.  Where the light falls off smoothly towards every side (:func:`vignette_of`), the
    frame is named for that (:attr:`LightBands.vignette`) and its bands are judged over the fall-off."""
    f = np.asarray(frame_profile, np.float64)
    r = np.asarray(reference_profile, np.float64)
    ok = r > 0.05 * float(np.max(r)) if r.size else np.zeros(r.shape, bool)
    ratio = np.where(ok, f / np.where(ok, r, 1.0), np.nan)
    vignette = vignette_of(ratio)
    if vignette is None:
        return _judged(ratio, notch)
    # bands are what the light does over the vignette's smooth fall-off
    return dataclasses.replace(_judged(ratio / vignette.model, notch), vignette=vignette)


def _judged(ratio, notch) -> LightBands:
    """:func:`light_bands` of a frame's row profile over its reference's (``ratio``, NaN where the reference is
    dark)."""
    gains = []
    for cols in np.array_split(np.arange(ratio.shape[1]), 4):
        part = ratio[:, cols]
        if cols.size == 0 or not np.isfinite(part).any():
            return LightBands(0.0, 0.0, np.ones(ratio.shape[0]))
        with np.errstate(all="ignore"):
            g = _median_of_rows(part) if np.isfinite(part).all() else np.nanmedian(part, axis=1)
        finite = np.isfinite(g)
        gains.append(g if finite.all() else np.where(finite, g, np.nanmedian(g)))
    g = np.array(gains)
    # rows with almost no light (lost packets, a black object across the frame) are no bands of light
    lit = np.all(g > LIT_MIN_GAIN, axis=0)
    g = np.where(lit, g, 1.0)
    trend = g
    for _ in range(3):  # three boxes of 2 TREND_ROWS: a Gaussian of TREND_ROWS, in O(rows)
        trend = uniform_filter1d(trend, size=int(2 * TREND_ROWS) + 1, axis=1, mode="nearest")
    d = np.where(lit, g / trend - 1.0, 0.0)
    judged = _notched(d, notch, lit) if len(notch) else d
    same = lit & (np.all(judged > 0, axis=0) | np.all(judged < 0, axis=0))
    shared = np.where(same, np.sign(judged[0]) * np.min(np.abs(judged), axis=0), 0.0)
    # the gains themselves are not notched: sharp bands have harmonics at every frequency, and one left in a
    # frame evened out without it kept their edges (simulate's bump 0.13 -> 3.0 % instead of 0.13 %)
    return LightBands(float(np.sqrt(np.mean(shared ** 2))), float(np.mean(same)), 1.0 + _median_of_rows(d.T))


def _notched(d, notch, lit):
    """The departures ``d`` (quarters, rows) with the row frequencies ``notch`` (cycles/row) taken out,
    :data:`BOARD_NOTCH_BINS` either side; 0 on the rows not ``lit``."""
    n = d.shape[1]
    spectrum = np.fft.rfft(d, axis=1)
    bins = np.fft.rfftfreq(n)
    for f in notch:
        spectrum[:, np.abs(bins - f) <= BOARD_NOTCH_BINS / n] = 0.0
    return np.where(lit, np.fft.irfft(spectrum, n=n, axis=1), 0.0)


def clipped(image, saturated_pct: Optional[float] = None) -> bool:
    """Are more than :data:`processing.live_view.SATURATION_MAX_PCT` % of ``image``'s pixels saturated
    (:func:`processing.live_view.saturation_pct`, or ``saturated_pct`` where the caller has it)?  (A few
    glints change no row's light.)"""
    return (saturation_pct(image) if saturated_pct is None else saturated_pct) > SATURATION_MAX_PCT


@dataclasses.dataclass(frozen=True)
class RowLight:
    """A reference's light along its rows, as recorded: what frames' bands are judged against
    (:func:`frame_light_bands`; :func:`reference_light`)."""

    #: :func:`row_profile` of the reference
    profile: np.ndarray = dataclasses.field(repr=False)
    #: whether the reference is clipped (:func:`clipped`): then no frame is judged
    clipped: bool = False


def reference_light(reference) -> RowLight:
    """The :class:`RowLight` of a reference image (2-D, as recorded)."""
    return RowLight(row_profile(reference), clipped(reference))


def frame_light_bands(image, reference: Optional[RowLight], carriers=None,
                      saturated_pct: Optional[float] = None) -> Optional[LightBands]:
    """:func:`light_bands` of ``image`` (2-D) against ``reference`` (its :class:`RowLight`); None where
    there is none to judge against, the image is not the reference's size (what measures it says so), or
    either is clipped (:func:`clipped`, which the saturation check names).  What the batch and the live
    window both judge each frame by: about 1.4 ms a 1024^2 frame.  ``carriers``: the board's
    (:class:`processing.carriers.Carriers`; None for random dots): the row frequencies of its harmonics
    are notched out (:func:`board_row_frequencies`).  ``saturated_pct``: the image's
    (:func:`processing.live_view.saturation_pct`) where the caller has it already.

    Clipped, a checkerboard changes each row's mean with the row's place on the board (the bright
    squares' share), alike across the width: ``tirdeflect simulate``'s bump and waves at 256^2 and 512^2,
    the frames or the reference 1.25-1.6x as bright (35-47 % of the pixels clipped), read as bands 2-7 %
    deep at 0.8-0.97 of agreement, and evened out, those false bands doubled to quintupled the heights'
    error (the bump, frames 1.6x 1.46 -> 2.82 %, frames 1.3x 0.62 -> 1.48 %, the reference 1.3x 0.34 ->
    1.76 %; 6 Dec 2026).  Profiling both over the pixels clipped in neither was tried: where the pattern
    moves (waves filling the frame) the kept pixels are not the same part of the board in both, and
    the rows' gains scattered by 0.1-0.2 (bands 30 % deep then went unnamed)."""
    if reference is None or reference.clipped or np.shape(image)[0] != np.shape(reference.profile)[0]:
        return None
    profile = row_profile(image)
    if profile.shape != np.shape(reference.profile) or clipped(image, saturated_pct):
        return None
    if carriers is None:
        return light_bands(profile, reference.profile)
    cols = np.shape(image)[1]
    found = light_bands(profile, reference.profile, board_row_frequencies(carriers.freq, cols))
    evenable = bool(np.all(np.abs(np.asarray(carriers.freq)[:, 1]) * cols / 4 >= MIN_CYCLES_PER_QUARTER))
    return found if evenable else dataclasses.replace(found, evenable=False)


def bands_of(reconstruct, image, saturated_pct: Optional[float] = None) -> Optional[LightBands]:
    """:func:`frame_light_bands` of ``image`` against ``reconstruct``'s reference (a
    :class:`processing.Reconstructor`: its ``row_light`` and ``carriers``; None where it keeps no row light)."""
    return frame_light_bands(image, getattr(reconstruct, "row_light", None), getattr(reconstruct, "carriers", None),
                             saturated_pct)


def evened_frame(image, bands: Optional[LightBands]):
    """The frame to measure: ``image`` with its rows evened out (:func:`even_rows`) where ``bands`` says so
    (:attr:`LightBands.evened`), else ``image`` itself."""
    return even_rows(image, bands) if bands is not None and bands.evened else image


def _median_of_rows(a):
    """``np.median(a, axis=1)`` of a 2-D float array without NaN, the same numbers: the rows sorted (a
    few dozen values each, where NumPy's vectorised sort is 5-7x faster than the median's partition of
    each row, so that the live window can judge its frames: :func:`light_bands` at 1024^2 1.85 -> 0.95
    ms) and the middle one, or the mean of the middle two."""
    s = np.sort(a, axis=1)
    m = s.shape[1] // 2
    return s[:, m] if s.shape[1] % 2 else (s[:, m - 1] + s[:, m]) / 2
