"""Heights from displacement: least squares of the exact TIR operator.

The displacement ``u`` (pixels, FD convention ``I(r) = I0(r - u)``) is linear in
the height and its gradient (see :meth:`Geometry.linear_response`):
``u = a h + B grad_px(h)`` per sample, ``grad_px`` the derivatives along
(row, col). Hence ``grad_px(h) + kappa h = g`` with ``g = B^-1 u`` and
``kappa = B^-1 a``. For a telecentric TIR camera this is the paper's
``(d/dx, d/dy + T/H) h = -(u_x, u_y cos^2 theta) / 2H`` in surface units (the
sign of the ``T/H`` term flips with the direction of the image rows); for a
telecentric FS-SS camera ``kappa = 0`` and ``g`` is Moisy's ``grad h`` (see
:meth:`Geometry.fsss_gradient_per_px`); with a finite FS-SS camera height the
oblique off-axis rays get their own response (exact refraction, linearised).

Discretisation and solvers
--------------------------
With ``n = exp(-Phi)``, ``grad Phi ~ kappa`` (the integrating factor of the
paper; exact for a telecentric camera) and ``h = n f``, the equations become
``grad f + (kappa - grad Phi) f = g / n``. They are imposed on every edge
between two neighbouring samples: the difference ``(f_j - f_i) / spacing``
against the *cell average* of ``g/n`` over the edge, from the four-point
formula ``(-G_{i-1} + 13 G_i + 13 G_j - G_{j+1}) / 24`` (fourth-order; it falls
back to ``(G_i + G_j)/2`` at borders and masks). Least squares over all
edges with weight 1 (valid edges) or 0 (an edge touching an invalid sample).

* ``spectral``: all samples valid and ``kappa`` constant (telecentric): the
  normal equations are the Neumann Poisson problem, solved exactly by a DCT-II
  in O(N log N). This is the least-squares solution of the exact operator
  with the paper's integrating-factor weights ``exp(2 Phi)`` (they vary by
  ``exp(2 T L_y / H)`` across a field of length ``L_y``, a few per cent).
  Its float32 form for a telecentric camera is :mod:`processing.height_spectral`.
* ``masked``: any validity mask and variable ``kappa`` (finite camera
  distance): preconditioned conjugate gradients on the normal equations,
  preconditioned by the spectral solver; invalid samples carry no equation,
  so they cannot pollute the heights elsewhere (:mod:`processing.height_masked`,
  with the operator on the edges).

This module holds :class:`HeightSolver` (the per-sample optics, the null
space, the choice of path and the pin of each frame), :class:`SurfaceResult`,
:func:`surface_from_displacement` and the solvers' cache :func:`solver_for`;
the discretisation's kernels are :mod:`processing.height_kernels`, the pin's
rule :mod:`processing.pin`.

Null space: ``f`` is defined up to one constant per connected piece of the
valid samples, i.e. ``h`` up to ``alpha exp(-Phi)`` (``exp(-T y/H)`` for TIR, a
constant for FS-SS). Each piece is pinned by the *pin samples* it contains
(least squares of ``alpha n`` there, i.e. mean height 0 on them); a piece
with fewer than :data:`PIN_MIN_PIECE_SAMPLES` pin samples is reported invalid
(NaN), since its offset was not measured.

What the pin needs (:func:`choose_pin_samples`): the pin samples are the
valid samples of the reference region (``geometry.reference_region``, or the
region the caller passes, e.g. the Reconstructor's border band of the
reference's valid area) when there are at least
``pin_samples_needed(region size)`` of them: :data:`PIN_MIN_SAMPLES` (the
demodulation filter correlates about 2 x 2 neighbouring samples of the
decimated grid, so 16 samples hold at least 4 independent measurements and
halve the noise of one sample), and :data:`PIN_MIN_FRACTION` of the region (a
region that lost most of its samples in this frame lost the pattern there:
what survives sits at mask edges, where the phase is least reliable, and the
frame would no longer be pinned on the same ground as its neighbours). Else
the fallback rule applies, the same for every frame: ``"nearest"`` pins on
the ``needed`` valid samples nearest the region (ties included), ``"refuse"``
raises :class:`GeometryError`. Either way :class:`PinStatus` says which.
"""

