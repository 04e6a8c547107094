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
carrier periods long it halves what FD's band limit leaves (2.9 % -> 1.4 %
rms height error), but on bumps and dimples it is worse than FD (up to
2.4 % where FD has 0.4 %): with the true displacement the residual
``I - I0(r - u)`` of ray-traced frames stays 5x above the interpolation
floor of a pure translation, and the optimum of the image match is not the
true ``u`` (cause not found).  A fully global solve (bilinear nodes, exact
transpose, second-difference regulariser, CG) converged to that biased
optimum and was dropped.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["refine_displacement", "reference_gradients"]


def reference_gradients(reference):
    """``(dI0/drow, dI0/dcol)`` of the reference, float32 (central differences)."""
    ref = np.asarray(reference, np.float32)
    return (np.gradient(ref, axis=0).astype(np.float32), np.gradient(ref, axis=1).astype(np.float32))


def refine_displacement(reference, frame, u, valid, *, upsample, grid_shape, reference_gradient=None,
                        valid_px=None, iterations: int = 6, window: float = 1.0, step: float = 1.0,
                        interpolation=cv2.INTER_CUBIC):
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

    for _ in range(iterations):
        map_r = upsample(-u[0])
        map_c = upsample(-u[1])
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
        du_r = -(ncc * br - nrc * bc) / det
        du_c = -(nrr * bc - nrc * br) / det
        u[0] += np.where(ok, np.float32(step) * du_r, 0.0).astype(np.float32)
        u[1] += np.where(ok, np.float32(step) * du_c, 0.0).astype(np.float32)
    return u
