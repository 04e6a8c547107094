"""Compiled kernels (Numba) of each Gauss-Newton step of :func:`processing.dic.refine_height`.

:func:`row_moments`, the pixel pass: from the blurred warped reference
``W``, the (normalised, blurred) frame ``I`` and the pixel weights ``w``
(0 or 1) a step needs the gradients of ``W`` (centred differences, ``W``
reflected at the edges: OpenCV's Sobel of ksize 1 with BORDER_REFLECT), the
residual ``e = I - W``, its weighted sum of squares, and the sums of the
five products ``g_r g_r, g_r g_c, g_c g_c`` (weights ``P^2`` and ``P P'``)
and ``g_r e, g_c e`` (weight ``P``) to the node rows, ``P`` the bilinear
node -> pixel weights of :class:`processing.dic_nodes.NodeGrid` along the
rows.  As NumPy that was two Sobel calls, a subtraction, five full-size
products and their row sums; here one pass over the pixels, each row's
products kept in a small buffer.  :func:`column_pairs` then sums those
node rows along the pixel columns to the nodes (was NumPy's batched
``matmul`` of 4 x 3 weights: 0.33 -> 0.15 ms an array of 256 x 1024, a
matrix step's column sums 9.2 -> 3.1 ms alone, 6.0 -> 2.5 ms in the chain, 8 Dec
2026).

:func:`normal_apply`, the conjugate gradients' operator
``(L^T M L + lam R) x`` on the node grid in one call (was about 130 NumPy
passes), with the stencils zero-padded (:func:`pad_stencil`) so that no
inner loop branches.

:func:`lanczos_columns` and :func:`warp_map_rows`, the warp's map
(:meth:`processing.dic_nodes.NodeGrid.warp_map`): OpenCV's Lanczos resize of
the node displacement to every pixel, in two passes of 8 taps each, written
straight into ``cv2.remap``'s map (was a resize, a scaling and a subtraction
of full-size two-channel arrays).

:func:`cell_moments` and :func:`normalise_rows`, the intensity model
(:mod:`processing.dic_intensity`): the five moments of its cells in one
pass over the pixels (OpenCV's area means, :func:`processing.dic_intensity.area_taps`), and the
division by the gain and offset fields, bilinear from those cells inside
the same pass (OpenCV's bilinear resize, :func:`processing.dic_intensity.linear_taps`).

:func:`dot64`, the conjugate gradients' dot products: float32 arrays summed
in float64 without BLAS's threads (which spin on a loaded 2-core machine),
9 us instead of NumPy's einsum's 49 at 256^2 (the einsum cast every sample
to float64 first); the order of the sum is the vector loop's own, so the
last bits of a float64 differ from einsum's.

All compute what the NumPy and OpenCV operations they replace do
(tests compare them, to float32 rounding); compiled once per checkout and
cached in ``__pycache__``.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["row_moments", "column_pairs", "cell_moments", "normalise_rows", "normal_apply", "pad_stencil",
           "lanczos_columns", "warp_map_rows", "dot64"]


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
def row_moments(W, img, w, s, t0, t1, xd, xo, xl, first, tmp, matrix=True):  # pragma: no cover - compiled
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
    ``tmp`` (5, cols) float32 scratch.  ``matrix`` False: the right-hand
    sides ``xl`` alone (``xd``, ``xo`` and their rows of ``first`` are not
    touched; :func:`processing.dic.refine_height` keeps its first step's
    matrix).  Returns the weighted residual sum of squares of those pixel
    rows (float64)."""
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
            # the interior without the edge's branches, through views shifted by one column
            # (indices from 0: no wraparound test, SIMD)
            n_in = cols - 2
            w1, d1, u1, i1, p1, pl, pr = wp[1:], Wd[1:], Wu[1:], Ip[1:], Wp[1:], Wp[0:], Wp[2:]
            t_0, t_1, t_2, t_3, t_4 = tmp[0, 1:], tmp[1, 1:], tmp[2, 1:], tmp[3, 1:], tmp[4, 1:]
            for k in range(n_in):
                wt = w1[k]
                gr = half * (d1[k] - u1[k]) * wt
                gc = half * (pr[k] - pl[k]) * wt
                e = i1[k] - p1[k]
                t_0[k] = gr * gr
                t_1[k] = gr * gc
                t_2[k] = gc * gc
                t_3[k] = gr * e
                t_4[k] = gc * e
                row_cost += np.float64(wt * e * e)
            cost += row_cost
            a2 = np.float32(al * al)
            b2 = np.float32(be * be)
            ab = np.float32(al * be)
            a1 = np.float32(al)
            b1 = np.float32(be)
            for q in range(3 if matrix else 0):
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



