"""What the GPU chain (:mod:`processing.gpu`) runs on the device beyond array code: the fused
warp kernel of FD's refinement, and host memory the device copies to and from at full speed."""

from __future__ import annotations

import numpy as np

__all__ = ["PINNED_LIMIT_BYTES", "host_empty", "to_host", "warp_kernel"]

# The GPU chain's bilinear sample of the envelopes (cv2.remap's reflecting border, one
# reflection) and processing.refine.modulate, per output sample, in float32 as the array code does
_WARP_SOURCE = """
    const int plane = rows * cols;
    const int p = (int)(i % plane);
    const int row = p / cols, col = p - row * cols;
    const float X = (float)col + off_c, Y = (float)row + off_r;
    const float fx0 = floorf(X), fy0 = floorf(Y);
    const float fx = X - fx0, fy = Y - fy0;
    int x0 = (int)fx0, y0 = (int)fy0, x1 = x0 + 1, y1 = y0 + 1;
    x0 = x0 < 0 ? -x0 - 1 : x0;  x0 = x0 >= cols ? 2 * cols - x0 - 1 : x0;
    x1 = x1 < 0 ? -x1 - 1 : x1;  x1 = x1 >= cols ? 2 * cols - x1 - 1 : x1;
    y0 = y0 < 0 ? -y0 - 1 : y0;  y0 = y0 >= rows ? 2 * rows - y0 - 1 : y0;
    y1 = y1 < 0 ? -y1 - 1 : y1;  y1 = y1 >= rows ? 2 * rows - y1 - 1 : y1;
    float e[4];
    for (int ch = 0; ch < 4; ++ch) {
        const float top = (1.0f - fx) * env[(y0 * cols + x0) * 4 + ch] + fx * env[(y0 * cols + x1) * 4 + ch];
        const float bottom = (1.0f - fx) * env[(y1 * cols + x0) * 4 + ch] + fx * env[(y1 * cols + x1) * 4 + ch];
        e[ch] = (1.0f - fy) * top + fy * bottom;
    }
    const float phi0 = k00 * off_r + k01 * off_c, phi1 = k10 * off_r + k11 * off_c;
    const float c0 = cosf(phi0), s0 = sinf(phi0), c1 = cosf(phi1), s1 = sinf(phi1);
    const float cc0 = ccos[p], cs0 = csin[p], cc1 = ccos[plane + p], cs1 = csin[plane + p];
    const float t0 = e[0] * (cc0 * c0 - cs0 * s0) - e[1] * (cc0 * s0 + cs0 * c0);
    const float t1 = e[2] * (cc1 * c1 - cs1 * s1) - e[3] * (cc1 * s1 + cs1 * c1);
    out = 2.0f * (t0 + t1);
"""
_WARP_KERNELS = {}


def warp_kernel(xp):
    """The fused warp of the GPU chain's refinement (``processing.gpu``) as a CuPy elementwise kernel, or None
    when ``xp`` has none (NumPy, which runs the array code instead)."""
    if not hasattr(xp, "ElementwiseKernel"):
        return None
    if "warp" not in _WARP_KERNELS:
        _WARP_KERNELS["warp"] = xp.ElementwiseKernel(
            "float32 off_r, float32 off_c, raw float32 env, raw float32 ccos, raw float32 csin, "
            "float32 k00, float32 k01, float32 k10, float32 k11, int32 rows, int32 cols",
            "float32 out", _WARP_SOURCE, "tirdeflect_warp_smooth")
    return _WARP_KERNELS["warp"]


# one page-locked host array at most this large; a larger one is plain (pageable) memory
PINNED_LIMIT_BYTES = 512 << 20


def host_empty(xp, shape, dtype):
    """An empty host array that the device copies to and from at full speed:
    page-locked (``cupyx.empty_pinned``, CuPy's pinned memory pool) when ``xp``
    is CuPy and it holds at most :data:`PINNED_LIMIT_BYTES`; else plain NumPy."""
    if xp is not np and int(np.prod(shape)) * np.dtype(dtype).itemsize <= PINNED_LIMIT_BYTES:
        try:
            import cupyx
        except ImportError:  # NumPy standing in for CuPy (tests)
            pass
        else:
            return cupyx.empty_pinned(shape, dtype)
    return np.empty(shape, dtype)


def to_host(xp, a, pinned=False):
    """``a`` on the host, as a NumPy array (into page-locked memory with ``pinned``)."""
    if not hasattr(xp, "asnumpy"):
        return np.asarray(a)
    if not pinned:
        return xp.asnumpy(a)
    out = host_empty(xp, a.shape, a.dtype)
    xp.asnumpy(a, out=out)
    return out

