"""Compiled parts (Numba) of the masked height solve (:func:`processing.height_masked.solve_masked`):
its operator and its data on the edges.

:func:`masked_normal_apply` is ``v * A^T W A f``, the weighted normal operator
the conjugate gradients apply once an iteration, in two passes over the grid:
the edges' values ``W A f`` into two scratch arrays, then each sample's
transposed divergence gathered from its four edges.  As NumPy it was about
fourteen full-grid passes (``A`` by differences, the weights,
:func:`processing.height_masked.apply_AT`, the mask): on the live
270 x 270 grid of a 1024^2 frame 0.24 -> 0.10 ms an iteration.  Every sum
is formed in the NumPy operations' own order and precision (float32 edges,
the finite camera distance's terms in float64 rounded to float32), so the
result is the same to the bit; a test compares them.

:func:`edge_data_into` is :func:`processing.height_masked.edge_data`, the
fourth-order cell averages of ``g / n`` on the edges, in one call where NumPy
took about twenty passes (1.6 -> 0.3 ms at 270^2), the same bits.  Compiled
once per checkout and cached in ``__pycache__``.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["masked_normal_apply", "edge_data_into"]


@numba.njit(nogil=True, cache=True)
def masked_normal_apply(f, wc, wr, vf, dc, dr, dk_c, dk_r, ec, er, out):  # pragma: no cover - compiled
    """``out = vf * A^T (w * A f)`` (float32, (rows, cols)).

    ``wc`` (rows, cols - 1) and ``wr`` (rows - 1, cols): the edge weights (0 or 1);
    ``vf`` (rows, cols): the sample weights; ``dc``, ``dr``: the sample spacing
    along the columns and rows (float32, px); ``dk_c`` (rows, cols - 1) and ``dk_r``
    (rows - 1, cols): the finite camera distance's edge terms (float64), or arrays
    of size 0 for a telecentric camera; ``ec`` (rows, cols + 1) and ``er``
    (rows + 1, cols): scratch whose outer columns / rows are 0 (the edges beyond
    the grid: adding their 0 changes no sum, and no inner loop branches)."""
    n, m = f.shape
    half = 0.5
    for i in range(n):
        fr, e, w = f[i], ec[i, 1:m], wc[i]
        if dk_c.size:
            k = dk_c[i]
            for j in range(m - 1):
                a = (fr[j + 1] - fr[j]) / dc + np.float32(k[j] * half * np.float64(fr[j + 1] + fr[j]))
                e[j] = a * w[j]
        else:
            for j in range(m - 1):
                e[j] = (fr[j + 1] - fr[j]) / dc * w[j]
    for i in range(n - 1):
        f0, f1, e, w = f[i], f[i + 1], er[i + 1], wr[i]
        if dk_r.size:
            k = dk_r[i]
            for j in range(m):
                a = (f1[j] - f0[j]) / dr + np.float32(k[j] * half * np.float64(f1[j] + f0[j]))
                e[j] = a * w[j]
        else:
            for j in range(m):
                e[j] = (f1[j] - f0[j]) / dr * w[j]
    for i in range(n):
        # the transposed divergence in apply_AT's order: the edge right of the sample, left, below, above
        right, left, below, above, v, o = ec[i, 1:m + 1], ec[i, 0:m], er[i + 1], er[i], vf[i], out[i]
        for j in range(m):
            o[j] = (((np.float32(0.0) - right[j] / dc) + left[j] / dc) - below[j] / dr) + above[j] / dr
        if dk_c.size:
            # then the finite distance's half edge terms, in the same order (0 beyond the grid)
            for j in range(m):
                t = o[j]
                if j < m - 1:
                    t += np.float32(half * dk_c[i, j] * np.float64(right[j]))
                if j > 0:
                    t += np.float32(half * dk_c[i, j - 1] * np.float64(left[j]))
                if i < n - 1:
                    t += np.float32(half * dk_r[i, j] * np.float64(below[j]))
                if i > 0:
                    t += np.float32(half * dk_r[i - 1, j] * np.float64(above[j]))
                o[j] = t
        for j in range(m):
            o[j] *= v[j]


@numba.njit(nogil=True, cache=True, inline="always")
def _edge_mean(g0, g1, gm, gp, ok, corrected):  # pragma: no cover - compiled
    """The fourth-order mean of an edge between samples ``g0``, ``g1`` (``gm`` before, ``gp`` after):
    the trapezoid, plus ``(-gm + g0 + g1 - gp) / 24`` where ``corrected`` (the edge is not an end one)
    and ``ok`` (its four samples usable), else plus 0, as :func:`processing.height_kernels.cell_average`."""
    out = 0.5 * (g0 + g1)
    if corrected:
        out += (((-gm + g0) + g1) - gp) / 24.0 if ok else 0.0
    return out


@numba.njit(nogil=True, cache=True)
def edge_data_into(gr, gc, null, ok, er, ec):  # pragma: no cover - compiled
    """:func:`processing.height_masked.edge_data` (float64): the cell averages of ``gr / null`` on the
    row edges into ``er`` (rows - 1, cols) and of ``gc / null`` on the column edges into ``ec``
    (rows, cols - 1); ``ok`` (rows, cols) bool, the samples the wide stencil may use, or of size 0
    (all). Each sum in the NumPy expressions' order (the same bits; a test compares them)."""
    n, m = gr.shape
    every = ok.size == 0
    G_r = gr / null
    G_c = gc / null
    for e in range(n - 1):  # the edge between rows e and e + 1
        corrected = n >= 4 and 1 <= e <= n - 3
        a, b, lo, hi = G_r[e], G_r[e + 1], G_r[max(e - 1, 0)], G_r[min(e + 2, n - 1)]
        for j in range(m):
            good = corrected and (every or (ok[e - 1, j] and ok[e, j] and ok[e + 1, j] and ok[e + 2, j]))
            er[e, j] = _edge_mean(a[j], b[j], lo[j], hi[j], good, corrected)
    for i in range(n):
        row = G_c[i]
        for e in range(m - 1):  # the edge between columns e and e + 1
            corrected = m >= 4 and 1 <= e <= m - 3
            good = corrected and (every or (ok[i, e - 1] and ok[i, e] and ok[i, e + 1] and ok[i, e + 2]))
            ec[i, e] = _edge_mean(row[e], row[e + 1], row[max(e - 1, 0)], row[min(e + 2, m - 1)], good, corrected)
