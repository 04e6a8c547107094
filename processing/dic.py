"""Image-domain refinement: global Gauss-Newton image matching for the height (DIC).

Fourier demodulation sees the frame through a band around each carrier;
where the surface has features a few carrier periods wide the phase
modulation spills out of that band and FD's displacement comes out smoothed
(docs/processing.md, section 6).  :func:`refine_height` matches images
instead of phases.  Its unknown is the height ``h`` on a grid of nodes every
:data:`NODE_PX` pixels; the displacement follows from it through the exact
linear response of the geometry (:meth:`Geometry.linear_response` at the
nodes: ``u = a h + B grad_px h``, ``I(r) = I0(r - u(r))``), so ``u`` is
physically consistent (curl-free up to the ``a h`` term) with half the
unknowns of a free displacement.  Starting from FD's height it solves

    min_h  sum_r w(r) [G*I (r) - G*(I0(r - u(r)))]^2  +  lam (|D3r h|^2 + |D3c h|^2)

by Gauss-Newton (``w``: FD's valid mask on the pixels; ``G*``: a Gaussian
blur of :data:`BLUR_PX` applied to both images *after* the warp, so the
right ``u`` still matches exactly while the aliased content of sharp-edged
patterns is damped; ``D3``: third differences of the node heights, which
cost a quadratic height nothing and hold the node grid's Nyquist mode that
the centred differences do not see).  The Reconstructor
(``refine_method="image"``) then passes ``u`` at the nodes to its masked
height solver and pin, and interpolates the heights to every pixel.

The frame need not be exposed as the reference: its smooth gain and offset
fields (:func:`intensity_fit`, DIC's ZNSSD normalisation on 16 px cells) are
fitted against the reference warped by FD's start, and the frame is divided
by them before the blur (issue 18: 0.5x brightness 12.7 % -> 0.81 %).  Every
loop is bounded and each step is tested before the warp; a solve leaving the
range where it can be right raises :class:`RefinementDiverged`, and the
Reconstructor keeps FD's heights with a note (:attr:`Result.note`).

The reference is warped by linear interpolation of its cubic-spline
interpolation on a grid 2-3 times finer (:func:`fine_reference`, the factor
by :func:`fine_factor`: within 1e-3 px on the shortest carrier; kept as
16-bit counts, :class:`FineReference`, so the warp reads half the memory):
OpenCV's cubic remap biases image matching towards whole pixels by up to
0.035 px.  The remap's map is written from the node displacement by
:meth:`NodeGrid.warp_map` (OpenCV's Lanczos taps, compiled).

Each step's pixel pass and the conjugate gradients' operator are compiled
(:mod:`processing.dic_kernels`); the five node sums run in bands on the
Reconstructor's ``threads``.

Measured (docs/processing.md, section 6): ray-traced waves 3-6 carrier
periods long 2.90 % (FD) -> 0.82 % rms height error; every case of the
accuracy table at or below FD's.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import cv2
import numpy as np

from .dic_intensity import INTENSITY_CELL_PX, intensity_fit, normalised_frame
from .dic_nodes import BLUR_PX, NODE_PX, FineReference, HeightNodes, NodeGrid, fine_factor, fine_reference, fits
from .fill import nearest_fill_index
from .pools import thread_map
from .specks import SPECK_STEP, specks_to_leave_out

__all__ = ["NODE_PX", "BLUR_PX", "INTENSITY_CELL_PX", "FineReference", "NodeGrid", "HeightNodes", "RefinementDiverged",
           "fine_factor", "fine_reference", "fits", "intensity_fit", "refine_height", "ImageMatch"]


# ------------------------------------------------------------------ the match
#: Pixels along each side of the frame left out of the match: on them the gradient of the blurred
#: warped reference is a one-sided difference of OpenCV's mirror image, not the warp's response (its
#: mirrored half moves the other way), and the Gauss-Newton steps of the border nodes overshot.
#: Measured over four board placements (bench_processing.py --placements 4; 256^2 ray-traced, 4 x 4
#: rays; narrow bump / waves 6-12 mm / waves 12-30 mm, interior): 0 px 0.361 / 0.758 / 0.230 %,
#: 1 px 0.365 / 0.757 / 0.232 %, 2 px 0.360 / 0.763 / 0.230 %, 3 px 0.359 / 0.787 / 0.229 %, 4 px
#: (the blur's reach) 0.360 / 0.760 / 0.228 %; over the whole frame 2 px 0.400 / 1.281 / 0.437 %,
#: 4 px 0.400 / 1.701 / 0.464 % (fewer data for the border's nodes).  What decides is convergence: on
#: the 12-30 mm waves at the fourth placement the rms residual over six steps went 4.00, 1.98, 2.28,
#: 1.53, 1.94, 1.45 grey levels with 0 px (the border's steps from one side of the answer to the
#: other), 2.81, 1.26, 1.11, 1.02, 1.02, 1.00 with 2 px, the steps shrinking 0.090 -> 0.004 px rms.
BORDER_PX = 2


#: Conjugate-gradient iterations of each Gauss-Newton step (:func:`refine_height`): on frames whose
#: pixels all count 3 and 15 give the same heights (docs/processing.md section 6).
CG_ITERATIONS = 3

#: ... and on checkerboards where some do not (a masked patch, ray crossings, FD's mask: the
#: ``masked_cg_iterations`` that :class:`processing.chain_image.ImageRefinement` passes): the DCT
#: preconditioner knows no mask, and 3 iterations left the steps far from solved there. Measured
#: (5 Dec 2026, 256^2, 4 x 4 rays, two board placements, a 40 x 70 px blank patch in the frame;
#: rel. RMS height error %, no refinement / 3 / 6 / 10 / 20 iterations): 4 um bump 0.314 / 0.415 / 0.398 / 0.209 / 0.172, narrow
#: bump 3.016 / 0.884 / 0.772 / 0.618 / 0.602, waves 12-30 mm 0.581 / 1.148 / 0.619 / 0.417 / 0.339,
#: noisy dimple 0.279 / 0.542 / 0.283 / 0.162 / 0.127, deep dimple 0.212 / 0.449 / 0.501 / 0.201 /
#: 0.226, waves 6-12 mm 6.499 / 1.229 / 1.471 / 0.882 / 0.822: with 3, worse than no refinement on
#: four of six; a 10 um spike (sigma 0.8 mm, 6 % masked by its ray crossings) 4.120 / 7.260 / - /
#: 2.489, a 20 um dimple (26 % masked) 4.667 / 2.544 / - / 1.509; a patch of 20 x 30 px as well (the
#: 4 um bump 0.246 / 0.313 / - / 0.158). Not on random dots: started from PIV, their steps come out
#: worse with more iterations, masked or not (four dot seeds, 4 x 4 rays, 3 -> 10 iterations on every
#: frame: narrow bump 1.460 -> 1.871 %, waves 6-12 mm 1.802 -> 3.058 %).
MASKED_CG_ITERATIONS = 10

#: Divergence: the residual (sum of squares) grew by this factor over its smallest so far.
#: Sound steps were seen to raise it by up to 3.3x (camera at 1.5 m, where the heights still
#: improved); a diverging solve raises it by orders of magnitude.
RESIDUAL_RISE = 10.0


class RefinementDiverged(ArithmeticError):
    """:func:`refine_height` stopped: its iterations left the range where they
    can be right (the message says which test and the figures); the caller
    keeps FD's answer for the frame."""


