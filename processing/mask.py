"""The quality mask of the Reconstructor's chains, and the reference region.

What the reference fixes once (:func:`reference_contrast_ok`,
:func:`choose_reference_region`, :func:`reference_pin_region`) and what each
frame goes through (:func:`exposure_gain`, :func:`dilate_invalid`,
:func:`fold_ok`, :func:`drop_islands`), plus the input checks of any image
(:func:`check_sample_range`, :func:`validate_image`) and the sensor's hot and dead
pixels (:func:`defect_pixels`, :func:`repair_pixels`).  Pure functions of arrays.
"""

from __future__ import annotations

import math
import os
from typing import NamedTuple, Optional

import cv2
import numpy as np

from .errors import SampleRangeError
from .geometry import DEFAULT_REFERENCE_BAND, default_reference_region_mask
from .pin import USER_REGION_PREFIX
from .regions import connected_regions

__all__ = ["MIN_EXPOSURE_GAIN", "MAX_SAMPLE_MAGNITUDE", "POOR_FRAME_VALID_FRACTION", "DEFECT_CONTRAST_FRACTION",
           "exposure_gain", "percentiles", "darker_than_reference", "brightness_sample", "mean_level",
           "check_sample_range", "image_array", "validate_image", "defect_pixels",
           "HOT_CANDIDATES_MAX_FRACTION", "HOT_EXCESS_FRACTION", "HOT_EXCESS_OVER_REFERENCE", "HOT_FRAME_SCALE",
           "hot_pixel_limits", "hot_pixels_above", "repair_pixels", "dilate_invalid", "fold_ok",
           "drop_islands", "reference_contrast_ok", "reference_pin_region", "ReferenceRegion",
           "choose_reference_region"]

#: A frame with less than this fraction of valid samples always gets the full
#: pattern check (:func:`processing.carriers.check_pattern_match`), even when the cheap one passed:
#: noise or another pattern can leave the windows' spectral centroid in place.
POOR_FRAME_VALID_FRACTION = 0.5

#: Reference contrast below this fraction of the contrast where the pattern is
#: seen best (90th percentile of the field) marks a blank, dirty or blurred
#: part of the pattern.  The 90th percentile, not the median: where most of the
#: field is blurred (a pattern sharp only in a central disk) the median is the
#: camera noise, and noise samples would pass as pattern (measured on the four
#: real references in tests/data the two agree to 0.1 % of the samples).
REF_CONTRAST_FRACTION = 0.25
REF_CONTRAST_PERCENTILE = 90.0

#: Darkest exposure (frame / reference brightness) the quality mask makes up for.
MIN_EXPOSURE_GAIN = 0.25

#: Largest sample magnitude accepted: no camera gives samples wider than 32 bits.
MAX_SAMPLE_MAGNITUDE = 2.0 ** 32


def exposure_gain(frame, reference_mean: float, amplitude) -> float:
    """How much darker than the reference the frame was exposed: the larger of
    its mean brightness ratio and the 90th percentile of its contrast ratio
    ``|g| / |g0|``, within [:data:`MIN_EXPOSURE_GAIN`, 1].

    The quality mask's ``min_amplitude`` is scaled by it, so a frame taken at
    half the exposure (or with a lamp dimmed) keeps the samples a well exposed
    frame keeps; a blurred frame (contrast lost, brightness kept) or one with an
    offset (brightness up or negative, contrast kept) gets 1, and one more than
    4x darker is masked as before (a 12-bit reference against 8-bit frames
    stays "no contrast").
    """
    if not reference_mean > 0:
        return 1.0
    by_mean = mean_level(frame) / reference_mean
    if not by_mean < 1.0:  # as bright or brighter (or NaN): nothing to make up for
        return 1.0
    by_contrast = percentiles(amplitude, [90])[0] if np.size(amplitude) else 1.0
    gain = max(by_mean, by_contrast)
    return float(min(1.0, max(MIN_EXPOSURE_GAIN, gain))) if math.isfinite(gain) else 1.0


