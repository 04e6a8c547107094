"""The image-domain refinement's grid and operator (:mod:`processing.dic`):
the reference on a finer grid (:func:`fine_reference`), the node grid every
:data:`NODE_PX` pixels (:class:`NodeGrid`, bilinear nodes <-> pixels) and the
geometry's linear response at the nodes (:class:`HeightNodes`: height ->
displacement, its transpose, the Gauss-Newton normal operator as a 9-point
stencil :class:`Stencil9`)."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from .refine import warp_fine_factor

__all__ = ["FINE", "FINE_COUNTS", "NODE_PX", "BLUR_PX", "FineReference", "NodeGrid", "lanczos_taps", "HeightNodes",
           "Stencil9", "fine_factor", "fine_reference", "fits"]


#: Least refinement of the grid the reference is interpolated from (see :func:`fine_reference`); the
#: image chain takes more for short carriers (:func:`fine_factor`).
FINE = 2


def fine_factor(freq, shape) -> int:
    """How many times finer than the pixels :func:`fine_reference` samples the reference for image
    matching: FD's warp grid rule (:func:`processing.refine.warp_fine_factor`: linear interpolation
    within 1e-3 px on the shortest carrier, a bounded number of samples), at least :data:`FINE`.

    2 for the 11.5-20 px carriers of a 2 mm board at 0.1 mm/px, 3 for 8 px carriers. Measured
    (docs/processing.md section 6) on the pure cosines of 8 px with J0 ring waves (issue 19): 2x
    finer 0.64 % full-grid displacement error, 3x 0.42 %, 4x 0.41 %, 8x 0.39 %: on 2x the linear
    interpolation's pull towards the fine samples (0.0034 px at 2 x 8 px, ``linear_interpolation_shift_px``)
    was image matching's largest error in the middle of the frame.
    """
    return max(FINE, warp_fine_factor(freq, shape))


#: Counts of the 16-bit samples of :class:`FineReference` (its grey-level range over 0..65535).
FINE_COUNTS = 65535


@dataclasses.dataclass(frozen=True)
class FineReference:
    """The reference sampled ``factor`` times finer than the pixels (:func:`fine_reference`),
    kept as 16-bit counts: grey level ``= offset + scale * count``.

    Why 16 bits: the warp (:func:`processing.dic._warp`) reads about two thirds of these
    samples at every Gauss-Newton step, and at 1024^2 with 8 px carriers (3x finer, 3072^2
    samples) float32 samples are 36 MiB, more than the cache: ``cv2.remap`` of them took 5.8 ms,
    of 16-bit counts 3.4 ms (one thread, 5 Dec 2026). The counts' step is the reference's
    grey-level range / 65535 (a 12-bit reference: 0.06 grey levels, rms rounding 0.018 of a camera
    count), far below a camera's own quantisation and noise.

    Attributes
    ----------
    counts : ndarray uint16 (factor * rows, factor * cols)
        Sample ``(i, j)`` at pixel ``(i / factor, j / factor)``.
    factor : int
    offset, scale : float
        Grey level of count 0, grey levels per count.
    """

    counts: np.ndarray
    factor: int
    offset: float
    scale: float

    @property
    def shape(self):
        """Shape of :attr:`counts` (samples)."""
        return self.counts.shape

    def grey(self, counts):
        """Grey levels (float32) of ``counts`` (any shape; interpolated counts too), in place
        where ``counts`` is float32 already."""
        x = counts if counts.dtype == np.float32 else counts.astype(np.float32)
        x *= np.float32(self.scale)
        x += np.float32(self.offset)
        return x


def fine_reference(reference, factor: int = FINE) -> FineReference:
    """The reference, cubic-spline interpolated to a grid ``factor`` times finer
    (sample ``i`` at pixel ``i / factor``), as 16-bit counts (:class:`FineReference`).

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
    factor = int(factor)
    r = np.arange(factor * ref.shape[0]) / factor
    c = np.arange(factor * ref.shape[1]) / factor
    coef = ndimage.spline_filter(ref, order=3, mode="mirror")
    out = np.empty((r.size, c.size), np.float32)
    # rows in blocks: the coordinate arrays stay small
    step = max(1, 2_000_000 // max(c.size, 1))
    for i in range(0, r.size, step):
        rr, cc = np.meshgrid(r[i:i + step], c, indexing="ij")
        out[i:i + step] = ndimage.map_coordinates(coef, [rr, cc], order=3, prefilter=False, mode="mirror")
    lo, hi = float(out.min()), float(out.max())
    scale = (hi - lo) / FINE_COUNTS if hi > lo else 1.0
    out -= np.float32(lo)
    out *= np.float32(1.0 / scale)
    counts = np.rint(out, out=out).clip(0, FINE_COUNTS).astype(np.uint16)
    return FineReference(counts=counts, factor=factor, offset=lo, scale=scale)


# ------------------------------------------------------------------ node grid
#: Node spacing of the global solve, pixels (frame sides must be multiples of it).
NODE_PX = 4

#: Gaussian blur (sigma, pixels) applied to the frame and to the warped reference.
BLUR_PX = 1.25


def fits(frame_shape) -> bool:
    """Whether frames of ``frame_shape`` suit the node grid (sides multiples of
    :data:`NODE_PX`, at least 5 nodes each way)."""
    rows, cols = frame_shape
    return rows % NODE_PX == 0 and cols % NODE_PX == 0 and min(rows, cols) >= 5 * NODE_PX


def lanczos_taps(n_nodes: int, n_px: int):
    """``(index, weight)``, each (n_px, 8), int64 and float32: the node taps of each pixel in
    OpenCV's Lanczos resize (``cv2.INTER_LANCZOS4``) of ``n_nodes`` samples to ``n_px``
    (:func:`processing.fullgrid.lanczos_matrix`'s nonzero entries: taps the edge's clamping
    merges are one), unused taps weight 0."""
    from .fullgrid import lanczos_matrix

    a = lanczos_matrix(n_px, n_nodes)
    index = np.zeros((n_px, 8), np.int64)
    weight = np.zeros((n_px, 8), np.float32)
    for j in range(n_px):
        taps = np.flatnonzero(a[j])
        index[j, :taps.size] = taps
        weight[j, :taps.size] = a[j, taps]
    return index, weight


class NodeGrid:
    """Nodes every ``s`` pixels at ``j * s + (s - 1) / 2`` (cv2.resize's
    pixel-centre convention) and the bilinear node -> pixel map ``P``."""

    def __init__(self, frame_shape, s: int = NODE_PX):
        rows, cols = frame_shape
        if rows % s or cols % s:
            raise ValueError(f"the image refinement needs frame sides that are multiples of {s} px; "
                             f"got {rows} x {cols}: crop the frames (region of interest) or use refine_method='fd'")
        self.s = s
        self.frame_shape = (rows, cols)
        self.shape = (rows // s, cols // s)
        self.rows_px = np.arange(self.shape[0]) * s + (s - 1) / 2.0
        self.cols_px = np.arange(self.shape[1]) * s + (s - 1) / 2.0
        self._taps = None  # lanczos_taps of the rows and of the columns, made on first use

    def warp_map(self, u, factor: int, threads: int = 1) -> np.ndarray:
        """``cv2.remap``'s map (rows, cols, 2) float32 (column, row) into a grid ``factor``
        times finer of the pixels ``r - u(r)``: the node displacement ``u`` (2, node rows,
        node columns; pixels) resampled to every pixel as OpenCV's Lanczos resize does
        (:func:`lanczos_taps`, the same taps and sums to float32 rounding), in two compiled
        passes (:mod:`processing.dic_kernels`) that write the map directly; the pixel rows in
        bands on ``threads``.  Was ``factor * (identity - resize(u))`` of full-size
        two-channel arrays: 4.1 -> 1.8 ms a 1024^2 frame, one thread (5 Dec 2026)."""
        from .dic_kernels import lanczos_columns, warp_map_rows
        from .pools import thread_map

        if self._taps is None:
            self._taps = (lanczos_taps(self.shape[0], self.frame_shape[0]),
                          lanczos_taps(self.shape[1], self.frame_shape[1]))
        (i_r, w_r), (i_c, w_c) = self._taps
        rows, cols = self.frame_shape
        m_r, m_c = self.shape
        # node columns as rows, (u_col, u_row) interleaved along them
        u_t = cv2.merge([np.ascontiguousarray(u[1], np.float32).T, np.ascontiguousarray(u[0], np.float32).T])
        h_t = np.empty((cols, 2 * m_r), np.float32)
        lanczos_columns(u_t.reshape(m_c, 2 * m_r), i_c, w_c, h_t)
        h = cv2.transpose(h_t.reshape(cols, m_r, 2)).reshape(m_r, 2 * cols)
        out = np.empty((rows, cols, 2), np.float32)
        flat = out.reshape(rows, 2 * cols)
        n_bands = max(1, min(int(threads), rows // 64))
        edges = [rows * b // n_bands for b in range(n_bands + 1)]

        def band(r0, r1):
            warp_map_rows(h, i_r, w_r, factor, r0, r1, flat, np.empty(2 * cols, np.float32))

        thread_map(band, [(edges[b], edges[b + 1]) for b in range(n_bands)], threads)
        return out

    def up(self, x, interpolation=cv2.INTER_LINEAR):
        rows, cols = self.frame_shape
        return cv2.resize(np.ascontiguousarray(x, np.float32), (cols, rows), interpolation=interpolation)

    def down(self, x):
        """Cell means (pixels -> nodes)."""
        return cv2.resize(np.ascontiguousarray(x, np.float32), (self.shape[1], self.shape[0]),
                          interpolation=cv2.INTER_AREA)


# ------------------------------------------------------------------ height on the node grid
def _tent_weights(s: int, quadratic: bool) -> np.ndarray:
    """``(s, k)`` weights of the ``s`` pixels between two nodes: the lower and
    upper node's bilinear weight (k = 2), or their squares and product (k = 3)."""
    f = (np.arange(s) + 0.5) / s
    cols = [(1 - f) ** 2, f ** 2, (1 - f) * f] if quadratic else [1 - f, f]
    return np.stack(cols, axis=1).astype(np.float32)


def _pair_sums(x, s, quadratic, axis):
    """Pixels -> nodes along ``axis`` (0 or 1) through cv2's bilinear weights
    ``P[p, i]`` (nodes every ``s`` px at ``j s + (s - 1) / 2``, clamped outside).

    quadratic: ``(sum_p P[p,i]^2 x[p], sum_p P[p,i] P[p,i+1] x[p])``;
    else ``sum_p P[p,i] x[p]`` (the exact transpose of the resize).  Along the
    columns compiled (:func:`processing.dic_kernels.column_pairs`)."""
    n = x.shape[axis]
    m = n // s
    hs = s // 2
    W = _tent_weights(s, quadratic)
    if axis == 1:
        from .dic_kernels import column_pairs

        out = np.empty((x.shape[0], m), np.float32)
        off = np.empty((x.shape[0], m - 1), np.float32) if quadratic else out
        column_pairs(np.ascontiguousarray(x, np.float32), W, out, off)
        return (out, off) if quadratic else out
    parts = W.T @ x[hs:n - hs].reshape(m - 1, s, -1)  # (m - 1, k, cols)
    parts = [parts[:, k] for k in range(W.shape[1])]
    first, last = x[:hs].sum(axis=0), x[n - hs:].sum(axis=0)
    out = np.zeros((m, x.shape[1]), np.float32)
    out[:-1] += parts[0]
    out[1:] += parts[1]
    out[0] += first
    out[-1] += last
    return (out, parts[2]) if quadratic else out


class Stencil9:
    """Symmetric 9-point node stencil ``P^T N P`` (N diagonal on the pixels)
    from its coefficients ``dd`` self, ``do`` (i,j)-(i,j+1), ``od`` (i,j)-(i+1,j),
    ``oo`` (i,j)-(i+1,j+1) and (i,j+1)-(i+1,j); applied on the flat
    (row-major) node index, each neighbour a contiguous shifted slice."""

    def __init__(self, dd, do, od, oo):
        self.shape = dd.shape
        self.parts = (dd, do, od, oo)
        self.dd = dd.ravel()
        self._mean_row_sum = float(np.mean(dd) + 2 * np.mean(do) + 2 * np.mean(od) + 4 * np.mean(oo))
        self._links = None  # made by the first product (the compiled CG reads the parts)

    def mean_row_sum(self) -> float:
        return self._mean_row_sum

    def _flat(self, x, c0):
        """Coefficient between node k and k + offset, at k (flat, zero beyond ``x``)."""
        out = np.zeros(self.shape, np.float32)
        out[:x.shape[0], c0:c0 + x.shape[1]] = x
        return out.ravel()

    def __matmul__(self, x):
        if self._links is None:
            m_c, m = self.shape[1], self.dd.size
            _, do, od, oo = self.parts
            self._links = [(off, coef[:m - off]) for off, coef in
                           ((1, self._flat(do, 0)), (m_c, self._flat(od, 0)), (m_c + 1, self._flat(oo, 0)),
                            (m_c - 1, self._flat(oo, 1)))]
        xf = x.ravel()
        y = self.dd * xf
        t = np.empty_like(y)
        for off, c in self._links:
            n = c.size
            np.multiply(c, xf[off:], out=t[:n])
            y[:n] += t[:n]
            np.multiply(c, xf[:n], out=t[:n])
            y[off:] += t[:n]
        return y.reshape(self.shape)


class HeightNodes:
    """The height on a :class:`NodeGrid` and the exact linear optics of the
    geometry (:meth:`Geometry.linear_response` at the nodes):
    ``u = a h + B grad_px h`` (pixels), ``grad_px`` fourth-order central
    differences of the node heights (second-order at the borders)."""

    def __init__(self, geometry, grid: NodeGrid):
        if grid.s % 2 or min(grid.shape) < 5:
            raise ValueError("the height refinement needs an even node spacing and at least 5 x 5 nodes")
        self.grid = grid
        self._dense = None
        self._kernel_cache = {}
        lr = geometry.linear_response(grid.rows_px[:, None], grid.cols_px[None, :], grid.frame_shape)

        def coef(x):  # a constant (telecentric camera) as a scalar, 0 as None
            x = np.asarray(x, np.float64)
            if np.all(x == 0):
                return None
            if np.allclose(x, x.flat[0], rtol=1e-12, atol=0):
                return float(x.flat[0])
            return x.astype(np.float32)

        self.a = [coef(lr.a[..., i]) for i in range(2)]
        self.B = [[coef(lr.B[..., i, j]) for j in range(2)] for i in range(2)]
        self.B_mean = lr.B.reshape(-1, 2, 2).mean(axis=0)
        m_r, m_c = grid.shape
        s = grid.s
        kr = np.pi * np.arange(m_r) / m_r
        kc = np.pi * np.arange(m_c) / m_c
        d1r = ((8 * np.sin(kr) - np.sin(2 * kr)) / 6 / s) ** 2
        d1c = ((8 * np.sin(kc) - np.sin(2 * kc)) / 6 / s) ** 2
        self.symbol_d1 = (d1r[:, None], d1c[None, :])  # DCT symbols of D1^T D1 (rows, cols)
        self.symbol_reg = (2 - 2 * np.cos(kr))[:, None] ** 3 + (2 - 2 * np.cos(kc))[None, :] ** 3

    def dense_response(self):
        """``(6, m_r, m_c)`` float32 ``a_r, a_c, B_rr, B_rc, B_cr, B_cc``, zeros where
        the geometry has no such term (the compiled operator's input,
        :func:`processing.dic_kernels.normal_apply`); built once."""
        if self._dense is None:
            terms = [self.a[0], self.a[1], self.B[0][0], self.B[0][1], self.B[1][0], self.B[1][1]]
            self._dense = np.stack([np.broadcast_to(np.asarray(0.0 if t is None else t, np.float32), self.grid.shape)
                                    for t in terms])
        return self._dense

    def _kernel_args(self, dtype):
        """``(coef, present, constants)`` of the compiled node operators for arrays of ``dtype``
        (float32 or float64): the six coefficients a_r, a_c, B_rr, B_rc, B_cr, B_cc as NumPy's
        expressions meet them (a float32 array, or a scalar taken in the array's type), which of
        them the geometry has, and D1's constants and the node spacing; built once per type."""
        dtype = np.dtype(dtype)
        if dtype not in self._kernel_cache:
            terms = [self.a[0], self.a[1], self.B[0][0], self.B[0][1], self.B[1][0], self.B[1][1]]
            coef = np.stack([np.broadcast_to(np.asarray(0.0 if t is None else t).astype(dtype), self.grid.shape)
                             for t in terms])
            present = np.array([t is not None for t in terms])
            constants = np.array([8.0, 12.0, 0.5, 1.5, 2.0, -1.5, self.grid.s], dtype)
            self._kernel_cache[dtype] = (coef, present, constants)
        return self._kernel_cache[dtype]

    @staticmethod
    def _float(x):
        """``x`` as float32 or float64 (what the compiled node operators take)."""
        x = np.asarray(x)
        return x if x.dtype in (np.float32, np.float64) else x.astype(np.float64)

    def displacement(self, h):
        """``(2, m_r, m_c)`` displacement (pixels) at the nodes of node heights ``h`` (mm):
        ``u_i = a_i h + B_i0 D1r h + B_i1 D1c h`` (:func:`processing.dic_node_ops.node_displacement`,
        ``h``'s type)."""
        from .dic_node_ops import node_displacement

        h = self._float(h)
        out = np.empty((2,) + h.shape, h.dtype)
        node_displacement(h, *self._kernel_args(h.dtype), out)
        return out

    def displacement_T(self, vr, vc):
        """Transpose of :meth:`displacement` (:func:`processing.dic_node_ops.node_displacement_T`)."""
        from .dic_node_ops import node_displacement_T

        vr, vc = self._float(vr), self._float(vc)
        vc = vc.astype(vr.dtype, copy=False)
        out = np.empty(vr.shape, vr.dtype)
        node_displacement_T(vr, vc, *self._kernel_args(vr.dtype), out)
        return out

    @staticmethod
    def regulariser(h):
        """``(D3r^T D3r + D3c^T D3c) h`` (:func:`processing.dic_node_ops.node_regulariser`, ``h``'s type)."""
        from .dic_node_ops import node_regulariser

        h = HeightNodes._float(h)
        out = np.empty(h.shape, h.dtype)
        node_regulariser(h, h.dtype.type(3.0), out)
        return out

    def node_normal(self, n_px):
        """``P^T N P`` for the pixel weight ``n_px`` (:class:`Stencil9`)."""
        s = self.grid.s
        xd, xo = _pair_sums(n_px, s, True, 0)
        dd, do = _pair_sums(xd, s, True, 1)
        od, oo = _pair_sums(xo, s, True, 1)
        return Stencil9(dd, do, od, oo)

    def column_sums(self, xd, xo, xl):
        """``(Nrr, Nrc, Ncc, br, bc)`` from the row sums of
        :func:`processing.dic_kernels.row_moments` (node rows x pixel columns):
        the sums along the columns that :meth:`node_normal` and :meth:`node_rhs`
        do after their row sums."""
        s = self.grid.s
        out = []
        for q in range(3):
            dd, do = _pair_sums(np.ascontiguousarray(xd[q]), s, True, 1)
            od, oo = _pair_sums(np.ascontiguousarray(xo[q]), s, True, 1)
            out.append(Stencil9(dd, do, od, oo))
        return (*out, *self.column_rhs(xl))

    def column_rhs(self, xl):
        """``(br, bc)`` alone from the row sums ``xl`` (:meth:`column_sums`)."""
        s = self.grid.s
        return tuple(_pair_sums(np.ascontiguousarray(xl[q]), s, False, 1) for q in range(2))

    def node_rhs(self, y_px):
        """``P^T y`` (m_r, m_c)."""
        s = self.grid.s
        return _pair_sums(_pair_sums(y_px, s, False, 0), s, False, 1)
