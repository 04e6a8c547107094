"""Nearest-valid-sample fill: what every interpolation of a masked grid needs."""

from __future__ import annotations

__all__ = ["nearest_fill_index"]


def nearest_fill_index(valid):
    """Index arrays that map every sample to its nearest valid one (None if all
    valid): invalid samples must not drag their valid neighbours towards 0
    when interpolating."""
    if valid.all() or not valid.any():
        return None
    from scipy import ndimage

    _, idx = ndimage.distance_transform_edt(~valid, return_indices=True)
    return (idx[0], idx[1])