def percentiles(values, pcts) -> list:
    """``np.percentile(values, pcts)`` for a list ``pcts`` (linear between the two nearest order
    statistics: the same floats, tested), each through one partition at its upper order statistic,
    the lower the largest value before it: 0.03 ms for the 90th of the live grid of a 1024^2 frame,
    where ``np.percentile`` takes 0.5 ms, and a partition at both order statistics is 10x slower
    than at one.  The exposure gain's contrast decile and the window's colour ranges (every map, every
    frame) take them.  ``values`` finite, not empty."""
    flat = np.asarray(values).reshape(-1)
    n = flat.size
    out = []
    for pct in pcts:
        position = pct / 100.0 * (n - 1)
        low = int(position)
        high = min(low + 1, n - 1)
        part = np.partition(flat, high)
        b = part[high]
        a = part[:high].max() if high > low else b
        t = position - low
        step = float(b - a)  # in the samples' own type, as NumPy's lerp takes it; then in float64
        out.append(float(a) + step * t if t < 0.5 else float(b) - step * (1.0 - t))
    return out


def darker_than_reference(frame, reference_mean: float) -> str:
    """Why a frame with no sample left may read as "no contrast": where its mean brightness is below
    :data:`MIN_EXPOSURE_GAIN` of the reference's (``reference_mean``, its :func:`mean_level`),
    beyond what :func:`exposure_gain` makes up for, a sentence that says by how much and what may
    cause it (a reference stored at another bit depth: 12-bit data in the top bits of 16-bit words
    read 16x brighter than the camera's frames); else ""."""
    if not reference_mean > 0:
        return ""
    level = mean_level(frame)
    if not level < MIN_EXPOSURE_GAIN * reference_mean:
        return ""
    if not level > 0:
        return (f"the frame is black (mean level {level:.5g} against the reference's {reference_mean:.5g}): the "
                f"light is off, the lens covered or the exposure too short")
    return (f"the frame is {reference_mean / level:.3g}x darker than the reference (mean level {level:.5g} against "
            f"{reference_mean:.5g}): the light, "
            f"exposure or gain changed since the reference, or the reference was stored at another bit depth "
            f"(12-bit data in the top bits of 16-bit words reads 16x brighter); take the reference with this "
            f"camera at these settings")


def brightness_sample(image):
    """Every 4th pixel of every 4th row, for the mean brightness at 1/16 of the cost (frame and
    reference sampled alike; the mask's threshold needs the ratio to a few per cent)."""
    return np.asarray(image)[::4, ::4]


def mean_level(image) -> float:
    """The mean grey level of :func:`brightness_sample` of ``image`` (float64 sum): what a frame's and
    its reference's brightness are compared by (:func:`exposure_gain`, :func:`darker_than_reference`)."""
    return float(np.mean(brightness_sample(image), dtype=np.float64))


def check_sample_range(image, name: str = "frame") -> None:
    """Refuse an image whose samples no camera gives: NaN or infinite, or
    beyond +-:data:`MAX_SAMPLE_MAGNITUDE` (a float image rescaled by 1e10...),
    with :class:`SampleRangeError` naming the value and where it is.  Cheap
    (min and max); run before any solver."""
    a = np.asarray(image)
    if a.dtype.kind not in "uif" or not a.size:
        return
    if a.dtype.kind in "ui" and a.dtype.itemsize <= 4:
        return  # within 32 bits by its type
    lo, hi = float(a.min()), float(a.max())
    if math.isfinite(lo) and math.isfinite(hi) and max(-lo, hi) <= MAX_SAMPLE_MAGNITUDE:
        return
    if not (math.isfinite(lo) and math.isfinite(hi)):
        bad = ~np.isfinite(a)
        r, c = (int(v) for v in np.argwhere(bad)[0])
        raise SampleRangeError(
            f"{name} holds {int(np.count_nonzero(bad))} NaN or infinite sample(s) (the first at row {r}, "
            f"column {c}); pass the raw camera image, not a processed one")
    worst = hi if hi >= -lo else lo
    r, c = (int(v) for v in np.unravel_index(int(np.argmax(np.abs(a))), a.shape))
    raise SampleRangeError(
        f"{name} holds a sample of {worst:.3g} (row {r}, column {c}), beyond what any camera gives "
        f"(|value| <= {MAX_SAMPLE_MAGNITUDE:.3g}, 32 bits): the image was rescaled; pass the camera's "
        f"own values (or divide the scale back out)")


