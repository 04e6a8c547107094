"""The pixel pass of each Gauss-Newton step of :func:`processing.dic.refine_height`, compiled (Numba).

From the blurred warped reference ``W``, the (normalised, blurred) frame
``I`` and the pixel weights ``w`` (0 or 1) a step needs the gradients of
``W`` (centred differences, ``W`` reflected at the edges: OpenCV's Sobel of
ksize 1 with BORDER_REFLECT), the residual ``e = I - W``, its weighted sum
of squares, and the sums of the five products ``g_r g_r, g_r g_c, g_c g_c``
(weights ``P^2`` and ``P P'``) and ``g_r e, g_c e`` (weight ``P``) to the node
rows, ``P`` the bilinear node -> pixel weights of
:class:`processing.dic_nodes.NodeGrid` along the rows.  As NumPy that is
two Sobel calls, a subtraction, five full-size products and their row
sums; here one pass over the pixels, each row's products kept in a small
buffer.  The column sums stay NumPy (:func:`processing.dic_nodes._pair_sums`
on arrays a quarter of the frame).
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["row_moments"]


@numba.njit(nogil=True, cache=True, inline="always")
def _pixel(Wp, Wu, Wd, Ip, wp, c, cl, cr, tmp):  # pragma: no cover - compiled
    """Gradients, residual and products of pixel ``c`` of a row into ``tmp[:, c]``
    (neighbours ``cl``, ``cr``: the edge reflected); its weighted squared residual."""
    half = np.float32(0.5)
    wt = wp[c]
    gr = half * (Wd[c] - Wu[c]) * wt
    gc = half * (Wp[cr] - Wp[cl]) * wt
    e = Ip[c] - Wp[c]
    tmp[0, c] = gr * gr
    tmp[1, c] = gr * gc
    tmp[2, c] = gc * gc
    tmp[3, c] = gr * e
    tmp[4, c] = gc * e
    return np.float64(wt * e * e)


@numba.njit(nogil=True, cache=True, fastmath={"reassoc", "contract"})
def row_moments(W, img, w, s, t0, t1, xd, xo, xl, first, tmp):  # pragma: no cover - compiled
    """Sums of the pixel rows of node intervals ``t0 <= t < t1`` to the node rows.

    Interval ``t`` holds the pixel rows between node rows ``t`` and ``t + 1``
    (``t = -1``: the rows above node 0, all weight on it; ``t = m - 1``: the rows
    below the last).  Outputs float32, row ``t + 1`` = node row ``t`` (so
    ``m + 2`` rows, the outer two receiving zero weights only): ``xd``
    (3, m + 2, cols) the ``P^2``-weighted sums of ``g_r g_r, g_r g_c, g_c g_c``,
    ``xo`` (3, m + 2, cols) the ``P_t P_{t+1}`` sums at row ``t + 1``, ``xl``
    (2, m + 2, cols) the ``P``-weighted sums of ``g_r e, g_c e``.  The band's
    first node row ``t0`` goes to ``first`` (8, cols) instead, ``xd``'s three
    rows, ``xo``'s, ``xl``'s two (it is the previous band's last: bands then
    write no row in common and may run side by side; the caller adds it).
    ``tmp`` (5, cols) float32 scratch.  Returns the weighted residual sum of
    squares of those pixel rows (float64)."""
    rows, cols = W.shape
    m = rows // s
    hs = s // 2
    cost = 0.0
    half = np.float32(0.5)
    for t in range(t0, t1):
        for p in range(max(0, t * s + hs), min(rows, t * s + hs + s)):
            if t < 0:
                al, be = 0.0, 1.0
            elif t >= m - 1:
                al, be = 1.0, 0.0
            else:
                f = (p - t * s - hs + 0.5) / s
                al, be = 1.0 - f, f
            Wp, Wu, Wd = W[p], W[max(p - 1, 0)], W[min(p + 1, rows - 1)]
            Ip, wp = img[p], w[p]
            row_cost = _pixel(Wp, Wu, Wd, Ip, wp, 0, 0, min(1, cols - 1), tmp)
            if cols > 1:
                row_cost += _pixel(Wp, Wu, Wd, Ip, wp, cols - 1, cols - 2, cols - 1, tmp)
            for c in range(1, cols - 1):  # the interior without the edge's branches
                wt = wp[c]
                gr = half * (Wd[c] - Wu[c]) * wt
                gc = half * (Wp[c + 1] - Wp[c - 1]) * wt
                e = Ip[c] - Wp[c]
                tmp[0, c] = gr * gr
                tmp[1, c] = gr * gc
                tmp[2, c] = gc * gc
                tmp[3, c] = gr * e
                tmp[4, c] = gc * e
                row_cost += np.float64(wt * e * e)
            cost += row_cost
            a2 = np.float32(al * al)
            b2 = np.float32(be * be)
            ab = np.float32(al * be)
            a1 = np.float32(al)
            b1 = np.float32(be)
            for q in range(3):
                d_lo = first[q] if t == t0 else xd[q, t + 1]
                o_lo = first[3 + q] if t == t0 else xo[q, t + 1]
                d_hi, tq = xd[q, t + 2], tmp[q]
                for c in range(cols):
                    v = tq[c]
                    d_lo[c] += a2 * v
                    d_hi[c] += b2 * v
                    o_lo[c] += ab * v
            for q in range(2):
                l_lo = first[6 + q] if t == t0 else xl[q, t + 1]
                l_hi, tq = xl[q, t + 2], tmp[3 + q]
                for c in range(cols):
                    v = tq[c]
                    l_lo[c] += a1 * v
                    l_hi[c] += b1 * v
    return cost

