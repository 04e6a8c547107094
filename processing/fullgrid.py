"""Decimated results to every pixel (step 8 of :mod:`processing.reconstruct`):
:class:`Upsampler`, :func:`interpolate_full` (checkerboards, cubic B-spline),
:func:`dots_full` (the PIV grid, cubic spline), :func:`full_coordinates`."""

from __future__ import annotations

import dataclasses
import threading
import time

import cv2
import numpy as np

from .angle_kernels import angle_of_product
from .fill import nearest_fill_index
from .fullgrid_kernels import sparse_rows, spline_prefilter
from .pools import pool
from .result import Result

__all__ = ["Upsampler", "run_pair", "resize_all", "full_coordinates", "grid_surface_positions", "interpolate_full",
           "dots_full", "full_ifft", "lanczos_matrix", "spline_weights", "spline_taps", "spline_taps_matrix",
           "spline_matrix_at", "spline_matrix"]


def spline_weights(n_out: int, n_in: int):
    """``(index, weight)``, each (n_out, 4): the cubic B-spline taps that take
    ``n_in`` spline coefficients to ``n_out`` values, sample ``j`` at output
    position ``(j + 0.5) n_out / n_in - 0.5`` (cv2.resize's pixel-centre
    mapping); coefficients beyond the ends mirrored about the half sample
    (``scipy.ndimage``'s ``mode="reflect"``, which :func:`spline_coefficients` matches)."""
    return spline_taps(pixel_centres(n_out, n_in), n_in)


def pixel_centres(n_out: int, n_in: int) -> np.ndarray:
    """Where ``n_out`` output samples sit on a grid of ``n_in`` (cv2.resize's pixel-centre mapping), samples
    (float64)."""
    return (np.arange(n_out, dtype=np.float64) + 0.5) * (n_in / n_out) - 0.5


def spline_taps(pos, n_in: int):
    """``(index, weight)``, each (n, 4): the cubic B-spline taps of ``n_in`` spline
    coefficients at the positions ``pos`` (in samples of the input grid), mirror ends as
    :func:`spline_weights`."""
    pos = np.asarray(pos, np.float64)
    n_out = pos.size
    i0 = np.floor(pos).astype(np.int64)
    t = (pos - i0)[:, None]
    weight = np.concatenate([(1 - t) ** 3, 3 * t**3 - 6 * t**2 + 4, -3 * t**3 + 3 * t**2 + 3 * t + 1, t**3],
                            axis=1) / 6.0
    index = i0[:, None] + np.arange(-1, 3)[None, :]
    for _ in range(2):  # half-sample mirror (twice: grids of 1-2 samples)
        index = np.where(index < 0, -index - 1, index)
        index = np.where(index >= n_in, 2 * n_in - index - 1, index)
    return np.clip(index, 0, n_in - 1), weight


def spline_taps_matrix(pos, n_in: int, dtype=np.float64):
    """(n, n_in) sparse matrix of :func:`spline_taps`: cubic B-spline coefficients of a
    grid of ``n_in`` samples to its values at ``pos`` (samples); the coefficients by
    :func:`spline_coefficients` or ``scipy.ndimage.spline_filter(..., mode="reflect")``."""
    from scipy import sparse

    index, weight = spline_taps(pos, n_in)
    n = index.shape[0]
    m = sparse.csr_matrix((weight.ravel().astype(dtype), index.ravel(), np.arange(0, 4 * n + 1, 4)), shape=(n, n_in))
    m.sum_duplicates()
    return m


def spline_matrix_at(pos, n_in: int) -> np.ndarray:
    """(n, n_in) float32: the cubic B-spline interpolation of a grid of ``n_in`` samples at
    the positions ``pos`` (samples), its prefilter folded in (a dense matrix: one product
    per axis takes samples to values)."""
    from scipy import ndimage

    prefilter = ndimage.spline_filter1d(np.eye(n_in), order=3, axis=0, mode="reflect")
    return np.asarray(spline_taps_matrix(pos, n_in) @ prefilter).astype(np.float32)


def spline_coefficients(field, dtype=np.float32) -> np.ndarray:
    """Cubic B-spline coefficients of a 2-D grid of samples (mirror ends, ``scipy.ndimage``'s
    ``mode="reflect"``), computed in float64 (:func:`processing.fullgrid_kernels.spline_prefilter`,
    along the rows then the columns, as ``scipy.ndimage.spline_filter``: the same bits on grids of
    20 or more samples a side, 0.39 against 0.85 ms at 256^2), returned as ``dtype``."""
    coef = np.array(field, np.float64, order="C")  # a copy: filtered in place
    if coef.ndim != 2:
        raise ValueError(f"spline_coefficients needs a 2-D grid of samples, got shape {coef.shape}")
    spline_prefilter(coef, 0)
    spline_prefilter(coef, 1)
    return coef.astype(dtype, copy=False)


