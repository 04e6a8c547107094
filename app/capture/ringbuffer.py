"""Preallocated ring buffer of camera frames with per-frame metadata.

One writer (the camera thread, :class:`app.capture.acquisition.Acquisition`) and two
kinds of consumer, each with its own queue policy:

* **newest only** -- :meth:`RingBuffer.latest` hands out the most recent frame
  (the processing worker, the display); frames it never saw are counted in
  :attr:`RingBuffer.latest_skipped`. Skipping is the policy, not a loss.
* **every frame, in order** -- a :class:`RingCursor` (the recorder) reads frame
  after frame. The ring is its bounded queue: when the writer laps a cursor,
  the overwritten frames are *counted exactly* (:attr:`RingCursor.lost`) and
  the next frame the cursor returns carries ``FrameFlags.RING_OVERRUN_BEFORE``
  and ``lost_before``. Nothing is lost silently.

Frames are numbered by a host *sequence* number: contiguous, starting at 0,
one per frame the writer committed. Copies out of the ring are validated
seqlock-style: a copy is only returned if the writer did not start
overwriting that slot while it was being copied.

Memory is allocated (and committed: every page mapped, :func:`committed_zeros`) once, in the
constructor; :meth:`RingBuffer.bytes_for` says the cost beforehand and
:func:`check_memory` compares it with the memory the system has available.
"""

from __future__ import annotations

import dataclasses
import math
import mmap
import sys
import threading
import time
from typing import Optional, Tuple

import numpy as np

from app.sizes import format_bytes  # noqa: F401  (importable from here, as before)
from drivers.base import FrameFlags

__all__ = [
    "RingFrame",
    "RingBuffer",
    "RingCursor",
    "RingClosed",
    "MemoryBudgetError",
    "available_memory_bytes",
    "check_memory",
    "format_bytes",
]

#: bytes of metadata stored per slot (sequence, frame id, device ts, host ts, missing bytes: int64; flags: uint32)
META_BYTES_PER_FRAME = 5 * 8 + 4

#: fraction of the available memory a ring may take before we refuse to allocate it
MEMORY_FRACTION = 0.8


class RingClosed(RuntimeError):
    """The writer closed the ring and a consumer has read everything that was in it.

    Attributes
    ----------
    error : str or None
        The writer's error message (e.g. the camera was lost), None after a
        normal stop.
    """

    def __init__(self, message: str, error: Optional[str] = None):
        super().__init__(message)
        self.error = error


class MemoryBudgetError(MemoryError):
    """A buffer would not fit into the memory the system has available."""


