"""What pins the height's null space in one frame (:mod:`processing.height`'s
module docstring says why): :func:`choose_pin_samples` and its :class:`PinStatus`."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from .errors import GeometryError, TirdeflectError

__all__ = ["PIN_MIN_SAMPLES", "PIN_MIN_FRACTION", "PIN_MIN_PIECE_SAMPLES", "PIN_FALLBACKS", "PinStatus",
           "choose_pin_samples", "pin_samples_needed"]


#: Fewest valid samples the pin of the null space needs (see the module docstring).
PIN_MIN_SAMPLES = 16
#: Smallest fraction of the reference region that must be valid for the pin.
PIN_MIN_FRACTION = 0.25
#: A connected piece of valid samples needs this many pin samples to be pinned
#: (one independent filter footprint); smaller pieces are reported invalid.
PIN_MIN_PIECE_SAMPLES = 4
PIN_FALLBACKS = ("nearest", "refuse")


def pin_samples_needed(region_samples: int) -> int:
    """How many valid samples the pin needs in a region of ``region_samples`` samples."""
    return max(PIN_MIN_SAMPLES, math.ceil(PIN_MIN_FRACTION * int(region_samples)))


@dataclass(frozen=True)
class PinStatus:
    """Where the null space of one frame was pinned (one per reconstructed frame).

    Attributes
    ----------
    rule : {"region", "nearest"}
        "region": on the valid samples of the reference region;
        "nearest": too few of them were valid, so the fallback took the valid
        samples nearest the region.
    region : str
        Which region: ``"reference_region [r0, r1, c0, c1]"`` or the default.
    region_samples : int
        Samples of the grid in the region.
    valid_samples : int
        Of those, valid in this frame.
    needed : int
        Valid samples the pin needs (:func:`pin_samples_needed`).
    used_samples : int
        Samples the offset was measured on.
    unpinned_fraction : float
        Fraction of the frame's valid samples dropped (NaN) because their
        connected piece held fewer than :data:`PIN_MIN_PIECE_SAMPLES` pin samples.
    """

    rule: str
    region: str
    region_samples: int
    valid_samples: int
    needed: int
    used_samples: int
    unpinned_fraction: float = 0.0

    @property
    def ok(self) -> bool:
        """Pinned on the region itself, with as many samples as it needs."""
        return self.rule == "region"

    def describe(self) -> str:
        """One line for logs and summaries."""
        if self.region_samples == 0:
            where = f"{self.region}: no sample where the reference shows the pattern"
        else:
            where = (f"{self.region}: {self.valid_samples} of {self.region_samples} samples valid"
                     f" (needs {self.needed})")
        if self.rule == "region":
            text = f"pinned on {where}"
        else:
            text = f"FALLBACK: {where}, pinned on the {self.used_samples} valid samples nearest it"
        if self.unpinned_fraction > 0:
            text += f"; {100 * self.unpinned_fraction:.1f} % of valid samples dropped (no pin sample in their piece)"
        return text


def choose_pin_samples(region: np.ndarray, valid: np.ndarray, *, fallback: str = "nearest",
                       region_name: str = "reference region", near: np.ndarray | None = None):
    """Pin samples of one frame and their :class:`PinStatus`.

    Parameters
    ----------
    region : ndarray bool (n_rows, n_cols)
        The reference region on the sample grid (the same for every frame).
    valid : ndarray bool (n_rows, n_cols)
        Valid samples of this frame.
    fallback : {"nearest", "refuse"}
        What to do when the region holds fewer valid samples than
        :func:`pin_samples_needed`: pin on the valid samples nearest the
        region, or raise GeometryError.
    region_name : str
        How the status names the region.
    near : ndarray bool or None
        Where "nearest" measures from (default: ``region``; e.g. the user's box
        when none of it is valid in the reference).

    Returns
    -------
    samples : ndarray bool (n_rows, n_cols)
    status : PinStatus (``unpinned_fraction`` still 0)
    """
    if fallback not in PIN_FALLBACKS:
        raise TirdeflectError(f"pin fallback must be one of {PIN_FALLBACKS}, got {fallback!r}")
    n_region = int(np.count_nonzero(region))
    inside = region & valid
    n_valid = int(np.count_nonzero(inside))
    needed = pin_samples_needed(n_region)
    if n_valid >= needed:
        return inside, PinStatus("region", region_name, n_region, n_valid, needed, n_valid)
    if fallback == "refuse":
        raise GeometryError(
            f"{region_name} has {n_valid} valid samples in this frame (of {n_region}); the height offset "
            f"needs {needed} to be measured; choose a reference_region where the surface is at rest and the "
            f"pattern is visible, or allow the 'nearest' fallback"
        )
    n_all = int(np.count_nonzero(valid))
    if n_all == 0:
        from .errors import AllInvalidError

        raise AllInvalidError("no valid sample to pin the height offset on; check the mask and the frame")
    anchor = region if near is None else near
    if anchor.any():
        dist = ndimage.distance_transform_edt(~anchor)
    else:  # nothing to measure from: every valid sample is as near
        dist = np.zeros(region.shape)
    d = dist[valid]
    k = min(needed, n_all)
    cut = np.partition(d, k - 1)[k - 1]
    samples = valid & (dist <= cut)
    return samples, PinStatus("nearest", region_name, n_region, n_valid, needed, int(np.count_nonzero(samples)))
