"""A worker process's maps handed to the run's process through shared memory, in blocks used again.

A 1024^2 frame's maps are 13 MB. Pickled through the pool's pipe they cost
7.7 ms a frame of the parent's core; a fresh shared-memory block per frame
costs what the kernel spends handing out 13 MB of new pages, zeroed: on a
1,000-frame run, a quarter of both cores' time went to zeroing tmpfs pages
(``perf``: ``clear_page_erms`` under ``shmem_get_folio_gfp``), and the
run slowed from its first hundred frames to its last. So a worker keeps its
blocks mapped and fills them again once the run's process has written them:

- the worker (:class:`SharedFrame.put`) copies a frame's maps into a block
  of its own that is free (first byte :data:`FREE`), or into a new one, and
  marks it :data:`FILLED`;
- the run's process (:meth:`SharedFrame.take`, through its
  :class:`ParentBlocks`) maps a block the first time it sees it, removes its
  name from /dev/shm at once (nothing is left there whatever happens next;
  the memory lives as long as someone maps it) and keeps the mapping; once
  the writer is done with the maps and no view of them is left, it marks
  the block :data:`FREE` for its worker.

Blocks are named after the run (:func:`shm_name`), and registered with
multiprocessing's resource tracker when made, so that those of a run that
died are freed with its workers.
"""

from __future__ import annotations

import dataclasses
import os
import threading
import uuid
import weakref

import numpy as np

__all__ = ["SharedFrame", "ParentBlocks", "shm_name", "set_run_pid", "unlink_left_blocks", "MAKING_BLOCK", "FREE",
           "FILLED"]

#: First byte of a block: free for its worker to fill / filled, waiting for the run's process
FREE, FILLED = 0, 1
#: The maps start this far into a block (the flag before them; 64: a cache line, aligned maps)
HEADER_BYTES = 64

#: Held while a worker creates a shared-memory block (:meth:`SharedFrame.put`): between the
#: file's creation in /dev/shm and its registration with the resource tracker, a worker that
#: ends with its run (app.batch.parallel's watch thread) would leave the block for good.
MAKING_BLOCK = threading.Lock()

#: the run's process, in one of its pool's workers (:func:`set_run_pid`); None elsewhere
_run_pid = None


def set_run_pid(run_pid: int) -> None:
    """In a worker process: the run whose process is ``run_pid`` names the blocks made here."""
    global _run_pid
    _run_pid = run_pid


def shm_name(run_pid: int) -> str:
    """A new shared-memory block's name for the run whose process is
    ``run_pid``: ``tdf<pid>_<random>`` (in /dev/shm on Linux), so that what a
    run holds can be told apart from any other program's; short enough for
    macOS (31 characters)."""
    return f"tdf{run_pid}_{uuid.uuid4().hex[:10]}"


def unlink_left_blocks(run_pid: int) -> int:
    """In the run's process, once its pool's workers have ended: remove the blocks named after the
    run (:func:`shm_name`) still in /dev/shm, and return how many.  The run unlinks every block it
    takes (:meth:`ParentBlocks.attach`), so these are a worker's that was killed (SIGKILL) between a
    block's creation and its registration with the resource tracker, which :data:`MAKING_BLOCK`
    closes for the worker's own exit but not for a signal: one 832 KB block stayed after a suite
    run whose tests kill workers (6 Dec 2026).  Nothing where there is no /dev/shm."""
    import glob
    from multiprocessing import shared_memory

    removed = 0
    for path in glob.glob(os.path.join("/dev/shm", f"tdf{int(run_pid)}_*")):
        name = os.path.basename(path)
        try:
            block = shared_memory.SharedMemory(name=name)
        except (OSError, ValueError):  # gone already, or made but never sized (killed first)
            try:
                os.unlink(path)
            except OSError:
                continue
        else:
            block.close()
            try:
                block.unlink()  # (and out of the resource tracker's list)
            except OSError:
                continue
        removed += 1
    return removed


class _WorkerBlocks:
    """The blocks this process made for the run ``run_key``, kept mapped (a Dask
    worker runs several tasks at once in threads: :meth:`claim` is locked)."""

    def __init__(self, run_key):
        self.run_key = run_key
        self.blocks = []
        self._lock = threading.Lock()

    def claim(self, nbytes: int):
        """A block of at least ``nbytes`` after the header, free, now marked FILLED."""
        with self._lock:
            for block in self.blocks:
                if block.size >= HEADER_BYTES + nbytes and block.buf[0] == FREE:
                    block.buf[0] = FILLED
                    return block
            from multiprocessing import shared_memory

            # named after the run (a pool worker's parent is the app's fork server, not the run)
            run_pid = _run_pid if _run_pid is not None else os.getppid()
            with MAKING_BLOCK:  # created and registered with the resource tracker, or not at all
                block = shared_memory.SharedMemory(name=shm_name(run_pid), create=True,
                                                   size=HEADER_BYTES + max(1, nbytes))
            block.buf[0] = FILLED
            self.blocks.append(block)
            return block

    def close(self) -> None:
        for block in self.blocks:
            try:
                block.close()
            except BufferError:
                pass
        self.blocks = []


