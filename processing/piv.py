"""Displacement of random-dot patterns by PIV/DIC with window deformation (OpenPIV).

Labs that film a random-dot pattern instead of a checkerboard (the usual
FS-SS set-up) get the displacement ``u`` (pixels, ``I(r) = I0(r - u(r))``,
the same convention as Fourier demodulation) from OpenPIV's multi-pass
cross-correlation with window deformation (the passes of
:func:`openpiv.windef.first_pass` and :func:`openpiv.windef.multipass_img_deform`;
symmetric deformation, cubic spline interpolation, Gaussian sub-pixel peak),
reference as the first image and the frame as the second.  The passes are
driven here (:meth:`DotDisplacement.passes`), so that each image's spline
coefficients are computed once instead of on every pass and the images move
in threads.  Each pass's stages are OpenPIV's, compiled: the correlation
(FFT correlation, Gaussian peak, signal-to-noise ratio) on FFTW plans a
chunk of windows at a time (:mod:`processing.piv_correlate`), the validation
and outlier replacement in two loops (:mod:`processing.piv_validate`):
every flag equal to ``openpiv.windef``'s, every vector within 1e-6 px; with
``backend="rust"`` or ``"scipy"`` OpenPIV's own functions give its vectors
bit for bit (tests/processing/test_piv.py).  The :class:`processing.reconstruct.Reconstructor`
then masks, integrates and pins the heights exactly as for checkerboards
(``Reconstructor(reference, geometry, pattern="dots")``).

Grid: the centres of the last pass's interrogation windows, ``window_px``
wide with half overlap, i.e. one sample every ``window_px / 2`` pixels, as
OpenPIV reports them.  Symmetric deformation measures the displacement half
way between reference and frame; it is moved to the frame's pixels
(``u(x) = u_sym(x - u(x) / 2)``), which took the height error of ray-traced
bumps from 1.9-2.5 % to 0.3-0.6 % (measured with the grid as above).

Validity: OpenPIV's own validation (signal-to-noise, global and local
median) of the last pass; invalid vectors are not replaced, they are invalid
samples for the masked height solver.  Then every vector is checked against
the images themselves (:func:`window_correlation`): the reference moved by
the measured displacement must correlate with the frame over the window
around the sample (zero-normalised, at least :data:`MIN_WINDOW_CORRELATION`).
OpenPIV's tests let through vectors of windows with nothing to correlate: a
60 x 60 px black patch on a 256^2 frame (a shadow, lost TIR) left 24 % of the
samples inside it valid, off by up to 4 px (the bump's own displacement
there: 2-3 px), and the heights of the whole frame 3.2 % off instead of
0.5 %.
"""

from __future__ import annotations

import logging
import math
import sys

import numpy as np

from .errors import AllInvalidError, TirdeflectError
from .pools import pool, thread_map

__all__ = ["DotDisplacement", "FINAL_REPEATS", "MIN_WINDOW_CORRELATION", "DOTS_PER_WINDOW_MIN", "dot_alignment",
           "interrogation_windows", "sparse_dots_note",
           "window_correlation"]

#: Least zero-normalised correlation, over the window around a sample, of the
#: frame and the reference moved by the sample's displacement, for the sample
#: to count (:func:`window_correlation`).  Measured on ray-traced dot frames
#: of waves (256^2, 8 and 12 bit, noise 1-20 DN, 0.3x-1x brightness): median
#: 0.95-0.99, lowest 0.59-0.67; below 0.3 in a black patch; with sparse large
#: dots (0.8 mm, density 0.2) the windows that hold no dot, about 1 % of them.
MIN_WINDOW_CORRELATION = 0.5

#: Extra passes at the last window size: each one re-deforms the windows by
#: the displacement found so far.  Measured on a ray-traced 4 um bump (dots
#: 0.5 mm, 16 px windows): error in u 7.6 % -> 6.3 % -> 5.8 % with 0, 1, 3
#: extra passes (before the midpoint correction of ``_to_frame_positions``).
FINAL_REPEATS = 2


