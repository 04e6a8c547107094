"""Imported once by the app's fork server (:mod:`app.worker_processes`): prepares a process to reconstruct.

Importing it imports the modules every worker needs (the live measurement, the batch engine's
worker side, the processing chain and its libraries) and then reconstructs one small synthetic
checkerboard frame with the default options, one thread and FFTW's estimate planner (and calls the
unwrapper's compiled kernels and the masked height solve's operator once): the first call of each
Numba kernel of the default chain loads it from Numba's cache and sets up Numba's compiler context
(0.4 s on a quiet 2-core PC), once here instead of in every forked worker.

Nothing here may end the server: a failure is ignored (the workers then load what they need
themselves). OpenCV is kept at one thread during the warm-up and set back to its default after,
so that its thread pool is first made in each worker, never inherited half-made by a fork.
"""

from __future__ import annotations

import logging

import numpy as np

import app.batch.parallel  # noqa: F401  (the pool workers' side)
import app.capture.live_measure  # noqa: F401  (the live process's side)
import processing.chain_image  # noqa: F401
import processing.reconstruct  # noqa: F401

__all__ = ["warm_up"]

log = logging.getLogger(__name__)


def warm_up(size_px: int = 96) -> bool:
    """Reconstruct a ``size_px`` square synthetic frame once; True when it ran through."""
    import cv2

    from processing import ReconstructOptions, Reconstructor
    from processing.geometry import Geometry

    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        period_px = 8.0
        rows, cols = np.mgrid[0:size_px, 0:size_px].astype(np.float64)

        def board(shift_px: float) -> np.ndarray:
            phase = 2 * np.pi / period_px
            image = 0.5 + 0.2 * (np.cos(phase * (cols - shift_px)) + np.cos(phase * rows))
            return np.round(200 * image).astype(np.uint8)

        geometry = Geometry(theta_deg=55.0, depth_mm=300.0, pixel_mm=0.08, rows_toward_camera=False)
        options = ReconstructOptions(threads=1, planner_effort="FFTW_ESTIMATE")
        shift = 0.3 * np.exp(-((rows - size_px / 2) ** 2 + (cols - size_px / 2) ** 2) / (2 * (size_px / 6) ** 2))
        Reconstructor(board(0.0), geometry, options)(board(shift))
        # the unwrapper's compiled fills, growth and path following, which a frame this smooth does not
        # reach (compiled on the first call after a checkout, 1.5 s; loaded from Numba's cache after)
        from processing.unwrap_kernels import flood_fill, grow_into, path_follow, scan_fill

        flood_fill(np.zeros((4, 4)), np.ones((4, 4), bool), np.zeros((4, 4)))
        scan_fill(np.zeros((4, 4)), np.zeros((4, 4)))
        grow_into(np.zeros(16), np.zeros(16), np.ones(16, bool), np.array([5]), 4, 4, 16)
        path_follow(np.zeros((4, 4)), np.ones((4, 4), bool), np.zeros((4, 4)))
        # and the masked height solve's operator (a frame with invalid samples)
        from processing.height_compiled import edge_data_into, masked_normal_apply

        f32 = np.float32
        ones = np.ones((4, 4), f32)
        masked_normal_apply(ones, ones[:, 1:], ones[1:], ones, f32(1), f32(1), np.zeros((0, 0)), np.zeros((0, 0)),
                            np.zeros((4, 5), f32), np.zeros((5, 4), f32), np.empty((4, 4), f32))
        grid64 = np.ones((4, 4))
        edge_data_into(grid64, grid64, grid64, np.ones((4, 4), bool), np.empty((3, 4)), np.empty((4, 3)))
        # and the fold test of a strained frame (a smooth one never reaches its determinant)
        from processing.mask_kernels import fold_determinant

        fold_determinant(np.ones((2, 4, 4), f32), 1.0, 1.0, f32(1), np.empty((4, 4), f32))
        # and the second-order correction's trace (slopes this small never call it)
        from processing.trace_kernels import trace_planes_tir

        one = np.ones(1)
        trace_planes_tir(np.array([[0.0], [0.0], [1.0]]), np.array([[0.0], [0.5], [-1.0]]), 0 * one, 0 * one,
                         0 * one, 0 * one, 0 * one, 1.0, 0.75, 300.0, 1e-9, 60, np.empty(1), np.empty(1),
                         np.empty(1, bool), np.empty((6, 1)))
        return True
    except Exception as exc:  # noqa: BLE001 - a warm-up only: the workers load what they need themselves
        log.debug("worker warm-up skipped: %s", exc)
        return False
    finally:
        cv2.setNumThreads(threads)


warm_up()
