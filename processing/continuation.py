"""The pattern continued beyond the frame's border, for FD's refinement (issue 19).

Fourier demodulation needs a border treatment: the FFT joins each border to
the opposite one.  The pipeline's is a cosine taper one carrier period wide
(:class:`processing.demodulation.Demodulator`), and it is wrong in one way:
within a filter footprint of the border the band-pass sees the pattern fade
to zero, not the pattern going on, so the phase there is a one-sided average.
Where the displacement changes towards the border the error reaches several
carrier periods in (docs/processing.md section 6), and FD's refinement, which
demodulates frame and warped reference through the same taper, converges
towards the border only slowly.

:class:`PatternContinuation` puts an image in a frame about four carrier
periods larger on each side and fills that pad with the pattern itself: each
carrier's envelope is measured along a line :data:`INSET_PERIODS` of a period
inside the border (a Gaussian-weighted local demodulation over the pixels,
sigma :data:`ENVELOPE_SIGMA_PERIODS` of a period) and put back on its carrier
at every pad pixel, from the nearest point of that line; a cosine taper in the
outer half of the pad closes the frame.  :class:`ContinuedSignals`
demodulates continued images on the padded frame (a ``Demodulator`` with no
border window of its own) and takes the product of two images' analytic
signals to a chain's decimated grid by cubic B-spline (the padded frame's
samples do not fall on the chain's).  FD's full grid measures its phase this
way and its refinement its correction (:func:`processing.refine.refine_fd`),
and the reference it warps is band-limited on its continued frame
(:func:`processing.refine.warp_reference`).  The live decimated grid and
image matching's start keep the taper.

Measured (docs/processing.md section 6; ``benchmarks/bench_border_extension.py``
for the demodulation alone): ray-traced pure cosines of issue 19 (float
frames), no refinement 0.92 -> 0.46 %, FD's refinement 0.73 -> 0.48 %
displacement and 0.53 -> 0.16 % height; accuracy table, FD on the 12-30 mm
waves 0.50 -> 0.12 %, and FD no longer worse than no refinement on the deep
dimple (0.07 -> 0.03 against 0.04 %).
"""

from __future__ import annotations

import math

import numpy as np

from .carrier_peaks import Carriers
from .demodulation import Demodulator, nice_fft_size, tukey

__all__ = ["CONTINUATION_PERIODS", "ENVELOPE_SIGMA_PERIODS", "INSET_PERIODS", "PatternContinuation",
           "ContinuedSignals"]

#: Pad on each side of the frame, in (longest) carrier periods (then rounded up to a fast FFT size).
CONTINUATION_PERIODS = 4.0
#: Sigma of the Gaussian window that measures the envelopes along the border, carrier periods.
ENVELOPE_SIGMA_PERIODS = 0.5
#: How far inside the border the envelopes are measured, carrier periods: half a period measured
#: best on both the pure cosines and the 2 mm board (a whole period: 0.64 against 0.57 %).
INSET_PERIODS = 0.5


def _gaussian(n_half: int, sigma: float) -> np.ndarray:
    x = np.arange(-n_half, n_half + 1, dtype=np.float64)
    return np.exp(-0.5 * (x / sigma) ** 2)


