"""Compiled node operators (Numba) of :class:`processing.dic_nodes.HeightNodes`, exact.

:func:`node_displacement`, :func:`node_displacement_T` and
:func:`node_regulariser` are the node operators of
:class:`processing.dic_nodes.HeightNodes` (``L``, ``L^T`` and the
regulariser ``D3r^T D3r + D3c^T D3c``) that each Gauss-Newton step applies
to the heights, its step and its right-hand sides: each sum in the order
and precision of the NumPy expressions they replaced (kept as the reference
in tests/processing/test_dic.py, which compares them: the same bits in
float32 and float64; the constants in the array's own type), every inner
loop along the rows; the NumPy versions' passes along transposed views
were 1.8 ms of each Gauss-Newton step at 256^2 nodes, these 0.7.
Unlike :mod:`processing.dic_kernels` (whose sums may be reordered), no
fastmath here: every sum keeps the NumPy expressions' order and rounding.
Compiled once per checkout and cached in ``__pycache__``.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["node_displacement", "node_displacement_T", "node_regulariser"]

_EXACT = dict(nogil=True, cache=True)
_INLINE = dict(nogil=True, cache=True, inline="always")


@numba.njit(**_INLINE)
def _d1_at(xa, xb, xc, xd, c8, c12):  # pragma: no cover - compiled
    """D1's centred value ``((x[i-2] - x[i+2]) + 8 (x[i+1] - x[i-1])) / 12`` (``xa .. xd`` in that order)."""
    return ((xa - xb) + c8 * (xc - xd)) / c12


@numba.njit(**_INLINE)
def _four_terms(a, b, c, d, f0, f1, f2, f3, sign, w):  # pragma: no cover - compiled
    """``sign a - sign b + w c - w d`` summed from a zero in that order, each term only where its flag
    says the NumPy version's slices reach the sample (``sign`` +-1: exact, and adding a negated term
    is subtracting it).  D1^T's centred part from ``q = y / 12``: ``(q[i+2], q[i-2], q[i-1], q[i+1])``,
    sign +1, ``w`` 8; D3^T D3's from the third differences ``d``: ``(d[i], d[i-3], d[i-1], d[i-2])``,
    sign -1, ``w`` 3."""
    t = w - w
    if f0:
        t = t + sign * a
    if f1:
        t = t - sign * b
    if f2:
        t = t + w * c
    if f3:
        t = t - w * d
    return t


@numba.njit(**_EXACT)
def _d1_into(x, k, axis, y):  # pragma: no cover - compiled
    """``y = D1 x`` along ``axis`` (the test's ``_numpy_d1``; axis 1: ``_numpy_d1(x.T).T``): fourth-order centred
    differences inside, second-order at the ends, per node spacing; ``k`` the constants
    (8, 12, 0.5, 1.5, 2, -1.5, s) in ``x``'s type.  Inner loops run along the rows (contiguous)."""
    n, m = x.shape
    c8, c12, half, c15, c2, m15, s = k[0], k[1], k[2], k[3], k[4], k[5], k[6]
    if axis == 0:
        for i in range(2, n - 2):
            a, b, c, d, o = x[i - 2], x[i + 2], x[i + 1], x[i - 1], y[i]
            for j in range(m):
                o[j] = _d1_at(a[j], b[j], c[j], d[j], c8, c12) / s
        for j in range(m):
            y[1, j] = half * (x[2, j] - x[0, j]) / s
            y[n - 2, j] = half * (x[n - 1, j] - x[n - 3, j]) / s
            y[0, j] = ((m15 * x[0, j] + c2 * x[1, j]) - half * x[2, j]) / s
            y[n - 1, j] = ((c15 * x[n - 1, j] - c2 * x[n - 2, j]) + half * x[n - 3, j]) / s
        return
    for i in range(n):
        r, o = x[i], y[i]
        for j in range(2, m - 2):
            o[j] = _d1_at(r[j - 2], r[j + 2], r[j + 1], r[j - 1], c8, c12) / s
        o[1] = half * (r[2] - r[0]) / s
        o[m - 2] = half * (r[m - 1] - r[m - 3]) / s
        o[0] = ((m15 * r[0] + c2 * r[1]) - half * r[2]) / s
        o[m - 1] = ((c15 * r[m - 1] - c2 * r[m - 2]) + half * r[m - 3]) / s


