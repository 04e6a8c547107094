"""The Reconstructor's chain on a GPU (CuPy), batched over frames.

:class:`BatchChain` runs, for a batch of frames at once and with the
constants of one :class:`~processing.reconstruct.Reconstructor`: apodization,
the real FFT of each frame, both carrier windows and their small inverse
FFTs (decimated grid), phase, amplitude ratio and mask, temporal unwrapping
(a cumulative sum of the wrapped changes over the batch, with the reference
region kept nearest 0 as the CPU path does), displacement, the fold test,
the bias-removal iteration (upsampling of ``u`` as two matrix products with
cv2's INTER_LANCZOS4 weights, as the CPU's warp maps; the band-limited reference
warped as on the CPU: its carriers' envelopes bilinearly with cv2.remap's reflecting
border, the carriers exact; its FFT and windows), the
spectral height solve (as matrix products) and the full grid (the CPU's
kernel as two matrix products: the cubic B-spline of
:func:`processing.fullgrid.spline_matrix`, or Lanczos4 with
``full_interpolation="lanczos"``; slopes as the linear map of u and h). Written against an array module
``xp``: CuPy on the GPU; NumPy runs the very same code on the CPU, which is
how it is tested where there is no GPU (tests/processing/test_gpu.py).

What stays on the CPU, frame by frame, through the Reconstructor itself:

- the first frame of a series (spatial unwrapping; 2 x m^2 samples go to
  the CPU and back);
- any frame with invalid samples (low contrast, folds) or whose change since
  the previous frame has 2 pi jumps, and the rest of its batch: masks,
  island removal, masked CG height solve and growing into newly valid
  samples are sequential, irregular work that the CPU path does well;
- geometries without uniform optics (a finite camera distance: no spectral
  solver) and ``full_method="ifft"``: every frame;
- on the full grid, a frame whose heights need the second-order solve
  (:mod:`processing.second_order`), and the rest of its batch;
- the cheap pattern check (frames of one recording show the reference's
  pattern; ``tirdeflect process`` checks the first frame on the CPU).

Checked on an NVIDIA H200 (2026-12-04, ``benchmarks/gpu_check.py``): heights
within 1.3e-5 of the RMS height of the CPU Reconstructor's, the same masks;
its speed goals are not met yet (1024^2: 727 frames/s full grid, 3400
decimated, 3.4 ms a live frame; docs/processing.md section 8), so the GPU
stays opt-in. Host copies go through page-locked memory; FD's warp of the
reference is one CuPy elementwise kernel where CuPy runs (NumPy runs the
array code it fuses, which is how the rest is tested without a GPU).
"""

from __future__ import annotations

import dataclasses
import time
from typing import NamedTuple

import numpy as np

from .fullgrid import lanczos_matrix, spline_matrix
from .gpu_device import host_empty, to_host, warp_kernel
from .pin import SHIFT_TOL_PX, USER_REGION_PREFIX, frame_motion_step, motion_of
from .refine import WarpReference, modulate
from .second_order import SECOND_ORDER_MIN_EFFECT, SecondOrderOptics, batch_effects
from .unwrap import TWO_PI

__all__ = ["BatchChain", "cupy_or_reason", "lanczos_matrix", "live_device", "ran_on_gpu"]


def cupy_or_reason():
    """(cupy, None) when CuPy and a CUDA device are usable, else (None, why not)."""
    try:
        import cupy
    except ImportError:
        return None, "CuPy is not installed (pip install 'tirdeflect[gpu]')"
    try:
        n = cupy.cuda.runtime.getDeviceCount()
    except Exception as exc:  # no driver, no device
        return None, f"no usable CUDA device ({type(exc).__name__}: {exc})"
    if n < 1:
        return None, "no CUDA device found"
    try:  # what the chain needs, once: a kernel compiled (NVRTC), cuFFT and cuBLAS loaded
        a = cupy.arange(64, dtype=cupy.float32).reshape(8, 8)
        cupy.fft.rfft2(a)
        cupy.matmul(a, a)
        cupy.cuda.Device().synchronize()
    except Exception as exc:  # noqa: BLE001 - e.g. cupy-cuda12x without a CUDA toolkit: no NVRTC
        return None, (f"CuPy cannot run on this GPU ({type(exc).__name__}: {exc}); install "
                      f"'cupy-cuda12x[ctk]' or a CUDA toolkit")
    return cupy, None