def _dot(a, b) -> float:
    """Dot product of two float32 node arrays in float64, without BLAS threads (they spin on a
    loaded 2-core machine): :func:`processing.dic_kernels.dot64`."""
    from .dic_kernels import dot64

    return float(dot64(a, b))


def _rms(u) -> float:
    """RMS over the nodes of the displacement (or step) ``u`` (2, m_r, m_c), pixels: the
    divergence tests' measure (a few border nodes move by pixels in a sound step)."""
    if not u.size:
        return 0.0
    f = np.ravel(u)
    return math.sqrt(float(np.einsum("i,i->", f, f, dtype=np.float64)) / max(1, u[0].size))


def _diverged(test: str, figures: str):
    return RefinementDiverged(f"{test} ({figures})")


def refine_height(fine, frame, h0, valid_px, nodes: HeightNodes, *, speck_contrast: float | None = None,
                  **options) -> "ImageMatch":
    """Global Gauss-Newton image matching for the height on the node grid of ``nodes``.

    Minimises ``sum_r w [G*((I - b) / a) - G*I0(r - P L h)]^2 + lam (|D3r h|^2 + |D3c h|^2)``
    (module docstring; docs/processing.md section 6 for the settings measured):
    ``outer`` steps, each solving the normal equations by ``cg_iterations`` preconditioned CG
    iterations (:class:`_NormalOperator`; ``masked_cg_iterations``, if given, where ``valid_px``
    leaves pixels out); ``lam`` is ``regularisation`` times the data term's weight per node at unit
    spatial frequency.  Every loop is bounded; the iterations stop with :class:`RefinementDiverged`
    (the caller keeps FD's answer; the message names the test and its figures) when they leave the
    range where they can be right (:func:`_check_displacement`, :func:`_check_cost`, :func:`_check_step`).

    Parameters
    ----------
    fine : FineReference
        :func:`fine_reference` of the reference (any factor).
    frame : ndarray (rows, cols)
    h0 : ndarray (n_rows, n_cols)
        Starting heights at the nodes (mm; FD's; NaN: the nearest finite node's).
    valid_px : ndarray bool (rows, cols)
        Pixels whose residual counts.
    nodes : HeightNodes
    intensity_cell_px : float or None
        Cell of the gain and offset fields (:func:`intensity_fit`); None: gain 1, offset 0.
    period_px : float or None
        The pattern's shorter carrier period, px (None: no bound).
    threads : int
        Threads for each step's node sums (the result does not depend on it).
    border_px : int or (int, int, int, int)
        Pixels along each side left out of the match (:data:`BORDER_PX`), or along the top, bottom, left, right.
    matrix_once, matrix_once_beside_masks : bool
        Keep the first step's Gauss-Newton matrix for the later steps (right-hand sides their own) where
        every pixel of ``valid_px`` counts, and with the second where some are masked (else each step's own).
    offset_px : ndarray (2, n_rows, n_cols) or None
        Node displacement (px) added to the warp, not solved for (a turn: :mod:`processing.turn`).
    speck_contrast : float or None
        Look for specks the reference lacks before step :data:`processing.specks.SPECK_STEP`
        (:func:`processing.specks.speck_pixels` with this contrast) and, where there are, match again
        from the start without their pixels; None: look for none.

    Returns
    -------
    ImageMatch
        Node heights (mm, null space not pinned: pass the displacement to the height solver); the
        displacement at the nodes (px, ``offset_px`` not included); the nodes whose cell is all
        valid (specks aside); the share of the frame's pixels left out as specks.
    """
    try:
        return _refine(fine, frame, h0, valid_px, nodes, speck_contrast=speck_contrast, **options)
    except _SpecksFound as specks:
        again = _refine(fine, frame, h0, np.logical_and(valid_px, ~specks.pixels), nodes, **options)
        # the nodes beside them stay free: their displacement follows the pixels left and the regulariser
        return again._replace(free=specks.free, speck_share=specks.share)