class DotDisplacement:
    """PIV/DIC displacement of frames against one random-dot reference.

    Parameters
    ----------
    reference : ndarray (rows, cols)
        The dot pattern seen via the flat surface.
    window_px : int
        Interrogation window of the last pass, pixels (even, >= 8); the
        passes before it use 4x and 2x that (where the frame holds at least
        four such windows).
    max_displacement_px : float
        Largest displacement the validation accepts, pixels.
    threads : int
        Threads that move the images between passes (the rows split among
        them); OpenPIV's compiled correlations (``openpiv-rust``) use their
        own pool (``RAYON_NUM_THREADS``, set by the batch workers).
    backend : {"fftw", "rust", "scipy"}, optional
        Each pass's stages: ``"fftw"`` (default) OpenPIV's correlation, peak
        and signal-to-noise ratio on FFTW plans a chunk of windows at a time
        (:class:`processing.piv_correlate.WindowCorrelation`), its validation
        and replacement compiled (:mod:`processing.piv_validate`): the same
        flags, the vectors to rounding, 2.5x faster; ``"rust"`` or
        ``"scipy"``: OpenPIV's own functions, correlating on that backend
        (``openpiv.windef``'s vectors bit for bit; for comparison).
    """

    def __init__(self, reference, *, window_px: int = 16, max_displacement_px: float = 30.0, threads: int = 1,
                 backend: str | None = None):
        try:
            from openpiv import filters, pyprocess, validation, windef
        except ImportError as exc:  # pragma: no cover - a dependency in pyproject
            raise TirdeflectError("pattern='dots' needs the openpiv package: pip install openpiv") from exc
        ref = np.asarray(reference)
        if ref.ndim != 2:
            raise ValueError(f"reference must be 2-D (rows, cols); got shape {ref.shape}")
        window_px = int(window_px)
        if window_px < 8 or window_px % 2:
            raise ValueError(f"window_px must be an even number >= 8; got {window_px}")
        if min(ref.shape) < 4 * window_px:
            raise ValueError(f"the frame {ref.shape} is too small for {window_px} px windows "
                             f"(needs at least {4 * window_px} px a side): use smaller windows")
        self.shape = ref.shape
        self._pyprocess, self._validation, self._filters = pyprocess, validation, filters
        self.backend = "fftw" if backend is None else backend
        if self.backend not in ("fftw", "rust", "scipy"):
            raise ValueError(f"backend must be 'fftw', 'rust' or 'scipy'; got {backend!r}")
        self.threads = max(1, int(threads))
        _quiet_openpiv()
        sizes = [w for w in (4 * window_px, 2 * window_px, window_px) if min(ref.shape) >= 4 * w]
        sizes += [window_px] * FINAL_REPEATS
        s = windef.PIVSettings()
        s.windowsizes = tuple(sizes)
        s.overlap = tuple(w // 2 for w in sizes)
        s.num_iterations = len(sizes)
        s.deformation_method = "symmetric"
        s.interpolation_order = 3
        s.subpixel_method = "gaussian"
        s.sig2noise_method = "peak2mean"
        s.sig2noise_validate = True
        s.validation_first_pass = True
        # no global standard-deviation test: it rejects every vector longer than std_threshold times the
        # field's spread, so on water mostly at rest a single feature is its own outlier (a ray-traced
        # bump of sigma 2.5 mm at 512^2: 22 vectors at its centre dropped, 15.2 % height error by PIV
        # and 7.1 % after image matching; at 256^2, where the bump fills more of the frame, none).
        # The local median test and the signal-to-noise test still catch the spurious vectors.
        s.std_threshold = math.inf
        s.min_max_u_disp = (-max_displacement_px, max_displacement_px)
        s.min_max_v_disp = (-max_displacement_px, max_displacement_px)
        s.replace_vectors = True  # between passes only; the last pass's flags are kept
        s.show_plot = s.save_plot = s.show_all_plots = False
        self.settings = s
        # the correlation stage of each pass (backend "fftw"): what processing.piv_correlate computes
        # is OpenPIV's stage for exactly these settings
        assert (s.correlation_method, s.normalized_correlation, s.use_vectorized, s.subpixel_method,
                s.sig2noise_method) == ("circular", False, True, "gaussian", "peak2mean")
        # and its validation and replacement (processing.piv_validate): these tests and this filter
        assert (s.median_normalized, s.median_size, s.filter_method, math.isinf(s.std_threshold)) == (
            False, 1, "localmean", True)
        self._correlations = {}
        self.window_px = window_px
        self._ref = ref.astype(np.float64)
        self._ref32 = ref.astype(np.float32)  # what the vectors' check moves, converted once
        self._ref_coef = spline_coefficients(self._ref)  # what every pass moves, computed once
        self._bases = {}  # pass -> the B-spline bases of its dense field (_dense)
        # grid of the last pass: OpenPIV's window centres (measured: taking
        # them half a pixel earlier, at start + (window - 1) / 2, raised the
        # height error of a ray-traced bump from 0.5 % to 1.6 %)
        x, y = windef.get_rect_coordinates(self.shape, sizes[-1], sizes[-1] // 2)
        self.rows_px = np.asarray(y[:, 0], float)
        self.cols_px = np.asarray(x[0, :], float)

    def __call__(self, frame):
        """Displacement of ``frame`` against the reference.

        Returns
        -------
        u : ndarray float32 (2, n_rows, n_cols)
            ``(u_row, u_col)`` in pixels at ``(rows_px, cols_px)``, NaN where invalid.
        valid : ndarray bool (n_rows, n_cols)
        """
        img = np.asarray(frame, np.float64)
        # a window with nothing to correlate (a shadow, lost TIR) has a flat correlation map, whose
        # Gaussian sub-pixel fit takes the log of zeros: that vector is refused below, not an error
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v, flags = self.passes(img)
        u = np.ma.filled(u, np.nan).astype(np.float32)
        v = np.ma.filled(v, np.nan).astype(np.float32)
        valid = ~np.asarray(flags, bool) & np.isfinite(u) & np.isfinite(v)
        disp = np.stack([v, u])  # OpenPIV: u along x (columns), v along rows (down)
        disp = self._to_frame_positions(disp, valid)
        if valid.any():
            valid &= window_correlation(self._ref32, img, disp, self.rows_px, self.cols_px,
                                        self.window_px) >= MIN_WINDOW_CORRELATION
        disp[:, ~valid] = np.nan
        return disp, valid

    def _correlate(self, a, b, it):
        """One pass's displacement ``(u, v, s2n)``, each (n_rows, n_cols), of
        image ``b`` against image ``a``: the stages of OpenPIV's
        ``extended_search_area_piv`` (search area = window), on FFTW plans
        (backend ``"fftw"``, :class:`processing.piv_correlate.WindowCorrelation`)
        or OpenPIV's own FFT correlation, sub-pixel peak and signal-to-noise
        ratio on windows cut here (:func:`interrogation_windows`: the same
        samples as OpenPIV's ``sliding_window_array``, whose compiled version
        took 6 ms a 512^2 image against 1.7 for a strided copy)."""
        s, pp = self.settings, self._pyprocess
        size, overlap = s.windowsizes[it], s.overlap[it]
        if self.backend == "fftw":
            key = (size, overlap)
            if key not in self._correlations:
                from .piv_correlate import WindowCorrelation

                self._correlations[key] = WindowCorrelation(self.shape, size, overlap, threads=self.threads)
            return self._correlations[key].displacements(a, b)
        shape = tuple(pp.get_field_shape(self.shape, (size, size), (overlap, overlap)))
        corr = pp.fft_correlate_images(interrogation_windows(a, size, overlap), interrogation_windows(b, size, overlap),
                                       correlation_method=s.correlation_method,
                                       normalized_correlation=s.normalized_correlation, backend=self.backend)
        u, v = pp.vectorized_correlation_to_displacements(corr, shape[0], shape[1], subpixel_method=s.subpixel_method)
        s2n = pp.vectorized_sig2noise_ratio(corr, sig2noise_method=s.sig2noise_method, width=s.sig2noise_mask)
        return u, v, s2n.reshape(shape)

    def passes(self, img):
        """OpenPIV's multi-pass window deformation (``openpiv.windef``: first
        pass, then each pass correlating the reference and the frame moved
        half way back and forth by the last pass's displacement, validated
        and with outliers replaced), with the cubic-spline coefficients of
        both images computed once instead of on every pass, the images
        moved half way each by :func:`sample_moved` and each pass's dense field by
        :meth:`_dense`.  ``(u, v, flags)`` of the last pass on its grid
        (OpenPIV's axes: ``u`` along the columns, ``v`` along the rows),
        ``img`` float64.  Raises AllInvalidError when every vector of a pass
        fails validation (a frame without dots)."""
        from scipy.interpolate import RectBivariateSpline

        s, pp = self.settings, self._pyprocess
        # the frame's spline coefficients (serial, 4 ms at 512^2) beside the first pass's correlation
        coef_job = pool(self.threads).submit(spline_coefficients, img) if (
            self.threads > 1 and s.num_iterations > 1) else None
        u, v, _s2n = self._correlate(self._ref, img, 0)
        y, x = self._pass_grid(0)
        flags = np.zeros(u.shape, bool)
        coef_img = None
        for it in range(1, s.num_iterations):
            if coef_img is None:
                coef_img = spline_coefficients(img) if coef_job is None else coef_job.result()
            y_new, x_new = self._pass_grid(it)
            u_pre = RectBivariateSpline(y, x, np.nan_to_num(np.ma.filled(u, 0.0)))(y_new, x_new)
            v_pre = RectBivariateSpline(y, x, np.nan_to_num(np.ma.filled(v, 0.0)))(y_new, x_new)
            # the dense field: cubic spline through the pass's grid at every pixel, both components side by side
            dense_u, dense_v = thread_map(
                lambda pre: self._dense(RectBivariateSpline(y_new, x_new, pre, kx=3, ky=3), it),
                [(u_pre,), (v_pre,)], self.threads)
            moved_ref = sample_moved(self._ref_coef, dense_v, dense_u, -0.5, self.threads)
            moved_img = sample_moved(coef_img, dense_v, dense_u, 0.5, self.threads)
            du, dv, s2n = self._correlate(moved_ref, moved_img, it)
            u, v, flags = self._validate(du + u_pre, dv + v_pre, s2n)
            if np.all(flags):  # OpenPIV's windef stops here too ("Something happened in the validation")
                raise AllInvalidError(f"every PIV vector of the frame failed validation (pass {it + 1} of "
                                      f"{s.num_iterations}, {s.windowsizes[it]} px windows): check that the dots "
                                      "are in focus and lit, and that the frame shows the reference's pattern")
            u, v = self._replace(u, v, flags)
            y, x = y_new, x_new
        if s.num_iterations == 1:
            flags = ~np.isfinite(u) | ~np.isfinite(v)
        return u, v, flags

    def _validate(self, u, v, s2n):
        """``(u, v, flags)`` of a pass: OpenPIV's ``typical_validation`` (compiled,
        :func:`processing.piv_validate.outlier_flags`, with backend ``"fftw"``)."""
        s = self.settings
        if self.backend == "fftw":
            from .piv_validate import outlier_flags

            return u, v, outlier_flags(u, v, s2n, s.min_max_u_disp, s.min_max_v_disp, s.median_threshold,
                                       s.sig2noise_threshold if s.sig2noise_validate else -np.inf)
        u = np.ma.masked_array(u, mask=np.zeros(u.shape, bool))
        v = np.ma.masked_array(v, mask=np.zeros(v.shape, bool))
        return u, v, self._validation.typical_validation(u, v, s2n, s)

    def _replace(self, u, v, flags):
        """``(u, v)`` with the flagged vectors replaced by their neighbours' mean (OpenPIV's
        ``replace_outliers``; compiled, :func:`processing.piv_validate.replace_outliers`, with ``"fftw"``)."""
        s = self.settings
        if self.backend == "fftw":
            from .piv_validate import replace_outliers

            return replace_outliers(u, v, flags, max_iter=s.max_filter_iteration, kernel_size=s.filter_kernel_size)
        return self._filters.replace_outliers(u, v, flags, method=s.filter_method, max_iter=s.max_filter_iteration,
                                              kernel_size=s.filter_kernel_size)

    def _dense(self, spline, it):
        """``spline`` (a cubic RectBivariateSpline through pass ``it``'s grid) at
        every pixel, as FITPACK evaluates it (positions beyond the outer knots
        clamped to them), as two matrix products with the B-spline basis at
        the pixels, which depends on the grid alone (built once per pass):
        1.8 against 6.8 ms a 512^2 field, equal to 2e-15.  The bases are
        sparse (four B-splines are non-zero at a pixel) and the products
        SciPy's own loops, not BLAS: OpenBLAS's threads, spinning beside the
        pass's own, made the dense products 6.3 ms a field on one core
        (50 ms of a 100 ms live frame)."""
        t_r, t_c, coef = spline.tck
        basis = self._bases.get(it)
        if basis is None:
            from scipy import sparse

            basis = self._bases[it] = tuple(sparse.csr_matrix(_spline_basis(t, n))
                                            for t, n in ((t_r, self.shape[0]), (t_c, self.shape[1])))
        along_cols = basis[1] @ coef.reshape(len(t_r) - 4, len(t_c) - 4).T  # (cols, n_basis_r)
        return np.asarray(basis[0] @ np.ascontiguousarray(along_cols.T))

    def _pass_grid(self, it):
        """Window centres ``(rows, cols)`` of pass ``it``, pixels (OpenPIV's)."""
        size, overlap = self.settings.windowsizes[it], self.settings.overlap[it]
        x, y = self._pyprocess.get_rect_coordinates(self.shape, size, overlap)
        return np.asarray(y[:, 0], float), np.asarray(x[0, :], float)

    def _to_frame_positions(self, disp, valid):
        """Symmetric window deformation measures the displacement half way
        between the reference and the frame: at grid point ``x`` it is the
        displacement of the frame pixel ``x + u / 2``.  The frame's
        convention wants it at the frame pixel: ``u(x) = u_sym(x - u(x) / 2)``
        (two fixed-point steps, cubic spline on the grid)."""
        from scipy import ndimage

        from .fill import nearest_fill_index

        fill = nearest_fill_index(valid)
        src = disp if fill is None else disp[:, fill[0], fill[1]]
        src = np.nan_to_num(src).astype(np.float64)
        dr = self.rows_px[1] - self.rows_px[0]
        dc = self.cols_px[1] - self.cols_px[0]
        gr, gc = np.meshgrid(np.arange(src.shape[1], dtype=float), np.arange(src.shape[2], dtype=float), indexing="ij")
        coef = [ndimage.spline_filter(src[i], order=3, mode="nearest") for i in range(2)]
        u = src.copy()
        for _ in range(2):
            at = [gr - 0.5 * u[0] / dr, gc - 0.5 * u[1] / dc]
            u = np.stack([ndimage.map_coordinates(coef[i], at, order=3, prefilter=False, mode="nearest")
                          for i in range(2)])
        return u.astype(np.float32)


#: Pixels of edge padding before the spline coefficients (scipy.ndimage's own for ``mode="nearest"``).
_SPLINE_PAD = 12


def spline_coefficients(image) -> np.ndarray:
    """Cubic B-spline coefficients of ``image`` (float64, padded by
    :data:`_SPLINE_PAD` edge pixels), as ``scipy.ndimage.map_coordinates(...,
    order=3, mode="nearest")`` computes them on every call: computed once per
    image here, :func:`sample_spline` reads them."""
    from scipy import ndimage

    padded = np.pad(np.asarray(image, np.float64), _SPLINE_PAD, mode="edge")
    return ndimage.spline_filter(padded, order=3, output=np.float64, mode="nearest")


def sample_spline(coef, rows, cols, threads: int = 1) -> np.ndarray:
    """The image of :func:`spline_coefficients` at pixel positions ``(rows,
    cols)`` (broadcast to one 2-D shape), float64
    (:func:`processing.spline_kernels.sample_rows`: ``scipy.ndimage.map_coordinates``'s
    cubic spline, compiled); the rows split among ``threads`` threads."""
    rows, cols = np.broadcast_arrays(np.asarray(rows, np.float64), np.asarray(cols, np.float64))  # views
    return _sample(coef, rows, cols, 0.0, 1.0, threads)


def sample_moved(coef, disp_rows, disp_cols, scale: float, threads: int = 1) -> np.ndarray:
    """The image of :func:`spline_coefficients` at every pixel ``(i, j)``
    moved by ``scale`` times the displacement ``(disp_rows, disp_cols)``
    (pixels, the image's shape): :func:`sample_spline` at ``(i + scale *
    disp_rows, j + scale * disp_cols)``, the same floats, without building
    the position arrays."""
    return _sample(coef, np.asarray(disp_rows, np.float64), np.asarray(disp_cols, np.float64), 1.0, float(scale),
                   threads)


#: Bands of rows :func:`_sample` cuts its rows into, per thread.
SAMPLE_BANDS_PER_THREAD = 4


def _sample(coef, rows, cols, grid, scale, threads):
    """:func:`processing.spline_kernels.sample_rows` over every row, in bands of rows taken one at a time by
    ``threads`` workers (:data:`SAMPLE_BANDS_PER_THREAD` a worker: one set aside by the OS holds up one band)."""
    from .spline_kernels import sample_rows

    out = np.empty(rows.shape, np.float64)
    n = rows.shape[0]
    pad = float(_SPLINE_PAD)
    if threads <= 1 or n < 64:
        sample_rows(coef, rows, cols, out, 0, n, pad, grid, scale)
        return out
    bounds = np.linspace(0, n, min(n // 16, SAMPLE_BANDS_PER_THREAD * threads) + 1).astype(int)
    thread_map(lambda lo, hi: sample_rows(coef, rows, cols, out, lo, hi, pad, grid, scale),
               list(zip(bounds[:-1], bounds[1:])), threads)
    return out


def _spline_basis(knots, n_px: int) -> np.ndarray:
    """(n_px, n_basis) float64: the cubic B-splines of ``knots`` at pixels
    ``0 ... n_px - 1``, each position clamped to the knots' base interval
    (FITPACK's evaluation outside it)."""
    from scipy.interpolate import BSpline

    n_basis = len(knots) - 4
    pos = np.clip(np.arange(n_px, dtype=np.float64), knots[3], knots[n_basis])
    return BSpline(knots, np.eye(n_basis), 3, extrapolate=False)(pos)


def interrogation_windows(image, size: int, overlap: int) -> np.ndarray:
    """``(n_windows, size, size)`` float64 C-contiguous copy of the square windows
    of ``image`` that start every ``size - overlap`` pixels from its top-left
    corner, row by row (as many as fit: OpenPIV's ``get_field_shape``), the
    layout of OpenPIV's ``sliding_window_array``."""
    from .piv_correlate import window_view

    return np.ascontiguousarray(window_view(image, size, overlap)).reshape(-1, size, size)


def correlation_backend() -> str:
    """OpenPIV's backend: ``"rust"`` where the ``openpiv-rust`` wheel is
    installed (the same correlations and peaks, bit for bit, compiled),
    else ``"scipy"``."""
    try:
        import openpiv_rust  # noqa: F401
    except ImportError:
        return "scipy"
    return "rust"


def window_correlation(reference, frame, displacement, rows_px, cols_px, window_px: int) -> np.ndarray:
    """Zero-normalised correlation of ``frame`` and ``reference`` moved by
    ``displacement`` (``I(r) = I0(r - u(r))``, pixels, on the grid ``rows_px``
    x ``cols_px``; linear between samples, NaN samples given their nearest
    finite neighbour's), over the ``window_px`` square around each grid sample.

    Returns float32 (n_rows, n_cols) in [-1, 1]; 0 where either window is flat."""
    import cv2

    from .fill import nearest_fill_index

    rows, cols = frame.shape
    u = np.asarray(displacement, np.float32)
    fill = nearest_fill_index(np.isfinite(u[0]) & np.isfinite(u[1]))
    if fill is not None:
        u = u[:, fill[0], fill[1]]
    # every pixel's place on the grid, in samples (constant beyond the outer samples)
    gr = np.clip((np.arange(rows) - rows_px[0]) / (rows_px[1] - rows_px[0]), 0, len(rows_px) - 1)
    gc = np.clip((np.arange(cols) - cols_px[0]) / (cols_px[1] - cols_px[0]), 0, len(cols_px) - 1)
    at_c, at_r = np.meshgrid(gc.astype(np.float32), gr.astype(np.float32))
    px, py = np.meshgrid(np.arange(cols, dtype=np.float32), np.arange(rows, dtype=np.float32))
    px -= cv2.remap(np.ascontiguousarray(u[1]), at_c, at_r, cv2.INTER_LINEAR)
    py -= cv2.remap(np.ascontiguousarray(u[0]), at_c, at_r, cv2.INTER_LINEAR)
    moved = cv2.remap(np.asarray(reference, np.float32), px, py, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    a = np.asarray(frame, np.float32)
    box = (int(window_px), int(window_px))

    def mean(x):
        return cv2.blur(x, box, borderType=cv2.BORDER_REFLECT)

    ma, mm = mean(a), mean(moved)
    cov = mean(a * moved) - ma * mm
    var = np.maximum(mean(a * a) - ma * ma, 0) * np.maximum(mean(moved * moved) - mm * mm, 0)
    zncc = np.where(var > 0, cov / np.sqrt(np.where(var > 0, var, 1)), 0).astype(np.float32)
    ri = np.clip(np.rint(rows_px).astype(int), 0, rows - 1)
    ci = np.clip(np.rint(cols_px).astype(int), 0, cols - 1)
    return zncc[np.ix_(ri, ci)]


log = logging.getLogger(__name__)


def _openpiv_note(*args, **_kwargs):
    log.debug("OpenPIV: %s", " ".join(str(a) for a in args))


def _quiet_openpiv() -> None:
    """OpenPIV prints notes (fallback peak fits, bad peaks) on stdout: send
    them to this module's debug log instead, for OpenPIV's own modules only
    (swapping sys.stdout would silence every other thread's output too)."""
    for name, module in list(sys.modules.items()):
        if name == "openpiv" or name.startswith("openpiv."):
            if getattr(module, "print", None) is not _openpiv_note:
                module.print = _openpiv_note


def dot_alignment(frame, *, window_px: int = 16) -> dict:
    """What matters when aligning a random-dot set-up, from one frame.

    Returns
    -------
    dict
        ``dot_size_px`` (2,): full width at half maximum of one dot along
        rows and columns, the median over the bright local maxima of a
        Gaussian through each maximum and its two neighbours (above the
        ground level, the 1st percentile), as PIV's sub-pixel peak fit does
        (2-4 px is what PIV wants; below 2 px peak locking biases the
        displacement towards whole pixels).  Measured on ray-traced TIR
        frames (dots 1.0-5.9 px FWHM, density 0.3-0.6): 0.1-0.2 px above
        the rendered dots' FWHM (the pixels' own width adds), where the
        autocorrelation's width (its FWHM / sqrt 2) read up to 0.8 px small
        (overlapping dots narrow its peak);
        ``dots_per_window``: bright local maxima per final interrogation
        window (``window_px`` squared; PIV wants about 5-10);
        ``contrast``: ``(p99 - p1) / (p99 + p1)`` of the grey levels;
        ``focus``: ``1 - acf(1 px)``, mean of both axes (0: blurred flat, 1:
        white noise; dots in focus at 3 px give about 0.3-0.5).
    """
    a = np.asarray(frame, np.float64)
    n_r, n_c = a.shape
    crop = a[n_r // 2 - min(n_r, 512) // 2: n_r // 2 + min(n_r, 512) // 2,
             n_c // 2 - min(n_c, 512) // 2: n_c // 2 + min(n_c, 512) // 2]
    z = crop - crop.mean()
    spec = np.fft.rfft2(z)
    acf = np.fft.irfft2(spec * np.conj(spec), s=z.shape)
    acf = acf / acf[0, 0] if acf[0, 0] > 0 else acf

    def fwhm(profile):
        # profile[0] = 1 at zero lag; first lag where it falls below 0.5
        below = np.flatnonzero(profile < 0.5)
        if below.size == 0:
            return float("nan")
        k = int(below[0])
        p0, p1 = profile[k - 1], profile[k]
        return 2.0 * (k - 1 + (p0 - 0.5) / (p0 - p1))

    from scipy import ndimage

    smooth = ndimage.gaussian_filter(crop, 0.7)
    peaks = (smooth == ndimage.maximum_filter(smooth, size=3)) & (smooth > smooth.mean() + smooth.std())
    per_window = float(np.count_nonzero(peaks)) * window_px * window_px / crop.size
    lo, hi = np.percentile(crop, [1, 99])
    size = _peak_fwhm(crop, peaks, lo)
    if not np.all(np.isfinite(size)):  # no dot to fit: the autocorrelation's width
        size = np.array([fwhm(acf[:, 0]), fwhm(acf[0, :])]) / math.sqrt(2.0)
    return {
        "dot_size_px": size,
        "dots_per_window": per_window,
        "contrast": float((hi - lo) / (hi + lo)) if hi + lo > 0 else 0.0,
        "focus": float(1.0 - 0.5 * (acf[1, 0] + acf[0, 1])),
    }


#: Fewest dots per final interrogation window below which random dots are too sparse for PIV: a dots run
#: is named (:func:`sparse_dots_note`) and the live window's Alignment tab is NOT READY (PIV wants about
#: 5-10).  By-hand sweep (7 Dec 2026, 256^2 ray-traced TIR frames of simulate's 2 um bump, dots 0.25-0.9
#: mm, density 0.08-0.7, full grid): 4.97 / 9.1 / 13.0 dots a window 0.32 / 0.25 / 0.94 % rms height error;
#: 1.45 (density 0.08) 7.8 %, 1.12 (0.9 mm dots, density 0.2) 3.2 %, exit 0 and no word.
DOTS_PER_WINDOW_MIN = 4.0


def sparse_dots_note(reference, *, window_px: int = 16):
    """A sentence where the reference's random dots are too sparse for PIV's final ``window_px`` windows
    (fewer than :data:`DOTS_PER_WINDOW_MIN` bright dots a window, :func:`dot_alignment`), else None."""
    per_window = dot_alignment(reference, window_px=window_px)["dots_per_window"]
    if per_window >= DOTS_PER_WINDOW_MIN:
        return None
    return (f"the reference shows {per_window:.1f} dots per {window_px} x {window_px} px interrogation window, "
            f"PIV needs about {DOTS_PER_WINDOW_MIN:g} or more (ray-traced, 1.1-1.5 a window put the heights 3-8 % "
            f"off, 5 and more 0.3 %): many windows hold no dot to correlate. Use a denser or finer dot pattern, "
            f"or a lens that puts more dots in each window")


def _peak_fwhm(image, peaks, ground):
    """FWHM (rows, cols) in pixels of the dots at ``peaks``: median of the
    three-point Gaussian fits through each maximum (``ground`` subtracted)."""
    inner = peaks.copy()
    inner[0, :] = inner[-1, :] = inner[:, 0] = inner[:, -1] = False
    r, c = np.nonzero(inner)
    if r.size == 0:
        return np.full(2, np.nan)
    log_i = np.log(np.maximum(image - ground, 1e-6 * max(float(image.max() - ground), 1e-30)))
    out = []
    for dr, dc in ((1, 0), (0, 1)):
        curvature = 2.0 * log_i[r, c] - log_i[r - dr, c - dc] - log_i[r + dr, c + dc]  # 1 / sigma^2
        curvature = curvature[curvature > 0]
        out.append(2.0 * math.sqrt(2.0 * math.log(2.0) / np.median(curvature)) if curvature.size else np.nan)
    return np.array(out)