def live_device() -> tuple:
    """("cuda", "GPU <name>") when CuPy and a CUDA device are usable, else
    ("cpu", "CPU (<why no GPU>)"): the device a live view reconstructs on,
    with the words that say so."""
    cupy, why = cupy_or_reason()
    if cupy is None:
        return "cpu", f"CPU ({why})"
    try:
        name = cupy.cuda.runtime.getDeviceProperties(cupy.cuda.Device().id)["name"]
        name = name.decode() if isinstance(name, bytes) else str(name)
    except Exception:  # noqa: BLE001 - the name is only for the user
        name = "CUDA device"
    return "cuda", f"GPU {name}"


def ran_on_gpu(result) -> bool:
    """Whether ``result`` (a :class:`~processing.result.Result`) came from the GPU chain: a
    ``device="cuda"`` Reconstructor sends frames it cannot do to the CPU (a frame with masked
    samples, folds or 2 pi jumps since the last, a series' first frame), each such Result as
    the CPU makes it. The GPU chain's Results time their whole batch (``timings_ms["batch"]``)."""
    return "batch" in getattr(result, "timings_ms", {})


def _wrap(xp, a):
    return a - np.float32(TWO_PI) * xp.rint(a / np.float32(TWO_PI))


class _Windows(NamedTuple):
    """A Demodulator's constants on ``xp`` (its :class:`processing.plan.DemodulationPlan`):
    border window, carrier windows' bins, filters, DC leak and the small inverse's scale."""

    window2d: object
    gather: object
    mirror: object
    filters: object
    dc_leak: object
    scale: np.float32


def _windows(xp, demod) -> _Windows:
    dp = demod.plan
    (rows, cols), (m_r, m_c) = demod.shape, demod.window_shape
    to = xp.asarray
    return _Windows(None if dp.window2d is None else to(dp.window2d.astype(np.float32)), to(dp.gather_index),
                    None if dp.gather_mirror is None else to(dp.gather_mirror), to(dp.filters),
                    None if dp.dc_leak is None else to(dp.dc_leak),
                    np.float32(m_r * m_c / (rows * cols)))  # ifft2 of xp normalises by 1/(m_r m_c)


class _Continued(NamedTuple):
    """FD's demodulation of frames continued beyond their border on ``xp``
    (:class:`processing.continuation.ContinuedSignals`)."""

    continuation: object
    windows: _Windows
    g0: object
    rows_matrix: object
    cols_matrix_t: object
    static: object