@numba.njit(nogil=True, cache=True, fastmath={"reassoc", "contract"})
def column_pairs(x, W, d, o):  # pragma: no cover - compiled
    """Pixel columns -> node columns of each row of ``x`` (rows, n) through the bilinear
    node -> pixel weights ``P[p, j]`` (nodes every ``s`` px at ``j s + (s - 1) / 2``, the
    outer ``s // 2`` pixels of each side all on the outer node), ``W`` (s, k) the weights of
    the ``s`` pixels between two nodes (:func:`processing.dic_nodes._tent_weights`): with
    k = 3, ``d`` (rows, n // s) ``sum_p P[p, j]^2 x[p]`` and ``o`` (rows, n // s - 1)
    ``sum_p P[p, j] P[p, j + 1] x[p]``; with k = 2, ``d`` ``sum_p P[p, j] x[p]`` (``o`` not
    touched).  :func:`processing.dic_nodes._pair_sums` along the columns, float32."""
    rows, n = x.shape
    s = W.shape[0]
    quadratic = W.shape[1] == 3
    m = n // s
    hs = s // 2
    for r in range(rows):
        xr, dr = x[r], d[r]
        lo = np.float32(0.0)  # the lower node's share so far: the outer pixels' first
        for p in range(hs):
            lo += xr[p]
        last = np.float32(0.0)
        for p in range(n - hs, n):
            last += xr[p]
        for t in range(m - 1):
            base = hs + t * s
            a = np.float32(0.0)
            b = np.float32(0.0)
            c = np.float32(0.0)
            for k in range(s):
                v = xr[base + k]
                a += W[k, 0] * v
                b += W[k, 1] * v
                if quadratic:
                    c += W[k, 2] * v
            dr[t] = lo + a
            lo = b
            if quadratic:
                o[r, t] = c
        dr[m - 1] = lo + last


@numba.njit(nogil=True, cache=True, inline="always")
def _add_moments(acc, k, a, fp, wp, weight, p):  # pragma: no cover - compiled
    """``a`` times pixel row ``p``'s five moments added to the accumulator rows ``acc[:, k]``."""
    a0, a1, a2, a3, a4 = acc[0, k], acc[1, k], acc[2, k], acc[3, k], acc[4, k]
    if weight.size > 0:
        wr = weight[p]
        for q in range(fp.size):
            w = np.float64(wr[q])
            wi, ww = w * np.float64(fp[q]), w * np.float64(wp[q])
            a0[q] += a * w
            a1[q] += a * wi
            a2[q] += a * ww
            a3[q] += a * wi * np.float64(fp[q])
            a4[q] += a * ww * np.float64(wp[q])
    else:
        for q in range(fp.size):
            i, wv = np.float64(fp[q]), np.float64(wp[q])
            a0[q] += a
            a1[q] += a * i
            a2[q] += a * wv
            a3[q] += a * i * i
            a4[q] += a * wv * wv