from __future__ import annotations

import dataclasses
import threading
from collections import OrderedDict
from types import MappingProxyType
from typing import NamedTuple

import numpy as np

from .errors import GeometryError, ShapeMismatchError, TirdeflectError
from .geometry import Geometry
from .height_kernels import cell_average, check_grid, div_T, neumann_eigenvalues, poisson_neumann, variable_optics
from .height_masked import apply_AT, edge_data, solve_masked
from .height_spectral import prepare_spectral, spectral_solve
from .pin import (PIN_MIN_PIECE_SAMPLES, USER_REGION_PREFIX, PinStatus, choose_pin_samples, level_of_shift_um,
                  null_mode_offset, region_motion, shift_judged)
from .regions import connected_regions

__all__ = [
    "SurfaceResult",
    "HeightSolver",
    "surface_from_displacement",
    "solver_for",
]


def _with_motion(status, displacement_px, samples, grid):
    """``status`` (a :class:`PinStatus`) with how the pattern moved on the pin ``samples``
    (:func:`processing.pin.region_motion`; the user's ``reference_region`` judged by its spread too)."""
    user = str(status.region).startswith(USER_REGION_PREFIX)
    return dataclasses.replace(status, **region_motion(displacement_px, samples, grid.rows_px, grid.cols_px,
                                                       user_region=user))


class SurfaceResult(NamedTuple):
    """Heights and slopes on the sample grid, image frame.

    Attributes
    ----------
    height_mm : ndarray (n_rows, n_cols) float32
        Height in mm, NaN where not valid.
    slope_x, slope_y : ndarray (n_rows, n_cols) float32
        ``dh/dx`` (x along increasing column) and ``dh/dy`` (y along
        increasing row), dimensionless, NaN where not valid.
    x_mm : ndarray (n_cols,) float64
        Surface x of each column (along the central row), mm.
    y_mm : ndarray (n_rows,) float64
        Surface y of each row (along the central column), mm.
    valid : ndarray (n_rows, n_cols) bool
        Samples with a measured height (input validity minus pieces that no
        reference sample pins).
    iterations : int
        Conjugate-gradient iterations (0 for the spectral solver).
    surface_xy_mm : ndarray (2, n_rows, n_cols) float64 or None
        Exact surface position (x, y) of each sample for a finite camera
        distance (the grid is not separable then); None when telecentric.
    pin : PinStatus or None
        Where the null space was pinned.
    pin_samples : ndarray (n_rows, n_cols) bool or None
        The samples it was pinned on.
    """

    height_mm: np.ndarray
    slope_x: np.ndarray
    slope_y: np.ndarray
    x_mm: np.ndarray
    y_mm: np.ndarray
    valid: np.ndarray
    iterations: int = 0
    surface_xy_mm: np.ndarray | None = None
    pin: PinStatus | None = None
    pin_samples: np.ndarray | None = None