class BatchChain:
    """Batches of frames through one Reconstructor's chain on ``xp`` (see module doc).

    Parameters
    ----------
    recon : Reconstructor
        Constants (carriers, filters, masks, solver) and the series state.
    xp : module
        ``cupy`` (the GPU) or ``numpy`` (the same code on the CPU).
    """

    def __init__(self, recon, xp):
        self.r = recon
        self.xp = xp
        d = recon.demod
        self.reason = None
        if getattr(recon, "pattern", "checkerboard") != "checkerboard":
            self.reason = "dot patterns go through PIV on the CPU"
            return
        plan = recon.plan
        dp = plan.demodulation
        hs = recon.height_solver()
        F = hs.spectral_coefficients
        if F is None or recon.solver not in ("auto", "spectral"):
            self.reason = "the geometry has no spectral height solver (finite camera distance)"
        elif recon.full_method != "interpolate":
            self.reason = "full_method='ifft'"
        elif getattr(recon, "refine_method", "fd") != "fd":
            self.reason = "refine_method='image' (image matching on the CPU)"
        elif not plan.reference_valid_everywhere:
            self.reason = "the reference has blank parts (every frame is masked)"
        elif recon.options.full_interpolation not in ("spline", "lanczos"):
            self.reason = "full_interpolation other than 'spline' or 'lanczos' (the GPU resizes with those only)"
        elif recon.options.turn_removal != "none":
            self.reason = "turn_removal (the turn since the reference is measured and taken out on the CPU)"
        elif recon.options.shift_removal:
            self.reason = "shift_removal (a shift of the whole pattern is taken out on the CPU)"
        if self.reason is not None:
            return
        to = xp.asarray
        rows, cols = recon.shape
        m_r, m_c = d.window_shape
        self.windows = _windows(xp, d)
        self.continued = None  # FD's continued demodulation (_Continued), made on first use
        self.conj_g0 = to(plan.conj_g0)
        self.g0_den = to(plan.g0_amplitude)
        self.local_inv = None if dp.local_inverse is None else to(dp.local_inverse)
        self.global_inv = -np.linalg.inv(d.wavevectors).astype(np.float32)
        self.ref_idx = to(plan.reference_region_index)
        self.spacing = (np.float32(recon.rows_px[1] - recon.rows_px[0]),
                        np.float32(recon.cols_px[1] - recon.cols_px[0]))
        along = spline_matrix if recon.options.full_interpolation == "spline" else lanczos_matrix
        self.up_r = to(along(rows, m_r))
        self.up_cT = to(np.ascontiguousarray(along(cols, m_c).T))
        # the refinement's warp maps: Lanczos4 whatever the full grid's kernel, as on the CPU (refine.WARP_MAP_INTERPOLATION)
        self.warp_r = to(lanczos_matrix(rows, m_r))
        self.warp_cT = to(np.ascontiguousarray(lanczos_matrix(cols, m_c).T))
        # spectral height solve as matrix products, whatever the grid size
        from .height_spectral import dct_matrix, divergence_matrix as op

        self.Mr = to(op(m_r, hs.grid.dr) * F["gr"].T)
        self.McT = to(np.ascontiguousarray(op(m_c, hs.grid.dc).T))
        cr, cc = dct_matrix(m_r), dct_matrix(m_c)
        self.Cr, self.CrT, self.Cc, self.CcT = to(cr), to(np.ascontiguousarray(cr.T)), to(cc), to(
            np.ascontiguousarray(cc.T))
        self.F = {k: to(F[k]) for k in ("gc", "null", "inv_denom")}
        # the pin of a frame valid everywhere depends on the reference region only
        self.plan = plan  # (its pin region, for a shifted frame's HeightSolver.shift_status)
        samples, self.pin, (w, nn) = hs.pin_choice(
            np.ones(hs.shape, bool), True, plan.reference_region, recon.pin_fallback,
            recon.reference_region_name, plan.region_near)
        self.pin_samples = samples
        self.pin_index = to(np.flatnonzero(samples))  # where each frame's motion there is measured
        pin_r, pin_c = np.nonzero(samples)
        self.pin_pos = np.stack([recon.rows_px[pin_r], recon.cols_px[pin_c]])  # (for processing.pin.motion_of)
        self.F["w"] = to(w)
        self.nn = float(nn)
        self.sx, self.sy_u, self.sy_h = float(F["sx"]), float(F["sy_u"]), float(F["sy_h"])
        self.coef = hs.slope_coefficients()
        second = SecondOrderOptics(recon.geometry, recon.rows_px, recon.cols_px, recon.shape, hs.x_mm, hs.y_mm)
        # TIR's hit-point effect; FS-SS's own (h / h_p, the slope's square) is not judged here: its heights linear
        self.second = None if second.fsss else (to(second.t.astype(np.float32)), hs.y_mm, hs.x_mm)
        self.smooth = None
        self.staging = None  # page-locked host buffer the frames go up from (reused: each batch ends synchronised)
        self.rows_f = xp.arange(rows, dtype=xp.float32)[:, None]
        self.cols_f = xp.arange(cols, dtype=xp.float32)[None, :]

    # ------------------------------------------------------------ pieces
    def _decimated(self, images, windows=None):
        """(B, rows, cols) float32 -> analytic signals (B, 2, m_r, m_c) complex64 through
        ``windows`` (the Reconstructor's demodulator's, or another :class:`_Windows`)."""
        xp = self.xp
        w = self.windows if windows is None else windows
        B = images.shape[0]
        means = images[:, ::4, ::4].astype(xp.float64).mean(axis=(1, 2))
        if w.window2d is None:
            prepared = images - means.astype(xp.float32)[:, None, None]
            means = xp.zeros_like(means)
        else:
            prepared = images * w.window2d
        spec = xp.fft.rfft2(prepared, axes=(-2, -1)).astype(xp.complex64)
        wins = xp.take(spec.reshape(B, -1), w.gather.reshape(-1), axis=1).reshape((B,) + w.gather.shape)
        if w.mirror is not None:
            wins = xp.where(w.mirror, xp.conj(wins), wins)
        wins = wins * w.filters
        if w.dc_leak is not None:
            wins = wins - means.astype(xp.complex64)[:, None, None, None] * w.dc_leak
        g = xp.fft.ifft2(wins, axes=(-2, -1)).astype(xp.complex64)
        return g * w.scale

    def _continued(self) -> _Continued:
        """FD's continued demodulation on ``xp`` (the CPU chain's constants, moved once)."""
        if self.continued is None:
            xp, cs = self.xp, self.r.continued_signals()
            a_rows, a_cols = cs.spline_matrices()
            static = cs.static_phase(self.r.warp_reference().band_limited)
            self.continued = _Continued(cs.continuation, _windows(xp, cs.demod), xp.asarray(cs.g0),
                                        xp.asarray(a_rows), xp.asarray(np.ascontiguousarray(a_cols.T)),
                                        xp.asarray(static))
        return self.continued

    def _continued_signals(self, images):
        """(B, rows, cols) -> the analytic signals (B, 2, ...) of the images continued beyond their border."""
        c = self._continued()
        return self._decimated(c.continuation(images, xp=self.xp), c.windows)

    def _phase_difference(self, g_a, g_b):
        """``arg(g_a conj(g_b))`` on the decimated grid (B, 2, m_r, m_c) of two continued signals, as
        :meth:`processing.continuation.ContinuedSignals.phase_difference` (its spline as two products)."""
        xp, c = self.xp, self._continued()
        p = g_a * xp.conj(g_b)
        return xp.angle(xp.matmul(xp.matmul(c.rows_matrix, p), c.cols_matrix_t)).astype(xp.float32)

    def _to_displacement(self, phase):
        xp = self.xp
        if self.local_inv is not None:
            return (self.local_inv[None] * phase[:, None]).sum(axis=2).astype(xp.float32)
        inv = self.global_inv
        return xp.stack([inv[0, 0] * phase[:, 0] + inv[0, 1] * phase[:, 1],
                         inv[1, 0] * phase[:, 0] + inv[1, 1] * phase[:, 1]], axis=1)

    def _up(self, field, warp=False):
        """(..., m_r, m_c) -> (..., rows, cols): the CPU's resize as two products (the
        full grid's kernel, or Lanczos4 for the refinement's warp maps with ``warp``)."""
        if warp:
            return self.xp.matmul(self.xp.matmul(self.warp_r, field), self.warp_cT)
        return self.xp.matmul(self.xp.matmul(self.up_r, field), self.up_cT)

    def _warp_smooth(self, u):
        """The band-limited reference sampled at r - u(r), (B, rows, cols), as the CPU chain warps it
        (:func:`processing.refine.sample_band_limited`): the carriers' envelopes interpolated bilinearly
        (reflecting border), the carriers exact."""
        xp = self.xp
        if self.smooth is None:
            plan = self.r.warp_reference()
            dense = [xp.ascontiguousarray(xp.asarray(a, dtype=xp.float32))
                     for a in (plan.envelopes, plan.carrier_cos, plan.carrier_sin)]
            self.smooth = WarpReference(*dense, plan.wavevectors, plan.band_limited)
        plan = self.smooth
        rows, cols = plan.envelopes.shape[:2]
        off_c = -self._up(u[:, 1], warp=True)
        off_r = -self._up(u[:, 0], warp=True)
        kernel = warp_kernel(xp)
        if kernel is not None:  # CuPy: the lines below fused into one pass (a tenth of their time on an H200)
            k = np.asarray(plan.wavevectors, np.float32)
            return kernel(off_r.astype(xp.float32, copy=False), off_c.astype(xp.float32, copy=False),
                          plan.envelopes, plan.carrier_cos, plan.carrier_sin,
                          k[0, 0], k[0, 1], k[1, 0], k[1, 1], np.int32(rows), np.int32(cols))
        X = self.cols_f + off_c
        Y = self.rows_f + off_r
        ix = xp.floor(X)
        iy = xp.floor(Y)
        fx = (X - ix).astype(xp.float32)[..., None]
        fy = (Y - iy).astype(xp.float32)[..., None]
        ix = ix.astype(xp.int32)
        iy = iy.astype(xp.int32)

        def reflect(i, n):
            i = xp.where(i < 0, -i - 1, i)
            return xp.where(i >= n, 2 * n - i - 1, i)

        x0, x1 = reflect(ix, cols), reflect(ix + 1, cols)
        y0, y1 = reflect(iy, rows), reflect(iy + 1, rows)
        e = plan.envelopes
        top = (1 - fx) * e[y0, x0] + fx * e[y0, x1]
        bottom = (1 - fx) * e[y1, x0] + fx * e[y1, x1]
        sampled = ((1 - fy) * top + fy * bottom).astype(xp.float32)
        return modulate(xp, sampled, plan, off_r.astype(xp.float32), off_c.astype(xp.float32)).astype(xp.float32)

    def _height(self, u):
        """Spectral least-squares height of all-valid u (B, 2, m_r, m_c): (h, slope_x, slope_y)."""
        xp = self.xp
        F = self.F
        ur, uc = u[:, 0], u[:, 1]
        rhs = xp.matmul(self.Mr, ur) + xp.matmul(uc, self.McT) * F["gc"]
        c = xp.matmul(xp.matmul(self.Cr, rhs), self.CcT) * F["inv_denom"]
        f = xp.matmul(xp.matmul(self.CrT, c), self.Cc)
        if self.nn > 0:
            alpha = (F["w"] * f * F["null"]).sum(axis=(1, 2), dtype=xp.float64) / self.nn
            f = f - alpha.astype(xp.float32)[:, None, None]
        h = f * F["null"]
        return h, uc * np.float32(self.sx), ur * np.float32(self.sy_u) - np.float32(self.sy_h) * h

    # --------------------------------------------------------------- stages
    def _demodulate(self, frames):
        """Frames -> (the frames on the device as float32, analytic signals g, wrapped phase,
        amplitude ratio, all_valid per frame, hot pixels repaired per frame)."""
        xp = self.xp
        checked, hot = zip(*(self.r.checked_frame(f) for f in frames))
        B = len(checked)
        # the frames go up as they came (uint8: a quarter of float32's bytes) from page-locked memory
        dtype = np.result_type(*checked)
        if self.staging is None or self.staging.shape[0] < B or self.staging.dtype != dtype:
            self.staging = host_empty(xp, (B,) + checked[0].shape, dtype)
        for k, frame in enumerate(checked):
            self.staging[k] = frame
        images = xp.asarray(self.staging[:B]).astype(xp.float32)
        g = self._decimated(images)
        wrapped = xp.angle(g * self.conj_g0).astype(xp.float32)
        ratio = xp.abs(g) / self.g0_den
        amplitude = xp.minimum(ratio[:, 0], ratio[:, 1])
        all_valid = to_host(xp, amplitude.reshape(B, -1).min(axis=1)) >= self.r.min_amplitude
        return images, g, wrapped, amplitude, all_valid, hot

    def _series_start(self, state, wrapped, all_valid):
        """Where the batch's unwrapping starts: ``(first, prev, start)``, or None
        when the CPU must take every frame (the first frame of a series masked).

        ``prev``: the previous frame's unwrapped phase from the series state;
        else frame 0 unwrapped in space on the CPU (``start``), and the batch
        follows it from frame ``first = 1``."""
        r, xp = self.r, self.xp
        if not r.unwrap:
            return 0, None, None
        if r.temporal and state is not None:
            return 0, xp.asarray(state.phase.astype(np.float32)), None
        if not bool(all_valid[0]):
            return None
        w0 = to_host(xp, wrapped[0])
        start = r.unwrap_phase(w0, np.ones(w0.shape[1:], bool), True)
        return 1, None, xp.asarray(np.asarray(start, np.float32))

    def _follow(self, before, seq):
        """Temporal unwrapping of ``seq`` after the phase ``before`` (1, 2, m_r, m_c):
        (unwrapped phase, per frame whether its change has a neighbour jump > pi)."""
        xp = self.xp
        # wrapped changes frame to frame; each frame's neighbour-jump test as on the CPU
        prior = xp.concatenate([before, seq[:-1]], axis=0)
        delta = _wrap(xp, seq - prior)
        jumps = xp.maximum(xp.abs(xp.diff(delta, axis=2)).reshape(delta.shape[0], -1).max(axis=1),
                           xp.abs(xp.diff(delta, axis=3)).reshape(delta.shape[0], -1).max(axis=1))
        jumps = to_host(xp, jumps) > np.pi
        summed = before + xp.cumsum(delta, axis=0)
        # snapped to the wrapped phase + 2 pi k (no drift from the sum)
        return seq + np.float32(TWO_PI) * xp.rint((summed - seq) / np.float32(TWO_PI)), jumps

    def _reference_near_zero(self, phase, first):
        """Each frame's phase shifted by 2 pi k so that the reference region stays
        nearest 0, sequentially as each frame follows the shifted one."""
        xp = self.xp
        B = phase.shape[0]
        vals = phase.reshape(B, 2, -1)[:, :, self.ref_idx]
        lo, hi, med = to_host(xp, xp.stack([vals.min(axis=2), vals.max(axis=2), xp.median(vals, axis=2)]))  # one copy
        J = np.zeros((B, 2))
        shift = np.zeros(2)
        for n in range(first, B):
            for s in range(2):
                if not (lo[n, s] - TWO_PI * shift[s] > -np.pi and hi[n, s] - TWO_PI * shift[s] < np.pi):
                    shift[s] += np.round((med[n, s] - TWO_PI * shift[s]) / TWO_PI)
            J[n] = shift
        return phase - xp.asarray((TWO_PI * J).astype(np.float32))[:, :, None, None]

    def _unwrap(self, wrapped, all_valid, first, prev, start):
        """(phase of every frame, how many frames from the first go on here)."""
        B = wrapped.shape[0]
        if not self.r.unwrap:
            ok = np.array(all_valid, bool)  # a masked frame goes to the CPU, as with unwrapping
            return wrapped, (int(np.argmin(ok)) if not ok.all() else B)
        before = prev[None] if prev is not None else start[None]
        seq = wrapped[first:]
        if seq.shape[0]:
            snapped, jumps = self._follow(before, seq)
            phase = self.xp.concatenate([start[None], snapped], axis=0) if first else snapped
        else:  # one frame, unwrapped in space
            jumps = np.zeros(0, bool)
            phase = start[None]
        if self.ref_idx.size:
            phase = self._reference_near_zero(phase, first)
        ok = np.ones(B, bool)
        ok[first:] &= ~jumps
        ok &= all_valid
        return phase, (int(np.argmin(ok)) if not ok.all() else B)

    def _fold_limit(self, u, ok_upto):
        """``ok_upto`` lowered to the first frame whose ``det(I - grad u)`` reaches
        ``min_fold`` anywhere (the CPU's cheap bound first)."""
        xp = self.xp
        B = u.shape[0]
        dr, dc = self.spacing
        t = xp.maximum(xp.abs(xp.diff(u, axis=2)).reshape(B, -1).max(axis=1) / dr,
                       xp.abs(xp.diff(u, axis=3)).reshape(B, -1).max(axis=1) / dc)
        need = to_host(xp, 1.0 - 2.0 * t) <= self.r.min_fold + 1e-6
        if need.any():
            dur_dr, dur_dc = xp.gradient(u[:, 0], float(dr), float(dc), axis=(1, 2))
            duc_dr, duc_dc = xp.gradient(u[:, 1], float(dr), float(dc), axis=(1, 2))
            det = (1.0 - dur_dr) * (1.0 - duc_dc) - dur_dc * duc_dr
            folded = to_host(xp, det.reshape(B, -1).min(axis=1)) <= self.r.min_fold
            bad = np.flatnonzero(need & folded)
            if bad.size:
                ok_upto = min(ok_upto, int(bad[0]))
        return ok_upto

    def _refine(self, images, phase, u, grid):
        """FD's full grid and refinement as the CPU's (:func:`processing.refine.refine_fd`): the
        phase measured again on the frames continued beyond their border (unwrapped by the
        taper's ``phase``), then the smooth reference warped by ``u``, continued, re-demodulated,
        and the phase left over added to ``u`` (the Reconstructor's iterations)."""
        xp = self.xp
        r = self.r
        iterations = r.refine_iterations
        if iterations is None:
            iterations = {"decimated": 0, "full": 1}[grid]
        if iterations <= 0 and grid != "full":
            return u
        c = self._continued()
        g_frames = self._continued_signals(images)
        measured = self._phase_difference(g_frames, c.g0[None])
        u = self._to_displacement(phase + _wrap(xp, measured - phase))
        for _ in range(iterations):
            gw = self._continued_signals(self._warp_smooth(u))
            dphi = _wrap(xp, self._phase_difference(g_frames, gw) - c.static)
            u = u + self._to_displacement(dphi)
        return u

    def _check_series(self, phase, h):
        """The series check of each frame against the previous one (CPU, decimated
        grid: cheap), in order; the series then goes on from the last frame.
        Returns (phase on the host, [SeriesCheck])."""
        xp = self.xp
        r = self.r
        ph_host = to_host(xp, phase.astype(xp.float32, copy=False))
        h_host = to_host(xp, h)
        valid_dec = np.ones(phase.shape[2:], bool)
        series = [r.check_series(ph_host[k], valid_dec, _Surface(h_host[k], self.pin_samples))
                  for k in range(phase.shape[0])]
        r.remember_phase(to_host(xp, phase[-1]), np.ones(phase.shape[2:], bool), True)
        return ph_host, series

    # --------------------------------------------------------------- call
    def __call__(self, frames, grid: str, essentials: bool = False):
        """Results of ``frames`` (a sequence of 2-D images) in order, continuing the series."""
        r = self.r
        if not len(frames):
            return []
        if self.reason is not None:
            return [r.call_cpu(f, grid=grid) for f in frames]
        t0 = time.perf_counter()
        images, g, wrapped, amplitude, all_valid, hot = self._demodulate(frames)
        state = r.series_state()  # a copy of the decimated grid's memory (small)
        if r.unwrap and state is not None and not state.all_valid:
            # the previous frame was masked: this one follows it on the CPU, then the rest here
            return [r.call_cpu(frames[0], grid=grid)] + (self(frames[1:], grid, essentials) if len(frames) > 1 else [])
        start = self._series_start(state, wrapped, all_valid)
        if start is None:
            return [r.call_cpu(f, grid=grid) for f in frames]
        phase, ok_upto = self._unwrap(wrapped, all_valid, *start)
        u = self._to_displacement(phase)
        n = self._fold_limit(u, ok_upto)
        if n == 0:
            return [r.call_cpu(f, grid=grid) for f in frames]
        phase, u, g, amplitude = phase[:n], u[:n], g[:n], amplitude[:n]
        u = self._refine(images[:n], phase, u, grid)
        h, sx, sy = self._height(u)
        m = n
        if grid == "full" and self.second is not None:
            t, y_mm, x_mm = self.second
            need = np.flatnonzero(to_host(self.xp, batch_effects(self.xp, t, h, y_mm, x_mm)) >= SECOND_ORDER_MIN_EFFECT)
            m = int(need[0]) if need.size else n
        if m < n:  # heights the CPU solves again to second order (processing.second_order), and the rest
            if m == 0:
                return [r.call_cpu(f, grid=grid) for f in frames]
            n, phase, u, g, amplitude, h, sx, sy = m, phase[:m], u[:m], g[:m], amplitude[:m], h[:m], sx[:m], sy[:m]
        ph_host, series = self._check_series(phase, h)
        results = self._results(grid, u, h, sx, sy, amplitude, ph_host, n, 1e3 * (time.perf_counter() - t0),
                                essentials, series, hot)
        return results + [r.call_cpu(f, grid=grid) for f in frames[n:]]

    def _results(self, grid, u, h, sx, sy, amplitude, ph, n, ms, essentials, series, hot):
        from .result import Result

        xp = self.xp
        r = self.r
        hs = r.height_solver()
        timings = {"total": ms / max(n, 1), "batch": ms}
        # processing.pin.region_motion of each frame's displacement on the pin samples (as the CPU's solve)
        pin_u = to_host(xp, u[:n].reshape(n, 2, -1)[:, :, self.pin_index])
        user = str(self.pin.region).startswith(USER_REGION_PREFIX)
        moved = [motion_of(pin_u[k], self.pin_pos, user_region=user) for k in range(n)]
        valid_dec = np.ones(ph.shape[2:], bool)
        # processing.pin.frame_motion of each frame (every k-th row and column, as the CPU's), and where the
        # whole pattern shifted, what that puts into the heights (HeightSolver.shift_status, on the host)
        step = frame_motion_step(valid_dec.size)
        sub = u[:n, :, ::step, ::step].reshape(n, 2, -1)
        shift = xp.median(sub, axis=2)
        tol = xp.maximum(SHIFT_TOL_PX, 0.5 * xp.hypot(shift[:, 0], shift[:, 1]))  # processing.pin.shift_tolerance_px
        share = to_host(xp, xp.mean(xp.hypot(sub[:, 0] - shift[:, 0, None], sub[:, 1] - shift[:, 1, None])
                                    <= tol[:, None], axis=1))
        shift = to_host(xp, shift)
        pins = [hs.shift_status(dataclasses.replace(self.pin, **moved[k]), shift[k], share[k],
                                valid_dec, self.plan.reference_region, pin_fallback=r.pin_fallback,
                                region_name=r.reference_region_name, near=self.plan.region_near) for k in range(n)]
        if grid == "full":
            rows, cols = r.shape
            disp = self._up(u)
            height = self._up(h)
            amp = None if essentials else self._up(amplitude)
            c = self.coef
            srcs = (disp[:, 0], disp[:, 1], height)
            slopes = []
            for row in c:
                acc = xp.zeros_like(height)
                for k, src in zip(row, srcs):
                    if k != 0.0:
                        acc = acc + np.float32(k) * src
                slopes.append(acc)
            x_mm, y_mm = r.grid_coordinates("full")
            fields = dict(height=height, slope_x=slopes[0], slope_y=slopes[1], displacement=disp,
                          amplitude=amp)
            extra = dict(x_mm=x_mm, y_mm=y_mm, grid="full", rows_px=np.arange(rows, dtype=float),
                         cols_px=np.arange(cols, dtype=float))
            valid = np.ones(r.shape, bool)
        else:
            fields = dict(height=h, slope_x=sx, slope_y=sy, displacement=u, amplitude=amplitude)
            extra = dict(x_mm=np.asarray(hs.x_mm), y_mm=np.asarray(hs.y_mm), grid="decimated",
                         rows_px=r.rows_px, cols_px=r.cols_px)
            valid = valid_dec
        if essentials:
            fields["displacement"] = fields["amplitude"] = None
        # down into fresh page-locked memory (CuPy's pool: back to it once the Results are dropped);
        # a pageable copy ran at 1.7 GB/s on an H200, 7 of the full grid's 8.5 ms a frame
        host = {k: (None if v is None else to_host(xp, v.astype(xp.float32, copy=False), pinned=True))
                for k, v in fields.items()}
        return [Result(valid=valid.copy(), carriers=r.carriers, phase=ph[k], valid_fraction=1.0,
                       timings_ms=dict(timings), pin=pins[k],
                       series=series[k], hot_pixels=hot[k],
                       **{key: None if v is None else v[k] for key, v in host.items()}, **extra)
                for k in range(n)]


class _Surface:
    """What the Reconstructor's series check reads of a height solve."""

    def __init__(self, height_mm, pin_samples):
        self.height_mm = height_mm
        self.pin_samples = pin_samples
