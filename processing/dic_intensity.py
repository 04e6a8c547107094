"""The frame's smooth gain and offset against the warped reference, for image matching (:mod:`processing.dic`).

The frame need not be exposed as the reference: its gain and offset fields
(:func:`intensity_cells`, DIC's ZNSSD normalisation on cells of about
:data:`INTENSITY_CELL_PX`) are fitted against the reference warped by FD's
start, and :func:`normalised_frame` divides the frame by them before the
blur (issue 18: 0.5x brightness 12.7 % -> 0.81 %).

The cells' moments are one compiled pass over the pixels
(:func:`processing.dic_kernels.cell_moments`, OpenCV's area means to float
rounding), and the fields reach the pixels inside the division's own pass
(:func:`processing.dic_kernels.normalise_rows`, OpenCV's bilinear resize to
float rounding): at 1024^2 on one thread the normalisation with its blur went
from 8.7-9.0 ms (five area resizes, two products, two full-size resizes,
three passes) to 6.0 ms (8 Dec 2026).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

__all__ = ["INTENSITY_CELL_PX", "MIN_GAIN", "area_taps", "linear_taps", "intensity_cells", "intensity_fit",
           "normalised_frame"]

#: Cell of the frame's gain and offset fields (pixels, :func:`intensity_cells`).
INTENSITY_CELL_PX = 16

#: Smallest gain the frame is divided by, as a fraction of its median gain.
MIN_GAIN = 0.1


def area_taps(n_px: int, n_cells: int):
    """``(index, weight_lo, weight_hi)`` of each of ``n_px`` pixels along one axis in OpenCV's area
    resize (``cv2.INTER_AREA``) to ``n_cells`` cells: the pixel's share of cell ``index`` and of cell
    ``index + 1`` (the overlap of ``[p, p + 1)`` with the cell's ``n_px / n_cells`` pixels, over that
    width; float64, 0 where the pixel lies in one cell)."""
    scale = n_px / n_cells
    p = np.arange(n_px, dtype=np.float64)
    index = np.minimum((p // scale).astype(np.int64), n_cells - 1)
    edge = (index + 1) * scale  # the cell's upper edge
    lo = np.minimum(edge - p, 1.0)
    hi = np.where(index + 1 < n_cells, 1.0 - lo, 0.0)
    return index, lo / scale, hi / scale


def linear_taps(n_px: int, n_cells: int):
    """``(index, weight)`` of each of ``n_px`` pixels along one axis in OpenCV's bilinear resize
    (``cv2.INTER_LINEAR``) of ``n_cells`` cells to ``n_px``: the pixel takes ``1 - weight`` of cell
    ``index`` and ``weight`` of cell ``index + 1`` (cell centres by :func:`processing.fullgrid.pixel_centres`,
    clamped at the outer ones; float32 weights)."""
    from .fullgrid import pixel_centres

    at = pixel_centres(n_px, n_cells)
    index = np.floor(at).astype(np.int64)
    weight = at - index
    low = index < 0
    index[low], weight[low] = 0, 0.0
    high = index >= n_cells - 1
    index[high], weight[high] = n_cells - 1, 0.0
    return index, weight.astype(np.float32)


def intensity_cells(frame, warped, weight=None, *, cell_px: float = INTENSITY_CELL_PX):
    """Smooth gain and offset fields with ``frame ~ gain * warped + offset``.

    The normalisation of ZNSSD in DIC, locally: ``gain = std(I) / std(W)``,
    ``offset = mean(I) - gain mean(W)`` over windows of about ``3 cell_px``
    (several pattern periods, so the pattern's own mean and variance are
    steady there).  The ratio of standard deviations, not the regression
    slope ``cov(I, W) / var(W)``: where the warp is still off (the first
    steps, a fast-moving region) the slope shrinks towards 0 with the
    correlation, and dividing the frame by it blew the residual up (3x on a
    dimple of 8 px) and the steps with it.  The moments ``sum w``,
    ``sum w I``, ``sum w W``, ``sum w I^2``, ``sum w W^2`` are averaged over
    cells of about ``cell_px`` pixels, then over 3 x 3 cells (:func:`intensity_fit`
    and :func:`normalised_frame` interpolate each cell's fit bilinearly to every
    pixel).  Where a cell has no
    weight or no contrast in ``warped`` its gain and offset are the whole
    frame's.

    Parameters
    ----------
    frame, warped : ndarray float32 (rows, cols)
        The (blurred) frame and the (blurred) warped reference.
    weight : ndarray float32 (rows, cols) or None
        Pixel weights (None: all 1).
    cell_px : float

    Returns
    -------
    gain, offset : ndarray float32 (cell rows, cell cols)
        Cells of ``rows / cell_px`` x ``cols / cell_px`` (rounded) spanning the frame.
    """
    from .dic_kernels import cell_moments

    rows, cols = frame.shape
    m_r = max(1, int(round(rows / cell_px)))
    m_c = max(1, int(round(cols / cell_px)))
    # the cell means of w, w I, w W, w I^2, w W^2 (OpenCV's area resize of each, in one compiled pass)
    moments = np.zeros((5, m_r, m_c))
    cell_moments(np.ascontiguousarray(frame, np.float32), np.ascontiguousarray(warped, np.float32),
                 np.empty((0, 0), np.float32) if weight is None else np.ascontiguousarray(weight, np.float32),
                 *area_taps(rows, m_r), *area_taps(cols, m_c), moments)
    if weight is None:
        moments[0] = 1.0
    moments = list(moments)
    total = [float(m.sum()) for m in moments]
    if m_r >= 3 and m_c >= 3:
        moments = [cv2.blur(m, (3, 3), borderType=cv2.BORDER_REFLECT) for m in moments]
    n, si, sw, sii, sww = moments
    var_i = n * sii - si * si  # n^2 times the variances
    var_w = n * sww - sw * sw
    tn, ti, tw, tii, tww = total
    t_var_i = tn * tii - ti * ti
    t_var_w = tn * tww - tw * tw
    g_all = math.sqrt(t_var_i / t_var_w) if t_var_w > 0 and t_var_i > 0 else 1.0
    o_all = (ti - g_all * tw) / tn if tn > 0 else 0.0
    # a cell needs weight and contrast: at least a tenth of the frame's mean weight
    # per cell and a tenth of the frame's variance of the warped reference
    if tn > 0:
        ok = (n > 0.1 * tn / n.size) & (var_w > 0.1 * (t_var_w / tn ** 2) * n ** 2) & (var_i > 0)
    else:
        ok = np.zeros_like(n, bool)
    gain = np.where(ok, np.sqrt(np.where(ok, var_i, 1.0) / np.where(ok, var_w, 1.0)), g_all)
    offset = np.where(ok, (si - gain * sw) / np.where(ok, n, 1.0), o_all)
    return gain.astype(np.float32), offset.astype(np.float32)


def intensity_fit(frame, warped, weight=None, *, cell_px: float = INTENSITY_CELL_PX):
    """:func:`intensity_cells` interpolated bilinearly to every pixel (``cv2.resize``):
    ``(gain, offset)``, each float32 (rows, cols) like ``frame``."""
    rows, cols = np.shape(frame)
    cells = intensity_cells(frame, warped, weight, cell_px=cell_px)
    gain, offset = (cv2.resize(x, (cols, rows), interpolation=cv2.INTER_LINEAR) for x in cells)
    return gain, offset


def normalised_frame(raw, blurred, warped, weight, cell_px, blur_px):
    """The frame brought to the reference's intensities, ``G*((I - b) / a)``
    (:func:`intensity_cells` of the blurred frame against the blurred warped
    reference, bilinear to every pixel; the gain floored at :data:`MIN_GAIN`
    of the cells' median): every pixel then weighs the same whatever its
    gain.  Divided before the blur: ``G*(a I0) = a G*I0 + sigma^2 grad a .
    grad I0 + ...``, so dividing the blurred frame would leave a displacement
    of ``sigma^2 grad a / a``."""
    from .dic_kernels import normalise_rows

    gain, offset = intensity_cells(blurred, warped, weight, cell_px=cell_px)
    floor = MIN_GAIN * float(np.median(gain))
    raw = np.ascontiguousarray(raw, np.float32)
    rows, cols = raw.shape
    img = np.empty_like(raw)
    normalise_rows(raw, np.stack([gain, offset]), np.float32(floor if floor > 0 else 1e-30),
                   *linear_taps(rows, gain.shape[0]), *linear_taps(cols, gain.shape[1]), img)
    if blur_px:
        img = cv2.GaussianBlur(img, (0, 0), blur_px)
    return img
