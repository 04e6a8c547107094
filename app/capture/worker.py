"""Processing worker: the newest camera frame -> :class:`processing.Reconstructor` -> the newest result.

One thread, no Qt. Queue policy: **newest only**. The worker never queues
frames: each time it is free it takes the newest frame from the ring buffer and
processes it on the decimated grid (live speed); frames that arrived meanwhile
are skipped *for display only* and counted in :attr:`ProcessingWorker.skipped`
(the recorder reads every frame from its own ring cursor, so skipping here never
loses data).

Publishes (all thread-safe reads)
---------------------------------
``latest()``
    The newest :class:`Processed` (frame, result or error, alignment metrics), or None.
``counters()``
    ``processed``, ``skipped`` (frames passed over because a newer one was there),
    ``failed`` (frames whose processing raised), ``fps`` (processed frames per
    second, counted once per second), ``last_error`` (message or None),
    ``processing_ms`` (duration of the last reconstruction).
Listeners added with ``add_listener(fn)`` are called *in the worker thread*
with each :class:`Processed` (the auto-trigger is fed this way); a listener
that raises is reported in ``last_error`` and does not stop the worker.

Takes (commands, thread-safe)
-----------------------------
``set_reconstructor(reconstructor_or_None, reference=None)``, ``set_grid("decimated"|"full")``,
``set_alignment(enabled, interval_s=...)``, ``start()``, ``stop(timeout_s)``.

Where the reconstruction runs
-----------------------------
One loop (:meth:`ProcessingWorker._run`) and one function of a frame
(:func:`measure_live`). With ``separate_process=True`` and a reference given to
:meth:`ProcessingWorker.set_reconstructor`, :func:`measure_live` runs in a worker
process (:class:`app.capture.live_process.LiveProcess`: the frame goes in and the
maps come back through shared memory), so the reconstruction does not share this
process's GIL with the camera, recorder and GUI threads. If that process dies, the
frame being measured is published with the error, :attr:`ProcessingWorker.process_error`
says why, and the worker goes on in its own thread (the recorder never depends on it).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import threading
import time
from typing import Callable, List, Optional, Tuple

import numpy as np

from .live_measure import LiveJob, Measured, WorkerStopped, error_message, measure_live

__all__ = ["Processed", "ProcessingWorker", "LiveJob", "Measured", "WorkerStopped", "measure_live",
           "saturation_percent", "ring_source", "BANDS_INTERVAL_S"]

log = logging.getLogger(__name__)

# A frame source returns the newest frame strictly newer than ``after_seq`` or
# None when there is none within ``timeout_s``: (seq, image, host_timestamp_ns).
FrameSource = Callable[[int, float], Optional[Tuple[int, np.ndarray, int]]]


@dataclasses.dataclass(frozen=True)
class Processed:
    """One published processing outcome.

    Attributes
    ----------
    seq : int
        Ring-buffer sequence number of the processed frame.
    host_timestamp_ns : int
        ``time.monotonic_ns()`` when the driver received the frame (camera-to-screen
        latency = display time - this).
    image : ndarray, shape (rows, cols), uint8/uint16
        The raw frame that was processed (a private copy).
    result : processing.Result or None
        Reconstruction on the worker's grid; None without reference or on error.
    error : str or None
        Message of the processing error for this frame (e.g. all pixels invalid).
    alignment : dict or None
        ``Reconstructor.alignment(frame)`` (periods, rotation, theta, modulation, focus,
        saturation), refreshed every ``interval_s`` while alignment is on.
    spectrum : object or None
        ``Reconstructor.spectrum(frame)`` refreshed with ``alignment``.
    saturation_pct : float
        Percentage of pixels at the top code value of the frame's bit depth.
    processing_s : float
        Wall time of the reconstruction in seconds.
    done_ns : int
        ``time.monotonic_ns()`` when processing finished.
    picked_ns : int
        ``time.monotonic_ns()`` when the worker took the frame from the ring (the wait before it is
        the time the worker was busy with the previous frame).
    cpu_s : float
        CPU time of the reconstruction in the thread that ran it (here or in the worker process).
    queued_s : float
        Time of the reconstruction that thread was runnable but waited for a core (other programs);
        ``processing_s - cpu_s - queued_s`` is time it was blocked: above all, in this process,
        waiting for the GIL that the GUI, camera and recorder threads hold.
    light_bands : processing.banding.LightBands or None
        Bands of light along the rows that the reference does not show (a rolling shutter under
        PWM-dimmed light): judged every :data:`BANDS_INTERVAL_S` while none were found, on every frame
        (each evened out before measuring) while they are; the last verdict in between; None without
        a reference.
    """

    seq: int
    host_timestamp_ns: int
    image: np.ndarray
    result: object = None
    error: Optional[str] = None
    alignment: Optional[dict] = None
    spectrum: object = None
    saturation_pct: float = 0.0
    processing_s: float = 0.0
    done_ns: int = 0
    picked_ns: int = 0
    cpu_s: float = 0.0
    queued_s: float = 0.0
    light_bands: object = None


def saturation_percent(image: np.ndarray, bit_depth: Optional[int] = None, *, step: int = 2) -> float:
    """Percentage of pixels at the sensor's top code value.

    Parameters
    ----------
    image : ndarray, shape (rows, cols), uint8 or uint16
        Raw camera frame.
    bit_depth : int, optional
        Significant bits (8, 10, 12, 16). Default: 8 for uint8, 16 for uint16.
    step : int
        Subsampling stride along both axes (speed; 2 reads a quarter of the pixels).

    Returns
    -------
    float
        Saturated pixels in percent, 0..100.
    """
    if image.dtype.kind == "f":
        return 0.0
    if bit_depth is None:
        bit_depth = 8 * image.dtype.itemsize
    top = (1 << int(bit_depth)) - 1
    sub = image[::step, ::step]
    return 100.0 * float(np.count_nonzero(sub >= top)) / max(sub.size, 1)


def ring_source(ring) -> FrameSource:
    """A :data:`FrameSource` on :meth:`app.capture.ringbuffer.RingBuffer.latest` (newest frame, copied).

    ``ring.latest`` is the ring's one newest-only consumer: give it to one worker only.
    """

    def source(after_seq: int, timeout_s: float):
        f = ring.latest(timeout_s)
        if f is None:
            if ring.closed:  # camera gone: do not spin
                time.sleep(min(timeout_s, 0.05))
            return None
        return f.sequence, f.image, f.host_timestamp_ns

    return source


#: Seconds between two judgements of a frame's bands of light (:func:`processing.banding.frame_light_bands`,
#: 1.4 ms at 1024^2: a third of the live heights' time on every frame) while the last found none; flickering
#: light is a state of the room, named within this long, and while it lasts every frame is judged and evened.
BANDS_INTERVAL_S = 0.25


@dataclasses.dataclass(frozen=True)
class _Plan:
    """What the worker does with one frame, decided when it takes the frame (see ProcessingWorker._plan)."""

    reconstructor: object
    reference: Optional[np.ndarray]
    job: LiveJob
    bit_depth: Optional[int]
    alignment_fn: object
    t_start: float


class ProcessingWorker:
    """Thread that turns the newest frame into the newest :class:`Processed`.

    Parameters
    ----------
    source : callable
        ``source(after_seq, timeout_s) -> (seq, image, host_timestamp_ns) or None``:
        the newest frame newer than ``after_seq`` (see :func:`ring_source`).
    reconstructor : processing.Reconstructor, optional
        None until a reference exists: frames are then published raw (saturation only).
    grid : {"decimated", "full"}
        Grid passed to the reconstructor; "decimated" is the live default.
    bit_depth : int, optional
        Significant bits of the camera's pixels (for the saturation percentage).
    alignment_fn : callable, optional
        ``alignment_fn(frame) -> (alignment_dict, spectrum)`` used while alignment
        is on and no reconstructor is set (e.g. carriers from the live frame).
    poll_timeout_s : float
        Longest wait for a new frame before checking for stop (bounds :meth:`stop`).
    nice : int
        Linux nice increment of the worker thread (0: none), and of the worker process.
        A positive value lets the camera, recorder and display threads win the CPU; the
        worker then skips more frames.
    separate_process : bool
        Reconstruct in a worker process (:mod:`app.capture.live_process`) whenever
        :meth:`set_reconstructor` is given the reference image (it is started then, and
        ended by :meth:`stop`); False: in this thread.
    """

    def __init__(self, source: FrameSource, reconstructor=None, *, grid: str = "decimated",
                 bit_depth: Optional[int] = None, alignment_fn=None, poll_timeout_s: float = 0.05,
                 nice: int = 0, separate_process: bool = False):
        if grid not in ("decimated", "full"):
            raise ValueError(f"grid must be 'decimated' or 'full'; got {grid!r}")
        self._source = source
        self._lock = threading.Lock()
        self._reconstructor = reconstructor
        self._grid = grid
        self._bit_depth = bit_depth
        self._alignment_fn = alignment_fn
        self._alignment = False
        self._alignment_interval_s = 0.1
        self._last_alignment_t = 0.0
        self._bands = None  # the last frame's LightBands verdict (None: none yet on this reconstructor)
        self._last_bands_t = -BANDS_INTERVAL_S
        self._poll_timeout_s = float(poll_timeout_s)
        self._nice = int(nice)
        self._latest: Optional[Processed] = None
        self._listeners: List[Callable[[Processed], None]] = []
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._new_result = threading.Condition(self._lock)
        # one list per running wait_for: the results published while it waits, each checked there (the
        # newest-only _latest may have moved on before the waiting thread ran); none kept otherwise
        self._waiting: List[List[Processed]] = []
        self.processed = 0
        self.skipped = 0
        self.failed = 0
        self.fps = 0.0
        self.last_error: Optional[str] = None
        self.processing_ms = 0.0
        self._last_seq = -1
        self._reset_series = False
        self._reference = None  # the reconstructor's reference image (what the worker process builds on)
        self._separate_process = bool(separate_process)
        self._live_process = None  # app.capture.live_process.LiveProcess once started
        self._taken_ahead = None  # a frame taken while the one before it was handed on (see _look_ahead)
        #: Frames the worker process began while the one before them was handed on here (pipelined).
        self.sent_ahead = 0
        #: Why reconstruction left the worker process for this thread (it died), else None.
        self.process_error: Optional[str] = None

    # -- commands ------------------------------------------------------------
    def set_reconstructor(self, reconstructor, reference: Optional[np.ndarray] = None) -> None:
        """Use ``reconstructor`` from the next frame on (None: publish raw frames only).

        ``reference``: the reference image ``reconstructor`` was built on; with
        ``separate_process`` the worker process then builds the same reconstructor from it
        (``reconstructor.geometry``, ``.options``, ``.carriers``) and measures there.
        """
        with self._lock:
            self._reconstructor = reconstructor
            self._reference = None if reconstructor is None else reference
            self._reset_series = reconstructor is not None
            self._bands, self._last_bands_t = None, -BANDS_INTERVAL_S  # judged anew against this reference
            self._latest = None if reconstructor is None else self._latest
            if reconstructor is None:
                for published in self._waiting:
                    published.clear()

    @property
    def reconstructor(self):
        with self._lock:
            return self._reconstructor

    def set_grid(self, grid: str) -> None:
        if grid not in ("decimated", "full"):
            raise ValueError(f"grid must be 'decimated' or 'full'; got {grid!r}")
        with self._lock:
            self._grid = grid
            self._reset_series = True

    def set_bit_depth(self, bit_depth: Optional[int]) -> None:
        with self._lock:
            self._bit_depth = bit_depth

    def set_alignment(self, enabled: bool, interval_s: float = 0.1) -> None:
        """Compute alignment metrics and the spectrum every ``interval_s`` seconds while enabled
        (default 10 a second: one costs about the live heights' time at 1024^2), on the next frame
        due; a slow one (before a reference) waits as long as it took, so takes at most half the worker."""
        with self._lock:
            self._alignment = bool(enabled)
            self._alignment_interval_s = float(interval_s)
            self._last_alignment_t = 0.0

    def set_alignment_fn(self, alignment_fn) -> None:
        with self._lock:
            self._alignment_fn = alignment_fn

    def add_listener(self, fn: Callable[[Processed], None]) -> None:
        """Call ``fn(processed)`` in the worker thread after each frame."""
        with self._lock:
            self._listeners.append(fn)

    def remove_listener(self, fn) -> None:
        with self._lock:
            if fn in self._listeners:
                self._listeners.remove(fn)

    def start(self) -> "ProcessingWorker":
        if self._thread is not None and self._thread.is_alive():
            return self
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="tirdeflect-processing", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop the thread; raises TimeoutError if it did not end within ``timeout_s``."""
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(timeout_s)
        process, self._live_process = self._live_process, None
        if process is not None:  # ended whatever the thread does: no process is left behind
            process.close()
        if thread is not None:
            if thread.is_alive():
                raise TimeoutError(
                    f"processing worker did not stop within {timeout_s} s (a reconstruction is still "
                    "running); it will end after the current frame")

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    # -- publications --------------------------------------------------------
    def latest(self) -> Optional[Processed]:
        with self._lock:
            return self._latest

    def wait_for(self, predicate: Callable[[Processed], bool], timeout_s: float) -> Optional[Processed]:
        """Block until the latest result, or one published while waiting, satisfies ``predicate``
        (None when ``timeout_s`` passes first).

        Every result published during the wait is checked, in order, not only the newest: on a loaded
        machine the worker can publish the next frame before the waiting thread runs (a frame that
        failed between two that did not was missed so).
        """
        deadline = time.monotonic() + timeout_s
        with self._new_result:
            if self._latest is not None and predicate(self._latest):
                return self._latest
            published: List[Processed] = []
            self._waiting.append(published)
            try:
                while True:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        return None
                    self._new_result.wait(left)
                    while published:
                        p = published.pop(0)
                        if predicate(p):
                            return p
            finally:
                self._waiting = [other for other in self._waiting if other is not published]

    def counters(self) -> dict:
        return {"processed": self.processed, "skipped": self.skipped, "failed": self.failed,
                "fps": self.fps, "last_error": self.last_error, "processing_ms": self.processing_ms,
                "reconstructed_in": self.reconstructed_in, "process_error": self.process_error,
                "sent_ahead": self.sent_ahead}

    @property
    def process_starting(self) -> Optional[tuple]:
        """``(seconds, timeout_s)`` while the worker process is starting (not answered yet), else None."""
        process = self._live_process
        s = process.starting_s if process is not None else None
        return None if s is None else (s, process.start_timeout_s)

    @property
    def reconstructed_in(self) -> str:
        """Where the live reconstruction runs now: "worker process (pid N)" or "this process"."""
        process = self._live_process
        pid = process.pid if process is not None else None
        return f"worker process (pid {pid})" if pid is not None else "this process"

    # -- thread --------------------------------------------------------------
    def _run(self) -> None:
        if self._nice:
            # newest-only consumer: under CPU pressure it should yield to the camera, recorder and
            # display threads (it just skips more frames); Linux lets a thread have its own nice value
            try:
                os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), self._nice)
            except (AttributeError, OSError):
                pass
        count_start = time.monotonic()
        count = 0
        while not self._stop.is_set():
            taken, self._taken_ahead = self._taken_ahead, None
            if taken is None:
                try:
                    got = self._source(self._last_seq, self._poll_timeout_s)
                except Exception as exc:  # the source (ring) failed: report, keep trying
                    self.last_error = f"frame source failed: {exc}"
                    log.exception("frame source failed")
                    self._stop.wait(0.1)
                    continue
                taken = None if got is None else self._take(got)
            now = time.monotonic()
            if now - count_start >= 1.0:
                self.fps = count / (now - count_start)
                count, count_start = 0, now
            if taken is None:
                continue
            try:
                processed = self._process(*taken)
            except WorkerStopped:
                break
            self.processed += 1
            count += 1
            with self._new_result:
                self._latest = processed
                for published in self._waiting:
                    published.append(processed)
                listeners = list(self._listeners)
                self._new_result.notify_all()
            for fn in listeners:
                try:
                    fn(processed)
                except Exception as exc:
                    self.last_error = f"listener {getattr(fn, '__name__', fn)!s} failed: {exc}"
                    log.exception("worker listener failed")

    def _take(self, got) -> tuple:
        """A frame from the source, counted (frames jumped over are skipped ones), with what is to be
        done with it: ``(seq, image, host_ns, picked_ns, plan)``."""
        seq, image, host_ns = got
        picked_ns = time.monotonic_ns()
        if seq > self._last_seq + 1:  # frames never seen (also before the first one)
            self.skipped += seq - self._last_seq - 1
        self._last_seq = seq
        return seq, image, host_ns, picked_ns, self._plan()

    def _plan(self) -> _Plan:
        """What the next frame gets, decided when it is taken (a frame sent ahead to the worker process
        is taken before the one in front of it is handed on)."""
        with self._lock:
            t_start = time.monotonic()
            do_alignment = self._alignment and t_start - self._last_alignment_t >= self._alignment_interval_s
            if do_alignment:
                self._last_alignment_t = t_start  # until it ends (below): the next frame is not due as well
            reset, self._reset_series = self._reset_series, False
            flagged = self._bands is not None and self._bands.flagged
            do_bands = flagged or t_start - self._last_bands_t >= BANDS_INTERVAL_S
            if do_bands:
                self._last_bands_t = t_start
            return _Plan(self._reconstructor, self._reference, LiveJob(self._grid, reset, do_alignment, do_bands),
                         self._bit_depth, self._alignment_fn, t_start)

    def _look_ahead(self):
        """Called by the worker process's :meth:`LiveProcess.measure` once the child has answered:
        the newest frame, if one is newer, taken now and returned for the child to start at once."""
        try:
            got = self._source(self._last_seq, 0.0)
        except Exception:  # noqa: BLE001 - the loop's own call reports a failing source
            return None
        if got is None:
            return None
        self._taken_ahead = taken = self._take(got)
        plan = taken[4]
        return (taken[0], plan.reconstructor, taken[1], plan.job) if plan.reconstructor is not None else None

    def _process(self, seq: int, image: np.ndarray, host_ns: int, picked_ns: int = 0,
                 plan: Optional[_Plan] = None) -> Processed:
        with self._lock:  # a frame taken ahead, then the reconstructor or grid changed: planned anew
            stale = plan is not None and (plan.reconstructor is not self._reconstructor or plan.job.grid != self._grid)
        plan = self._plan() if plan is None or stale else plan
        rec, reference, job = plan.reconstructor, plan.reference, plan.job
        bit_depth, alignment_fn, t_start = plan.bit_depth, plan.alignment_fn, plan.t_start
        do_alignment = job.alignment
        if rec is not None:
            m = self._measure(rec, reference, image, job, token=seq)
        else:
            m = Measured()
            if do_alignment and alignment_fn is not None:
                try:
                    m.alignment, m.spectrum = alignment_fn(image)
                except Exception as exc:
                    m.alignment = {"error": error_message(exc)}
        if m.error is not None:
            self.failed += 1
            self.last_error = m.error
            if m.traceback_text:
                log.error("processing failed:\n%s", m.traceback_text)
        self.processing_ms = 1e3 * m.processing_s
        alignment, spectrum = m.alignment, m.spectrum
        if do_alignment:
            t_end = time.monotonic()
            with self._lock:
                # due interval_s after this one began, and never sooner than its own duration after it
                # ended: a slow one (before a reference: the full search) takes at most half the worker
                self._last_alignment_t = max(t_start, 2 * t_end - t_start - self._alignment_interval_s)
        elif self._latest is not None and self._alignment:
            alignment, spectrum = self._latest.alignment, self._latest.spectrum
        if m.result is not None:
            self.last_error = None
        with self._lock:
            if job.bands and rec is self._reconstructor:
                self._bands = m.light_bands
            bands = self._bands if rec is not None else None
        return Processed(seq=seq, host_timestamp_ns=host_ns, image=image, result=m.result, error=m.error,
                         alignment=alignment, spectrum=spectrum,
                         saturation_pct=saturation_percent(image, bit_depth),
                         processing_s=m.processing_s, done_ns=time.monotonic_ns(), picked_ns=picked_ns,
                         cpu_s=m.cpu_s, queued_s=m.queued_s, light_bands=bands)

    def _measure(self, rec, reference, image: np.ndarray, job: LiveJob, token=None) -> Measured:
        """:func:`measure_live` in the worker process where there is one to use, else here."""
        if self._separate_process and reference is not None and self.process_error is None:
            from .live_process import LiveProcess, LiveProcessError

            try:
                if self._live_process is None:
                    try:
                        self._live_process = LiveProcess(nice=self._nice)
                    except Exception as exc:  # e.g. a script that starts the window unguarded by __main__
                        raise LiveProcessError(f"the live reconstruction process could not start: "
                                               f"{error_message(exc)}") from exc
                process = self._live_process
                before = process.sent_ahead
                try:
                    return process.measure(rec, reference, image, job, self._stop, token=token,
                                           ahead=self._look_ahead)
                finally:
                    self.sent_ahead += process.sent_ahead - before
            except LiveProcessError as exc:  # it died or could not build: say so, go on here
                process, self._live_process = self._live_process, None
                if process is not None:
                    process.close()
                self.process_error = str(exc)
                log.error("%s", exc)
                with self._lock:
                    self._reset_series = True  # this thread's reconstructor has its own series memory
                return Measured(error=f"{exc}; the live heights go on in the window's process (slower)")
        return measure_live(rec, image, job)
