"""Reference + frame -> surface height: the :class:`Reconstructor`.

Pipeline (docs/processing.md has the measured accuracy and speed):

1. carriers of the reference (:mod:`processing.carriers`), sub-bin;
2. Fourier demodulation on the decimated grid (:mod:`processing.demodulation`):
   ``g_s conj(g0_s)`` for both carriers, amplitude ratio ``|g_s| / |g0_s|``;
3. quality mask: amplitude ratio (TIR lost, caustics, blur), reference
   contrast, fold test ``det(I - grad u) > min_fold`` (rays crossing), dilated;
4. phase unwrapping (:mod:`processing.unwrap`), in time against the previous
   frame of the series when there is one, else in space; the 2 pi multiple
   puts the reference region's phase nearest 0;
5. displacement ``u = -K^-1 phase`` (pixels);
6. bias removal (``refine_iterations``, default 1 on the full grid, 0 on
   the decimated one): warp the band-limited reference by the current ``u``,
   demodulate the frame against it, add the residual (the wide flat-top
   band-pass and sub-bin carriers already remove most of the bias FD is
   known for; this removes what features narrower than the band leave);
7. height by least squares of the exact operator
   (:func:`processing.height.surface_from_displacement`), null space pinned by
   the reference region (``Result.pin`` says where, :func:`reference_pin_region`
   how the default region is found, :mod:`processing.height` what the pin
   needs and the fallback); ``Result.series`` says whether the frame is
   continuous with the previous one (:class:`SeriesCheck`);
8. full grid: the decimated results interpolated (Lanczos) to every
   pixel (``full_method="interpolate"``), or full-size inverse FFTs
   (``full_method="ifft"``).

This module is the facade; the stages live by topic: the chains
(:mod:`processing.chain_checkerboard`: steps 2-7, :mod:`processing.chain_image`:
the image refinement, :mod:`processing.chain_dots`: random dots), the mask and
reference region (:mod:`processing.mask`), the series memory
(:mod:`processing.series`), FD's refinement (:mod:`processing.refine`), the
full grid (:mod:`processing.fullgrid`), the live view (:mod:`processing.live_view`);
what the reference fixes once is :attr:`Reconstructor.plan` (:mod:`processing.plan`).
"""

from __future__ import annotations

import dataclasses
import time
from typing import Optional

import numpy as np

from .carriers import Carriers
from .chain_checkerboard import CheckerboardChain
from .chain_dots import DotsChain
from .errors import ShapeMismatchError, TirdeflectError
from .geometry import checked_geometry
from .live_view import LiveView, saturation_pct
from .mask import (MAX_SAMPLE_MAGNITUDE, MIN_EXPOSURE_GAIN, POOR_FRAME_VALID_FRACTION, check_sample_range,
                   defect_pixels, exposure_gain, hot_pixel_limits, hot_pixels_above, reference_pin_region,
                   image_array, repair_pixels, validate_image)
from .options import PATTERNS, ReconstructOptions, full_grid_refinement
from .refine import (WARP_MAX_INTERPOLATION_ERROR_PX, band_limited_reference, linear_interpolation_shift_px,
                     warp_fine_factor)
from .result import Result, SeriesCheck
from .plan import read_only
from .series import EMPTY, SERIES_MAX_PIN_SHIFT, SERIES_MAX_SLIP_FRACTION, SeriesState, copy_check
from .series import check_series as _check_series
from .series import unwrap_phase as _unwrap_phase
from .banding import reference_light
from .mosaic import equalise_mosaic, equalised_reference

__all__ = ["Reconstructor", "Result", "SeriesCheck", "SeriesState", "reference_pin_region", "PATTERNS",
           "exposure_gain", "check_sample_range", "saturation_pct", "warp_fine_factor", "band_limited_reference",
           "linear_interpolation_shift_px", "MIN_EXPOSURE_GAIN", "MAX_SAMPLE_MAGNITUDE",
           "POOR_FRAME_VALID_FRACTION", "SERIES_MAX_SLIP_FRACTION", "SERIES_MAX_PIN_SHIFT",
           "WARP_MAX_INTERPOLATION_ERROR_PX"]


