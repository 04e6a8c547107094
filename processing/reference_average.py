"""A reference averaged only from frames that agree: still water, or a refusal that says so.

A reference taken while the water moves holds the pattern displaced by that motion, and every
height measured against it is wrong by it (issue 20: heights 31 % off after a reference on the
waves). :class:`ReferenceAverager` is fed the frames one by one; each is compared with the first:

* checkerboard: the carrier phase of the frame minus that of the first frame, at the first
  frame's carriers (a band of the spectrum around each carrier, demodulated to baseband), RMS
  over the field weighted by the carrier amplitude -- in radians of carrier phase (2 pi: one
  pattern period of displacement);
* random dots (no carriers): the RMS grey-level change over the first frame's RMS contrast,
  which for a sinusoidal pattern is the same phase in radians to first order.

Frames within :data:`PHASE_BOUND_RAD` are averaged. When more than :data:`MAX_DISAGREEING`
of them disagree, :meth:`ReferenceAverager.result` raises :class:`WaterMovingError`:
"the water is moving: <what to do>", with the measured figure. The live window's Ctrl+R
(app.gui.session) and ``tirdeflect process --reference-frames`` (app.files.imageio) average
through it alike.
"""

from __future__ import annotations

import dataclasses
from typing import List, Optional

import numpy as np

from .errors import NoCarrierError, TirdeflectError

__all__ = ["PHASE_BOUND_RAD", "MAX_DISAGREEING", "WaterMovingError", "ReferenceReport", "ReferenceAverager",
           "carrier_baseband", "half_spectrum_baseband", "phase_change_rad", "worst_tile_rms", "CHANGE_TILES",
           "grey_change", "first_frame_carriers",
           "DEPARTURE_MAX_PX", "reference_departure_px", "departure_note", "reconstructor_departure_px"]

#: Carrier-phase change against the first frame (rad, :func:`phase_change_rad`: the RMS of the worst tile
#: of the field) above which a frame does not agree. Measured on the synthetic tank (256^2, 0.5 counts of
#: noise): still water 0.0012 rad, the waves scene 0.6-1.3 rad, the drop's rings as they fade 0.15 (whole-field
#: RMS 0.049: accepted before 7 Dec 2026, and every later height map carried the rings' negative, about a
#: tenth of the drop's own signal). 0.05 rad is 0.8 % of a pattern period (0.1 px of a 12 px period).
PHASE_BOUND_RAD = 0.05
#: :func:`phase_change_rad` judges the field in this many tiles along each side.
CHANGE_TILES = 4
#: Fraction of the frames that may disagree (a passing glitch) before the capture is refused.
MAX_DISAGREEING = 0.2


class WaterMovingError(TirdeflectError):
    """The frames of a reference capture do not agree: the message names the figure and what to do."""


@dataclasses.dataclass(frozen=True)
class ReferenceReport:
    """What a reference capture measured: frames averaged, refused, and their phase change (rad)."""

    n_frames: int
    n_averaged: int
    max_change_rad: float
    changes_rad: tuple
    bound_rad: float
    measure: str  # "carrier phase" or "grey level / contrast"

    def disagreement(self, frame_numbers=None) -> str:
        """``"9 of 10 frames differ from the first by more than 0.05 rad of carrier phase (frame 10: 0.64 rad)"``,
        the worst frame named by its place in ``frame_numbers`` (default: 1, 2, ... as fed)."""
        worst = int(np.argmax(self.changes_rad))
        number = worst + 1 if frame_numbers is None else list(frame_numbers)[worst]
        return (f"{self.n_frames - self.n_averaged} of {self.n_frames} frames differ from the first by more than "
                f"{self.bound_rad:g} rad of {self.measure} (frame {number}: {self.changes_rad[worst]:.2f} rad)")

    def text(self) -> str:
        dropped = self.n_frames - self.n_averaged
        return (f"{self.n_averaged} of {self.n_frames} frames averaged, {self.measure} within "
                f"{self.max_change_rad:.3f} rad of the first (bound {self.bound_rad:g})"
                + (f"; {dropped} disagreeing frames left out" if dropped else ""))


