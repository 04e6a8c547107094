"""The TIR trace of a surface taken as a plane at each ray, compiled: the second-order correction's trace
(:meth:`processing.second_order.SecondOrderOptics`), one pass over the rays instead of NumPy's two dozen
passes over 65,536 node rays (6 of the 15 ms of a 1024^2 default frame's correction, 7 Dec 2026).

The same arithmetic, in the same order, as :func:`processing.forward.trace_tir` of
``second_order._LocalPlanes``: the Newton steps on every ray until the largest step is below the tolerance
(for a plane one step and its check), then the reflection on the local normal and the way down to the
pattern (tests/processing/test_second_order.py compares the two to the bit).
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["trace_planes_tir"]


@numba.njit(nogil=True, cache=True)
def trace_planes_tir(origin, d, h, gx, gy, x0, y0, row_sign, critical_sin, depth_mm, tol_mm, max_iter,
                     pat_x, pat_y, lost, work):  # pragma: no cover - compiled
    """Trace TIR camera rays (``origin``, ``d``: (3, n) float64, the rays' components) to the surface
    taken as the plane of height ``h`` and image-frame gradient ``(gx, gy)`` through ``(x0, y0)`` at each
    ray ((n,) float64; the image frame's y is ``row_sign`` times the tracer's), reflect them on its
    normal and carry them down to the pattern at ``depth_mm``.  Writes ``pat_x``, ``pat_y`` (mm, tracer
    frame; NaN where the reflected ray goes up) and ``lost`` (incidence sine at most ``critical_sin``, or
    a reflected ray not going down); ``work`` (6, n) float64 scratch.  Returns the Newton steps taken, -1
    where ``max_iter`` did not bring the largest step below ``tol_mm``."""
    n = h.shape[0]
    t, px, py, pz, g_y, steps_px = work[0], work[1], work[2], work[3], work[4], work[5]
    for i in range(n):
        t[i] = -origin[2, i] / d[2, i]
    steps = -1
    for it in range(max_iter):
        largest = 0.0
        for i in range(n):
            dx, dy, dz = d[0, i], d[1, i], d[2, i]
            px[i] = origin[0, i] + t[i] * dx
            py[i] = origin[1, i] + t[i] * dy
            pz[i] = origin[2, i] + t[i] * dz
            hi = h[i] + gx[i] * (px[i] - x0[i]) + gy[i] * (row_sign * py[i] - y0[i])
            g_y[i] = gy[i] * row_sign
            step = (pz[i] - hi) / (dz - gx[i] * dx - g_y[i] * dy)
            a = abs(step)
            if a > largest or a != a:  # a NaN step stays the largest: never below the tolerance (np.max)
                largest = a
            steps_px[i] = step
        if largest < tol_mm:
            steps = it
            break
        for i in range(n):
            t[i] = t[i] - steps_px[i]
    if steps < 0:
        return -1
    for i in range(n):
        dx, dy, dz = d[0, i], d[1, i], d[2, i]
        nx, ny = -gx[i], -g_y[i]
        length = math.sqrt(nx * nx + ny * ny + 1.0)
        nx, ny, nz = nx / length, ny / length, 1.0 / length
        cos_i = dx * nx + dy * ny + dz * nz
        s2 = 1.0 - cos_i * cos_i
        if s2 < 0.0:
            s2 = 0.0
        sin_i = math.sqrt(s2)
        twice = 2.0 * cos_i
        rx, ry, rz = dx - twice * nx, dy - twice * ny, dz - twice * nz
        lost[i] = (sin_i <= critical_sin) or (rz >= 0.0)
        if rz < 0.0:
            tt = (-depth_mm - pz[i]) / rz
        else:
            tt = np.nan
        pat_x[i] = px[i] + tt * rx
        pat_y[i] = py[i] + tt * ry
    return steps
