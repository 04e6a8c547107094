"""The live reconstruction in a worker process of its own, beside the window's process.

Why: in the window's process the reconstruction shares one GIL with the GUI thread (pyqtgraph
draws 1024^2 images in Python and NumPy), the camera thread and the recorder; measured in the
running window, the GUI thread held the GIL about four fifths of the time the GIL was held and
the worker thread got about a tenth, so the heights came at a fraction of what the reconstruction
alone allows (docs/acquisition.md, "Live heights"). A worker process has its own interpreter and
GIL; the window's process keeps the camera, the ring, the recorder (lossless, untouched) and the
drawing.

How: :class:`LiveProcess` (used by :class:`app.capture.worker.ProcessingWorker`, newest frame
only, the next one sent as soon as the child answers: see :meth:`LiveProcess.measure`) starts one
process from the app's fork server (:mod:`app.worker_processes`: a
fresh interpreter's state, safe beside Qt and threads, ready at once after the first one).
It sends the child a :class:`Recipe` when the reconstructor changes (the reference image,
``Geometry``, the picklable ``ReconstructOptions``, the reference's carriers and this process's
FFTW wisdom, so that the child demodulates exactly as the window's own reconstructor would); the
child builds its :class:`processing.Reconstructor` from it. For each frame the image goes into a
shared-memory block, a small message through a pipe says which job to run; the child runs
:func:`app.capture.live_measure.measure_live`, writes the result's arrays into a second
shared-memory block and answers with the rest (pickled: a few hundred bytes, plus the alignment
metrics and spectrum when asked for). Two maps blocks, used in turn, let the child write one
frame's maps while this process copies out the previous frame's. All blocks belong to this
process (created, grown and removed here), so a child that dies leaves nothing behind.

Life: the child ends when told (:meth:`LiveProcess.close`: asked, then SIGTERM, then SIGKILL,
each waited for a bounded time), and by itself when the window's process is gone (its end of
the pipe reads EOF). A child that dies (a crash in native code, a signal, out of memory) is
reported as :class:`LiveProcessError` with its exit code or signal, at the next look (the
waits poll every 50 ms); the worker then says so and goes on in its own thread.
"""

from __future__ import annotations

import dataclasses
import os
import signal
import time
import uuid
from typing import Optional

import numpy as np

from .live_measure import LiveJob, Measured, WorkerStopped, error_message, measure_live

__all__ = ["LiveProcess", "LiveProcessError", "Recipe"]

#: How often a wait for the child looks whether it is still alive or the worker was stopped (s).
POLL_S = 0.05


class LiveProcessError(RuntimeError):
    """The worker process died, or could not build the reconstructor; the message says which and why."""


@dataclasses.dataclass(frozen=True)
class Recipe:
    """What the worker process needs to build the window's reconstructor (picklable).

    ``reference``: the reference image; ``geometry``: :class:`processing.Geometry`; ``options``:
    the reconstructor's resolved :class:`processing.ReconstructOptions`; ``carriers``: the
    reference's carriers as the window's reconstructor found them (None for dots); ``wisdom``:
    FFTW wisdom of this process (its plans, measured once), b"" for none.
    """

    reference: np.ndarray
    geometry: object
    options: object
    carriers: object = None
    wisdom: bytes = b""

    @classmethod
    def of(cls, reconstructor, reference: np.ndarray) -> "Recipe":
        """The recipe of ``reconstructor`` (built on ``reference``), with FFT threads for the child.

        The child's FFTs use at most the cores the window's process leaves it (all but one: its GUI
        thread paints 45-70 % of the time), so that the FFTs' threads do not wait for each other:
        on 2 cores 1 thread (measured at load 6-11, docs/acquisition.md: 512^2 18.6-29.9 Hz in four
        runs against a median of 8.6 Hz over seven runs with 2). One thread's FFT plans sum in another
        order: the heights agree to float32 rounding (tests/app/test_live_process.py). Random dots keep
        their threads: there they are PIV's workers (:func:`processing.pools.slot_map`, each taking the
        next chunk of windows or rows, FFTW on one thread each), which wait for no one's fixed share
        (512^2 in the window, four rounds alternated: 10.1-13.1 Hz on two threads, 9.8-10.7 on one).
        """
        from processing import fft

        options = reconstructor.options
        threads = int(options.threads)
        if reconstructor.pattern != "dots":
            threads = max(1, min(threads, (os.cpu_count() or 1) - 1))
        if threads != options.threads:
            options = options.replace(threads=threads)
        return cls(np.asarray(reference), reconstructor.geometry, options,
                   getattr(reconstructor, "carriers", None), fft.export_wisdom())

    def build(self):
        """The :class:`processing.Reconstructor` of this recipe (in the worker process)."""
        from processing import Reconstructor, fft

        if self.wisdom:
            fft.import_wisdom(self.wisdom)
        return Reconstructor(self.reference, self.geometry, self.options, carriers=self.carriers)


