"""The image-domain refinement chain of the full grid (``refine_method="image"``):
FD's heights (checkerboards, :class:`ImageRefinement`) or PIV's (random dots,
:class:`DotsImageRefinement`) on a node grid every ``dic.NODE_PX`` pixels
refined by image matching (:func:`processing.dic.refine_height`), then the
same masked height solver and pin, then every pixel."""

from __future__ import annotations

import dataclasses
import math
import time

import cv2
import numpy as np

from . import dic
from .fill import nearest_fill_index
from .fullgrid import interpolate_full
from .height import solver_for
from .result import Result
from .second_order import SecondOrderOptics, solved_again
from .specks import SPECK_CONTRAST, speck_note

__all__ = ["ImageRefinement", "DotsImageRefinement", "DOTS_BLUR_PX", "DOTS_BORDER_PX", "DOTS_FINE", "MATRIX_ONCE"]


class _NodeRefinement:
    """What both image refinements fix over a chain (checkerboard or dots): the node grid, its
    height operator, and the chain's reference region (and the pin fallback's box) carried to
    the nodes by each node's nearest sample of the chain's grid (``pick``)."""

    def __init__(self, chain):
        self.chain = chain
        ng = self.node_grid = dic.NodeGrid(chain.shape)
        self.height_nodes = dic.HeightNodes(chain.geometry, ng)
        self.pick = (np.abs(ng.rows_px[:, None] - chain.rows_px[None, :]).argmin(axis=1),
                     np.abs(ng.cols_px[:, None] - chain.cols_px[None, :]).argmin(axis=1))
        near = chain.region.near
        self.reference_region = chain.region.region[np.ix_(*self.pick)]
        self.near = None if near is None else near[np.ix_(*self.pick)]
        self._second_order = None  # SecondOrderOptics of the node grid, made on first use

    def _solve(self, hs, u, valid):
        """Heights and pin of the node displacement ``u`` by the height solver ``hs`` of the node grid."""
        o = self.chain.options
        return hs.solve_at_tolerance(np.where(valid, u, np.nan), valid, o.solver, self.chain.cg_tol, self.reference_region,
                                     pin_fallback=o.pin_fallback, region_name=self.chain.region.name,
                                     near=self.near, shift_removal=o.shift_removal)

    def _refined(self, hs, u_nodes, valid, timings):
        """``(surface, valid_nodes, u_nodes, second_order)`` of image matching's node displacement:
        heights and pin solved, the displacement NaN where the solve left a node out.  Where the
        heights' slopes make the linear model's second-order terms count
        (:data:`processing.second_order.SECOND_ORDER_MIN_EFFECT`), solved again without them
        (:class:`processing.second_order.SecondOrderOptics`; ``second_order`` True, the time in
        ``timings["second_order"]``): the deep dimple of the accuracy table 0.179 -> 0.028 %, on random
        dots 0.297 -> 0.132 % (4 x 4 rays a pixel); below the threshold nothing changes."""
        surf = self._solve(hs, u_nodes, valid)
        valid_nodes = np.asarray(surf.valid, bool)
        if self._second_order is None:
            self._second_order = SecondOrderOptics(self.chain.geometry, self.node_grid.rows_px,
                                                   self.node_grid.cols_px, self.chain.shape, hs.x_mm, hs.y_mm)
        again = solved_again(self._second_order, u_nodes, surf.height_mm, valid_nodes,
                             lambda u2: self._solve(hs, u2, valid_nodes), timings)
        second = again is not None
        if second:
            surf = again
            valid_nodes = np.asarray(surf.valid, bool)
        return surf, valid_nodes, np.where(valid_nodes, u_nodes, np.float32(np.nan)).astype(np.float32), second

    def turn_offset(self, turn):
        """The node displacement (2, n_rows, n_cols) of a turn the chain took out of the start
        (``turn``: the start's :class:`processing.turn.TurnCheck`), added to image matching's warp
        and not solved for; None when nothing was taken out."""
        if turn is None or not turn.removed:
            return None
        ng = self.node_grid
        return self.chain.turn_gauge().field(turn.turn_mrad, ng.rows_px, ng.cols_px, turn.removed)

    @staticmethod
    def start_shift(start):
        """The uniform shift (2,; row, col px) that the start's height solve took out of its displacement
        (``shift_removal`` where the whole pattern shifted: :attr:`processing.pin.PinStatus.shift_removed`),
        else None.  The start's heights lack it: image matching from them alone began that far from the
        frame and pulled a tilt of the heights toward it, short of it in its few steps, and the solve
        then took out that tilt's median (simulate's bump, 512^2, shifted 3 px along the columns: 2.68 px
        taken out, 18.4 % rms height error against FD's 0.33 %)."""
        pin = start.pin
        if pin is None or not pin.shift_removed:
            return None
        return np.array([pin.frame_motion_row_px, pin.frame_motion_col_px], np.float64)

    def warp_offset(self, turn, shift):
        """The node displacement (2, n_rows, n_cols) added to image matching's warp and not solved for: the
        turn the chain took out of the start (:meth:`turn_offset`) and the start's uniform ``shift``
        (:meth:`start_shift`); None when neither."""
        offset = self.turn_offset(turn)
        if shift is None:
            return offset
        uniform = np.zeros((2, *self.node_grid.shape), np.float64) + shift[:, None, None]
        return uniform if offset is None else offset + uniform

    @staticmethod
    def shift_border(border_px: int, shift, blur_px: float):
        """Image matching's pixels left out along the top, bottom, left and right: ``border_px`` each, and
        where the start's uniform ``shift`` (:meth:`start_shift`) was taken out, along the sides from which
        it brought the frame's pixels in, as many more as it is long and the blur (``blur_px``) reaches
        (2.5 sigma), rounded up: the reference never saw what they show.  Counted, with the warp's start
        short of the shift there, they matched the reference's border and pulled the border's nodes off by
        pixels.  simulate's bump (512^2, 12 bit) shifted 2 / 2.5 / 3 px along the columns, 3 px along the
        rows, rel. RMS height error (%): none left out 0.75 / 1.64 / 2.26 / 0.34 (the first node column 4 px
        off at 3 px), the shift's 0.11 / 0.18 / 0.18 / 0.34, with the blur's 0.11 / 0.18 / 0.19 / 0.10
        (FD 0.28 / 0.31 / 0.32 / 0.16)."""
        if shift is None:
            return border_px
        reach = 2.5 * blur_px
        more = [int(math.ceil(s + reach)) if s > 0 else 0 for s in (shift[0], -shift[0], shift[1], -shift[1])]
        return tuple(border_px + m for m in more)

    @staticmethod
    def with_shift(u_nodes, shift):
        """Image matching's node displacement ``u_nodes`` (without its warp's offset) with the start's uniform
        ``shift`` (:meth:`start_shift`) put back, as FD's holds it: the height solve measures the shift
        again on it and takes it out (``shift_removal``), and the output reports that one."""
        return u_nodes if shift is None else (u_nodes + shift[:, None, None]).astype(np.float32)

    def _node_result(self, surf, valid_nodes, u_nodes, **fields) -> Result:
        """The node grid's :class:`Result` of a refined surface; ``fields``: the pattern's own
        (amplitude, carriers, phase, timings_ms, pin, series)."""
        ng = self.node_grid
        return Result(height=np.asarray(surf.height_mm, np.float32), valid=valid_nodes,
                      slope_x=np.asarray(surf.slope_x, np.float32), slope_y=np.asarray(surf.slope_y, np.float32),
                      displacement=u_nodes, x_mm=np.asarray(surf.x_mm), y_mm=np.asarray(surf.y_mm),
                      grid="decimated", rows_px=ng.rows_px, cols_px=ng.cols_px,
                      valid_fraction=float(valid_nodes.mean()), **fields)


