"""What a :class:`~processing.reconstruct.Reconstructor` computes once from its
reference and every chain over it reads: :class:`ReferencePlan` (read-only).

The GPU chain (:mod:`processing.gpu`) is built from it and from the public
methods of the Reconstructor, never from its private attributes, so a change
inside the CPU chain cannot silently change a path that rarely runs on a GPU
(checked on one once, docs/processing.md section 8).
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np

__all__ = ["ReferencePlan", "DemodulationPlan", "read_only"]


def read_only(a):
    """A read-only view of array ``a`` (None stays None)."""
    if a is None:
        return None
    v = np.asarray(a).view()
    v.flags.writeable = False
    return v


@dataclasses.dataclass(frozen=True)
class DemodulationPlan:
    """What a :class:`Demodulator` computed once from the reference, read-only:
    what another implementation of its chain (processing/gpu.py) needs.

    Attributes
    ----------
    window2d : ndarray float32 (rows, cols) or None
        Border window both images are multiplied by (None: ``border="none"``).
    gather_index : ndarray int64 (2, m_rows, m_cols)
        Flat index into the real FFT ``(rows, cols // 2 + 1)`` of each carrier
        window's bin, ifftshift order.
    gather_mirror : ndarray bool (2, m_rows, m_cols) or None
        Bins taken from the mirrored half (to be conjugated); None when none is.
    filters : ndarray complex64 (2, m_rows, m_cols)
        Band-pass gain times the phase ramp that puts the samples at ``rows_px``, ``cols_px``.
    dc_leak : ndarray complex64 (2, m_rows, m_cols) or None
        The border window's own spectrum in the carrier windows (times the
        image mean: what is subtracted); None without a window.
    local_inverse : ndarray float32 (2, 2, m_rows, m_cols) or None
        ``-K(r)^-1`` per decimated sample (local carriers), None with global ones.
    window_centres : ndarray int64 (2, 2)
        ``(row, col)`` bin of each carrier window's centre (the carrier rounded to a bin).
    """

    window2d: Optional[np.ndarray]
    gather_index: np.ndarray
    gather_mirror: Optional[np.ndarray]
    filters: np.ndarray
    dc_leak: Optional[np.ndarray]
    local_inverse: Optional[np.ndarray]
    window_centres: np.ndarray


@dataclasses.dataclass(frozen=True)
class ReferencePlan:
    """The reference's constants on the decimated grid (arrays read-only).

    Attributes
    ----------
    conj_g0 : ndarray complex64 (2, m_rows, m_cols)
        Conjugate of the reference's analytic signals: ``arg(g conj_g0)`` is a frame's phase.
    g0_amplitude : ndarray float32 (2, m_rows, m_cols)
        ``|g0|`` floored at 1e-30: the amplitude ratio ``|g| / |g0|`` divides by it.
    reference_region : ndarray bool (m_rows, m_cols)
        Where the height offset is pinned (``Reconstructor.reference_region``).
    reference_region_index : ndarray int64
        Its flat indices (temporal unwrapping keeps its median phase nearest 0).
    region_near : ndarray bool or None
        The user's box when none of it shows the pattern: the "nearest"
        fallback measures distances from it; None otherwise.
    reference_valid_everywhere : bool
        The reference shows the pattern on every sample (no blank part masks every frame).
    demodulation : DemodulationPlan
        The demodulator's constants (border window, carrier windows, filters, local carriers).
    """

    conj_g0: np.ndarray
    g0_amplitude: np.ndarray
    reference_region: np.ndarray
    reference_region_index: np.ndarray
    region_near: Optional[np.ndarray]
    reference_valid_everywhere: bool
    demodulation: DemodulationPlan
