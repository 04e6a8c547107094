"""The second-order optics the height solve's linear model leaves out (:class:`SecondOrderOptics`).

The height solver inverts ``u = a h + B grad h`` (notes.md), the first-order
response of the reflection to the surface.  Two second-order terms, of
opposite sign, make the heights of even the exact displacement off by an
amount that grows with the displacement (``python3
benchmarks/bench_height_floor.py``: 0.013 % for a 1 um dimple, 0.190 % for the
accuracy table's 15 um one, 1.5 % at 60 um):

* the reflection's nonlinearity in the slope (the pattern point moves with
  ``tan(theta + 2 alpha)``, not ``2 alpha / cos^2 theta``);
* the hit point's move with the height: pixel ``r``'s ray meets the raised
  surface at ``X0 + t h``, ``t = d_xy / d_z`` of the camera ray, so the
  heights seen on the pixel grid, ``H(X0) = h(X0 + t H)``, have the gradient
  ``grad h (1 + t . grad h)`` to second order.

:meth:`SecondOrderOptics.corrected_displacement` takes both off a measured
displacement, computed from a first solve's heights: the exact trace of the
surface as a plane at each sample (``processing.forward.trace_tir``) less its
linear part (:meth:`Geometry.linear_response`), then the slope part scaled by ``1 + t . grad h``.  Solved again,
the exact displacement's heights came within 0.003 % (15 um) and 0.08 %
(60 um) of the truth, telecentric either way round and with the camera at
1.5 m.

FS-SS the same way, its trace ``processing.forward.trace_fsss`` through the
surface and the layers: there the water column under a raised surface is
``h`` taller (a term ``h / h_p`` against the first order) and the refraction
bends with the slope's square, so the effect is judged by ``|h| / h_p +
|grad h|^2`` too, and the correction is repeated from each solve's heights
(:data:`FSSS_PASSES`: it is a fixed point, not a small term, where the
heights reach a tenth of the depth).  By-hand sweep of 7 Dec 2026:
``simulate``'s bump (1.1 mm on 10 mm of water, telecentric) 3.6 % off with
exit 0 and no word, 0.04 % now; 2.2 mm on 5 mm with the camera 300 mm
above, 14.4 -> 0.4 %.

Where it runs: the full grid's final height solve, where the first solve's
slopes make the terms count (:data:`SECOND_ORDER_MIN_EFFECT`): image
matching's (``processing.chain_image``, checkerboards and random dots) and
FD's or no refinement's decimated heights before every pixel
(``CheckerboardChain.to_second_order``; the GPU chain hands such frames to
the CPU, :func:`batch_effects`).  The live (decimated) grid and
``full_method="ifft"`` keep the linear model.
"""

from __future__ import annotations

import time

import numpy as np

from .errors import GeometryError
from .fill import nearest_fill_index
from .forward import trace_fsss
from .trace_kernels import trace_planes_tir

__all__ = ["SecondOrderOptics", "SECOND_ORDER_MIN_EFFECT", "FSSS_PASSES", "FSSS_SETTLED", "batch_effects",
           "solved_again"]

#: The correction runs where ``|t . grad h|`` (the hit point's relative move, which the
#: reflection's nonlinearity matches in size) reaches this somewhere.  Below it the floor is
#: under about 0.1 % and the heights' other errors (noise, the band-pass, image matching's
#: own) are larger: corrected at 5e-4 the accuracy table's image-matching column moved by
#: -0.15 to +0.03 points (12-30 mm waves 0.135 -> 0.097 %, but the noisy 12-bit dimple
#: 0.084 -> 0.104, the narrow bump 0.310 -> 0.327, the dots' 4 um bump 0.116 -> 0.150):
#: errors that had partly cancelled the floor.  At 1e-3 only the deep dimple is corrected.
SECOND_ORDER_MIN_EFFECT = 1e-3
#: FS-SS: corrections from each solve's heights in turn, at most (:func:`solved_again`); they stop once the
#: heights move by less than :data:`FSSS_SETTLED` of their RMS.  ``simulate``'s bump on 10 mm of water
#: (1.1 mm high): 3.85 % -> 0.31 / 0.054 / 0.042 % after 1 / 2 / 4 passes; on 5 mm with the camera at
#: 300 mm (2.2 mm high): 15.2 -> 4.9 / 1.9 / 0.38 % (heights rms error, 256^2, 8 bit, full grid).
FSSS_PASSES = 4
FSSS_SETTLED = 1e-4


class _LocalPlanes:
    """The surface as a plane at each ray: height ``h`` and gradient ``(gx, gy)`` (image frame,
    mm / mm) through the ray's point ``(x0, y0)`` on the flat surface (arrays of the rays' shape)."""

    def __init__(self, h, gx, gy, x0, y0):
        self.h, self.gx, self.gy, self.x0, self.y0 = h, gx, gy, x0, y0

    def height_and_gradient(self, x, y):
        return self.h + self.gx * (x - self.x0) + self.gy * (y - self.y0), self.gx, self.gy