#: Checkerboards' image matching keeps its first Gauss-Newton step's matrix for the later steps
#: (:func:`processing.dic.refine_height`, ``matrix_once``: the right-hand sides are each step's own,
#: so a converged answer is the same; the later steps' pixel pass sums 2 products instead of 5,
#: their column sums are 2 of 8, and the operator is not set up again). Measured (5 Dec 2026), mean
#: rel. RMS height error (%), every step's matrix -> the first's: eight board placements (256^2, 8 x 8 rays) narrow bump 0.391 -> 0.379, waves 6-12 mm 0.789 ->
#: 0.783, waves 12-30 mm 0.211 -> 0.212, deep dimple 0.044 -> 0.045, the six others equal to the
#: printed digit; the held-out 1024^2 waves (issue 22's three frames) 0.370 -> 0.362; the golden
#: masked spike 9.99 -> 9.59 % (whole frame), the 128^2 bump 2.88 -> 2.90 %. Random dots, started
#: from PIV, do not (four dot seeds, 4 x 4 rays: narrow bump 1.460 -> 1.685 %, waves 6-12 mm 1.802
#: -> 1.892 %): :class:`DotsImageRefinement` recomputes it every step.  Nor do frames with masked
#: pixels (6 Dec 2026): beside a hole the first step's matrix led the later steps astray.  A 4 um bump of
#: sigma 3 mm whose ray crossings mask its centre (256^2, 4 x 4 rays, 12 bit), the board turned 0 / 9 /
#: 20 / 30 / 45 deg: the first step's matrix 1.74 / 1.97 / 2.54 / 5.99 / 1.88 % (FD's heights kept at 45),
#: each step's own 0.75 / 1.11 / 1.01 / 1.14 / 1.47 % (FD 1.87 / 1.78 / 1.73 / 1.54 / 1.89 %); beside
#: ``bench_processing.py --masked 4``'s blank patch 4 um bump 0.235 -> 0.217, 2 um bump 0.305 -> 0.298,
#: narrow bump 0.658 -> 0.588, waves 12-30 mm 0.614 -> 0.383 (FD 0.548), noisy dimple 0.162 -> 0.164, deep
#: dimple 0.187 -> 0.188, waves 6-12 mm 0.903 -> 0.953, 1.5-period bump 0.309 -> 0.314 (no case worse
#: than no refinement by the paired verdict, as before); the golden masked spike 6.36 -> 2.55 % (interior).
#: (:func:`processing.dic.refine_height` keeps it only where every pixel counts.)  Where those steps
#: leave the range where they can be right (a 128^2 frame of simulate's waves, a few pixels masked: steps
#: 0.43 -> 0.88 px rms), :class:`ImageRefinement` tries again with the first step's kept before it gives
#: FD's heights.
MATRIX_ONCE = True


