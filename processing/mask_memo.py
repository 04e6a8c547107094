"""What a mask gives, computed once: a small cache keyed by the mask itself.

A frame's chain asks for the same few masks' derived arrays several times (the
decimated grid's valid samples: its nearest-valid fill, its connected regions),
and a live series mostly for the same masks again.  :class:`MaskMemo` keeps the
last ``size`` answers, least recently used dropped first, keyed by the mask's
shape and packed bits (the mask itself: no collision possible; 0.02 ms for a
270^2 grid).  Thread-safe; the answers are shared between callers, so what it
holds must be read-only.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Any, Callable

import numpy as np

__all__ = ["MaskMemo"]


class MaskMemo:
    """``memo(valid, compute)``: ``compute(valid)`` the first time ``valid`` (bool array) is seen, the
    same object for the next ``size - 1`` other masks asked for."""

    def __init__(self, size: int):
        self.size = int(size)
        self._cache: "OrderedDict[tuple, Any]" = OrderedDict()
        self._lock = threading.Lock()

    def __call__(self, valid: np.ndarray, compute: Callable[[np.ndarray], Any]) -> Any:
        key = (valid.shape, np.packbits(valid).tobytes())
        with self._lock:
            hit = self._cache.get(key)
            if hit is not None:
                self._cache.move_to_end(key)
                return hit
        answer = compute(valid)
        with self._lock:
            self._cache[key] = answer
            while len(self._cache) > self.size:
                self._cache.popitem(last=False)
        return answer

    def __len__(self) -> int:
        return len(self._cache)
