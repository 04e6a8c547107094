"""Height at a surface point between grid samples: the virtual probe's bilinear rule.

Used by ``tirdeflect probe`` (app/batch/probe.py) on OUT.h5 and by the live
window's probes on each drawn Result, so both read a point the same way: the
four samples around ``(x_mm, y_mm)`` weighted bilinearly, NaN when any sample
with a non-zero weight is unmeasured (never a value from an unmeasured sample).
"""

from __future__ import annotations

import math

import numpy as np

from .errors import TirdeflectError

__all__ = ["ProbeCell", "probe_cell", "probe_cell_2d", "grid_index_of_point", "sample_cell"]


class ProbeCell(tuple):
    """``(row0, col0, row_fraction, col_fraction)``: the grid cell holding a probe point."""

    __slots__ = ()


def _fractional_index(coord: np.ndarray, value: float, what: str) -> float:
    coord = np.asarray(coord, dtype=np.float64)
    idx = np.arange(coord.size, dtype=np.float64)
    if coord.size > 1 and coord[-1] < coord[0]:
        coord, idx = coord[::-1], idx[::-1]
    lo, hi = float(coord[0]), float(coord[-1])
    if not lo <= value <= hi:
        raise TirdeflectError(
            f"probe {what} = {value:g} mm is outside the measured field ({what} from {lo:.3f} "
            f"to {hi:.3f} mm); choose a point inside it")
    return float(np.interp(value, coord, idx))


def probe_cell(x_mm: np.ndarray, y_mm: np.ndarray, x: float, y: float) -> ProbeCell:
    """Cell of the grid (columns at ``x_mm``, rows at ``y_mm``, mm) holding the point ``(x, y)`` mm.

    Raises
    ------
    TirdeflectError
        The point lies outside the grid.
    """
    rows, cols = len(y_mm), len(x_mm)
    c = _fractional_index(x_mm, float(x), "x")
    r = _fractional_index(y_mm, float(y), "y")
    r0, c0 = max(min(int(math.floor(r)), rows - 2), 0), max(min(int(math.floor(c)), cols - 2), 0)
    return ProbeCell((r0, c0, r - r0, c - c0))


def _bilinear_map(surface_x_mm, surface_y_mm, row: float, col: float):
    """The piecewise-bilinear map (row, col) -> (x, y) mm of the grid's positions at a fractional index
    (its edge cells extended beyond the grid), and its Jacobian ``d(x, y) / d(row, col)``."""
    rows, cols = surface_x_mm.shape
    r0 = max(min(int(math.floor(row)), rows - 2), 0)
    c0 = max(min(int(math.floor(col)), cols - 2), 0)
    fr, fc = row - r0, col - c0
    corners = np.stack([surface_x_mm[r0:r0 + 2, c0:c0 + 2], surface_y_mm[r0:r0 + 2, c0:c0 + 2]])  # (2, 2, 2)
    p00, p01, p10, p11 = corners[:, 0, 0], corners[:, 0, 1], corners[:, 1, 0], corners[:, 1, 1]
    point = (1 - fr) * ((1 - fc) * p00 + fc * p01) + fr * ((1 - fc) * p10 + fc * p11)
    d_row = (1 - fc) * (p10 - p00) + fc * (p11 - p01)
    d_col = (1 - fr) * (p01 - p00) + fr * (p11 - p10)
    return point, np.stack([d_row, d_col], axis=-1)


def grid_index_of_point(surface_x_mm, surface_y_mm, x: float, y: float) -> tuple:
    """Fractional ``(row, col)`` of the point ``(x, y)`` mm on a grid whose samples lie at the 2-D
    positions ``surface_x_mm``, ``surface_y_mm`` (``(rows, cols)`` each, mm; a keystoned grid, whose
    columns' x change along the rows): the inverse of the bilinear map of the positions between samples,
    by Newton's method from the nearest sample. An index outside ``[0, rows - 1] x [0, cols - 1]`` means a
    point outside the grid (the edge cells' maps extended); NaN where Newton's method does not converge
    (a point far outside it, where the extended map folds).

    Raises
    ------
    TirdeflectError
        The positions are not a grid of at least 2 x 2 finite samples.
    """
    sx = np.asarray(surface_x_mm, dtype=np.float64)
    sy = np.asarray(surface_y_mm, dtype=np.float64)
    if sx.ndim != 2 or sx.shape != sy.shape or min(sx.shape) < 2 or not np.all(np.isfinite(sx) & np.isfinite(sy)):
        raise TirdeflectError(f"the surface positions are not a grid of at least 2 x 2 finite samples "
                              f"(shapes {sx.shape} and {sy.shape})")
    target = np.array([float(x), float(y)])
    row, col = (float(v) for v in np.unravel_index(np.argmin((sx - target[0]) ** 2 + (sy - target[1]) ** 2), sx.shape))
    reach = float(max(sx.shape))
    for _ in range(60):
        point, jac = _bilinear_map(sx, sy, row, col)
        try:
            step = np.clip(np.linalg.solve(jac, target - point), -reach, reach)  # bounded: a far point
        except np.linalg.LinAlgError:
            return float("nan"), float("nan")
        row, col = row + float(step[0]), col + float(step[1])
        if np.all(np.abs(step) < 1e-10):
            return row, col
    return float("nan"), float("nan")


def probe_cell_2d(surface_x_mm, surface_y_mm, x: float, y: float) -> ProbeCell:
    """Cell of the grid whose samples lie at the 2-D positions ``surface_x_mm``, ``surface_y_mm``
    (``(rows, cols)``, mm) holding the point ``(x, y)`` mm (:func:`grid_index_of_point`); the same
    bilinear cell as :func:`probe_cell` where the positions are separable.

    Raises
    ------
    TirdeflectError
        The point lies outside the grid.
    """
    sx = np.asarray(surface_x_mm, dtype=np.float64)
    sy = np.asarray(surface_y_mm, dtype=np.float64)
    rows, cols = sx.shape if sx.ndim == 2 else (0, 0)
    r, c = grid_index_of_point(sx, sy, x, y)
    tol = 1e-9
    if not (-tol <= r <= rows - 1 + tol and -tol <= c <= cols - 1 + tol):
        raise TirdeflectError(
            f"probe point (x, y) = ({float(x):g}, {float(y):g}) mm is outside the measured field (x from "
            f"{sx.min():.3f} to {sx.max():.3f} mm, y from {sy.min():.3f} to {sy.max():.3f} mm; the field is "
            f"keystoned: its edges' x change along the rows, /surface_x_mm and /surface_y_mm say where each "
            f"sample lies); choose a point inside it")
    r, c = min(max(r, 0.0), rows - 1.0), min(max(c, 0.0), cols - 1.0)
    r0, c0 = max(min(int(math.floor(r)), rows - 2), 0), max(min(int(math.floor(c)), cols - 2), 0)
    return ProbeCell((r0, c0, r - r0, c - c0))


def sample_cell(values: np.ndarray, cell: ProbeCell, row_offset: int = 0) -> float:
    """Bilinear value of ``values`` (2-D, rows from ``row_offset``) in ``cell``; NaN if a used sample is not finite."""
    r0, c0, fr, fc = cell
    q = np.asarray(values[r0 - row_offset:r0 - row_offset + 2, c0:c0 + 2], dtype=np.float64)
    w = np.array([[(1 - fr) * (1 - fc), (1 - fr) * fc], [fr * (1 - fc), fr * fc]])[:q.shape[0], :q.shape[1]]
    used = w > 1e-12
    return float(np.sum(q[used] * w[used])) if np.all(np.isfinite(q[used])) else float("nan")