class ImageRefinement(_NodeRefinement):
    """The node grid's constants over a :class:`processing.chain_checkerboard.CheckerboardChain`
    (built once), called on a frame's FD result."""

    def __init__(self, chain):
        _NodeRefinement.__init__(self, chain)
        self.ref_fine = dic.fine_reference(chain.ref_f32, dic.fine_factor(chain.demod.freq, chain.shape))

    def start(self, u, valid, hs, frame, amplitude):
        """``(valid_px, valid_nodes, FD's surface at the nodes)``: the start; AllInvalidError where no node
        has all its pixels valid (``frame`` and its decimated ``amplitude`` name the contrast)."""
        up, ng = self.chain.upsampler, self.node_grid
        all_valid = bool(valid.all())
        fill = None if all_valid else nearest_fill_index(valid)
        uf = u if fill is None else u[:, fill[0], fill[1]]
        valid_px = np.ones(self.chain.shape, bool) if all_valid else up.mask(valid)
        valid_nodes = ng.down(valid_px.astype(np.float32)) > 0.999
        if not valid_nodes.any():  # specks of valid samples, none a node's cell across (a blurred frame)
            raise self.chain.nothing_measured(frame, amplitude)
        u_start = np.stack([up.cell_means(np.nan_to_num(uf[i]), ng.s) for i in range(2)])
        return valid_px, valid_nodes, self._solve(hs, u_start, valid_nodes)

    def __call__(self, m, fd: Result, t3) -> Result:
        """Full-grid result of a frame from its FD result ``fd`` (decimated; its
        series check and pin carried over), ``m`` its :class:`processing.chain_checkerboard.Measured`."""
        chain, ng, timings = self.chain, self.node_grid, fd.timings_ms
        hs = solver_for(chain.geometry, ng.rows_px, ng.cols_px, chain.shape)
        valid_px, valid_nodes, start = self.start(fd.displacement, fd.valid, hs, m.frame, m.amplitude)
        periods, shift = np.asarray(chain.carriers.periods_px, np.float64), self.start_shift(start)
        args = (self.ref_fine, m.frame, np.asarray(start.height_mm, np.float64), valid_px, self.height_nodes)
        kw = dict(outer=chain.options.image_iterations, period_px=float(periods.min()),
                  intensity_cell_px=max(dic.INTENSITY_CELL_PX, 1.6 * float(periods.max())),
                  threads=chain.planner.threads, matrix_once=MATRIX_ONCE,
                  masked_cg_iterations=dic.MASKED_CG_ITERATIONS, offset_px=self.warp_offset(fd.turn, shift),
                  speck_contrast=SPECK_CONTRAST, border_px=self.shift_border(dic.BORDER_PX, shift, dic.BLUR_PX))
        try:
            match = dic.refine_height(*args, **kw)
        except dic.RefinementDiverged:
            if not MATRIX_ONCE or valid_px.all():
                raise
            # beside masked pixels each step took its own matrix (MATRIX_ONCE); where those steps left the
            # range, the first step's kept for all is tried before FD's heights are
            match = dic.refine_height(*args, **kw, matrix_once_beside_masks=True)
        u_nodes, valid_nodes = self.with_shift(match.displacement_px, shift), match.free
        t4 = time.perf_counter()
        timings["refine"] += 1e3 * (t4 - t3)
        surf, valid_nodes, u_nodes, second = self._refined(hs, u_nodes, valid_nodes, timings)
        pin, fd_pin = surf.pin, fd.pin
        if fd_pin is not None and fd_pin.unpinned_fraction > 0:
            # FD dropped them before the node grid: of FD's valid samples, that share and the nodes' own
            dropped = fd_pin.unpinned_fraction + (1.0 - fd_pin.unpinned_fraction) * pin.unpinned_fraction
            pin = dataclasses.replace(pin, unpinned_fraction=dropped)
        t5 = time.perf_counter()
        timings["height"] += 1e3 * (t5 - t4)
        amp_nodes = chain.upsampler.cell_means(m.amplitude, ng.s)
        res = self._node_result(surf, valid_nodes, u_nodes, amplitude=amp_nodes, carriers=chain.carriers,
                                phase=np.asarray(m.phase, np.float32), timings_ms=timings, pin=pin, series=fd.series,
                                turn=fd.turn, note=speck_note(match.speck_share))
        # the slopes of second-order heights are not the linear map of u and h: interpolated as they are
        res = chain.interpolate_full(res, solver=None if second else hs)
        timings["interpolate"] = 1e3 * (time.perf_counter() - t5)
        timings["total"] = 1e3 * (time.perf_counter() - m.t0)
        return res


