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

__all__ = ["ProbeCell", "probe_cell", "sample_cell"]


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


def sample_cell(values: np.ndarray, cell: ProbeCell, row_offset: int = 0) -> float:
    """Bilinear value of ``values`` (2-D, rows from ``row_offset``) in ``cell``; NaN if a used sample is not finite."""
    r0, c0, fr, fc = cell
    q = np.asarray(values[r0 - row_offset:r0 - row_offset + 2, c0:c0 + 2], dtype=np.float64)
    w = np.array([[(1 - fr) * (1 - fc), (1 - fr) * fc], [fr * (1 - fc), fr * fc]])[:q.shape[0], :q.shape[1]]
    used = w > 1e-12
    return float(np.sum(q[used] * w[used])) if np.all(np.isfinite(q[used])) else float("nan")