class HeightSolver:
    """Displacement -> heights for one geometry and one sample grid.

    Construction precomputes the per-sample optics and the spectral
    eigenvalues; calling it is then cheap. :func:`surface_from_displacement`
    keeps a small cache of these.

    Parameters
    ----------
    geometry : Geometry
    rows_px : ndarray (n_rows,)
        Pixel row of each sample row (evenly spaced: full or strided grid).
    cols_px : ndarray (n_cols,)
        Pixel column of each sample column.
    frame_shape : (int, int)
        Shape of the camera frame the pixels belong to.
    tol : float
        Relative residual at which conjugate gradients stop.
    max_iter : int
        Conjugate-gradient iteration cap (a TirdeflectError says if reached).
    """

    def __init__(self, geometry: Geometry, rows_px, cols_px, frame_shape, *, tol: float = 1e-6, max_iter: int = 500):
        if not isinstance(geometry, Geometry):
            raise GeometryError(f"geometry must be a processing.Geometry, got {type(geometry).__name__}")
        self.geometry = geometry
        self.grid = grid = check_grid(rows_px, cols_px, frame_shape)
        self.tol = float(tol)
        self.max_iter = int(max_iter)
        n_rows, n_cols = grid.rows_px.size, grid.cols_px.size
        self.shape = (n_rows, n_cols)
        g = geometry
        R = grid.rows_px[:, None]
        C = grid.cols_px[None, :]
        self.surface_xy = None
        if g.setup == "tir":
            if g.telecentric:
                rc = np.array([[(grid.frame_shape[0] - 1) / 2.0]])
                cc = np.array([[(grid.frame_shape[1] - 1) / 2.0]])
                lr = g.linear_response(rc, cc, grid.frame_shape)
                Binv = np.linalg.inv(lr.B[0, 0])
                kappa = Binv @ lr.a[0, 0]
                self.Binv = Binv  # (2, 2)
                self.kappa = kappa  # (2,) per pixel along (row, col)
                self.Kinv_T = np.swapaxes(np.linalg.inv(lr.jac_surface[0, 0]), -1, -2)
                self.constant = True
            else:
                self.Binv, self.kappa, self.Kinv_T, sxy = variable_optics(g, grid)
                self.constant = False
                self.surface_xy = np.moveaxis(sxy, -1, 0)
        elif g.telecentric:
            s = -g.fsss_gradient_per_px() * g.pixel_mm  # dh/dpixel (mm/px) per px of u
            self.Binv = np.eye(2) * s
            self.kappa = np.zeros(2)
            self.Kinv_T = np.eye(2) / g.pixel_mm
            self.constant = True
        else:
            # off-axis rays are oblique: per-sample response from the exact refraction
            self.Binv, self.kappa, self.Kinv_T, sxy = variable_optics(g, grid)
            self.constant = False
            self.surface_xy = np.moveaxis(sxy, -1, 0)
        rcen = np.array([(grid.frame_shape[0] - 1) / 2.0])
        ccen = np.array([(grid.frame_shape[1] - 1) / 2.0])
        self.x_mm = np.asarray(g.surface_point(rcen[:, None], grid.cols_px[None, :], grid.frame_shape)[0]).ravel()
        self.y_mm = np.asarray(g.surface_point(grid.rows_px[:, None], ccen[None, :], grid.frame_shape)[1]).ravel()
        self.x_mm = np.broadcast_to(self.x_mm, (n_cols,)).astype(np.float64)
        self.y_mm = np.broadcast_to(self.y_mm, (n_rows,)).astype(np.float64)
        self.denom = neumann_eigenvalues(n_rows, grid.dr)[:, None] + neumann_eigenvalues(n_cols, grid.dc)[None, :]
        self.denom[0, 0] = 1.0
        # integrating factor Phi (grad Phi ~ kappa), centred on the grid
        if self.constant:
            yy = (np.arange(n_rows) - (n_rows - 1) / 2.0) * grid.dr
            xx = (np.arange(n_cols) - (n_cols - 1) / 2.0) * grid.dc
            self.phi = self.kappa[0] * yy[:, None] + self.kappa[1] * xx[None, :]
            self.dk_c = None
            self.dk_r = None
        else:
            kr, kc = self.kappa[..., 0], self.kappa[..., 1]
            ec = cell_average(kc, 1, None)
            er = cell_average(kr, 0, None)
            phi = poisson_neumann(div_T(ec, er, self.shape, grid.dc, grid.dr), self.denom)
            self.phi = phi - phi[n_rows // 2, n_cols // 2]
            self.dk_c = 0.5 * (kc[:, 1:] + kc[:, :-1]) - np.diff(self.phi, axis=1) / grid.dc
            self.dk_r = 0.5 * (kr[1:, :] + kr[:-1, :]) - np.diff(self.phi, axis=0) / grid.dr
        self.null = np.exp(-self.phi)
        self._fast = None
        self._pin_cache = None
        self.ref = geometry.reference_mask(grid.rows_px, grid.cols_px, grid.frame_shape)
        if not self.ref.any():
            raise GeometryError(
                f"{self.region_name()} contains no sample of the grid "
                f"(rows {grid.rows_px[0]:g}..{grid.rows_px[-1]:g}, cols {grid.cols_px[0]:g}..{grid.cols_px[-1]:g}); "
                f"choose a larger region inside the frame"
            )
        self._fast = prepare_spectral(self)

    # ------------------------------------------------------------------ fast path
    def region_name(self) -> str:
        """How :class:`PinStatus` names ``geometry.reference_region``."""
        r = self.geometry.reference_region
        return "default border band of the frame" if r is None else f"reference_region {list(r)}"

    @property
    def spectral_coefficients(self):
        """The float32 spectral path's coefficients (read-only mapping of arrays:
        ``gr``, ``gc``, ``null``, ``denom``, ``inv_denom``, ``sx``, ``sy_u``,
        ``sy_h``, and on small grids the matrices ``Mr``, ``McT``, ``Cr``...),
        or None where the optics are not uniform and diagonal (no spectral path)."""
        return None if self._fast is None else MappingProxyType(self._fast)

    def pin_choice(self, v, all_valid, reference_mask, fallback, region_name, near):
        """(pin samples, PinStatus, fast-path weights or None) of one frame; cached
        for frames valid everywhere (the answer depends on the region only).

        ``v``: valid samples; ``reference_mask``: the region (None: the
        geometry's); ``fallback``, ``region_name``, ``near``: as
        :func:`choose_pin_samples`.  Weights: ``(pin samples x null space,
        their squared norm)`` for frames valid everywhere."""
        region = self.ref if reference_mask is None else np.asarray(reference_mask, bool)
        if region.shape != self.shape:
            raise ShapeMismatchError(f"reference_mask must have shape {self.shape} like the grid, got {region.shape}")
        name = self.region_name() if region_name is None else region_name
        key = (id(region), fallback, name)
        if all_valid:
            c = self._pin_cache
            if c is not None and c[0] == key and c[1] is region:
                return c[2], c[3], c[4]
        samples, status = choose_pin_samples(region, v, fallback=fallback, region_name=name, near=near)
        weights = None
        if all_valid:
            null = self.null[:, :1] if self.constant else self.null
            wn = samples * null
            weights = (wn.astype(np.float32), float(np.sum(wn.astype(np.float64) ** 2)))
            self._pin_cache = (key, region, samples, status, weights)
        return samples, status, weights

    def slope_coefficients(self):
        """(2, 3) matrix M with ``(slope_x, slope_y) = M @ (u_row, u_col, h)`` per
        sample when the optics are uniform (telecentric), else None.

        Slopes are linear in the displacement and the height with constant
        coefficients then, so they may be interpolated through u and h.
        """
        if not self.constant:
            return None
        F = self._fast
        if F is not None:  # exactly what spectral_solve computes
            return np.array([[0.0, float(F["sx"]), 0.0],
                             [float(F["sy_u"]), 0.0, -float(F["sy_h"])]])
        Kt = np.asarray(self.Kinv_T, float)
        Bk = np.concatenate([np.asarray(self.Binv, float), -np.asarray(self.kappa, float)[:, None]], axis=1)
        sy, sx = Kt @ Bk  # rows of Kt: (sy, sx) from (slope_row, slope_col)
        return np.stack([sx, sy])

    # ------------------------------------------------------------------ pieces
    def gradients(self, displacement_px: np.ndarray):
        """``g = B^-1 u``: pixel derivatives (dh/drow, dh/dcol) in mm/px, float64."""
        ur = np.asarray(displacement_px[0], dtype=np.float64)
        uc = np.asarray(displacement_px[1], dtype=np.float64)
        Bi = self.Binv
        if Bi.ndim == 2:
            gr = Bi[0, 0] * ur if Bi[0, 1] == 0 else Bi[0, 0] * ur + Bi[0, 1] * uc
            gc = Bi[1, 1] * uc if Bi[1, 0] == 0 else Bi[1, 0] * ur + Bi[1, 1] * uc
        else:
            gr = Bi[..., 0, 0] * ur + Bi[..., 0, 1] * uc
            gc = Bi[..., 1, 0] * ur + Bi[..., 1, 1] * uc
        return gr, gc

    # ------------------------------------------------------------------ solve
    def solve(self, displacement_px, valid=None, *, solver: str = "auto", reference_mask=None,
              pin_fallback: str = "nearest", region_name: str | None = None,
              shift_removal: bool = False) -> SurfaceResult:
        """Heights (mm) and slopes from a displacement field.

        Parameters
        ----------
        displacement_px : ndarray (2, n_rows, n_cols) float
            ``(u_row, u_col)`` in pixels on this solver's grid.
        valid : ndarray (n_rows, n_cols) bool or None
            Samples to use; non-finite displacements are invalid too.
        solver : {"auto", "spectral", "masked"}
            "auto": spectral when every sample is valid and the optics are
            uniform (telecentric), masked otherwise.
        reference_mask : ndarray (n_rows, n_cols) bool or None
            The reference region on this grid (None: ``geometry.reference_region``
            or its default border band).
        pin_fallback : {"nearest", "refuse"}
            When the region holds fewer valid samples than the pin needs
            (:func:`choose_pin_samples`).
        region_name : str or None
            How :class:`PinStatus` names the region.
        shift_removal : bool
            Where the whole pattern shifted alike (:attr:`PinStatus.shifted`),
            solve the displacement less that shift (``PinStatus.shift_removed``).

        Returns
        -------
        SurfaceResult
            with ``pin`` (:class:`PinStatus`) and ``pin_samples``.
        """
        return self._solve(displacement_px, valid, solver, self.tol, reference_mask,
                           pin_fallback=pin_fallback, region_name=region_name, shift_removal=shift_removal)

    def solve_at_tolerance(self, displacement_px, valid, solver, tol, reference_mask=None, *,
                           pin_fallback="nearest", region_name=None, near=None, shift_removal=False) -> SurfaceResult:
        """:meth:`solve` with the conjugate-gradient tolerance ``tol`` and the
        "nearest" fallback's box ``near`` given (what the Reconstructor's chains call);
        ``shift_removal``: :class:`processing.options.ReconstructOptions`'
        (:func:`processing.pin.shift_judged`)."""
        return self._solve(displacement_px, valid, solver, tol, reference_mask, pin_fallback=pin_fallback,
                           region_name=region_name, near=near, shift_removal=shift_removal)

    def solve_spectral(self, displacement_px, valid, reference_mask=None, *, pin_fallback="nearest",
                       region_name=None, near=None, judge_shift=True, shift_removal=False) -> SurfaceResult:
        """The spectral path of :meth:`solve` for a finite displacement valid
        everywhere (needs :attr:`spectral_coefficients`, uniform optics)."""
        u, motion = shift_judged(displacement_px, valid, judge_shift, shift_removal)
        h, sx, sy, status, samples = spectral_solve(self, self._fast, u, valid, reference_mask,
                                                    pin_fallback=pin_fallback, region_name=region_name, near=near)
        status = _with_motion(status, displacement_px, samples, self.grid)
        if motion is not None:  # (the whole pattern shifted alike since the reference?)
            status = self.shift_status(status, *motion, valid, reference_mask, pin_fallback=pin_fallback,
                                       region_name=region_name, near=near, removed=shift_removal)
        return SurfaceResult(h, sx, sy, self.x_mm.copy(), self.y_mm.copy(), valid, 0, self.surface_xy, status,
                             samples)

    def shift_status(self, status, median_px, share, valid, reference_mask=None, *, pin_fallback="nearest",
                     region_name=None, near=None, removed=False) -> PinStatus:
        """``status`` with a frame's :func:`processing.pin.frame_motion` (``median_px`` (2,), ``share``); where
        the whole pattern shifted (:attr:`PinStatus.shifted`), also the RMS (um) of the heights that uniform
        displacement alone gives, solved on ``valid`` and pinned as the frame (linear: what the shift put
        into them), and the water level that moves the pattern so (TIR's ``a = B kappa``, grid mean);
        ``removed``: the option ``shift_removal`` took it out (``shift_removed``)."""
        status = dataclasses.replace(status, frame_motion_px=float(np.hypot(*median_px)),
                                     frame_shift_share=float(share), frame_motion_row_px=float(median_px[0]),
                                     frame_motion_col_px=float(median_px[1]))
        if not status.shifted:
            return status
        effect_um = self.shift_effect_um(median_px, valid, reference_mask, pin_fallback=pin_fallback,
                                         region_name=region_name, near=near)
        return dataclasses.replace(status, shift_effect_um=effect_um, shift_level_um=self.shift_level_um(median_px),
                                   shift_removed=bool(removed))

    def shift_effect_um(self, shift_px, valid=None, reference_mask=None, *, pin_fallback="nearest",
                        region_name=None, near=None) -> float:
        """RMS (um) over ``valid`` (None: every sample) of the heights that the uniform displacement
        ``shift_px`` (2,) alone gives, solved and pinned as a frame: what a shift of the whole pattern
        puts into them (linear)."""
        v = np.ones(self.shape, bool) if valid is None else np.asarray(valid, bool)
        uniform = np.empty((2,) + self.shape)
        uniform[0], uniform[1] = shift_px
        h = np.asarray(self._solve(uniform, v, "auto", self.tol, reference_mask, pin_fallback=pin_fallback,
                                   region_name=region_name, near=near, judge_shift=False).height_mm, np.float64)
        return 1e3 * float(np.sqrt(np.nanmean(h[v] ** 2)))

    def shift_level_um(self, shift_px) -> float:
        """:func:`processing.pin.level_of_shift_um` of the uniform displacement ``shift_px`` (2,) on this
        grid (TIR's ``a = B kappa``, the grid's mean)."""
        a = np.linalg.solve(self.Binv, self.kappa[..., None])[..., 0].reshape(-1, 2).mean(axis=0)
        return level_of_shift_um(shift_px, a)

    def _solve(self, displacement_px, valid, solver, tol, reference_mask=None, *, pin_fallback="nearest",
               region_name=None, near=None, judge_shift=True, shift_removal=False):
        """:meth:`solve` with the conjugate-gradient tolerance given (the
        Reconstructor's is tied to the noise of measured displacements); ``judge_shift``: whether
        the whole pattern shifted (:meth:`shift_status`; not for the uniform shift's own solve)."""
        u = np.asarray(displacement_px)
        if u.ndim != 3 or u.shape[0] != 2 or u.shape[1:] != self.shape:
            raise ShapeMismatchError(
                f"displacement_px must have shape (2, {self.shape[0]}, {self.shape[1]}) (u_row, u_col on the grid), "
                f"got {u.shape}"
            )
        finite = np.isfinite(u[0]) & np.isfinite(u[1])
        if valid is None:
            v = finite
        else:
            valid = np.asarray(valid)
            if valid.shape != self.shape:
                raise ShapeMismatchError(
                    f"valid must have shape {self.shape} like the displacement grid, got {valid.shape}"
                )
            v = valid.astype(bool) & finite
        all_valid = bool(v.all())
        if solver not in ("auto", "spectral", "masked"):
            raise TirdeflectError(f"solver must be 'auto', 'spectral' or 'masked', got {solver!r}")
        if solver == "spectral" and not (all_valid and self.constant):
            raise TirdeflectError(
                "the spectral solver needs every sample valid and a telecentric camera; "
                f"{int((~v).sum())} samples are invalid: use solver='masked' (or 'auto')"
            )
        if not v.any():
            from .errors import AllInvalidError

            raise AllInvalidError("no valid displacement sample: nothing to integrate; check the mask and the frame")
        use_spectral = solver == "spectral" or (solver == "auto" and all_valid and self.constant)
        if use_spectral and self._fast is not None:
            return self.solve_spectral(u, v, reference_mask, pin_fallback=pin_fallback, region_name=region_name,
                                       near=near, judge_shift=judge_shift, shift_removal=shift_removal)
        samples, status, _ = self.pin_choice(v, all_valid, reference_mask, pin_fallback, region_name, near)
        status = _with_motion(status, u, samples & v, self.grid)
        u_solved, motion = shift_judged(u, v, judge_shift, shift_removal)
        if motion is not None:
            status = self.shift_status(status, *motion, v, reference_mask, pin_fallback=pin_fallback,
                                       region_name=region_name, near=near, removed=shift_removal)
        uz = np.where(v, u_solved, 0.0) if not all_valid else u_solved
        gr, gc = self.gradients(uz)
        iterations = 0
        if use_spectral:
            ec, er = edge_data(self, gr, gc, None)
            f = poisson_neumann(apply_AT(self, ec, er), self.denom)
            pieces, n_pieces = None, 1
        else:
            f, iterations = solve_masked(self, gr, gc, v, tol)
            pieces, n_pieces = connected_regions(v)
        h = f * self.null
        n_valid = int(np.count_nonzero(v))
        v, pinned = self._pin(h, v, pieces, n_pieces, samples)
        dropped = n_valid - int(np.count_nonzero(v))
        if dropped or pinned > 1:
            status = dataclasses.replace(status, unpinned_fraction=dropped / n_valid, pieces=pinned)
        # slopes from the data: grad_px h = g - kappa h, then to surface units
        kr = self.kappa[..., 0]
        kc = self.kappa[..., 1]
        sr = gr - kr * h
        sc = gc - kc * h
        Kt = self.Kinv_T
        if Kt.ndim == 2:
            sy = Kt[0, 0] * sr + Kt[0, 1] * sc
            sx = Kt[1, 0] * sr + Kt[1, 1] * sc
        else:
            sy = Kt[..., 0, 0] * sr + Kt[..., 0, 1] * sc
            sx = Kt[..., 1, 0] * sr + Kt[..., 1, 1] * sc
        nan = np.float32(np.nan)
        if v.all():
            hh, sx, sy = h.astype(np.float32), sx.astype(np.float32), sy.astype(np.float32)
        else:
            hh = np.where(v, h, nan).astype(np.float32)
            sx = np.where(v, sx, nan).astype(np.float32)
            sy = np.where(v, sy, nan).astype(np.float32)
        return SurfaceResult(hh, sx, sy, self.x_mm.copy(), self.y_mm.copy(), v, iterations, self.surface_xy,
                             status, samples)

    def _pin(self, h, v, pieces, n_pieces, samples):
        """Subtract alpha * null mode per connected piece (in place); returns the final validity and how
        many pieces were pinned.

        A piece is pinned by the least squares of ``alpha n`` on its pin
        samples; one with fewer than PIN_MIN_PIECE_SAMPLES of them is invalid."""
        ref = samples & v
        if not ref.any():
            from .errors import AllInvalidError

            raise AllInvalidError("no valid pin sample: the height offset cannot be measured; check the mask")
        n = self.null
        if pieces is None:
            h -= null_mode_offset(h, n, ref) * n
            return v, 1
        v = v.copy()
        # per-piece sums over the pin samples alone (a tenth of the grid or so: 20x faster than
        # ndimage.sum_labels over every sample)
        at = np.flatnonzero(ref)
        label = pieces.reshape(-1)[at]
        n_at = n.reshape(-1)[at]
        num = np.bincount(label, weights=h.reshape(-1)[at] * n_at, minlength=n_pieces + 1)[1:]
        den = np.bincount(label, weights=n_at * n_at, minlength=n_pieces + 1)[1:]
        count = np.bincount(label, minlength=n_pieces + 1)[1:]
        has_ref = (den > 0) & (count >= min(PIN_MIN_PIECE_SAMPLES, int(np.count_nonzero(ref))))
        alpha = np.zeros(n_pieces + 1)
        alpha[1:][has_ref] = num[has_ref] / den[has_ref]
        h -= alpha[pieces] * n
        pinned = np.zeros(n_pieces + 1, dtype=bool)
        pinned[1:] = has_ref
        v &= pinned[pieces]
        return v, int(np.count_nonzero(has_ref))

_CACHE: "OrderedDict[tuple, HeightSolver]" = OrderedDict()
_CACHE_SIZE = 8
_CACHE_LOCK = threading.Lock()  # the GUI and the processing worker may solve at once


def solver_for(geometry, rows_px, cols_px, frame_shape) -> HeightSolver:
    r = np.asarray(rows_px, dtype=np.float64).ravel()
    c = np.asarray(cols_px, dtype=np.float64).ravel()
    key = (
        geometry,
        r.size,
        float(r[0]) if r.size else None,
        float(r[-1]) if r.size else None,
        c.size,
        float(c[0]) if c.size else None,
        float(c[-1]) if c.size else None,
        tuple(int(s) for s in frame_shape),
    )
    with _CACHE_LOCK:
        s = _CACHE.get(key)
        if s is not None:
            _CACHE.move_to_end(key)
            return s
    s = HeightSolver(geometry, r, c, frame_shape)  # solvers are read-only once built
    with _CACHE_LOCK:
        _CACHE[key] = s
        while len(_CACHE) > _CACHE_SIZE:
            _CACHE.popitem(last=False)
    return s


def surface_from_displacement(displacement_px, valid, geometry, *, rows_px, cols_px, frame_shape, solver="auto",
                              reference_mask=None, pin_fallback="nearest", region_name=None, shift_removal=False):
    """Surface heights and slopes from a displacement field (pixels).

    Parameters
    ----------
    displacement_px : ndarray (2, n_rows, n_cols) float32
        ``(u_row, u_col)`` in image pixels, FD convention ``I(r) = I0(r - u)``,
        sampled at pixel coordinates ``rows_px x cols_px``.
    valid : ndarray (n_rows, n_cols) bool or None
        Samples to use (None: all finite samples).
    geometry : Geometry
    rows_px : ndarray (n_rows,)
        Pixel rows of the samples (evenly spaced: full grid or every k-th row).
    cols_px : ndarray (n_cols,)
        Pixel columns of the samples.
    frame_shape : (int, int)
        Shape of the camera frame (its centre is the optical axis).
    solver : {"auto", "spectral", "masked"}
    reference_mask, pin_fallback, region_name, shift_removal :
        See :meth:`HeightSolver.solve` (default: ``geometry.reference_region``,
        fallback to the valid samples nearest it, a shift left in).

    Returns
    -------
    SurfaceResult
        ``height_mm``, ``slope_x``, ``slope_y`` (image frame: x along
        increasing column, y along increasing row, mm on the surface), NaN
        where not valid; ``x_mm`` (n_cols,), ``y_mm`` (n_rows,). The null
        space is pinned by ``geometry.reference_region`` (mean height 0
        there); ``pin`` says where it was pinned (:class:`PinStatus`).

    Raises
    ------
    GeometryError
        The reference region holds fewer valid samples than the pin needs
        and ``pin_fallback="refuse"``.
    ShapeMismatchError
        Arrays and grid disagree.

    Examples
    --------
    >>> import numpy as np
    >>> from processing.geometry import Geometry
    >>> g = Geometry(theta_deg=60, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False)
    >>> u = np.zeros((2, 64, 64), np.float32)
    >>> r = surface_from_displacement(u, None, g, rows_px=np.arange(64), cols_px=np.arange(64), frame_shape=(64, 64))
    >>> float(np.abs(r.height_mm).max())
    0.0
    """
    s = solver_for(geometry, rows_px, cols_px, frame_shape)
    return s.solve(displacement_px, valid, solver=solver, reference_mask=reference_mask,
                   pin_fallback=pin_fallback, region_name=region_name, shift_removal=shift_removal)
