"""The discretisation :class:`processing.height.HeightSolver` is built on
(:mod:`processing.height`'s module docstring): the Neumann Poisson solve by
DCT-II (:func:`poisson_neumann`, :func:`neumann_eigenvalues`), the
fourth-order cell average of an edge (:func:`cell_average`) and its
transposed divergence (:func:`div_T`), the sample grid (:func:`check_grid`)
and the optics of a finite camera distance (:func:`variable_optics`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft

from .errors import ShapeMismatchError
from .geometry import Geometry

__all__ = ["fft_workers", "neumann_eigenvalues", "poisson_neumann", "cell_average", "div_T", "SampleGrid",
           "check_grid", "variable_optics"]

_WORKERS = 2  # FFT threads for large grids (the target machine has 2 cores)


def fft_workers(shape) -> int:
    """Threads only pay off above about 256 x 256 samples."""
    return _WORKERS if shape[0] * shape[1] > 300_000 else 1



# ============================================================================ kernels
def neumann_eigenvalues(n: int, spacing: float) -> np.ndarray:
    k = np.arange(n)
    return (2.0 * np.sin(np.pi * k / (2.0 * n)) / spacing) ** 2


def poisson_neumann(div_rhs: np.ndarray, denom: np.ndarray) -> np.ndarray:
    """Solve the Neumann Poisson normal equations by DCT-II.

    Parameters
    ----------
    div_rhs : ndarray (n_rows, n_cols) float64
        ``D^T G`` (minus the divergence of the edge data, zero flux outside).
    denom : ndarray (n_rows, n_cols) float64
        Eigenvalues of ``D^T D`` in the DCT-II basis; ``denom[0, 0]`` is
        ignored (the constant mode, returned as zero).
    """
    w = fft_workers(div_rhs.shape)
    c = sfft.dctn(div_rhs, type=2, norm="ortho", workers=w)
    c[0, 0] = 0.0
    c /= denom
    return sfft.idctn(c, type=2, norm="ortho", workers=w)


def cell_average(G: np.ndarray, axis: int, ok: np.ndarray | None) -> np.ndarray:
    """Average of G over each edge along ``axis`` (fourth order where possible).

    ``ok`` (bool, same shape as G or None) marks samples usable in the wide
    stencil; edges whose outer neighbours are missing use the trapezoid.
    """
    G = np.moveaxis(G, axis, 0)
    n = G.shape[0]
    out = 0.5 * (G[:-1] + G[1:])
    if n >= 4:
        # (-G[i-1] + 13 G[i] + 13 G[j] - G[j+1]) / 24 = trapezoid + this correction
        corr = (-G[:-3] + G[1:-2] + G[2:-1] - G[3:]) / 24.0
        if ok is not None:
            okm = np.moveaxis(ok, axis, 0)
            good = okm[:-3] & okm[1:-2] & okm[2:-1] & okm[3:]
            corr = np.where(good, corr, 0.0)
        out[1:-1] += corr
    return np.moveaxis(out, 0, axis)


def div_T(ec: np.ndarray | None, er: np.ndarray | None, shape, dc: float, dr: float) -> np.ndarray:
    """``D^T e`` for edge data ec (rows, cols-1) and er (rows-1, cols)."""
    dtype = np.result_type(*(e.dtype for e in (ec, er) if e is not None))
    out = np.zeros(shape, dtype=dtype)
    if ec is not None:
        out[:, :-1] -= ec / dc
        out[:, 1:] += ec / dc
    if er is not None:
        out[:-1, :] -= er / dr
        out[1:, :] += er / dr
    return out


# ============================================================================ solver
@dataclass
class SampleGrid:
    rows_px: np.ndarray
    cols_px: np.ndarray
    frame_shape: tuple
    dr: float
    dc: float


def check_grid(rows_px, cols_px, frame_shape) -> SampleGrid:
    rows_px = np.asarray(rows_px, dtype=np.float64).ravel()
    cols_px = np.asarray(cols_px, dtype=np.float64).ravel()
    if len(frame_shape) != 2:
        raise ShapeMismatchError(f"frame_shape must be (n_rows, n_cols), got {frame_shape!r}")
    frame_shape = (int(frame_shape[0]), int(frame_shape[1]))
    steps = []
    for name, v in (("rows_px", rows_px), ("cols_px", cols_px)):
        if v.size < 2:
            raise ShapeMismatchError(f"{name} needs at least 2 samples, got {v.size}")
        d = np.diff(v)
        if not (d[0] > 0 and np.allclose(d, d[0], rtol=1e-6, atol=1e-9)):
            raise ShapeMismatchError(
                f"{name} must be evenly spaced and increasing (a full or strided grid), "
                f"got steps from {d.min():g} to {d.max():g}"
            )
        steps.append(float(d[0]))
    return SampleGrid(rows_px, cols_px, frame_shape, steps[0], steps[1])


def variable_optics(g: Geometry, grid: SampleGrid):
    """Per-sample ``B^-1``, ``kappa``, ``K^-T`` and surface (x, y) for a finite camera distance.

    The coefficients vary on the scale of the camera distance, so on large
    grids they are computed exactly on a 65 x 65 lattice spanning the grid
    and interpolated by bicubic splines (relative error far below 1e-6).
    """
    from scipy.interpolate import RectBivariateSpline

    def exact(rows, cols):
        lr = g.linear_response(rows[:, None], cols[None, :], grid.frame_shape)
        Binv = np.linalg.inv(lr.B)
        kappa = np.einsum("...ij,...j->...i", Binv, lr.a)
        Kinv_T = np.swapaxes(np.linalg.inv(lr.jac_surface), -1, -2)
        return Binv, kappa, Kinv_T, lr.surface_xy

    rows, cols = grid.rows_px, grid.cols_px
    if rows.size * cols.size <= 128 * 128:
        return exact(rows, cols)
    rc = np.linspace(rows[0], rows[-1], min(rows.size, 65))
    cc = np.linspace(cols[0], cols[-1], min(cols.size, 65))
    coarse = exact(rc, cc)
    out = []
    for arr in coarse:
        flat = arr.reshape(rc.size, cc.size, -1)
        comp = [
            RectBivariateSpline(rc, cc, flat[..., k], kx=min(3, rc.size - 1), ky=min(3, cc.size - 1))(rows, cols)
            for k in range(flat.shape[-1])
        ]
        out.append(np.stack(comp, axis=-1).reshape(rows.size, cols.size, *arr.shape[2:]))
    return tuple(out)