def carrier_baseband(image: np.ndarray, freq, half_width: Optional[int] = None, *, spec=None) -> np.ndarray:
    """Complex baseband of ``image`` around carrier ``freq`` = (f_row, f_col) cycles/px, at low resolution.

    The spectrum's bins within ``half_width`` of the carrier (default: a third of the carrier's distance
    from 0, so neighbouring carriers and DC stay out), Gaussian-weighted, inverse-transformed: a
    ``(2 half_width, 2 half_width)`` complex map whose angle is the carrier phase over the field.
    ``spec``: the mean-free image's ``fft2``, where the caller has it (both carriers from one transform).
    """
    img = np.asarray(image, np.float32)
    if spec is None:
        spec = np.fft.fft2(img - img.mean())
    off, rr, cc = _band(freq, img.shape, half_width)
    return _baseband(spec[np.ix_(rr, cc)], off)


def half_spectrum_baseband(half_spectrum, shape, freq, half_width: Optional[int] = None) -> np.ndarray:
    """:func:`carrier_baseband` from an ``rfft2`` half spectrum (rows, cols // 2 + 1) of an image of
    ``shape`` (the bins of negative columns read from its Hermitian mirror): the live alignment's
    windowed spectrum serves without another transform."""
    rows, cols = shape
    half = np.asarray(half_spectrum)
    if half.shape != (rows, cols // 2 + 1):
        raise ValueError(f"half spectrum of shape {half.shape} does not belong to a {rows} x {cols} image")
    off, rr, cc = _band(freq, shape, half_width)
    sub = np.empty((off.size, off.size), np.complex128)
    direct = cc <= cols // 2
    sub[:, direct] = half[np.ix_(rr, cc[direct])]
    sub[:, ~direct] = np.conj(half[np.ix_((-rr) % rows, cols - cc[~direct])])
    return _baseband(sub, off)


def _band(freq, shape, half_width):
    """``(offsets, rows, cols)``: the bins of :func:`carrier_baseband`'s band (indices modulo the shape)."""
    rows, cols = shape
    kr, kc = float(freq[0]) * rows, float(freq[1]) * cols  # carrier in bins
    if half_width is None:
        half_width = max(2, int(np.hypot(kr, kc) / 3))
    half_width = int(min(half_width, rows // 4, cols // 4))
    off = np.arange(-half_width, half_width)
    return off, (int(round(kr)) + off) % rows, (int(round(kc)) + off) % cols


def _baseband(sub, off):
    """The band ``sub`` (bins ``off`` about the carrier along both axes), Gaussian-weighted, to baseband."""
    g = np.exp(-0.5 * (off / (0.5 * max(1, off.size // 2))) ** 2)
    return np.fft.ifft2(np.fft.ifftshift(sub * np.outer(g, g)))


def phase_change_rad(basebands, first_basebands) -> float:
    """The carrier phase change between two frames (rad): per carrier the phase of ``z conj(z0)``
    (:func:`carrier_baseband` of each frame at the same carriers and width), its RMS weighted by ``|z0|``
    in the worst of :data:`CHANGE_TILES` x :data:`CHANGE_TILES` tiles of the field
    (:func:`worst_tile_rms`), the larger over the carriers (2 pi: a pattern period of displacement)."""
    worst = 0.0
    for z, z0 in zip(basebands, first_basebands):
        worst = max(worst, worst_tile_rms(np.angle(z * np.conj(z0)), np.abs(z0)))
    return worst


def worst_tile_rms(change, weight, tiles: int = CHANGE_TILES) -> float:
    """The largest over ``tiles`` x ``tiles`` tiles of a map of the ``weight``-weighted RMS of ``change``
    (both (rows, cols); weight 0 where not measured): a change confined to part of the field (a drop's
    rings fading) is not diluted by the still rest, as the whole field's RMS dilutes it."""
    change = np.asarray(change, np.float64)
    weight = np.asarray(weight, np.float64)
    worst = 0.0
    for rows in np.array_split(np.arange(change.shape[0]), tiles):
        for cols in np.array_split(np.arange(change.shape[1]), tiles):
            w = weight[np.ix_(rows, cols)]
            total = float(w.sum())
            if total > 0:
                d = change[np.ix_(rows, cols)]
                worst = max(worst, float(np.sqrt(np.sum(w * d * d) / total)))
    return worst


def grey_change(image, first) -> float:
    """Random dots' change between two frames: the RMS grey-level difference over ``first``'s RMS
    contrast (for a sinusoidal pattern the same as :func:`phase_change_rad` to first order)."""
    f = np.asarray(image, np.float64)
    f0 = np.asarray(first, np.float64)
    return float(np.sqrt(np.mean((f - f0) ** 2)) / max(float(f0.std()), 1e-12))


class ReferenceAverager:
    """Average reference frames that agree with the first one (see the module's docstring).

    Parameters
    ----------
    carriers_freq : array (2, 2) or None
        The pattern's carriers (``Carriers.freq``) measured on the first frame; None for random dots.
    bound_rad : float
        :data:`PHASE_BOUND_RAD`.
    remedy : str
        What the refusal tells the user to do (the live window: wait and capture again).
    """

    def __init__(self, carriers_freq=None, *, bound_rad: float = PHASE_BOUND_RAD,
                 max_disagreeing: float = MAX_DISAGREEING, remedy: str = "wait and capture again"):
        self.remedy = str(remedy)
        self.carriers_freq = None if carriers_freq is None else np.asarray(carriers_freq, float)
        self.bound_rad = float(bound_rad)
        self.max_disagreeing = float(max_disagreeing)
        self.changes: List[float] = []
        self._first = None
        self._first_base = None
        self._total = None
        self._n_sum = 0

    def _baseband(self, image):
        img = np.asarray(image, np.float32)
        spec = np.fft.fft2(img - img.mean())  # one transform for both carriers (0.12 -> 0.08 s a 1024^2 frame)
        return [carrier_baseband(img, f, spec=spec) for f in self.carriers_freq]

    def change_rad(self, image) -> float:
        """RMS phase change of ``image`` against the first frame (rad); the first frame gives 0."""
        if self.carriers_freq is None:
            return grey_change(image, self._first)
        return phase_change_rad(self._baseband(image), self._first_base)

    def add(self, image) -> float:
        """Feed one frame; returns its phase change against the first (rad)."""
        if self._first is None:
            self._first = np.asarray(image, np.float64)
            if self.carriers_freq is not None:
                self._first_base = self._baseband(image)
            self._total = np.zeros(self._first.shape, np.float64)
            change = 0.0
        else:
            change = self.change_rad(image)
        self.changes.append(change)
        if change <= self.bound_rad:
            self._total += image
            self._n_sum += 1
        return change

    def report(self) -> ReferenceReport:
        return ReferenceReport(len(self.changes), self._n_sum, max(self.changes, default=0.0),
                               tuple(self.changes), self.bound_rad,
                               "carrier phase" if self.carriers_freq is not None else "grey level / contrast")

    def result(self, frame_numbers=None):
        """``(reference float32, ReferenceReport)``; raises :class:`WaterMovingError` if too many disagree,
        naming the worst frame by its place in ``frame_numbers`` (default: 1, 2, ... as fed; a file's
        frame indices where the frames came from one)."""
        rep = self.report()
        if rep.n_frames == 0:
            raise ValueError("no frame was fed to the reference average")
        if rep.n_frames - rep.n_averaged > self.max_disagreeing * rep.n_frames:
            raise WaterMovingError(f"the water is moving: {self.remedy}. {rep.disagreement(frame_numbers)}; a "
                                   "reference needs still water.")
        return (self._total / rep.n_averaged).astype(np.float32), rep


def first_frame_carriers(image, pattern: str = "checkerboard"):
    """The carriers (``Carriers.freq``, (2, 2) cycles/px) a reference average compares its frames at: those
    of its first frame ``image``; None for random dots, or where no checkerboard is found (the
    reconstructor then refuses the reference with the reason)."""
    if pattern == "dots":
        return None
    from .carriers import find_carriers_live

    try:
        return find_carriers_live(image)[0].freq
    except NoCarrierError:
        return None


#: RMS displacement (px) of a reference's pattern from a smooth (flat-water) board beyond a cubic in the field
#: (:func:`reference_departure_px`) above which the water was probably not still.  Measured 7 Dec 2026:
#: ray-traced still water 0.014-0.018 px (256^2, 512^2); two real FS-SS references through real lenses
#: (tests/data, 1024^2) 0.13 and 0.15 px; ``simulate``'s waves (256^2, 4 frames) averaged into the reference
#: 0.53 px, every height measured against it 28-31 % off (0.46 % against the still reference); a single frame
#: of those waves is refused by the carrier search already (:func:`processing.carriers.find_reference_carriers`).
DEPARTURE_MAX_PX = 0.35


def reference_departure_px(g0, wavevectors, valid, degree: int = 3, border: int = 3) -> float:
    """RMS displacement (px) of a reference's pattern from the smooth one a board seen on still water gives.

    ``g0``: the reference's two analytic signals on the decimated grid (complex, (2, m_rows, m_cols));
    ``wavevectors``: their carriers' (2, 2) rad/px (row, col); ``valid``: the samples with the pattern's
    contrast.  Each carrier's phase is unwrapped and a polynomial of ``degree`` in the field fitted to it
    (the view's keystone and the lens's smooth distortion); what is left, as displacement (the 2 x 2 solve
    of :meth:`processing.demodulation.Demodulator.phase_to_displacement`), RMS over the valid samples
    ``border`` samples inside the grid.  Where the water moved while the reference was taken (frames
    averaged over waves), that is their mean displacement: every frame's is measured against it."""
    from .unwrap import unwrap_spatial

    g0 = np.asarray(g0)
    m_r, m_c = g0.shape[1:]
    ok = np.array(valid, bool, copy=True)
    ok[:border], ok[-border:], ok[:, :border], ok[:, -border:] = False, False, False, False
    if np.count_nonzero(ok) < 4 * (degree + 1) ** 2:
        return float("nan")
    rr, cc = np.meshgrid(np.linspace(-1.0, 1.0, m_r), np.linspace(-1.0, 1.0, m_c), indexing="ij")
    terms = np.stack([(rr ** i * cc ** j)[ok] for i in range(degree + 1) for j in range(degree + 1 - i)], axis=1)
    left = np.empty((2, np.count_nonzero(ok)))
    for s in range(2):
        phase = unwrap_spatial(np.angle(g0[s]).astype(np.float64), ok)[ok]
        coef = np.linalg.lstsq(terms, phase, rcond=None)[0]
        left[s] = phase - terms @ coef
    u = -np.linalg.inv(np.asarray(wavevectors, np.float64)) @ left
    return float(np.sqrt(np.mean(np.sum(u ** 2, axis=0))))


def reconstructor_departure_px(reconstruct) -> float:
    """:func:`reference_departure_px` of a :class:`processing.Reconstructor`'s checkerboard reference (NaN for
    random dots): what ``tirdeflect process`` and the live window judge a reference by."""
    if reconstruct.pattern != "checkerboard":
        return float("nan")
    chain = reconstruct.chain
    return reference_departure_px(chain.demod.g0, chain.demod.wavevectors, chain.reference_valid)


def departure_note(departure_px: float) -> str:
    """What to tell of a reference whose pattern departs by ``departure_px`` (:func:`reference_departure_px`);
    "" within :data:`DEPARTURE_MAX_PX` (or not measured)."""
    if not departure_px > DEPARTURE_MAX_PX:
        return ""
    return (f"the reference's pattern departs from a board seen on still water by {departure_px:.2f} px RMS (beyond "
            f"the view's smooth distortion; still water reads under {DEPARTURE_MAX_PX:g} px): the water was probably "
            "moving when it was taken (a reference averaged over waves holds their mean displacement, and every "
            "height is measured against it: ray-traced waves 0.46 -> 28 % off). Take it again on still water (the "
            "Alignment tab says when the surface has settled), or average frames of still water with "
            "--reference-frames, which refuses frames that disagree")