@numba.njit(nogil=True, cache=True)
def cell_moments(frame, warped, weight, r_idx, r_lo, r_hi, c_idx, c_lo, c_hi, out):  # pragma: no cover - compiled
    """The cell means (area weights of :func:`processing.dic_intensity.area_taps` along the rows and the columns) of
    ``w``, ``w I``, ``w W``, ``w I^2``, ``w W^2`` into ``out`` (5, cell rows, cell cols) float64,
    ``I`` the ``frame``, ``W`` the ``warped`` reference, ``w`` the ``weight`` (an empty array: 1
    everywhere): the pixel rows summed to the cell rows in one pass, then the columns
    (:func:`processing.dic.intensity_fit`'s moments, which were five OpenCV area resizes and
    two products)."""
    rows, cols = frame.shape
    n_r, n_c = out.shape[1], out.shape[2]
    acc = np.zeros((5, n_r, cols), np.float64)
    for p in range(rows):
        _add_moments(acc, r_idx[p], r_lo[p], frame[p], warped[p], weight, p)
        if r_hi[p] != 0.0:
            _add_moments(acc, r_idx[p] + 1, r_hi[p], frame[p], warped[p], weight, p)
    for m in range(5):
        for k in range(n_r):
            src, dst = acc[m, k], out[m, k]
            for q in range(cols):
                j = c_idx[q]
                dst[j] += c_lo[q] * src[q]
                if c_hi[q] != 0.0:
                    dst[j + 1] += c_hi[q] * src[q]

@numba.njit(nogil=True, cache=True, fastmath={"contract"})
def _lerp_segments(lo_row, hi_row, f, c_idx, c_w, floor, g_row, o_row, g_inv, o_px):  # pragma: no cover
    """One pixel row's fields: the cell rows ``lo_row``, ``hi_row`` ((2, cell cols): gain, offset)
    mixed by ``f``, then to every pixel along the columns (cells of a run of pixels in turn: each
    run's inner loop over contiguous pixels with its two cells' values fixed)."""
    one = np.float32(1.0)
    n_c = g_row.size
    for j in range(n_c):
        g_row[j] = (one - f) * lo_row[0, j] + f * hi_row[0, j]
        o_row[j] = (one - f) * lo_row[1, j] + f * hi_row[1, j]
    q, cols = 0, c_idx.size
    while q < cols:
        j = c_idx[q]
        end = q
        while end < cols and c_idx[end] == j:
            end += 1
        j1 = min(j + 1, n_c - 1)
        g0, dg, o0, do = g_row[j], g_row[j1] - g_row[j], o_row[j], o_row[j1] - o_row[j]
        for k in range(q, end):
            g_inv[k] = one / max(g0 + c_w[k] * dg, floor)
            o_px[k] = o0 + c_w[k] * do
        q = end


@numba.njit(nogil=True, cache=True, fastmath={"contract"})
def normalise_rows(raw, fields, floor, r_idx, r_w, c_idx, c_w, out):  # pragma: no cover - compiled
    """``out = (raw - b) / max(a, floor)``, ``a`` and ``b`` the cell fields ``fields`` (2, cell rows,
    cell cols: gain, offset) bilinear at every pixel (:func:`processing.dic_intensity.linear_taps` along the rows and
    the columns: what ``cv2.resize(..., cv2.INTER_LINEAR)`` of them gives, to float rounding), in one
    pass (:func:`processing.dic_intensity.normalised_frame`)."""
    rows, cols = raw.shape
    n_r, n_c = fields.shape[1], fields.shape[2]
    by_row = np.ascontiguousarray(fields.transpose(1, 0, 2))  # (cell rows, 2, cell cols)
    g_row = np.empty(n_c, np.float32)
    o_row = np.empty(n_c, np.float32)
    g_inv = np.empty(cols, np.float32)
    o_px = np.empty(cols, np.float32)
    for p in range(rows):
        i = r_idx[p]
        _lerp_segments(by_row[i], by_row[min(i + 1, n_r - 1)], r_w[p], c_idx, c_w, floor, g_row, o_row, g_inv, o_px)
        rp, op = raw[p], out[p]
        for q in range(cols):
            op[q] = (rp[q] - o_px[q]) * g_inv[q]

# ------------------------------------------------------------------ the CG's operator on the node grid
_FAST = dict(nogil=True, cache=True, fastmath={"reassoc", "contract"})


