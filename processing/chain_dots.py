"""The random-dot chain: displacement by PIV (:class:`processing.piv.DotDisplacement`),
then the same island removal, masked height solve and pin as the checkerboard
chain; on the full grid then image matching for the height from PIV's start
(:class:`processing.chain_image.DotsImageRefinement`, ``refine_method="image"``,
the default there) or PIV's heights to every pixel (:func:`processing.fullgrid.dots_full`)."""

from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np

from .chain_base import GridChain
from .errors import AllInvalidError
from .fullgrid import dots_full
from .mask import choose_reference_region, drop_islands
from .piv import DotDisplacement
from .result import Result

#: PIV windows along the frame's border whose displacement the turn check leaves out
#: (:class:`processing.turn.TurnGauge`).
TURN_BAND_WINDOWS = 2.0

__all__ = ["DotsChain", "DotsMeasured"]


class DotsMeasured(NamedTuple):
    """A frame after :meth:`DotsChain.measure`: the PIV grid."""

    u: np.ndarray  # displacement (2, n_rows, n_cols), pixels
    valid: np.ndarray
    frame: np.ndarray  # the validated frame (image matching reads it)
    timings: dict
    t0: float


class DotsChain(GridChain):
    """What a random-dot reference fixes (the PIV grid, the reference region)
    and the stages a frame goes through, the same three as
    :class:`processing.chain_checkerboard.CheckerboardChain`'s (``measure``,
    ``solve``, ``to_grid``).  No series memory: every frame is measured
    against the reference alone (the state given passes through)."""

    def __init__(self, ref, geometry, options):
        GridChain.__init__(self)
        self.options = options
        self.geometry = geometry
        self.shape = ref.shape
        self.reference_image = ref
        self.piv = DotDisplacement(ref, window_px=options.window_px, threads=options.threads)
        self.rows_px, self.cols_px = self.piv.rows_px, self.piv.cols_px
        self.reference_valid = np.ones((self.rows_px.size, self.cols_px.size), bool)
        # no mask dilation here: the band starts at the grid's border
        self.region = choose_reference_region(geometry, self.reference_valid, self.rows_px, self.cols_px,
                                              self.shape, skip=0)
        self.cg_tol = 1e-4  # as the checkerboard chain's masked solve
        # the turn check (processing.turn): PIV's outermost windows see the border
        self.turn_band_px = TURN_BAND_WINDOWS * float(options.window_px)
        self.turn_reference_mask = self.region.region
        self._image = None

    def image_refinement(self):
        """Image matching from PIV's start (:class:`processing.chain_image.DotsImageRefinement`, built once)."""
        if self._image is None:
            from .chain_image import DotsImageRefinement

            self._image = DotsImageRefinement(self)
        return self._image

    def measure(self, frame, grid, state, t0):
        """``(DotsMeasured, state)``: PIV of one validated frame, small islands
        dropped (``state``, the series memory, passes through: dots keep none)."""
        timings = {}
        u, valid = self.piv(frame)
        timings["piv"] = 1e3 * (time.perf_counter() - t0)
        if not valid.any():
            raise AllInvalidError("no interrogation window of the frame correlates with the reference: check that "
                                  "the dots are in focus and lit, and that the frame shows the reference's pattern")
        valid = drop_islands(valid, self.region.region, self.options.min_island)
        return DotsMeasured(u, valid, frame, timings, t0), state

    def solve(self, m, grid, state):
        """``(Result, state)``: heights and pin on the PIV grid."""
        o, t1 = self.options, time.perf_counter()
        u, turn = self.judge_turn(m.u, m.valid)  # a turn of camera or board since the reference is no surface's
        surf = self.height_solver().solve_at_tolerance(
            np.where(m.valid, u, np.nan), m.valid, o.solver, self.cg_tol, self.region.region,
            pin_fallback=o.pin_fallback, region_name=self.region.name, near=self.region.near,
            shift_removal=o.shift_removal)
        valid = np.asarray(surf.valid, bool)
        u = np.where(valid, u, np.float32(np.nan)).astype(np.float32)
        m.timings["height"] = 1e3 * (time.perf_counter() - t1)
        res = Result(height=np.asarray(surf.height_mm, np.float32), valid=valid,
                     slope_x=np.asarray(surf.slope_x, np.float32), slope_y=np.asarray(surf.slope_y, np.float32),
                     displacement=u, amplitude=valid.astype(np.float32), x_mm=np.asarray(surf.x_mm),
                     y_mm=np.asarray(surf.y_mm), grid="decimated", rows_px=self.rows_px, cols_px=self.cols_px,
                     carriers=None, phase=np.zeros((2, 0, 0), np.float32),
                     valid_fraction=float(valid.mean()), timings_ms=m.timings, pin=surf.pin,
                     turn=turn)
        return res, state

    def to_grid(self, m, res, grid) -> Result:
        """``res`` on ``grid``: on the full grid image matching from PIV's start
        where ``refine_method="image"`` (PIV's heights kept, with a note, where it
        diverges), else every pixel by cubic spline (:func:`processing.fullgrid.dots_full`)."""
        if grid == "full":
            t2 = time.perf_counter()
            refined = None
            if self.options.refine_method == "image":
                from .dic import RefinementDiverged

                try:
                    refined = self.image_refinement()(m, res)
                except RefinementDiverged as exc:  # PIV's heights below, and the reason with them
                    res.note = f"image refinement stopped: {exc}; PIV's heights kept"
            if refined is None:
                res = dots_full(res, self.shape, self.full_coordinates())
                m.timings["interpolate"] = 1e3 * (time.perf_counter() - t2)
            else:
                res = refined
        m.timings["total"] = 1e3 * (time.perf_counter() - m.t0)
        return res