def image_array(image, name):
    """``np.asarray(image)``; TypeError for a file's path (a script that passed the name, not the image)."""
    if isinstance(image, (str, os.PathLike)):
        raise TypeError(f"{name} must be an image array (rows, cols), got the path {str(image)!r}; read it "
                        f"first, e.g. app.files.imageio.read_image(path)")
    return np.asarray(image)


def validate_image(image, name):
    """``image`` as an array, checked: 2-D, a grey dtype, samples a camera gives (ValueError, SampleRangeError)."""
    a = image_array(image, name)
    if a.ndim != 2:
        raise ValueError(f"{name} must be a 2-D grey image (rows, cols); got shape {a.shape}. "
                         "Convert colour images to grey first")
    if a.dtype.kind not in "uif" or a.dtype.itemsize > 8:
        raise ValueError(f"{name} must be uint8, uint16 or float; got dtype {a.dtype}")
    check_sample_range(a, name)
    return a


#: A pixel is a sensor defect (:func:`defect_pixels`) where it lies beyond all eight neighbours by
#: more than their own spread and by more than this fraction of the image's contrast (1st to
#: 99th percentile).
DEFECT_CONTRAST_FRACTION = 0.25


def _contrast(x) -> float:
    """The contrast of image ``x`` the defect tests measure against: its 1st to 99th
    percentile (of every 4th pixel each way), grey levels."""
    p1, p99 = np.percentile(x[::4, ::4], (1.0, 99.0))
    return float(p99 - p1)


def _neighbours(a, r, c):
    """The 8 neighbours (8, n) of the pixels ``(r, c)`` of ``a``, float64, clamped at the border."""
    rows, cols = a.shape
    return np.stack([a[np.clip(r + dr, 0, rows - 1), np.clip(c + dc, 0, cols - 1)].astype(np.float64)
                     for dr in (-1, 0, 1) for dc in (-1, 0, 1) if dr or dc])


#: The 8 neighbours of a pixel (a 3 x 3 kernel without its centre).
_RING = np.ones((3, 3), np.uint8)
_RING[1, 1] = 0


def _ring_max(x):
    """The largest of each pixel's 8 neighbours (float32 ``x``; mirrored at the border)."""
    return cv2.dilate(x, _RING, borderType=cv2.BORDER_REFLECT_101)


def defect_pixels(image, contrast_fraction: float = DEFECT_CONTRAST_FRACTION):
    """Flat indices (int64, sorted) of the isolated hot or dead pixels of ``image``: above the
    largest of its 8 neighbours, or below the smallest, by more than the neighbours' range and
    by more than ``contrast_fraction`` of the image's contrast. No pattern these methods read
    has such a pixel (a checkerboard's period or a dot is several pixels); a stuck sensor pixel
    is one, and FD's band-pass spreads it over a few carrier periods of phase: 20 pixels at
    65535 in a 12-bit reference and its frames took a 4 um bump from 0.075 to 2.5 % rms height
    error (ray-traced, 256^2; 5 Dec 2026). Found on every table case's reference and frame:
    none (the noisy dimple, the sharp board and the dots included). Pixels on the frame's outer
    row and column are not judged."""
    x = np.asarray(image, np.float32)
    high, low = _ring_max(x), cv2.erode(x, _RING, borderType=cv2.BORDER_REFLECT_101)  # the 8 neighbours' extremes
    margin = np.maximum(high - low, np.float32(contrast_fraction * _contrast(x)))
    found = ((x - high) > margin) | ((low - x) > margin)
    # the outer pixels are left alone: half their neighbours are missing, and a dot or a
    # square's corner cut by the border peaks there like a defect (a 0.5 mm dot did)
    found[[0, -1], :] = False
    found[:, [0, -1]] = False
    return np.flatnonzero(found)


#: :func:`hot_pixels_above` first looks at a frame's pixels brighter than the reference's brightest;
#: where more than this fraction of the frame is (a brighter frame: exposure, lamp), at those beyond
#: its ``level`` alone.
HOT_CANDIDATES_MAX_FRACTION = 0.005
#: Where only a few pixels are brighter than the whole reference, one of them is hot where it lies
#: above all eight neighbours by this fraction of the reference's contrast (not their range as well:
#: a camera's hot pixel at its ceiling beside a square's edge is above the bright side by 12 % of
#: the contrast, and the edge's range is most of it) ...
HOT_EXCESS_FRACTION = 0.1
#: ... and by this many times the most any pixel of the reference's own pattern stands above its
#: neighbours (:func:`hot_pixel_limits`' ``peak_excess``): boards 0.03 of the contrast or less,
#: 0.5 mm random dots 0.29, real FS-SS frames 0.11-0.20 (docs/processing.md section 3): a frame's
#: dot a little brighter than the reference's brightest is the pattern, not a hot pixel.
HOT_EXCESS_OVER_REFERENCE = 1.5