@numba.njit(**_FAST)
def _d1_rows(x, inv_s, out):  # pragma: no cover - compiled
    """D1 (:func:`_d1_into`'s differences) along axis 0, times ``inv_s``, with fastmath (the CG's operator)."""
    n, m = x.shape
    c12, c8 = np.float32(1.0 / 12.0), np.float32(8.0 / 12.0)
    for i in range(2, n - 2):
        for j in range(m):
            out[i, j] = (c12 * (x[i - 2, j] - x[i + 2, j]) + c8 * (x[i + 1, j] - x[i - 1, j])) * inv_s
    for j in range(m):
        out[1, j] = np.float32(0.5) * (x[2, j] - x[0, j]) * inv_s
        out[n - 2, j] = np.float32(0.5) * (x[n - 1, j] - x[n - 3, j]) * inv_s
        out[0, j] = (np.float32(-1.5) * x[0, j] + np.float32(2.0) * x[1, j] - np.float32(0.5) * x[2, j]) * inv_s
        out[n - 1, j] = (np.float32(1.5) * x[n - 1, j] - np.float32(2.0) * x[n - 2, j]
                         + np.float32(0.5) * x[n - 3, j]) * inv_s


@numba.njit(**_FAST)
def _d1_cols(x, inv_s, out):  # pragma: no cover - compiled
    """D1 along axis 1, as :func:`_d1_rows`."""
    n, m = x.shape
    c12, c8 = np.float32(1.0 / 12.0), np.float32(8.0 / 12.0)
    for i in range(n):
        # offset views indexed from 0: a loop index numba knows is not negative (no wraparound test: SIMD)
        a, b, c, d, o = x[i, 0:m - 4], x[i, 4:m], x[i, 3:m - 1], x[i, 1:m - 3], out[i, 2:m - 2]
        for k in range(m - 4):
            o[k] = (c12 * (a[k] - b[k]) + c8 * (c[k] - d[k])) * inv_s
        out[i, 1] = np.float32(0.5) * (x[i, 2] - x[i, 0]) * inv_s
        out[i, m - 2] = np.float32(0.5) * (x[i, m - 1] - x[i, m - 3]) * inv_s
        out[i, 0] = (np.float32(-1.5) * x[i, 0] + np.float32(2.0) * x[i, 1] - np.float32(0.5) * x[i, 2]) * inv_s
        out[i, m - 1] = (np.float32(1.5) * x[i, m - 1] - np.float32(2.0) * x[i, m - 2]
                         + np.float32(0.5) * x[i, m - 3]) * inv_s


@numba.njit(**_FAST)
def _d1_T_weights(k, n):
    """The weights of ``y[k + 2], y[k - 2], y[k - 1], y[k + 1]`` in ``(D1^T y)[k]`` from
    D1's centred rows ``2 <= i <= n - 3`` (0 where that row is not centred), and
    those rows clipped into the array (their weight is 0 where clipped)."""
    c12, c8, zero = np.float32(1.0 / 12.0), np.float32(8.0 / 12.0), np.float32(0.0)
    w = (c12 if 2 <= k + 2 <= n - 3 else zero, -c12 if 2 <= k - 2 <= n - 3 else zero,
         c8 if 2 <= k - 1 <= n - 3 else zero, -c8 if 2 <= k + 1 <= n - 3 else zero)
    rows = (min(k + 2, n - 1), max(k - 2, 0), max(k - 1, 0), min(k + 1, n - 1))
    return w, rows


@numba.njit(**_FAST)
def _d1_T_edge(n, i):
    """D1's row ``i`` when it is not centred (``i`` in 0, 1, n - 2, n - 1): the rows
    ``k0..k3`` it reads and their weights ``w0..w3`` (:func:`_d1_rows`)."""
    if i == 1 or i == n - 2:
        return (i + 1, i - 1, i, i), (np.float32(0.5), np.float32(-0.5), np.float32(0.0), np.float32(0.0))
    if i == 0:
        return (0, 1, 2, 0), (np.float32(-1.5), np.float32(2.0), np.float32(-0.5), np.float32(0.0))
    return (n - 1, n - 2, n - 3, n - 1), (np.float32(1.5), np.float32(-2.0), np.float32(0.5), np.float32(0.0))