def available_memory_bytes() -> int:
    """Memory the kernel says can be allocated without swapping (``MemAvailable``), in bytes."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:  # pragma: no cover - not Linux
        pass
    try:  # pragma: no cover - fallback
        import os

        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):  # pragma: no cover
        return 1 << 62


def check_memory(needed_bytes: int, what: str, *, available_bytes: Optional[int] = None) -> None:
    """Raise :class:`MemoryBudgetError` when ``needed_bytes`` exceeds 80 % of available memory.

    Parameters
    ----------
    needed_bytes : int
        Bytes about to be allocated.
    what : str
        What the memory is for, echoed in the message (e.g. ``"ring buffer of 2000 frames 1024x1024 uint8"``).
    available_bytes : int, optional
        Override of :func:`available_memory_bytes` (tests).
    """
    avail = available_memory_bytes() if available_bytes is None else int(available_bytes)
    if needed_bytes > MEMORY_FRACTION * avail:
        raise MemoryBudgetError(
            f"{what} needs {format_bytes(needed_bytes)} but only {format_bytes(avail)} of memory is "
            f"available (at most {MEMORY_FRACTION:.0%} of it may be used); use fewer frames or a smaller ROI"
        )


@dataclasses.dataclass
class RingFrame:
    """One frame copied out of the ring, with its metadata.

    Attributes
    ----------
    image : ndarray, shape (rows, cols), uint8 or uint16
        The pixels (a copy owned by the consumer, or the ``out`` array it passed).
    sequence : int
        Host sequence number (contiguous from 0 over everything the camera thread committed).
    frame_id : int
        The camera's frame/block id.
    device_timestamp_ns : int or None
        Device timestamp in ns; None when the camera gave none (then ``flags`` has NO_DEVICE_TIMESTAMP).
    host_timestamp_ns : int
        ``time.monotonic_ns()`` when the driver received the frame.
    flags : FrameFlags
        Status bits; RING_OVERRUN_BEFORE when this consumer lost frames just before this one.
    lost_before : int
        Number of frames this consumer lost to ring overwrites right before this one (0 normally).
    missing_bytes : int
        Image bytes the transport never delivered (their pixels are 0; flag INCOMPLETE); 0 normally.
    """

    image: np.ndarray
    sequence: int
    frame_id: int
    device_timestamp_ns: Optional[int]
    host_timestamp_ns: int
    flags: FrameFlags
    lost_before: int = 0
    missing_bytes: int = 0


#: Linux's madvise(MADV_POPULATE_WRITE) (kernel 5.14 and later; Python's mmap module names it from 3.13
#: on, its value on Linux is 23); None elsewhere
_MADV_POPULATE_WRITE = (getattr(mmap, "MADV_POPULATE_WRITE", 23)
                        if sys.platform.startswith("linux") and hasattr(mmap.mmap, "madvise") else None)


def committed_zeros(shape, dtype) -> np.ndarray:
    """A zeroed array whose memory is committed now (every page mapped and written), so that
    filling it later at a camera's rate takes no page faults.

    On Linux the kernel maps and zeroes the pages in one call (anonymous mmap,
    ``madvise(MADV_POPULATE_WRITE)``): measured 0.28 s for 512 MiB where writing zeros
    from Python (``fill(0)``, a page fault per page) took 0.85-1.37 s on the same
    machine. Elsewhere, or on older kernels (the call is refused), the zeros are written.
    """
    nbytes = int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize
    if _MADV_POPULATE_WRITE is not None and nbytes >= mmap.PAGESIZE:
        block = mmap.mmap(-1, nbytes)
        try:
            block.madvise(_MADV_POPULATE_WRITE)
        except OSError:  # a kernel before 5.14 (EINVAL): write the zeros below
            populated = False
        else:
            populated = True
        out = np.frombuffer(block, dtype=dtype).reshape(shape)  # the array keeps the mapping alive
        if not populated:
            out.fill(0)
        return out
    out = np.empty(shape, dtype=dtype)
    out.fill(0)
    return out


class RingBuffer:
    """Fixed-size ring of ``n_frames`` images of one shape and dtype, plus metadata.

    Parameters
    ----------
    shape : (int, int)
        Image shape (rows, cols) in pixels.
    dtype : numpy dtype
        ``uint8`` or ``uint16``.
    n_frames : int
        Number of slots (>= 2).
    check_available_memory : bool
        Refuse (:class:`MemoryBudgetError`) a ring larger than 80 % of available memory.

    Notes
    -----
    Single writer: :meth:`put` (or :meth:`begin_write` + :meth:`commit`) from
    one thread only. Any number of readers. Slot ``i`` of the arrays holds
    sequence ``s`` with ``i = s % n_frames``. Device timestamps are stored as
    -1 when missing.
    """

    def __init__(self, shape: Tuple[int, int], dtype, n_frames: int, *, check_available_memory: bool = True):
        shape = tuple(int(s) for s in shape)
        if len(shape) != 2 or min(shape) < 1:
            raise ValueError(f"ring buffer frames must be 2-D (rows, cols) with positive sizes; got shape {shape}")
        dtype = np.dtype(dtype)
        if dtype not in (np.dtype(np.uint8), np.dtype(np.uint16)):
            raise ValueError(f"ring buffer dtype must be uint8 or uint16; got {dtype}")
        n_frames = int(n_frames)
        if n_frames < 2:
            raise ValueError(f"ring buffer needs at least 2 frames; got n_frames={n_frames}")
        self.shape = shape
        self.dtype = dtype
        self.n_frames = n_frames
        self.nbytes = self.bytes_for(shape, dtype, n_frames)
        if check_available_memory:
            check_memory(self.nbytes, f"ring buffer of {n_frames} frames {shape[0]}x{shape[1]} {dtype}")
        self.frames = committed_zeros((n_frames,) + shape, dtype)  # no page faults during acquisition
        self.sequence = np.full(n_frames, -1, dtype=np.int64)
        self.frame_id = np.zeros(n_frames, dtype=np.int64)
        self.device_ts_ns = np.full(n_frames, -1, dtype=np.int64)
        self.host_ts_ns = np.zeros(n_frames, dtype=np.int64)
        self.flags = np.zeros(n_frames, dtype=np.uint32)
        self.missing_bytes = np.zeros(n_frames, dtype=np.int64)
        self._head = 0  # number of frames committed == sequence of the next frame
        self._started = -1  # highest sequence the writer began writing (slot may be dirty)
        self._cond = threading.Condition(threading.Lock())
        self._waiters = 0
        self._closed = False
        self._error: Optional[str] = None
        self._latest_seq = -1
        #: frames the newest-only consumer (:meth:`latest`) never saw
        self.latest_skipped = 0

    # ------------------------------------------------------------------ sizes
    @staticmethod
    def bytes_for(shape: Tuple[int, int], dtype, n_frames: int) -> int:
        """Bytes a ring of ``n_frames`` frames of ``shape`` and ``dtype`` allocates, metadata included."""
        frame = int(np.prod(shape)) * np.dtype(dtype).itemsize
        return int(n_frames) * (frame + META_BYTES_PER_FRAME)

    @staticmethod
    def frames_for(shape: Tuple[int, int], dtype, n_bytes: int) -> int:
        """How many frames of ``shape``/``dtype`` fit into ``n_bytes`` (metadata included)."""
        frame = int(np.prod(shape)) * np.dtype(dtype).itemsize
        return int(n_bytes) // (frame + META_BYTES_PER_FRAME)

    # ----------------------------------------------------------------- status
    @property
    def head(self) -> int:
        """Number of frames committed so far (= sequence number of the next frame)."""
        return self._head

    @property
    def oldest(self) -> int:
        """Sequence number of the oldest frame still intact in the ring."""
        return max(0, self._started + 1 - self.n_frames)

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def error(self) -> Optional[str]:
        """The writer's error message after :meth:`close` with an error, else None."""
        return self._error

    # ----------------------------------------------------------------- writer
    def begin_write(self) -> Tuple[int, np.ndarray]:
        """Claim the next slot: returns ``(sequence, view_of_slot)``; fill the view, then :meth:`commit`."""
        seq = self._head
        self._started = seq  # readers of seq - n_frames now know that slot is dirty
        return seq, self.frames[seq % self.n_frames]

    def commit(self, frame_id: int, device_timestamp_ns: Optional[int], host_timestamp_ns: int, flags: int = 0,
               missing_bytes: int = 0) -> int:
        """Publish the slot claimed by :meth:`begin_write`; returns its sequence number."""
        seq = self._head
        i = seq % self.n_frames
        self.missing_bytes[i] = missing_bytes
        self.frame_id[i] = frame_id
        if device_timestamp_ns is None:
            self.device_ts_ns[i] = -1
            flags |= FrameFlags.NO_DEVICE_TIMESTAMP
        else:
            self.device_ts_ns[i] = device_timestamp_ns
        self.host_ts_ns[i] = host_timestamp_ns
        self.flags[i] = int(flags)
        self.sequence[i] = seq
        self._head = seq + 1
        if self._waiters:
            with self._cond:
                self._cond.notify_all()
        return seq

    def put(self, image: np.ndarray, frame_id: int, device_timestamp_ns: Optional[int], host_timestamp_ns: int,
            flags: int = 0) -> int:
        """Copy ``image`` into the next slot and publish it; returns its sequence number."""
        if image.shape != self.shape:
            raise ValueError(f"frame shape {image.shape} does not match the ring's {self.shape}")
        _, slot = self.begin_write()
        np.copyto(slot, image, casting="same_kind")
        return self.commit(frame_id, device_timestamp_ns, host_timestamp_ns, flags)

    def add_flags(self, sequence: int, flags: int) -> bool:
        """OR ``flags`` into a frame still in the ring (e.g. TRIGGER); False when it is gone."""
        i = sequence % self.n_frames
        if self.sequence[i] != sequence:
            return False
        self.flags[i] |= int(flags)
        return True

    def close(self, error: Optional[str] = None) -> None:
        """No more frames will come; wake every waiting consumer. ``error`` says why, if it was a failure."""
        with self._cond:
            if not self._closed:
                self._closed = True
                self._error = error
            self._cond.notify_all()

    # ---------------------------------------------------------------- readers
    def _intact(self, seq: int) -> bool:
        return seq + self.n_frames > self._started

    def wait_for(self, sequence: int, timeout_s: float) -> bool:
        """Wait until frame ``sequence`` is committed or the ring is closed; True when it is committed."""
        if self._head > sequence:
            return True
        deadline = time.monotonic() + max(0.0, float(timeout_s))
        with self._cond:
            self._waiters += 1
            try:
                while self._head <= sequence and not self._closed:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        break
                    self._cond.wait(left)
            finally:
                self._waiters -= 1
        return self._head > sequence

    def copy(self, sequence: int, out: Optional[np.ndarray] = None) -> Optional[RingFrame]:
        """Copy committed frame ``sequence`` out of the ring; None when it was already overwritten."""
        if sequence >= self._head:
            raise ValueError(f"frame {sequence} is not in the ring yet (head is {self._head})")
        if not self._intact(sequence):
            return None
        i = sequence % self.n_frames
        if out is None:
            out = np.empty(self.shape, self.dtype)
        np.copyto(out, self.frames[i])
        fid = int(self.frame_id[i])
        dts = int(self.device_ts_ns[i])
        hts = int(self.host_ts_ns[i])
        flags = int(self.flags[i])
        missing = int(self.missing_bytes[i])
        if not self._intact(sequence) or self.sequence[i] != sequence:
            return None  # the writer started overwriting the slot while we copied it
        return RingFrame(out, sequence, fid, None if dts < 0 else dts, hts, FrameFlags(flags), missing_bytes=missing)

    def latest(self, timeout_s: float = 0.0, out: Optional[np.ndarray] = None) -> Optional[RingFrame]:
        """The newest frame not yet returned by ``latest`` (the processing worker's policy).

        Waits at most ``timeout_s`` seconds for one; returns None when none came
        (or the ring is closed). Frames it jumps over are added to :attr:`latest_skipped`.
        """
        deadline = time.monotonic() + max(0.0, float(timeout_s))
        while True:
            head = self._head
            if head - 1 > self._latest_seq:
                seq = head - 1
                frame = self.copy(seq, out)
                if frame is not None:
                    if self._latest_seq >= 0:
                        self.latest_skipped += seq - self._latest_seq - 1
                    else:
                        self.latest_skipped += seq
                    self._latest_seq = seq
                    return frame
                continue  # overwritten while copying (ring of 2 at full speed): take the newer one
            left = deadline - time.monotonic()
            if left <= 0 or self._closed:
                return None
            self.wait_for(head, left)

    def cursor(self, start: Optional[int] = None) -> "RingCursor":
        """A consumer that reads every frame in order from sequence ``start`` (default: the next frame)."""
        return RingCursor(self, self._head if start is None else int(start))


