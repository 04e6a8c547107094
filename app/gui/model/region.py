"""The reference region (where the height offset is pinned) is edited inside the frame, or refused.

A box dragged partly off the frame is clamped back onto it at the edit (:func:`clamp_region`); one
typed outside it is refused with the reason (:func:`region_problem`), so that the reference in use
is never thrown away by an edit.
"""

from __future__ import annotations

from typing import Optional, Tuple

__all__ = ["MIN_REGION_PX", "clamp_region", "region_problem", "roi_of", "reference_crop", "region_after_roi_change",
           "profile_line_for"]

#: Smallest side of a reference region (px): a region that small is the user's choice (the pin then
#: says how many of its samples were valid), but an empty one is none.
MIN_REGION_PX = 4

Region = Tuple[int, int, int, int]


def clamp_region(region, shape) -> Tuple[Region, bool]:
    """``(row0, row1, col0, col1)`` moved and cut to lie in a frame of ``shape`` (rows, cols), at least
    :data:`MIN_REGION_PX` (or the frame) on a side; and whether anything changed."""
    r0, r1, c0, c1 = (int(round(v)) for v in region)
    rows, cols = int(shape[0]), int(shape[1])

    def fit(lo, hi, n):
        size = min(max(hi - lo, MIN_REGION_PX), n)
        lo = min(max(lo, 0), n - size)
        hi = min(max(hi, lo + size), n)
        return lo, hi

    r0n, r1n = fit(r0, r1, rows)
    c0n, c1n = fit(c0, c1, cols)
    out = (r0n, r1n, c0n, c1n)
    return out, out != (r0, r1, c0, c1)


def region_problem(region, shape) -> Optional[str]:
    """Why ``region`` cannot be the reference region in a frame of ``shape``; None when it can."""
    if region is None or shape is None:
        return None
    r0, r1, c0, c1 = (int(v) for v in region)
    rows, cols = int(shape[0]), int(shape[1])
    if r0 < 0 or c0 < 0 or r1 > rows or c1 > cols:
        return (f"reference region rows {r0}-{r1}, columns {c0}-{c1} lies outside the {cols}×{rows} px frame: "
                f"give rows within 0-{rows} and columns within 0-{cols}; the region in use is kept")
    if r1 - r0 < MIN_REGION_PX or c1 - c0 < MIN_REGION_PX:
        return (f"reference region {r1 - r0}×{c1 - c0} px is smaller than {MIN_REGION_PX} px on a side: "
                "make it larger; the region in use is kept")
    return None


def roi_of(settings) -> Optional[Tuple[int, int, int, int]]:
    """``(offset_x, offset_y, width, height)`` of camera settings (None: unknown)."""
    if settings is None:
        return None
    roi = tuple(getattr(settings, k, None) for k in ("offset_x", "offset_y", "width", "height"))
    return None if any(v is None for v in roi) else tuple(int(v) for v in roi)


def reference_crop(reference_roi, new_roi):
    """Where frames of ``new_roi`` lie in a reference taken with ``reference_roi`` (both
    ``(offset_x, offset_y, width, height)`` on the sensor): ``(row slice, col slice)``, or None when the
    new ROI is not inside the reference's (a new reference is needed)."""
    if reference_roi is None or new_roi is None:
        return None
    rx, ry, rw, rh = reference_roi
    nx, ny, nw, nh = new_roi
    if nx < rx or ny < ry or nx + nw > rx + rw or ny + nh > ry + rh:
        return None
    return slice(ny - ry, ny - ry + nh), slice(nx - rx, nx - rx + nw)


def region_after_roi_change(region, old_roi, new_roi) -> Tuple[Optional[Region], str]:
    """The reference region ``(row0, row1, col0, col1)``, in pixels of frames of ``old_roi``, at the same
    place on the water in pixels of frames of ``new_roi`` (both ``(offset_x, offset_y, width, height)`` on
    the sensor); and a note for the user ("" when it lies whole in the new frame).

    Part of it outside the new frame is cut off; when less than :data:`MIN_REGION_PX` of it is left on a
    side, None (the reconstructor's default region) with a note that says so: keeping its numbers would
    pin the heights at another place on the water, in silence.
    """
    if region is None or old_roi is None or new_roi is None:
        return (None if region is None else tuple(int(v) for v in region)), ""
    dx, dy = int(new_roi[0]) - int(old_roi[0]), int(new_roi[1]) - int(old_roi[1])
    rows, cols = int(new_roi[3]), int(new_roi[2])
    r0, r1, c0, c1 = (int(v) for v in region)
    moved = (r0 - dy, r1 - dy, c0 - dx, c1 - dx)
    cut = (max(moved[0], 0), min(moved[1], rows), max(moved[2], 0), min(moved[3], cols))
    where = f"rows {r0}-{r1}, columns {c0}-{c1}"
    if cut[1] - cut[0] < MIN_REGION_PX or cut[3] - cut[2] < MIN_REGION_PX:
        return None, (f"the reference region ({where}) lies outside the new ROI: the default region is used; "
                      "draw or type one in the new frame")
    if cut != moved:
        return cut, (f"the reference region ({where}) was cut to the part inside the new ROI: rows {cut[0]}-{cut[1]}, "
                     f"columns {cut[2]}-{cut[3]}")
    if (dx, dy) != (0, 0):
        return cut, (f"the reference region moved with the ROI to rows {cut[0]}-{cut[1]}, columns {cut[2]}-{cut[3]} "
                     "(the same place on the water)")
    return cut, ""


def profile_line_for(ends, placed_extent, extent, middle_y: Optional[float] = None):
    """Where the profile line goes on maps spanning ``extent`` = (x0, x1, y0, y1) mm: ``None`` to leave it at
    ``ends`` ((x, y), (x, y) mm), else new ends across the middle row.

    ``placed_extent``: the extent it was last checked against (None: never placed). It is placed on the first
    maps, and again when the maps' extent changed (a new ROI) and an end lies outside the new maps: the line of
    the 512-px frame ran far past a 256-px ROI's maps, half its profile empty (by-hand trial 2 Dec 2026). A line
    the user dragged stays where it is otherwise."""
    x0, x1, y0, y1 = (float(v) for v in extent)
    if placed_extent is not None:
        if tuple(placed_extent) == (x0, x1, y0, y1):
            return None
        lo_x, hi_x, lo_y, hi_y = min(x0, x1), max(x0, x1), min(y0, y1), max(y0, y1)
        if all(lo_x <= px <= hi_x and lo_y <= py <= hi_y for px, py in ends):
            return None
    ym = (y0 + y1) / 2 if middle_y is None else float(middle_y)  # the caller: the grid row nearest the middle
    return (x0, ym), (x1, ym)
