"""One PIV pass's correlation stage, OpenPIV's on FFTW plans (:class:`WindowCorrelation`).

What ``openpiv.pyprocess.extended_search_area_piv`` does when the search area
is the window (the passes of :class:`processing.piv.DotDisplacement`):
circular FFT cross-correlation of every interrogation window of the frame
against the reference's (``fft_correlate_images``, not normalised), the
correlation peak with OpenPIV's Gaussian three-point sub-pixel fit
(``vectorized_correlation_to_displacements``: on the map in float32 plus
1e-7, a parabolic fit where a neighbour is not positive, NaN where the peak
touches the map's border) and its peak-to-mean ratio
(``vectorized_sig2noise_ratio``, ``"peak2mean"``: 0 where the peak is below
1e-3 or on the border).  The same numbers to rounding: the transforms are
FFTW's instead of pocketfft's or openpiv-rust's, the sums are taken in
another order (tests/processing/test_piv.py: every vector within 1e-6 px of
OpenPIV's, every flag equal).  Why: at 512^2 with 16 px windows, cutting
the windows out took openpiv-rust 5-6 ms an image, its correlation 11-14 ms
a pass and the NumPy peak search another 3-4 ms; here 6.3-6.6 ms for all of
it (FFTW plans built once per window layout, a chunk of windows at a time so
that it stays in the cache, the ``fftshift`` folded into the spectrum as a
sign, one compiled pass over the maps).
"""

from __future__ import annotations

import numba
import numpy as np

from .fft import pyfftw

__all__ = ["CHUNK_SAMPLES", "WindowCorrelation", "correlation_peaks", "window_view"]


def window_view(image, size: int, overlap: int) -> np.ndarray:
    """``(n_rows, n_cols, size, size)`` float64 view (no copy where ``image`` is
    float64) of the square windows of ``image`` that start every ``size -
    overlap`` pixels from its top-left corner, as many as fit: OpenPIV's window
    layout (``get_field_shape``, ``sliding_window_array``)."""
    from numpy.lib.stride_tricks import sliding_window_view

    step = int(size) - int(overlap)
    return sliding_window_view(np.asarray(image, np.float64), (size, size))[::step, ::step]


#: Samples of one window array a chunk of windows holds (512 KB of float64): each chunk goes through
#: both transforms, the cross spectrum, the inverse and the peak search while it is in the cache (the
#: whole field at once, 42 MB at 512^2 with 16 px windows, made each step wait for memory: 8.3 ms a pass
#: for the windows and transforms alone, against 6.3-6.6 ms for all of it, the peak search included).
CHUNK_SAMPLES = 65536