class _SpecksFound(Exception):
    def __init__(self, found, free):
        super().__init__("specks found")
        (self.pixels, self.share), self.free = found, free


def _refine(fine, frame, h0, valid_px, nodes: HeightNodes, *, outer: int = 3, cg_iterations: int = CG_ITERATIONS,
            masked_cg_iterations: int | None = None, regularisation: float = 0.03, blur_px: float = BLUR_PX,
            intensity_cell_px: float | None = INTENSITY_CELL_PX, period_px: float | None = None, threads: int = 1,
            border_px=BORDER_PX, matrix_once: bool = False, matrix_once_beside_masks: bool = False,
            offset_px=None, speck_contrast: float | None = None):
    """:func:`refine_height`'s Gauss-Newton steps (its parameters); :class:`_SpecksFound` where specks are
    found before step :data:`SPECK_STEP`."""
    grid = nodes.grid
    raw, img, w, all_valid, free = _frame_and_weights(frame, valid_px, grid, blur_px, border_px)
    n_cg = masked_cg_iterations if masked_cg_iterations and not all_valid else cg_iterations
    h = _start_heights(h0)
    u = u_start = nodes.displacement(h) if offset_px is None else nodes.displacement(h) + offset_px
    prev_step = prev_cost = operator = None
    w_sum, wk_buf = float(w.sum()), np.empty_like(w)
    for k in range(outer + 1):
        _check_displacement(u, u_start, k, grid.frame_shape, period_px, free)  # before any warp
        if k == outer:
            break
        warped, outside = _warp(fine, grid, u, blur_px, threads)
        wk = _weights_within(w, outside, wk_buf)
        if intensity_cell_px and k == 0:
            # once, against the reference warped by FD's start (before every step: the same
            # heights, 10-20 % slower; weighted by wk at the border: the same, 3 ms more)
            img = normalised_frame(raw, img, warped, None if all_valid else wk, intensity_cell_px, blur_px)
        if k == 0 and speck_contrast:
            start_warped = warped
        if k == SPECK_STEP and speck_contrast and period_px:
            found = specks_to_leave_out(img, start_warped, warped, wk, grid, period_px, speck_contrast)
            if found is not None:  # matched again from the start without them (the first step bent to them)
                raise _SpecksFound(found, free)
        cost, stencils, rhs = _node_sums(nodes, warped, img, wk, threads, matrix=operator is None)
        # per pixel that counts (how many do moves with the warp at the border)
        prev_cost = _check_cost(cost, float(wk.sum()) if outside else w_sum, prev_cost, k, w.size)
        step_operator = operator or _NormalOperator(nodes, stencils, regularisation, k)
        # kept only where every pixel counts: beside a masked hole the first step's matrix led the later
        # steps astray (processing.chain_image.MATRIX_ONCE)
        operator = step_operator if matrix_once and (all_valid or matrix_once_beside_masks) else None
        x = step_operator.solve(rhs, h, n_cg)
        du = nodes.displacement(x)
        prev_step = _check_step(_rms(du), prev_step, k)
        h += x
        u = u + du  # the displacement is linear in the heights: one operator call a step, not two
    return ImageMatch(h, (u if offset_px is None else u - offset_px).astype(np.float32), free, 0.0)