class PatternContinuation:
    """An image continued by its own pattern into a larger frame (module docstring).

    Parameters
    ----------
    shape : (int, int)
        ``(rows, cols)`` of the images.
    freq : array_like (2, 2)
        The carriers, ``(f_row, f_col)`` cycles per pixel.

    Attributes
    ----------
    padded_shape : (int, int)
        The continued frame's shape (fast FFT sizes).
    offset : (int, int)
        Where the image sits in it: pixel ``(r, c)`` is ``(r + offset[0], c + offset[1])``.
    """

    def __init__(self, shape, freq):
        rows, cols = self.shape = (int(shape[0]), int(shape[1]))
        f = np.asarray(freq, np.float64)
        k = 2.0 * np.pi * f
        period = float(np.max(1.0 / np.hypot(f[:, 0], f[:, 1])))
        pad = int(math.ceil(CONTINUATION_PERIODS * period))
        R, C = self.padded_shape = (nice_fft_size(rows + 2 * pad), nice_fft_size(cols + 2 * pad))
        pr, pc = self.offset = ((R - rows) // 2, (C - cols) // 2)
        d0 = max(0, min(int(round(INSET_PERIODS * period)), (min(rows, cols) - 1) // 2))
        sigma = max(0.5, ENVELOPE_SIGMA_PERIODS * period)
        reach = int(math.ceil(4.0 * sigma))
        self._kernel = _gaussian(reach, sigma)
        # weights across the border of the rows (top, bottom) and columns (left, right) that measure
        # the lines: a Gaussian about the inset, only over pixels of the image
        self._n_rows = min(rows, d0 + reach + 1)
        self._n_cols = min(cols, d0 + reach + 1)
        w_r = np.exp(-0.5 * ((np.arange(self._n_rows) - d0) / sigma) ** 2)
        w_c = np.exp(-0.5 * ((np.arange(self._n_cols) - d0) / sigma) ** 2)
        r = np.arange(rows, dtype=np.float64)
        c = np.arange(cols, dtype=np.float64)
        # e^{-i k.r} split by axis, with the weights across the border folded in
        self._top = np.stack([w_r * np.exp(-1j * k[s, 0] * r[:self._n_rows]) for s in range(2)])
        self._bottom = np.stack([w_r[::-1] * np.exp(-1j * k[s, 0] * r[rows - self._n_rows:]) for s in range(2)])
        self._left = np.stack([w_c * np.exp(-1j * k[s, 1] * c[:self._n_cols]) for s in range(2)])
        self._right = np.stack([w_c[::-1] * np.exp(-1j * k[s, 1] * c[cols - self._n_cols:]) for s in range(2)])
        self._along_c = np.stack([np.exp(-1j * k[s, 1] * c) for s in range(2)])
        self._along_r = np.stack([np.exp(-1j * k[s, 0] * r) for s in range(2)])
        # the normalised window: its weight within the image at each point of a line
        self._norm_c = np.convolve(np.ones(cols), self._kernel, mode="same") * w_r.sum()
        self._norm_r = np.convolve(np.ones(rows), self._kernel, mode="same") * w_c.sum()
        # the pattern put back: e^{i k.r} over the padded frame (image coordinates), each pad pixel's
        # nearest point on the lines, and the outer taper
        rp = np.arange(R, dtype=np.float64) - pr
        cp = np.arange(C, dtype=np.float64) - pc
        self._up_r = np.stack([np.exp(1j * k[s, 0] * rp) for s in range(2)]).astype(np.complex64)
        self._up_c = np.stack([np.exp(1j * k[s, 1] * cp) for s in range(2)]).astype(np.complex64)
        self._near_c = np.clip(np.arange(C) - pc, d0, cols - 1 - d0)
        self._near_r = np.clip(np.arange(rows), d0, rows - 1 - d0)
        taper = min(pr, R - rows - pr, pc, C - cols - pc) / 2.0
        self._taper_r = tukey(R, taper)
        self._taper_c = tukey(C, taper)
        self._on = {}

    def _constants(self, xp):
        """The continuation's constants on the array module ``xp`` (made once per module)."""
        got = self._on.get(xp.__name__)
        if got is None:
            names = ("_kernel", "_top", "_bottom", "_left", "_right", "_along_c", "_along_r", "_norm_c", "_norm_r",
                     "_up_r", "_up_c", "_near_c", "_near_r", "_taper_r", "_taper_c")
            got = self._on[xp.__name__] = {n: xp.asarray(getattr(self, n)) for n in names}
        return got

    @staticmethod
    def _line(xp, a, along, norm, kernel):
        """Envelopes along the border lines, (..., 2, n): ``a`` the weighted sums across the
        border, moved to their carriers by ``along``, then the Gaussian along the line (zero
        beyond the image, normalised by ``norm``): a sum of shifted copies, the same on any module."""
        b = a * along
        reach = (kernel.shape[0] - 1) // 2
        n = b.shape[-1]
        padded = xp.zeros(b.shape[:-1] + (n + 2 * reach,), b.dtype)
        padded[..., reach:reach + n] = b
        acc = xp.zeros_like(b)
        for t in range(kernel.shape[0]):
            acc += kernel[t] * padded[..., t:t + n]
        return (acc / norm).astype(xp.complex64)

    def __call__(self, image, out=None, xp=np):
        """The continued image (float32 ``padded_shape``, its mean removed), written into ``out``
        if given; ``image`` may be a batch (..., rows, cols) and ``xp`` numpy or cupy."""
        rows, cols = self.shape
        R, C = self.padded_shape
        pr, pc = self.offset
        x = xp.asarray(image, dtype=xp.float32)
        if tuple(x.shape[-2:]) != self.shape:
            raise ValueError(f"image has shape {tuple(x.shape)}, the continuation was made for {self.shape}")
        k = self._constants(xp)
        lead = tuple(x.shape[:-2])
        mean = xp.mean(x, axis=(-2, -1), dtype=xp.float64).astype(xp.float32)
        if out is None:
            out = xp.empty(lead + (R, C), xp.float32)
        inner = out[..., pr:pr + rows, pc:pc + cols]
        xp.subtract(x, mean[..., None, None], out=inner)
        nr, nc = self._n_rows, self._n_cols
        kern = k["_kernel"]
        top = self._line(xp, xp.matmul(k["_top"], inner[..., :nr, :]), k["_along_c"], k["_norm_c"], kern)
        bottom = self._line(xp, xp.matmul(k["_bottom"], inner[..., rows - nr:, :]), k["_along_c"], k["_norm_c"], kern)
        left = self._line(xp, xp.swapaxes(xp.matmul(inner[..., :, :nc], k["_left"].T), -1, -2), k["_along_r"],
                          k["_norm_r"], kern)
        right = self._line(xp, xp.swapaxes(xp.matmul(inner[..., :, cols - nc:], k["_right"].T), -1, -2),
                           k["_along_r"], k["_norm_r"], kern)
        up_r, up_c, tr, tc = k["_up_r"], k["_up_c"], k["_taper_r"], k["_taper_c"]
        near_c, near_r = k["_near_c"], k["_near_r"]
        for line, rs in ((top, slice(0, pr)), (bottom, slice(pr + rows, R))):
            band = sum(up_r[s, rs, None] * (line[..., s, near_c] * up_c[s])[..., None, :] for s in range(2))
            out[..., rs, :] = 2.0 * band.real * tr[rs, None] * tc[None, :]
        rs = slice(pr, pr + rows)
        for line, cs in ((left, slice(0, pc)), (right, slice(pc + cols, C))):
            band = sum((line[..., s, near_r] * up_r[s, rs])[..., :, None] * up_c[s, cs][None, :] for s in range(2))
            out[..., rs, cs] = 2.0 * band.real * tc[None, cs]
        return out


class ContinuedSignals:
    """The carriers' analytic signals of continued images, and products of two of them on a
    chain's decimated grid (module docstring).

    Parameters
    ----------
    demod : Demodulator
        The chain's demodulator (its carriers, filter and decimated grid).
    reference : ndarray (rows, cols)
        The reference image.
    """

    def __init__(self, demod: Demodulator, reference):
        self.continuation = cont = PatternContinuation(demod.shape, demod.freq)
        carriers = Carriers(freq=np.asarray(demod.freq, np.float64), shape=cont.padded_shape,
                            contrast=np.ones(2), sharpness=np.ones(2))
        self.demod = Demodulator(cont(reference), carriers, planner=demod.planner, filter_radius=demod.filter_radius,
                                 filter_flat=demod.flat, filter_shape=demod.filter_shape, oversample=demod.oversample,
                                 border="none", local_carriers=False)
        d = self.demod
        from .fullgrid import spline_taps_matrix

        # the chain's samples on this grid, in its samples
        self._at = ((np.asarray(demod.rows_px) + cont.offset[0] - d.rows_px[0]) / (d.rows_px[1] - d.rows_px[0]),
                    (np.asarray(demod.cols_px) + cont.offset[1] - d.cols_px[0]) / (d.cols_px[1] - d.cols_px[0]))
        self._along_r, self._along_c = (spline_taps_matrix(at, n) for at, n in zip(self._at, d.window_shape))
        self.g0 = d.g0
        self._static = self._static_of = None

    def static_phase(self, band_limited) -> np.ndarray:
        """:meth:`phase_difference` of the reference against its band-limited copy
        ``band_limited`` (:func:`processing.refine.warp_reference`): what the right
        displacement leaves (computed once per copy)."""
        if self._static is None or self._static_of is not band_limited:
            self._static = self.phase_difference(self.g0, self.signals(band_limited))
            self._static_of = band_limited
        return self._static

    def spline_matrices(self):
        """``(A_rows, A_cols)``, dense float32 (n_chain, n_padded) per axis, the cubic B-spline
        of :meth:`phase_difference` with its prefilter folded in: ``A_rows @ p @ A_cols.T`` takes
        a product ``p`` to the chain's grid (the GPU chain's two matrix products)."""
        from .fullgrid import spline_matrix_at

        return tuple(spline_matrix_at(at, n) for at, n in zip(self._at, self.demod.window_shape))

    def signals(self, image) -> np.ndarray:
        """Analytic signals (2, m_rows, m_cols of the padded frame) of ``image`` continued."""
        d = self.demod
        return d.decimated_from_windows(d.frame_windows(write=lambda dst: self.continuation(image, out=dst)))

    def phase_difference(self, g_a, g_b) -> np.ndarray:
        """``arg(g_a conj(g_b))`` (2, the chain's decimated grid) of two :meth:`signals`: their
        product taken to the chain's samples by cubic B-spline, then its argument, float32."""
        from .fullgrid import spline_coefficients

        p = g_a * np.conj(g_b)
        out = np.empty((2,) + (self._along_r.shape[0], self._along_c.shape[0]), np.float32)
        for s in range(2):
            parts = []
            for part in (p[s].real, p[s].imag):
                coef = spline_coefficients(part, np.float64)
                parts.append(self._along_r @ (self._along_c @ coef.T).T)
            out[s] = np.arctan2(parts[1], parts[0])
        return out
