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
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Optional

import cv2
import numpy as np

from .carriers import (Carriers, check_pattern_match, display_spectrum, find_carriers, find_carriers_live,
                       match_error, theta_from_carriers)
from .demodulation import Demodulator
from .errors import AllInvalidError, SampleRangeError, ShapeMismatchError, TirdeflectError
from .fft import FFTPlanner
from .geometry import DEFAULT_REFERENCE_BAND, default_reference_region_mask
from .height import PIN_MIN_PIECE_SAMPLES, PinStatus
from .fill import nearest_fill_index
from .options import PATTERNS, ReconstructOptions, full_grid_refinement
from .plan import ReferencePlan, read_only
from .result import Result, SeriesCheck
from .unwrap import TWO_PI, unwrap_spatial, unwrap_temporal, wrap

__all__ = ["Reconstructor", "Result", "SeriesCheck", "SeriesState", "reference_pin_region", "PATTERNS"]

_DEFAULT_ITERATIONS = {"decimated": 0, "full": 1}
# Masked height solve (CG in float32): stop at a relative residual of 1e-4.
# Against 1e-6 that moves heights by at most 3.4e-5 of the peak (rms 3e-6)
# on the app's 1024^2 scene (measured), 30x below the best accuracy the method reaches on
# ray-traced frames (~0.1 % rms), and saves about a third of the iterations.
_CG_TOL = 1e-4

#: A frame with less than this fraction of valid samples always gets the full
#: pattern check (:func:`check_pattern_match`), even when the cheap one passed:
#: noise or another pattern can leave the windows' spectral centroid in place.
POOR_FRAME_VALID_FRACTION = 0.5

#: Reference contrast below this fraction of the contrast where the pattern is
#: seen best (90th percentile of the field) marks a blank, dirty or blurred
#: part of the pattern.  The 90th percentile, not the median: where most of the
#: field is blurred (a pattern sharp only in a central disk) the median is the
#: camera noise, and noise samples would pass as pattern (measured on the four
#: real references in tests/data the two agree to 0.1 % of the samples).
_REF_CONTRAST_FRACTION = 0.25
_REF_CONTRAST_PERCENTILE = 90.0

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


def reference_pin_region(reference_valid, rows_px, cols_px, frame_shape, *, skip: int = 0) -> np.ndarray:
    """The default reference region: the border band of where the reference is valid.

    Parameters
    ----------
    reference_valid : ndarray bool (n_rows, n_cols)
        Samples of the grid where the reference shows the pattern.
    rows_px, cols_px : ndarray
        Pixel rows and columns of the grid (evenly spaced).
    frame_shape : (int, int)
    skip : int
        Samples next to an invalid part of the reference that every frame
        loses anyway (the Reconstructor's mask dilation): the band starts
        inside them.

    Returns
    -------
    ndarray bool (n_rows, n_cols)
        The frame's border band (:func:`processing.geometry.default_reference_region_mask`,
        ``ceil(0.04 min(n_rows, n_cols))`` px wide) where the reference is
        valid, plus a band as wide along the inner edge of the valid area
        (after ``skip`` samples): the outermost valid ground, where a
        deformation in the middle of the view has died out.  Holes in the
        valid area (invalid parts enclosed by valid ones) get no band.  Where
        the reference is valid everywhere (but for holes) this is the frame's
        border band.
    """
    valid = np.asarray(reference_valid, bool)
    band = default_reference_region_mask(rows_px, cols_px, frame_shape)
    if valid.all() or not valid.any():
        return band & valid
    from scipy import ndimage

    # only the outer edge: a hole in the valid area (a dirty spot of the
    # pattern) lies in the middle of the view, where the surface may move
    outer = ndimage.binary_fill_holes(valid)
    if outer.all():
        return band & valid
    spacing = 0.5 * (float(rows_px[1] - rows_px[0]) + float(cols_px[1] - cols_px[0]))
    width_px = max(1, math.ceil(DEFAULT_REFERENCE_BAND * min(frame_shape)))
    width = max(2, math.ceil(width_px / spacing))
    # chessboard distance (samples) to the nearest invalid sample, as the dilation counts
    dist = ndimage.distance_transform_cdt(outer, metric="chessboard")
    return valid & (band | ((dist > skip) & (dist <= skip + width)))


@dataclasses.dataclass
class SeriesState:
    """Temporal-unwrapping memory of a :class:`Reconstructor` after a frame.

    Attributes
    ----------
    phase : ndarray, shape (2, m_rows, m_cols)
        Unwrapped carrier phases of the last frame on the decimated grid,
        radians, NaN where invalid.
    valid : ndarray, bool, shape (m_rows, m_cols)
        Its valid samples.
    all_valid : bool
        Every sample was valid.
    check : tuple or None
        What the series check (:class:`SeriesCheck`) compares the next frame
        with: the last frame's phase, valid samples, decimated height and
        pin samples.
    """

    phase: np.ndarray
    valid: np.ndarray
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


class _Upsampler:
    """Decimated grid -> every pixel (cv2.resize; the decimated samples sit at
    the pixel-centre positions cv2.resize assumes, see Demodulator.rows_px)."""

    def __init__(self, shape, window_shape, interpolation="cubic"):
        self.shape = shape
        self.interpolation = {"cubic": cv2.INTER_CUBIC, "lanczos": cv2.INTER_LANCZOS4,
                              "linear": cv2.INTER_LINEAR}[interpolation]

    def __call__(self, field, interpolation=None, out=None):
        src = np.ascontiguousarray(field, dtype=np.float32)
        ip = self.interpolation if interpolation is None else interpolation
        if out is None:
            return cv2.resize(src, (self.shape[1], self.shape[0]), interpolation=ip)
        cv2.resize(src, (self.shape[1], self.shape[0]), dst=out, interpolation=ip)
        return out

    def mask(self, valid):
        v = self(valid.astype(np.float32), cv2.INTER_LINEAR)
        return v > 0.999


_POOL = None
_POOL_LOCK = threading.Lock()


def _pool():
    global _POOL
    if _POOL is None:
        with _POOL_LOCK:
            if _POOL is None:
                _POOL = ThreadPoolExecutor(2, thread_name_prefix="tirdeflect-resize")
    return _POOL


def _run_pair(shape, job_a, job_b, threads=2):
    """Run two full-size jobs (numpy/cv2 release the GIL), in parallel on large frames
    when ``threads`` > 1 (one thread: a worker of a parallel batch run, whose
    cores are taken by the other workers)."""
    if shape[0] * shape[1] < 600_000 or threads < 2:
        job_a()
        job_b()
        return
    other = _pool().submit(job_b)
    job_a()
    other.result()


def _resize_all(up, jobs, threads=2):
    """``up(src, out=dst)`` for every (src, dst) pair, two at a time in threads
    (cv2 releases the GIL; measured at 1024^2: four Lanczos resizes 5.4 ms in
    turn, 2.8 ms two at a time; no gain at 512^2, so small frames stay in turn)."""
    def run(part):
        for a, o in part:
            up(a, out=o)

    if len(jobs) < 2:
        run(jobs)
        return
    _run_pair(jobs[0][1].shape, lambda: run(jobs[0::2]), lambda: run(jobs[1::2]), threads)


#: Darkest exposure (frame / reference brightness) the quality mask makes up for.
MIN_EXPOSURE_GAIN = 0.25


def exposure_gain(frame, reference_mean: float, amplitude) -> float:
    """How much darker than the reference the frame was exposed: the larger of
    its mean brightness ratio and the 90th percentile of its contrast ratio
    ``|g| / |g0|``, within [:data:`MIN_EXPOSURE_GAIN`, 1].

    The quality mask's ``min_amplitude`` is scaled by it, so a frame taken at
    half the exposure (or with a lamp dimmed) keeps the samples a well exposed
    frame keeps; a blurred frame (contrast lost, brightness kept) or one with an
    offset (brightness up or negative, contrast kept) gets 1, and one more than
    4x darker is masked as before (a 12-bit reference against 8-bit frames
    stays "no contrast").
    """
    if not reference_mean > 0:
        return 1.0
    by_mean = float(np.mean(_brightness_sample(frame), dtype=np.float64)) / reference_mean
    if not by_mean < 1.0:  # as bright or brighter (or NaN): nothing to make up for
        return 1.0
    by_contrast = float(np.percentile(amplitude, 90)) if np.size(amplitude) else 1.0
    gain = max(by_mean, by_contrast)
    return float(min(1.0, max(MIN_EXPOSURE_GAIN, gain))) if math.isfinite(gain) else 1.0


