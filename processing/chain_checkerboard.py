"""The checkerboard chain: a frame through Fourier demodulation, the quality
mask, unwrapping in space and time, FD's refinement and the height solve
(steps 2-7 of :mod:`processing.reconstruct`), over constants computed once
from the reference (:class:`CheckerboardChain`).

A frame goes :meth:`CheckerboardChain.measure` (demodulate, mask, unwrap,
refine: the series' unwrapping memory after it) then
:meth:`CheckerboardChain.solve` (height, pin, series check) then
:meth:`CheckerboardChain.to_grid` (the full grid: interpolation, or the image
refinement of :mod:`processing.chain_image`); each takes and returns the
series memory (:class:`processing.series.SeriesState`) instead of keeping it.
"""

from __future__ import annotations

import dataclasses
import time
from typing import NamedTuple, Optional

import cv2
import numpy as np

from .angle_kernels import angle_of_product
from .carriers import board_period_note, check_board_period, check_pattern_match, find_reference_carriers
from .binning import binned_bands_clear
from .demodulation import Demodulator
from .chain_base import GridChain
from .errors import AllInvalidError
from .fft import FFTPlanner
from .fullgrid import Upsampler, full_ifft, interpolate_full
from .mask import (POOR_FRAME_VALID_FRACTION, choose_reference_region, darker_than_reference, dilate_invalid,
                   drop_islands, exposure_gain, fold_ok, mean_level, reference_contrast_ok)
from .plan import ReferencePlan, read_only
from .continuation import ContinuedSignals
from .refine import refine_fd, refine_fd_tapered, static_phase, warp_reference
from .result import Result
from .second_order import SecondOrderOptics, solved_again
from .series import EMPTY, after_unwrap, check_series, series_slip, unwrap_phase
from .turn import TURN_BAND_PERIODS

__all__ = ["CheckerboardChain", "Measured", "CG_TOL", "DEFAULT_ITERATIONS"]

#: FD refinement iterations when ``refine_iterations`` is None, per grid.
DEFAULT_ITERATIONS = {"decimated": 0, "full": 1}
#: Masked height solve (CG in float32): stop at a relative residual of 1e-4.
#: Against 1e-6 that moves heights by at most 3.4e-5 of the peak (rms 3e-6)
#: on the app's 1024^2 scene (measured), 30x below the best accuracy the method reaches on
#: ray-traced frames (~0.1 % rms), and saves about a third of the iterations.
CG_TOL = 1e-4
#: The live grid bins frames of at least this many pixels (``options.live_binning``): below it the
#: transform is a small part of a live frame, and tests and the golden file keep their numbers.
LIVE_BINNING_MIN_PIXELS = 512 * 512


class Measured(NamedTuple):
    """A frame after :meth:`CheckerboardChain.measure`: decimated grid."""

    frame: np.ndarray
    wins: np.ndarray
    u: np.ndarray  # displacement after refinement, float32, NaN where invalid
    u_first: np.ndarray  # before refinement
    valid: np.ndarray
    all_valid: bool
    amplitude: np.ndarray
    phase: np.ndarray
    timings: dict
    t0: float
    slip: float = 0.0  # processing.series.series_slip of the series (above 0: the frame was unwrapped alone)