#: A frame whose contrast (1st to 99th percentile) is more than this many times the reference's is on
#: another scale (frames' counts against a float 0..1 reference, 12-bit frames against an 8-bit one):
#: :func:`hot_pixels_above` scales the reference's limits by it.  By-hand trial of 7 Dec 2026: a float 0..1
#: reference against 12-bit frames "repaired" 38 pixels of noise as hot pixels a frame.
HOT_FRAME_SCALE = 3.0


def hot_pixel_limits(reference) -> tuple:
    """``(level, contrast, brightest, peak_excess)`` of :func:`hot_pixels_above` from the
    reference: its contrast (1st to 99th percentile, grey levels), its brightest pixel, the
    level above which a frame's pixel is beyond anything its pattern can show (the brightest
    plus that contrast: a frame twice as bright as the reference over a pattern whose dark
    squares are below half its bright ones stays under it), and the most any of its inner
    pixels stands above all eight neighbours (grey levels: how peaked the pattern itself is)."""
    x = np.asarray(reference, np.float32)
    contrast = _contrast(x)
    excess = (x - _ring_max(x))[1:-1, 1:-1]
    return float(x.max()) + contrast, contrast, float(x.max()), float(max(excess.max(initial=0.0), 0.0))


def hot_pixels_above(image, level: float, contrast: float, brightest: float | None = None,
                     peak_excess: float = 0.0, contrast_fraction: float = DEFECT_CONTRAST_FRACTION):
    """Flat indices (int64, sorted) of a frame's isolated pixels: brighter than ``level`` and
    above the largest of their 8 neighbours by more than the neighbours' range and by more
    than ``contrast_fraction`` of ``contrast`` (the reference's, grey levels,
    :func:`hot_pixel_limits`); or, where at most :data:`HOT_CANDIDATES_MAX_FRACTION` of the
    frame is brighter than ``brightest`` (the reference's brightest pixel), those above all 8
    neighbours by :data:`HOT_EXCESS_FRACTION` of ``contrast`` and
    :data:`HOT_EXCESS_OVER_REFERENCE` times ``peak_excess`` (the reference's own most peaked
    pixel): a cosmic
    ray, or a hot pixel that the reference, taken at another exposure or temperature, does
    not show (:func:`defect_pixels` finds the ones it does). One at 65535 in a 12-bit frame
    took a narrow ray-traced bump from 0.185 to 3.1 % rms height error, 20 to 11.5 % (256^2,
    5 Dec 2026). A camera's own hot pixels stop at its ceiling (4095 for 12 bits), under
    ``level`` where the reference reaches 3693: 0.1 % of the frame's pixels there took
    ``tirdeflect simulate``'s bump from 0.05 to 0.25 %, waves from 0.20 to 0.37 %, none
    repaired until ``brightest`` was looked at (6 Dec 2026). A frame whose brightest pixel is
    under ``brightest`` costs one maximum; pixels on the outer row and column are not judged."""
    a = np.asarray(image)
    if a.size == 0:
        return np.empty(0, np.int64)
    row_top = a.max(axis=1)
    first = level if brightest is None else min(level, brightest)
    if float(row_top.max()) <= first:
        return np.empty(0, np.int64)
    scale = _contrast(a) / contrast if float(row_top.max()) > level and contrast > 0 else 1.0
    if scale > HOT_FRAME_SCALE:  # the limits on the frame's scale (counts against a float 0..1 reference...)
        level, contrast, peak_excess = level * scale, contrast * scale, peak_excess * scale
        first = level if brightest is None else min(level, brightest * scale)
        if float(row_top.max()) <= first:
            return np.empty(0, np.int64)
    r, c = _above(a, row_top, first)
    few = first < level  # a few pixels brighter than the whole reference: the looser test
    if r.size > HOT_CANDIDATES_MAX_FRACTION * a.size and few:
        r, c = _above(a, row_top, level)
        few = False
    rows, cols = a.shape
    inner = (r > 0) & (r < rows - 1) & (c > 0) & (c < cols - 1)
    r, c = r[inner], c[inner]
    near = _neighbours(a, r, c).astype(np.float32)
    high, low = near.max(axis=0, initial=-np.inf), near.min(axis=0, initial=np.inf)
    if few:  # above every neighbour by a tenth of the contrast, edges beside it or not
        margin = np.float32(max(HOT_EXCESS_FRACTION * contrast, HOT_EXCESS_OVER_REFERENCE * peak_excess))
    else:
        margin = np.maximum(high - low, np.float32(contrast_fraction * contrast))
    hot = (a[r, c].astype(np.float32) - high) > margin
    return np.sort(np.ravel_multi_index((r[hot], c[hot]), a.shape))