def lanczos_matrix(n_out: int, n_in: int) -> np.ndarray:
    """(n_out, n_in) float32 matrix of cv2.resize's INTER_LANCZOS4 along one axis
    (8 taps, pixel-centre mapping, replicated border): ``A @ f @ B.T`` is
    ``cv2.resize(f, (n_cols_out, n_rows_out), interpolation=INTER_LANCZOS4)``
    to float32 rounding (measured 2.5e-6 of the values at 171 -> 1024)."""
    scale = n_in / n_out
    A = np.zeros((n_out, n_in), np.float64)
    s45 = 0.70710678118654752440084436210485
    cs = ((1, 0), (-s45, -s45), (0, 1), (s45, -s45), (-1, 0), (s45, s45), (0, -1), (-s45, s45))
    for d in range(n_out):
        fx = np.float32((d + 0.5) * scale - 0.5)
        sx = int(np.floor(fx))
        x = np.float32(fx - sx)
        y0 = -(x + 3) * np.pi * 0.25
        s0, c0 = np.sin(y0), np.cos(y0)
        co = np.empty(8, np.float32)
        for i in range(8):
            t = np.float32(x + 3 - i)
            if abs(t) >= 1e-6:
                y = -t * np.pi * 0.25
                co[i] = np.float32((cs[i][0] * s0 + cs[i][1] * c0) / (y * y))
            else:
                co[i] = np.float32(1e30)
        co *= np.float32(1.0 / co.sum(dtype=np.float32))
        for i in range(8):
            A[d, min(max(sx - 3 + i, 0), n_in - 1)] += co[i]
    return A.astype(np.float32)


def spline_matrix(n_out: int, n_in: int) -> np.ndarray:
    """(n_out, n_in) float32: the cubic B-spline interpolation of :class:`Upsampler`
    along one axis (prefilter included), so that ``A @ f @ B.T`` is
    ``Upsampler(..., "spline")(f)`` (the GPU chain's two matrix products)."""
    return spline_matrix_at(pixel_centres(n_out, n_in), n_in)


class _SplineResize:
    """Cubic B-spline interpolation from one grid shape to the frame's: the
    coefficients by the exact recursive prefilter on the small grid, then four
    taps per axis as two sparse products (built once per source shape)."""

    def __init__(self, shape, src_shape):
        self.mats = [spline_taps_matrix(pixel_centres(n_out, n_in), n_in, np.float32)
                     for n_out, n_in in zip(shape, src_shape)]

    def __call__(self, field, out):
        along_rows, along_cols = self.mats
        bad = ~np.isfinite(field)
        if bad.any():
            # the prefilter would spread a NaN over the whole grid: NaN only
            # where a linear resize of the bad samples reaches, as cv2 does
            self(np.where(bad, np.float32(0.0), field), out)
            reach = cv2.resize(bad.astype(np.float32), (out.shape[1], out.shape[0]), interpolation=cv2.INTER_LINEAR)
            np.copyto(out, np.float32(np.nan), where=reach > 0)
            return out
        coef = spline_coefficients(field)
        half = np.ascontiguousarray((along_cols @ coef.T).T)  # (m_rows, cols)
        sparse_rows(along_rows.indptr, along_rows.indices, along_rows.data, half, out)  # along_rows @ half
        return out