class LiveProcess:
    """One worker process measuring live frames (see the module docstring).

    Parameters
    ----------
    nice : int
        Linux nice increment of the child (0: none).
    start_timeout_s : float
        Longest wait for the child's first answer (its imports and first build): one that never
        answers is ended and reported, e.g. a script that opens the window at its top level, not
        under ``if __name__ == "__main__":`` (a worker process imports the script it was started
        from, and would run it).
    """

    def __init__(self, nice: int = 0, start_timeout_s: float = 180.0):
        from app.worker_processes import context

        ctx = context()
        self._conn, child_end = ctx.Pipe()
        self._proc = ctx.Process(target=serve, args=(child_end, int(nice)), name="tirdeflect-live",
                                 daemon=True)
        self._proc.start()
        child_end.close()  # the child's death then reads as EOF here
        self._blocks = {}  # "frames"/"maps0"/"maps1" -> SharedMemory owned by this process
        self._built_for = None  # the window's reconstructor the child has built the same of
        self._slot = 0  # the maps block ("maps0"/"maps1") the next frame's maps go into
        self._ahead = None  # (token, slot, job) of a frame sent before its measure() call (see measure)
        self.sent_ahead = 0  # frames sent while the one before them was handed on (pipelined)
        self._closed = False
        self._start_timeout_s = float(start_timeout_s)
        self._answered = False  # the child answered once (it started)
        self._started_at = time.monotonic()

    @property
    def pid(self) -> Optional[int]:
        return None if self._closed else self._proc.pid

    @property
    def starting_s(self) -> Optional[float]:
        """Seconds since the child was started while it has not answered yet (its imports and first
        build), None once it has (or it was closed)."""
        return None if self._answered or self._closed else time.monotonic() - self._started_at

    @property
    def start_timeout_s(self) -> float:
        """The longest wait for the child's first answer before it is ended and reported."""
        return self._start_timeout_s

    def measure(self, reconstructor, reference: np.ndarray, image: np.ndarray, job: LiveJob, stop,
                token=None, ahead=None) -> Measured:
        """:func:`~app.capture.live_measure.measure_live` of ``image`` in the child.

        ``reconstructor`` (built on ``reference``) is rebuilt in the child whenever it is another
        than the last one. ``stop``: a ``threading.Event``; set, the wait ends with
        :class:`~app.capture.live_measure.WorkerStopped`. Raises :class:`LiveProcessError` when the
        child died or could not build the reconstructor.

        Pipelining (``ahead``, ``token``): once the child has answered, ``ahead()`` may return
        ``(token, reconstructor, image, job)`` of the next frame, which is sent at once, so that
        the child measures it while this frame's maps are copied out and handed on here (the
        window's process does that under its GUI thread's GIL: 5-10 ms a frame at 1024^2). The
        next call with that ``token`` and job then only waits for its answer; a call with another
        token, job (the grid changed meanwhile) or reconstructor first waits for that answer and
        drops it. The maps of two frames in flight go through two blocks, used in turn.
        """
        if self._ahead is not None and (self._ahead[0] != token or self._ahead[2] != job
                                        or self._built_for is not reconstructor):
            self._drop_ahead(stop)
        if self._ahead is None:
            if self._built_for is not reconstructor:
                self._build(reconstructor, reference, stop)
            slot = self._send_frame(image, job)
        else:
            slot = self._ahead[1]
            self._ahead = None
        _, measured, layout, needed = self._wait(stop)
        if ahead is not None:
            nxt = ahead()
            if nxt is not None and nxt[1] is self._built_for:
                self._ahead = (nxt[0], self._send_frame(nxt[2], nxt[3]), nxt[3])
                self.sent_ahead += 1
        maps = self._blocks.get(slot)
        if layout:
            measured.result = dataclasses.replace(measured.result, **{
                name: np.array(np.ndarray(shape, np.dtype(dt), buffer=maps.buf, offset=offset))
                for name, shape, dt, offset in layout})
        if needed > (maps.size if maps is not None else 0):
            self._block(slot, needed)  # this frame's maps came pickled; the next ones through the block
        return measured

    def close(self, timeout_s: float = 2.0) -> None:
        """End the child (asked, then SIGTERM, then SIGKILL) and remove the shared memory; idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            self._conn.send(("stop",))
        except (OSError, ValueError):
            pass
        self._proc.join(timeout_s)
        for end in (self._proc.terminate, self._proc.kill):
            if self._proc.exitcode is not None:
                break
            end()
            self._proc.join(1.0)
        self._conn.close()
        for block in self._blocks.values():
            _remove(block)
        self._blocks.clear()

    # -- here ------------------------------------------------------------------
    def _build(self, reconstructor, reference, stop) -> None:
        self._built_for = None
        self._send(("build", Recipe.of(reconstructor, reference)))
        kind, message = self._wait(stop, None if self._answered else self._start_timeout_s)
        self._answered = True
        if kind != "built":
            raise LiveProcessError(f"the live reconstruction process could not build the reconstructor: "
                                   f"{message}")
        self._built_for = reconstructor

    def _send_frame(self, image: np.ndarray, job: LiveJob) -> str:
        """``image`` into the frames block (the child copies it out first thing) and the job to the
        child, its maps to go into the next maps block; returns that block's kind."""
        image = np.ascontiguousarray(image)
        frames = self._block("frames", image.nbytes)
        np.ndarray(image.shape, image.dtype, buffer=frames.buf)[...] = image
        slot, other = f"maps{self._slot}", f"maps{1 - self._slot}"
        self._slot = 1 - self._slot
        names = [self._blocks[k].name if k in self._blocks else None for k in (slot, other)]
        self._send(("frame", frames.name, image.shape, image.dtype.str, job, *names))
        return slot

    def _drop_ahead(self, stop) -> None:
        """Wait for the answer to the frame sent ahead, and drop it."""
        self._ahead = None
        self._wait(stop)

    def _block(self, kind: str, nbytes: int):
        """This process's shared-memory block ``kind`` of at least ``nbytes`` (a new one if smaller)."""
        from multiprocessing import shared_memory

        block = self._blocks.get(kind)
        if block is not None and block.size >= nbytes:
            return block
        if block is not None:
            _remove(block)
        block = shared_memory.SharedMemory(name=f"tdl{os.getpid()}_{uuid.uuid4().hex[:10]}", create=True,
                                           size=max(1, int(nbytes)))
        self._blocks[kind] = block
        return block

    def _send(self, message) -> None:
        try:
            self._conn.send(message)
        except (OSError, ValueError):  # the child is gone: its end is closed
            raise LiveProcessError(self._death()) from None

    def _wait(self, stop, timeout_s: Optional[float] = None):
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while not self._conn.poll(POLL_S):
            if stop.is_set():
                raise WorkerStopped()
            if not self._proc.is_alive():
                break
            if deadline is not None and time.monotonic() > deadline:
                raise LiveProcessError(
                    f"the live reconstruction process (pid {self._proc.pid}) did not answer within "
                    f"{timeout_s:g} s of its start (a script that opens the window must do so under "
                    f"`if __name__ == \"__main__\":`: the process imports the script)")
        try:
            return self._conn.recv()
        except (EOFError, OSError):
            raise LiveProcessError(self._death()) from None

    def _death(self) -> str:
        self._proc.join(1.0)
        code = self._proc.exitcode
        if code is None:
            how = "its pipe closed"
        elif code < 0:
            try:
                how = f"killed by {signal.Signals(-code).name}"
            except ValueError:
                how = f"killed by signal {-code}"
        else:
            how = f"exit code {code}"
        return f"the live reconstruction process (pid {self._proc.pid}) ended unexpectedly ({how})"