class ImageMatch(NamedTuple):  # refine_height's answer
    height_mm: np.ndarray
    displacement_px: np.ndarray
    free: np.ndarray
    speck_share: float


def _frame_and_weights(frame, valid_px, grid, blur_px, border_px):
    """``(raw, blurred frame, pixel weights, all valid, free nodes)`` of :func:`refine_height`
    (the weights 0 on the outer ``border_px`` pixels of each side, or of the top, bottom, left, right;
    ``all valid``: every pixel of ``valid_px`` is)."""
    raw = img = np.asarray(frame, np.float32)
    if blur_px:
        img = cv2.GaussianBlur(img, (0, 0), blur_px)
    w = np.array(valid_px, np.float32)  # a copy: its border is written below
    all_valid = bool(w.all())
    free = grid.down(w) > 0.999
    if not all_valid and blur_px:
        # the blur mixes what lies within about 2.5 sigma into a pixel: only
        # pixels whose blurred frame and warped reference see valid pixels alone count
        reach = int(math.ceil(2.5 * blur_px))
        w = cv2.erode(w, np.ones((2 * reach + 1, 2 * reach + 1), np.uint8), borderType=cv2.BORDER_REPLICATE)
    top, bottom, left, right = (int(b) for b in np.broadcast_to(border_px, 4))
    w[:top], w[w.shape[0] - bottom:], w[:, :left], w[:, w.shape[1] - right:] = 0.0, 0.0, 0.0, 0.0
    return raw, img, w, all_valid, free


def _warp(fine, grid, u, blur_px, threads=1):
    """``(warped, outside)``: the fine reference warped by the node displacement
    ``u`` (Lanczos to the pixels, :meth:`NodeGrid.warp_map`), blurred as the frame,
    and :func:`_outside` of the warp (empty: every pixel is the reference's own)."""
    factor = fine.factor
    fine_map = grid.warp_map(u, factor, threads)
    # Lanczos overshoots the node values by a few per cent: one pixel more than the largest
    band_px = int(math.ceil(1.1 * float(np.abs(u).max()))) + 1 if u.size else 1
    outside = _outside(fine_map, fine.shape, band_px, factor)
    warped = cv2.remap(fine.counts, fine_map, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT).astype(np.float32)
    if blur_px:
        warped = cv2.GaussianBlur(warped, (0, 0), blur_px)
    return fine.grey(warped), outside