@numba.njit(**_FAST)
def _add_d1_T(y, inv_s, axis, z):  # pragma: no cover - compiled
    """``z += D1^T y`` along ``axis`` (the transpose of :func:`_d1_rows` / :func:`_d1_cols`):
    the centred rows of D1 gathered (one store a sample, SIMD along the rows), its four
    one-sided and half-width rows scattered."""
    n, m = y.shape
    if axis == 0:
        for k in range(n):
            (w0, w1, w2, w3), (r0, r1, r2, r3) = _d1_T_weights(k, n)
            a, b, c, d, o = y[r0], y[r1], y[r2], y[r3], z[k]
            for j in range(m):
                o[j] += (w0 * a[j] + w1 * b[j] + w2 * c[j] + w3 * d[j]) * inv_s
        for i in range(n):
            if 2 <= i <= n - 3:
                continue
            (k0, k1, k2, k3), (w0, w1, w2, w3) = _d1_T_edge(n, i)
            for j in range(m):
                v = y[i, j] * inv_s
                z[k0, j] += w0 * v
                z[k1, j] += w1 * v
                z[k2, j] += w2 * v
                z[k3, j] += w3 * v
        return
    c12, c8 = np.float32(1.0 / 12.0), np.float32(8.0 / 12.0)
    inner = 4 if m > 8 else m  # columns 4 .. m - 5 (m > 8) read four centred rows of D1
    for t in range(n):
        yr, zr = y[t], z[t]
        if m > 8:  # offset views from 0 (SIMD)
            a, b, c, d, o = yr[6:m - 1], yr[2:m - 5], yr[3:m - 4], yr[5:m - 2], zr[4:m - 4]
            for q in range(m - 8):
                o[q] += (c12 * (a[q] - b[q]) + c8 * (c[q] - d[q])) * inv_s
        for k in range(inner):  # the columns left: 0..3 and m - 4..m - 1 (all of them if m <= 8)
            (w0, w1, w2, w3), (r0, r1, r2, r3) = _d1_T_weights(k, m)
            zr[k] += (w0 * yr[r0] + w1 * yr[r1] + w2 * yr[r2] + w3 * yr[r3]) * inv_s
        for k in range(max(inner, m - 4), m):
            (w0, w1, w2, w3), (r0, r1, r2, r3) = _d1_T_weights(k, m)
            zr[k] += (w0 * yr[r0] + w1 * yr[r1] + w2 * yr[r2] + w3 * yr[r3]) * inv_s
        for e in range(4):  # D1's non-centred rows 0, 1, m - 2, m - 1, each once (0..m - 1 if m < 4)
            i = e if e < 2 else m - 4 + e
            if e >= 2 and i < 2:
                continue
            (k0, k1, k2, k3), (w0, w1, w2, w3) = _d1_T_edge(m, i)
            v = yr[i] * inv_s
            zr[k0] += w0 * v
            zr[k1] += w1 * v
            zr[k2] += w2 * v
            zr[k3] += w3 * v


@numba.njit(**_FAST)
def _add_d3_T_d3(x, lam, z):  # pragma: no cover - compiled
    """``z += lam (D3r^T D3r + D3c^T D3c) x``."""
    n, m = x.shape
    three = np.float32(3.0)
    if n >= 4:  # along the columns: the rows of differences D[i + 3] = d_i, zero around them, gathered
        dr = np.zeros((n + 3, m), np.float32)
        for i in range(n - 3):
            a, b, c, e, d = x[i + 3], x[i], x[i + 1], x[i + 2], dr[i + 3]
            for j in range(m):
                d[j] = lam * (a[j] - b[j] + three * (c[j] - e[j]))
        for k in range(n):
            d0, d1, d2, d3, zr = dr[k + 3], dr[k], dr[k + 2], dr[k + 1], z[k]
            for j in range(m):
                zr[j] += -d0[j] + d1[j] + three * d2[j] - three * d3[j]
    if m < 4:
        return
    # along the rows: the differences first (dp[j + 3] = d_j, zero around them), then gathered,
    # one store a sample, indices from 0 (SIMD; the scatter above ran scalar along a row)
    dp = np.zeros(m + 3, np.float32)
    for i in range(n):
        r, d, zr = x[i], dp[3:m], z[i]
        a, b, c, e = r[3:m], r[0:m - 3], r[1:m - 2], r[2:m - 1]
        for j in range(m - 3):
            d[j] = lam * (a[j] - b[j] + three * (c[j] - e[j]))
        d0, d1, d2, d3 = dp[3:m + 3], dp[0:m], dp[2:m + 2], dp[1:m + 1]
        for k in range(m):
            zr[k] += -d0[k] + d1[k] + three * d2[k] - three * d3[k]


