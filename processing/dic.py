"""Image-domain refinement of the displacement (DIC-style Gauss-Newton, windowed).

Fourier demodulation sees the frame through a band around each carrier;
where the surface has features a few carrier periods wide the phase
modulation spills out of that band and FD's displacement comes out smoothed
(docs/processing.md, section 6).  This module matches images instead of
phases: starting from FD's displacement ``u`` (pixels, ``I(r) = I0(r - u(r))``,
on the Reconstructor's decimated grid) each Gauss-Newton step warps the
reference by ``u`` (``u`` interpolated to every pixel by the caller's resize,
the reference by cubic interpolation, its gradient ``g`` with it) and solves,
for every node of the grid,

    sum_r w(r) g g^T  du  =  - sum_r w(r) g e,      e = I - I0(r - u)

with ``w`` a window around the node (the node's cell, then a Gaussian of
``window`` nodes): Lucas-Kanade with window deformation, on every node at
once.  The update of a smooth field is not biased by the window (it vanishes
when the warped reference matches the frame), so the window acts only on the
step, not on the result.  ``w`` is zero on pixels the Reconstructor marked
invalid.

Experimental (docs/processing.md, section 6): on ray-traced waves 3-6
carrier periods long it more than halves what FD's band limit leaves (2.9 %
-> 1.3 % rms height error), is level with FD on most other cases and worse
on a sharp board (0.39 -> 0.80 %) and a narrow 12-bit bump (0.37 -> 0.61 %).
The iteration converges slowly on waves short along the (compressed) rows
and diverges with smaller windows; a global solve (CG on the same
equations) was tried with OpenCV's biased cubic warp only.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["refine_displacement", "reference_gradients"]


def reference_gradients(reference):
    """``(dI0/drow, dI0/dcol)`` of the reference, float32 (central differences)."""
    ref = np.asarray(reference, np.float32)
    return (np.gradient(ref, axis=0).astype(np.float32), np.gradient(ref, axis=1).astype(np.float32))


#: Refinement of the grid the reference is interpolated from (see :func:`fine_reference`).
FINE = 2


def fine_reference(reference):
    """The reference, cubic-spline interpolated to a grid ``FINE`` times finer
    (sample ``i`` at pixel ``i / FINE``), float32.

    Warping it with linear interpolation is as accurate as warping the
    reference with the cubic spline itself, at OpenCV's speed: measured on a
    ray-traced 2 mm board shifted by 0.25-0.75 px, the shift found by image
    matching is off by 0.005 px (cv2 cubic on the reference: 0.035 px, cv2
    linear 0.009 px; the cubic kernel's error and the 1/32 px position
    quantisation of cv2.remap are what bias image matching towards whole
    pixels).
    """
    from scipy import ndimage

    ref = np.asarray(reference, np.float64)
    r = np.arange(FINE * ref.shape[0]) / FINE
    c = np.arange(FINE * ref.shape[1]) / FINE
    coef = ndimage.spline_filter(ref, order=3, mode="mirror")
    out = np.empty((r.size, c.size), np.float32)
    # rows in blocks: the coordinate arrays stay small
    step = max(1, 2_000_000 // max(c.size, 1))
    for i in range(0, r.size, step):
        rr, cc = np.meshgrid(r[i:i + step], c, indexing="ij")
        out[i:i + step] = ndimage.map_coordinates(coef, [rr, cc], order=3, prefilter=False, mode="mirror")
    return out


def refine_displacement(reference, frame, u, valid, *, upsample, grid_shape, reference_gradient=None,
                        valid_px=None, iterations: int = 6, window: float = 1.0, step: float = 1.0,
                        interpolation=cv2.INTER_CUBIC, fine_reference=None):
    """Windowed Gauss-Newton image matching of ``frame`` against the warped ``reference``.

    Parameters
    ----------
    reference, frame : ndarray float32 (rows, cols)
    u : ndarray (2, n_rows, n_cols)
        Starting displacement on the grid (pixels, NaN-free: invalid samples
        carry their nearest valid neighbour's value).
    valid : ndarray bool (n_rows, n_cols)
        Samples to refine; the others keep their value.
    upsample : callable
        ``upsample(field) -> (rows, cols)`` float32 (the Reconstructor's
        Lanczos resize: the grid's samples sit at cv2.resize's pixel centres).
    grid_shape : (int, int)
        ``(n_rows, n_cols)``.
    reference_gradient : (ndarray, ndarray) or None
        :func:`reference_gradients` of the reference (computed if None).
    valid_px : ndarray bool (rows, cols) or None
        Pixels whose residual counts (None: all).
    iterations : int
        Gauss-Newton steps (one warp each).
    window : float
        Gaussian window on the grid, in grid samples (after the cell average).
    step : float
        Fraction of each Gauss-Newton step taken.

    Returns
    -------
    ndarray float32 (2, n_rows, n_cols)
    """
    ref = np.asarray(reference, np.float32)
    img = np.asarray(frame, np.float32)
    if reference_gradient is None:
        reference_gradient = reference_gradients(ref)
    g0r, g0c = reference_gradient
    u = np.array(u, dtype=np.float32, copy=True)
    valid = np.asarray(valid, bool)
    m_r, m_c = grid_shape
    w = None if valid_px is None or bool(np.all(valid_px)) else np.asarray(valid_px, np.float32)
    flags = interpolation | cv2.WARP_RELATIVE_MAP
    lin = cv2.INTER_LINEAR | cv2.WARP_RELATIVE_MAP
    border = cv2.BORDER_REFLECT

    def down(x):
        s = cv2.resize(x, (m_c, m_r), interpolation=cv2.INTER_AREA)
        if window > 0:
            s = cv2.GaussianBlur(s, (0, 0), window, borderType=cv2.BORDER_REFLECT)
        return s

    fine = fine_reference
    if fine is not None:
        rows_px = np.arange(ref.shape[0], dtype=np.float32)[:, None]
        cols_px = np.arange(ref.shape[1], dtype=np.float32)[None, :]
    for _ in range(iterations):
        map_r = upsample(-u[0])
        map_c = upsample(-u[1])
        if fine is not None:
            # the reference, spline-interpolated to a grid FINE x finer, linearly
            # interpolated there: absolute maps in fine-grid pixels
            map_c_abs = (map_c + cols_px) * np.float32(FINE)
            map_r_abs = (map_r + rows_px) * np.float32(FINE)
            warped = cv2.remap(fine, map_c_abs, map_r_abs, cv2.INTER_LINEAR, borderMode=border)
        else:
            warped = cv2.remap(ref, map_c, map_r, flags, borderMode=border)
        gr = cv2.remap(g0r, map_c, map_r, lin, borderMode=border)
        gc = cv2.remap(g0c, map_c, map_r, lin, borderMode=border)
        e = img - warped
        if w is not None:
            gr *= w
            gc *= w
        nrr, nrc, ncc = down(gr * gr), down(gr * gc), down(gc * gc)
        br, bc = down(gr * e), down(gc * e)
        det = nrr * ncc - nrc * nrc
        ok = valid & (det > 1e-6 * np.maximum(nrr * ncc, 1e-30))
        det = np.where(ok, det, 1.0)

        def prec(vr, vc):
            return (np.where(ok, (ncc * vr - nrc * vc) / det, 0.0).astype(np.float32),
                    np.where(ok, (nrr * vc - nrc * vr) / det, 0.0).astype(np.float32))

        du_r, du_c = prec(-br, -bc)
        u[0] += np.where(ok, np.float32(step) * du_r, 0.0).astype(np.float32)
        u[1] += np.where(ok, np.float32(step) * du_c, 0.0).astype(np.float32)
    return u