def _resolved(ref, geometry, options, overrides):
    """``(options, pattern)``: the options with pattern and ``refine_method`` resolved, validated."""
    opts = ReconstructOptions() if options is None else options
    if not isinstance(opts, ReconstructOptions):
        raise TypeError(f"options must be a processing.ReconstructOptions; got {type(opts).__name__}")
    if overrides:
        opts = opts.replace(**overrides)  # validated again; unknown names raise TypeError
    pattern = opts.pattern if opts.pattern is not None else geometry.pattern
    if pattern not in PATTERNS:
        raise ValueError(f"pattern must be one of {PATTERNS}; got {pattern!r}")
    if opts.device == "cuda" and pattern != "checkerboard":
        raise TirdeflectError("device='cuda' reads checkerboards only (Fourier demodulation); "
                              "use device='cpu' for a dot pattern")
    refine_method = opts.refine_method
    if refine_method == "image":
        from .dic import NodeGrid

        NodeGrid(ref.shape)  # frame sides must suit the node grid: say so now, not at the first frame
    elif refine_method == "auto":
        refine_method, _ = full_grid_refinement(opts, ref.shape, pattern, grid="full")
    # the GPU transforms whole frames: the frames it hands to the CPU are read the same way
    live_binning = opts.live_binning and opts.device != "cuda"
    return opts.replace(pattern=pattern, refine_method=refine_method, live_binning=live_binning), pattern


