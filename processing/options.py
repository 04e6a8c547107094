"""One value for every option of the reconstruction: :class:`ReconstructOptions`.

Frozen and picklable: the CLI, the batch engine, its worker processes and
Dask tasks, the GPU batches and the GUI pass this one value around instead
of retyping the option list, and it is validated here, once, with messages
that echo the bad value.  :func:`full_grid_refinement` is the one place that
chooses the full grid's refinement for ``refine_method="auto"`` (the
default): every caller, ``Reconstructor(reference, geometry)(frame)`` as
much as ``tirdeflect process``, gets the same heights.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

from .fft import PLANNER_EFFORTS
from .pin import PIN_FALLBACKS

__all__ = ["ReconstructOptions", "full_grid_refinement", "PATTERNS", "GRIDS", "REFINE_METHODS", "TURN_REMOVALS"]

#: Patterns the Reconstructor reads: checkerboards by Fourier demodulation,
#: random dots by PIV (processing.piv).
PATTERNS = ("checkerboard", "dots")
GRIDS = ("full", "decimated")
#: ``"auto"``: the most accurate refinement that applies (:func:`full_grid_refinement`).
REFINE_METHODS = ("auto", "fd", "image")
DEVICES = ("cpu", "cuda")
#: what a flagged turn since the reference is taken to be (:mod:`processing.turn`): "none" (flagged only)
TURN_REMOVALS = ("none", "camera", "board")
_FILTER_SHAPES = ("flattop", "disc")
_BORDERS = ("apodize", "none")
_FULL_METHODS = ("interpolate", "ifft")
_FULL_INTERPOLATIONS = ("spline", "lanczos", "cubic", "linear")


def _one_of(name, value, allowed):
    if value not in allowed:
        listed = ", ".join(repr(a) for a in allowed)
        raise ValueError(f"{name} must be one of {listed}; got {value!r}")


def _number(name, value, lo=None, hi=None, *, integer=False, lo_open=False):
    kind = "an integer" if integer else "a number"
    ok = not isinstance(value, bool) and isinstance(value, (int, float) if not integer else int)
    if integer and not ok:
        try:  # numpy integers
            ok = int(value) == value and not isinstance(value, bool)
        except (TypeError, ValueError):
            ok = False
    if not ok or value != value:  # NaN
        raise ValueError(f"{name} must be {kind}; got {value!r}")
    if lo is not None and (value <= lo if lo_open else value < lo):
        raise ValueError(f"{name} must be {'>' if lo_open else '>='} {lo}; got {value!r}")
    if hi is not None and value > hi:
        raise ValueError(f"{name} must be <= {hi}; got {value!r}")


@dataclasses.dataclass(frozen=True)
class ReconstructOptions:
    """Every option of :class:`processing.Reconstructor` (docs/processing.md says
    what each does and what it measured).

    Grid and pattern: ``grid`` ("full": every pixel, batch; "decimated": the
    demodulation's grid, live), ``pattern`` ("checkerboard", "dots", None:
    the geometry's ``pattern``), ``window_px`` (PIV's last window, dots).
    Demodulation: ``filter_radius``, ``filter_flat``, ``filter_shape``,
    ``oversample``, ``border``, ``subbin`` (:class:`processing.demodulation.Demodulator`).
    Mask: ``min_amplitude``, ``min_fold``, ``dilate``, ``min_island``,
    ``check_pattern``.  Unwrapping: ``unwrap``, ``temporal``.  Refinement:
    ``refine_iterations`` (None: 1 on the full grid, 0 on the decimated one),
    ``refine_method`` ("auto": :func:`full_grid_refinement`; "fd"; "image"),
    ``image_iterations``.  Full grid: ``full_method``, ``full_interpolation``.
    Height: ``solver``, ``pin_fallback``.  Live grid: ``live_binning``.  Device and FFT: ``device``
    ("cpu", "cuda"), ``threads``, ``planner_effort``.

    Parameters
    ----------
    grid : {"full", "decimated"}, optional
        Default output grid: every pixel (batch) or the decimated grid of the
        demodulation (live, about one sample per half carrier period).
    unwrap : bool, optional
        Unwrap carrier phases (default True).  Off reproduces FD without
        unwrapping (wrong where ``|k . u| > pi``).
    temporal : bool, optional
        Unwrap against the previous frame of the series (default True);
        :meth:`reset_series` forgets it.
    refine_iterations : int or None, optional
        Warp-and-redemodulate iterations that remove the band-pass bias
        (notes.md).  None (default): 0 on the decimated grid (live speed),
        1 on the full grid (batch accuracy).  Measured (docs/processing.md):
        one iteration halves the error on features narrower than two carrier
        periods (2.7 % -> 1.4 %) and never hurt on the test frames; it costs
        one full-size warp and FFT (about 10 ms at 1024^2).
    filter_radius, filter_flat, filter_shape, oversample, border, subbin :
        Demodulation options, see :class:`processing.demodulation.Demodulator`
        (``oversample`` defaults to 1.5 here: measured on ray-traced frames,
        1.25 to 2 change the height error by < 0.05 %, while the decimated
        grid, where unwrapping, masking and the height solve run, shrinks).
    full_method : {"interpolate", "ifft"}, optional
        How the full grid is made (see module docstring).
    full_interpolation : {"spline", "lanczos", "cubic", "linear"}, optional
        Kernel of ``full_method="interpolate"`` (and of the u upsampling of
        FD's refinement): ``"spline"`` (default) cubic B-spline
        (:class:`processing.fullgrid.Upsampler`), the others cv2.resize's.
        Measured (issue 19): the true displacement of the ray-traced pure
        cosines taken from the decimated grid to every pixel comes back
        within 0.01 % by the spline, 0.28 % by Lanczos4 (its windowed sinc
        moves values by up to 0.05 px), 1.8 % cubic, 2.4 % linear.
    min_island : float, optional
        Valid regions cut off from the reference region and smaller than this
        fraction of the grid are dropped (their 2 pi offset is unknowable in
        space); default 0.01.
    min_amplitude : float, optional
        Smallest accepted ``|g| / |g0|`` (both carriers), default 0.3.
    min_fold : float, optional
        Smallest accepted ``det(I - grad u)`` (1: no distortion, 0: rays
        cross), default 0.2.
    dilate : int, optional
        Invalid regions grow by this many decimated samples (default 1).
    check_pattern : bool, optional
        Refuse frames whose pattern (period, rotation) differs from the
        reference's (default True).
    solver : str, optional
        Passed to :func:`processing.height.surface_from_displacement`.
    threads : int, optional
        FFTW threads (default 2).
    planner_effort : str, optional
        FFTW planner effort (default "FFTW_ESTIMATE"; the app uses
        "FFTW_MEASURE" with wisdom from :func:`processing.fft.import_wisdom`).
    pin_fallback : {"nearest", "refuse"}, optional
        When a frame's reference region holds fewer valid samples than the pin
        needs (:func:`processing.pin.choose_pin_samples`): pin on the valid
        samples nearest the region (default; ``Result.pin.rule == "nearest"``)
        or refuse the frame (GeometryError).  The same rule for every frame.
    turn_removal : {"none", "camera", "board"}, optional
        A turn of the pattern since the reference (:mod:`processing.turn`) is
        always measured and flagged; "none" (default) leaves it in the
        heights (a saddle; the flag says how large), "camera" takes it out as
        the camera's turn about its axis (the image turned), "board" as the
        board's turn in its plane (seen foreshortened: a turn and a shear of
        the image).  Taken out as the wrong one it costs more than left in
        (ray-traced 2 um bump, 1 mrad: the camera's turn 7.95 % left in, 0.29 %
        taken out as the camera's; the board's 1.82 % left in, 8.70 % taken out
        as the camera's), so only the user who knows what moved says so.
    shift_removal : bool, optional
        Where the whole pattern shifted alike since the reference
        (:attr:`processing.pin.PinStatus.shifted`: a water level that changed,
        or a camera or board that moved), solve the heights of the
        displacement less that shift, as a reference taken at that moment
        would (``Result.pin.shift_removed``); False (default): the shift's
        tilt stays in the heights and is named.  Unshifted frames are the same
        either way.
    live_binning : bool, optional
        The decimated grid, when nothing refines it (the live window's), reads
        frames of 512^2 pixels or more binned 2 x 2 (cv2.pyrDown) where the
        carriers' bands stay clear of what the binning folds
        (:func:`processing.binning.binned_bands_clear`): the same grid and
        band from a quarter of the transform (default True; False: the whole
        frame; ``device="cuda"`` resolves it to False).  Measured (1024^2,
        ray-traced waves, 12 bit, one thread): 4.30 -> 3.40 ms a live frame
        (6.40 -> 4.88 ms when other work had evicted the caches), decimated
        heights 1.22 / 0.57 / 0.58 % -> 1.24 / 0.60 / 0.60 % rel. RMS error.
        Boards of periods under about 10 px (and some up to 14 px, seen
        along a diagonal) fold a harmonic into a band and are read whole.
    pattern : {"checkerboard", "dots"} or None, optional
        What the reference shows (None, default: ``geometry.pattern``).  "dots": a random-dot pattern, displacement
        by PIV with window deformation (:class:`processing.piv.DotDisplacement`,
        OpenPIV), last window ``window_px`` (default 16) px, one sample every
        ``window_px / 2`` px; then the same mask, height solve and pin, and on
        the full grid image matching from PIV's start (``refine_method``; the
        carrier options, unwrapping, FD's refinement, ``alignment`` and
        ``spectrum`` do not apply; ``Result.carriers`` is None).
    refine_method : {"auto", "fd", "image"}, optional
        "auto" (default): :func:`processing.options.full_grid_refinement`
        chooses, the same for every caller (this snippet, ``tirdeflect
        process``, the GUI's export): "image" on the CPU with frame sides
        multiples of 4 px, else "fd".  "fd": the warp-and-redemodulate
        refinement only (random dots: PIV's heights alone).  "image":
        after it, on the full grid, ``image_iterations`` (default 3) global
        Gauss-Newton steps of image matching for the height on a node grid
        every 4 px (:func:`processing.dic.refine_height`), starting from FD's
        height: the reference warped by the displacement that the height
        gives through the geometry's exact linear response, matched to the
        frame pixel by pixel, which is not band-limited; the displacement at
        the nodes then goes through the same masked height solver and pin
        (``Result.series`` from FD's heights).  Frame sides must be multiples of 4 px.
        Measured on ray-traced frames (docs/processing.md section 6): waves
        3-6 carrier periods long 2.87 % -> 0.82 %, a bump of 1.25 periods
        1.42 % -> 0.32 %, every case of the accuracy table at or below "fd";
        2-3.5x the time of "fd" per frame (about 5x its single-thread CPU).
        Random dots: the same solve from PIV's displacement
        (:class:`processing.chain_image.DotsImageRefinement`; measured,
        section 11: a bump 3.7 windows wide at half height 4.8 % -> 0.8 %,
        every dot case of the accuracy table at 0.1-0.6x PIV's error).
        The decimated (live) grid never runs it.
    device : {"cpu", "cuda"}, optional
        "cuda": the chain runs on the GPU through CuPy, batched by
        :meth:`batch` (processing/gpu.py says which frames and steps stay on
        the CPU); checkerboards only; TirdeflectError when CuPy or a GPU is missing.  Heights checked
        on an H200 (benchmarks/gpu_check.py); its speed goals not met yet, so opt-in.


    Raises
    ------
    ValueError
        An option out of range, naming it and the value given.
    """

    grid: str = "full"
    pattern: Optional[str] = None
    unwrap: bool = True
    temporal: bool = True
    refine_iterations: Optional[int] = None
    refine_method: str = "auto"
    image_iterations: int = 3
    filter_radius: float = 0.7
    filter_flat: float = 0.8
    filter_shape: str = "flattop"
    oversample: float = 1.5
    border: str = "apodize"
    subbin: bool = True
    full_method: str = "interpolate"
    full_interpolation: str = "spline"
    min_amplitude: float = 0.3
    min_fold: float = 0.2
    dilate: int = 1
    min_island: float = 0.01
    check_pattern: bool = True
    solver: str = "auto"
    threads: int = 2
    planner_effort: str = "FFTW_ESTIMATE"
    pin_fallback: str = "nearest"
    window_px: int = 16
    device: str = "cpu"
    turn_removal: str = "none"
    shift_removal: bool = False
    live_binning: bool = True

    def __post_init__(self):
        _one_of("grid", self.grid, GRIDS)
        if self.pattern is not None:
            _one_of("pattern", self.pattern, PATTERNS)
        _one_of("refine_method", self.refine_method, REFINE_METHODS)
        _one_of("device", self.device, DEVICES)
        _one_of("filter_shape", self.filter_shape, _FILTER_SHAPES)
        _one_of("border", self.border, _BORDERS)
        _one_of("full_method", self.full_method, _FULL_METHODS)
        _one_of("full_interpolation", self.full_interpolation, _FULL_INTERPOLATIONS)
        _one_of("pin_fallback", self.pin_fallback, PIN_FALLBACKS)
        _one_of("turn_removal", self.turn_removal, TURN_REMOVALS)
        if not isinstance(self.shift_removal, bool):
            raise ValueError(f"shift_removal must be True or False; got {self.shift_removal!r}")
        _one_of("planner_effort", self.planner_effort, PLANNER_EFFORTS)
        _one_of("solver", self.solver, ("auto", "spectral", "masked"))
        if self.refine_iterations is not None:
            _number("refine_iterations", self.refine_iterations, 0, integer=True)
        _number("image_iterations", self.image_iterations, 1, integer=True)
        _number("filter_radius", self.filter_radius, 0.05, 0.75)
        _number("filter_flat", self.filter_flat, 0.0, None)
        if not self.filter_flat < 1.0:
            raise ValueError(f"filter_flat must be < 1; got {self.filter_flat!r}")
        _number("oversample", self.oversample, 1.0)
        _number("min_amplitude", self.min_amplitude, 0.0)
        _number("min_fold", self.min_fold)
        _number("dilate", self.dilate, 0, integer=True)
        _number("min_island", self.min_island, 0.0, 1.0)
        _number("threads", self.threads, 1, integer=True)
        _number("window_px", self.window_px, 8, integer=True)
        for name in ("unwrap", "temporal", "subbin", "check_pattern", "live_binning"):
            value = getattr(self, name)
            if not isinstance(value, bool) and value not in (0, 1):
                raise ValueError(f"{name} must be True or False; got {value!r}")
            object.__setattr__(self, name, bool(value))

    def replace(self, **changes) -> "ReconstructOptions":
        """A copy with ``changes`` (validated again); unknown names raise TypeError naming them."""
        unknown = sorted(set(changes) - {f.name for f in dataclasses.fields(self)})
        if unknown:
            raise TypeError(f"unknown reconstruction option(s) {', '.join(unknown)}; the options are "
                            f"{', '.join(f.name for f in dataclasses.fields(self))}")
        return dataclasses.replace(self, **changes)


def full_grid_refinement(options: ReconstructOptions, frame_shape, pattern: str, *, grid: Optional[str] = None):
    """``(method, why)``: the refinement the full grid gets, ``"image"`` or ``"fd"``.

    ``refine_method="auto"`` (the default): image matching for the height
    (:mod:`processing.dic`), the most accurate method on every ray-traced case
    of docs/processing.md's accuracy table (waves 3-6 carrier periods long
    2.9 % -> 0.8 %; random dots from PIV's start: 6.6 % -> 1.8 %) at about 5x
    FD's CPU time, where it applies: the full grid, the CPU, frame sides multiples of
    ``dic.NODE_PX``, not ``refine_iterations=0`` (no refinement) nor
    ``full_method="ifft"``; elsewhere FD's refinement.  The decimated (live) grid
    never runs it.  ``why``: None, or the reason image matching does not
    apply (``"image"`` given explicitly where it does not apply: the caller
    says it cannot be used).  ``"fd"``: ``("fd", None)``.

    Parameters
    ----------
    grid : {"full", "decimated"} or None
        The grid of the run (None: ``options.grid``; a Reconstructor asks
        for ``"full"``, its full-grid calls are what the method is for).
    """
    from . import dic

    grid = options.grid if grid is None else grid
    if options.refine_method == "fd":
        return "fd", None
    rows, cols = frame_shape
    why = None
    if grid != "full":
        why = "it refines the full grid only"
    elif options.device == "cuda":
        why = "it runs on the CPU, not with device 'cuda'"
    elif not dic.fits(frame_shape):
        why = (f"the frame sides ({rows} x {cols} px) must be multiples of {dic.NODE_PX} px "
               f"and at least {5 * dic.NODE_PX} px")
    elif options.refine_method == "auto" and options.full_method != "interpolate":
        why = "full_method='ifft' asks for full-size inverse FFTs instead"
    elif options.refine_method == "auto" and options.refine_iterations == 0:
        why = "refine_iterations=0 asks for no refinement"
    return ("image", None) if why is None else ("fd", why)