def _remove(block) -> None:
    try:
        block.close()
    except BufferError:  # a view still exported (never kept here): the name goes anyway
        pass
    try:
        block.unlink()
    except FileNotFoundError:
        pass


# -- in the child ------------------------------------------------------------------
def serve(conn, nice: int = 0) -> None:
    """The worker process: build on each recipe, measure each frame, until told to stop or EOF."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C in the terminal is the window's to handle
    if nice:
        try:
            os.nice(nice)
        except OSError:
            pass
    attached = {}
    reconstructor = None
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):  # the window's process is gone
            break
        if message[0] == "stop":
            break
        if message[0] == "build":
            reconstructor = None
            try:
                reconstructor = message[1].build()
                conn.send(("built", None))
            except Exception as exc:  # a bad reference, out of memory: the worker says so
                conn.send(("build_failed", error_message(exc)))
            continue
        _, frames_name, shape, dtype, job, maps_name, other_maps_name = message
        frames = _attach(attached, frames_name, maps_name, other_maps_name)  # both maps blocks stay mapped
        # a private copy: the reconstructor's series memory may keep the frame, the block is rewritten
        image = np.array(np.ndarray(shape, np.dtype(dtype), buffer=frames.buf))
        measured = measure_live(reconstructor, image, job)
        layout, needed = (), 0
        if measured.result is not None:
            measured.result, layout, needed = _pack(measured.result, attached.get(maps_name))
        conn.send(("measured", measured, layout, needed))
    for block in attached.values():
        block.close()


def _attach(attached: dict, *names):
    """The blocks ``names`` mapped here (those no longer named are let go); returns the first."""
    from multiprocessing import shared_memory

    for name in [n for n in attached if n not in names]:
        attached.pop(name).close()
    for name in names:
        if name is not None and name not in attached:
            attached[name] = shared_memory.SharedMemory(name=name)
    return attached[names[0]]


def _pack(result, block):
    """``(result without its arrays, layout, bytes needed)``: the arrays written into ``block``;
    ``result`` whole (pickled) with an empty layout when they do not fit."""
    arrays = {f.name: getattr(result, f.name) for f in dataclasses.fields(result)
              if isinstance(getattr(result, f.name), np.ndarray)}
    offsets, needed = {}, 0
    for name, a in arrays.items():
        offsets[name] = needed
        needed += -(-a.nbytes // 64) * 64  # each array on a 64-byte boundary
    if block is None or block.size < needed:
        return result, (), needed
    layout = []
    for name, a in arrays.items():
        np.ndarray(a.shape, a.dtype, buffer=block.buf, offset=offsets[name])[...] = a
        layout.append((name, a.shape, a.dtype.str, offsets[name]))
    return dataclasses.replace(result, **{name: None for name in arrays}), tuple(layout), needed