@numba.njit(**_FAST)
def _stencil_row(dd, do, od, oo, vp, i, out, add):  # pragma: no cover - compiled
    """Row ``i`` of the 9-point stencil (padded coefficients, :func:`pad_stencil`)
    applied to the zero-bordered ``vp``; into ``out`` (row), added if ``add``."""
    m = out.shape[0]
    for j in range(m):
        y = (dd[i, j] * vp[i + 1, j + 1] + do[i, j + 1] * vp[i + 1, j + 2] + do[i, j] * vp[i + 1, j]
             + od[i + 1, j] * vp[i + 2, j + 1] + od[i, j] * vp[i, j + 1]
             + oo[i + 1, j + 1] * vp[i + 2, j + 2] + oo[i, j] * vp[i, j]
             + oo[i + 1, j] * vp[i + 2, j] + oo[i, j + 1] * vp[i, j + 2])
        out[j] = out[j] + y if add else y


@numba.njit(**_FAST)
def normal_apply(x, A, SD, SDO, SOD, SOO, inv_s, lam, work, vpad, out):  # pragma: no cover - compiled
    """``out = (L^T M L + lam R) x``: the normal operator of a Gauss-Newton step
    on the node grid, float32 (m_r, m_c).

    ``A`` (6, m_r, m_c): the linear response ``a_r, a_c, B_rr, B_rc, B_cr, B_cc``
    (:meth:`processing.dic_nodes.HeightNodes.dense_response`); ``SD .. SOO`` the
    three stencils rr, rc, cc padded (:func:`pad_stencil`); ``work`` (4, m_r, m_c)
    scratch; ``vpad`` (2, m_r + 2, m_c + 2) scratch whose border stays 0."""
    n, m = x.shape
    dr, dc, mr, mc = work[0], work[1], work[2], work[3]
    _d1_rows(x, inv_s, dr)
    _d1_cols(x, inv_s, dc)
    for i in range(n):
        for j in range(m):
            vpad[0, i + 1, j + 1] = A[0, i, j] * x[i, j] + A[2, i, j] * dr[i, j] + A[3, i, j] * dc[i, j]
            vpad[1, i + 1, j + 1] = A[1, i, j] * x[i, j] + A[4, i, j] * dr[i, j] + A[5, i, j] * dc[i, j]
    for i in range(n):
        _stencil_row(SD[0], SDO[0], SOD[0], SOO[0], vpad[0], i, mr[i], False)
        _stencil_row(SD[1], SDO[1], SOD[1], SOO[1], vpad[1], i, mr[i], True)
        _stencil_row(SD[1], SDO[1], SOD[1], SOO[1], vpad[0], i, mc[i], False)
        _stencil_row(SD[2], SDO[2], SOD[2], SOO[2], vpad[1], i, mc[i], True)
    for i in range(n):
        for j in range(m):
            a, b = mr[i, j], mc[i, j]
            out[i, j] = A[0, i, j] * a + A[1, i, j] * b
            dr[i, j] = A[2, i, j] * a + A[4, i, j] * b  # D1r^T of this
            dc[i, j] = A[3, i, j] * a + A[5, i, j] * b  # D1c^T of this
    _add_d1_T(dr, inv_s, 0, out)
    _add_d1_T(dc, inv_s, 1, out)
    _add_d3_T_d3(x, lam, out)


