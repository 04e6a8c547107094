"""The automatic colour range of a view: which levels a map is drawn with.

A view's range follows its data (:func:`data_levels`) and moves when the data ask for it
(:func:`range_moves`). Two rules (:class:`ColourRule`):

* :data:`CAMERA` for camera images: the 1st to 99th percentile, so that hot pixels and glints
  do not set the range;
* :data:`SURFACE` for the maps of the surface (height, slopes, displacement): the 0.1st to 99.9th
  percentile, and never less than what two neighbouring samples reach together. The event being
  watched (a disc's dimple at its start, a drop) may cover a few samples of the drawn map, fewer
  than the 0.1 % the percentile leaves out: a feature two samples across is held, a stray sample
  is not (on a map of noise alone the pairs reach less than the percentile: nothing changes).
"""

from __future__ import annotations

import dataclasses
from typing import Optional, Tuple

import numpy as np

from processing.mask import percentiles

__all__ = ["ColourRule", "CAMERA", "SURFACE", "finite_sample", "robust_levels", "feature_levels", "data_levels",
           "range_moves", "without_spread"]


@dataclasses.dataclass(frozen=True)
class ColourRule:
    """How a view's automatic colour range follows its data.

    percentiles : (low, high) percentiles of the data (of ``|data|``, the high one, when the view is
    symmetric about zero); hold_features : the range also holds every value reached by a 2 x 2 block
    of samples (:func:`feature_levels`).
    """

    percentiles: Tuple[float, float] = (1.0, 99.0)
    hold_features: bool = False


CAMERA = ColourRule((1.0, 99.0), hold_features=False)
SURFACE = ColourRule((0.1, 99.9), hold_features=True)


def finite_sample(data: np.ndarray, max_samples: int = 20000) -> np.ndarray:
    """Every k-th sample of ``data`` in memory order (about ``max_samples`` of them), the finite ones:
    what :func:`robust_levels` takes its percentiles of and :func:`without_spread` looks at."""
    flat = data.ravel()
    sub = flat[::max(1, flat.size // max_samples)]
    return sub[np.isfinite(sub)] if sub.dtype.kind == "f" else sub


def robust_levels(data: np.ndarray, *, symmetric: bool = False, lo_pct: float = 1.0,
                  hi_pct: float = 99.0, max_samples: int = 20000) -> Tuple[float, float]:
    """Display levels from percentiles of a subsample, ignoring NaN.

    Parameters
    ----------
    data : ndarray
        Any 2-D array (NaN allowed).
    symmetric : bool
        Levels ``(-m, m)`` around zero (heights, slopes).
    lo_pct, hi_pct : float
        Percentiles for the low and high level.

    Returns
    -------
    (float, float)
        Low and high level, ``low < high`` always.
    """
    sub = finite_sample(data, max_samples)
    if sub.size == 0:
        return (0.0, 1.0)
    if symmetric:
        m = percentiles(np.abs(sub), [hi_pct])[0]
        m = m if m > 0 else 1.0
        return (-m, m)
    lo, hi = percentiles(sub, [lo_pct, hi_pct])
    if not hi > lo:
        hi = lo + 1.0
    return (lo, hi)


def feature_levels(data: np.ndarray, *, symmetric: bool = False,
                   max_samples: int = 65536) -> Optional[Tuple[float, float]]:
    """The lowest and highest values that two neighbouring samples (in a row or a column) reach together.

    A single stray sample does not count; the core of a feature two samples across does. Maps larger
    than ``max_samples`` are looked at every k-th row and column.

    Parameters
    ----------
    data : ndarray, shape (rows, cols)
        A map (NaN allowed: a pair with a NaN sample counts for nothing).
    symmetric : bool
        Of ``|data|``: ``(-m, m)``.

    Returns
    -------
    (float, float) or None
        None where no pair of neighbours is finite.
    """
    step = max(1, int(np.ceil(np.sqrt(data.size / max_samples))))
    d = np.asarray(data[::step, ::step], dtype=np.float32)
    if d.ndim != 2 or d.size < 2:
        return None
    if symmetric:
        d = np.abs(d)
    pairs = [(d[:, :-1], d[:, 1:]), (d[:-1], d[1:])]
    hi, lo = -np.inf, np.inf
    for a, b in pairs:
        low_of_pair = np.minimum(a, b)  # NaN where either is: such a pair counts for nothing
        finite = np.isfinite(low_of_pair)
        if finite.any():
            hi = max(hi, float(low_of_pair[finite].max()))
            if not symmetric:
                lo = min(lo, float(np.maximum(a, b)[finite].min()))
    if not np.isfinite(hi):
        return None
    return (-hi, hi) if symmetric else (lo, hi)


def data_levels(data: np.ndarray, rule: ColourRule, *, symmetric: bool = False) -> Tuple[float, float]:
    """The levels the data ask for under ``rule`` (``low < high``)."""
    lo_pct, hi_pct = rule.percentiles
    lo, hi = robust_levels(data, symmetric=symmetric, lo_pct=lo_pct, hi_pct=hi_pct)
    if rule.hold_features and data.dtype.kind == "f":
        held = feature_levels(data, symmetric=symmetric)
        if held is not None:
            lo, hi = min(lo, held[0]), max(hi, held[1])
    return (lo, hi)


def without_spread(data: np.ndarray, *, max_samples: int = 20000) -> bool:
    """True where the finite samples of ``data`` (the subsample :func:`robust_levels` reads) are all one
    value, or there are none: its levels are :func:`robust_levels`' stand-in (a width of 1), not the
    data's.  A live frame that is the reference itself gives such maps (heights and slopes exactly 0):
    the next map with a spread must set its own range at once, not a few times a second by 10 % steps
    from +-1 (its bump of +-0.4 mrad stood under +-1 mrad after the frame was drawn)."""
    sub = finite_sample(data, max_samples)
    return bool(sub.size == 0 or sub.min() == sub.max())


def range_moves(old: Tuple[float, float], new: Tuple[float, float], *, due: bool) -> bool:
    """Whether a view drawn with levels ``old`` moves to ``new`` now.

    At once when the data reach more than 10 % of the half range past either end (a deepening dimple
    is never drawn clipped for long; with "at once only when the range doubled" the synthetic
    impact's 2.4 um dimple stood under a +-1.16 um range, and at 10 % of the whole range, +-m
    growing only past 1.2 m, the slope map's steepest samples stood up to 20 % over its end) or when the
    range shrank to a quarter; otherwise only when ``due`` (a few times a second: the colour bar's
    axis is costly to redraw) and by more than 10 % of the range.
    """
    old_lo, old_hi = old
    lo, hi = new
    span = max(old_hi - old_lo, 1e-30)
    reach = 0.05 * span  # 10 % of the half range
    if hi - lo < 0.25 * span or lo < old_lo - reach or hi > old_hi + reach:
        return True
    return due and (abs(lo - old_lo) > 0.1 * span or abs(hi - old_hi) > 0.1 * span)