class Upsampler:
    """Decimated grid -> every pixel (the decimated samples sit at the
    pixel-centre positions cv2.resize assumes, see Demodulator.rows_px).

    ``"spline"``: cubic B-spline interpolation (the default of
    :class:`processing.options.ReconstructOptions`); it reproduces cubics
    exactly.  cv2's kernels do not: Lanczos4 (a windowed sinc) moves a
    sample's value by up to 0.053 px at a 3.66 px grid (the first moment of
    its weights, alternating with the sub-sample position), which on the
    ray-traced pure cosines of issue 19 put 0.28 % of the displacement's
    RMS into the full grid from the true decimated displacement alone (the
    spline 0.01 %); cubic (a = -0.75) 1.8 %, linear 2.4 %.  The others stay
    for comparison (``full_interpolation``) and for the masks (linear)."""

    def __init__(self, shape, window_shape, interpolation="spline"):
        self.shape = shape
        self.kind = interpolation
        self.interpolation = {"cubic": cv2.INTER_CUBIC, "lanczos": cv2.INTER_LANCZOS4,
                              "linear": cv2.INTER_LINEAR, "spline": None}[interpolation]
        self._spline = {}
        self._lock = threading.Lock()

    def _spline_for(self, src_shape):
        sp = self._spline.get(src_shape)
        if sp is None:
            with self._lock:
                sp = self._spline.get(src_shape)
                if sp is None:
                    sp = self._spline[src_shape] = _SplineResize(self.shape, src_shape)
        return sp

    def __call__(self, field, interpolation=None, out=None):
        src = np.ascontiguousarray(field, dtype=np.float32)
        ip = self.interpolation if interpolation is None else interpolation
        if ip is None:
            if out is None:
                out = np.empty(self.shape, np.float32)
            return self._spline_for(src.shape)(src, out)
        if out is None:
            return cv2.resize(src, (self.shape[1], self.shape[0]), interpolation=ip)
        cv2.resize(src, (self.shape[1], self.shape[0]), dst=out, interpolation=ip)
        return out

    def mask(self, valid):
        v = self(valid.astype(np.float32), cv2.INTER_LINEAR)
        return v > 0.999

    def cell_means(self, field, cell_px: int) -> np.ndarray:
        """Means over cells of ``cell_px`` x ``cell_px`` pixels of the field interpolated to
        every pixel, float32 (frame sides multiples of ``cell_px``): what
        ``cv2.resize(self(field), cells, interpolation=cv2.INTER_AREA)`` gives, to float32
        rounding, without the full-size field (the spline's taps and the cells' means folded
        into one sparse matrix per axis; other kinds through the full-size field)."""
        src = np.ascontiguousarray(field, dtype=np.float32)
        rows, cols = self.shape
        cells = (rows // cell_px, cols // cell_px)
        if self.interpolation is not None or not np.isfinite(src).all():
            # (a NaN sample: NaN wherever the full-size path puts it)
            return cv2.resize(self(src), (cells[1], cells[0]), interpolation=cv2.INTER_AREA)
        key = ("cells", src.shape, int(cell_px))
        mats = self._spline.get(key)
        if mats is None:
            with self._lock:
                mats = self._spline[key] = [_cell_taps(n_out, n_in, int(cell_px))
                                            for n_out, n_in in zip(self.shape, src.shape)]
        along_rows, along_cols = mats
        coef = spline_coefficients(src)
        half = np.ascontiguousarray((along_cols @ coef.T).T)
        return np.ascontiguousarray(along_rows @ half, dtype=np.float32)


def _cell_taps(n_out: int, n_in: int, cell_px: int):
    """(n_out // cell_px, n_in) sparse float32: the cubic B-spline taps of :class:`_SplineResize`
    along one axis, averaged over each cell of ``cell_px`` output samples."""
    from scipy import sparse

    taps = spline_taps_matrix(pixel_centres(n_out, n_in), n_in, np.float64)
    n_cells = n_out // cell_px
    box = sparse.csr_matrix((np.full(n_cells * cell_px, 1.0 / cell_px), np.arange(n_cells * cell_px),
                             np.arange(0, n_cells * cell_px + 1, cell_px)), shape=(n_cells, n_out))
    return (box @ taps).astype(np.float32).tocsr()


def run_pair(shape, job_a, job_b, threads=2):
    """Run two full-size jobs (numpy/cv2 release the GIL), in parallel on large frames
    when ``threads`` > 1 (one thread: a worker of a parallel batch run, whose
    cores are taken by the other workers)."""
    if shape[0] * shape[1] < 600_000 or threads < 2:
        job_a()
        job_b()
        return
    other = pool(2).submit(job_b)
    job_a()
    other.result()


def resize_all(up, jobs, threads=2):
    """``up(src, out=dst)`` for every (src, dst) pair, two at a time in threads
    (cv2 releases the GIL; measured at 1024^2: four Lanczos resizes 5.4 ms in
    turn, 2.8 ms two at a time; no gain at 512^2, so small frames stay in turn)."""
    def run(part):
        for a, o in part:
            up(a, out=o)

    if len(jobs) < 2:
        run(jobs)
        return
    run_pair(jobs[0][1].shape, lambda: run(jobs[0::2]), lambda: run(jobs[1::2]), threads)


def full_coordinates(geometry, shape):
    """x_mm (cols,), y_mm (rows,) of every pixel column and row: where the
    rays through the frame's central row / column meet the resting
    surface (the convention of processing.height). Every pixel's own where
    the geometry is not separable (a keystoned TIR camera at a finite
    distance): ``geometry.grid_surface_mm``."""
    rows, cols = shape
    rcen = np.array([[(rows - 1) / 2.0]])
    ccen = np.array([[(cols - 1) / 2.0]])
    x = np.asarray(geometry.surface_point(rcen, np.arange(cols, dtype=float)[None, :], shape)[0], float)
    y = np.asarray(geometry.surface_point(np.arange(rows, dtype=float)[:, None], ccen, shape)[1], float)
    return (np.broadcast_to(x.ravel(), (cols,)).copy(), np.broadcast_to(y.ravel(), (rows,)).copy())


def grid_surface_positions(geometry, frame_shape, grid: str, rows_px, cols_px):
    """``(x_mm, y_mm)``, each ``(rows, cols)`` float64: the surface position of every sample of a grid's
    results (``grid`` "full": every pixel of a frame of ``frame_shape``; "decimated": the processing
    grid's ``rows_px`` x ``cols_px``, e.g. a Reconstructor's): ``geometry.grid_surface_mm``;
    None where the geometry is separable (``geometry.surface_separable``) and :func:`full_coordinates`'
    1-D axes already say where every sample lies."""
    if geometry.surface_separable:
        return None
    if grid == "full":
        rows_px, cols_px = np.arange(frame_shape[0]), np.arange(frame_shape[1])
    return geometry.grid_surface_mm(rows_px, cols_px, frame_shape)


def _slopes_from(coef, disp, height, shape, threads):
    """``(slope_x, slope_y)`` as ``coef @ (u_row, u_col, h)`` per pixel (uniform optics)."""
    srcs = (disp[0], disp[1], height)
    slope_x = np.empty(shape, np.float32)
    slope_y = np.empty(shape, np.float32)

    def combine(row, out):
        first = True
        for c, src in zip(row, srcs):
            if c == 0.0:
                continue
            if first:
                np.multiply(src, np.float32(c), out=out)
                first = False
            else:
                cv2.scaleAdd(src, float(c), out, dst=out)
        if first:
            out.fill(0.0)

    run_pair(shape, lambda: combine(coef[0], slope_x), lambda: combine(coef[1], slope_y), threads)
    return slope_x, slope_y


def interpolate_full(res, up, coords, solver=None, threads=2):
    """Decimated result -> every pixel (:class:`Upsampler`: cubic B-spline by default).

    With uniform optics the slopes are fixed linear combinations of u and
    h (:meth:`HeightSolver.slope_coefficients`); interpolation is linear,
    so they are formed from the interpolated u and h instead of being
    interpolated themselves (two resizes fewer, same values up to
    rounding).  ``coords``: :func:`full_coordinates`."""
    shape = up.shape
    rows, cols = shape
    all_valid = bool(res.valid.all())
    if all_valid:
        valid = np.ones(shape, bool)
        fill = None
    else:
        valid = up.mask(res.valid)
        fill = nearest_fill_index(res.valid)
    invalid = None if all_valid else ~valid

    def src(field):
        return field if all_valid else np.nan_to_num(field if fill is None else field[fill])

    coef = solver.slope_coefficients() if solver is not None else None
    derive = coef is not None
    disp = np.empty((2, rows, cols), np.float32)
    height = np.empty(shape, np.float32)
    amplitude = np.empty(shape, np.float32)
    jobs = [(src(res.displacement[0]), disp[0]), (src(res.displacement[1]), disp[1]),
            (src(res.height), height), (res.amplitude, amplitude)]
    if not derive:
        slope_x = np.empty(shape, np.float32)
        slope_y = np.empty(shape, np.float32)
        jobs += [(src(res.slope_x), slope_x), (src(res.slope_y), slope_y)]
    resize_all(up, jobs, threads)
    if derive:
        slope_x, slope_y = _slopes_from(coef, disp, height, shape, threads)
    if invalid is not None:
        for a in (disp, height, slope_x, slope_y):
            np.copyto(a, np.float32(np.nan), where=invalid)
    x_mm, y_mm = coords
    return dataclasses.replace(
        res, height=height, valid=valid, slope_x=slope_x,
        slope_y=slope_y, displacement=disp, amplitude=amplitude,
        x_mm=x_mm, y_mm=y_mm, grid="full",
        rows_px=np.arange(rows, dtype=float), cols_px=np.arange(cols, dtype=float),
        valid_fraction=1.0 if all_valid else float(np.count_nonzero(valid)) / valid.size)


def dots_full(res, shape, coords):
    """PIV grid -> every pixel (cubic spline; pixels beyond the outer
    window centres take the border value; invalid where the nearest sample is)."""
    rows, cols = shape
    rows_px, cols_px = res.rows_px, res.cols_px
    r = (np.arange(rows, dtype=np.float32) - np.float32(rows_px[0])) / np.float32(rows_px[1] - rows_px[0])
    c = (np.arange(cols, dtype=np.float32) - np.float32(cols_px[0])) / np.float32(cols_px[1] - cols_px[0])
    map_r = np.broadcast_to(r[:, None], shape).astype(np.float32)
    map_c = np.broadcast_to(c[None, :], shape).astype(np.float32)
    fill = nearest_fill_index(res.valid)

    from scipy import ndimage

    def up(field):
        # cubic spline through the samples (cv2's cubic kernel measured
        # 2x the height error of the PIV grid itself on ray-traced bumps)
        f = field if fill is None else field[fill]
        return ndimage.map_coordinates(np.nan_to_num(f).astype(np.float64), [map_r, map_c], order=3,
                                       mode="nearest").astype(np.float32)

    valid = cv2.remap(res.valid.astype(np.uint8), map_c, map_r, cv2.INTER_NEAREST,
                      borderMode=cv2.BORDER_REPLICATE).astype(bool)
    nan = np.float32(np.nan)
    out = {k: np.where(valid, up(getattr(res, k)), nan) for k in ("height", "slope_x", "slope_y")}
    disp = np.stack([np.where(valid, up(res.displacement[i]), nan) for i in range(2)])
    x_mm, y_mm = coords
    return dataclasses.replace(res, valid=valid, displacement=disp, amplitude=valid.astype(np.float32),
                               x_mm=x_mm, y_mm=y_mm, grid="full", rows_px=np.arange(rows, dtype=float),
                               cols_px=np.arange(cols, dtype=float), valid_fraction=float(valid.mean()), **out)


def full_ifft(chain, wins, u, u_first, valid, amplitude, phase, timings, t3):
    """Full grid from full-size inverse FFTs (``full_method="ifft"``), unwrapped
    against the decimated phase; height solved on the full grid (slow, exact).
    ``chain``: the :class:`processing.chain_checkerboard.CheckerboardChain`."""
    from .height import surface_from_displacement

    rows, cols = chain.shape
    up, d, o = chain.upsampler, chain.demod, chain.options
    valid_full = up.mask(valid)
    gf = d.full_from_windows(wins)
    wrapped = angle_of_product(gf, np.conj(chain.full_reference_signal()))
    guide = np.stack([up(np.nan_to_num(phase[s])) for s in range(2)])
    full_phase = wrapped + 2 * np.pi * np.round((guide - wrapped) / (2 * np.pi))
    uf = d.phase_to_displacement(full_phase)
    corr = np.nan_to_num(np.where(valid, u - u_first, 0.0))
    uf = uf + np.stack([up(corr[0]), up(corr[1])])
    _, turn = chain.judge_turn(u, valid)
    if turn.removed:  # the turn taken out as the decimated chain does, here on every pixel
        uf = uf - chain.turn_gauge().field(turn.turn_mrad, np.arange(rows), np.arange(cols), turn.removed)
    uf = np.where(valid_full, uf, np.nan).astype(np.float32)
    surf = surface_from_displacement(uf, valid_full, chain.geometry, rows_px=np.arange(rows, dtype=float),
                                     cols_px=np.arange(cols, dtype=float), frame_shape=chain.shape,
                                     solver=o.solver, reference_mask=chain.full_reference_region(),
                                     pin_fallback=o.pin_fallback, region_name=chain.region.name,
                                     shift_removal=o.shift_removal)
    valid_full = np.asarray(surf.valid, bool)
    timings["height"] = 1e3 * (time.perf_counter() - t3)
    return Result(height=np.asarray(surf.height_mm, np.float32), valid=valid_full,
                  slope_x=np.asarray(surf.slope_x, np.float32), slope_y=np.asarray(surf.slope_y, np.float32),
                  displacement=uf, amplitude=up(amplitude), x_mm=np.asarray(surf.x_mm),
                  y_mm=np.asarray(surf.y_mm), grid="full",
                  rows_px=np.arange(rows, dtype=float), cols_px=np.arange(cols, dtype=float),
                  carriers=chain.carriers, phase=np.asarray(phase, np.float32),
                  valid_fraction=float(valid_full.mean()), timings_ms=timings, pin=surf.pin, turn=turn)