@numba.njit(**_EXACT)
def _d1_T_into(y, k, axis, z):  # pragma: no cover - compiled
    """``z = D1^T y`` along ``axis`` (the test's ``_numpy_d1_T``; axis 1 its transposed use), the constants ``k``
    as :func:`_d1_into`'s."""
    n, m = y.shape
    c8, c12, half, c15, c2, s = k[0], k[1], k[2], k[3], k[4], k[6]
    yes, one = True, c8 / c8  # 1 in y's type
    q = np.empty_like(y)  # y / 12 once a sample, as the NumPy version's yi
    for i in range(n):
        for j in range(m):
            q[i, j] = y[i, j] / c12
    if axis == 0:
        for i in range(n):
            f0, f1, f2, f3 = i <= n - 5, i >= 4, 3 <= i <= n - 2, 1 <= i <= n - 4
            a, b, c, d, o = q[min(i + 2, n - 1)], q[max(i - 2, 0)], q[max(i - 1, 0)], q[min(i + 1, n - 1)], z[i]
            if f0 and f1 and f2 and f3:
                for j in range(m):
                    o[j] = _four_terms(a[j], b[j], c[j], d[j], yes, yes, yes, yes, one, c8)
            else:
                for j in range(m):
                    o[j] = _four_terms(a[j], b[j], c[j], d[j], f0, f1, f2, f3, one, c8)
        for j in range(m):  # the end rows, in the NumPy version's order
            z[0, j] -= half * y[1, j]
            z[2, j] += half * y[1, j]
            z[n - 3, j] -= half * y[n - 2, j]
            z[n - 1, j] += half * y[n - 2, j]
            z[0, j] -= c15 * y[0, j]
            z[1, j] += c2 * y[0, j]
            z[2, j] -= half * y[0, j]
            z[n - 1, j] += c15 * y[n - 1, j]
            z[n - 2, j] -= c2 * y[n - 1, j]
            z[n - 3, j] += half * y[n - 1, j]
        for i in range(n):
            o = z[i]
            for j in range(m):
                o[j] = o[j] / s
        return
    for i in range(n):
        r, p, o = y[i], q[i], z[i]
        for j in range(4, m - 4):
            o[j] = _four_terms(p[j + 2], p[j - 2], p[j - 1], p[j + 1], yes, yes, yes, yes, one, c8)
        for j in range(m):
            if 4 <= j <= m - 5:
                continue
            o[j] = _four_terms(p[min(j + 2, m - 1)], p[max(j - 2, 0)], p[max(j - 1, 0)], p[min(j + 1, m - 1)],
                               j <= m - 5, j >= 4, 3 <= j <= m - 2, 1 <= j <= m - 4, one, c8)
        o[0] -= half * r[1]
        o[2] += half * r[1]
        o[m - 3] -= half * r[m - 2]
        o[m - 1] += half * r[m - 2]
        o[0] -= c15 * r[0]
        o[1] += c2 * r[0]
        o[2] -= half * r[0]
        o[m - 1] += c15 * r[m - 1]
        o[m - 2] -= c2 * r[m - 1]
        o[m - 3] += half * r[m - 1]
        for j in range(m):
            o[j] = o[j] / s


@numba.njit(**_EXACT)
def node_displacement(h, coef, present, k, out):  # pragma: no cover - compiled
    """``out`` (2, n, m) ``= L h``: ``u_i = a_i h + B_i0 D1r h + B_i1 D1c h`` over the terms ``present``
    (6 booleans: a_r, a_c, B_rr, B_rc, B_cr, B_cc), ``coef`` (6, n, m) their coefficients in ``h``'s
    type, ``k`` :func:`_d1_into`'s constants."""
    n, m = h.shape
    dr = np.empty_like(h)
    dc = np.empty_like(h)
    _d1_into(h, k, 0, dr)
    _d1_into(h, k, 1, dc)
    zero = k[0] - k[0]
    for comp in range(2):
        ia, ib0, ib1 = comp, 2 + 2 * comp, 3 + 2 * comp
        pa, pb0, pb1 = present[ia], present[ib0], present[ib1]
        for i in range(n):
            ca, cb0, cb1, hr, rr, rc, o = coef[ia, i], coef[ib0, i], coef[ib1, i], h[i], dr[i], dc[i], out[comp, i]
            for j in range(m):
                t = zero
                if pa:
                    t = t + ca[j] * hr[j]
                if pb0:
                    t = t + cb0[j] * rr[j]
                if pb1:
                    t = t + cb1[j] * rc[j]
                o[j] = t


@numba.njit(**_INLINE)
def _three_terms(t, u, v, ct, cu, cv, pt, pu, pv, x):  # pragma: no cover - compiled
    """``(t + ct x, u + cu x, v + cv x)``, each only where its term is present (``pt``, ``pu``, ``pv``)."""
    if pt:
        t = t + ct * x
    if pu:
        u = u + cu * x
    if pv:
        v = v + cv * x
    return t, u, v