def _outside(fine_map, fine_shape, band_px, ramp):
    """``[(slice, weight), ...]``: where the warp (``fine_map``, :func:`_warp`'s map
    into the fine reference of ``fine_shape``) reaches beyond the reference's
    border, within the strip ``slice`` of the frame, each pixel's ``weight``
    (float32): 1 inside, falling linearly to 0 at ``ramp`` fine samples (one
    pixel) beyond the border, 0 further out; empty where no pixel reaches
    beyond.  Only the outer ``band_px`` pixels of each side can (``band_px``:
    more than the largest displacement).

    Beyond its border the warped reference is the mirror image OpenCV makes,
    not the pattern the frame shows there, and matching it pulled the border
    nodes by pixels a step: on ray-traced 12-30 mm waves (256^2, FD's start 2-5
    px at the upper border) steps of 4-10 px at the first node row, an rms
    residual of 10 grey levels that did not fall, and heights 0.14-0.69 % off
    over four board placements where no refinement gave 0.23-0.51 %
    (docs/processing.md, section 6).  The pixels within the blur's reach of
    those are not left out as well: measured, that cost as much as it gained.
    The ramp keeps the weights, and with them the heights, a continuous
    function of the displacement: a pixel simply in or out is a jump that the
    last bits of an FFT plan could flip.
    """
    rows, cols = fine_map.shape[:2]
    b_r, b_c = min(band_px, rows), min(band_px, cols)
    # each side tests its own coordinate (channel 0: column, 1: row); a corner pixel is in two strips
    sides = ((np.s_[:b_r, :], 1, None), (np.s_[rows - b_r:, :], 1, fine_shape[0] - 1),
             (np.s_[:, :b_c], 0, None), (np.s_[:, cols - b_c:], 0, fine_shape[1] - 1))
    outside = []
    for sl, channel, top in sides:
        at = fine_map[sl + (channel,)]
        beyond = -at if top is None else at - np.float32(top)
        if (beyond > 0).any():
            outside.append((sl, np.clip(1.0 - beyond / np.float32(ramp), 0.0, 1.0).astype(np.float32)))
    return outside


def _weights_within(w, outside, out):
    """``w`` times the weights of :func:`_outside`'s list, into ``out`` (``w`` itself
    when the list is empty)."""
    if not outside:
        return w
    np.copyto(out, w)
    for sl, weight in outside:
        out[sl] *= weight
    return out


def _check_cost(cost, counted, prev_cost, k, n_px):
    """The lowest image residual so far, per pixel that counts (``counted`` of the ``n_px`` pixels'
    weight) in units of ``n_px`` pixels; RefinementDiverged when none counts, or it is not finite or rose."""
    if not counted > 0.0:
        raise _diverged("no pixel left to match", f"the warp samples the reference nowhere after {k} step(s)")
    cost = cost * n_px / counted
    if not math.isfinite(cost):
        raise _diverged("non-finite image residual", f"after {k} step(s)")
    if prev_cost is not None and cost > RESIDUAL_RISE * prev_cost:
        raise _diverged("image residual rose after a step",
                        f"rms {math.sqrt(prev_cost / n_px):.3g} -> {math.sqrt(cost / n_px):.3g} "
                        f"after step {k}")
    return cost if prev_cost is None else min(cost, prev_cost)


def _check_step(step, prev_step, k):
    """``step`` (rms px of a Gauss-Newton step); RefinementDiverged when it is not finite or grows."""
    if not math.isfinite(step):
        raise _diverged("non-finite Gauss-Newton step", f"step {k + 1}")
    if prev_step is not None and step > 2.0 * prev_step and step > 0.05:
        raise _diverged("Gauss-Newton steps grow",
                        f"{prev_step:.3g} -> {step:.3g} px rms at step {k + 1}")
    return step


