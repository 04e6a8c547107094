"""The float32 spectral path of :class:`processing.height.HeightSolver`: a
frame valid everywhere on uniform, diagonal optics (a telecentric camera),
where the normal equations are the Neumann Poisson problem solved by one
DCT-II pair.

:func:`prepare_spectral` computes its coefficients once per solver (or says
the optics do not allow it), :func:`spectral_solve` runs one frame,
:func:`div_T_cellavg` is the right-hand side's operator along one axis and
:func:`divergence_matrix` the same and :func:`dct_matrix` the DCT-II as dense matrices (small grids here, every
grid in processing/gpu.py).  The discretisation is the one of
:mod:`processing.height`'s module docstring; the numbers are those of the
solver's float64 path to float32 rounding.
"""

from __future__ import annotations

import numpy as np
import scipy.fft as sfft

from .height_kernels import fft_workers

__all__ = ["divergence_matrix", "div_T_cellavg", "dct_matrix", "prepare_spectral", "spectral_solve"]


def divergence_matrix(n: int, spacing: float) -> np.ndarray:
    """(n, n) float32 matrix of the operator ``D^T cellavg / spacing`` along one
    axis (fourth order inside, :class:`~processing.height.HeightSolver`'s
    discretisation): applied to a grid's rows (``M @ G``) it gives what the
    solver's right-hand side adds along that axis."""
    m = np.zeros((n, n), np.float32)
    div_T_cellavg(np.eye(n, dtype=np.float32), 0, spacing, m)
    return m


def div_T_cellavg(G, axis, spacing, out):
    """Add ``D^T cellavg(G) / spacing`` along ``axis`` to ``out`` (float32, in place)."""
    G = np.moveaxis(G, axis, 0)
    o = np.moveaxis(out, axis, 0)
    s = np.float32(1.0 / (24.0 * spacing))
    # interior nodes 2..n-3: (-G[i-2] + 14 G[i-1] - 14 G[i+1] + G[i+2]) / 24
    t = G[1:-3] - G[3:-1]
    t *= np.float32(14.0)
    t -= G[:-4]
    t += G[4:]
    t *= s
    o[2:-2] += t
    # edges 0 and n-2 (trapezoid), 1 and n-3 (four-point), for nodes 0, 1, n-2, n-1
    e0 = (G[0] + G[1]) * np.float32(0.5 / spacing)
    e1 = (-G[0] + 13 * G[1] + 13 * G[2] - G[3]) * s
    el = (G[-2] + G[-1]) * np.float32(0.5 / spacing)
    el1 = (-G[-4] + 13 * G[-3] + 13 * G[-2] - G[-1]) * s
    o[0] -= e0
    o[1] += e0 - e1
    o[-2] += el1 - el
    o[-1] += el


def dct_matrix(n):
    """Orthonormal DCT-II as an (n, n) float32 matrix: ``X = C x``."""
    k = np.arange(n)[:, None]
    c = np.sqrt(2.0 / n) * np.cos(np.pi * k * (2 * np.arange(n)[None, :] + 1) / (2 * n))
    c[0] /= np.sqrt(2.0)
    return c.astype(np.float32)