@numba.njit(**_EXACT)
def node_displacement_T(vr, vc, coef, present, k, out):  # pragma: no cover - compiled
    """``out = L^T (vr, vc)`` (``HeightNodes.displacement_T``), arguments as :func:`node_displacement`'s."""
    n, m = vr.shape
    yr = np.empty_like(vr)
    yc = np.empty_like(vr)
    zero = k[0] - k[0]
    p0, p1, p2, p3, p4, p5 = present[0], present[1], present[2], present[3], present[4], present[5]
    for i in range(n):
        a, b, o, r_, c_ = vr[i], vc[i], out[i], yr[i], yc[i]
        for j in range(m):
            # vr's terms (a_r, B_rr, B_rc), then vc's (a_c, B_cr, B_cc), as displacement_T's loop adds them
            t, u, v = _three_terms(zero, zero, zero, coef[0, i, j], coef[2, i, j], coef[3, i, j], p0, p2, p3, a[j])
            o[j], r_[j], c_[j] = _three_terms(t, u, v, coef[1, i, j], coef[4, i, j], coef[5, i, j], p1, p4, p5, b[j])
    z = np.empty_like(vr)
    _d1_T_into(yr, k, 0, z)
    for i in range(n):
        for j in range(m):
            out[i, j] = out[i, j] + z[i, j]
    _d1_T_into(yc, k, 1, z)
    for i in range(n):
        for j in range(m):
            out[i, j] = out[i, j] + z[i, j]


@numba.njit(**_EXACT)
def _d3_T_d3_into(x, three, axis, z):  # pragma: no cover - compiled
    """``z = D3^T D3 x`` along ``axis`` (the test's ``_numpy_d3_T_d3``; axis 1 its transposed use)."""
    n, m = x.shape
    yes, one = True, three / three  # 1 in x's type
    if (n if axis == 0 else m) < 4:  # no third difference fits: D3^T D3 x = 0 (as the empty slices give)
        for i in range(n):
            for j in range(m):
                z[i, j] = three - three
        return
    if axis == 0:
        d = np.empty((n - 3, m), x.dtype)
        for i in range(n - 3):
            a, b, c, e, o = x[i + 3], x[i], x[i + 1], x[i + 2], d[i]
            for j in range(m):
                o[j] = (a[j] - b[j]) + three * (c[j] - e[j])
        for i in range(n):
            f0, f1, f2, f3 = i <= n - 4, i >= 3, 1 <= i <= n - 3, 2 <= i <= n - 2
            lo = n - 4
            a, b, c, e, o = d[min(i, lo)], d[max(i - 3, 0)], d[min(max(i - 1, 0), lo)], d[min(max(i - 2, 0), lo)], z[i]
            if f0 and f1 and f2 and f3:
                for j in range(m):
                    o[j] = _four_terms(a[j], b[j], c[j], e[j], yes, yes, yes, yes, -one, three)
            else:
                for j in range(m):
                    o[j] = _four_terms(a[j], b[j], c[j], e[j], f0, f1, f2, f3, -one, three)
        return
    d = np.empty(m - 3, x.dtype)
    lo = m - 4
    for i in range(n):
        r, o = x[i], z[i]
        for j in range(m - 3):
            d[j] = (r[j + 3] - r[j]) + three * (r[j + 1] - r[j + 2])
        for j in range(3, m - 3):
            o[j] = _four_terms(d[j], d[j - 3], d[j - 1], d[j - 2], yes, yes, yes, yes, -one, three)
        for j in range(m):
            if 3 <= j <= m - 4:
                continue
            o[j] = _four_terms(d[min(j, lo)], d[max(j - 3, 0)], d[min(max(j - 1, 0), lo)], d[min(max(j - 2, 0), lo)],
                               j <= m - 4, j >= 3, 1 <= j <= m - 3, 2 <= j <= m - 2, -one, three)


@numba.njit(**_EXACT)
def node_regulariser(h, three, out):  # pragma: no cover - compiled
    """``out = (D3r^T D3r + D3c^T D3c) h``; ``three`` 3 in ``h``'s type."""
    _d3_T_d3_into(h, three, 0, out)
    z = np.empty_like(h)
    _d3_T_d3_into(h, three, 1, z)
    n, m = h.shape
    for i in range(n):
        for j in range(m):
            out[i, j] = out[i, j] + z[i, j]