class CheckerboardChain(GridChain):
    """What the reference fixes for a checkerboard (carriers, demodulator,
    reference contrast and region, :attr:`plan`) and the stages a frame goes
    through.  ``options``: the resolved :class:`processing.options.ReconstructOptions`."""

    def __init__(self, ref, geometry, options, carriers=None):
        GridChain.__init__(self)
        o = self.options = options
        self.geometry = geometry
        self.shape = ref.shape
        self.planner = FFTPlanner(threads=o.threads, planner_effort=o.planner_effort)
        self.carriers = carriers if carriers is not None else find_reference_carriers(ref)
        board_period_note(geometry, self.carriers, ref.shape, reference=ref)  # refuses a board not the geometry's
        self.demod = d = Demodulator(ref, self.carriers, planner=self.planner, filter_radius=o.filter_radius,
                                     filter_flat=o.filter_flat, filter_shape=o.filter_shape,
                                     oversample=o.oversample, border=o.border, subbin=o.subbin)
        self.rows_px, self.cols_px = d.rows_px, d.cols_px
        self.ref_f32 = ref.astype(np.float32)
        self.ref_mean = mean_level(ref)
        self.reference_valid = reference_contrast_ok(d, self.shape)
        self.region = choose_reference_region(geometry, self.reference_valid, self.rows_px, self.cols_px,
                                              self.shape, skip=int(o.dilate))
        self.upsampler = Upsampler(self.shape, d.window_shape, o.full_interpolation)
        self.cg_tol = CG_TOL
        self.warp_interpolation = cv2.INTER_LINEAR  # of the carriers' slow envelopes (refine.warp_reference)
        # pattern-check tolerance in bins: 2 % of the carrier frequency (a
        # pattern 4 % off moves the centroid about 3 %; the full check decides)
        self.check_tol_bins = np.maximum(0.02 * np.hypot(*(d.freq * np.array(self.shape)).T), 0.75)
        self.win_centre = (d.freq * np.array(self.shape)) - d.plan.window_centres
        self.q_r = np.fft.fftfreq(d.window_shape[0], 1.0 / d.window_shape[0])
        self.q_c = np.fft.fftfreq(d.window_shape[1], 1.0 / d.window_shape[1])
        #: Raised to what a frame that passed the full search showed (:meth:`cheap_pattern_check`).
        self.check_threshold = 1.0
        region = self.region.region
        self.plan = ReferencePlan(
            conj_g0=read_only(np.conj(d.g0)), g0_amplitude=read_only(np.maximum(d.g0_abs, np.float32(1e-30))),
            reference_region=read_only(region), reference_region_index=read_only(np.flatnonzero(region)),
            region_near=read_only(self.region.near), reference_valid_everywhere=bool(self.reference_valid.all()),
            demodulation=d.plan)
        # the turn check (processing.turn) leaves out FD's least true displacement, near the border
        self.turn_band_px = TURN_BAND_PERIODS * float(np.max(self.carriers.periods_px))
        self.turn_reference_mask = region
        self._smooth_ref, self._continued, self._tapered = {}, None, None
        self._g0_full = self._region_full = self._image = self._second_order = None
        self._live = None
        self._board_note = None

    # ------------------------------------------------------- built on first use
    @property
    def board_note(self) -> str:
        """What the reference's board says of the geometry short of refusing it
        (:func:`processing.carriers.check_board_period`: its perspective not the declared camera's, its period
        2-4.5 % off), judged at the first ask: the batch's and the window's, not every worker's build (the
        keystone costs 0.02-0.12 s; the build refused a board too far off already)."""
        if self._board_note is None:
            self._board_note = check_board_period(self.geometry, self.carriers, self.shape, reference=self.ref_f32)
        return self._board_note

    def warp_reference(self, continued: bool = True):
        """The reference band-limited around the two carriers (continued beyond its border, or alone
        for image matching's start; no apodization), as carrier envelopes and carriers
        (:class:`processing.refine.WarpReference`)."""
        if continued not in self._smooth_ref:
            d = self.demod
            self._smooth_ref[continued] = warp_reference(self.ref_f32, d.freq, d.radius, continued=continued)
        return self._smooth_ref[continued]

    def continued_signals(self):
        """The demodulation of frames continued beyond their border that FD's full grid measures its
        phase, and its refinement its correction, with (:class:`processing.continuation.ContinuedSignals`)."""
        if self._continued is None:
            self._continued = ContinuedSignals(self.demod, self.ref_f32)
        return self._continued

    def live_demodulation(self):
        """``(Demodulator, ReferencePlan)`` of the decimated grid when nothing refines it (the live
        grid): the frame binned 2 x 2 where ``options.live_binning``, the frame has at least
        :data:`LIVE_BINNING_MIN_PIXELS` and the carriers' bands allow it
        (:func:`processing.binning.binned_bands_clear`; the same grid, a quarter of the transform),
        else the chain's own.  Built at the first such frame (batch runs never make one)."""
        if self._live is None:
            d = self.demod
            if (self.options.live_binning and self.shape[0] * self.shape[1] >= LIVE_BINNING_MIN_PIXELS
                    and binned_bands_clear(d.freq, d.radius, self.shape)):
                o = self.options
                b = Demodulator(self.ref_f32, self.carriers, planner=self.planner, filter_radius=o.filter_radius,
                                filter_flat=o.filter_flat, filter_shape=o.filter_shape, oversample=o.oversample,
                                border=o.border, subbin=o.subbin, binning=2)
                plan = dataclasses.replace(self.plan, conj_g0=read_only(np.conj(b.g0)),
                                           g0_amplitude=read_only(np.maximum(b.g0_abs, np.float32(1e-30))),
                                           demodulation=b.plan)
                self._live = (b, plan)
            else:
                self._live = (d, self.plan)
        return self._live

    def image_refinement(self):
        """The image-domain refinement over this chain (:class:`processing.chain_image.ImageRefinement`)."""
        if self._image is None:
            from .chain_image import ImageRefinement

            self._image = ImageRefinement(self)
        return self._image

    # ------------------------------------------------------------------ stages
    def cheap_pattern_check(self, wins, frame):
        """Is the spectral centroid of each carrier window where the reference's
        carrier is?  A deformed frame keeps it there (its mean local frequency
        is the carrier's); another period or rotation moves it.  Only when it
        moved run the full check on the frame (:func:`check_pattern_match`,
        which always decides), which raises PatternMismatchError for a
        different pattern and NoCarrierError for none at all.  A frame that passes the
        full search raises the threshold to what it showed, so a series of
        strongly deformed frames does not pay for the search every time."""
        if not self.options.check_pattern:
            return False
        # |w|^2 summed along columns and along rows, both carriers in one pass each
        p = np.abs(wins)
        p *= p
        rows_p = p.sum(axis=2)
        cols_p = p.sum(axis=1)
        total = rows_p.sum(axis=1)
        ok = total > 0
        if not ok.any():
            return False
        tot = np.where(ok, total, 1.0)
        cr = (rows_p @ self.q_r) / tot - self.win_centre[:, 0]
        cc = (cols_p @ self.q_c) / tot - self.win_centre[:, 1]
        worst = float(np.max(np.where(ok, np.hypot(cr, cc) / self.check_tol_bins, 0.0)))
        if worst > self.check_threshold:
            check_pattern_match(self.carriers, frame)
            self.check_threshold = max(self.check_threshold, 1.5 * worst)
            return True
        return False

    def quality_mask(self, frame, g, plan=None):
        """``(wrapped, amplitude, valid, all_valid)``: carrier phases against the
        reference, the smaller amplitude ratio, the samples that pass the
        contrast test (scaled by :func:`processing.mask.exposure_gain`), dilated.
        ``plan``: the reference's of the demodulation that gave ``g`` (default :attr:`plan`)."""
        o = self.options
        plan = self.plan if plan is None else plan
        wrapped = angle_of_product(g, plan.conj_g0)
        ratio = np.abs(g)
        ratio /= plan.g0_amplitude
        amplitude = np.minimum(ratio[0], ratio[1])
        valid = amplitude >= o.min_amplitude * exposure_gain(frame, self.ref_mean, amplitude)
        if not plan.reference_valid_everywhere:
            valid &= self.reference_valid
        all_valid = bool(valid.all())
        if not all_valid:
            valid &= ~dilate_invalid(~valid, o.dilate)
        return wrapped, amplitude, valid, all_valid

    def unwrapped(self, frame, d, wrapped, amplitude, valid, all_valid, checked, state, judge=True):
        """``(phase, u, valid, all_valid)``: the carrier phases unwrapped against ``state``
        (:func:`processing.series.unwrap_phase`), the displacement of the demodulator ``d``, and the
        samples that pass :meth:`displacement_mask` (``judge``: and :meth:`judge_measured`, raising where the frame
        is refused).  :meth:`measure` unwraps again against ``EMPTY``
        (in space, as a series' first frame) where the series' count of 2 pi is no unwrapping of this
        frame on any sample (:func:`processing.series.series_slip`: frames far apart in time, frames
        lost, a surface too fast for the frame rate).  By-hand trial of 7 Dec 2026: every third frame of
        ``simulate``'s waves came out 1500-3700 % off from the third frame on (slips on 30-47 % of the
        samples), each flagged as a jump, kept and carried on to every later frame; two samples of 476
        slipped (0.4 %, under the jump's bound) took a frame from 6.1 to 10.9 %; alone, each is as in
        the consecutive run."""
        o = self.options
        phase = unwrap_phase(wrapped, valid, all_valid, state, unwrap=o.unwrap, temporal=o.temporal,
                             ref_mask=self.plan.reference_region, ref_idx=self.plan.reference_region_index)
        u = d.phase_to_displacement(phase if all_valid else np.nan_to_num(phase))
        valid, all_valid = self.displacement_mask(u, valid, all_valid)
        if judge:
            self.judge_measured(frame, valid, all_valid, amplitude, checked)
        return phase, u, valid, all_valid

    def displacement_mask(self, u, valid, all_valid):
        """``(valid, all_valid)`` after the fold test and island removal."""
        o = self.options
        fold = (fold_ok(u, self.rows_px, self.cols_px, o.min_fold, finite=True) if all_valid
                else fold_ok(np.where(valid, u, 0.0), self.rows_px, self.cols_px, o.min_fold))
        if fold is not None:
            valid &= ~dilate_invalid(~fold, o.dilate)
            all_valid = bool(valid.all())
        if not all_valid:
            valid = drop_islands(valid, self.plan.reference_region, o.min_island)
        return valid, all_valid

    def judge_measured(self, frame, valid, all_valid, amplitude, checked) -> None:
        """For a poor frame (:data:`processing.mask.POOR_FRAME_VALID_FRACTION`) the full pattern check;
        AllInvalidError when nothing is left.  Judged on the unwrapping :meth:`measure` keeps, never on a
        series' count of 2 pi that it gives up: a frame given after one far from it in time was refused as
        "no clear carrier peak" on the folds of that count, and measured on 57 % of its area alone or after
        another (by-hand trial of 7 Dec 2026: a frame's verdict hung on the frame before it)."""
        o = self.options
        if (o.check_pattern and not checked and not all_valid
                and np.count_nonzero(valid) < POOR_FRAME_VALID_FRACTION * valid.size):
            # noise or another pattern leaves the windows' centroid in place;
            # a poor frame gets the full check, which names what is wrong
            check_pattern_match(self.carriers, frame)
        if not all_valid and not valid.any():
            raise self.nothing_measured(frame, amplitude)

    def nothing_measured(self, frame, amplitude) -> AllInvalidError:
        """The error of a frame no part of which could be measured, with its pattern contrast against the
        reference's (``amplitude``, the decimated grid's) and what to check (darker than the reference: by how
        much), or that the reference's own valid area is too small to measure on."""
        rv, n_dilate = self.reference_valid, int(self.options.dilate)
        kept = int(np.count_nonzero(rv & ~dilate_invalid(~rv, n_dilate)))
        if kept < (2 * n_dilate + 1) ** 2:
            period = float(np.max(self.carriers.periods_px))
            return AllInvalidError(
                f"no part of the frame could be measured: the reference shows the pattern on only "
                f"{int(np.count_nonzero(rv))} of the {rv.size} samples of the grid "
                f"({self.rows_px[1] - self.rows_px[0]:.1f} px apart) and {kept} are left once its edges are trimmed "
                f"by {n_dilate} sample(s), a valid area too small for this frame and board; take a reference whose "
                f"pattern is sharp and lit "
                f"over the whole view, and a frame (or region of interest) that sees at least {10 * period:.0f} px "
                f"(ten board periods of {period:.1f} px) of it across")
        darker = darker_than_reference(frame, self.ref_mean)
        return AllInvalidError(
            f"no part of the frame could be measured: pattern contrast relative to the reference "
            f"is {float(np.median(amplitude)):.2f} (median; need >= {self.options.min_amplitude}); "
            + (darker if darker else "check the focus (a blurred pattern loses its contrast), that TIR holds "
               "(theta, water level), the light and the exposure, and that nothing blocks the view"))

    def refine(self, frame, phase, u, valid, iterations):
        """FD's displacement on the continued frame and its bias removal
        (:func:`processing.refine.refine_fd`), ``iterations`` times."""
        return refine_fd(self.demod, self.warp_reference(), self.continued_signals(), frame, phase, u, valid,
                         iterations, self.upsampler, interpolation=self.warp_interpolation,
                         threads=self.planner.threads)

    def refine_tapered(self, g, u, valid, iterations):
        """Image matching's start: FD's bias removal through the taper
        (:func:`processing.refine.refine_fd_tapered`), ``iterations`` times."""
        plan = self.warp_reference(continued=False)
        if self._tapered is None:
            self._tapered = static_phase(self.demod, plan.band_limited)
        return refine_fd_tapered(self.demod, plan, self._tapered, g, u, valid, iterations, self.upsampler,
                                 interpolation=self.warp_interpolation, threads=self.planner.threads)

    def measure(self, frame, grid, state, t0):
        """``(Measured, state)``: demodulate, mask, unwrap (against ``state``)
        and refine one validated frame; ``state`` continued by its phase."""
        o, timings = self.options, {}
        iterations = DEFAULT_ITERATIONS[grid] if o.refine_iterations is None else o.refine_iterations
        d, plan = self.live_demodulation() if grid == "decimated" and iterations == 0 else (self.demod, self.plan)
        wins = d.frame_windows(frame)
        g = d.decimated_from_windows(wins)
        checked = self.cheap_pattern_check(wins, frame)
        t1 = time.perf_counter()
        timings["demodulate"] = 1e3 * (t1 - t0)
        wrapped, amplitude, valid, all_valid = self.quality_mask(frame, g, plan)
        in_series = o.unwrap and o.temporal and state.phase is not None
        # (displacement_mask writes into valid: the quality mask's kept for unwrapping again)
        masked = self.unwrapped(frame, d, wrapped, amplitude, valid.copy() if in_series else valid, all_valid,
                                checked, state, judge=not in_series)
        slip = 0.0
        if in_series:
            # against what the series check compares with (the previous frame's; at a join of chunks, the
            # other chunk's own, which a slip in the memory handed over does not share)
            prev_phase, prev_valid = state.check[:2] if state.check is not None else (state.phase, state.valid)
            slip = series_slip(masked[0], masked[2], prev_phase, prev_valid, self.plan.reference_region)
            if slip > 0.0:  # the series' count is no unwrapping of this frame there: the frame's own
                masked = self.unwrapped(frame, d, wrapped, amplitude, valid, all_valid, checked, EMPTY)
            else:
                self.judge_measured(frame, masked[2], masked[3], amplitude, checked)
        phase, u, valid, all_valid = masked
        t2 = time.perf_counter()
        timings["unwrap_mask"] = 1e3 * (t2 - t1)
        u_first = u
        if grid == "full" and o.refine_method == "image":
            if iterations > 0:  # image matching's start keeps the taper (refine.refine_fd_tapered)
                u = self.refine_tapered(g, u, valid, iterations)
        elif iterations > 0 or grid == "full":
            # FD's full grid and any FD refinement: the phase measured on the continued frame (the
            # live grid keeps the taper's, one transform less)
            u = self.refine(frame, phase, u, valid, iterations)
        timings["refine"] = 1e3 * (time.perf_counter() - t2)
        # series memory (unwrapped phase of the final displacement)
        all_valid = all_valid and bool(valid.all())
        if o.temporal:
            state = after_unwrap(state, phase, valid, all_valid)
        if not all_valid or u.dtype != np.float32:
            u = np.where(valid, u, np.nan).astype(np.float32)
        return Measured(frame, wins, u, u_first, valid, all_valid, amplitude, phase, timings, t0, slip), state

    def solve_height(self, u, valid, all_valid):
        """The decimated grid's heights and pin (:class:`processing.height.SurfaceResult`)."""
        o, hs = self.options, self.height_solver()
        pin_kw = dict(pin_fallback=o.pin_fallback, region_name=self.region.name, near=self.region.near,
                      shift_removal=o.shift_removal)
        if all_valid and hs.spectral_coefficients is not None and o.solver in ("auto", "spectral"):
            # what solve() picks for finite u, all valid
            return hs.solve_spectral(u, valid, self.plan.reference_region, **pin_kw)
        return hs.solve_at_tolerance(u, valid, o.solver, self.cg_tol, self.plan.reference_region, **pin_kw)

    def solve(self, m: Measured, grid, state):
        """``(Result, state)``: heights on the decimated grid, pin and series
        check (``state`` continued by it); with ``full_method="ifft"`` and
        FD's refinement on the full grid the full-grid result itself."""
        o = self.options
        t3 = time.perf_counter()
        if grid == "full" and o.full_method == "ifft" and o.refine_method == "fd":
            res = full_ifft(self, m.wins, m.u, m.u_first, m.valid, m.amplitude, m.phase, m.timings, t3)
            m.timings["total"] = 1e3 * (time.perf_counter() - m.t0)
            return res, state
        u, valid, all_valid = m.u, m.valid, m.all_valid
        u, turn = self.judge_turn(u, valid)  # a turn of camera or board since the reference is no surface's
        surf = self.solve_height(u, valid, all_valid)
        if surf.valid is not valid and not np.array_equal(surf.valid, valid):
            # pieces the pin could not reach: their offset was not measured
            valid = np.asarray(surf.valid, bool)
            all_valid = False
            u = np.where(valid, u, np.float32(np.nan)).astype(np.float32)
        series, state = check_series(m.phase, valid, surf, state, self.plan.reference_region, slip=m.slip)
        m.timings["height"] = 1e3 * (time.perf_counter() - t3)
        res = Result(height=np.asarray(surf.height_mm, np.float32), valid=valid,
                     slope_x=np.asarray(surf.slope_x, np.float32),
                     slope_y=np.asarray(surf.slope_y, np.float32), displacement=u,
                     amplitude=m.amplitude, x_mm=np.asarray(surf.x_mm), y_mm=np.asarray(surf.y_mm),
                     grid="decimated", rows_px=self.rows_px, cols_px=self.cols_px,
                     carriers=self.carriers, phase=np.asarray(m.phase, np.float32),
                     valid_fraction=1.0 if all_valid else float(valid.mean()), timings_ms=m.timings,
                     pin=surf.pin, series=series, turn=turn, note="" if series is None else series.alone_text())
        return res, state

    def to_grid(self, m: Measured, res: Result, grid) -> Result:
        """The decimated ``res`` on ``grid``: the image refinement on the full
        grid where it runs (FD's heights kept, with a note, where it diverges),
        else interpolation to every pixel."""
        t4 = time.perf_counter()
        if res.grid == "full":  # full_method="ifft"
            return res
        if grid == "full" and self.options.refine_method == "image":
            from .dic import RefinementDiverged

            try:
                refined = self.image_refinement()(m, res, t4)
                # how the decimated grid was measured (unwrapped alone), then image matching's own (specks)
                refined.note = "; ".join(n for n in (res.note, refined.note) if n)
                return refined
            except RefinementDiverged as exc:  # FD's heights below, and the reason with them
                res.note = "; ".join(n for n in (res.note, f"image refinement stopped: {exc}; FD's heights kept") if n)
        if grid == "full":
            res, second = self.to_second_order(res)
            # the slopes of second-order heights are not the linear map of u and h: interpolated as they are
            res = interpolate_full(res, self.upsampler, self.full_coordinates(),
                                   None if second else self.height_solver(), self.planner.threads)
            res.timings_ms["interpolate"] = 1e3 * (time.perf_counter() - t4)
        res.timings_ms["total"] = 1e3 * (time.perf_counter() - m.t0)
        return res

    def to_second_order(self, res: Result):
        """``(res, corrected)``: the decimated heights of FD's full grid solved again without the linear
        model's second-order terms where its slopes make them count
        (:class:`processing.second_order.SecondOrderOptics`, ``timings_ms["second_order"]``)."""
        hs = self.height_solver()
        if self._second_order is None:
            self._second_order = SecondOrderOptics(self.geometry, self.rows_px, self.cols_px, self.shape,
                                                   hs.x_mm, hs.y_mm)
        surf = solved_again(self._second_order, res.displacement, res.height, res.valid,
                            lambda u2: self.solve_height(u2, res.valid, bool(res.valid.all())), res.timings_ms)
        if surf is None:
            return res, False
        return dataclasses.replace(res, height=np.asarray(surf.height_mm, np.float32),
                                   slope_x=np.asarray(surf.slope_x, np.float32),
                                   slope_y=np.asarray(surf.slope_y, np.float32), pin=surf.pin), True

    def full_reference_signal(self):
        """The reference's analytic signals on the full grid (``full_method="ifft"``, built once)."""
        if self._g0_full is None:
            d = self.demod
            self._g0_full = d.full_from_windows(d.frame_windows(self.ref_f32)).copy()
        return self._g0_full

    def full_reference_region(self):
        """The reference region on every pixel (``full_method="ifft"``, built once)."""
        if self._region_full is None:
            self._region_full = self.upsampler.mask(self.plan.reference_region)
        return self._region_full

    def interpolate_full(self, res: Result, solver: Optional[object] = None) -> Result:
        """:func:`processing.fullgrid.interpolate_full` with this chain's upsampler and coordinates."""
        return interpolate_full(res, self.upsampler, self.full_coordinates(), solver, self.planner.threads)
