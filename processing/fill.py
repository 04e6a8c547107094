"""Nearest-valid-sample fill: what every interpolation of a masked grid needs."""

from __future__ import annotations

import numpy as np

from .mask_memo import MaskMemo

__all__ = ["nearest_fill_index", "FILL_CACHE_SIZE"]

#: Masks whose fill index is kept (least recently used dropped first).  A frame's
#: chain asks for the same few masks several times (the decimated grid's, the
#: node grid's), and a series of frames mostly for the same ones again: the
#: Euclidean distance transform behind each costs 1-2 ms at 256^2 whatever the
#: number of invalid samples (9 ms of a 1024^2 frame's image refinement).
FILL_CACHE_SIZE = 8

_memo = MaskMemo(FILL_CACHE_SIZE)


def nearest_fill_index(valid):
    """Index arrays that map every sample to its nearest valid one (None if all
    valid or none is): invalid samples must not drag their valid neighbours
    towards 0 when interpolating.  The arrays are read-only and may be shared
    with other callers that passed the same mask."""
    valid = np.asarray(valid, bool)
    if valid.all() or not valid.any():
        return None
    return _memo(valid, _fill_index)


def _fill_index(valid):
    from scipy import ndimage

    _, idx = ndimage.distance_transform_edt(~valid, return_indices=True)
    idx.flags.writeable = False  # and so every view of it
    return idx[0], idx[1]
