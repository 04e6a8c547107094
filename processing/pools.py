"""Thread pools kept for the process's life, one per thread count: what the
chains use to run NumPy, OpenCV and compiled work that releases the GIL on
several cores within one frame (:func:`thread_map`, :func:`pool`).

Before, three modules kept pools of their own and random dots' spline
sampling made one per call (twice a PIV pass): under cProfile the thread
starts looked like 15-17 ms of a 512^2 frame, but timed without it the dots'
frame was 227-236 ms either way.  A forked child inherits the pools but not
their threads, so they are forgotten in the child (it makes its own).

The calling thread works too, and the jobs are taken one at a time by whichever
worker is free (:func:`slot_map`): a worker that the OS sets aside (on 2 cores
beside the window's process, whose threads win the CPU) holds up only the job
it has, not a fixed share of the frame.  Before, ``threads`` pool threads each
took a fixed slice while the caller waited: the dots' live worker process on
two threads used 1.2 of the 1.66 cores the window left it, its main thread
blocked 51 ms of a 96 ms frame.
"""

from __future__ import annotations

import itertools
import os
import threading
from concurrent.futures import ThreadPoolExecutor

__all__ = ["pool", "slot_map", "thread_map"]

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


def slot_map(fn, jobs, threads: int) -> list:
    """``[fn(slot, *job) for job in jobs]``, in order, on ``threads`` workers: this thread (slot 0)
    and ``threads - 1`` threads of :func:`pool` (slots 1, 2, ...), each taking the next job not yet
    taken until none is left.  ``slot``: which worker runs the job (no two run the same slot at
    once), for scratch arrays or FFTW plans of the worker's own.  An exception is raised here once
    every worker has stopped (the jobs already taken are finished)."""
    jobs = list(jobs)
    n = len(jobs)
    if threads <= 1 or n < 2:
        return [fn(0, *job) for job in jobs]
    out = [None] * n
    taken = itertools.count()  # one C call a job: atomic under the GIL

    def work(slot):
        for i in taken:
            if i >= n:
                return
            out[i] = fn(slot, *jobs[i])

    helpers = [pool(threads).submit(work, slot) for slot in range(1, min(threads, n))]
    try:
        work(0)
    finally:
        # a helper not started yet is let go; one that started may still be inside a job (its
        # slot's scratch): waited for
        errors = [h.exception() for h in helpers if not h.cancel()]
    for exc in errors:
        if exc is not None:
            raise exc
    return out


def thread_map(fn, jobs, threads: int) -> list:
    """``[fn(*job) for job in jobs]``, in order, shared among ``threads`` workers as
    :func:`slot_map` shares them (this thread alone for one thread or one job)."""
    return slot_map(lambda _slot, *job: fn(*job), jobs, threads)
