"""Alignment metrics of a live frame *before* any reference exists.

While the physicist sets up the pattern and theta there is no reference yet,
so :meth:`processing.Reconstructor.alignment` cannot be used. This falls back
on :func:`processing.carriers.find_carriers` applied to the live frame itself
(carrier periods, rotation, theta from the pattern's aspect, peak sharpness as
focus metric) plus a display spectrum. Once a reference exists the worker
uses the Reconstructor's own ``alignment``/``spectrum``.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

__all__ = ["frame_alignment", "display_spectrum", "modulation_map"]


def display_spectrum(frame: np.ndarray, *, size: int = 256, max_freq: float = 0.25) -> dict:
    """Centred log-magnitude spectrum of ``frame`` for display.

    Parameters
    ----------
    frame : ndarray, shape (rows, cols)
        Raw frame.
    size : int
        At most about this many samples per axis (block maxima keep the peaks).
    max_freq : float
        Show frequencies up to this many cycles per pixel (0.25: periods >= 4 px).

    Returns
    -------
    dict
        ``log_magnitude`` float32 (n_rows, n_cols): log10 |FFT| (Hann window);
        ``freq_x`` (n_cols,), ``freq_y`` (n_rows,): cycles per pixel, increasing
        (see :func:`processing.carriers.display_spectrum`).
    """
    from processing.carriers import display_spectrum as _display

    img = np.asarray(frame, np.float32)
    rows, cols = img.shape
    win = np.outer(np.hanning(rows).astype(np.float32), np.hanning(cols).astype(np.float32))
    half = np.abs(np.fft.rfft2((img - img.mean()) * win))
    return _display(half, cols, size=size, max_freq=max_freq)


def modulation_map(frame: np.ndarray, *, window_px: int = 32, step_px: int = 16):
    """Local pattern contrast: local standard deviation over local mean.

    For a square wave between ``m - a`` and ``m + a`` this is the Michelson
    contrast ``a / m`` when the window spans whole pattern periods.

    Parameters
    ----------
    frame : ndarray, shape (rows, cols)
        Raw frame.
    window_px : int
        Side of the averaging window in pixels (a few pattern periods).
    step_px : int
        Sampling step of the returned map in pixels.

    Returns
    -------
    (ndarray, ndarray, ndarray)
        Map float32 (n_rows, n_cols), 0 (no pattern) .. about 1 (full-scale
        black and white squares), and the pixel rows (n_rows,) and columns
        (n_cols,) where it is sampled.
    """
    import cv2

    img = np.asarray(frame, np.float32)
    k = int(max(3, window_px))
    mean = cv2.blur(img, (k, k), borderType=cv2.BORDER_REFLECT)
    mean2 = cv2.blur(img * img, (k, k), borderType=cv2.BORDER_REFLECT)
    std = np.sqrt(np.maximum(mean2 - mean * mean, 0.0))
    rows = np.arange(step_px // 2, img.shape[0], step_px)
    cols = np.arange(step_px // 2, img.shape[1], step_px)
    mod = std[np.ix_(rows, cols)] / np.maximum(mean[np.ix_(rows, cols)], 1e-6)
    return mod.astype(np.float32), rows, cols


def frame_alignment(frame: np.ndarray, theta_configured_deg: Optional[float] = None):
    """``(alignment_dict, spectrum_dict)`` of a live frame without reference.

    The dict has ``periods_px`` (2,), ``rotation_deg``, ``theta_estimate_deg``,
    ``theta_configured_deg``, ``focus`` (carrier peak sharpness, 0..1), ``modulation``
    (map, see :func:`modulation_map`) and ``contrast`` (its median) -- or ``error``
    with the message of :class:`processing.errors.NoCarrierError`.
    """
    from processing.carriers import find_carriers

    spectrum = display_spectrum(frame)
    try:
        c = find_carriers(frame)
    except ValueError as exc:  # NoCarrierError
        mod, rows, cols = modulation_map(frame)
        return {"error": str(exc), "modulation": mod, "modulation_rows_px": rows,
                "modulation_cols_px": cols}, spectrum
    # a window of two periods along both image axes averages the squares out
    axis_period = float(np.max(c.periods_px)) * np.sqrt(2.0)
    window = int(round(2 * axis_period))
    mod, rows, cols = modulation_map(frame, window_px=window, step_px=max(4, window // 4))
    carriers = [(float(f[1]), float(f[0])) for f in np.asarray(c.freq)]  # (f_col, f_row), f_col >= 0
    spectrum["carriers"] = carriers + [(-fx, -fy) for fx, fy in carriers]
    a = {
        "periods_px": np.asarray(c.periods_px, float),
        "rotation_deg": float(c.rotation_deg),
        "theta_estimate_deg": float(c.theta_deg),
        "focus": float(np.min(c.sharpness)),
        "modulation": mod,
        "modulation_rows_px": rows,
        "modulation_cols_px": cols,
        "contrast": float(np.median(mod)),
    }
    if theta_configured_deg is not None:
        a["theta_configured_deg"] = float(theta_configured_deg)
    return a, spectrum