#: Gaussian blur (sigma, pixels) of frame and warped reference when image matching reads random
#: dots (:class:`DotsImageRefinement`), instead of :data:`processing.dic.BLUR_PX` (1.25 px, for
#: sharp-edged boards). Gaussian dots are smooth already and their contrast sits at high
#: frequencies. Measured on the accuracy table's dot cases (256^2, 8 bit, noise 1 DN, dots
#: 0.5 mm, docs/processing.md section 11), rel. RMS height error of narrow bump / waves 12-30 mm /
#: deep dimple / waves 6-12 mm / bump 1 um (%): blur 1.25 px 0.96 / 0.41 / 0.50 / 2.65 / 1.00,
#: 1.0 px 0.80 / 0.28 / 0.44 / 2.33 / 0.78, 0.6 px 0.70 / 0.25 / 0.31 / 2.09 / 0.53, 0.4 px
#: 0.76 / 0.23 / 0.28 / 1.90 / 0.49, none 0.78 / 0.22 / 0.28 / 2.36 / 0.49; 1.8 px worse again.
DOTS_BLUR_PX = 0.5

#: Pixels along each side of the frame that image matching leaves out on random dots
#: (:data:`processing.dic.BORDER_PX`, 2 for boards, blurred by 1.25 px): none. With the dots'
#: 0.5 px blur OpenCV's mirror image reaches a pixel into the frame, and the border's nodes need
#: the data PIV's coarse start lacks there. Measured over four dot seeds (256^2, 4 x 4 rays, 8 bit,
#: noise 1 DN; narrow bump / waves 6-12 mm / waves 12-30 mm): 0 px 1.485 / 1.799 / 0.254 %, 1 px
#: 1.612 / 1.867 / 0.243 %, 2 px 1.716 / 2.245 / 0.206 % (before the warp's samples beyond the
#: reference's border were left out, :func:`processing.dic._outside`: 1.455 / 1.721 / 0.320 %; the
#: deep dimple 0.079 -> 0.031 %).
DOTS_BORDER_PX = 0

