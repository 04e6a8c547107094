"""A camera whose pixels come in a 2 x 2 mosaic of responses: a colour camera's
Bayer filter read raw (``BayerRG8``, ``BayerGR12``, a colour high-speed camera's
raw file), or a sensor whose alternate columns or rows are read by amplifiers of
other gains.  Each of the four sub-grids (every 2nd row and column, from one of
the four corners of a 2 x 2 cell) sees the same grey board through its own
gain; left as it is, a colour camera's mosaic puts every other pixel above
all its neighbours, and the reference's defect search
(:func:`processing.mask.defect_pixels`) took them for stuck pixels: a
ray-traced bump 0.13 -> 14 %, waves 0.4 -> 29-34 % rel. RMS height error with
exit 0 and no word (``tirdeflect simulate`` 256^2, 12 bit, the mosaic of a
colour camera under white light, gains 1 / 0.6 / 0.6 / 0.4; 7 Dec 2026).

:func:`mosaic_response` measures the four responses on the reference (each
sub-grid's spread and levels: the board's light is the same on all four, so
their differences are the camera's) and says whether they differ
(:data:`MOSAIC_MIN_SPREAD`); :func:`equalise_mosaic` maps each sub-grid onto
the common response (:func:`mosaic_maps`, made once), the reference and every
frame alike: about 4 ms a 1024^2 frame (a camera without the mosaic pays
nothing).  The heights of a camera without the mosaic again: the bump above
0.13 %, its heights within 0.006 % of the unmosaicked frames', with or without
other black levels per sub-grid.
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import numpy as np

__all__ = ["MOSAIC_MIN_SPREAD", "MOSAIC_MIN_SIDE", "MosaicResponse", "mosaic_response", "mosaic_maps",
           "equalise_mosaic", "equalised_reference"]

#: The four sub-grids differ (a mosaic) when both the largest of their
#: standard deviations and the largest of their 10-90 % ranges (the board's
#: contrast through each gain; the range is blind to stuck pixels, the standard
#: deviation less noisy on random dots) are more than this fraction above the
#: smallest.  Measured without a mosaic (standard deviation / range): boards
#: of 3-20 px at most 0.001 / 0.008 (64-256^2), both real cameras of the tests'
#: data 0.030-0.036 / 0.026-0.038 (alternate rows read 3 % apart: left as they
#: are, and a 10 % row mosaic moves a ray-traced bump's heights by 0.03
#: points), random dots 0.08 / 0.12 at 128^2 (0.02 / 0.05 at 256^2: the dots
#: each sub-grid happens to see), 20 stuck pixels at 65535 in a 12-bit 256^2
#: reference 0.16 / 0.  A colour camera under white light: 0.3-1.5 both.
MOSAIC_MIN_SPREAD = 0.2
#: Frames smaller than this a side are not judged (too few dots in a sub-grid).
MOSAIC_MIN_SIDE = 128


class MosaicResponse(NamedTuple):
    """The reference's four sub-grids (index ``[i, j]``: rows ``i::2``, columns ``j::2``)."""

    #: (2, 2) 10th percentile of each sub-grid, grey levels
    low: np.ndarray
    #: (2, 2) its 90th percentile
    high: np.ndarray

    def gains(self) -> np.ndarray:
        """(2, 2) each sub-grid's gain relative to their mean (its 10-90 % range over theirs)."""
        span = self.high - self.low
        return span / span.mean()

    def describe(self) -> str:
        gains = " / ".join(f"{g:.2f}" for g in self.gains().ravel())
        return (f"the reference shows a 2 x 2 mosaic of pixel gains (a colour camera's Bayer filter read raw, or "
                f"alternate columns or rows read at other gains): its four sub-grids' gains {gains}; each was "
                "mapped onto their common response in the reference and every frame (a camera set to a mono "
                "pixel format needs none of it)")


def _spread(values) -> float:
    """How far the largest of four positive values is above the smallest, as a fraction."""
    return float(values.max() / values.min() - 1.0)


def mosaic_response(reference) -> Optional[MosaicResponse]:
    """The reference's :class:`MosaicResponse` where its four sub-grids differ by more than
    :data:`MOSAIC_MIN_SPREAD` (see there), else None (and None for a frame under
    :data:`MOSAIC_MIN_SIDE` px a side or without contrast)."""
    a = np.asarray(reference)
    if a.ndim != 2 or min(a.shape) < MOSAIC_MIN_SIDE:
        return None
    rows, cols = (a.shape[0] // 2) * 2, (a.shape[1] // 2) * 2
    std = np.empty((2, 2))
    low = np.empty((2, 2))
    high = np.empty((2, 2))
    for i in range(2):
        for j in range(2):
            sub = np.asarray(a[i:rows:2, j:cols:2], np.float64)
            std[i, j] = sub.std()
            low[i, j], high[i, j] = np.percentile(sub, (10.0, 90.0))
    span = high - low
    if not (np.all(np.isfinite(std)) and np.all(np.isfinite(span)) and std.min() > 0 and span.min() > 0):
        return None
    if min(_spread(std), _spread(span)) <= MOSAIC_MIN_SPREAD:
        return None
    return MosaicResponse(low=low, high=high)


def mosaic_maps(response: Optional[MosaicResponse], shape):
    """``(gain, offset)``: the float32 maps of ``shape`` that :func:`equalise_mosaic`
    applies, each sub-grid onto the common response (its 10th and 90th percentiles
    onto the four's means of them); None where ``response`` is None."""
    if response is None:
        return None
    span = response.high - response.low
    g = span.mean() / span
    b = response.low.mean() - response.low * g
    reps = ((shape[0] + 1) // 2, (shape[1] + 1) // 2)
    gain = np.ascontiguousarray(np.tile(g.astype(np.float32), reps)[: shape[0], : shape[1]])
    offset = np.ascontiguousarray(np.tile(b.astype(np.float32), reps)[: shape[0], : shape[1]])
    return gain, offset


def equalised_reference(reference):
    """``(response, maps, reference)``: the reference's :func:`mosaic_response`, its
    :func:`mosaic_maps` and the reference equalised by them (itself where no mosaic)."""
    response = mosaic_response(reference)
    maps = mosaic_maps(response, np.shape(reference))
    return response, maps, equalise_mosaic(reference, maps)


def equalise_mosaic(image, maps) -> np.ndarray:
    """``image`` (2-D) with each sub-grid mapped onto the common response by ``maps``
    (:func:`mosaic_maps`), float32 (a copy); ``image`` itself where ``maps`` is None."""
    if maps is None:
        return image
    gain, offset = maps
    out = np.array(image, dtype=np.float32)  # a copy: the caller's frame stays as recorded
    out *= gain
    out += offset
    return out