def prepare_spectral(solver):
    """Coefficients of the float32 spectral path of ``solver`` (a
    :class:`~processing.height.HeightSolver` whose optics, null space and
    eigenvalues are built), or None where the optics are not uniform and
    diagonal (telecentric, no cross terms) or the grid is under 6 samples."""
    Bi, Kt, k = solver.Binv, solver.Kinv_T, solver.kappa
    shape = solver.shape
    if not (solver.constant and Bi[0, 1] == 0 and Bi[1, 0] == 0 and Kt[0, 1] == 0 and Kt[1, 0] == 0
            and k[1] == 0 and min(shape) >= 6):
        return None
    null_r = solver.null[:, :1].astype(np.float64)  # varies along rows only
    out = {}
    if max(shape) <= 96:
        # small grids: D^T cellavg along each axis as a dense matrix (one
        # matrix product instead of ~25 small array operations).  Only
        # small: above ~100^2 OpenBLAS goes multithreaded and its spinning
        # threads then slow the FFTW and OpenCV calls that follow (measured
        # 3.3 -> 10 ms per decimated 1024^2 frame)
        gr = (Bi[0, 0] / null_r).astype(np.float32)
        out["Mr"] = np.ascontiguousarray(divergence_matrix(shape[0], solver.grid.dr) * gr.T)
        out["McT"] = np.ascontiguousarray(divergence_matrix(shape[1], solver.grid.dc).T)
        cr, cc = dct_matrix(shape[0]), dct_matrix(shape[1])
        out["Cr"], out["CrT"] = cr, np.ascontiguousarray(cr.T)
        out["Cc"], out["CcT"] = cc, np.ascontiguousarray(cc.T)
    denom = solver.denom
    return dict(
        **out,
        gr=(Bi[0, 0] / null_r).astype(np.float32),  # (n_rows, 1)
        gc=(Bi[1, 1] / null_r).astype(np.float32),
        null=null_r.astype(np.float32),
        denom=denom.astype(np.float32),
        inv_denom=np.where(np.arange(denom.size).reshape(shape) == 0, 0.0, 1.0 / denom).astype(np.float32),
        sx=np.float32(Bi[1, 1] * Kt[1, 1]),
        sy_u=np.float32(Bi[0, 0] * Kt[0, 0]),
        sy_h=np.float32(k[0] * Kt[0, 0]),
    )


def spectral_solve(solver, F, u, v, reference_mask=None, *, pin_fallback="nearest", region_name=None, near=None):
    """One frame through the spectral path: ``(height_mm, slope_x, slope_y,
    PinStatus, pin samples)``, float32 on the solver's grid.

    ``F``: :func:`prepare_spectral`'s coefficients of ``solver``; ``u``: the
    displacement (2, n_rows, n_cols), finite everywhere; ``v``: its validity
    (all True); the rest as :meth:`~processing.height.HeightSolver.solve`.
    """
    ur = np.asarray(u[0], dtype=np.float32)
    uc = np.asarray(u[1], dtype=np.float32)
    if "Mr" in F:
        # the same linear operator as below as two small matrix products
        rhs = F["Mr"] @ ur
        t = uc @ F["McT"]
        t *= F["gc"]
        rhs += t
    else:
        rhs = np.zeros(solver.shape, dtype=np.float32)
        # D^T of the cell averages of g / n, in the order (row edges, column edges)
        div_T_cellavg(ur * F["gr"], 0, solver.grid.dr, rhs)
        div_T_cellavg(uc * F["gc"], 1, solver.grid.dc, rhs)
    if "Cr" in F:  # small grid: the DCT pair as four small matrix products
        c = F["Cr"] @ rhs @ F["CcT"]
        c *= F["inv_denom"]  # 0 for the constant mode
        f = F["CrT"] @ c @ F["Cc"]
    else:
        w = fft_workers(solver.shape)
        c = sfft.dctn(rhs, type=2, norm="ortho", workers=w, overwrite_x=True)
        c *= F["inv_denom"]  # 0 for the constant mode
        f = sfft.idctn(c, type=2, norm="ortho", workers=w, overwrite_x=True)
    # pin: h = (f - alpha) n with alpha the n^2-weighted mean of f on the pin samples
    samples, status, (w, nn) = solver.pin_choice(v, True, reference_mask, pin_fallback, region_name, near)
    alpha = float(np.vdot(w, f * F["null"])) / nn if nn > 0 else 0.0
    f -= np.float32(alpha)
    h = f
    h *= F["null"]
    sx = uc * F["sx"]
    sy = ur * F["sy_u"]
    sy -= F["sy_h"] * h
    return h, sx, sy, status, samples