def _start_heights(h0):
    """``h0`` as float64, nodes without a start given the nearest valid node's
    height (no jump at the mask's edge)."""
    h = np.asarray(h0, np.float64).copy()
    finite = np.isfinite(h)
    if not finite.any():
        raise _diverged("no finite starting height", "every node is NaN or infinite")
    fill = nearest_fill_index(finite)
    return h if fill is None else h[fill[0], fill[1]]


def _check_displacement(u, u_start, k, frame_shape, period_px, free=None):
    """The divergence tests on the node displacement ``u`` after ``k`` steps
    (:func:`refine_height`): finite, within the frame's size anywhere, within
    half the pattern's period of the start (rms over the ``free`` nodes, those
    whose cell is all valid, where there are any).

    Why only those: where the frame shows no pattern (a blank patch, a splash)
    the nodes have no data, only the regulariser, and their displacement is an
    extension of their surroundings' that may lie far from FD's start there (FD
    has nothing there either); counted, it stopped sound solves. Measured
    (``bench_processing.py --masked``'s deep dimple, 15 um, 2 placements, 4 x 4
    rays): one of two placements stopped "5 px rms from FD's" and kept FD's
    heights, 0.199 % mean; counting the free nodes, neither stops: 0.153 %
    (no refinement 0.212 %); the other masked cases unchanged (none stopped).
    On an all-valid frame every node is free: the same test as before."""
    size = float(np.abs(u).max()) if u.size else 0.0
    if free is not None and free.any() and not free.all():
        # the squares summed over the components first, then the free nodes picked from that
        # 2-D map (NumPy's boolean index of the 3-D pair took 2 ms a call at 256^2 nodes)
        d = u - u_start
        sq = np.einsum("kij,kij->ij", d, d, dtype=np.float64)
        move = math.sqrt(float(sq[free].sum()) / int(np.count_nonzero(free)))
    else:
        move = _rms(u - u_start)
    if not (math.isfinite(size) and math.isfinite(move)):
        raise _diverged("non-finite displacement", f"after {k} step(s)")
    if size > max(frame_shape):
        raise _diverged("displacement beyond the frame's size",
                        f"{size:.3g} px after {k} step(s), frame {frame_shape[0]} x {frame_shape[1]} px")
    if period_px is not None and move > 0.5 * float(period_px):
        raise _diverged("displacement moved by more than half the pattern's period",
                        f"{move:.3g} px rms from FD's, period {period_px:.3g} px, after {k} step(s)")


