"""Specks in a frame that its reference lacks: dust or bubbles on the water, a drop on the window.

Image matching (:func:`processing.dic.refine_height`) explains every difference between the frame
and the warped reference by a displacement.  A speck the reference does not have (a particle
floating on the surface frustrates the reflection: a dark spot of a few pixels) is no displacement,
and matching it bent the heights around it: 40 specks of 1-3 px radius, 40-90 % darker, on the
accuracy table's 256^2 ray-traced frames (2 x 2 rays) put its ten cases 0.27-5.75 % off instead of
0.03-0.74 %, every sample valid, no word said.

What tells a speck from a displacement: over a carrier period a checkerboard has the same mean
intensity wherever the surface moves it, so the residual of a misplaced pattern averages out over a
period and a speck's does not.  :func:`local_change` averages the residual over the node cells and a
Gaussian of half the shorter carrier period, over the warped reference's local mean.  Against FD's
start that holds where the start is near; beside a strong feature it is not (simulate's bump at
128^2, FD 1.2 % off: a 4.5 % change at its centre, 0.6 % after one Gauss-Newton step), and after a
step the specks are partly matched away.  So :func:`speck_pixels` takes the cells that changed by
more than :data:`SPECK_CONTRAST` against the start and keep that sign after the first step, and in
them the pixels whose residual against the start exceeds :data:`SPECK_CORE` of the local mean; image
matching then starts again from FD's start without them (:data:`SPECK_STEP`).

Measured (the ten cases with 40 specks, each as before without): 2 um bump 2.26 -> 0.61 %, narrow
bump 3.34 -> 0.97 %, 12-30 mm waves 1.21 -> 0.47 %, deep dimple 0.27 -> 0.08 %, 6-12 mm waves 4.03 ->
1.37 %, 1.5-period bump 5.75 -> 1.61 % (all ten 0.08-1.61 %); without specks nothing is found on any
of them, nor on simulate's frames, a cos^4 or Gaussian vignette (corners at 5 %) or the golden masked
frame: the same heights to the bit.  Not covered: FD and the live grid (they keep the specks' bias),
random dots (not looked for), dust dense enough that the start's median residual passes
:data:`START_RESIDUAL_MAX`.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["SPECK_CONTRAST", "SPECK_CORE", "SPECK_STEP", "CONFIRM", "MAX_SPECK_SHARE", "MIN_SPECK_SHARE",
           "START_RESIDUAL_MAX", "local_change", "speck_pixels", "specks_to_leave_out", "speck_note"]

#: Local change of the mean intensity against the start (a fraction of the warped reference's local
#: mean, :func:`local_change`) that marks a node cell as a speck's: without specks 0.2-2.3 % inside
#: the accuracy table's frames at the start (its waves furthest off); at 40 specks' darker cores the
#: median 6-9 %.
SPECK_CONTRAST = 0.02

#: A speck's pixels: where the local mean marks one, those whose own residual has the change's sign
#: and exceeds this share of the local mean.
SPECK_CORE = 0.2

#: Largest share of the frame's pixels left out as specks (40 specks of 1-3 px on a 256^2 frame
#: are 1 %).  Beyond it the frame's light differs from the reference's in patches too many to be
#: specks (another board, light from elsewhere): image matching keeps every pixel.
MAX_SPECK_SHARE = 0.1

#: Smallest share of the frame's pixels acted on: a few stray pixels are no speck that moves the
#: heights (found against the start alone, the golden frame with ray crossings had 1 of 16,384).
MIN_SPECK_SHARE = 5e-4

#: The start's median residual (a fraction of the warped reference's median) beyond which no speck is
#: looked for: where FD's start is that far off, a misplaced pattern no longer averages out over a period.
#: Measured (256^2, the accuracy table's ten cases): 0.0002-0.011 without specks, 0.008-0.019 with 40;
#: simulate's 0.5 um waves at 128^2 (FD 6-31 % off) 0.055-0.070, where looking made 6 of 12 frames worse
#: (10.9 -> 30.9 % at worst).
START_RESIDUAL_MAX = 0.03

#: The share of ``contrast`` that the local change must keep, with its sign, after the first step
#: (0: the sign alone; 0.25 left more specks in: the 2 um bump 0.68 against 0.61 %).
CONFIRM = 0.0


def local_change(frame_cells, warped, weight_cells, grid, period_px: float):
    """The local mean of the residual ``frame - warped`` over the warped reference's, on the node cells
    (a Gaussian of half the shorter carrier period; 0 where not judged: under 90 % of the pixels around
    count, or within a period of a cell with a pixel that does not count inside the frame, beside which
    FD's start is off), and the warped reference's local mean.  ``frame_cells``, ``weight_cells``: the
    frame's and the weights' cell means (``grid.down``); ``warped`` (rows, cols)."""
    warped_cells = grid.down(warped)
    residual = frame_cells - warped_cells
    sigma = 0.5 * float(period_px) / grid.s  # node cells
    mean_residual, level, counted = [cv2.GaussianBlur(x, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
                                     for x in (residual, warped_cells, weight_cells)]
    judged = (counted > 0.9) & (level > 1e-3 * max(float(level.max()), 1e-30))
    masked = weight_cells < 0.999  # cells with a pixel that does not count
    masked[:1], masked[-1:], masked[:, :1], masked[:, -1:] = False, False, False, False  # the frame's edge
    reach = int(np.ceil(float(period_px) / grid.s)) + 1
    judged &= cv2.dilate(masked.astype(np.uint8), np.ones((2 * reach + 1, 2 * reach + 1), np.uint8)) == 0
    change = np.zeros_like(mean_residual)
    np.divide(mean_residual, level, out=change, where=judged)
    return change, level


def speck_pixels(frame, start_warped, after_warped, weight, grid, period_px: float,
                 contrast: float = SPECK_CONTRAST, core: float = SPECK_CORE):
    """Pixels of specks the reference lacks: cells whose local mean differs from the warped reference's
    by more than ``contrast`` against the start, with the same sign after a Gauss-Newton step (a start
    misplaced beside a strong feature changes it there too, but no longer after the step: simulate's bump
    at 128^2, 4.5 % -> 0.6 % at its centre), and in them the pixels whose own residual against the start
    has that sign and exceeds ``core`` of the local mean.

    Parameters
    ----------
    frame : ndarray float32 (rows, cols)
        The frame brought to the reference's intensities (blurred): :func:`processing.dic.refine_height`'s.
    start_warped, after_warped : ndarray float32 (rows, cols)
        The reference warped by the start and after the first step (blurred alike).
    weight : ndarray float32 (rows, cols)
        Pixels that count (0: masked, beyond the border).
    grid : processing.dic_nodes.NodeGrid
        The node cells (``grid.s`` px a side; the frame's sides their multiples).
    period_px : float
        The pattern's shorter carrier period (pixels).
    contrast, core : float
        Fractions of the local mean (:data:`SPECK_CONTRAST`, :data:`SPECK_CORE`).

    Returns
    -------
    ndarray bool (rows, cols)
        True on the pixels of specks.
    """
    found = np.zeros(np.shape(frame), bool)
    every = np.s_[::8, ::8]  # the medians of every 8th pixel's: as good, 64 x fewer
    if (np.median(np.abs(frame[every] - start_warped[every]))
            > START_RESIDUAL_MAX * np.median(np.abs(start_warped[every]))):
        return found  # the start is too far off to tell a speck from a misplaced pattern
    frame_cells, weight_cells = grid.down(frame), grid.down(weight)
    before = local_change(frame_cells, start_warped, weight_cells, grid, period_px)
    if not (np.abs(before[0]) > contrast).any():
        return found
    now = local_change(frame_cells, after_warped, weight_cells, grid, period_px)
    sign = np.sign(before[0]) * (np.abs(before[0]) > contrast)
    rows, cols = np.nonzero(sign * now[0] > CONFIRM * contrast)
    if not len(rows):
        return found
    # the candidate cells' pixels alone: (cells, s, s) blocks of the frame's (n_rows, s, n_cols, s) view
    s = grid.s
    n_r, n_c = frame_cells.shape
    blocks = [np.asarray(x).reshape(n_r, s, n_c, s)[rows, :, cols, :] for x in (frame, start_warped, weight)]
    bound = (core * before[1][rows, cols])[:, None, None]
    sign = sign[rows, cols][:, None, None]
    found.reshape(n_r, s, n_c, s)[rows, :, cols, :] = (blocks[2] > 0) & (sign * (blocks[0] - blocks[1]) > bound)
    return found


#: The Gauss-Newton step before which specks are looked for: after FD's start has been matched once
#: (against the start itself, a misplaced pattern beside strong features looked like specks: simulate's
#: bump at 128^2, FD 1.2 % off, changed the local mean at its centre by 4.5 % at the start, 0.6 % after
#: one step).  Where specks are found, the match starts again from FD's start without them.
SPECK_STEP = 1


def specks_to_leave_out(frame, start_warped, after_warped, weight, grid, period_px: float,
                        contrast: float = SPECK_CONTRAST):
    """``(pixels, share of the frame)`` of :func:`speck_pixels` where the share lies within
    :data:`MIN_SPECK_SHARE` .. :data:`MAX_SPECK_SHARE`, else None."""
    found = speck_pixels(frame, start_warped, after_warped, weight, grid, period_px, contrast)
    share = float(np.count_nonzero(found)) / found.size
    return (found, share) if MIN_SPECK_SHARE <= share <= MAX_SPECK_SHARE else None


def speck_note(share: float) -> str:
    """What a frame's Result.note says of the specks image matching left out (``share`` of the frame's
    pixels); "" for none."""
    if share < MIN_SPECK_SHARE:
        return ""
    return (f"specks the reference lacks (dust or bubbles on the water?) on {100 * share:.1f} % of the frame: "
            f"left out of image matching (heights there follow their surroundings)")
