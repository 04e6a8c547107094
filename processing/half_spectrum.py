"""Reading an rfft2 half spectrum: where a full DFT's bin sits in it
(:func:`half_spectrum_index`), which bins the display spectrum of the Alignment
tab shows (:func:`display_bins`), and that display from it, reading only the bins
shown (:func:`display_spectrum_of`).  Shared by :mod:`processing.alignment` (the
live alignment metrics), :mod:`processing.live_view` (the live spectrum) and
:func:`processing.carrier_peaks.frame_spectrum` (the spectrum before a reference)."""

from __future__ import annotations

import functools

import numpy as np

__all__ = ["half_spectrum_index", "display_bins", "display_spectrum_of"]


def display_bins(shape, size: int, max_freq: float) -> tuple:
    """The centred (fftshift) spectrum's bins a display of ``size`` shows:
    ``(freq_y, freq_x, keep_rows, keep_cols, step_rows, step_cols)``, the
    frequencies (cycles/px) of every row and column, the rows and columns
    within ``max_freq`` cut to whole blocks of ``step`` bins (block maxima)."""
    rows, cols = shape
    fy = np.fft.fftshift(np.fft.fftfreq(rows))
    fx = np.fft.fftshift(np.fft.fftfreq(cols))
    keep_r = np.flatnonzero(np.abs(fy) <= max_freq)
    keep_c = np.flatnonzero(np.abs(fx) <= max_freq)
    step_r = max(1, len(keep_r) // size)
    step_c = max(1, len(keep_c) // size)
    keep_r = keep_r[: len(keep_r) // step_r * step_r]
    keep_c = keep_c[: len(keep_c) // step_c * step_c]
    return fy, fx, keep_r, keep_c, step_r, step_c


def half_spectrum_index(shape, kr, kc) -> tuple:
    """Where the full 2-D DFT's bins ``(kr, kc)`` (any integers) sit in an rfft2 half spectrum.

    Returns
    -------
    (flat_index, conjugate)
        Flat indices into the ``(rows, cols // 2 + 1)`` half spectrum and a
        boolean array: True where the bin is the conjugate of the stored one
        (columns beyond ``cols // 2``, by the symmetry of a real image).
    """
    rows, cols = shape
    kr = np.asarray(kr) % rows
    kc = np.asarray(kc) % cols
    conj = kc > cols // 2
    r = np.where(conj, (-kr) % rows, kr)
    c = np.where(conj, cols - kc, kc)
    r, c, conj = np.broadcast_arrays(r, c, conj)
    return r * (cols // 2 + 1) + c, conj


@functools.lru_cache(maxsize=8)
def _display_layout(shape, size: int, max_freq: float) -> tuple:
    """Where :func:`display_spectrum_of` reads: the half-spectrum rows and
    columns shown, and for every shown bin, block by block, its place among them."""
    rows, cols = shape
    fy, fx, keep_r, keep_c, step_r, step_c = display_bins(shape, size, max_freq)
    nr, nc = len(keep_r) // step_r, len(keep_c) // step_c
    # shifted index i holds the unshifted bin (i - n // 2) mod n
    kr, kc = (keep_r - rows // 2)[:, None], (keep_c - cols // 2)[None, :]
    idx, _ = half_spectrum_index(shape, kr, kc)
    h = cols // 2 + 1
    r_half, c_half = np.divmod(idx, h)
    # read only the rows and leading columns of the half spectrum that hold shown bins
    r_sel = np.unique(r_half)
    n_c = int(c_half.max()) + 1
    local = np.searchsorted(r_sel, r_half) * n_c + c_half
    # (step_r * step_c, nr * nc): the blocks' members along the first axis
    local = local.reshape(nr, step_r, nc, step_c).transpose(1, 3, 0, 2).reshape(step_r * step_c, nr * nc)
    freq_x = fx[keep_c].reshape(nc, step_c).mean(axis=1)
    freq_y = fy[keep_r].reshape(nr, step_r).mean(axis=1)
    return r_sel, n_c, local, (nr, nc), freq_x, freq_y


def display_spectrum_of(half_spectrum, shape, *, leak=None, size: int = 256, max_freq: float = 0.25) -> dict:
    """:func:`processing.carrier_peaks.display_spectrum` of ``|half_spectrum - leak|``, reading only the shown bins.

    Parameters
    ----------
    half_spectrum : ndarray, complex (rows, cols // 2 + 1)
    shape : (rows, cols)
    leak : (mean, window_spectrum) or None
        Subtract ``mean * window_spectrum`` (the frame's mean through the
        border window: its peak at DC) first.

    Returns
    -------
    dict
        The same ``log_magnitude``, ``freq_x``, ``freq_y`` as ``display_spectrum``.
    """
    r_sel, n_c, local, (nr, nc), freq_x, freq_y = _display_layout(tuple(shape), int(size), float(max_freq))
    vals = np.asarray(half_spectrum)[r_sel, :n_c]
    if leak is not None and leak[0]:
        vals = vals - np.complex64(leak[0]) * np.asarray(leak[1])[r_sel, :n_c]
    mag = np.abs(vals).astype(np.float32, copy=False).reshape(-1)
    sub = mag[local].max(axis=0).reshape(nr, nc)
    out = np.log10(sub + 1e-6 * float(sub.max() or 1.0)).astype(np.float32)
    return {"log_magnitude": out, "freq_x": freq_x.copy(), "freq_y": freq_y.copy()}
