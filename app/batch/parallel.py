"""The frames of one batch run, reconstructed in order: here, over processes, or on a Dask cluster.

:func:`frame_results` is what :func:`app.batch.engine.run_process` loops
over: ``(item, outcome)`` pairs in input order, where ``outcome()`` returns
the frame's :class:`processing.reconstruct.Result` (here, on the GPU) or
:class:`app.batch.writer.OutputFrame` (made in a worker: NaN mask and
compression already done, so the parent only writes), or raises what
reconstructing it raised. Three ways to get them, same heights:

- **serial** (``workers=1``, or few frames): one Reconstructor in this
  process, frame after frame (what the engine always did);
- **processes** (``workers=N``): ``N`` worker processes, each with its own
  Reconstructor and ``cores // N`` FFT threads;
- **Dask** (``dask="local:N"`` or ``"tcp://HOST:8786"``): the same work as
  tasks on a Dask cluster (docs/cluster.md).

Temporal unwrapping links each frame to the one before, so the selection is
cut into contiguous *chunks*. A worker starts its chunk from the previous
chunk's last frame (the one-frame overlap, unwrapped in space and only on
the decimated grid), keeps the :class:`~processing.reconstruct.SeriesState`
that frame left and goes on in time. Before a chunk's frames are handed on,
that start state is checked against the state the previous chunk ended
with (:meth:`SeriesState.agrees_with`: same valid samples, same unwrapped
phase); a chunk that disagrees (spatial unwrapping alone was ambiguous
there, e.g. an island cut off by a masked ring whose phase is beyond pi) is
redone from the previous chunk's end state, i.e. exactly as a serial run
continues. Frames come out in order; at most ``workers + 1`` chunks are in
flight, and chunks are sized so that they hold no more than
an eighth of the memory available of results (:func:`default_memory_budget_bytes`;
never the whole recording).
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import logging
import math
import os
import threading
import time
import uuid
import warnings
from pathlib import Path
from typing import Optional

import numpy as np

from app.batch.interruptible import call_interruptibly
from app.batch.shm_results import MAKING_BLOCK, ParentBlocks, SharedFrame, set_run_pid, unlink_left_blocks
from app.batch.writer import output_frame
from app.files import imageio
from processing.errors import TirdeflectError

__all__ = ["available_cores", "fft_threads", "frame_results", "process_chunk", "plan_chunks", "stop_requested",
           "ReconstructorSpec", "Chunk", "ChunkOutcome", "AUTO_PARALLEL_MIN_FRAMES",
           "MEMORY_BUDGET_BYTES", "default_memory_budget_bytes"]

log = logging.getLogger(__name__)

#: Without --workers, runs shorter than this stay serial: starting a worker
#: process (imports, FFT plans) costs about a second, 50 frames of 1024^2.
AUTO_PARALLEL_MIN_FRAMES = 64

#: Results (height, slopes, valid) of all chunks in flight stay below this share of
#: the memory available when a run starts (:func:`default_memory_budget_bytes`), and within
#: MEMORY_BUDGET_BYTES .. MEMORY_BUDGET_MAX_BYTES.
MEMORY_SHARE = 1 / 8
MEMORY_BUDGET_BYTES = 1 << 30
MEMORY_BUDGET_MAX_BYTES = 16 << 30

#: Chunks per worker aimed at (load balance), as long as chunks keep at least
#: MIN_CHUNK_FRAMES frames (each chunk costs one extra decimated frame).
CHUNKS_PER_WORKER = 4

#: Frames sent to the GPU at once with --device cuda (the issue's prototype: 32 frames of 1024^2).
GPU_BATCH = 32

#: Times a run replaces its worker processes after one died.
MAX_POOL_RESTARTS = 2

#: Worker processes hand results over in shared memory (False: pickled through pipes).
SHARED_MEMORY = True
MIN_CHUNK_FRAMES = 8


def default_memory_budget_bytes() -> int:
    """Bytes the results of the chunks in flight may take: an eighth of the memory
    available now (Linux ``MemAvailable``), at least 1 GiB, at most 16 GiB.

    Longer chunks cost less (each starts with one extra frame, and a video's
    worker decodes from the keyframe before it): at 1024^2 (13 MB of results a
    frame) and 2 workers, 1 GiB allows 19-frame chunks, a 24 GB machine's
    eighth 52; with 16 workers 4 and (on 128 GB) 68."""
    available = None
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    available = int(line.split()[1]) * 1024
                    break
    except (OSError, ValueError, IndexError):
        pass
    if available is None:
        return MEMORY_BUDGET_BYTES
    return int(min(MEMORY_BUDGET_MAX_BYTES, max(MEMORY_BUDGET_BYTES, available * MEMORY_SHARE)))


def available_cores() -> int:
    """Cores this process may run on (affinity / cgroup-aware where Python can tell)."""
    count = getattr(os, "process_cpu_count", None)  # Python >= 3.13
    if count is not None:
        n = count()
    else:
        try:
            n = len(os.sched_getaffinity(0))
        except (AttributeError, OSError):
            n = os.cpu_count()
    return max(1, int(n or 1))


def fft_threads(workers: int, cores: Optional[int] = None) -> int:
    """FFTW threads per frame so that ``workers x threads`` fits the cores."""
    cores = available_cores() if cores is None else cores
    return max(1, cores // max(1, workers))


# ----------------------------------------------------------------- tasks


@dataclasses.dataclass(frozen=True)
class ReconstructorSpec:
    """What a worker needs to build its own Reconstructor (picklable, sent with each task).

    ``options``: the engine's Reconstructor's :attr:`processing.Reconstructor.options`
    (the one :class:`processing.ReconstructOptions` value, refinement resolved);
    the worker changes only its ``threads``.
    ``carriers`` are the ones the engine found on the reference, so every
    worker demodulates exactly as a serial run. ``threads`` None: the worker
    picks its cores / the tasks that run at once on its machine, which
    ``tasks_per_host`` gives for a Dask cluster (``(host, worker threads)``
    pairs from the scheduler: ``dask worker --nworkers 16 --nthreads 1`` is
    16 processes of one task each on one machine, and each must use one
    core, not all 16).
    """

    key: str
    reference: np.ndarray
    geometry: object
    options: object  # processing.ReconstructOptions
    carriers: object
    threads: Optional[int] = None
    shared_memory: bool = False
    compression: Optional[str] = None
    tasks_per_host: tuple = ()


@dataclasses.dataclass(frozen=True)
class Chunk:
    """Frames ``first..last`` (sequence indices, inclusive, every ``step``-th) of ``paths``.

    ``overlap``: sequence index of the previous chunk's last frame, processed
    first (decimated grid) to start temporal unwrapping; None for the first
    chunk. ``redo``: start from ``start`` instead (the previous chunk's end
    state; None = in space, as after ``reset_series``), no overlap frame.
    ``items``: the frames themselves (overlap frame first when there is one),
    read by the client and sent with the task, for workers that cannot read
    ``paths``.
    """

    index: int
    paths: tuple
    first: int
    last: int
    step: int
    overlap: Optional[int]
    redo: bool = False
    start: object = None
    items: Optional[tuple] = None

    @property
    def label(self) -> str:
        return f"chunk {self.index} (frames {self.first}..{self.last})"


@dataclasses.dataclass
class ChunkOutcome:
    """A chunk's results: ``frames`` is a list of ``(item, (OutputFrame | None, FrameOutcome))``
    (:class:`app.batch.writer.OutputFrame`: the frame as OUT.h5 stores it, made in the
    worker; items without their image), or ``(None, TirdeflectError)``: reading failed
    there, nothing after it;
    ``start``/``end`` the series states after the overlap frame (or the given start) and
    after the last frame; ``pid`` and ``host`` of the worker that computed it.
    ``stopped``: the run was ending (:func:`stop_requested`), so the chunk ended after the frame it
    was measuring, its ``frames`` short: nobody writes them (the run's process frees their memory)."""

    index: int
    start: object
    frames: list
    end: object
    pid: int
    host: str
    stopped: bool = False


_RECONSTRUCTORS: dict = {}
#: In a worker process of the local pool: the run's "stop" event (:func:`_init_worker`); None elsewhere (Dask)
_STOP = None
#: Runs (``ReconstructorSpec.key``) whose FFTW wisdom this process has stored.
_WISDOM_STORED: set = set()


def _reconstructor(spec: ReconstructorSpec):
    """This process's Reconstructor of ``spec`` (built once per run and process)."""
    recon = _RECONSTRUCTORS.get(spec.key)
    if recon is not None:
        return recon
    _RECONSTRUCTORS.clear()  # a long-lived Dask worker keeps only the current run's
    reuse_freed_memory()
    threads = spec.threads
    if threads is None:
        threads = fft_threads(_tasks_on_this_machine(spec.tasks_per_host))
    import cv2

    cv2.setNumThreads(threads)
    # OpenPIV's compiled correlations (random dots) start their thread pool on first use, one
    # thread per core unless told: one worker's share instead, as OpenCV's and FFTW's
    os.environ.setdefault("RAYON_NUM_THREADS", str(threads))
    from app.files import cache
    from processing import Reconstructor

    cache.restore_fftw_wisdom()
    recon = Reconstructor(spec.reference, spec.geometry, spec.options.replace(threads=threads),
                          carriers=spec.carriers)
    _RECONSTRUCTORS[spec.key] = recon
    return recon


def reuse_freed_memory() -> bool:
    """Let this process's C allocator keep large freed blocks for the next array.

    A Dask nanny starts its workers with ``MALLOC_TRIM_THRESHOLD_=65536``
    (``distributed.nanny.pre-spawn-environ``, to hand memory back to the
    system quickly). Setting any malloc threshold switches off glibc's
    adaptive one, so every array above 128 kB (a 1024^2 map is 8 MB) is a
    fresh ``mmap`` that the kernel zero-fills page by page, and is unmapped
    again when freed: a 1024^2 frame cost 345 ms instead of 100 ms (CPU 425
    against 148 ms) in a process started that way. Here the thresholds are
    set back to what the adaptive scheme reaches for such arrays: blocks up
    to 32 MB (glibc's largest) come from the heap and are reused, and the
    heap is trimmed only above 256 MB free. Only when such a variable is set
    (a Dask worker, or a user's environment) and on glibc; True when set."""
    if not any(k in os.environ for k in ("MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_THRESHOLD_",
                                         "MALLOC_TOP_PAD_", "MALLOC_MMAP_MAX_")):
        return False
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        m_trim_threshold, m_mmap_threshold = -1, -3  # <malloc.h>
        ok = libc.mallopt(m_mmap_threshold, 32 << 20) == 1
        return bool(libc.mallopt(m_trim_threshold, 256 << 20) == 1 and ok)
    except (OSError, AttributeError):  # not glibc (macOS, musl): nothing to undo
        return False


def _tasks_on_this_machine(tasks_per_host: tuple = ()) -> int:
    """Tasks that run at once on this machine: in a Dask worker, all the
    cluster's worker threads on its host (``tasks_per_host``, else its own
    threads); 1 outside Dask."""
    try:
        from distributed import get_worker

        worker = get_worker()
    except (ImportError, ValueError):
        return 1
    host = _host_of(worker.address)
    on_host = sum(n for h, n in tasks_per_host if h == host)
    if on_host:
        return on_host
    try:
        return max(1, int(worker.state.nthreads))
    except AttributeError:
        return 1


def _host_of(address: str) -> str:
    """``tcp://10.0.0.5:40123`` -> ``10.0.0.5``."""
    from distributed.comm import get_address_host

    return get_address_host(address)


def _dask_tasks_per_host(client) -> tuple:
    """``((host, worker threads on it), ...)`` of the cluster behind ``client``."""
    counts: dict = {}
    for address, threads in client.nthreads().items():
        host = _host_of(address)
        counts[host] = counts.get(host, 0) + int(threads or 1)
    return tuple(sorted(counts.items()))


def _in_dask() -> bool:
    try:
        from distributed import get_worker

        get_worker()
        return True
    except (ImportError, ValueError):
        return False


def stop_requested() -> bool:
    """Is the run of this worker process ending (Ctrl-C, an error: :meth:`_Pool.shutdown`), so
    that a chunk must end after the frame it is measuring? Always False outside the local pool
    (a Dask task asks its run's :class:`_DaskStop`)."""
    return _STOP is not None and _STOP.is_set()


#: How often a Dask task asks the scheduler whether its run is ending, seconds (a round trip each)
DASK_STOP_POLL_S = 0.25


def _dask_stop_name(run_key: str) -> str:
    return f"tirdeflect-stop-{run_key}"


class _DaskStop:
    """In a Dask task: has the run ``run_key`` ended (Ctrl-C, an error: its client set the run's
    ``distributed.Event``, :func:`_stop_dask_tasks`)? Asked at most every :data:`DASK_STOP_POLL_S`;
    a scheduler that cannot be asked any more means the run has gone. Cancelling a Dask future
    does not stop a task that runs: without this a Ctrl-C on ``--dask`` waited for every chunk
    running to end (12 frames of 0.25 s each after the signal, 7 Dec 2026)."""

    def __init__(self, run_key: str):
        from distributed import Event

        self._event = Event(_dask_stop_name(run_key))
        self._asked = -math.inf
        self._ending = False

    def __call__(self) -> bool:
        now = time.monotonic()
        if not self._ending and now - self._asked >= DASK_STOP_POLL_S:
            self._asked = now
            try:
                self._ending = bool(self._event.is_set())
            except Exception:  # noqa: BLE001 - the scheduler has gone: so has the run
                self._ending = True
        return self._ending


def _stop_dask_tasks(client, run_key: str) -> None:
    """In the run's process: the chunks its Dask tasks are measuring end after their current frame."""
    try:
        from distributed import Event

        Event(_dask_stop_name(run_key), client=client).set()
    except Exception as exc:  # noqa: BLE001 - a cluster already gone: nothing runs there
        log.debug("could not tell the Dask tasks to stop (%s)", exc)


def measure(reconstruct, item, ref_shape, grid: str):
    """``(Result, OK)`` or ``(None, why the frame is invalid)`` of one input frame,
    as the engine's serial loop measures it (:mod:`app.batch.frame_status`)."""
    from app.batch.frame_status import measure_frame, outcome_of_error

    if item.error is not None:
        outcome = outcome_of_error(item.error)
        if outcome is None:  # not the frame's fault (a full disk): the run stops
            raise item.error
        return None, outcome
    return measure_frame(reconstruct, item.image, ref_shape, grid)


def process_chunk(spec: ReconstructorSpec, chunk: Chunk) -> ChunkOutcome:
    """Reconstruct one chunk in this process (a pool worker or a Dask task); see the module doc.

    Each frame is measured as in the engine's serial loop, and a frame that
    could not be measured ends the series (no temporal unwrapping across a hole).
    Between two frames, a run that is ending (:func:`stop_requested`) ends the chunk
    (``stopped``): its worker is free at once, not after the chunk's last frame.
    """
    recon = _reconstructor(spec)
    shape = tuple(np.shape(spec.reference))
    if chunk.redo or chunk.overlap is None:
        recon.restore_series(chunk.start)
        first = chunk.first
    else:
        recon.reset_series()
        first = chunk.overlap
    if chunk.items is not None:
        frames = iter(chunk.items)
    else:
        frames = imageio.iter_frames(list(chunk.paths), first=first, last=chunk.last, step=chunk.step,
                                     errors="yield", losses_from=chunk.overlap)
    out = []
    start = None
    ending = _DaskStop(spec.key) if _in_dask() else stop_requested
    stopped = ending()
    try:
        if first != chunk.first and not stopped:  # the overlap frame: only its series state is kept
            result, _ = measure(recon, next(frames), shape, "decimated")
            if result is None:
                recon.reset_series()
        start = recon.series_state()
        for item in frames:
            stopped = stopped or ending()
            if stopped:
                break
            result, outcome = measure(recon, item, shape, spec.options.grid)
            if result is None:
                recon.reset_series()
            else:  # the per-pixel part of writing it (NaN mask, compression) is done here
                result = output_frame(result, spec.compression)
                if spec.shared_memory:
                    result = SharedFrame.put(result, spec.key)
            out.append((dataclasses.replace(item, image=None), (result, outcome)))
    except TirdeflectError as exc:  # a whole file became unreadable: frames before it stand
        if _in_dask():
            import socket

            exc = type(exc)(f"{exc} (read on {socket.gethostname()}; workers that do not see the "
                            f"input files at this path need --dask-send-frames, docs/cluster.md)")
        out.append((None, exc))
    if spec.options.planner_effort == "FFTW_MEASURE" and spec.key not in _WISDOM_STORED and not stopped:
        from app.files import cache

        cache.store_fftw_wisdom()
        _WISDOM_STORED.add(spec.key)
    import socket

    return ChunkOutcome(index=chunk.index, start=start, frames=out, end=recon.series_state(),
                        pid=os.getpid(), host=socket.gethostname(), stopped=stopped)


# ----------------------------------------------------------------- planning


def plan_chunks(selected: int, *, first: int, step: int, paths, workers: int, frame_bytes: int,
                chunk_frames: Optional[int] = None,
                memory_budget_bytes: Optional[int] = None, keyframes=None) -> list:
    """Contiguous chunks of the ``selected`` frames ``first, first + step, ...``.

    Chunk length: ``chunk_frames`` if given, else about ``selected / (4 workers)``,
    at least 8, and small enough that ``workers + 2`` chunks of results
    (``frame_bytes`` each frame) fit ``memory_budget_bytes`` (default
    :func:`default_memory_budget_bytes`).

    ``keyframes``: the frames a video decoder can start at (sequence indices;
    None: any). Without ``chunk_frames``, each chunk then ends on a keyframe
    (its last frame is the next chunk's overlap frame, where that chunk's
    worker starts decoding) when one lies in its second half, so that a
    worker decodes no frame it does not use (a 12-frame group of pictures otherwise costs up to 11
    decoded frames per chunk, 47 ms each for FFV1 at 1024^2).
    """
    if memory_budget_bytes is None:
        memory_budget_bytes = default_memory_budget_bytes()
    if chunk_frames is None:
        size = max(MIN_CHUNK_FRAMES, math.ceil(selected / (CHUNKS_PER_WORKER * workers)))
        size = min(size, max(1, memory_budget_bytes // ((workers + 2) * max(1, frame_bytes))))
    else:
        size = int(chunk_frames)
    size = max(1, min(size, selected))
    if keyframes is not None and chunk_frames is None:
        starts = _starts_after_keyframes(selected, size, first, step, keyframes)
    else:
        starts = list(range(0, selected, size))
    chunks = []
    for index, k0 in enumerate(starts):
        k1 = starts[index + 1] if index + 1 < len(starts) else selected
        chunks.append(Chunk(index=index, paths=tuple(paths), first=first + k0 * step,
                            last=first + (k1 - 1) * step, step=step,
                            overlap=None if k0 == 0 else first + (k0 - 1) * step))
    return chunks


def _starts_after_keyframes(selected: int, size: int, first: int, step: int, keyframes) -> list:
    """Chunk starts (selected-frame counts) whose overlap frame is a keyframe:
    each chunk as long as it can be, at most ``size`` (the memory budget) and
    at least half of it, else exactly ``size``."""
    keys = set(int(k) for k in keyframes)
    out = [0]
    while out[-1] + size < selected:
        prev = out[-1]
        found = [j for j in range(prev + size, prev + max(1, size // 2) - 1, -1)
                 if first + (j - 1) * step in keys]
        out.append(found[0] if found else prev + size)
    return out


def _keyframes(inputs) -> Optional[tuple]:
    """The keyframes of a single video input (its frame indices are the
    sequence indices), else None."""
    from app.files import formats

    if len(inputs) != 1 or formats.kind_of(Path(inputs[0])) != "video":
        return None
    try:
        with formats.open_source(Path(inputs[0])) as source:
            return source.keyframes()
    except Exception:  # noqa: BLE001 - planning only: the workers report a bad file themselves
        return None


def _states_agree(start, end) -> bool:
    if start is None or end is None:
        return start is None and end is None
    return start.agrees_with(end)


def _given(value):
    return value


def _wait(future, timeout_s: float) -> bool:
    """Wait up to ``timeout_s`` for a pool or Dask future; True when it is done.
    (Not ``result(timeout=)``: on a Dask future each timeout cancels the
    gathering of its result, measured to lose it after a few.)"""
    import concurrent.futures

    if isinstance(future, concurrent.futures.Future):
        concurrent.futures.wait([future], timeout=timeout_s)
    else:
        from distributed import wait

        import asyncio

        try:
            wait(future, timeout=timeout_s)
        except (TimeoutError, asyncio.TimeoutError):
            pass
    return future.done()


def _discard(frames, blocks) -> None:
    """Hand back the shared memory of results nobody will take (``blocks``: the run's
    :class:`~app.batch.shm_results.ParentBlocks`)."""
    for item, payload in frames:
        if item is not None and isinstance(payload[0], SharedFrame):
            payload[0].discard(blocks)


def _discard_finished(futures, blocks) -> None:
    """Hand back the shared memory of the chunks among ``futures`` that finished but that nobody
    will take (cancelled too late, or submitted again)."""
    for future in futures:
        try:
            if future.done() and not future.cancelled() and future.exception() is None:
                _discard(future.result().frames, blocks)
        except Exception:  # a Dask future after its client closed: nothing in shared memory
            pass


# ----------------------------------------------------------------- runners


class _Serial:
    """The engine's Reconstructor, frame after frame, each measured when the engine asks."""

    def __init__(self, job, reconstruct, reference, paths):
        self.attrs = {"workers": 1}
        self._frames = imageio.iter_frames(paths, first=job.first, last=job.last, step=job.step,
                                           errors="yield")
        self._measure = functools.partial(measure, reconstruct, ref_shape=tuple(reference.shape),
                                          grid=job.grid)

    def __iter__(self):
        return self

    def __next__(self):
        item = next(self._frames)
        return item, functools.partial(call_interruptibly, self._measure_logged, item)

    def _measure_logged(self, item):
        log.debug("frame %d (%s): measuring", item.sequence_index, item.label)
        return self._measure(item)

    def close(self):
        self._frames.close()


def _out_of_gpu_memory(exc: BaseException) -> bool:
    """CuPy's ``cupy.cuda.memory.OutOfMemoryError`` (or cuFFT's allocation failure),
    told by name: this module does not import CuPy."""
    return type(exc).__name__ == "OutOfMemoryError" or "CUFFT_ALLOC_FAILED" in str(exc)


class _GpuBatches:
    """A Reconstructor with ``device="cuda"`` of its own (the engine's resets its
    series after a hole; this one is ahead by a batch): frames read and sent to
    the GPU ``GPU_BATCH`` at a time (processing/gpu.py), results in order."""

    def __init__(self, job, reconstruct, reference, geometry, paths):
        from processing import Reconstructor

        # the engine's options, on the GPU (its refinement was chosen for device "cuda")
        self._recon = Reconstructor(reference, geometry, reconstruct.options.replace(device="cuda"),
                                    carriers=reconstruct.carriers)
        why = self._recon.gpu_fallback
        self.attrs = {"device": "cuda" if why is None else f"cpu ({why})", "gpu_batch": GPU_BATCH}
        if why is not None:
            log.warning("--device cuda: frames go through the CPU: %s", why)
        self._shape = tuple(reference.shape)
        self._grid = job.grid
        self._frames = imageio.iter_frames(paths, first=job.first, last=job.last, step=job.step,
                                           errors="yield")
        self._ready = collections.deque()
        self._read_error = None
        self._batch_size = GPU_BATCH  # halved each time the GPU runs out of memory
        self._again = collections.deque()  # frames read for a batch the GPU could not hold

    def __iter__(self):
        return self

    def _plain(self, item) -> bool:
        """A frame the GPU can take with the others (read, right shape, not uniform)."""
        from processing.banding import bands_of

        image = item.image
        if not (item.error is None and image is not None and image.shape == self._shape
                and image.min() != image.max()):
            return False
        bands = bands_of(self._recon, image)  # banded frames are named (and evened) on the CPU (frame_status)
        return bands is None or not bands.flagged

    def _one_by_one(self, items):
        for it in items:
            result, outcome = measure(self._recon, it, self._shape, self._grid)
            if result is None:
                self._recon.reset_series()  # no temporal unwrapping across a hole
            self._ready.append((it, functools.partial(_given, (result, outcome))))

    def _batch(self) -> bool:
        """Read up to a batch of frames and reconstruct them; False at the end of the frames."""
        from app.batch.frame_status import FrameOutcome

        items, last_plain = [], True
        while len(items) < self._batch_size:
            try:
                item = self._again.popleft() if self._again else next(self._frames)
            except StopIteration:
                break
            except TirdeflectError as exc:  # a whole file unreadable: the frames before it first
                self._read_error = exc
                break
            items.append(item)
            last_plain = self._plain(item)  # (its bands judged once)
            if not last_plain:
                break  # measured on its own after the ones before it
        if not items:
            return False
        plain = items if last_plain else items[:-1]
        state = self._recon.series_state()
        try:
            results = self._recon.batch([it.image for it in plain], grid=self._grid, essentials=True)
            if any(not np.asarray(r.valid).any() for r in results):
                raise TirdeflectError("a frame without valid samples")
        except Exception as exc:
            self._recon.restore_series(state)
            if _out_of_gpu_memory(exc):
                if self._batch_size == 1:
                    raise TirdeflectError(
                        f"the GPU has too little free memory for even one frame ({exc}); close other "
                        f"programs using it, or run without --device cuda (the CPU)") from exc
                # the same frames again, in batches half as large, the series from the same state
                self._batch_size //= 2
                self.attrs["gpu_batch"] = self._batch_size
                log.warning("the GPU ran out of memory with %d frames at once; going on with %d",
                            len(plain), self._batch_size)
                self._again.extendleft(reversed(items))
                return True
            if not isinstance(exc, TirdeflectError):
                raise
            self._one_by_one(items)  # one frame at a time from the batch's start: each frame's own outcome
            return True
        from processing.live_view import saturation_pct

        for it, r in zip(plain, results):
            outcome = FrameOutcome(saturated_pct=saturation_pct(it.image), hot_pixels=r.hot_pixels)
            self._ready.append((it, functools.partial(_given, (r, outcome))))
        self._one_by_one(items[len(plain):])
        return True

    def __next__(self):
        while not self._ready and self._read_error is None:
            if not self._batch():  # the end of the frames
                break
        if self._ready:
            return self._ready.popleft()
        if self._read_error is not None:
            exc, self._read_error = self._read_error, None
            self._frames = iter(())
            raise exc
        raise StopIteration

    def close(self):
        close = getattr(self._frames, "close", None)
        if close is not None:
            close()


class _DeferredInterrupt:
    """Ctrl-C during a parallel run becomes KeyboardInterrupt at the next frame
    boundary (between two frames written; a second Ctrl-C at once). Raised
    wherever the signal lands, it can hit a garbage-collection callback of the
    process pool's machinery, where Python swallows it ("Exception ignored")
    and the run goes on (seen in 1 of 6 tries). Only in the main thread and
    only over Python's own handler (a GUI keeps its own)."""

    def __init__(self):
        import signal
        import threading

        self.hit = False
        self._old = None
        if (threading.current_thread() is threading.main_thread()
                and signal.getsignal(signal.SIGINT) is signal.default_int_handler):
            self._old = signal.signal(signal.SIGINT, self._handler)

    def _handler(self, signum, frame):
        if self.hit:
            raise KeyboardInterrupt
        self.hit = True

    def check(self):
        if self.hit:
            raise KeyboardInterrupt

    def restore(self):
        if self._old is not None:
            import signal

            signal.signal(signal.SIGINT, self._old)
            self._old = None


class _Chunked:
    """Chunks in flight on an executor (``submit(fn, *args) -> future``), frames out in order.

    ``sources``: the input paths the tasks were given -> the paths as the user
    named them (Dask workers may see the files under other names)."""

    def __init__(self, job, spec, chunks, submit, window, shutdown, description, restart=None, sources=None):
        self.job = job
        self.spec = spec
        self.submit = submit
        self.window = window
        self._shutdown = shutdown
        self._restart = restart
        self._redo = None
        self.restarts = 0
        self._chunks = iter(chunks)
        self.paths = chunks[0].paths if chunks else ()  # what the client reads with --dask-send-frames
        self._pending = collections.deque()
        self._frames = iter(())
        self._prev_end = None
        self._sources = dict(sources or {})
        self.redone = []
        self.attrs = {"parallel": description, "chunks": len(chunks), "chunks_redone": 0}
        self._closed = False
        self._blocks = ParentBlocks()  # the workers' shared-memory blocks, mapped once for the run
        self._interrupt = _DeferredInterrupt()
        self._fill()

    def _fill(self):
        while len(self._pending) < self.window:
            chunk = next(self._chunks, None)
            if chunk is None:
                return
            if self.job.send_frames:
                chunk = dataclasses.replace(chunk, items=self._read(chunk))
            self._pending.append((chunk, self.submit(process_chunk, self.spec, chunk)))

    def _read(self, chunk):
        first = chunk.first if (chunk.redo or chunk.overlap is None) else chunk.overlap
        return tuple(imageio.iter_frames(list(self.paths), first=first, last=chunk.last,
                                         step=chunk.step, errors="yield", losses_from=chunk.overlap))

    def _result(self, chunk, future):
        """The chunk's outcome; after a worker process died, a fresh pool takes
        every chunk in flight (at most MAX_POOL_RESTARTS times a run)."""
        from concurrent.futures.process import BrokenProcessPool

        while True:
            try:
                self._interrupt.check()
                if not _wait(future, 0.25):
                    continue  # a Ctrl-C is seen within a quarter second
                # and once more: a Ctrl-C that came before the chunk ended ends the run before its frames are
                # written (it could be taken during that last wait, its handler run by the call below)
                self._interrupt.check()
                return future.result()
            except BrokenProcessPool as exc:
                if self._restart is None or self.restarts >= MAX_POOL_RESTARTS:
                    raise TirdeflectError(
                        f"a worker process died while reconstructing {chunk.label} ({exc}; killed, or "
                        f"out of memory?) {self.restarts + 1} time(s); run again with fewer --workers "
                        f"or --workers 1, and --first {chunk.first} to go on from there"
                        f"{_script_hint()}") from None
                self.restarts += 1
                _discard_finished((f for _, f in self._pending), self._blocks)  # the survivors' chunks: done again below
                log.warning("a worker process died during %s; starting new workers for the %d "
                            "chunk(s) in flight", chunk.label, len(self._pending) + 1)
                self._restart()
                self._pending = collections.deque(
                    (c, self.submit(process_chunk, self.spec, c)) for c, _ in self._pending)
                if self._pending and self._pending[0][0] is chunk:
                    future = self._pending[0][1]
                else:  # a redo
                    future = self.submit(process_chunk, self.spec, chunk)
                    self._redo = future
            except Exception as exc:
                if type(exc).__name__ != "KilledWorker":
                    raise
                raise TirdeflectError(
                    f"Dask gave up on {chunk.label}: the workers computing it died repeatedly ({exc}); "
                    f"check the workers' memory and logs, then run again with --first {chunk.first}"
                ) from None

    def _next_chunk(self):
        """Move on to the next chunk's frames. Every chunk whose shared memory is
        not yet freed stays where :meth:`close` finds it (Ctrl-C may come anywhere)."""
        chunk, future = self._pending[0]
        out = self._result(chunk, future)
        self._pending.popleft()
        self._frames = iter(out.frames)
        if chunk.index > 0 and not _states_agree(out.start, self._prev_end):
            log.info("%s: its start (unwrapped in space) disagrees with the end of the chunk before; "
                     "redone in time from there", chunk.label)
            _discard(self._frames, self._blocks)
            self.redone.append(chunk.index)
            self.attrs["chunks_redone"] = len(self.redone)
            redo = dataclasses.replace(chunk, redo=True, start=self._prev_end, overlap=None, items=None)
            if self.job.send_frames:
                redo = dataclasses.replace(redo, items=self._read(redo))
            self._fill()
            self._redo = self.submit(process_chunk, self.spec, redo)
            out = self._result(redo, self._redo)
            self._frames = iter(out.frames)
            self._redo = None
        self._prev_end = out.end
        self._fill()  # keep the workers busy while the engine writes this chunk

    def __iter__(self):
        return self

    def __next__(self):
        self._interrupt.check()
        while True:
            pair = next(self._frames, None)
            if pair is not None:
                item, payload = pair
                if item is None:  # a whole file became unreadable in the worker
                    raise payload
                item = dataclasses.replace(item, source=self._sources.get(item.source, item.source))
                result, outcome = payload
                if isinstance(result, SharedFrame):
                    try:
                        result = result.take(self._blocks)
                    except BaseException:  # Ctrl-C while attaching: free the block all the same
                        result.discard(self._blocks)
                        raise
                return item, functools.partial(_given, (result, outcome))
            if not self._pending:
                raise StopIteration
            self._next_chunk()

    def close(self):
        if self._closed:
            return
        self._closed = True
        self._interrupt.restore()
        _discard(self._frames, self._blocks)
        futures = [f for _, f in self._pending] + ([self._redo] if self._redo is not None else [])
        for future in futures:
            future.cancel()
        self._shutdown()
        _discard_finished(futures, self._blocks)  # finished before they could be cancelled
        self._pending.clear()
        self._blocks.close()


def _spec(job, reconstruct, reference, geometry, threads, shared_memory=False, tasks_per_host=()):
    return ReconstructorSpec(key=uuid.uuid4().hex, reference=np.asarray(reference), geometry=geometry,
                             options=reconstruct.options, carriers=reconstruct.carriers, threads=threads,
                             shared_memory=shared_memory, compression=getattr(job, "compression", None),
                             tasks_per_host=tasks_per_host)


def _frame_bytes(reconstruct, grid: str) -> int:
    if grid == "full":
        rows, cols = reconstruct.shape
    else:
        rows, cols = len(reconstruct.rows_px), len(reconstruct.cols_px)
    return rows * cols * (3 * 4 + 1)


def _init_worker(run_pid: int, parent, stop=None):
    """Set up a worker process of the run whose process is ``run_pid``.

    The worker takes the run's environment and working directory (``parent``, an
    :class:`app.worker_processes.ParentState`; forked from the app's fork server, it has the
    server's, from when the server started). Ctrl-C at the terminal reaches
    the workers too: the run's own process handles it (stops, keeps what was written, shuts the
    pool down), so the workers ignore it. If the run's process dies without shutting the pool
    down (SIGKILL, a crash, the OOM killer), the worker ends too, within half a second, instead
    of waiting for work forever (and so does the fork server, once no worker holds it); with the
    workers gone, the resource tracker frees the shared-memory blocks still held. The worker
    watches the run itself: its parent is the fork server, which lives as long as its workers.
    ``stop``: the run's event, set when it ends (:func:`stop_requested`)."""
    import signal

    from app.worker_processes import adopt_parent_state

    global _STOP
    _STOP = stop
    set_run_pid(run_pid)
    adopt_parent_state(parent)
    signal.signal(signal.SIGINT, signal.SIG_IGN)

    def exit_with_the_run():
        import time

        while _process_alive(run_pid):
            time.sleep(0.5)  # polling the run: there is no portable "that process died" event
        # not half way through making a block (what the tracker does not know of stays in /dev/shm)
        MAKING_BLOCK.acquire(timeout=10.0)
        os._exit(1)

    threading.Thread(target=exit_with_the_run, name="tirdeflect-run-watch", daemon=True).start()


def _process_alive(pid: int) -> bool:
    """Is process ``pid`` running (a killed process not yet reaped by its parent, a zombie, is not)?"""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:  # Linux: the state follows the command's ")"
            return f.read().rpartition(b")")[2].split()[0] != b"Z"
    except FileNotFoundError:
        return False
    except (OSError, IndexError):  # no /proc (macOS): whether a signal could reach it
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        except PermissionError:
            return True
        return True


class _Pool:
    """``workers`` processes from the app's fork server (:mod:`app.worker_processes`: a fresh
    interpreter's state, safe from a Qt GUI or a threaded program, where a plain fork is not);
    :meth:`restart` replaces a pool broken by a dead worker.

    :meth:`shutdown` first sets the run's stop event, which every worker sees between two frames
    (:func:`stop_requested`): the chunks running end after the frame each worker is measuring, and
    the shutdown waits for that frame only. Before, it waited for the chunks to end: Ctrl-C on
    ``--workers 2`` took up to a chunk's time to stop (a 60-frame chunk of 512^2: 3 s; at 1024^2,
    1,000 frames: about 25 s) while a serial run stops at once."""

    def __init__(self, workers: int):
        from app.worker_processes import context

        self.workers = workers
        self._stop = context().Event()
        self._pool = self._new()

    def _new(self):
        from concurrent.futures import ProcessPoolExecutor

        from app.worker_processes import context, parent_state

        return ProcessPoolExecutor(max_workers=self.workers, mp_context=context(), initializer=_init_worker,
                                   initargs=(os.getpid(), parent_state(), self._stop))

    def submit(self, fn, *args):
        from concurrent.futures import Future
        from concurrent.futures.process import BrokenProcessPool

        try:
            return self._pool.submit(fn, *args)
        except BrokenProcessPool as exc:  # a worker died between chunks: the caller restarts
            future = Future()
            future.set_exception(exc)
            return future

    def shutdown(self):
        self._stop.set()  # the chunks running end after their current frame; those not started at once
        if getattr(self._pool, "_broken", False):  # the run gives up after its last restart
            _release_feeder(self._pool)
        self._pool.shutdown(wait=True, cancel_futures=True)
        left = unlink_left_blocks(os.getpid())  # the workers have ended: what a killed one left
        if left:
            log.debug("removed %d shared-memory block(s) a killed worker left in /dev/shm", left)

    def restart(self):
        broken, self._pool = self._pool, self._new()
        _release_feeder(broken)
        broken.shutdown(wait=False, cancel_futures=True)


def _script_hint() -> str:
    """When this process runs a Python script (``python myscript.py``): the
    reminder that worker processes import that script, so that a call to
    ``run_process`` outside ``if __name__ == "__main__":`` kills every worker
    as it starts (multiprocessing's "bootstrapping phase" error)."""
    import sys

    main = sys.modules.get("__main__")
    path = getattr(main, "__file__", None)
    if not path or getattr(main, "__spec__", None) is not None:
        return ""  # python -m, the tirdeflect command, an interactive session
    return (f". If {os.path.basename(path)} calls run_process at its top level, move that call "
            f"under `if __name__ == \"__main__\":` (worker processes import the script)")


def _release_feeder(broken_pool) -> None:
    """Let a broken pool's clean-up end.

    The pool's thread that feeds work to the processes can be stuck writing a
    chunk into the pipe that only the (now killed) workers read; the pool's
    manager thread waits for it, and the interpreter waits for the manager
    thread at exit: a run whose worker died never ended (CPython before
    3.11.3, e.g. Debian 12's 3.11.2: python/cpython#94777). A thread of ours
    reads that pipe through a descriptor of its own (a duplicate of its read
    end) until the feeder, on its way out, closes the write end: the stuck
    write completes and the pool ends as it would have.

    The pool's own descriptors are left to the pool. Closing its read end here
    (as this function did before) raced with the feeder closing the same one
    when it ends: the second close failed inside the feeder, after it had
    taken the pool's "quit" token, and it waited for work forever -- a script
    without ``if __name__ == "__main__":`` that got its error message then
    never exited (a script calling ``run_process(workers=2)`` at its top level, beside
    ``stress-ng --cpu 4``: 2 of 40 runs hung, 0 of 40 with the descriptor of our own;
    tests/app/test_parallel.py::test_a_killed_worker_process_is_replaced fails without either).

    Only on those older Pythons: from 3.11.3 on the pool's manager thread
    ends the feeder itself."""
    import sys

    if sys.version_info >= (3, 11, 3):
        return
    queue = getattr(broken_pool, "_call_queue", None)
    reader = getattr(queue, "_reader", None)
    if reader is None:
        return
    try:
        fd = os.dup(reader.fileno())
    except (OSError, ValueError):  # the pool closed it already: nothing can be stuck
        return
    threading.Thread(target=_drain, args=(fd,), name="tirdeflect broken pool drain", daemon=True).start()


def _drain(fd: int) -> None:
    """Read ``fd`` (a pipe) until every write end is closed, then close it."""
    try:
        while os.read(fd, 1 << 16):
            pass
    except OSError:
        pass
    finally:
        os.close(fd)


def _results_fit_shm(chunks, workers: int, job, reconstruct) -> bool:
    """Results through shared memory (:data:`SHARED_MEMORY`) for ``workers`` on this
    machine, when /dev/shm holds the frames of the ``workers + 2`` chunks in flight."""
    in_flight = (workers + 2) * (chunks[0].last - chunks[0].first) // job.step + workers + 2
    return SHARED_MEMORY and _shm_room(in_flight * _frame_bytes(reconstruct, job.grid))


def _shm_room(need_bytes: int) -> bool:
    """Room for ``need_bytes`` of results in shared memory, twice over? (A
    container's /dev/shm is often 64 MB; writing past its end kills the worker
    with SIGBUS, so too small a one means pickling through pipes instead.)"""
    import shutil

    try:
        free = shutil.disk_usage("/dev/shm").free
    except OSError:
        return os.name != "posix"  # no /dev/shm: another OS's shared memory
    if free < 2 * need_bytes:
        log.info("/dev/shm has %.0f MB free, less than twice the %.0f MB of results in flight: "
                 "results travel through pipes", free / 1e6, need_bytes / 1e6)
        return False
    return True


def _dask_client(address: str):
    """(client, close) for ``local``, ``local:N`` or a scheduler address."""
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise TirdeflectError(
            "--dask needs Dask: pip install 'tirdeflect[dask]' (or pip install 'dask[distributed]')"
        ) from None
    if address == "local" or address.startswith("local:"):
        text = address.partition(":")[2]
        try:
            n = int(text) if text else available_cores()
        except ValueError:
            n = 0
        if n < 1:
            raise TirdeflectError(f"--dask {address!r}: the number after local: must be a whole "
                                  f"number >= 1 of worker processes, e.g. --dask local:4")
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                               dashboard_address=None, silence_logs=logging.ERROR)
        client = Client(cluster)

        def close():
            client.close()
            cluster.close()
            # a run interrupted mid-chunk: its worker processes were ended with result blocks made for
            # chunks it never took (they named them after this process): removed here, not left to the
            # resource tracker's "leaked shared_memory objects" warning at exit
            left = unlink_left_blocks(os.getpid())
            if left:
                log.debug("removed %d shared-memory block(s) the Dask workers left in /dev/shm", left)

        return client, close
    if "://" not in address and ":" not in address:
        raise TirdeflectError(f"--dask {address!r} is not a scheduler address; give "
                              f"tcp://HOST:8786 (see docs/cluster.md) or local[:N]")
    try:
        client = Client(address, timeout="20s")
    except (OSError, TimeoutError) as exc:
        raise TirdeflectError(f"cannot reach the Dask scheduler at {address!r} ({exc}); start "
                              f"`dask scheduler` there and `dask worker {address}` on each "
                              f"machine (docs/cluster.md)") from None
    return client, client.close


def _dask_submit(client):
    def submit(fn, spec, chunk):
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*[Ll]arge.*", category=UserWarning)
            return client.submit(fn, spec, chunk, pure=False,
                                 key=f"tirdeflect-{spec.key[:8]}-chunk-{chunk.index}"
                                     f"{'-redo' if chunk.redo else ''}")
    return submit


def frame_results(job, reconstruct, reference, geometry, selected: int, paths=None):
    """``(item, measured)`` of every selected frame in order (``reconstruct.options``: how every
    worker builds its own Reconstructor); ``measured()`` returns
    ``(Result, OK)`` or ``(None, FrameOutcome)`` as :func:`measure` does. Has ``attrs``
    (stored in the output) and ``close()``.

    ``paths``: the input files as the engine expanded them (default ``job.frames``).
    ``job.workers`` None: all cores for runs of at least
    :data:`AUTO_PARALLEL_MIN_FRAMES` frames, else serial; 1: serial.
    ``job.dask``: on a Dask cluster instead (docs/cluster.md).
    ``job.device`` "cuda": batches on the GPU in this process.
    """
    inputs = [str(p) for p in (job.frames if paths is None else paths)]
    workers = getattr(job, "workers", None)
    dask_address = getattr(job, "dask", None)
    if getattr(job, "device", "cpu") == "cuda":
        if dask_address or (workers is not None and workers != 1):
            raise TirdeflectError("--device cuda runs in one process on this machine's GPU; "
                                  "leave out --workers and --dask")
        return _GpuBatches(job, reconstruct, reference, geometry, inputs)
    if job.send_frames and not dask_address:
        raise TirdeflectError("--dask-send-frames is for Dask workers without the input files; "
                              "add --dask ADDRESS, or leave it out")
    if dask_address:
        if workers is not None:
            raise TirdeflectError("--workers and --dask exclude each other: a Dask cluster has "
                                  "its own workers (--dask local:N for N on this machine)")
        client, close = _dask_client(dask_address)
        try:
            if job.send_frames:
                task_paths = tuple(inputs)
            else:
                task_paths = tuple(str(Path(p).resolve()) for p in inputs)
            per_host = _dask_tasks_per_host(client)
            n = max(1, sum(threads for _, threads in per_host))
            chunks = plan_chunks(selected, first=job.first, step=job.step, paths=task_paths, workers=n,
                                 frame_bytes=_frame_bytes(reconstruct, job.grid),
                                 chunk_frames=job.chunk_frames, keyframes=_keyframes(inputs))
            # a LocalCluster's workers share this machine's memory: results come back through
            # shared memory as from worker processes, not pickled through TCP (13 MB a 1024^2 frame)
            local = dask_address == "local" or dask_address.startswith("local:")
            spec = _spec(job, reconstruct, reference, geometry, None,
                         shared_memory=local and _results_fit_shm(chunks, n, job, reconstruct),
                         tasks_per_host=per_host)

            def shutdown():
                _stop_dask_tasks(client, spec.key)  # the chunks running end after their frame
                close()

            runner = _Chunked(job, spec, chunks, _dask_submit(client), n + 1, shutdown,
                              f"dask {dask_address} ({n} worker threads)",
                              sources={a: o for a, o in zip(task_paths, inputs)})
        except BaseException:
            close()
            raise
        return runner
    if workers is None:
        workers = available_cores() if selected >= AUTO_PARALLEL_MIN_FRAMES else 1
    workers = min(int(workers), selected)
    if workers <= 1:
        return _Serial(job, reconstruct, reference, inputs)
    chunks = plan_chunks(selected, first=job.first, step=job.step, paths=tuple(inputs),
                         workers=workers, frame_bytes=_frame_bytes(reconstruct, job.grid),
                         chunk_frames=job.chunk_frames, keyframes=_keyframes(inputs))
    if len(chunks) < workers:  # a process per chunk at most: store and say what runs
        if getattr(job, "workers", None) is not None:
            log.warning("--workers %d: %d process(es) run, one per chunk of frames (%d frames, chunks of "
                        "at least %d; this machine has %d cores)", job.workers, len(chunks), selected,
                        MIN_CHUNK_FRAMES if job.chunk_frames is None else job.chunk_frames, available_cores())
        workers = max(1, len(chunks))
    spec = _spec(job, reconstruct, reference, geometry, fft_threads(workers),
                 shared_memory=_results_fit_shm(chunks, workers, job, reconstruct))
    pool = _Pool(workers)
    try:
        return _Chunked(job, spec, chunks, pool.submit, workers + 1, pool.shutdown,
                        f"{workers} processes x {spec.threads} FFT thread(s)", restart=pool.restart)
    except BaseException:
        pool.shutdown()
        raise