def _brightness_sample(image):
    """Every 4th pixel of every 4th row, for the mean brightness at 1/16 of the cost (frame and
    reference sampled alike; the mask's threshold needs the ratio to a few per cent)."""
    return np.asarray(image)[::4, ::4]


#: Largest sample magnitude accepted: no camera gives samples wider than 32 bits.
MAX_SAMPLE_MAGNITUDE = 2.0 ** 32


def check_sample_range(image, name: str = "frame") -> None:
    """Refuse an image whose samples no camera gives: NaN or infinite, or
    beyond +-:data:`MAX_SAMPLE_MAGNITUDE` (a float image rescaled by 1e10...),
    with :class:`SampleRangeError` naming the value and where it is.  Cheap
    (min and max); run before any solver."""
    a = np.asarray(image)
    if a.dtype.kind not in "uif" or not a.size:
        return
    if a.dtype.kind in "ui" and a.dtype.itemsize <= 4:
        return  # within 32 bits by its type
    lo, hi = float(a.min()), float(a.max())
    if math.isfinite(lo) and math.isfinite(hi) and max(-lo, hi) <= MAX_SAMPLE_MAGNITUDE:
        return
    if not (math.isfinite(lo) and math.isfinite(hi)):
        bad = ~np.isfinite(a)
        r, c = (int(v) for v in np.argwhere(bad)[0])
        raise SampleRangeError(
            f"{name} holds {int(np.count_nonzero(bad))} NaN or infinite sample(s) (the first at row {r}, "
            f"column {c}); pass the raw camera image, not a processed one")
    worst = hi if hi >= -lo else lo
    r, c = (int(v) for v in np.unravel_index(int(np.argmax(np.abs(a))), a.shape))
    raise SampleRangeError(
        f"{name} holds a sample of {worst:.3g} (row {r}, column {c}), beyond what any camera gives "
        f"(|value| <= {MAX_SAMPLE_MAGNITUDE:.3g}, 32 bits): the image was rescaled; pass the camera's "
        f"own values (or divide the scale back out)")


def _dilate(invalid, n):
    if n <= 0:
        return invalid
    k = np.ones((2 * n + 1, 2 * n + 1), np.uint8)
    return cv2.dilate(invalid.astype(np.uint8), k).astype(bool)


#: Largest error (pixels) that linear interpolation of the refinement's warp
#: may add to the position of the pattern's shortest carrier
#: (:func:`warp_fine_factor`).
WARP_MAX_INTERPOLATION_ERROR_PX = 1e-3
#: The fine warp grid holds at most this many samples (2048^2 frames: twice as fine).
_WARP_MAX_FINE_SAMPLES = 1 << 24


def linear_interpolation_shift_px(period_px: float) -> float:
    """Largest position error (pixels) of linear interpolation on a cosine of
    period ``period_px`` samples: ``max_d |arg((1 - d) + d exp(i k)) / k - d|``.

    0.0102 px at 8 px, 0.0034 px at 11.5 px, 0.0016 px at 20 px: linear
    interpolation pulls the pattern towards the samples by a shift that is
    periodic in the sub-pixel position."""
    k = 2.0 * np.pi / float(period_px)
    frac = np.linspace(0.0, 1.0, 257)
    return float(np.max(np.abs(np.angle((1.0 - frac) + frac * np.exp(1j * k)) / k - frac)))


def warp_fine_factor(freq, shape) -> int:
    """How many times finer than the pixels the refinement warps its smooth reference.

    The warp interpolates linearly (cv2.remap); on a grid ``f`` times finer
    its position error on the shortest carrier is
    ``linear_interpolation_shift_px(f P) / f``.  The smallest ``f`` (1-4) that
    keeps it within :data:`WARP_MAX_INTERPOLATION_ERROR_PX`, and at most
    ``2^24`` fine samples: 3x for 8 px carriers, 2x for the 11.5-20 px of a
    2 mm board at 0.1 mm/px (theta 55 deg), 1x from 27 px on.  Measured
    (docs/processing.md section 6): on the pixels themselves the error of
    linear interpolation became the refinement's own bias, pure cosines of
    8 px with ring waves of 1.8 px: displacement error 1.15 % without
    refinement, 2.26 % with it, 1.08 % 2x finer, 1.00 % 3x (an exact
    quintic spline on the pixels: 1.00 %); 2 mm board, bump 2 um sigma 4 mm:
    0.26 % without, 0.34 % on the pixels, 0.25 % 2x finer.
    """
    freq = np.asarray(freq, dtype=np.float64)
    period = float(1.0 / np.max(np.hypot(freq[:, 0], freq[:, 1])))
    rows, cols = shape
    factor = 1
    while (factor < 4 and (factor + 1) ** 2 * rows * cols <= _WARP_MAX_FINE_SAMPLES
           and linear_interpolation_shift_px(factor * period) / factor > WARP_MAX_INTERPOLATION_ERROR_PX):
        factor += 1
    return factor