class Reconstructor:
    """Turns camera frames into surface heights against one reference image.

    ``Reconstructor(reference_image, geometry)(frame)`` gives a :class:`Result`.
    A facade over a chain (:mod:`processing.chain_checkerboard` with FD's or
    the image refinement, :mod:`processing.chain_dots` for random dots, the
    GPU's :mod:`processing.gpu`), all over the reference's constants
    (:attr:`plan`); the series memory is one :class:`SeriesState`.

    Parameters
    ----------
    reference_image : ndarray, shape (rows, cols)
        The pattern seen via the flat, resting surface (uint8/uint16/float).
    geometry : processing.Geometry
        Optical geometry (TIR or FS-SS).
    options : processing.options.ReconstructOptions, optional
        Every option in one frozen, picklable value (default: the defaults;
        :class:`~processing.options.ReconstructOptions` documents each);
        keyword arguments of the same names override its fields
        (``Reconstructor(ref, g, grid="decimated")`` as before).
        :attr:`options` holds what this Reconstructor runs, pattern and
        ``refine_method`` resolved: give it to another Reconstructor (a
        worker process) to get the same chain.
    carriers : Carriers, optional
        Use these instead of searching the reference.

    Attributes
    ----------
    The same whatever the pattern (None or 0 where an option does not apply
    to it: ``carriers``, ``demod``, ``planner`` for dots, ``piv`` for
    checkerboards; dots run no unwrapping, series memory or refinement).
    ``options`` and its resolved fields (``grid``, ``pattern``, ``unwrap``,
    ``temporal``, ``refine_iterations``, ``refine_method``, ...),
    ``geometry``, ``shape``, ``rows_px``, ``cols_px`` (the decimated grid), ``reference_valid`` (bool on that
    grid: where the reference's pattern has the contrast to be measured; all of it for dots), and:

    reference_region : ndarray bool (n_rows, n_cols)
        The reference region on the decimated grid (``rows_px``, ``cols_px``),
        chosen once from the reference: ``geometry.reference_region`` where the
        reference is valid, or by default :func:`reference_pin_region`.
    reference_region_name : str
        How ``Result.pin`` names it.  ``mosaic``: :mod:`processing.mosaic`; ``row_light``: :mod:`processing.banding`.
    reference_region_valid_fraction : float
        Fraction of the candidate region (the user's box, or the frame's border band) where the reference is valid.

    Raises
    ------
    NoCarrierError
        The reference shows no checkerboard.
    """

    def __init__(self, reference_image, geometry, options: Optional[ReconstructOptions] = None, *,
                 carriers: Optional[Carriers] = None, **overrides):
        ref = validate_image(reference_image, "reference image")
        self.row_light = reference_light(ref)  # its light along the rows as recorded, for a frame's bands (banding)
        self.mosaic, self._mosaic_maps, ref = equalised_reference(ref)  # a colour camera's raw mosaic, or None
        #: The sensor's hot and dead pixels found in the reference (flat indices), repaired in it and every frame.
        self.defects = defect_pixels(ref)
        ref = repair_pixels(ref, self.defects)
        self._hot_limits = hot_pixel_limits(ref)  # a frame's pixels beyond the reference's reach
        geometry = checked_geometry(geometry, ref.shape)  # also its dict or TOML path; camera and rays vs the frame
        #: What this Reconstructor runs (pattern and refine_method resolved).
        self.options, self.pattern = opts, pattern = _resolved(ref, geometry, options, overrides)
        dots = pattern == "dots"
        self.geometry, self.shape, self.reference_dtype, self.device = geometry, ref.shape, ref.dtype, opts.device
        self.grid, self.solver, self.pin_fallback = opts.grid, opts.solver, opts.pin_fallback
        self.refine_method, self.image_iterations = opts.refine_method, opts.image_iterations
        self.full_method, self.min_island = opts.full_method, float(opts.min_island)
        self.min_amplitude, self.min_fold = float(opts.min_amplitude), float(opts.min_fold)
        self.check_pattern = bool(opts.check_pattern)
        self.unwrap, self.temporal = (False, False) if dots else (opts.unwrap, opts.temporal)
        self.refine_iterations = 0 if dots else opts.refine_iterations
        self.dilate = 0 if dots else int(opts.dilate)
        self.chain = DotsChain(ref, geometry, opts) if dots else CheckerboardChain(ref, geometry, opts, carriers)
        c = self.chain
        self.carriers, self.demod = (None, None) if dots else (c.carriers, c.demod)
        self.planner, self.piv = (None, c.piv) if dots else (c.planner, None)
        self.warp_interpolation = None if dots else c.warp_interpolation
        self.rows_px, self.cols_px, self.reference_valid = c.rows_px, c.cols_px, read_only(c.reference_valid)
        self.reference_region, self.reference_region_name = c.region.region, c.region.name
        self.reference_region_valid_fraction = c.region.valid_fraction
        self._view = LiveView(c, pattern)
        self._gpu = None
        self.reset_series()
        if opts.device == "cuda":
            from .gpu import BatchChain, cupy_or_reason

            cupy, why = cupy_or_reason()
            if cupy is None:
                raise TirdeflectError(f"device='cuda' is not available: {why}; use device='cpu'")
            self._gpu = BatchChain(self, cupy)

    @property
    def plan(self):
        """The reference's constants every chain reads (:class:`processing.plan.ReferencePlan`,
        read-only); checkerboards only (None for random dots)."""
        return None if self.pattern != "checkerboard" else self.chain.plan

    @property
    def gpu_fallback(self) -> Optional[str]:
        """With ``device="cuda"``: why frames still go through the CPU chain (e.g.
        a finite camera distance has no spectral height solver), or None when
        the GPU reconstructs them. None as well with ``device="cpu"``."""
        return None if self._gpu is None else self._gpu.reason

    @staticmethod
    def _check_grid(grid):
        if grid not in ("full", "decimated"):
            raise ValueError(f"grid must be 'full' or 'decimated'; got {grid!r}")

    def validate_frame(self, frame):
        """:meth:`checked_frame`'s array."""
        return self.checked_frame(frame)[0]

    def checked_frame(self, frame):
        """``(frame, hot_pixels)``: ``frame`` as an array, checked (the reference's shape, 2-D, a grey dtype), the
        reference's :attr:`mosaic` equalised, its :attr:`defects` and the frame's own isolated pixels beyond its
        reach (:func:`processing.mask.hot_pixels_above`: cosmic rays; ``hot_pixels`` of them) repaired (a copy)."""
        a = image_array(frame, "frame")
        if a.shape != self.shape:
            raise ShapeMismatchError(
                f"reference and frame must have equal shapes; got {self.shape} and {a.shape}: "
                "use the reference recorded with the same camera region of interest and binning")
        a = repair_pixels(equalise_mosaic(validate_image(a, "frame"), self._mosaic_maps), self.defects)
        hot = hot_pixels_above(a, *self._hot_limits)
        return repair_pixels(a, hot), int(hot.size)

    # ------------------------------------------------------------ series memory
    def reset_series(self) -> None:
        """Forget the previous frame: the next frame is unwrapped in space only."""
        self._series = EMPTY

    def remember_phase(self, phase, valid, all_valid: bool) -> None:
        """Set what temporal unwrapping continues from: the unwrapped phase (2,
        m_rows, m_cols) and valid samples of the last frame of the series, when
        that frame was reconstructed elsewhere (the GPU chain); the series
        check's memory (:meth:`check_series`) is kept.  A Reconstructor with
        ``temporal=False`` remembers nothing."""
        if self.temporal:
            self._series = dataclasses.replace(self._series, phase=np.array(phase, np.float32, copy=True),
                                               valid=np.array(valid, bool, copy=True), all_valid=bool(all_valid))

    def series_state(self) -> Optional[SeriesState]:
        """What temporal unwrapping remembers of the last frame (a copy), or
        None when the next frame would be unwrapped in space only.

        Everything one frame passes to the next is in it, so a Reconstructor
        given it with :meth:`restore_series` continues a series exactly as the
        one that made it (how ``tirdeflect process`` splits a recording over
        processes and checks where the pieces join).
        """
        s = self._series
        if s.phase is None:
            return None
        return SeriesState(phase=s.phase.copy(), valid=s.valid.copy(), all_valid=bool(s.all_valid),
                           check=copy_check(s.check))

    def restore_series(self, state: Optional[SeriesState]) -> None:
        """Continue a series from ``state`` (:meth:`series_state`; None = :meth:`reset_series`)."""
        if state is None:
            self.reset_series()
            return
        expected = (2, *self.rows_px.shape, *self.cols_px.shape)
        if tuple(state.phase.shape) != expected:
            raise ShapeMismatchError(
                f"series state has phase shape {tuple(state.phase.shape)}, this Reconstructor's "
                f"decimated grid needs {expected}; use a state of a Reconstructor with the same "
                "reference and options")
        self._series = SeriesState(phase=np.array(state.phase, copy=True),
                                   valid=np.array(state.valid, dtype=bool, copy=True),
                                   all_valid=bool(state.all_valid), check=copy_check(state.check))

    def unwrap_phase(self, wrapped, valid, all_valid=False):
        """Unwrapped carrier phases (2, m_rows, m_cols) of ``wrapped`` with mask
        ``valid`` (:func:`processing.series.unwrap_phase` against this series'
        memory, which it reads and does not change)."""
        return _unwrap_phase(wrapped, valid, all_valid, self._series, unwrap=self.unwrap, temporal=self.temporal,
                             ref_mask=self.reference_region, ref_idx=self.plan.reference_region_index)

    def check_series(self, phase, valid, surf) -> Optional[SeriesCheck]:
        """Compare this frame with the previous one (see :class:`SeriesCheck`);
        None for the first frame of a series.  The series memory moves on to it."""
        series, self._series = _check_series(phase, valid, surf, self._series, self.reference_region)
        return series

    # ------------------------------------------------------------------ frames
    def batch(self, frames, *, grid: Optional[str] = None, essentials: bool = False) -> list:
        """Results of several consecutive frames of the series, in order; with
        ``device="cuda"`` they go through the GPU together (processing/gpu.py).

        ``essentials``: frames done on the GPU come back with height, slopes and
        valid only (``displacement`` and ``amplitude`` None): half the copying
        from the device on the full grid, all that a batch output stores.
        """
        grid = self.grid if grid is None else grid
        self._check_grid(grid)
        if self._gpu is not None:
            return self._gpu(list(frames), grid, essentials=essentials)
        return [self.call_cpu(f, grid=grid) for f in frames]

    def __call__(self, frame, *, grid: Optional[str] = None) -> Result:
        """Reconstruct one frame (same shape as the reference; ``grid`` overrides
        the default grid for this frame).

        Raises
        ------
        ShapeMismatchError, PatternMismatchError, AllInvalidError
        NoCarrierError
            The frame shows no pattern at all (uniform, black, noise): the
            pattern check found no carrier, neither compact nor smeared.
        """
        if self._gpu is not None:
            return self.batch([frame], grid=grid)[0]
        return self.call_cpu(frame, grid=grid)

    def call_cpu(self, frame, *, grid: Optional[str] = None) -> Result:
        """:meth:`__call__` on the CPU, whatever the device (the GPU chain's path for what it leaves to the CPU)."""
        t0 = time.perf_counter()
        frame, hot_pixels = self.checked_frame(frame)
        grid = self.grid if grid is None else grid
        self._check_grid(grid)
        # the chains (checkerboard, dots) have the same three stages; each hands the series
        # memory on, so a frame that fails keeps what its stages already moved
        measured, self._series = self.chain.measure(frame, grid, self._series, t0)
        res, self._series = self.chain.solve(measured, grid, self._series)
        return dataclasses.replace(self.chain.to_grid(measured, res, grid), hot_pixels=hot_pixels)

    def warp_reference(self):
        """The band-limited reference FD's refinement warps (:class:`processing.refine.WarpReference`,
        :meth:`processing.chain_checkerboard.CheckerboardChain.warp_reference`)."""
        return self.chain.warp_reference()

    def continued_signals(self):
        """The demodulation of frames continued beyond their border that FD's full grid and
        refinement measure with (:class:`processing.continuation.ContinuedSignals`,
        :meth:`processing.chain_checkerboard.CheckerboardChain.continued_signals`)."""
        return self.chain.continued_signals()

    def height_solver(self):
        """Height solver of the decimated grid (built once)."""
        return self.chain.height_solver()

    def grid_coordinates(self, grid: Optional[str] = None) -> tuple:
        """``(x_mm, y_mm)`` of the columns and rows of a grid's results,
        without a frame (what a writer needs for a frame that could not be
        measured)."""
        grid = self.grid if grid is None else grid
        self._check_grid(grid)
        if grid == "full":
            x_mm, y_mm = self.chain.full_coordinates()
        else:
            hs = self.height_solver()
            x_mm, y_mm = hs.x_mm, hs.y_mm
        return np.asarray(x_mm, np.float64).copy(), np.asarray(y_mm, np.float64).copy()

    # ---------------------------------------------------------------- live view
    def alignment(self, frame) -> dict:
        """Live alignment metrics of a frame against this reference.

        Returns
        -------
        dict
            ``periods_px`` (2,) and ``rotation_deg`` of the frame's pattern
            in the image (NaN if none found), ``surface_rotation_deg`` (the
            board's rotation on the surface, rows scaled by the configured
            cos(theta); FS-SS: as seen), ``reference_periods_px``,
            ``reference_rotation_deg``, ``theta_estimate_deg`` (from the
            frame's aspect, telecentric camera, a square board or one
            stretched by the geometry's ``pattern_stretch_y``), ``theta_configured_deg``
            (geometry; None for FS-SS), ``focus`` (carrier peak sharpness 0..1,
            smaller of both), ``modulation`` (decimated map, fundamental-band
            contrast std/mean, about 0.8 for full-scale sharp squares),
            ``modulation_rows_px``, ``modulation_cols_px``, ``contrast`` (its
            median), ``amplitude`` (map ``|g|/|g0|``), ``saturation_pct``
            (pixels at the top code of the frame's bit depth), ``error``
            (only when the frame shows no pattern), ``carrier_freq`` (2, 2) of
            the frame, ``board_period_mm`` (the printed board's period that
            they show through the geometry, :meth:`processing.geometry.Geometry.board_period_mm`),
            ``disturbed`` (True when the carriers
            came from local tiles because the surface distorts the pattern: not still water).  Random dots
            (``pattern="dots"``): :func:`processing.piv.dot_alignment` of the
            frame (``dot_size_px``, ``dots_per_window``, ``contrast``,
            ``focus``), ``saturation_pct``, and ``reference``: the same of the
            reference.
        """
        return self._view.alignment(self.validate_frame(frame))

    def spectrum(self, frame, *, size: int = 256, max_freq: float = 0.25) -> dict:
        """Centred log-magnitude spectrum for display, with the carriers.

        Returns
        -------
        dict
            ``log_magnitude`` float32 (n, m): log10 |FFT| of the prepared
            frame; ``freq_x`` (m,), ``freq_y`` (n,): cycles per pixel
            (columns, rows), increasing; ``carriers``: list of
            ``(f_col, f_row)`` of both carriers and their mirrors (empty
            for random dots: the frame's own spectrum, Hann window).
        """
        return self._view.spectrum(self.validate_frame(frame), size=size, max_freq=max_freq)