#: How many times finer than the pixels the dot reference is sampled for the warp
#: (:func:`processing.dic.fine_reference`): 3, as for 8 px carriers (2x measured within 0.05
#: points of it on the cases above, the narrow bump 0.98 against 0.96 %).
DOTS_FINE = 3


class DotsImageRefinement(_NodeRefinement):
    """Image matching for the height on random dots: the PIV displacement of a
    :class:`processing.chain_dots.DotsChain` as the start, then the same global
    Gauss-Newton height solve as checkerboards (:func:`processing.dic.refine_height`:
    it does not care what the pattern is), the masked height solver and pin on
    the node grid, then every pixel by cubic spline."""

    def __init__(self, chain):
        from .fullgrid import Upsampler

        _NodeRefinement.__init__(self, chain)
        ng = self.node_grid
        self.ref_fine = dic.fine_reference(chain.reference_image, DOTS_FINE)
        self.solver = solver_for(chain.geometry, ng.rows_px, ng.cols_px, chain.shape)
        self.upsampler = Upsampler(chain.shape, ng.shape, "spline")
        # each node's place on the PIV grid, in samples (the start's spline)
        self.at = np.meshgrid((ng.rows_px - chain.rows_px[0]) / (chain.rows_px[1] - chain.rows_px[0]),
                              (ng.cols_px - chain.cols_px[0]) / (chain.cols_px[1] - chain.cols_px[0]), indexing="ij")

    def start(self, u_piv, valid_piv):
        """``(valid_px, valid_nodes, PIV's surface at the nodes)``: the PIV
        displacement (invalid samples: the nearest valid one's) to the nodes by
        cubic spline, solved for the height there."""
        from .piv import sample_spline, spline_coefficients

        fill = nearest_fill_index(valid_piv)
        src = u_piv if fill is None else u_piv[:, fill[0], fill[1]]
        # scipy.ndimage.map_coordinates(src, at, order=3, mode="nearest"), compiled (to 1e-13)
        u_nodes = np.stack([sample_spline(spline_coefficients(np.nan_to_num(src[i])), *self.at) for i in range(2)])
        ng = self.node_grid
        valid_nodes = valid_piv[np.ix_(*self.pick)]
        valid_px = np.ones(self.chain.shape, bool) if valid_nodes.all() else ng.up(valid_nodes, cv2.INTER_NEAREST) > 0
        return valid_px, valid_nodes, self._solve(self.solver, u_nodes, valid_nodes)

    def __call__(self, m, piv: Result) -> Result:
        """Full-grid result of a frame from its PIV result ``piv`` (PIV grid),
        ``m`` its :class:`processing.chain_dots.DotsMeasured`."""
        chain, timings = self.chain, piv.timings_ms
        t3 = time.perf_counter()
        valid_px, valid_nodes, start = self.start(piv.displacement, piv.valid)
        window, shift = float(chain.options.window_px), self.start_shift(start)
        _, u_nodes, free, _ = dic.refine_height(
            self.ref_fine, m.frame, np.asarray(start.height_mm, np.float64), valid_px, self.height_nodes,
            outer=chain.options.image_iterations, blur_px=DOTS_BLUR_PX, period_px=window / 2,
            intensity_cell_px=max(dic.INTENSITY_CELL_PX, window), threads=int(chain.options.threads),
            border_px=self.shift_border(DOTS_BORDER_PX, shift, DOTS_BLUR_PX),
            offset_px=self.warp_offset(piv.turn, shift))
        u_nodes = self.with_shift(u_nodes, shift)
        t4 = time.perf_counter()
        timings["refine"] = 1e3 * (t4 - t3)
        surf, valid_nodes, u_nodes, second = self._refined(self.solver, u_nodes, free & valid_nodes, timings)
        t5 = time.perf_counter()
        timings["height"] += 1e3 * (t5 - t4)
        res = self._node_result(surf, valid_nodes, u_nodes, amplitude=valid_nodes.astype(np.float32), carriers=None,
                                phase=piv.phase, timings_ms=timings, pin=surf.pin, turn=piv.turn)
        res = interpolate_full(res, self.upsampler, chain.full_coordinates(), None if second else self.solver)
        timings["interpolate"] = 1e3 * (time.perf_counter() - t5)
        return res