_worker_blocks = None
_worker_blocks_lock = threading.Lock()


def _blocks_for(run_key) -> _WorkerBlocks:
    """This process's blocks for the run ``run_key`` (a Dask worker outlives runs: another key
    drops the last run's blocks, which that run's process has unlinked)."""
    global _worker_blocks
    with _worker_blocks_lock:
        if _worker_blocks is None or _worker_blocks.run_key != run_key:
            if _worker_blocks is not None:
                _worker_blocks.close()
            _worker_blocks = _WorkerBlocks(run_key)
        return _worker_blocks


@dataclasses.dataclass
class SharedFrame:
    """An :class:`~app.batch.writer.OutputFrame` whose maps wait in a shared-memory
    block (worker processes on this machine): copied in once by the worker, and
    written to OUT.h5 by the parent straight from the block (no copy out).
    ``layout``: ``(name, shape, dtype, offset)`` of each map in the block."""

    name: str
    layout: tuple
    rest: object

    @classmethod
    def put(cls, frame, run_key=None) -> "SharedFrame":
        """In a worker: ``frame``'s maps copied into a free block of this process's
        blocks for the run ``run_key`` (a new block when none is free)."""
        arrays = [(name, np.ascontiguousarray(a)) for name, a in frame.maps.items()]
        block = _blocks_for(run_key).claim(sum(a.nbytes for _, a in arrays))
        layout, offset = [], HEADER_BYTES
        for name, a in arrays:
            np.ndarray(a.shape, a.dtype, buffer=block.buf, offset=offset)[...] = a
            layout.append((name, a.shape, a.dtype.str, offset))
            offset += a.nbytes
        return cls(block.name, tuple(layout), dataclasses.replace(frame, maps={}))

    def take(self, blocks: "ParentBlocks"):
        """In the run's process: the OutputFrame, its maps views of the block; its
        ``release`` (``OutputFrame.done``, once written) hands the block back to its
        worker, unless a view of the maps outlived the write."""
        block = blocks.attach(self.name)
        end = max((off + int(np.prod(shape, dtype=np.int64)) * np.dtype(dt).itemsize
                   for _, shape, dt, off in self.layout), default=HEADER_BYTES)
        # one array over the maps' bytes: every view of them has it as its base
        whole = np.ndarray((end,), np.uint8, buffer=block.buf)
        maps = {}
        for name, shape, dt, off in self.layout:
            size = int(np.prod(shape, dtype=np.int64)) * np.dtype(dt).itemsize
            maps[name] = whole[off:off + size].view(np.dtype(dt)).reshape(shape)
        views = weakref.ref(whole)
        del whole
        return dataclasses.replace(self.rest, maps=maps, release=lambda: _hand_back(block, views))

    def discard(self, blocks: "ParentBlocks") -> None:
        """In the run's process: nobody will take this frame; its block goes back to its worker."""
        try:
            block = blocks.attach(self.name)
        except OSError:
            return
        block.buf[0] = FREE


def _hand_back(block, views) -> None:
    if views() is None:  # no view of the maps left: the worker may fill the block again
        try:
            block.buf[0] = FREE
        except (TypeError, ValueError):  # the run ended first (ParentBlocks.close): nobody fills it
            pass


class ParentBlocks:
    """The run's process's mappings of its workers' blocks, kept for the run: a block
    filled again needs no new mapping (each fresh mapping of 13 MB costs a page
    fault per 4 KB page on first read). :meth:`close` when the run ends."""

    def __init__(self):
        self._blocks = {}
        #: blocks still viewed by someone when the run ended (their names are gone already):
        #: kept mapped until this process ends
        self.still_mapped = []

    def attach(self, name: str):
        block = self._blocks.get(name)
        if block is None:
            from multiprocessing import shared_memory

            # the worker registered the block with the resource tracker it shares with this
            # process; unlink() here unregisters it (a block left behind by a crash is removed
            # when this process ends)
            block = shared_memory.SharedMemory(name=name)
            block.unlink()
            self._blocks[name] = block
        return block

    def close(self) -> None:
        for block in self._blocks.values():
            try:
                block.close()
            except BufferError:  # a view of the maps outlived the run (kept by a caller)
                self.still_mapped.append(block)
        self._blocks = {}
