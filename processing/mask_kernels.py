"""Compiled fold test (Numba) of the quality mask (:func:`processing.mask.fold_ok`).

:func:`fold_determinant` is ``det(I - grad u)`` on the decimated grid as
``np.gradient`` and NumPy's expression give it (each difference in the
array's type, divided in float64 by the spacing, stored in the array's type;
one-sided at the ends), in one call instead of about fifteen NumPy passes (a
test compares them, to the bit); :func:`largest_steps` the largest neighbour
difference of ``u`` along each axis, the bound that spares the determinant on
smooth frames.  On the app's 1024^2 tank scene (270^2 grid, strained by the
caustics) the NumPy test took 1.1 ms a frame.
Compiled once per checkout and cached in ``__pycache__``.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["fold_determinant", "largest_steps"]


@numba.njit(nogil=True, cache=True)
def _gradient_into(f, axis, step, out):  # pragma: no cover - compiled
    """``np.gradient(f, ...)`` along ``axis`` (edge order 1) into ``out`` (``f``'s type): each difference in
    ``f``'s type, divided in float64 by ``step`` (twice it inside), stored in ``out``'s type."""
    n, m = f.shape
    two_step = 2.0 * step
    if axis == 0:
        for i in range(1, n - 1):
            for j in range(m):
                out[i, j] = np.float64(f[i + 1, j] - f[i - 1, j]) / two_step
        for j in range(m):
            out[0, j] = np.float64(f[1, j] - f[0, j]) / step
            out[n - 1, j] = np.float64(f[n - 1, j] - f[n - 2, j]) / step
        return
    for i in range(n):
        for j in range(1, m - 1):
            out[i, j] = np.float64(f[i, j + 1] - f[i, j - 1]) / two_step
        out[i, 0] = np.float64(f[i, 1] - f[i, 0]) / step
        out[i, m - 1] = np.float64(f[i, m - 1] - f[i, m - 2]) / step


@numba.njit(nogil=True, cache=True)
def fold_determinant(u, dr, dc, one, out):  # pragma: no cover - compiled
    """``out = (1 - dur/dr) (1 - duc/dc) - (dur/dc) (duc/dr)`` ((rows, cols), ``u``'s type, ``one`` 1 in
    it) of the displacement ``u`` ((2, rows, cols), finite; px), ``dr``, ``dc`` the grid's spacing (px),
    as ``np.gradient`` and NumPy's expression in ``u``'s type give it."""
    _, n, m = u.shape
    rr, rc, cr, cc = np.empty_like(out), np.empty_like(out), np.empty_like(out), np.empty_like(out)
    _gradient_into(u[0], 0, dr, rr)
    _gradient_into(u[0], 1, dc, rc)
    _gradient_into(u[1], 0, dr, cr)
    _gradient_into(u[1], 1, dc, cc)
    for i in range(n):
        for j in range(m):
            out[i, j] = (one - rr[i, j]) * (one - cc[i, j]) - rc[i, j] * cr[i, j]


@numba.njit(nogil=True, cache=True)
def largest_steps(u):  # pragma: no cover - compiled
    """``(max |u[k, i + 1, j] - u[k, i, j]|, max |u[k, i, j + 1] - u[k, i, j]|)`` over both components
    (differences in ``u``'s type, as ``np.abs(np.diff(u, axis=1)).max()`` and ``axis=2``; 0 for none)."""
    _, n, m = u.shape
    along_rows = u[0, 0, 0] - u[0, 0, 0]  # 0 in u's type
    along_cols = along_rows
    for k in range(2):
        f = u[k]
        for i in range(n):
            for j in range(m):
                if i + 1 < n:
                    along_rows = max(along_rows, abs(f[i + 1, j] - f[i, j]))
                if j + 1 < m:
                    along_cols = max(along_cols, abs(f[i, j + 1] - f[i, j]))
    return along_rows, along_cols