@numba.njit(**_FAST)
def _taps8(src, idx, wts, k, out):  # pragma: no cover - compiled
    """``out[:] = sum_t wts[k, t] * src[idx[k, t], :]`` over the 8 taps ``t`` (rows of ``src``
    contiguous): the 8 rows' values summed in registers, one store per output."""
    a0, a1, a2, a3 = src[idx[k, 0]], src[idx[k, 1]], src[idx[k, 2]], src[idx[k, 3]]
    a4, a5, a6, a7 = src[idx[k, 4]], src[idx[k, 5]], src[idx[k, 6]], src[idx[k, 7]]
    w0, w1, w2, w3 = wts[k, 0], wts[k, 1], wts[k, 2], wts[k, 3]
    w4, w5, w6, w7 = wts[k, 4], wts[k, 5], wts[k, 6], wts[k, 7]
    for c in range(out.shape[0]):
        out[c] = (w0 * a0[c] + w1 * a1[c] + w2 * a2[c] + w3 * a3[c]
                  + w4 * a4[c] + w5 * a5[c] + w6 * a6[c] + w7 * a7[c])


@numba.njit(**_FAST)
def lanczos_columns(u_t, idx, wts, out):  # pragma: no cover - compiled
    """First pass of :meth:`processing.dic_nodes.NodeGrid.warp_map`: ``u_t`` (node columns,
    2 x node rows) the node displacement with the node columns as rows (u_col, u_row
    interleaved), resampled to every pixel column: ``out`` (cols, 2 x node rows)."""
    for c in range(out.shape[0]):
        _taps8(u_t, idx, wts, c, out[c])


@numba.njit(**_FAST)
def warp_map_rows(h, idx, wts, factor, r0, r1, out, acc):  # pragma: no cover - compiled
    """Second pass of :meth:`processing.dic_nodes.NodeGrid.warp_map`, pixel rows ``r0 <= r < r1``:
    ``h`` (node rows, 2 x cols) the first pass (u_col, u_row interleaved), resampled to pixel
    row ``r`` and written as ``cv2.remap``'s map into a grid ``factor`` times finer:
    ``out[r, 2 c] = factor (c - u_col)``, ``out[r, 2 c + 1] = factor (r - u_row)``
    (``out`` (rows, 2 x cols)); ``acc`` (2 x cols) float32 scratch."""
    cols = h.shape[1] // 2
    f = np.float32(factor)
    for r in range(r0, r1):
        _taps8(h, idx, wts, r, acc)
        o = out[r]
        rf = np.float32(r)
        for c in range(cols):
            o[2 * c] = f * (np.float32(c) - acc[2 * c])
            o[2 * c + 1] = f * (rf - acc[2 * c + 1])


def pad_stencil(parts):
    """``(dd, do, od, oo)`` of a :class:`processing.dic_nodes.Stencil9` with zero
    couplings beyond the grid: ``dd`` (m_r, m_c), ``do`` (m_r, m_c + 1) with
    ``do[i, j + 1]`` the (i, j)-(i, j + 1) coupling, ``od`` (m_r + 1, m_c) with
    ``od[i + 1, j]`` the (i, j)-(i + 1, j) one, ``oo`` (m_r + 1, m_c + 1) with
    ``oo[i + 1, j + 1]`` the (i, j)-(i + 1, j + 1) and (i, j + 1)-(i + 1, j) one."""
    dd, do, od, oo = parts
    m_r, m_c = dd.shape
    dop = np.zeros((m_r, m_c + 1), np.float32)
    dop[:, 1:m_c] = do
    odp = np.zeros((m_r + 1, m_c), np.float32)
    odp[1:m_r] = od
    oop = np.zeros((m_r + 1, m_c + 1), np.float32)
    oop[1:m_r, 1:m_c] = oo
    return np.asarray(dd, np.float32), dop, odp, oop


@numba.njit(**_FAST)
def dot64(a, b):  # pragma: no cover - compiled
    """``sum(a * b)`` of two float32 arrays of one shape, each product and the sum in float64."""
    fa, fb = a.ravel(), b.ravel()
    total = 0.0
    for i in range(fa.size):
        total += np.float64(fa[i]) * np.float64(fb[i])
    return total
