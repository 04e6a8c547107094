"""The random-dot chain: displacement by PIV (:class:`processing.piv.DotDisplacement`),
then the same island removal, masked height solve and pin as the checkerboard
chain, then every pixel (:func:`processing.fullgrid.dots_full`)."""

from __future__ import annotations

import time

import numpy as np

from .errors import AllInvalidError
from .fullgrid import dots_full, full_coordinates
from .mask import choose_reference_region, drop_islands
from .piv import DotDisplacement
from .result import Result

__all__ = ["DotsChain"]


class DotsChain:
    """What a random-dot reference fixes (the PIV grid, the reference region)
    and the stages a frame goes through.  No series memory: every frame is
    measured against the reference alone."""

    def __init__(self, ref, geometry, options):
        self.options = options
        self.geometry = geometry
        self.shape = ref.shape
        self.reference_image = ref
        self.piv = DotDisplacement(ref, window_px=options.window_px)
        self.rows_px, self.cols_px = self.piv.rows_px, self.piv.cols_px
        self.reference_valid = np.ones((self.rows_px.size, self.cols_px.size), bool)
        # no mask dilation here: the band starts at the grid's border
        self.region = choose_reference_region(geometry, self.reference_valid, self.rows_px, self.cols_px,
                                              self.shape, skip=0)
        self.cg_tol = 1e-4  # as the checkerboard chain's masked solve
        self._solver = self._coords = None

    def height_solver(self):
        """Height solver of the PIV grid (built once)."""
        if self._solver is None:
            from .height import solver_for

            self._solver = solver_for(self.geometry, self.rows_px, self.cols_px, self.shape)
        return self._solver

    def full_coordinates(self):
        """``(x_mm, y_mm)`` of every pixel column and row."""
        if self._coords is None:
            self._coords = full_coordinates(self.geometry, self.shape)
        return self._coords

    def __call__(self, frame, grid, t0) -> Result:
        """Result of one validated frame on ``grid``."""
        o, timings = self.options, {}
        u, valid = self.piv(frame)
        t1 = time.perf_counter()
        timings["piv"] = 1e3 * (t1 - t0)
        if not valid.any():
            raise AllInvalidError("no interrogation window of the frame correlates with the reference: check that "
                                  "the dots are in focus and lit, and that the frame shows the reference's pattern")
        valid = drop_islands(valid, self.region.region, o.min_island)
        surf = self.height_solver().solve_at_tolerance(
            np.where(valid, u, np.nan), valid, o.solver, self.cg_tol, self.region.region,
            pin_fallback=o.pin_fallback, region_name=self.region.name, near=self.region.near)
        valid = np.asarray(surf.valid, bool)
        u = np.where(valid, u, np.float32(np.nan)).astype(np.float32)
        timings["height"] = 1e3 * (time.perf_counter() - t1)
        res = Result(height=np.asarray(surf.height_mm, np.float32), valid=valid,
                     slope_x=np.asarray(surf.slope_x, np.float32), slope_y=np.asarray(surf.slope_y, np.float32),
                     displacement=u, amplitude=valid.astype(np.float32), x_mm=np.asarray(surf.x_mm),
                     y_mm=np.asarray(surf.y_mm), grid="decimated", rows_px=self.rows_px, cols_px=self.cols_px,
                     carriers=None, phase=np.zeros((2, 0, 0), np.float32),
                     valid_fraction=float(valid.mean()), timings_ms=timings, pin=surf.pin)
        if grid == "full":
            t2 = time.perf_counter()
            res = dots_full(res, self.shape, self.full_coordinates())
            timings["interpolate"] = 1e3 * (time.perf_counter() - t2)
        timings["total"] = 1e3 * (time.perf_counter() - t0)
        return res