def _node_sums(nodes, warped, img, w, threads, matrix=True):
    """``(weighted residual sum of squares, (Nrr, Nrc, Ncc), (br, bc))`` of one step:
    the gradients ``g`` of ``warped``, the residual ``e = img - warped``, the node
    stencils ``P^T (w g_a g_b) P`` and right-hand sides ``P^T (w g_a e)``.  The
    pixel rows in one compiled pass (:func:`processing.dic_kernels.row_moments`,
    bands of node rows on ``threads``), the columns by :meth:`HeightNodes.column_sums`.
    ``matrix`` False: the right-hand sides alone (the stencils None)."""
    from .dic_kernels import row_moments

    rows, cols = warped.shape
    s, m = nodes.grid.s, nodes.grid.shape[0]
    # bands of about 32 node rows whatever the thread count: the sums do not depend on it
    n_bands = max(1, (m + 1) // 32)
    edges = [-1 + (m + 1) * b // n_bands for b in range(n_bands + 1)]
    k_matrix = 3 if matrix else 0
    xd, xo = (np.zeros((k_matrix, m + 2, cols), np.float32) for _ in range(2))
    xl = np.zeros((2, m + 2, cols), np.float32)
    firsts = np.zeros((n_bands, 8, cols), np.float32)

    def band(b, t0, t1):
        return row_moments(warped, img, w, s, t0, t1, xd, xo, xl, firsts[b], np.empty((5, cols), np.float32), matrix)

    cost = sum(thread_map(band, [(b, edges[b], edges[b + 1]) for b in range(n_bands)], threads))
    for b in range(n_bands):  # each band's first node row, after the previous band's share of it
        r = edges[b] + 1
        if matrix:
            xd[:, r] += firsts[b, 0:3]
            xo[:, r] += firsts[b, 3:6]
        xl[:, r] += firsts[b, 6:8]
    if not matrix:
        return float(cost), None, nodes.column_rhs(xl[:, 1:m + 1])
    sums = nodes.column_sums(xd[:, 1:m + 1], xo[:, 1:m], xl[:, 1:m + 1])
    return float(cost), sums[:3], sums[3:]


class _NormalOperator:
    """The normal equations of one Gauss-Newton step of :func:`refine_height` from
    its node stencils (:func:`_node_sums`): ``(L^T P^T N P L + lam R) dh = -L^T P^T g e
    - lam R h``, solved (:meth:`solve`) by ``cg_iterations`` conjugate-gradient
    iterations (bounded, no tolerance loop), preconditioned by the
    constant-coefficient operator's DCT.  Built once per matrix: with
    ``matrix_once`` the first step's serves every step."""

    def __init__(self, nodes, stencils, regularisation, k):
        from .dic_kernels import pad_stencil

        Bm = nodes.B_mean
        Nrr, Nrc, Ncc = stencils
        nr = Nrr.mean_row_sum()
        nc = Ncc.mean_row_sum()
        lam = regularisation * (nr * Bm[0, 0] ** 2 + nc * Bm[1, 1] ** 2) / nodes.grid.s ** 2
        if not (math.isfinite(lam) and lam > 0):
            raise _diverged("no image gradient to match", f"data weight {lam:.3g} at step {k + 1}")
        sym = (nr * Bm[0, 0] ** 2 + nc * Bm[1, 0] ** 2) * nodes.symbol_d1[0]
        sym = sym + (nr * Bm[0, 1] ** 2 + nc * Bm[1, 1] ** 2) * nodes.symbol_d1[1] + lam * nodes.symbol_reg
        sym[0, 0] = np.inf  # the null space (a near-constant height) is the pin's business
        self.nodes = nodes
        self.sym = sym.astype(np.float32)
        self.lam = np.float32(lam)
        self.A = nodes.dense_response()
        self.stencils = [np.stack(p) for p in zip(*(pad_stencil(S.parts) for S in stencils))]
        shape = nodes.grid.shape
        self.work = np.empty((4,) + shape, np.float32)
        self.vpad = np.zeros((2, shape[0] + 2, shape[1] + 2), np.float32)
        self.inv_s = np.float32(1.0 / nodes.grid.s)

    def apply(self, x):
        """``(L^T M L + lam R) x``, compiled (:func:`processing.dic_kernels.normal_apply`)."""
        from .dic_kernels import normal_apply

        out = np.empty_like(x)
        normal_apply(x, self.A, *self.stencils, self.inv_s, self.lam, self.work, self.vpad, out)
        return out

    def precondition(self, r):
        import scipy.fft as sfft

        c = sfft.dctn(r, type=2, norm="ortho")
        c /= self.sym
        return sfft.idctn(c, type=2, norm="ortho", overwrite_x=True)

    def solve(self, rhs, h, cg_iterations):
        """The step ``dh`` for the right-hand sides ``rhs`` (``(br, bc)`` of
        :func:`_node_sums`) at the node heights ``h``."""
        nodes, lam = self.nodes, self.lam
        r = (-nodes.displacement_T(*rhs) - lam * nodes.regulariser(h)).astype(np.float32)
        x = np.zeros(h.shape, np.float32)
        z = self.precondition(r)
        p = z.copy()
        rz = _dot(r, z)
        r0 = math.sqrt(_dot(r, r))
        for k in range(cg_iterations):
            if r0 == 0.0 or not math.isfinite(rz):
                break
            q = self.apply(p)
            pq = _dot(p, q)
            if not (pq > 0.0 and math.isfinite(pq)):
                break
            al = np.float32(rz / pq)
            x += al * p
            if k == cg_iterations - 1:
                break  # the last step: no next search direction (its preconditioner and dot product unused)
            r -= al * q
            z = self.precondition(r)
            rz_new = _dot(r, z)
            p *= np.float32(rz_new / rz)
            p += z
            rz = rz_new
        return x