class _Plans:
    """FFTW plans and arrays for ``n`` windows of ``size`` x ``size``."""

    def __init__(self, n, size, planner_effort):
        self.a = pyfftw.empty_aligned((n, size, size), np.float64)
        self.b = pyfftw.empty_aligned((n, size, size), np.float64)
        self.corr = pyfftw.empty_aligned((n, size, size), np.float64)
        self.fa = pyfftw.empty_aligned((n, size, size // 2 + 1), np.complex128)
        self.fb = pyfftw.empty_aligned((n, size, size // 2 + 1), np.complex128)
        flags = (planner_effort,)
        self.forward_a = pyfftw.FFTW(self.a, self.fa, axes=(1, 2), flags=flags, threads=1)
        self.forward_b = pyfftw.FFTW(self.b, self.fb, axes=(1, 2), flags=flags, threads=1)
        self.inverse = pyfftw.FFTW(self.fa, self.corr, axes=(1, 2), direction="FFTW_BACKWARD",
                                   flags=flags + ("FFTW_DESTROY_INPUT",), threads=1)


class WindowCorrelation:
    """Circular cross-correlation of the ``size`` x ``size`` windows of two images
    that start every ``size - overlap`` pixels (OpenPIV's window layout,
    :func:`processing.piv.interrogation_windows`), on FFTW plans made for one
    image shape, rows of windows at a time (:data:`CHUNK_SAMPLES`; built once,
    one caller at a time: the plans own their arrays).

    Parameters
    ----------
    image_shape : (int, int)
    size, overlap : int
        Window side and overlap, pixels (``size`` even).
    planner_effort : str
        FFTW planner flag (``FFTW_ESTIMATE``, planned in milliseconds, measured
        as fast as ``FFTW_MEASURE`` here).
    threads : int
        Workers the chunks are shared among, each taking the next chunk on its
        own plans; the result does not depend on it.
    """

    def __init__(self, image_shape, size: int, overlap: int, planner_effort: str = "FFTW_ESTIMATE",
                 threads: int = 1):
        size, overlap = int(size), int(overlap)
        if size % 2:
            raise ValueError(f"window size must be even; got {size}")
        rows, cols = image_shape
        self.size = size
        self.step = size - overlap
        self.field_shape = ((rows - size) // self.step + 1, (cols - size) // self.step + 1)
        n_r, n_c = self.field_shape
        self.rows_per_chunk = max(1, min(n_r, CHUNK_SAMPLES // (n_c * size * size)))
        self.starts = list(range(0, n_r, self.rows_per_chunk))
        self.threads = max(1, min(int(threads), len(self.starts)))
        # per worker (processing.pools.slot_map's slots): chunk rows -> plans; any worker may take any chunk
        sizes = sorted({min(self.rows_per_chunk, n_r - r0) for r0 in self.starts})
        self._plans = [{k: _Plans(k * n_c, size, planner_effort) for k in sizes} for _ in range(self.threads)]
        # fftshift of the map by size / 2 both ways = the spectrum times (-1)^(k_r + k_c); and the inverse
        # transform's 1 / size^2 (numpy's irfft2 normalisation) taken with it
        k = np.arange(size)
        self._shift = ((-1.0) ** (k[:, None] + np.arange(size // 2 + 1)[None, :])) / float(size * size)

    def _run(self, image_a, image_b, use):
        """``use(first window, plans)`` for each chunk once its maps are computed (zero shift at
        ``[size // 2] * 2``), the chunks taken one at a time by :attr:`threads` workers
        (:func:`processing.pools.slot_map`)."""
        from .pools import slot_map

        s, (n_r, n_c) = self.size, self.field_shape
        views = [window_view(x, s, s - self.step) for x in (image_a, image_b)]

        def chunk(slot, r0):
            r1 = min(n_r, r0 + self.rows_per_chunk)
            p = self._plans[slot][r1 - r0]
            np.copyto(p.a.reshape(r1 - r0, n_c, s, s), views[0][r0:r1])
            np.copyto(p.b.reshape(r1 - r0, n_c, s, s), views[1][r0:r1])
            p.forward_a.execute()
            p.forward_b.execute()
            _cross_spectrum(p.fa, p.fb, self._shift)
            p.inverse.execute()
            use(r0 * n_c, p)

        slot_map(chunk, [(r0,) for r0 in self.starts], self.threads)

    def maps(self, image_a, image_b) -> np.ndarray:
        """``(n_windows, size, size)`` float64: each window of ``image_b`` correlated
        with ``image_a``'s, zero shift at ``[size // 2, size // 2]`` (OpenPIV's
        ``fft_correlate_images`` map, circular, not normalised)."""
        n = self.field_shape[0] * self.field_shape[1]
        out = np.empty((n, self.size, self.size))

        def keep(k0, p):
            out[k0:k0 + p.corr.shape[0]] = p.corr

        self._run(image_a, image_b, keep)
        return out

    def displacements(self, image_a, image_b):
        """``(u, v, s2n)``, each of :attr:`field_shape`: the correlation peaks
        (:func:`correlation_peaks`) of :meth:`maps`, chunk by chunk."""
        n = self.field_shape[0] * self.field_shape[1]
        index = np.empty((n, 2), np.int64)
        near = np.empty((5, n), np.float32)
        s2n = np.empty(n)

        def peaks(k0, p):
            k1 = k0 + p.corr.shape[0]
            _peak_pixels(p.corr, index[k0:k1], near[:, k0:k1], s2n[k0:k1])

        self._run(image_a, image_b, peaks)
        u, v = _subpixel(index, near, self.size, self.size)
        return tuple(x.reshape(self.field_shape) for x in (u, v, s2n))


@numba.njit(nogil=True, cache=True)
def _cross_spectrum(fa, fb, shift):  # pragma: no cover - compiled
    """``fa <- conj(fa) * fb * shift`` (shift broadcast over the windows), one pass
    over each window's spectrum as one flat run (C-contiguous arrays): with
    16 px windows a row of the half spectrum is 9 samples, and looping over
    rows and columns took 4x as long (0.075 against 0.018 ms a chunk).  The
    products are written out; for finite spectra they are the complex
    products bit for bit."""
    n = fa.shape[0]
    m = shift.size
    a2 = fa.reshape(n, m)
    b2 = fb.reshape(n, m)
    s = shift.reshape(m)
    for k in range(n):
        for q in range(m):
            ar = a2[k, q].real
            ai = a2[k, q].imag
            br = b2[k, q].real
            bi = b2[k, q].imag
            a2[k, q] = complex((ar * br + ai * bi) * s[q], (ar * bi - ai * br) * s[q])


@numba.njit(nogil=True, cache=True)
def _peak_pixels(corr, index, near, s2n):  # pragma: no cover - compiled; tested against OpenPIV's functions
    """Per map: the first largest sample of float32(map) + 1e-7 (``index``: row, col; -1 where it touches
    the border), it and its four neighbours as float32 (``near``: c, left, right, down, up in OpenPIV's
    names) and the float64 map's peak-to-mean ratio (``s2n``)."""
    n, h, w = corr.shape
    eps = np.float32(1e-7)
    for k in range(n):
        best = np.float32(corr[k, 0, 0]) + eps
        bi = 0
        bj = 0
        top = corr[k, 0, 0]
        ti = 0
        tj = 0
        total = 0.0
        for i in range(h):
            for j in range(w):
                x = corr[k, i, j]
                total += x
                x32 = np.float32(x) + eps
                if x32 > best:
                    best, bi, bj = x32, i, j
                if x > top:
                    top, ti, tj = x, i, j
        if bi < 1 or bi > h - 2 or bj < 1 or bj > w - 2:
            index[k, 0] = -1
            index[k, 1] = -1
            bi, bj = h // 2, w // 2  # as OpenPIV, a place to read from; the vector is NaN
        else:
            index[k, 0] = bi
            index[k, 1] = bj
        near[0, k] = np.float32(corr[k, bi, bj]) + eps
        near[1, k] = np.float32(corr[k, bi - 1, bj]) + eps
        near[2, k] = np.float32(corr[k, bi + 1, bj]) + eps
        near[3, k] = np.float32(corr[k, bi, bj - 1]) + eps
        near[4, k] = np.float32(corr[k, bi, bj + 1]) + eps
        mean = abs(total / (h * w))
        if top < 1e-3 or ti == 0 or ti == h - 1 or tj == 0 or tj == w - 1 or not mean > 0.0:
            s2n[k] = 0.0
        else:
            s2n[k] = top / mean


def correlation_peaks(corr):
    """``(u, v, s2n)``, each (n_windows,) float64, of correlation maps ``corr``
    (n_windows, rows, cols) whose zero shift is at ``[rows // 2, cols // 2]``:
    ``u`` along the columns, ``v`` along the rows (pixels; NaN where the peak
    touches the map's border), ``s2n`` the peak-to-mean ratio (module
    docstring).  The peak search compiled, the fit in NumPy with OpenPIV's
    own float32 operations (its logarithms are NumPy's)."""
    corr = np.ascontiguousarray(corr, np.float64)
    n, h, w = corr.shape
    index = np.empty((n, 2), np.int64)
    near = np.empty((5, n), np.float32)
    s2n = np.empty(n)
    _peak_pixels(corr, index, near, s2n)
    u, v = _subpixel(index, near, h, w)
    return u, v, s2n


def _subpixel(index, near, h, w):
    """``(u, v)`` of the peaks :func:`_peak_pixels` found in maps of ``h`` x ``w``: OpenPIV's
    Gaussian three-point fit, its own float32 NumPy operations."""
    c, cl, cr, cd, cu = near
    with np.errstate(divide="ignore", invalid="ignore"):
        log_c, log_l, log_r, log_d, log_u = np.log(near)
        nom1 = log_l - log_r
        den1 = 2 * log_l - 4 * log_c + 2 * log_r
        nom2 = log_d - log_u
        den2 = 2 * log_d - 4 * log_c + 2 * log_u
        shift_i = np.divide(nom1, den1, out=np.zeros_like(nom1), where=(den1 != 0.0))
        shift_j = np.divide(nom2, den2, out=np.zeros_like(nom2), where=(den2 != 0.0))
        low = (c <= 0) | (cl <= 0) | (cr <= 0) | (cu <= 0) | (cd <= 0)
        if low.any():  # OpenPIV's parabolic fallback where a value is not positive
            shift_i[low] = (cl[low] - cr[low]) / (2 * cl[low] - 4 * c[low] + 2 * cr[low])
            shift_j[low] = (cd[low] - cu[low]) / (2 * cd[low] - 4 * c[low] + 2 * cu[low])
    v = (index[:, 0].astype(np.float64) + shift_i) - np.floor(h / 2)
    u = (index[:, 1].astype(np.float64) + shift_j) - np.floor(w / 2)
    bad = index[:, 0] < 0
    u[bad] = np.nan
    v[bad] = np.nan
    return u, v