class SecondOrderOptics:
    """The second-order terms on one grid of samples (built once per grid).

    Parameters
    ----------
    geometry : Geometry
    rows_px, cols_px : ndarray (n_rows,), (n_cols,)
        Pixel coordinates of the grid's samples.
    frame_shape : (int, int)
    x_mm, y_mm : ndarray (n_cols,), (n_rows,)
        The height solver's coordinates of the samples (image frame), mm.

    Attributes
    ----------
    applies : bool
        True (TIR and FS-SS alike; kept for callers that ask).
    fsss : bool
        FS-SS: its effect and trace (see the module's docstring).
    """

    def __init__(self, geometry, rows_px, cols_px, frame_shape, x_mm, y_mm):
        self.geometry = geometry
        self.frame_shape = tuple(frame_shape)
        self.applies = True
        self.fsss = geometry.setup == "fsss"
        self.x_mm = np.asarray(x_mm, np.float64)
        self.y_mm = np.asarray(y_mm, np.float64)
        self.rows, self.cols = np.meshgrid(np.asarray(rows_px, np.float64), np.asarray(cols_px, np.float64),
                                           indexing="ij")
        if self.applies:
            self._rays = geometry.camera_rays(self.rows, self.cols, self.frame_shape)  # traced at every correction
            for ray in self._rays:
                ray.flags.writeable = False
            d = self._rays[1]
            self.x0, self.y0 = geometry.surface_point(self.rows, self.cols, self.frame_shape)
            # TIR's trace, compiled (processing.trace_kernels): the rays' components and the flat points in rows
            shape = self.rows.shape + (3,)
            self._components = [np.ascontiguousarray(np.moveaxis(np.broadcast_to(r, shape), -1, 0).reshape(3, -1))
                                for r in self._rays]
            self._flat_xy = [np.ascontiguousarray(np.broadcast_to(v, self.rows.shape), np.float64).ravel()
                             for v in (self.x0, self.y0)]
            # the hit point's move per mm of height, image frame (x along the columns, y = row_sign * canonical y
            # for TIR; FS-SS's frame is the image's)
            y_sign = 1.0 if self.fsss else geometry.row_sign
            self.t = np.stack([d[..., 0] / d[..., 2], y_sign * d[..., 1] / d[..., 2]])
            # the trace's linear part, u = a h + C (dh/dy, dh/dx): the height solver's own response with
            # the pixel gradient written through the surface's Jacobian K (grad_px = K^T grad_yx). Within
            # 7e-6 px of the trace of 1e-3 times the heights over 1e-3 (the 15 um dimple, whose N(h) is 6e-3
            # px), at half the cost: the trace is most of the correction's time
            lr = geometry.linear_response(self.rows, self.cols, self.frame_shape)
            self._a = np.moveaxis(lr.a, -1, 0)
            self._c = np.moveaxis(lr.B @ np.swapaxes(lr.jac_surface, -1, -2), (-2, -1), (0, 1))

    def _filled(self, height_mm, valid):
        h = np.asarray(height_mm, np.float64)
        fill = nearest_fill_index(np.asarray(valid, bool) & np.isfinite(h))
        return np.nan_to_num(h if fill is None else h[fill[0], fill[1]])

    def _hit_move(self, h):
        """``t . grad h`` (n_rows, n_cols) of filled heights: the hit point's relative move."""
        gy, gx = np.gradient(h, self.y_mm, self.x_mm)
        return gx, gy, self.t[0] * gx + self.t[1] * gy

    def effect(self, height_mm, valid) -> float:
        """Largest ``|t . grad h|`` on the valid samples (0 where nothing applies); FS-SS: the larger of that
        and ``|h| / h_p + |grad h|^2`` (the taller water column, the refraction's second order)."""
        v = np.asarray(valid, bool)
        if not self.applies or not v.any():
            return 0.0
        h = self._filled(height_mm, v)
        gx, gy, move = self._hit_move(h)
        effect = np.abs(move)
        if self.fsss:
            effect = np.maximum(effect, np.abs(h) / self.geometry.fsss_hp_mm + gx * gx + gy * gy)
        return float(np.max(effect[v]))

    def _trace(self, h, gx, gy):
        """Exact displacement (px, (2, n_rows, n_cols)) of the local planes; NaN where TIR is lost (FS-SS:
        where a ray is totally reflected on its way down)."""
        if self.fsss:
            pat, lost, _, _ = trace_fsss(_LocalPlanes(h, gx, gy, self.x0, self.y0), self.geometry, self.rows,
                                         self.cols, self.frame_shape)
            pat_x, pat_y = pat[..., 0], pat[..., 1]
        else:
            pat_x, pat_y, lost = self._trace_tir(h, gx, gy)
        r0, c0 = self.geometry.pixel_of_pattern_point(pat_x, pat_y, self.frame_shape)
        u = np.stack([self.rows - r0, self.cols - c0])
        u[:, lost] = np.nan
        return u

    def _trace_tir(self, h, gx, gy):
        """``(pat_x, pat_y, lost)`` of :func:`processing.forward.trace_tir` of the local planes, to the bit,
        by :func:`processing.trace_kernels.trace_planes_tir`."""
        g, shape = self.geometry, self.rows.shape
        n = self.rows.size
        pat_x, pat_y, lost = np.empty(n), np.empty(n), np.empty(n, bool)
        flat = [np.ascontiguousarray(v, np.float64).ravel() for v in (h, gx, gy)]
        steps = trace_planes_tir(*self._components, *flat, *self._flat_xy, float(g.row_sign),
                                 float(g.n_air / g.n_water), float(g.depth_mm), 1e-9, 60, pat_x, pat_y, lost,
                                 np.empty((6, n)))
        if steps < 0:  # (as forward.trace_tir)
            raise GeometryError("ray-surface intersection did not converge; the surface is too steep for the "
                                "camera rays")
        return pat_x.reshape(shape), pat_y.reshape(shape), lost.reshape(shape)

    def _terms(self, height_mm, valid):
        """``(N(h), 1 + t . grad h)`` of the filled heights, their gradient taken once."""
        h = self._filled(height_mm, valid)
        gx, gy, move = self._hit_move(h)
        # slopes the trace cannot follow end in forward's GeometryError; numpy's overflow warnings on the way
        # say nothing more (by-hand trial of 7 Dec 2026: ten lines of them before it)
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            linear = self._a * h + self._c[:, 0] * gy + self._c[:, 1] * gx
            nonlinear = np.nan_to_num(self._trace(h, gx, gy) - linear)
        return nonlinear, 1.0 + move

    def nonlinear_part(self, height_mm, valid) -> np.ndarray:
        """The reflection's second-order displacement (px, (2, n_rows, n_cols)) of heights ``height_mm``
        (mm; NaN or not ``valid``: the nearest valid sample's): the exact trace of the local planes less
        its linear part (the height solver's linear response)."""
        return self._terms(height_mm, valid)[0]

    def spacing_scale(self, height_mm, valid) -> np.ndarray:
        """``1 + t . grad h`` (n_rows, n_cols): what the hit point's move with the height does to the
        slopes seen on the pixel grid."""
        return 1.0 + self._hit_move(self._filled(height_mm, valid))[2]

    def corrected_displacement(self, u, height_mm, valid) -> np.ndarray:
        """The displacement ``u`` (px, (2, n_rows, n_cols)) whose first-order heights are the surface's
        heights to second order: ``(u - N(h)) (1 + t . grad h)`` (:meth:`nonlinear_part`,
        :meth:`spacing_scale`), both from ``height_mm`` (a first solve of ``u``).  float32; ``u`` itself
        where nothing applies."""
        u = np.asarray(u)
        if not self.applies:
            return u.astype(np.float32)
        nonlinear, scale = self._terms(height_mm, valid)
        return ((u - nonlinear) * scale).astype(np.float32)


