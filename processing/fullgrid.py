"""Decimated results to every pixel (step 8 of :mod:`processing.reconstruct`):
:class:`Upsampler`, :func:`interpolate_full` (checkerboards, Lanczos),
:func:`dots_full` (the PIV grid, cubic spline), :func:`full_coordinates`."""

from __future__ import annotations

import dataclasses
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np

from .fill import nearest_fill_index
from .result import Result

__all__ = ["Upsampler", "run_pair", "resize_all", "full_coordinates", "interpolate_full", "dots_full", "full_ifft"]


class Upsampler:
    """Decimated grid -> every pixel (cv2.resize; the decimated samples sit at
    the pixel-centre positions cv2.resize assumes, see Demodulator.rows_px)."""

    def __init__(self, shape, window_shape, interpolation="cubic"):
        self.shape = shape
        self.interpolation = {"cubic": cv2.INTER_CUBIC, "lanczos": cv2.INTER_LANCZOS4,
                              "linear": cv2.INTER_LINEAR}[interpolation]

    def __call__(self, field, interpolation=None, out=None):
        src = np.ascontiguousarray(field, dtype=np.float32)
        ip = self.interpolation if interpolation is None else interpolation
        if out is None:
            return cv2.resize(src, (self.shape[1], self.shape[0]), interpolation=ip)
        cv2.resize(src, (self.shape[1], self.shape[0]), dst=out, interpolation=ip)
        return out

    def mask(self, valid):
        v = self(valid.astype(np.float32), cv2.INTER_LINEAR)
        return v > 0.999


_POOL = None
_POOL_LOCK = threading.Lock()


def _pool():
    global _POOL
    if _POOL is None:
        with _POOL_LOCK:
            if _POOL is None:
                _POOL = ThreadPoolExecutor(2, thread_name_prefix="tirdeflect-resize")
    return _POOL


def run_pair(shape, job_a, job_b, threads=2):
    """Run two full-size jobs (numpy/cv2 release the GIL), in parallel on large frames
    when ``threads`` > 1 (one thread: a worker of a parallel batch run, whose
    cores are taken by the other workers)."""
    if shape[0] * shape[1] < 600_000 or threads < 2:
        job_a()
        job_b()
        return
    other = _pool().submit(job_b)
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
    surface (the convention of processing.height)."""
    rows, cols = shape
    rcen = np.array([[(rows - 1) / 2.0]])
    ccen = np.array([[(cols - 1) / 2.0]])
    x = np.asarray(geometry.surface_point(rcen, np.arange(cols, dtype=float)[None, :], shape)[0], float)
    y = np.asarray(geometry.surface_point(np.arange(rows, dtype=float)[:, None], ccen, shape)[1], float)
    return (np.broadcast_to(x.ravel(), (cols,)).copy(), np.broadcast_to(y.ravel(), (rows,)).copy())


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
    """Decimated result -> every pixel (the decimated grid is oversampled
    twice, so Lanczos interpolation is within 0.2 % of band-limited).

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
    wrapped = np.angle(gf * np.conj(chain.full_reference_signal()))
    guide = np.stack([up(np.nan_to_num(phase[s])) for s in range(2)])
    full_phase = wrapped + 2 * np.pi * np.round((guide - wrapped) / (2 * np.pi))
    uf = d.phase_to_displacement(full_phase)
    corr = np.nan_to_num(np.where(valid, u - u_first, 0.0))
    uf = uf + np.stack([up(corr[0]), up(corr[1])])
    uf = np.where(valid_full, uf, np.nan).astype(np.float32)
    surf = surface_from_displacement(uf, valid_full, chain.geometry, rows_px=np.arange(rows, dtype=float),
                                     cols_px=np.arange(cols, dtype=float), frame_shape=chain.shape,
                                     solver=o.solver, reference_mask=chain.full_reference_region(),
                                     pin_fallback=o.pin_fallback, region_name=chain.region.name)
    valid_full = np.asarray(surf.valid, bool)
    timings["height"] = 1e3 * (time.perf_counter() - t3)
    return Result(height=np.asarray(surf.height_mm, np.float32), valid=valid_full,
                  slope_x=np.asarray(surf.slope_x, np.float32), slope_y=np.asarray(surf.slope_y, np.float32),
                  displacement=uf, amplitude=up(amplitude), x_mm=np.asarray(surf.x_mm),
                  y_mm=np.asarray(surf.y_mm), grid="full",
                  rows_px=np.arange(rows, dtype=float), cols_px=np.arange(cols, dtype=float),
                  carriers=chain.carriers, phase=np.asarray(phase, np.float32),
                  valid_fraction=float(valid_full.mean()), timings_ms=timings, pin=surf.pin)
