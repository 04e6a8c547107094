"""Thread pools kept for the process's life, one per thread count: what the
chains use to run NumPy, OpenCV and compiled work that releases the GIL on
several cores within one frame (:func:`thread_map`, :func:`pool`).

Before, three modules kept pools of their own and random dots' spline
sampling made one per call (twice a PIV pass): under cProfile the thread
starts looked like 15-17 ms of a 512^2 frame, but timed without it the dots'
frame was 227-236 ms either way.  A forked child inherits the pools but not
their threads, so they are forgotten in the child (it makes its own).
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

__all__ = ["pool", "thread_map"]

_POOLS: dict = {}
_LOCK = threading.Lock()
# a forked child inherits the pools but not their threads: it would wait on them forever
os.register_at_fork(after_in_child=_POOLS.clear)


def pool(threads: int) -> ThreadPoolExecutor:
    """The process's pool of ``threads`` threads (made on first use)."""
    p = _POOLS.get(threads)
    if p is None:
        with _LOCK:
            p = _POOLS.get(threads)
            if p is None:
                p = _POOLS[threads] = ThreadPoolExecutor(threads, thread_name_prefix=f"tirdeflect-{threads}")
    return p


def thread_map(fn, jobs, threads: int) -> list:
    """``[fn(*job) for job in jobs]``, on ``threads`` threads of :func:`pool`
    when more than one (in this thread alone for one thread or one job)."""
    if threads <= 1 or len(jobs) < 2:
        return [fn(*job) for job in jobs]
    return list(pool(threads).map(lambda job: fn(*job), jobs))