def _above(a, row_top, level):
    """``(rows, cols)`` of the pixels of ``a`` above ``level``, searched in the rows whose
    maximum ``row_top`` is (a tenth of a full pass where those are a few)."""
    rows = np.flatnonzero(row_top > level)
    r, c = np.nonzero(a[rows] > level)
    return rows[r], c


def repair_pixels(image, defects):
    """``image`` with the pixels ``defects`` (flat indices, :func:`defect_pixels` of the
    reference: a sensor's defects are in every frame) replaced by the median of their 8
    neighbours (a copy; ``image`` itself when there are none)."""
    if len(defects) == 0:
        return image
    a = np.array(image, copy=True)
    r, c = np.unravel_index(np.asarray(defects), a.shape)
    median = np.median(_neighbours(a, r, c), axis=0)
    a[r, c] = (np.rint(median) if a.dtype.kind in "ui" else median).astype(a.dtype)
    return a


def dilate_invalid(invalid, n):
    """``invalid`` grown by ``n`` samples (a (2n+1)^2 square; n <= 0: unchanged)."""
    if n <= 0:
        return invalid
    k = np.ones((2 * n + 1, 2 * n + 1), np.uint8)
    return cv2.dilate(invalid.astype(np.uint8), k).astype(bool)


def fold_ok(u, rows_px, cols_px, min_fold, finite=False):
    """det(I - grad u) > min_fold on the decimated grid (u in pixels);
    None when it holds everywhere."""
    from .mask_kernels import fold_determinant, largest_steps

    dr = rows_px[1] - rows_px[0]
    dc = cols_px[1] - cols_px[0]
    uf = np.asarray(u if finite else np.nan_to_num(u))
    if uf.dtype not in (np.float32, np.float64):
        uf = uf.astype(np.float64)
    # |every partial derivative| <= t (central and one-sided differences
    # are bounded by the largest neighbour difference) gives
    # det >= (1 - t)^2 - t^2 = 1 - 2 t: no fold test needed below this
    step_r, step_c = largest_steps(uf)
    t = max(float(step_r) / dr, float(step_c) / dc)
    if 1.0 - 2.0 * t > min_fold + 1e-6:
        return None
    det = np.empty(uf.shape[1:], uf.dtype)
    fold_determinant(uf, float(dr), float(dc), uf.dtype.type(1.0), det)  # np.gradient's det(I - grad u)
    return det > min_fold


def drop_islands(valid, ref_mask, min_island):
    """Remove valid regions smaller than ``min_island`` (fraction of the grid)
    that do not reach the reference region ``ref_mask``."""
    if min_island <= 0:
        return valid
    if valid.all():
        return valid  # one region
    labels, n = connected_regions(valid)
    if n <= 1:
        return valid
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    touches = np.zeros(n + 1, bool)
    touches[np.unique(labels[ref_mask & valid])] = True
    keep = (sizes >= min_island * valid.size) | touches
    keep[0] = False
    return keep[labels]