def solved_again(optics: SecondOrderOptics, u, height_mm, valid, solve, timings):
    """``solve(u2)``, the heights ``height_mm`` (a first solve of ``u`` on ``optics``' grid, valid on
    ``valid``) solved again without the second-order terms, where their slopes make them count (the
    time in ``timings["second_order"]``); None where they do not.  FS-SS: again from each solve's heights,
    up to :data:`FSSS_PASSES` in all, until they settle (:data:`FSSS_SETTLED`).  What the chains' final
    solves call."""
    if optics.effect(height_mm, valid) < SECOND_ORDER_MIN_EFFECT:
        return None
    t0 = time.perf_counter()
    again = solve(optics.corrected_displacement(u, height_mm, valid))
    for _ in range(FSSS_PASSES - 1 if optics.fsss else 0):
        h0 = np.asarray(again.height_mm, np.float64)
        v = np.asarray(again.valid, bool) & np.isfinite(h0)
        if not v.any():
            break
        nxt = solve(optics.corrected_displacement(u, h0, v))
        h1 = np.asarray(nxt.height_mm, np.float64)
        both = v & np.isfinite(h1)
        again = nxt
        scale = float(np.sqrt(np.mean(np.square(h1[both])))) if both.any() else 0.0
        if not both.any() or float(np.sqrt(np.mean(np.square(h1[both] - h0[both])))) <= FSSS_SETTLED * scale:
            break
    timings["second_order"] = 1e3 * (time.perf_counter() - t0)
    return again


def batch_effects(xp, t, heights, y_mm, x_mm):
    """Largest ``|t . grad h|`` of each of a batch of height maps ``heights`` (B, n_rows, n_cols), mm,
    valid everywhere, as :meth:`SecondOrderOptics.effect` judges one map (compare with
    :data:`SECOND_ORDER_MIN_EFFECT`); ``xp``: numpy or cupy (the GPU chain's batches; the result stays
    on ``xp``), ``t`` a :attr:`SecondOrderOptics.t` on ``xp``, ``y_mm``, ``x_mm`` the grid's coordinates."""
    gy, gx = xp.gradient(heights, xp.asarray(y_mm), xp.asarray(x_mm), axis=(1, 2))
    return xp.abs(t[0] * gx + t[1] * gy).reshape(heights.shape[0], -1).max(axis=1)