def band_limited_reference(reference, freq, radius, factor: int = 1) -> np.ndarray:
    """The reference band-limited around its two carriers, sampled ``factor``
    times finer than the pixels (sample ``i`` at pixel ``i / factor``), float32.

    The band (each carrier and its mirror: gain 1 to 1.1 filter radii, cosine
    to 0 at 1.6) holds everything the band-pass can see after warping; being
    band-limited, the finer samples are exact (zero-padded spectrum), no
    interpolation kernel.  No apodization: the warp must not move a border
    window.
    """
    ref = np.asarray(reference, np.float32)
    ref = ref - np.float32(ref.mean())
    rows, cols = ref.shape
    spec = np.fft.rfft2(ref)
    fr = np.fft.fftfreq(rows)[:, None]
    fc = np.fft.rfftfreq(cols)[None, :]
    keep = np.zeros(spec.shape)
    for s in range(2):
        for sign in (1.0, -1.0):
            dist = np.hypot(fr - sign * freq[s, 0], fc - sign * freq[s, 1]) / radius
            t = np.clip((dist - 1.1) / 0.5, 0.0, 1.0)
            keep = np.maximum(keep, 0.5 + 0.5 * np.cos(np.pi * t))
    spec *= keep
    if factor == 1:
        return np.fft.irfft2(spec, s=(rows, cols)).astype(np.float32)
    # the band stays clear of Nyquist (carriers at >= 3 px): pad with zeros
    fine = np.zeros((factor * rows, factor * cols // 2 + 1), spec.dtype)
    pos = (rows + 1) // 2
    fine[:pos, : cols // 2] = spec[:pos, : cols // 2]
    fine[factor * rows - (rows - pos):, : cols // 2] = spec[pos:, : cols // 2]
    return (np.fft.irfft2(fine, s=(factor * rows, factor * cols)) * (factor * factor)).astype(np.float32)


class Reconstructor:
    """Turns camera frames into surface heights against one reference image.

    Parameters
    ----------
    reference_image : ndarray, shape (rows, cols)
        The pattern seen via the flat, resting surface (uint8/uint16/float).
    geometry : processing.Geometry
        Optical geometry (TIR or FS-SS).
    options : processing.options.ReconstructOptions, optional
        Every option below in one frozen, picklable value (default: the
        defaults); keyword arguments of the same names override its fields
        (``Reconstructor(ref, g, grid="decimated")`` as before).
        :attr:`options` holds what this Reconstructor runs, pattern and
        ``refine_method`` resolved: give it to another Reconstructor (a
        worker process) to get the same chain.
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
    full_interpolation : {"lanczos", "cubic", "linear"}, optional
        Kernel of ``full_method="interpolate"`` (cv2.resize).  Measured on
        ray-traced waves (wavelengths >= 25 samples of the decimated grid):
        interpolation alone adds 0.2 % (lanczos, default), 0.8 % (cubic),
        0.5 % (linear) rms height error.
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
    carriers : Carriers, optional
        Use these instead of searching the reference.
    pin_fallback : {"nearest", "refuse"}, optional
        When a frame's reference region holds fewer valid samples than the pin
        needs (:func:`processing.height.choose_pin_samples`): pin on the valid
        samples nearest the region (default; ``Result.pin.rule == "nearest"``)
        or refuse the frame (GeometryError).  The same rule for every frame.
    pattern : {"checkerboard", "dots"} or None, optional
        What the reference shows (None, default: ``geometry.pattern``).  "dots": a random-dot pattern, displacement
        by PIV with window deformation (:class:`processing.piv.DotDisplacement`,
        OpenPIV), last window ``window_px`` (default 16) px, one sample every
        ``window_px / 2`` px; then the same mask, height solve and pin (the
        carrier options, unwrapping, refinement, ``alignment`` and
        ``spectrum`` do not apply; ``Result.carriers`` is None).
    refine_method : {"auto", "fd", "image"}, optional
        "auto" (default): :func:`processing.options.full_grid_refinement`
        chooses, the same for every caller (this snippet, ``tirdeflect
        process``, the GUI's export): "image" for checkerboards on the CPU
        with frame sides multiples of 4 px, else "fd".  "fd": the
        warp-and-redemodulate refinement only.  "image":
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
        The decimated (live) grid never runs it.
    device : {"cpu", "cuda"}, optional
        "cuda": the chain runs on the GPU through CuPy, batched by
        :meth:`batch` (processing/gpu.py says which frames and steps stay on
        the CPU); checkerboards only; TirdeflectError when CuPy or a GPU is missing.  UNCHECKED ON GPU
        HARDWARE so far (benchmarks/gpu_check.py).

    Attributes
    ----------
    reference_region : ndarray bool (n_rows, n_cols)
        The reference region on the decimated grid (``rows_px``, ``cols_px``),
        chosen once from the reference: ``geometry.reference_region`` where the
        reference is valid, or by default :func:`reference_pin_region`.
    reference_region_name : str
        How ``Result.pin`` names it.
    reference_region_valid_fraction : float
        Fraction of the candidate region (the user's box, or the frame's
        border band) where the reference is valid.

    Raises
    ------
    NoCarrierError
        The reference shows no checkerboard.
    """

    def __init__(self, reference_image, geometry, options: Optional[ReconstructOptions] = None, *,
                 carriers: Optional[Carriers] = None, **overrides):
        ref = self._validate_image(reference_image, "reference image")
        opts = ReconstructOptions() if options is None else options
        geometry.check_frame(ref.shape)  # the field size is known here first: camera and rays vs the frame
        if not isinstance(opts, ReconstructOptions):
            raise TypeError(f"options must be a processing.ReconstructOptions; got {type(opts).__name__}")
        if overrides:
            opts = opts.replace(**overrides)  # validated again; unknown names raise TypeError
        pattern = opts.pattern if opts.pattern is not None else geometry.pattern
        if pattern not in PATTERNS:
            raise ValueError(f"pattern must be one of {PATTERNS}; got {pattern!r}")
        self.pattern = pattern
        self.device = device = opts.device
        self._gpu = None
        if device == "cuda" and pattern != "checkerboard":
            raise TirdeflectError("device='cuda' reads checkerboards only (Fourier demodulation); "
                                  "use device='cpu' for a dot pattern")
        refine_method = opts.refine_method
        if refine_method == "image":
            from .dic import NodeGrid

            NodeGrid(ref.shape)  # frame sides must suit the node grid: say so now, not at the first frame
        elif refine_method == "auto":
            refine_method, _ = full_grid_refinement(opts, ref.shape, pattern, grid="full")
        #: What this Reconstructor runs (pattern and refine_method resolved).
        self.options = opts = opts.replace(pattern=pattern, refine_method=refine_method)
        self.refine_method = refine_method
        self.image_iterations = opts.image_iterations
        grid, solver, pin_fallback = opts.grid, opts.solver, opts.pin_fallback
        if pattern == "dots":
            self.min_island = opts.min_island
            self._init_dots(ref, geometry, grid, opts.window_px, solver, pin_fallback)
            return
        self._ref_fine = None
        full_method, full_interpolation = opts.full_method, opts.full_interpolation
        unwrap, temporal, refine_iterations = opts.unwrap, opts.temporal, opts.refine_iterations
        min_amplitude, min_fold, dilate, min_island = opts.min_amplitude, opts.min_fold, opts.dilate, opts.min_island
        check_pattern, threads, planner_effort = opts.check_pattern, opts.threads, opts.planner_effort
        filter_radius, filter_flat, filter_shape = opts.filter_radius, opts.filter_flat, opts.filter_shape
        oversample, border, subbin = opts.oversample, opts.border, opts.subbin
        self.geometry = geometry
        self.shape = ref.shape
        self.reference_dtype = ref.dtype
        self.grid = grid
        self.unwrap = bool(unwrap)
        self.temporal = bool(temporal)
        self.refine_iterations = refine_iterations
        self.full_method = full_method
        self.min_amplitude = float(min_amplitude)
        self._ref_mean = float(np.mean(_brightness_sample(ref), dtype=np.float64))
        self.min_fold = float(min_fold)
        self.dilate = int(dilate)
        self.min_island = float(min_island)
        self.warp_interpolation = cv2.INTER_LINEAR  # from a grid fine enough for the period (warp_fine_factor)
        self.check_pattern = bool(check_pattern)
        self.pin_fallback = pin_fallback
        self.solver = solver
        self.planner = FFTPlanner(threads=threads, planner_effort=planner_effort)
        self.carriers = carriers if carriers is not None else find_carriers(ref)
        self.demod = Demodulator(ref, self.carriers, planner=self.planner, filter_radius=filter_radius,
                                 filter_flat=filter_flat, filter_shape=filter_shape, oversample=oversample,
                                 border=border, subbin=subbin)
        d = self.demod
        self.rows_px, self.cols_px = d.rows_px, d.cols_px
        # reference contrast, border taper divided out: blank or dirty parts of the pattern
        taper = self._taper_decimated()
        g0_min = d.g0_abs.min(axis=0) / np.maximum(taper, 1e-6)
        inside = taper >= 0.02
        best = np.percentile(g0_min[inside], _REF_CONTRAST_PERCENTILE) if inside.any() else 0.0
        self._ref_ok = (g0_min >= _REF_CONTRAST_FRACTION * best) & inside
        self._choose_reference_region(geometry)
        self._ref_mask_full = None
        self._up = _Upsampler(self.shape, d.window_shape, full_interpolation)
        self._smooth_ref = None
        self._smooth_static = None
        self._window_spectrum = None
        self._full_coords = None
        self._g0_full = None
        self._ref_f32 = ref.astype(np.float32)
        # pattern-check tolerance in bins: 2 % of the carrier frequency (a
        # pattern 4 % off moves the centroid about 3 %; the full check decides)
        self._check_tol_bins = np.maximum(0.02 * np.hypot(*(d.freq * np.array(self.shape)).T), 0.75)
        self._win_centre = (d.freq * np.array(self.shape)) - d.plan.window_centres
        self._q_r = np.fft.fftfreq(d.window_shape[0], 1.0 / d.window_shape[0])
        self._q_c = np.fft.fftfreq(d.window_shape[1], 1.0 / d.window_shape[1])
        self._check_threshold = 1.0
        # per-grid constants of the live path
        self._conj_g0 = np.conj(d.g0)
        self._g0_den = np.maximum(d.g0_abs, np.float32(1e-30))
        self._ref_ok_all = bool(self._ref_ok.all())
        self._ref_idx = np.flatnonzero(self._ref_mask)
        self._height_solver = None
        self._plan = None
        self.reset_series()
        if device == "cuda":
            from .gpu import BatchChain, cupy_or_reason

            cupy, why = cupy_or_reason()
            if cupy is None:
                raise TirdeflectError(f"device='cuda' is not available: {why}; use device='cpu'")
            self._gpu = BatchChain(self, cupy)

    # ------------------------------------------------------------ dots (PIV)
    def _init_dots(self, ref, geometry, grid, window_px, solver, pin_fallback):
        from .piv import DotDisplacement

        self.geometry = geometry
        self.shape = ref.shape
        self.reference_dtype = ref.dtype
        self.grid = grid
        self.solver = solver
        self.pin_fallback = pin_fallback
        self.carriers = None
        self.piv = DotDisplacement(ref, window_px=window_px)
        self._ref_dots = ref
        self.rows_px, self.cols_px = self.piv.rows_px, self.piv.cols_px
        n = (self.rows_px.size, self.cols_px.size)
        self._ref_ok = np.ones(n, bool)
        self._ref_ok_all = True
        self.dilate = 0
        self._choose_reference_region(geometry)
        self._height_solver = None
        self._full_coords = None
        self.reset_series()

    def _call_dots(self, frame, grid):
        t0 = time.perf_counter()
        timings = {}
        u, valid = self.piv(frame)
        t1 = time.perf_counter()
        timings["piv"] = 1e3 * (t1 - t0)
        if not valid.any():
            raise AllInvalidError("no interrogation window of the frame correlates with the reference: check that "
                                  "the dots are in focus and lit, and that the frame shows the reference's pattern")
        valid = self._drop_islands(valid)
        hs = self.height_solver()
        surf = hs._solve(np.where(valid, u, np.nan), valid, self.solver, _CG_TOL, self._ref_mask,
                         pin_fallback=self.pin_fallback, region_name=self.reference_region_name,
                         near=self._region_near)
        valid = np.asarray(surf.valid, bool)
        u = np.where(valid, u, np.float32(np.nan)).astype(np.float32)
        timings["height"] = 1e3 * (time.perf_counter() - t1)
        res = Result(height=np.asarray(surf.height_mm, np.float32), valid=valid,
                     slope_x=np.asarray(surf.slope_x, np.float32), slope_y=np.asarray(surf.slope_y, np.float32),
                     displacement=u, amplitude=valid.astype(np.float32), x_mm=np.asarray(surf.x_mm),
                     y_mm=np.asarray(surf.y_mm), grid="decimated", rows_px=self.rows_px, cols_px=self.cols_px,
                     carriers=None, phase=np.zeros((2, 0, 0), np.float32),
                     valid_fraction=float(valid.mean()), timings_ms=timings, pin=surf.pin)
        if grid == "full":
            t2 = time.perf_counter()
            res = self._dots_full(res)
            timings["interpolate"] = 1e3 * (time.perf_counter() - t2)
        timings["total"] = 1e3 * (time.perf_counter() - t0)
        return res

    def _dots_full(self, res):
        """PIV grid -> every pixel (cubic spline; pixels beyond the outer
        window centres take the border value; invalid where the nearest sample is)."""
        rows, cols = self.shape
        r = (np.arange(rows, dtype=np.float32) - np.float32(self.rows_px[0])) / np.float32(self.rows_px[1] - self.rows_px[0])
        c = (np.arange(cols, dtype=np.float32) - np.float32(self.cols_px[0])) / np.float32(self.cols_px[1] - self.cols_px[0])
        map_r = np.broadcast_to(r[:, None], self.shape).astype(np.float32)
        map_c = np.broadcast_to(c[None, :], self.shape).astype(np.float32)
        fill = nearest_fill_index(res.valid)

        from scipy import ndimage

        def up(field):
            # cubic spline through the samples (cv2's cubic kernel measured
            # 2x the height error of the PIV grid itself on ray-traced bumps)
            f = field if fill is None else field[fill]
            return ndimage.map_coordinates(np.nan_to_num(f).astype(np.float64), [map_r, map_c], order=3,
                                           mode="nearest").astype(np.float32)

        valid = cv2.remap(res.valid.astype(np.uint8), map_c, map_r, cv2.INTER_NEAREST,
                          borderMode=cv2.BORDER_REPLICATE).astype(bool)
        nan = np.float32(np.nan)
        out = {k: np.where(valid, up(getattr(res, k)), nan) for k in ("height", "slope_x", "slope_y")}
        disp = np.stack([np.where(valid, up(res.displacement[i]), nan) for i in range(2)])
        x_mm, y_mm = self._coords_full(res)
        return dataclasses.replace(res, valid=valid, displacement=disp, amplitude=valid.astype(np.float32),
                                   x_mm=x_mm, y_mm=y_mm, grid="full", rows_px=np.arange(rows, dtype=float),
                                   cols_px=np.arange(cols, dtype=float), valid_fraction=float(valid.mean()), **out)

    # ------------------------------------------------------------ helpers
    def _choose_reference_region(self, geometry):
        """The reference region on the decimated grid, once for the series."""
        rows_px, cols_px = self.rows_px, self.cols_px
        self._region_near = None
        if geometry.reference_region is None:
            candidate = default_reference_region_mask(rows_px, cols_px, self.shape)
            region = reference_pin_region(self._ref_ok, rows_px, cols_px, self.shape, skip=self.dilate)
            if self._ref_ok.all():
                name = "default border band of the frame"
            else:
                name = "default border band of the reference's valid area"
        else:
            candidate = geometry.reference_mask(rows_px, cols_px, self.shape)
            region = candidate & self._ref_ok
            name = f"reference_region {list(geometry.reference_region)}"
            if not region.any():
                self._region_near = candidate  # the fallback measures "nearest" from the box
        self.reference_region = region
        self.reference_region_name = name
        self.reference_region_valid_fraction = (float(np.count_nonzero(candidate & self._ref_ok))
                                                / max(1, int(np.count_nonzero(candidate))))
        self._ref_mask = region

    def _taper_decimated(self):
        """Border window at the decimated samples (1 without apodization)."""
        w = self.demod.plan.window2d
        if w is None:
            return np.ones(self.demod.window_shape, np.float32)
        rows, cols = self.shape
        return w[np.ix_(np.round(self.rows_px).astype(int) % rows, np.round(self.cols_px).astype(int) % cols)]

    @staticmethod
    def _check_grid(grid):
        if grid not in ("full", "decimated"):
            raise ValueError(f"grid must be 'full' or 'decimated'; got {grid!r}")

    def _validate_image(self, image, name):
        a = np.asarray(image)
        if a.ndim != 2:
            raise ValueError(f"{name} must be a 2-D grey image (rows, cols); got shape {a.shape}. "
                             "Convert colour images to grey first")
        if a.dtype.kind not in "uif" or a.dtype.itemsize > 8:
            raise ValueError(f"{name} must be uint8, uint16 or float; got dtype {a.dtype}")
        check_sample_range(a, name)
        return a

    def validate_frame(self, frame):
        """``frame`` as an array, checked: the reference's shape (ShapeMismatchError), 2-D, a grey dtype."""
        a = np.asarray(frame)
        if a.shape != self.shape:
            raise ShapeMismatchError(
                f"reference and frame must have equal shapes; got {self.shape} and {a.shape}: "
                "use the reference recorded with the same camera region of interest and binning")
        return self._validate_image(a, "frame")

    def reset_series(self) -> None:
        """Forget the previous frame: the next frame is unwrapped in space only."""
        self._prev_phase = None
        self._prev_valid = None
        self._prev_all_valid = False
        self._series_prev = None

    def remember_phase(self, phase, valid, all_valid: bool) -> None:
        """Set what temporal unwrapping continues from: the unwrapped phase (2,
        m_rows, m_cols) and valid samples of the last frame of the series, when
        that frame was reconstructed elsewhere (the GPU chain); the series
        check's memory (:meth:`check_series`) is kept.  A Reconstructor with
        ``temporal=False`` remembers nothing."""
        if not self.temporal:
            return
        self._prev_phase = np.array(phase, np.float32, copy=True)
        self._prev_valid = np.array(valid, bool, copy=True)
        self._prev_all_valid = bool(all_valid)

    @property
    def plan(self):
        """The reference's constants every chain reads (:class:`processing.plan.ReferencePlan`,
        read-only); checkerboards only (None for random dots)."""
        if self.pattern != "checkerboard":
            return None
        if self._plan is None:
            self._plan = ReferencePlan(
                conj_g0=read_only(self._conj_g0), g0_amplitude=read_only(self._g0_den),
                reference_region=read_only(self._ref_mask), reference_region_index=read_only(self._ref_idx),
                region_near=read_only(self._region_near), reference_valid_everywhere=self._ref_ok_all,
                demodulation=self.demod.plan)
        return self._plan

    @property
    def gpu_fallback(self) -> Optional[str]:
        """With ``device="cuda"``: why frames still go through the CPU chain (e.g.
        a finite camera distance has no spectral height solver), or None when
        the GPU reconstructs them. None as well with ``device="cpu"``."""
        return None if self._gpu is None else self._gpu.reason

    def series_state(self) -> Optional["SeriesState"]:
        """What temporal unwrapping remembers of the last frame (a copy), or
        None when the next frame would be unwrapped in space only.

        Everything one frame passes to the next is in it, so a Reconstructor
        given it with :meth:`restore_series` continues a series exactly as the
        one that made it (how ``tirdeflect process`` splits a recording over
        processes and checks where the pieces join).
        """
        if self._prev_phase is None:
            return None
        check = self._series_prev
        if check is not None:
            check = tuple(None if a is None else np.array(a, copy=True) for a in check)
        return SeriesState(phase=self._prev_phase.copy(), valid=self._prev_valid.copy(),
                           all_valid=bool(self._prev_all_valid), check=check)

    def restore_series(self, state: Optional["SeriesState"]) -> None:
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
        self._prev_phase = np.array(state.phase, copy=True)
        self._prev_valid = np.array(state.valid, dtype=bool, copy=True)
        self._prev_all_valid = bool(state.all_valid)
        self._series_prev = None if state.check is None else tuple(
            None if a is None else np.array(a, copy=True) for a in state.check)

    # ----------------------------------------------------------- pattern
    def _cheap_pattern_check(self, wins, frame):
        """Is the spectral centroid of each carrier window where the reference's
        carrier is?  A deformed frame keeps it there (its mean local frequency
        is the carrier's); another period or rotation moves it.  Only when it
        moved run the full check on the frame (:func:`check_pattern_match`,
        which always decides), which raises PatternMismatchError for a
        different pattern and NoCarrierError for none at all.  A frame that passes the
        full search raises the threshold to what it showed, so a series of
        strongly deformed frames does not pay for the search every time."""
        if not self.check_pattern:
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
        cr = (rows_p @ self._q_r) / tot - self._win_centre[:, 0]
        cc = (cols_p @ self._q_c) / tot - self._win_centre[:, 1]
        worst = float(np.max(np.where(ok, np.hypot(cr, cc) / self._check_tol_bins, 0.0)))
        if worst > self._check_threshold:
            check_pattern_match(self.carriers, frame)
            self._check_threshold = max(self._check_threshold, 1.5 * worst)
            return True
        return False

    # ------------------------------------------------------------- stages
    def unwrap_phase(self, wrapped, valid, all_valid=False):
        """Unwrapped carrier phases (2, m_rows, m_cols) of ``wrapped`` with mask
        ``valid``: against the series' last frame (temporal) when there is one,
        else in space, the reference region's median nearest 0; NaN-free
        where ``all_valid``.  Reads the series memory, does not change it."""
        if not self.unwrap:
            return np.where(valid, wrapped, np.nan)
        if all_valid and self.temporal and self._prev_phase is not None and self._prev_all_valid:
            out = self._unwrap_temporal_all_valid(wrapped)
            if out is not None:
                return out
        out = np.empty_like(wrapped)
        for s in range(2):
            if self.temporal and self._prev_phase is not None:
                out[s] = unwrap_temporal(wrapped[s], self._prev_phase[s], valid, self._prev_valid,
                                         ref_mask=self._ref_mask)
            else:
                out[s] = unwrap_spatial(wrapped[s], valid, ref_mask=self._ref_mask)
        return out

    def _unwrap_temporal_all_valid(self, wrapped):
        """unwrap_temporal for both carriers when this and the previous frame
        are valid everywhere (most live frames): the same arithmetic without
        masks; None when the change since the previous frame has a 2 pi jump
        (the general path unwraps it in space)."""
        prev = self._prev_phase
        pi = np.pi
        delta = wrap(wrapped - prev)
        # a change spanning <= pi cannot hold a neighbour jump > pi (the usual
        # case: two reductions instead of the difference test)
        if float(delta.max()) - float(delta.min()) > pi:
            if (np.abs(np.diff(delta, axis=1)).max(initial=0.0) > pi
                    or np.abs(np.diff(delta, axis=2)).max(initial=0.0) > pi):
                return None
        out = prev + delta
        if self._ref_idx.size:
            vals = out.reshape(2, -1)[:, self._ref_idx]
            lo = vals.min(axis=1)
            hi = vals.max(axis=1)
            for s in range(2):
                # median within (-pi, pi): the 2 pi multiple nearest it is 0
                if not (lo[s] > -pi and hi[s] < pi):
                    out[s] -= TWO_PI * np.round(np.median(vals[s]) / TWO_PI)
        return out

    def _drop_islands(self, valid):
        """Remove small valid regions that do not reach the reference region."""
        if self.min_island <= 0:
            return valid
        from scipy import ndimage

        if valid.all():
            return valid  # one region
        labels, n = ndimage.label(valid)
        if n <= 1:
            return valid
        sizes = np.bincount(labels.ravel(), minlength=n + 1)
        touches = np.zeros(n + 1, bool)
        touches[np.unique(labels[self._ref_mask & valid])] = True
        keep = (sizes >= self.min_island * valid.size) | touches
        keep[0] = False
        return keep[labels]

    def _fold_ok(self, u, finite=False):
        """det(I - grad u) > min_fold on the decimated grid (u in pixels);
        None when it holds everywhere."""
        dr = self.rows_px[1] - self.rows_px[0]
        dc = self.cols_px[1] - self.cols_px[0]
        uf = u if finite else np.nan_to_num(u)
        # |every partial derivative| <= t (central and one-sided differences
        # are bounded by the largest neighbour difference) gives
        # det >= (1 - t)^2 - t^2 = 1 - 2 t: no fold test needed below this
        t = max(float(np.abs(np.diff(uf, axis=1)).max(initial=0.0)) / dr,
                float(np.abs(np.diff(uf, axis=2)).max(initial=0.0)) / dc)
        if 1.0 - 2.0 * t > self.min_fold + 1e-6:
            return None
        dur_dr, dur_dc = np.gradient(uf[0], dr, dc)
        duc_dr, duc_dc = np.gradient(uf[1], dr, dc)
        det = (1.0 - dur_dr) * (1.0 - duc_dc) - dur_dc * duc_dr
        return det > self.min_fold

    def warp_reference(self):
        """Reference band-limited around the two carriers (no apodization) on the
        grid the refinement warps it from: ``(fine, factor)``, ``fine[i, j]`` at
        pixel ``(i / factor, j / factor)`` (:func:`warp_fine_factor`)."""
        if self._smooth_ref is None:
            d = self.demod
            factor = warp_fine_factor(d.freq, self.shape)
            self._smooth_ref = (band_limited_reference(self._ref_f32, d.freq, d.radius, factor), factor)
        return self._smooth_ref

    def _refine(self, frame_wins, g, u, valid, iterations):
        """Remove the band-pass bias: warp the smooth reference by u, demodulate
        the frame against it and add the residual displacement."""
        d = self.demod
        smooth, factor = self.warp_reference()
        if self._smooth_static is None:
            self._smooth_static = np.angle(d.g0 * np.conj(d.decimated(np.ascontiguousarray(smooth[::factor, ::factor]))))
        static = self._smooth_static
        fill = nearest_fill_index(valid)
        relative = getattr(cv2, "WARP_RELATIVE_MAP", None) if factor == 1 else None
        rows, cols = self.shape
        for _ in range(iterations):
            # invalid samples take their nearest valid neighbour's u: a jump to
            # 0 would tear the warped reference and ring through the band-pass
            uf = u if fill is None else u[:, fill[0], fill[1]]
            if fill is not None or not np.isfinite(uf).all():
                uf = np.nan_to_num(uf)
            # sample the smooth reference at r - u(r), written straight into
            # the FFT's input array; relative maps save two full-size passes
            map_c = np.empty(self.shape, np.float32)
            map_r = np.empty(self.shape, np.float32)
            _resize_all(self._up, [(np.float32(-factor) * uf[1], map_c), (np.float32(-factor) * uf[0], map_r)],
                        self.planner.threads)
            if relative is not None:
                flags = self.warp_interpolation | relative
            else:
                map_c += np.arange(0, factor * cols, factor, dtype=np.float32)[None, :]
                map_r += np.arange(0, factor * rows, factor, dtype=np.float32)[:, None]
                flags = self.warp_interpolation

            def warp(dst):
                cv2.remap(smooth, map_c, map_r, flags, dst=dst, borderMode=cv2.BORDER_REFLECT)

            gw = d.decimated_from_windows(d.windows(d.spectrum_of(warp)))
            # minus the static difference between the smooth and the real
            # reference (wrap-around leakage at the borders, where the
            # reference region usually is): zero residual when u is right
            dphi = wrap(np.angle(g * np.conj(gw)) - static)
            du = d.phase_to_displacement(dphi)
            u = u + np.where(valid, du, 0.0)
        return u

    def _image_full(self, frame, u, valid, amplitude, phase, series, timings, t0, t3, fd_pin=None):
        """Full grid by the global image-domain refinement (:func:`processing.dic.refine_height`):
        FD's heights on a node grid every ``dic.NODE_PX`` pixels are refined
        by image matching; the displacement they give at the nodes goes
        through the masked height solver and pin; the heights are
        interpolated to every pixel.  ``series``: FD's check of this frame
        against the previous one (:meth:`check_series`); ``fd_pin``: FD's pin
        status, whose dropped pieces (no pin sample in them) the nodes never see."""
        from . import dic
        from .height import solver_for

        if self._ref_fine is None:
            ng = dic.NodeGrid(self.shape)
            self._node_grid = ng
            self._height_nodes = dic.HeightNodes(self.geometry, ng)
            self._ref_fine = dic.fine_reference(self._ref_f32)
            pick_r = np.abs(ng.rows_px[:, None] - self.rows_px[None, :]).argmin(axis=1)
            pick_c = np.abs(ng.cols_px[:, None] - self.cols_px[None, :]).argmin(axis=1)
            self._node_ref_mask = self._ref_mask[np.ix_(pick_r, pick_c)]
            self._node_near = None if self._region_near is None else self._region_near[np.ix_(pick_r, pick_c)]
        ng = self._node_grid
        all_valid = bool(valid.all())
        fill = None if all_valid else nearest_fill_index(valid)
        uf = u if fill is None else u[:, fill[0], fill[1]]
        valid_px = np.ones(self.shape, bool) if all_valid else self._up.mask(valid)
        valid_nodes = ng.down(valid_px.astype(np.float32)) > 0.999
        # FD's heights at the nodes: the start
        u_start = np.stack([ng.down(self._up(np.nan_to_num(uf[i]))) for i in range(2)])
        hs = solver_for(self.geometry, ng.rows_px, ng.cols_px, self.shape)
        pin_kw = dict(pin_fallback=self.pin_fallback, region_name=self.reference_region_name, near=self._node_near)
        start = hs._solve(np.where(valid_nodes, u_start, np.nan), valid_nodes, self.solver, _CG_TOL,
                          self._node_ref_mask, **pin_kw)
        periods = np.asarray(self.carriers.periods_px, np.float64)
        _, u_nodes, valid_nodes = dic.refine_height(
            self._ref_fine, frame, np.asarray(start.height_mm, np.float64), valid_px, self._height_nodes,
            outer=self.image_iterations, period_px=float(periods.min()),
            intensity_cell_px=max(dic.INTENSITY_CELL_PX, 1.6 * float(periods.max())))
        t4 = time.perf_counter()
        timings["refine"] += 1e3 * (t4 - t3)
        surf = hs._solve(np.where(valid_nodes, u_nodes, np.nan), valid_nodes, self.solver, _CG_TOL,
                         self._node_ref_mask, **pin_kw)
        valid_nodes = np.asarray(surf.valid, bool)
        u_nodes = np.where(valid_nodes, u_nodes, np.float32(np.nan)).astype(np.float32)
        pin = surf.pin
        if fd_pin is not None and fd_pin.unpinned_fraction > 0:
            # FD dropped them before the node grid: of FD's valid samples, that share and the nodes' own
            dropped = fd_pin.unpinned_fraction + (1.0 - fd_pin.unpinned_fraction) * pin.unpinned_fraction
            pin = dataclasses.replace(pin, unpinned_fraction=dropped)
        t5 = time.perf_counter()
        timings["height"] += 1e3 * (t5 - t4)
        amp_nodes = ng.down(self._up(amplitude))
        res = Result(height=np.asarray(surf.height_mm, np.float32), valid=valid_nodes,
                     slope_x=np.asarray(surf.slope_x, np.float32), slope_y=np.asarray(surf.slope_y, np.float32),
                     displacement=u_nodes, amplitude=amp_nodes, x_mm=np.asarray(surf.x_mm),
                     y_mm=np.asarray(surf.y_mm), grid="decimated", rows_px=ng.rows_px, cols_px=ng.cols_px,
                     carriers=self.carriers, phase=np.asarray(phase, np.float32),
                     valid_fraction=float(valid_nodes.mean()), timings_ms=timings, pin=pin, series=series)
        res = self._interpolate_full(res, solver=hs)
        timings["interpolate"] = 1e3 * (time.perf_counter() - t5)
        timings["total"] = 1e3 * (time.perf_counter() - t0)
        return res

    # ---------------------------------------------------------------- call
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
        """Reconstruct one frame.

        Parameters
        ----------
        frame : ndarray, shape (rows, cols)
            Camera frame, same shape as the reference (uint8/uint16/float).
        grid : {"full", "decimated"}, optional
            Overrides the default grid for this frame.

        Returns
        -------
        Result

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
        frame = self.validate_frame(frame)
        grid = self.grid if grid is None else grid
        self._check_grid(grid)
        if self.pattern == "dots":
            return self._call_dots(frame, grid)
        d = self.demod
        timings = {}
        spec = d.spectrum(frame)
        wins = d.windows(spec)
        g = d.decimated_from_windows(wins)
        checked = self._cheap_pattern_check(wins, frame)
        t1 = time.perf_counter()
        timings["demodulate"] = 1e3 * (t1 - t0)
        wrapped = np.angle(g * self._conj_g0)
        ratio = np.abs(g)
        ratio /= self._g0_den
        amplitude = np.minimum(ratio[0], ratio[1])
        valid = amplitude >= self.min_amplitude * exposure_gain(frame, self._ref_mean, amplitude)
        if not self._ref_ok_all:
            valid &= self._ref_ok
        all_valid = bool(valid.all())
        if not all_valid:
            valid &= ~_dilate(~valid, self.dilate)
        phase = self.unwrap_phase(wrapped, valid, all_valid)
        u = d.phase_to_displacement(phase if all_valid else np.nan_to_num(phase))
        fold = self._fold_ok(u, finite=True) if all_valid else self._fold_ok(np.where(valid, u, 0.0))
        if fold is not None:
            valid &= ~_dilate(~fold, self.dilate)
            all_valid = bool(valid.all())
        if not all_valid:
            valid = self._drop_islands(valid)
        if (self.check_pattern and not checked and not all_valid
                and np.count_nonzero(valid) < POOR_FRAME_VALID_FRACTION * valid.size):
            # noise or another pattern leaves the windows' centroid in place;
            # a poor frame gets the full check, which names what is wrong
            check_pattern_match(self.carriers, frame)
        if not all_valid and not valid.any():
            raise AllInvalidError(
                f"no part of the frame could be measured: pattern contrast relative to the reference "
                f"is {float(np.median(amplitude)):.2f} (median; need >= {self.min_amplitude}); check "
                "that TIR holds (theta, water level), the light and the exposure, and that nothing "
                "blocks the view")
        t2 = time.perf_counter()
        timings["unwrap_mask"] = 1e3 * (t2 - t1)
        iterations = self.refine_iterations
        if iterations is None:
            iterations = _DEFAULT_ITERATIONS[grid]
        u_first = u
        if iterations > 0:
            u = self._refine(wins, g, u, valid, iterations)
        t3 = time.perf_counter()
        timings["refine"] = 1e3 * (t3 - t2)
        # series memory (unwrapped phase of the final displacement)
        all_valid = all_valid and bool(valid.all())
        if self.temporal:
            self._prev_phase = phase.copy() if all_valid else np.where(valid, phase, np.nan)
            self._prev_valid = valid.copy()
            self._prev_all_valid = all_valid
        if not all_valid or u.dtype != np.float32:
            u = np.where(valid, u, np.nan).astype(np.float32)

        if grid == "full" and self.full_method == "ifft" and self.refine_method == "fd":
            res = self._full_ifft(wins, u, u_first, valid, amplitude, phase, timings, t3)
            timings["total"] = 1e3 * (time.perf_counter() - t0)
            return res
        hs = self.height_solver()
        pin_kw = dict(pin_fallback=self.pin_fallback, region_name=self.reference_region_name,
                      near=self._region_near)
        if all_valid and hs._fast is not None and self.solver in ("auto", "spectral"):
            # what solve() picks for finite u, all valid
            surf = hs._solve_fast(u, valid, self._ref_mask, **pin_kw)
        else:
            surf = hs._solve(u, valid, self.solver, _CG_TOL, self._ref_mask, **pin_kw)
        if surf.valid is not valid and not np.array_equal(surf.valid, valid):
            # pieces the pin could not reach: their offset was not measured
            valid = np.asarray(surf.valid, bool)
            all_valid = False
            u = np.where(valid, u, np.float32(np.nan)).astype(np.float32)
        series = self.check_series(phase, valid, surf)
        t4 = time.perf_counter()
        timings["height"] = 1e3 * (t4 - t3)
        note = ""
        if grid == "full" and self.refine_method == "image":
            # FD's heights above gave the series check (temporal unwrapping, pin offset)
            from .dic import RefinementDiverged

            try:
                return self._image_full(frame, u, valid, amplitude, phase, series, timings, t0, t4, surf.pin)
            except RefinementDiverged as exc:  # FD's heights below, and the reason with them
                note = f"image refinement stopped: {exc}; FD's heights kept"
        res = Result(height=np.asarray(surf.height_mm, np.float32), valid=valid,
                     slope_x=np.asarray(surf.slope_x, np.float32),
                     slope_y=np.asarray(surf.slope_y, np.float32), displacement=u,
                     amplitude=amplitude, x_mm=np.asarray(surf.x_mm), y_mm=np.asarray(surf.y_mm),
                     grid="decimated", rows_px=self.rows_px, cols_px=self.cols_px,
                     carriers=self.carriers, phase=np.asarray(phase, np.float32),
                     valid_fraction=1.0 if all_valid else float(valid.mean()), timings_ms=timings,
                     pin=surf.pin, series=series, note=note)
        if grid == "full":
            res = self._interpolate_full(res)
            timings["interpolate"] = 1e3 * (time.perf_counter() - t4)
        timings["total"] = 1e3 * (time.perf_counter() - t0)
        return res

    def check_series(self, phase, valid, surf) -> Optional[SeriesCheck]:
        """Compare this frame with the previous one (see :class:`SeriesCheck`);
        None for the first frame of a series."""
        prev = self._series_prev
        height = np.asarray(surf.height_mm)
        pin_samples = surf.pin_samples
        self._series_prev = (phase, valid, height, pin_samples)
        if prev is None:
            return None
        p_phase, p_valid, p_height, p_pin = prev
        both = valid & p_valid
        n = int(np.count_nonzero(both))
        if n == 0:
            return SeriesCheck(True, "no sample is valid in both this and the previous frame: "
                               "its heights cannot be compared with the previous frame's", float("nan"),
                               float("nan"), 0)
        # Where the change since the previous frame stays within pi, temporal
        # unwrapping added nothing the images do not say.  Where it exceeds pi
        # (a fast surface), it is a slip only where the series' 2 pi count
        # disagrees with this frame's own spatial unwrapping; NaN compares False.
        change = np.abs(phase - p_phase)
        slip_fraction = 0.0
        if float(np.nanmax(change, initial=0.0)) > np.pi:
            slip = self._disagrees_with_spatial(phase, valid)
            slip_fraction = float(np.count_nonzero(slip & both)) / n
        reasons = []
        if slip_fraction > SERIES_MAX_SLIP_FRACTION:
            reasons.append(
                f"the unwrapped phase changed by more than half a carrier period since the previous frame, and on "
                f"{100 * slip_fraction:.1f} % of the samples the series counts other periods than this frame's "
                f"own spatial unwrapping (temporal unwrapping slipped, or the surface moved too fast for the "
                f"frame rate)")
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
        return SeriesCheck(bool(reasons), "; ".join(reasons), slip_fraction, shift, n)

    def _disagrees_with_spatial(self, phase, valid):
        """Samples where the unwrapped ``phase`` (2, m_rows, m_cols) differs by a
        multiple of 2 pi from this frame's own spatial unwrapping, on the valid
        islands that reach the reference region (elsewhere the frame alone
        cannot fix an island's 2 pi offset: the series is the only witness)."""
        from scipy import ndimage

        labels, count = ndimage.label(valid)
        anchored = np.unique(labels[valid & self._ref_mask]) if self._ref_mask is not None else np.array([], int)
        anchored = anchored[anchored > 0]
        if not anchored.size and count:
            anchored = np.array([1 + int(np.argmax(np.bincount(labels[valid])[1:]))])
        judged = np.isin(labels, anchored)
        out = np.zeros(valid.shape, bool)
        for s in range(2):
            own = unwrap_spatial(wrap(np.where(valid, phase[s], 0.0)), valid, ref_mask=self._ref_mask)
            turns = np.round((np.where(judged, phase[s], 0.0) - np.where(judged, own, 0.0)) / TWO_PI)
            if judged.any():
                turns -= np.median(turns[judged])  # one common offset is no slip
            out |= judged & (turns != 0)
        return out

    def grid_coordinates(self, grid: Optional[str] = None) -> tuple:
        """``(x_mm, y_mm)`` of the columns and rows of a grid's results,
        without a frame (what a writer needs for a frame that could not be
        measured)."""
        grid = self.grid if grid is None else grid
        self._check_grid(grid)
        if grid == "full":
            x_mm, y_mm = self._coords_full(None)
        else:
            hs = self.height_solver()
            x_mm, y_mm = hs.x_mm, hs.y_mm
        return np.asarray(x_mm, np.float64).copy(), np.asarray(y_mm, np.float64).copy()

    def height_solver(self):
        """Height solver of the decimated grid (built once)."""
        if self._height_solver is None:
            from .height import solver_for

            self._height_solver = solver_for(self.geometry, self.rows_px, self.cols_px, self.shape)
        return self._height_solver

    def _coords_full(self, res):
        """x_mm (cols,), y_mm (rows,) of every pixel column and row: where the
        rays through the frame's central row / column meet the resting
        surface (the convention of processing.height)."""
        if self._full_coords is None:
            rows, cols = self.shape
            g = self.geometry
            rcen = np.array([[(rows - 1) / 2.0]])
            ccen = np.array([[(cols - 1) / 2.0]])
            x = np.asarray(g.surface_point(rcen, np.arange(cols, dtype=float)[None, :], self.shape)[0], float)
            y = np.asarray(g.surface_point(np.arange(rows, dtype=float)[:, None], ccen, self.shape)[1], float)
            self._full_coords = (np.broadcast_to(x.ravel(), (cols,)).copy(),
                                 np.broadcast_to(y.ravel(), (rows,)).copy())
        return self._full_coords

    def _interpolate_full(self, res, solver=None):
        """Decimated result -> every pixel (the decimated grid is oversampled
        twice, so Lanczos interpolation is within 0.2 % of band-limited).

        With uniform optics the slopes are fixed linear combinations of u and
        h (:meth:`HeightSolver.slope_coefficients`); interpolation is linear,
        so they are formed from the interpolated u and h instead of being
        interpolated themselves (two resizes fewer, same values up to
        rounding)."""
        up = self._up
        rows, cols = self.shape
        all_valid = bool(res.valid.all())
        if all_valid:
            valid = np.ones(self.shape, bool)
            fill = None
        else:
            valid = up.mask(res.valid)
            fill = nearest_fill_index(res.valid)
        invalid = None if all_valid else ~valid

        def src(field):
            return field if all_valid else np.nan_to_num(field if fill is None else field[fill])

        if solver is None and self._height_solver is not None:
            solver = self.height_solver()
        coef = solver.slope_coefficients() if solver is not None else None
        derive = coef is not None
        disp = np.empty((2, rows, cols), np.float32)
        height = np.empty(self.shape, np.float32)
        amplitude = np.empty(self.shape, np.float32)
        jobs = [(src(res.displacement[0]), disp[0]), (src(res.displacement[1]), disp[1]),
                (src(res.height), height), (res.amplitude, amplitude)]
        if not derive:
            slope_x = np.empty(self.shape, np.float32)
            slope_y = np.empty(self.shape, np.float32)
            jobs += [(src(res.slope_x), slope_x), (src(res.slope_y), slope_y)]
        _resize_all(up, jobs, self.planner.threads)
        if derive:
            srcs = (disp[0], disp[1], height)
            slope_x = np.empty(self.shape, np.float32)
            slope_y = np.empty(self.shape, np.float32)

            def combine(row, out):
                first = True
                for c, src in zip(row, srcs):
                    if c == 0.0:
                        continue
                    if first:
                        np.multiply(src, np.float32(c), out=out)
                        first = False
                    else:
                        cv2.scaleAdd(src, float(c), out, dst=out)
                if first:
                    out.fill(0.0)

            _run_pair(self.shape, lambda: combine(coef[0], slope_x), lambda: combine(coef[1], slope_y),
                      self.planner.threads)
        if invalid is not None:
            for a in (disp, height, slope_x, slope_y):
                np.copyto(a, np.float32(np.nan), where=invalid)
        x_mm, y_mm = self._coords_full(res)
        return dataclasses.replace(
            res, height=height, valid=valid, slope_x=slope_x,
            slope_y=slope_y, displacement=disp, amplitude=amplitude,
            x_mm=x_mm, y_mm=y_mm, grid="full",
            rows_px=np.arange(rows, dtype=float), cols_px=np.arange(cols, dtype=float),
            valid_fraction=1.0 if all_valid else float(np.count_nonzero(valid)) / valid.size)

    def _full_ifft(self, wins, u, u_first, valid, amplitude, phase, timings, t3):
        """Full grid from full-size inverse FFTs, unwrapped against the
        decimated phase; height solved on the full grid (slow, exact)."""
        from .height import surface_from_displacement

        rows, cols = self.shape
        up = self._up
        d = self.demod
        valid_full = up.mask(valid)
        gf = d.full_from_windows(wins)
        if self._g0_full is None:
            self._g0_full = d.full_from_windows(d.windows(d.spectrum(self._ref_f32))).copy()
        wrapped = np.angle(gf * np.conj(self._g0_full))
        guide = np.stack([up(np.nan_to_num(phase[s])) for s in range(2)])
        full_phase = wrapped + 2 * np.pi * np.round((guide - wrapped) / (2 * np.pi))
        uf = d.phase_to_displacement(full_phase)
        corr = np.nan_to_num(np.where(valid, u - u_first, 0.0))
        uf = uf + np.stack([up(corr[0]), up(corr[1])])
        uf = np.where(valid_full, uf, np.nan).astype(np.float32)
        if self._ref_mask_full is None:
            self._ref_mask_full = up.mask(self._ref_mask)
        surf = surface_from_displacement(uf, valid_full, self.geometry, rows_px=np.arange(rows, dtype=float),
                                         cols_px=np.arange(cols, dtype=float), frame_shape=self.shape,
                                         solver=self.solver, reference_mask=self._ref_mask_full,
                                         pin_fallback=self.pin_fallback, region_name=self.reference_region_name)
        valid_full = np.asarray(surf.valid, bool)
        timings["height"] = 1e3 * (time.perf_counter() - t3)
        return Result(height=np.asarray(surf.height_mm, np.float32), valid=valid_full,
                      slope_x=np.asarray(surf.slope_x, np.float32), slope_y=np.asarray(surf.slope_y, np.float32),
                      displacement=uf, amplitude=up(amplitude), x_mm=np.asarray(surf.x_mm),
                      y_mm=np.asarray(surf.y_mm), grid="full",
                      rows_px=np.arange(rows, dtype=float), cols_px=np.arange(cols, dtype=float),
                      carriers=self.carriers, phase=np.asarray(phase, np.float32),
                      valid_fraction=float(valid_full.mean()), timings_ms=timings, pin=surf.pin)

    # ----------------------------------------------------------- alignment
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
            (only when the frame shows no pattern), ``disturbed`` (True when the carriers
            came from local tiles because the surface distorts the pattern: not still water).  Random dots
            (``pattern="dots"``): :func:`processing.piv.dot_alignment` of the
            frame (``dot_size_px``, ``dots_per_window``, ``contrast``,
            ``focus``), ``saturation_pct``, and ``reference``: the same of the
            reference.
        """
        frame = self.validate_frame(frame)
        if self.pattern == "dots":
            from .piv import dot_alignment

            out = dot_alignment(frame, window_px=self.piv.window_px)
            out["saturation_pct"] = saturation_pct(frame)
            out["reference"] = dot_alignment(self._ref_dots, window_px=self.piv.window_px)
            return out
        from .alignment import checkerboard_alignment, frame_key

        out, shown = checkerboard_alignment(
            self.demod, self._carrier_search(), self.carriers, frame,
            theta_configured_deg=(float(self.geometry.theta_deg)
                                  if getattr(self.geometry, "setup", "tir") == "tir" else None),
            pattern_stretch_y=getattr(self.geometry, "pattern_stretch_y", None) or 1.0)
        out["saturation_pct"] = saturation_pct(frame)
        # the display spectrum of the same FFT, for spectrum(frame) right after (the live worker's order)
        self._shown_spectrum = (frame_key(frame), shown)
        return out

    def _carrier_search(self):
        """:func:`processing.alignment.carrier_search` of the reference (built on first use)."""
        if getattr(self, "_alignment_search", None) is None:
            from .alignment import carrier_search

            self._alignment_search = carrier_search(self.shape, self.demod.freq, self.demod.border_window)
        return self._alignment_search

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
        frame = self.validate_frame(frame)
        if self.pattern == "dots":
            from .carriers import frame_spectrum

            return dict(frame_spectrum(frame, size=size, max_freq=max_freq), carriers=[])
        from .alignment import display_spectrum_of, frame_key

        cached = getattr(self, "_shown_spectrum", None)
        if cached is not None and (size, max_freq) == (256, 0.25) and cached[0] == frame_key(frame):
            out = dict(cached[1])  # alignment(frame) just transformed this very frame
        else:
            search = self._carrier_search()
            spec = self.demod.spectrum(frame)
            # the mean x border-window peak at DC removed, as for the carriers
            leak = None if search.window_spectrum is None else (self.demod.last_mean, search.window_spectrum)
            out = display_spectrum_of(spec, self.shape, leak=leak, size=size, max_freq=max_freq)
        carriers = [(float(f[1]), float(f[0])) for f in self.demod.freq]
        out["carriers"] = carriers + [(-a, -b) for a, b in carriers]
        return out


def saturation_pct(frame) -> float:
    """Percentage of pixels at the top code of the frame's bit depth.

    For integer frames the bit depth is the smallest that holds the frame's
    maximum (a 10-bit camera in uint16 saturates at 1023); float frames
    saturate at 1.0 or at their maximum if above 1.
    """
    a = np.asarray(frame)
    top = float(a.max()) if a.size else 0.0
    if a.dtype.kind in "ui":
        bits = max(1, int(math.ceil(math.log2(top + 1)))) if top > 0 else 1
        level = 2 ** bits - 1
    else:
        level = 1.0 if top <= 1.0 else top
    return float(100.0 * np.count_nonzero(a >= level) / max(a.size, 1))
