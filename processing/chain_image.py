"""The image-domain refinement chain of the full grid (``refine_method="image"``):
FD's heights on a node grid every ``dic.NODE_PX`` pixels refined by image
matching (:func:`processing.dic.refine_height`), then the same masked height
solver and pin, then every pixel (:class:`ImageRefinement`)."""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from . import dic
from .fill import nearest_fill_index
from .height import solver_for
from .result import Result

__all__ = ["ImageRefinement"]


class ImageRefinement:
    """The node grid's constants over a :class:`processing.chain_checkerboard.CheckerboardChain`
    (built once), called on a frame's FD result."""

    def __init__(self, chain):
        self.chain = chain
        ng = self.node_grid = dic.NodeGrid(chain.shape)
        self.height_nodes = dic.HeightNodes(chain.geometry, ng)
        self.ref_fine = dic.fine_reference(chain.ref_f32, dic.fine_factor(chain.demod.freq, chain.shape))
        pick_r = np.abs(ng.rows_px[:, None] - chain.rows_px[None, :]).argmin(axis=1)
        pick_c = np.abs(ng.cols_px[:, None] - chain.cols_px[None, :]).argmin(axis=1)
        near = chain.region.near
        self.reference_region = chain.plan.reference_region[np.ix_(pick_r, pick_c)]
        self.near = None if near is None else near[np.ix_(pick_r, pick_c)]

    def _solve(self, hs, u, valid):
        o = self.chain.options
        return hs.solve_at_tolerance(np.where(valid, u, np.nan), valid, o.solver, self.chain.cg_tol, self.reference_region,
                                     pin_fallback=o.pin_fallback, region_name=self.chain.region.name,
                                     near=self.near)

    def start(self, u, valid, hs):
        """``(valid_px, valid_nodes, FD's surface at the nodes)``: the start."""
        up, ng = self.chain.upsampler, self.node_grid
        all_valid = bool(valid.all())
        fill = None if all_valid else nearest_fill_index(valid)
        uf = u if fill is None else u[:, fill[0], fill[1]]
        valid_px = np.ones(self.chain.shape, bool) if all_valid else up.mask(valid)
        valid_nodes = ng.down(valid_px.astype(np.float32)) > 0.999
        u_start = np.stack([ng.down(up(np.nan_to_num(uf[i]))) for i in range(2)])
        return valid_px, valid_nodes, self._solve(hs, u_start, valid_nodes)

    def __call__(self, m, fd: Result, t3) -> Result:
        """Full-grid result of a frame from its FD result ``fd`` (decimated; its
        series check and pin carried over), ``m`` its :class:`processing.chain_checkerboard.Measured`."""
        chain, ng, timings = self.chain, self.node_grid, fd.timings_ms
        hs = solver_for(chain.geometry, ng.rows_px, ng.cols_px, chain.shape)
        valid_px, valid_nodes, start = self.start(fd.displacement, fd.valid, hs)
        periods = np.asarray(chain.carriers.periods_px, np.float64)
        _, u_nodes, valid_nodes = dic.refine_height(
            self.ref_fine, m.frame, np.asarray(start.height_mm, np.float64), valid_px, self.height_nodes,
            outer=chain.options.image_iterations, period_px=float(periods.min()),
            intensity_cell_px=max(dic.INTENSITY_CELL_PX, 1.6 * float(periods.max())), threads=chain.planner.threads)
        t4 = time.perf_counter()
        timings["refine"] += 1e3 * (t4 - t3)
        surf = self._solve(hs, u_nodes, valid_nodes)
        valid_nodes = np.asarray(surf.valid, bool)
        u_nodes = np.where(valid_nodes, u_nodes, np.float32(np.nan)).astype(np.float32)
        pin, fd_pin = surf.pin, fd.pin
        if fd_pin is not None and fd_pin.unpinned_fraction > 0:
            # FD dropped them before the node grid: of FD's valid samples, that share and the nodes' own
            dropped = fd_pin.unpinned_fraction + (1.0 - fd_pin.unpinned_fraction) * pin.unpinned_fraction
            pin = dataclasses.replace(pin, unpinned_fraction=dropped)
        t5 = time.perf_counter()
        timings["height"] += 1e3 * (t5 - t4)
        amp_nodes = ng.down(chain.upsampler(m.amplitude))
        res = Result(height=np.asarray(surf.height_mm, np.float32), valid=valid_nodes,
                     slope_x=np.asarray(surf.slope_x, np.float32), slope_y=np.asarray(surf.slope_y, np.float32),
                     displacement=u_nodes, amplitude=amp_nodes, x_mm=np.asarray(surf.x_mm),
                     y_mm=np.asarray(surf.y_mm), grid="decimated", rows_px=ng.rows_px, cols_px=ng.cols_px,
                     carriers=chain.carriers, phase=np.asarray(m.phase, np.float32),
                     valid_fraction=float(valid_nodes.mean()), timings_ms=timings, pin=pin, series=fd.series)
        res = chain.interpolate_full(res, solver=hs)
        timings["interpolate"] = 1e3 * (time.perf_counter() - t5)
        timings["total"] = 1e3 * (time.perf_counter() - m.t0)
        return res