def reference_contrast_ok(demod, shape):
    """Where the reference shows the pattern on the decimated grid: its
    contrast, border taper divided out, at least :data:`REF_CONTRAST_FRACTION`
    of the 90th percentile (blank, dirty or blurred parts of the pattern are not)."""
    w = demod.plan.window2d
    if w is None:
        taper = np.ones(demod.window_shape, np.float32)
    else:
        rows, cols = shape
        taper = w[np.ix_(np.round(demod.rows_px).astype(int) % rows, np.round(demod.cols_px).astype(int) % cols)]
    g0_min = demod.g0_abs.min(axis=0) / np.maximum(taper, 1e-6)
    inside = taper >= 0.02
    # the best contrast from where the taper is at least half: divided by a taper of 0.03 the outermost ring
    # reads ~7x its contrast, and on a 64^2 frame (35^2 grid) that ring is 11 % of the samples, so its
    # value was the 90th percentile and every sample inside it failed (by-hand trial of 7 Dec 2026)
    core = inside & (taper >= 0.5)
    core = core if core.any() else inside
    best = np.percentile(g0_min[core], REF_CONTRAST_PERCENTILE) if core.any() else 0.0
    return (g0_min >= REF_CONTRAST_FRACTION * best) & inside


def reference_pin_region(reference_valid, rows_px, cols_px, frame_shape, *, skip: int = 0) -> np.ndarray:
    """The default reference region: the border band of where the reference is valid.

    Parameters
    ----------
    reference_valid : ndarray bool (n_rows, n_cols)
        Samples of the grid where the reference shows the pattern.
    rows_px, cols_px : ndarray
        Pixel rows and columns of the grid (evenly spaced).
    frame_shape : (int, int)
    skip : int
        Samples next to an invalid part of the reference that every frame
        loses anyway (the Reconstructor's mask dilation): the band starts
        inside them.

    Returns
    -------
    ndarray bool (n_rows, n_cols)
        The frame's border band (:func:`processing.geometry.default_reference_region_mask`,
        ``ceil(0.04 min(n_rows, n_cols))`` px wide) where the reference is
        valid, plus a band as wide along the inner edge of the valid area
        (after ``skip`` samples): the outermost valid ground, where a
        deformation in the middle of the view has died out.  Holes in the
        valid area (invalid parts enclosed by valid ones) get no band.  Where
        the reference is valid everywhere (but for holes) this is the frame's
        border band.
    """
    valid = np.asarray(reference_valid, bool)
    band = default_reference_region_mask(rows_px, cols_px, frame_shape)
    if valid.all() or not valid.any():
        return band & valid
    from scipy import ndimage

    # only the outer edge: a hole in the valid area (a dirty spot of the
    # pattern) lies in the middle of the view, where the surface may move
    outer = ndimage.binary_fill_holes(valid)
    if outer.all():
        return band & valid
    spacing = 0.5 * (float(rows_px[1] - rows_px[0]) + float(cols_px[1] - cols_px[0]))
    width_px = max(1, math.ceil(DEFAULT_REFERENCE_BAND * min(frame_shape)))
    width = max(2, math.ceil(width_px / spacing))
    # chessboard distance (samples) to the nearest invalid sample, as the dilation counts
    dist = ndimage.distance_transform_cdt(outer, metric="chessboard")
    return valid & (band | ((dist > skip) & (dist <= skip + width)))


class ReferenceRegion(NamedTuple):
    """Where the height offset is pinned, chosen once for a series (:func:`choose_reference_region`)."""

    #: bool (n_rows, n_cols): the region on the grid.
    region: np.ndarray
    #: How ``Result.pin`` names it.
    name: str
    #: Fraction of the candidate (the user's box or the border band) where the reference is valid.
    valid_fraction: float
    #: The user's box when none of it shows the pattern ("nearest" measures from it), else None.
    near: Optional[np.ndarray]


def choose_reference_region(geometry, reference_valid, rows_px, cols_px, shape, *, skip: int) -> ReferenceRegion:
    """The reference region on a grid: ``geometry.reference_region`` where the
    reference is valid, or by default :func:`reference_pin_region`."""
    near = None
    if geometry.reference_region is None:
        candidate = default_reference_region_mask(rows_px, cols_px, shape)
        region = reference_pin_region(reference_valid, rows_px, cols_px, shape, skip=skip)
        if reference_valid.all():
            name = "default border band of the frame"
        else:
            name = "default border band of the reference's valid area"
    else:
        candidate = geometry.reference_mask(rows_px, cols_px, shape)
        region = candidate & reference_valid
        name = f"{USER_REGION_PREFIX} {list(geometry.reference_region)}"
        if not region.any():
            near = candidate  # the fallback measures "nearest" from the box
    fraction = (float(np.count_nonzero(candidate & reference_valid)) / max(1, int(np.count_nonzero(candidate))))
    return ReferenceRegion(region, name, fraction, near)