class RingCursor:
    """Reads every frame of a :class:`RingBuffer` in order; overruns are detected and counted.

    Attributes
    ----------
    next_sequence : int
        Sequence number of the next frame :meth:`read` returns.
    lost : int
        Frames this cursor lost to ring overwrites so far (exact count).
    lost_events : list of (int, int)
        ``(first_lost_sequence, count)`` per overrun.
    read_count : int
        Frames returned so far.
    """

    def __init__(self, ring: RingBuffer, start: int):
        if start < 0:
            raise ValueError(f"cursor start must be a sequence number >= 0; got {start}")
        self.ring = ring
        self.next_sequence = int(start)
        self.lost = 0
        self.lost_events: list = []
        self.read_count = 0
        self._pending = 0  # losses not yet reported on a returned frame

    @property
    def backlog(self) -> int:
        """Frames committed but not yet read by this cursor (capped at the ring size)."""
        return max(0, min(self.ring.head - self.next_sequence, self.ring.n_frames))

    def read(self, timeout_s: float, out: Optional[np.ndarray] = None) -> Optional[RingFrame]:
        """The next frame in order, waiting at most ``timeout_s`` seconds.

        Returns None on timeout. Raises :class:`RingClosed` when the ring is
        closed and this cursor has read everything committed before closing.
        """
        ring = self.ring
        while True:
            seq = self.next_sequence
            if seq >= ring.head:
                if ring.closed:
                    if seq >= ring.head:
                        msg = ring.error or "acquisition stopped"
                        raise RingClosed(f"no more frames after sequence {seq - 1}: {msg}", ring.error)
                    continue
                if not ring.wait_for(seq, timeout_s) and not ring.closed:
                    return None
                continue
            oldest = ring.oldest
            if seq < oldest:
                self._record_loss(seq, oldest - seq)
                self.next_sequence = oldest
                continue
            frame = ring.copy(seq, out)
            if frame is None:  # overwritten while copying: skip it, count it
                self._record_loss(seq, 1)
                self.next_sequence = seq + 1
                continue
            if self._pending:
                frame.flags |= FrameFlags.RING_OVERRUN_BEFORE
                frame.lost_before = self._pending
                self._pending = 0
            self.next_sequence = seq + 1
            self.read_count += 1
            return frame

    def _record_loss(self, first: int, count: int) -> None:
        self.lost += count
        self._pending += count
        if self.lost_events and self.lost_events[-1][0] + self.lost_events[-1][1] == first:
            f0, c0 = self.lost_events[-1]
            self.lost_events[-1] = (f0, c0 + count)
        else:
            self.lost_events.append((first, count))


def ceil_frames(seconds: float, frame_rate_hz: float) -> int:
    """Frames needed to cover ``seconds`` at ``frame_rate_hz`` (rounded up)."""
    return int(math.ceil(float(seconds) * float(frame_rate_hz) - 1e-9))
