"""HDF5 recorder: every frame from the ring, in order, lossless or loudly counted.

Layout of the file: ``docs/recording-format.md``. Two levels:

* :class:`RecordingFile` -- the file itself (no threads): creates the layout,
  appends frames (one HDF5 chunk per frame, written with
  ``write_direct_chunk``, no int32 offsets anywhere, files > 4 GB are normal),
  keeps the frame table, flushes, writes the summary, and never overwrites an
  existing file.
* :class:`Recorder` -- a writer thread that reads the ring buffer through a
  :class:`~app.capture.ringbuffer.RingCursor` (its bounded, lossless queue: it
  never drops a frame itself; when it falls behind, the backlog is logged
  loudly, and if the camera laps it the lost frames are counted exactly and
  flagged on the next frame) and writes a :class:`RecordingFile`.

Crash safety: data and frame-table rows are flushed every ``flush_interval_s``;
only then is ``frames_written`` advanced (attribute on ``/frames`` and on the
root). A process killed with SIGKILL or a full disk leaves a file that opens
with plain ``h5py.File(path, "r")`` and is valid up to ``frames_written``
(we do not use SWMR: a crashed SWMR writer leaves a file that HDF5 refuses to
open until ``h5clear`` resets it).

Full disks: the space a recording needs is allocated on disk ahead of HDF5
(``fallocate``; the whole planned file at the start, else in steps), so a
disk filled by another program makes *that* program fail, or stops the
recording cleanly while the space to close the file is still in hand. HDF5
itself never meets a full disk on a file system that can reserve space. If a
write fails anyway (I/O error, no fallocate), :meth:`RecordingFile.close`
writes nothing more (see there) and the file stays as the last flush left it.
Room, reservation and the superblock repair are :mod:`app.files.h5safe`'s,
shared with the batch writer.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
import zlib
from pathlib import Path
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np

from app.files import h5safe
from app.files.h5safe import (  # noqa: F401  (FS_MAX_FILE_BYTES, filesystem_type: importable from here as before)
    FS_MAX_FILE_BYTES,
    Preallocation,
    SpaceReserve,
    file_size_limit,
    filesystem_type,
    fit_to_eoa,
    max_file_bytes,
    repair_eof,
    room_bytes,
)
from drivers.base import FrameFlags

from .ringbuffer import RingBuffer, RingClosed, RingFrame, format_bytes

__all__ = [
    "FORMAT_VERSION",
    "FRAME_TABLE_DTYPE",
    "RecorderError",
    "DiskSpaceError",
    "DiskFullError",
    "RecordingFile",
    "Recorder",
    "unique_path",
    "software_version",
    "read_summary",
    "format_summary",
    "summary_rows",
]

log = logging.getLogger("tirdeflect.recorder")

FORMAT_VERSION = "1.2"  # 1.1: frame_table.missing_bytes; 1.2: frame_table.crc32, /reference crc32

#: one row per frame of ``/frame_table``
FRAME_TABLE_DTYPE = np.dtype(
    [
        ("sequence", "<i8"),  # host sequence number (contiguous over what the camera thread got)
        ("frame_id", "<i8"),  # camera frame/block id
        ("device_timestamp_ns", "<i8"),  # device clock, -1 when missing (flag NO_DEVICE_TIMESTAMP)
        ("host_timestamp_ns", "<i8"),  # time.monotonic_ns() at reception
        ("flags", "<u4"),  # drivers.base.FrameFlags
        ("trigger_index", "<i8"),  # frames from the trigger frame (0), negative before it
        ("missing_bytes", "<i8"),  # image bytes lost on the way (flag INCOMPLETE; their pixels are 0), else 0
        ("crc32", "<u4"),  # zlib.crc32 of the frame's bytes as stored in /frames (checked when read)
    ]
)

#: file-system overhead allowed on top of the raw frame bytes when checking free space
SPACE_MARGIN_BYTES = 16 * 1024 * 1024


class RecorderError(RuntimeError):
    """Recording could not start or failed; the message says what happened and what to do."""


class DiskSpaceError(RecorderError):
    """Not enough free space for the planned recording."""


class DiskFullError(DiskSpaceError, h5safe.DiskFullError):
    """The disk (or the file-size limit) ran out during the recording; the file is closed valid.

    Both a :class:`RecorderError` and the one :class:`app.files.h5safe.DiskFullError`.
    """


#: space kept allocated beyond the data so that the file can always be closed validly (trim, events, summary)
RESERVE_BYTES = 4 * 1024 * 1024

#: smallest step in which space is allocated ahead of the data when the length is not known, bytes
RESERVE_STEP_BYTES = 64 * 1024 * 1024


def software_version() -> str:
    """tirdeflect's version (see :func:`app.version`)."""
    from app import version

    return version()


def unique_path(path) -> Path:
    """``path`` if it does not exist, else ``name-001.ext``, ``name-002.ext`` ... (first free one)."""
    p = Path(path)
    if not p.exists():
        return p
    for i in range(1, 10000):
        q = p.with_name(f"{p.stem}-{i:03d}{p.suffix}")
        if not q.exists():
            return q
    raise RecorderError(f"no free file name like {p.stem}-NNN{p.suffix} in {p.parent}; clean up the folder")


def _attr_value(v):
    if v is None:
        return "None"
    if isinstance(v, (bool, np.bool_)):
        return int(v)
    if isinstance(v, (int, float, str, np.integer, np.floating)):
        return v
    return json.dumps(v, default=str)


class RecordingFile:
    """One HDF5 recording (see ``docs/recording-format.md``); not thread-safe, one writer.

    Parameters
    ----------
    path : str or Path
        Where to write. Never overwritten: an existing file raises
        :class:`RecorderError` (``on_exists="error"``) or a free name
        ``name-NNN.h5`` is chosen (``on_exists="rename"``); see :attr:`path`.
    shape : (int, int)
        Frame shape (rows, cols) in pixels.
    dtype : numpy dtype
        ``uint8`` or ``uint16``.
    n_frames : int or None
        Planned number of frames (preallocated extent; the free space check uses
        it). None: unknown, the datasets grow.
    bit_depth : int
        Significant bits per pixel.
    check_space : bool
        Refuse (:class:`DiskSpaceError`) when the disk has less free space than
        the planned size.
    camera_id : str
    camera_settings : dict, optional
        ``CameraSettings.as_dict()``, stored as attributes of ``/camera``.
    geometry_toml : str, optional
        Geometry as TOML text, stored as ``/geometry_toml``.
    reference_image : ndarray (rows, cols), optional
        Stored as ``/reference``.
    attrs : dict, optional
        Extra root attributes (trigger source, pre/post frames, frame rate ...).
    """

    def __init__(
        self,
        path,
        *,
        shape,
        dtype,
        n_frames: Optional[int] = None,
        bit_depth: Optional[int] = None,
        check_space: bool = True,
        on_exists: str = "error",
        camera_id: str = "",
        camera_settings: Optional[dict] = None,
        geometry_toml: Optional[str] = None,
        reference_image: Optional[np.ndarray] = None,
        attrs: Optional[dict] = None,
    ):
        import h5py

        p = Path(path)
        if on_exists not in ("error", "rename"):
            raise ValueError(f"on_exists must be 'error' or 'rename'; got {on_exists!r}")
        if p.exists():
            if on_exists == "error":
                raise RecorderError(
                    f"{str(p)!r} already exists and recordings are never overwritten; "
                    "choose another file name (or let tirdeflect number it: --auto-name)"
                )
            p = unique_path(p)
        if not p.parent.is_dir():
            raise RecorderError(f"folder {str(p.parent)!r} does not exist; create it or choose another --out")
        self.shape = (int(shape[0]), int(shape[1]))
        self.dtype = np.dtype(dtype)
        if self.dtype not in (np.dtype(np.uint8), np.dtype(np.uint16)):
            raise ValueError(f"recording dtype must be uint8 or uint16; got {self.dtype}")
        self.bit_depth = int(bit_depth or self.dtype.itemsize * 8)
        self.frame_bytes = self.shape[0] * self.shape[1] * self.dtype.itemsize
        self.n_planned = None if n_frames is None else int(n_frames)
        if self.n_planned is not None and self.n_planned < 1:
            raise ValueError(f"n_frames must be >= 1 or None; got {n_frames}")
        extra = 0 if reference_image is None else np.asarray(reference_image).nbytes
        self.planned_bytes = (
            None
            if self.n_planned is None
            else self.n_planned * (self.frame_bytes + FRAME_TABLE_DTYPE.itemsize) + extra + SPACE_MARGIN_BYTES
        )
        self._fs_max_bytes = max_file_bytes(p.parent)
        if check_space and self.planned_bytes is not None:
            free, what = room_bytes(p, 0, self._fs_max_bytes)
            if self.planned_bytes > free:
                where = f"on {str(p.parent)!r}" if what == "disk" else f"under the {what}"
                raise DiskSpaceError(
                    f"recording {self.n_planned} frames of {self.shape[0]}x{self.shape[1]} {self.dtype} needs "
                    f"{format_bytes(self.planned_bytes)} ({self.planned_bytes} bytes) but only {format_bytes(free)} "
                    f"({free} bytes) are free {where}; free space, record fewer frames or "
                    "choose another disk"
                )
        # "w-": fail if the file appeared since we looked (never overwrite); with "rename", the next free
        # name then (by-hand trial of 7 Dec 2026: of three recordings started at once with --auto-name, one
        # failed on the name another had just taken, told to add the --auto-name it had)
        for attempt in range(1000):
            try:
                self._f = h5safe.create_h5(p, "w-", libver="earliest",
                                           remedy="free disk space or choose another folder (one you can write to)")
                break
            except FileExistsError as exc:
                if on_exists != "rename" or attempt == 999:
                    raise RecorderError(f"cannot create {str(p)!r}: {exc}; choose another file name or folder") from exc
                p = unique_path(path)  # the first free name of the one asked for
            except h5safe.OutputLocationError as exc:  # says why from the errno, not HDF5's text
                # HDF5 created the file but could not write its first block (disk full): leave nothing behind
                try:
                    if p.exists() and p.stat().st_size < 4096:
                        p.unlink()
                except OSError:
                    pass
                raise RecorderError(str(exc)) from exc
        self.path = p
        f = self._f
        cap = self.n_planned if self.n_planned is not None else 256
        self._capacity = cap
        self.frames = f.create_dataset(
            "frames",
            shape=(cap,) + self.shape,
            maxshape=(None,) + self.shape,
            chunks=(1,) + self.shape,
            dtype=self.dtype,
            fillvalue=0,
        )
        self.table = f.create_dataset(
            "frame_table",
            shape=(cap,),
            maxshape=(None,),
            chunks=(min(max(cap, 1), 4096),),
            dtype=FRAME_TABLE_DTYPE,
            fillvalue=np.array((-1, -1, -1, -1, 0, 0, 0, 0), dtype=FRAME_TABLE_DTYPE),
        )
        fa = self.frames.attrs
        fa["frames_written"] = 0
        fa["frames_planned"] = -1 if self.n_planned is None else self.n_planned
        fa["bit_depth"] = self.bit_depth
        fa["axes"] = "frame, row, col"
        ra = f.attrs
        ra["format"] = "tirdeflect-recording"
        ra["format_version"] = FORMAT_VERSION
        ra["software"] = "tirdeflect"
        ra["software_version"] = software_version()
        ra["created_utc"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
        ra["camera_id"] = camera_id
        ra["bit_depth"] = self.bit_depth
        ra["frames_written"] = 0
        ra["complete"] = 0
        ra["error"] = ""
        for k, v in (attrs or {}).items():
            ra[k] = _attr_value(v)
        cam = f.create_group("camera")
        cam.attrs["camera_id"] = camera_id
        settings = dict(camera_settings or {})
        for k, v in settings.items():
            cam.attrs[k] = _attr_value(v)
        cam.attrs["settings_json"] = json.dumps(settings, default=str)
        if geometry_toml is not None:
            f.create_dataset("geometry_toml", data=str(geometry_toml), dtype=h5py.string_dtype())
        if reference_image is not None:
            ref = np.ascontiguousarray(reference_image)
            f.create_dataset("reference", data=ref)
            f["reference"].attrs["crc32"] = np.uint32(zlib.crc32(ref) & 0xFFFFFFFF)  # checked when read
        self.n_written = 0  # frames written (data + table row in memory)
        self.n_flushed = 0  # frames known to be on disk (frames_written)
        self._rows = np.empty(1024, dtype=FRAME_TABLE_DTYPE)
        self._rows_start = 0  # file row of self._rows[0]
        self._n_rows = 0
        self.events: List[dict] = []
        self.closed = False
        self.failed = False  # a write failed: HDF5 may hold half-done allocations
        f.flush()
        # Space is reserved on disk ahead of HDF5 (fallocate), so that another program filling the disk
        # gets "disk full" instead of us, and so that closing (trim, events, summary) always has room.
        self._fd = h5safe.descriptor_of(self._f)  # None: another HDF5 driver, no reservation
        self._alloc = Preallocation(self._fd, os.path.getsize(p), file_size_limit(self._fs_max_bytes))
        self._spare: Optional[SpaceReserve] = None  # the hidden reserve file (file systems without fallocate)
        if self.planned_bytes is not None and not self._reserve(self.planned_bytes, step=0):
            if check_space:  # the disk filled between the check above and now
                self._abandon()
                raise DiskSpaceError(
                    f"cannot reserve {format_bytes(self.planned_bytes)} on {str(p.parent)!r} for {self.n_planned} "
                    "frames: the disk is full; free space, record fewer frames or choose another disk"
                )

    # ------------------------------------------------------------ space
    def _reserve(self, end: int, more: int = 0, step: int = RESERVE_STEP_BYTES) -> bool:
        """Make sure the ``more`` bytes past ``end`` are allocated on disk (ahead in steps of
        ``step`` bytes where it can); False when there is no room.

        Never asks for more than the file-size limit (that would raise SIGXFSZ).
        A file system without fallocate turns reservation off: then
        :meth:`_check_room` compares with the free space instead, and a
        reserve file is made (:meth:`_make_reserve_file`).
        """
        could = self._alloc.supported
        ok = self._alloc.make_room(end, more, step)
        if could and not self._alloc.supported:
            log.info("recording %s: the file system cannot reserve space; checking free space instead", self.path)
            self._make_reserve_file()
        return ok

    def _make_reserve_file(self) -> None:
        """Without fallocate: hold ``RESERVE_BYTES`` in a hidden sibling file, given back when the disk is full.

        The space it frees is what the final flush, trim and summary are
        written into; without it, HDF5 could be cut off halfway through
        writing its metadata.
        """
        self._spare = SpaceReserve(self.path, RESERVE_BYTES)

    def _release_reserve(self) -> bool:
        """Give the reserve file's space to the file system (for closing); True if there was one."""
        spare, self._spare = self._spare, None
        return spare is not None and spare.release()

    def _abandon(self) -> None:
        """Close and delete a file that never held a frame (creation could not complete)."""
        self._release_reserve()
        try:
            self._f.close()
        except Exception:
            pass
        try:
            os.unlink(self.path)
        except OSError:
            pass
        self.closed = True

    # ------------------------------------------------------------ writing
    def _grow(self, need: int) -> None:
        cap = self._capacity
        while cap < need:
            cap = max(cap * 2, 256)
        self.frames.resize(cap, axis=0)
        self.table.resize(cap, axis=0)
        self._capacity = cap

    def write(self, image: np.ndarray, row: tuple) -> int:
        """Append one frame and its frame-table row; returns its index in the file.

        ``row`` = (sequence, frame_id, device_timestamp_ns or -1, host_timestamp_ns, flags, trigger_index
        [, missing_bytes]).
        Raises :class:`DiskFullError` (nothing written, the file closes
        normally) when no room can be reserved for the frame, OSError from HDF5
        (I/O error; :attr:`failed` is set and :meth:`close` writes nothing
        more); the file stays valid up to the last :meth:`flush`.
        """
        if self.failed:
            raise RecorderError(f"{str(self.path)!r}: a write failed before; the file takes no more frames")
        i = self.n_written
        if image.shape != self.shape or image.dtype != self.dtype:
            raise RecorderError(
                f"frame {row[0]} is {image.dtype} {image.shape}; the recording holds {self.dtype} {self.shape}"
            )
        self._check_room()
        try:
            if i >= self._capacity:
                self._grow(i + 1)
            image = np.ascontiguousarray(image)
            self.frames.id.write_direct_chunk((i, 0, 0), image)
        except OSError as exc:
            if self._release_reserve():
                # disk full on a file system that cannot reserve: frame i is not counted; the reserve's
                # space lets close() flush, trim and summarize what was written
                raise self._disk_full(0, "disk") from exc
            self.failed = True
            raise
        if self._n_rows == len(self._rows):
            self._write_rows()
        self._rows[self._n_rows] = tuple(row) + (0,) * (len(FRAME_TABLE_DTYPE) - len(row))  # missing_bytes: 0
        # the frame's checksum, so that a reader finds pixels changed after recording (a bad disk,
        # a damaged copy); zlib's CRC32 runs at ~1.2 GB/s on one core and releases the GIL
        self._rows[self._n_rows]["crc32"] = zlib.crc32(image) & 0xFFFFFFFF
        self._n_rows += 1
        self.n_written = i + 1
        return i

    def _disk_full(self, room: int, what: str) -> DiskFullError:
        if what == "disk":
            remedy = "free disk space or choose another disk"
        elif what.startswith("file size limit"):
            remedy = "raise the limit (ulimit -f) or record fewer frames"
        else:
            remedy = "record to a disk whose file system holds larger files, or fewer frames"
        return DiskFullError(
            f"{what} full: {format_bytes(max(room, 0))} left for {str(self.path)!r} beyond the "
            f"{format_bytes(RESERVE_BYTES)} kept to close it validly; recording stopped after {self.n_written} frames"
            + (f" of {self.n_planned}" if self.n_planned else "") + f"; {remedy}"
        )

    def _check_room(self) -> None:
        """Stop (DiskFullError) before the disk or the file-size limit is so full that closing could fail.

        With reservation: the next frame plus ``RESERVE_BYTES`` for closing must
        lie inside the space already allocated to the file, else more is
        allocated (in steps of at least ``RESERVE_STEP_BYTES``); when that fails
        the recording stops here, with the reserve for closing still in hand.
        """
        frame = self.frame_bytes + FRAME_TABLE_DTYPE.itemsize
        alloc = self._alloc
        if alloc.supported:
            try:
                end = int(self._f.id.get_filesize())  # HDF5's end of allocation
            except Exception:
                end = alloc.allocated_bytes
            need = end + frame + RESERVE_BYTES
            if self._reserve(end, frame + RESERVE_BYTES):
                return
            room = alloc.allocated_bytes - end - RESERVE_BYTES
            what = "disk" if need <= alloc.limit_bytes else (
                "file size limit (ulimit -f)" if self._fs_max_bytes is None or alloc.limit_bytes < self._fs_max_bytes
                else f"file system's largest file ({format_bytes(self._fs_max_bytes)})")
            raise self._disk_full(room, what)
        size = max(os.path.getsize(self.path), alloc.allocated_bytes)
        room, what = room_bytes(self.path, size, self._fs_max_bytes)
        if room < frame + (0 if self._spare is not None and self._spare.held else RESERVE_BYTES):
            self._release_reserve()
            raise self._disk_full(room, what)

    def _write_rows(self) -> None:
        if self._n_rows:
            a = self._rows_start
            self.table[a : a + self._n_rows] = self._rows[: self._n_rows]
            self._rows_start = a + self._n_rows
            self._n_rows = 0

    def flush(self, *, stop_when_full: bool = True) -> None:
        """Put everything written so far on disk and advance ``frames_written``.

        If the disk was full and only the reserve file's space let the flush
        complete, raises :class:`DiskFullError` afterwards (the recording must
        stop), unless ``stop_when_full`` is False (closing).
        """
        if self.failed:
            raise RecorderError(f"{str(self.path)!r}: a write failed before; nothing more is written")
        n = self.n_written
        for attempt in (0, 1):
            try:
                self._write_rows()
                self._f.flush()  # frame data and table rows first ...
                self.frames.attrs["frames_written"] = n  # ... then the counter that vouches for them
                self._f.attrs["frames_written"] = n
                self._f.flush()
                break
            except OSError as exc:
                # HDF5 keeps what it could not write dirty: with the reserve's space it writes it all again
                if attempt == 0 and self._release_reserve():
                    continue
                self.failed = True
                raise
        self.n_flushed = n
        if self._fd is not None:  # written once, read back by nobody here: out of the page cache
            h5safe.drop_written_pages(self._fd)
        if attempt == 1 and stop_when_full:
            raise self._disk_full(0, "disk")

    def add_event(self, kind: str, message: str = "", *, sequence: int = -1, host_timestamp_ns: Optional[int] = None,
                  **extra) -> None:
        """Remember an event (trigger, error, note); all events go to ``/events`` at :meth:`close`."""
        ev = dict(kind=kind, message=message, sequence=int(sequence),
                  host_timestamp_ns=int(time.monotonic_ns() if host_timestamp_ns is None else host_timestamp_ns))
        ev.update(extra)
        self.events.append(ev)

    def set_attrs(self, **attrs) -> None:
        """Set root attributes (e.g. trigger sequence once the trigger came)."""
        if self.failed:
            return
        for k, v in attrs.items():
            self._f.attrs[k] = _attr_value(v)

    def close(self, summary: Optional[dict] = None, error: Optional[str] = None) -> None:
        """The one way a recording ends: after success, a stop, a full disk or an I/O error.

        While no write has failed: flush, trim the datasets to what was
        written, store the error, events and summary (all inside the space
        reserved for closing). Once any write failed (:attr:`failed`), nothing
        more reaches the file: HDF5's descriptor is swapped for /dev/null
        before HDF5 closes, so the file stays exactly as the last successful
        flush left it (superblock, frame table and ``frames_written`` agree).
        Then the file is reopened read-only to check it; :attr:`n_flushed` is
        what it really holds. Never raises.
        """
        if self.closed:
            return
        import h5py

        f = self._f
        self.problems: List[str] = []
        if not self.failed:
            try:
                self.flush(stop_when_full=False)
            except Exception as exc:
                self.failed = True
                self.problems.append(f"final flush failed: {exc}")
        if not self.failed:
            try:
                n = self.n_flushed
                if n != self._capacity:
                    self.frames.resize(n, axis=0)
                    self.table.resize(n, axis=0)
                    self._capacity = n
                complete = error is None and (self.n_planned is None or n == self.n_planned)
                f.attrs["complete"] = int(complete)
                if summary is not None:  # complete and nothing lost on the way: what `record`'s exit 0 says
                    f.attrs["lossless"] = int(complete and not summary.get("total_missing") and not
                                              summary.get("incomplete"))
                f.attrs["error"] = error or ""
                if self.events:
                    f.create_dataset("events", data=[json.dumps(e, default=str) for e in self.events],
                                     dtype=h5py.string_dtype())
                if summary is not None:
                    g = f.create_group("summary")
                    for k, v in summary.items():
                        g.attrs[k] = _attr_value(v)
                    g.attrs["summary_json"] = json.dumps(summary, default=str)
                f.flush()
            except Exception as exc:
                self.failed = True
                self.problems.append(f"writing the summary failed: {exc}")
        if self.failed:
            self._detach()
        self.closed = True
        self.frames = self.table = None
        try:
            f.close()
        except Exception as exc:
            if not self.failed:
                self.problems.append(f"closing failed: {exc}")
        self._f = None
        self._release_reserve()
        self._check_closed_file()
        for msg in self.problems:
            log.error("recording %s: %s", self.path, msg)

    def _detach(self) -> None:
        """Point HDF5's descriptor at /dev/null: what HDF5 still writes while closing never reaches the file."""
        if self._fd is None:
            return
        try:
            h5safe.detach_descriptor(self._fd)
        except OSError as exc:  # pragma: no cover - the file vanished
            log.error("recording %s: could not stop HDF5 writing: %s", self.path, exc)

    def _check_closed_file(self) -> None:
        """Reopen the closed file read-only; repair the superblock's end address if HDF5 left it short.

        Sets :attr:`n_flushed` to the frames the file really vouches for
        (``frames_written``, frame-table rows with sequence numbers).
        """
        import h5py

        def frames_valid():
            with h5py.File(self.path, "r") as g:
                n = int(g["frames"].attrs.get("frames_written", 0))
                if n > min(len(g["frames"]), len(g["frame_table"])):
                    raise RecorderError(f"frames_written {n} exceeds the datasets")
                seq = g["frame_table"]["sequence"][:n] if n else np.zeros(0, np.int64)
                return n if np.all(seq >= 0) else int(np.argmax(seq < 0))

        found: List[int] = []
        try:
            n = frames_valid()
        except Exception as exc:
            # patch the superblock (app.files.h5safe.repair_eof), checking with frames_valid; else left as it was
            if not repair_eof(self.path, check=lambda _path: found.append(frames_valid())):
                self.problems.append(f"the file does not open after closing ({exc}); no frame can be vouched for")
                self.n_flushed = 0
                return
            n = found[-1]
            self.problems.append("the superblock's end address was short of the data; raised it to cover the data")
        else:
            fit_to_eoa(self.path)
        self.n_flushed = n


class Recorder:
    """Writer thread: ring cursor -> :class:`RecordingFile`, every frame in order.

    Parameters
    ----------
    ring : RingBuffer
        The ring the camera thread fills (``acquisition.ring``).
    path : str or Path
        Output file; never overwritten (see :class:`RecordingFile`).
    n_frames : int or None
        Frames to record (from ``start_sequence``); None: until :meth:`stop`.
    acquisition : Acquisition, optional
        For the camera id, settings and counters in the summary.
    flush_interval_s : float
        Seconds between flushes (what a crash can lose at most).
    defer : bool
        Burst-to-RAM: do not write while the camera runs; wait until all
        ``n_frames`` are in the ring (or the acquisition ended), then write
        them out (``progress`` reports it). Use when the disk is slower than
        the camera and the burst fits into the ring.
    backlog_warn_fraction : float
        Log a warning when the backlog exceeds this fraction of the ring.
    progress : callable, optional
        ``progress(frames_written, n_frames_planned)`` from the writer thread.
    **file_options
        Passed to :class:`RecordingFile` (``check_space``, ``on_exists``,
        ``geometry_toml``, ``reference_image``, ``attrs``, ``camera_id``,
        ``camera_settings``).

    Publishes: ``state`` ("armed", "recording", "done", "error"), ``error``,
    ``frames_written``, ``lost_overrun`` (frames lost to ring overwrite),
    ``backlog`` and ``backlog_max`` (frames), ``backlog_warnings``, ``path``,
    :meth:`summary`. Takes: :meth:`begin`, :meth:`stop`, :meth:`wait`.
    """

    def __init__(
        self,
        ring: RingBuffer,
        path,
        *,
        n_frames: Optional[int] = None,
        acquisition=None,
        flush_interval_s: float = 0.5,
        defer: bool = False,
        backlog_warn_fraction: float = 0.5,
        progress: Optional[Callable[[int, Optional[int]], None]] = None,
        read_timeout_s: float = 0.2,
        **file_options,
    ):
        if defer and n_frames is None:
            raise ValueError("defer=True (burst to RAM) needs n_frames: the burst must have a known length")
        if defer and n_frames is not None and n_frames > ring.n_frames:
            raise RecorderError(
                f"burst of {n_frames} frames does not fit into the ring of {ring.n_frames} frames; "
                "enlarge the ring (--ring-frames / more memory) or record without --burst"
            )
        self.ring = ring
        self.acquisition = acquisition
        self.n_frames = None if n_frames is None else int(n_frames)
        self.flush_interval_s = float(flush_interval_s)
        self.defer = bool(defer)
        self.backlog_warn_fraction = float(backlog_warn_fraction)
        self.progress = progress
        self.read_timeout_s = float(read_timeout_s)
        if acquisition is not None:
            file_options.setdefault("camera_id", acquisition.camera.camera_id)
            file_options.setdefault("camera_settings", acquisition.settings.as_dict())
            file_options.setdefault("bit_depth", acquisition.settings.bit_depth)
        self.file = RecordingFile(path, shape=ring.shape, dtype=ring.dtype, n_frames=self.n_frames, **file_options)
        self.path = self.file.path
        self.state = "armed"
        self.error: Optional[str] = None
        self.frames_written = 0
        self.lost_overrun = 0
        self.backlog = 0
        self.backlog_max = 0
        self.backlog_warnings = 0
        self.start_sequence: Optional[int] = None
        self.trigger_sequence: Optional[int] = None
        self._count_back_from: Optional[int] = None  # a stop before the trigger: trigger_index counts back from it
        self._cursor = None
        self._thread: Optional[threading.Thread] = None
        self._stop = threading.Event()
        self._stop_at: Optional[int] = None
        self._stop_error: Optional[str] = None  # why stop() ended it early, when that is an error (see there)
        self._done = threading.Event()
        self._t_begin = None
        self._t_end = None
        self._summary: Optional[dict] = None
        self._last_overrun_log = -1e9
        self._stats = dict(id_gap_frames=0, id_gap_events=0, missing_ids=[], time_gaps=0, lost_by_time=0,
                           incomplete=0, missing_bytes=0, no_timestamp=0, overrun_events=[])

    # ----------------------------------------------------------- commands
    def begin(self, start_sequence: Optional[int] = None, *, trigger_sequence: Optional[int] = None,
              attrs: Optional[dict] = None, stop_error: Optional[str] = None,
              stop_at: Optional[int] = None, count_back_from: Optional[int] = None) -> "Recorder":
        """Start writing from ring sequence ``start_sequence`` (default: the next frame).

        The ring cursor takes hold of the start first; then the file's attributes (``trigger_sequence``,
        ``pre_available``, ``start_sequence`` and ``attrs``) are written, before the writing thread starts.
        ``stop_error``: the recording begins only to keep what the ring holds after a failure (the camera
        lost before the trigger); why, stored as the file's error as by :meth:`stop`, also when the writer
        meets the ring's end before :meth:`stop` is called. ``stop_at``: the ring sequence it ends before, known
        when it begins (the frames a stopped capture keeps): the writer that reaches it first ends there, no
        error (a fresh-clone CI run saw "acquisition stopped after 12 of 22 frames" stored for a user's SIGTERM
        before the trigger, the writer at the ring's end before :meth:`stop` had said where it ends).
        ``count_back_from``: a triggered recording stopped before its trigger came (the frames the ring held are
        kept): the frames' ``trigger_index`` count back from this sequence (-N .. -1) while the file claims no
        trigger (no ``trigger_sequence`` nor ``pre_available`` attribute, no TRIGGER flag; docs/recording-format.md).
        """
        if self._thread is not None:
            raise RecorderError("this recorder already began; create a new one for another recording")
        if stop_error and self._stop_error is None:
            self._stop_error = str(stop_error)
        start = self.ring.head if start_sequence is None else int(start_sequence)
        if start < self.ring.oldest:
            raise RecorderError(
                f"recording should start at frame {start} but the ring only holds frames from {self.ring.oldest} "
                f"on ({self.ring.n_frames} frames): enlarge the ring or use fewer pre-trigger frames"
            )
        self.start_sequence = start
        self.trigger_sequence = trigger_sequence
        self._count_back_from = None if count_back_from is None else int(count_back_from)
        if stop_at is not None:
            self._stop_at = int(stop_at)
        self._cursor = self.ring.cursor(start)
        if trigger_sequence is not None:  # how many pre-trigger frames the file holds
            self.file.set_attrs(trigger_sequence=trigger_sequence, pre_available=trigger_sequence - start)
        self.file.set_attrs(start_sequence=start, **(attrs or {}))
        self.state = "recording"
        self._t_begin = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="tirdeflect-recorder", daemon=True)
        self._thread.start()
        return self

    def set_trigger(self, sequence: int, **event) -> None:
        """Tell the recorder which ring sequence is the trigger frame (index 0)."""
        self.trigger_sequence = int(sequence)
        self.file.add_event("trigger", sequence=sequence, **event)

    def stop(self, timeout_s: float = 10.0, *, drain: bool = True, error: Optional[str] = None) -> bool:
        """End the recording: write what is already in the ring (``drain``) and close; True if done in time.

        ``error``: why it ends before its planned length when that is a failure, not the user's stop (the
        camera lost before the trigger, the time limit run out). It is stored as the file's ``error``
        attribute and its end event (``complete`` 0), unless the writer met an error of its own first.
        """
        if error and self._stop_error is None:
            self._stop_error = str(error)
        if self._thread is None:
            self._finish(error=None)  # takes the stop's error
            return True
        self._stop_at = self.ring.head if drain else (self._cursor.next_sequence if self._cursor else 0)
        self._stop.set()
        return self._done.wait(timeout_s)

    def discard(self) -> None:
        """Give up before :meth:`begin`: delete the file, which holds no frame (a disarmed capture)."""
        if self._thread is not None:
            raise RecorderError("this recorder already began writing: stop() it, the frames it wrote are kept")
        self.file._abandon()
        self.state = "cancelled"
        self._summary = self.summary()
        self._done.set()

    def wait(self, timeout_s: float) -> bool:
        """Wait until the recording ended (complete, stopped or failed); True if it did."""
        return self._done.wait(timeout_s)

    @property
    def done(self) -> bool:
        return self._done.is_set()

    # -------------------------------------------------------------- thread
    def _index_origin(self) -> int:
        """The sequence whose frame has ``trigger_index`` 0: the trigger frame; else the stop a triggered
        recording ended at before its trigger came (its frames -N .. -1); else the first frame."""
        if self.trigger_sequence is not None:
            return self.trigger_sequence
        return self.start_sequence if self._count_back_from is None else self._count_back_from

    def _end_sequence(self) -> Optional[int]:
        ends = []
        if self.n_frames is not None:
            ends.append(self.start_sequence + self.n_frames)
        if self._stop_at is not None:
            ends.append(self._stop_at)
        return min(ends) if ends else None

    def _run(self) -> None:
        cur = self._cursor
        ring = self.ring
        rf = self.file
        buf = np.empty(ring.shape, ring.dtype)
        warn_at = max(1, int(self.backlog_warn_fraction * ring.n_frames))
        warned = False
        last_flush = time.monotonic()
        prev: Optional[RingFrame] = None
        error: Optional[str] = None
        try:
            if self.defer:
                end = self.start_sequence + self.n_frames
                while ring.head < end and not ring.closed and not self._stop.is_set():
                    ring.wait_for(end - 1, self.read_timeout_s)
            while True:
                end = self._end_sequence()
                if end is not None and cur.next_sequence >= end:
                    break
                if self._stop.is_set() and self._stop_at is None:
                    break
                try:
                    fr = cur.read(self.read_timeout_s, out=buf)
                except RingClosed as exc:
                    if self._stop_error is not None:
                        pass  # the end of the frames is what the error given to stop()/begin() explains
                    elif exc.error:
                        error = f"acquisition ended with an error: {exc.error}"
                    elif end is not None and self._stop_at is None:
                        error = (f"acquisition stopped after {self.frames_written} of {self.n_frames} frames "
                                 "were recorded")
                    break
                if fr is None:
                    continue
                if end is not None and fr.sequence >= end:
                    # the frames up to `end` were lost to overwrite; they are counted already
                    self._note_overrun(fr, end)
                    break
                if fr.lost_before:
                    self._note_overrun(fr, None)
                self._account(fr, prev)
                flags = int(fr.flags)
                if self.trigger_sequence is not None and fr.sequence == self.trigger_sequence:
                    flags |= FrameFlags.TRIGGER
                row = (fr.sequence, fr.frame_id, -1 if fr.device_timestamp_ns is None else fr.device_timestamp_ns,
                       fr.host_timestamp_ns, flags, fr.sequence - self._index_origin(), fr.missing_bytes)
                rf.write(fr.image, row)
                self.frames_written = rf.n_written
                if fr.frame_id >= 0:  # -1: id unknown (lost GigE leader); gaps are counted between known ids
                    prev = _keep_meta(fr)
                backlog = cur.backlog
                self.backlog = backlog
                if backlog > self.backlog_max:
                    self.backlog_max = backlog
                if backlog >= warn_at and not warned and not self.defer:
                    warned = True
                    self.backlog_warnings += 1
                    log.warning("recorder %s is %d frames behind the camera (ring holds %d): the disk is too "
                                "slow; frames will be lost if this goes on (use --burst)",
                                rf.path.name, backlog, ring.n_frames)
                elif backlog < warn_at // 2:
                    warned = False
                now = time.monotonic()
                if now - last_flush >= self.flush_interval_s:
                    rf.flush()
                    last_flush = now
                    if self.progress is not None:
                        self.progress(rf.n_flushed, self.n_frames)
        except DiskFullError as exc:
            error = str(exc)
            held = min(ring.head, self._end_sequence() or ring.head) - self.start_sequence - rf.n_written
            if self.defer and held > 0:  # (by-hand trial of 7 Dec 2026: said only as "stopped after 23 frames")
                error += (f"; the other {held} frames were captured into RAM (--burst) but there was no room to "
                          "write them: they are lost")
        except OSError as exc:
            error = (f"writing {str(rf.path)!r} failed at frame {rf.n_written} ({exc}); free disk space or "
                     "choose another disk")
        except Exception as exc:
            error = f"recorder crashed at frame {rf.n_written}: {type(exc).__name__}: {exc}"
        self._finish(error)

    def _note_overrun(self, fr: RingFrame, end: Optional[int]) -> None:
        cur = self._cursor
        self.lost_overrun = cur.lost if end is None else cur.lost - max(0, fr.sequence - end)
        self._stats["overrun_events"] = [list(e) for e in cur.lost_events]
        now = time.monotonic()
        if now - self._last_overrun_log >= 1.0:  # loud, but once a second, not once a frame
            self._last_overrun_log = now
            log.error("recorder %s lost frames to ring overwrite (the camera lapped the recorder): %d so far; "
                      "use --burst, a faster disk or a bigger ring", self.file.path.name, self.lost_overrun)

    def _account(self, fr: RingFrame, prev) -> None:
        st = self._stats
        flags = fr.flags
        if flags & FrameFlags.INCOMPLETE:
            st["incomplete"] += 1
            st["missing_bytes"] += int(fr.missing_bytes)
        if flags & FrameFlags.NO_DEVICE_TIMESTAMP:
            st["no_timestamp"] += 1
        if flags & FrameFlags.TIME_GAP_BEFORE:  # also before the first frame whose id is known (lost leaders)
            st["time_gaps"] += 1
        if prev is None:
            return
        seq_gap = fr.sequence - prev.sequence - 1  # lost to ring overwrite
        id_gap = fr.frame_id - prev.frame_id - 1
        upstream = id_gap - seq_gap
        if upstream > 0:
            st["id_gap_frames"] += upstream
            st["id_gap_events"] += 1
            if seq_gap == 0:
                st["missing_ids"].append([prev.frame_id + 1, upstream])
        if flags & FrameFlags.TIME_GAP_BEFORE:
            period = getattr(self.acquisition, "period_s", None) if self.acquisition is not None else None
            if period and fr.device_timestamp_ns is not None and prev.device_timestamp_ns is not None:
                n_periods = (fr.device_timestamp_ns - prev.device_timestamp_ns) * 1e-9 / period
                st["lost_by_time"] += max(0, int(round(n_periods)) - 1 - max(id_gap, 0))

    def _finish(self, error: Optional[str]) -> None:
        self._t_end = time.monotonic()
        error = error or self._stop_error  # the writer's own error first, else why stop() was called
        acq = self.acquisition
        if acq is not None and getattr(acq, "ending", False):
            # the camera stops after our last frame: wait (briefly) for its final transport counters
            # (packets resent, missing ...), so that the summary accounts for every packet
            acq.wait(2.0)
        if self._cursor is not None:
            # frames the cursor skipped inside the requested range [start, end) are lost
            events = [list(e) for e in self._cursor.lost_events]
            end = self._end_sequence()
            if end is not None:
                events = [[a, min(a + c, end) - a] for a, c in events if a < end]
            self._stats["overrun_events"] = events
            self.lost_overrun = sum(c for _, c in events)
        summary = self.summary(error=error)
        if error is None and self.n_frames is not None and self.frames_written < self.n_frames and \
                self.lost_overrun == 0 and self._stop_at is None:
            error = f"only {self.frames_written} of {self.n_frames} frames were recorded"
        try:
            self.file.add_event("end", error or "ok", sequence=(self._cursor.next_sequence - 1) if self._cursor else -1)
            self.file.close(summary=summary, error=error)
        except Exception as exc:  # pragma: no cover - close never raises, but be sure
            error = error or f"closing the file failed: {exc}"
        self.frames_written = self.file.n_flushed
        summary["frames_written"] = self.frames_written
        if self.file.failed or getattr(self.file, "problems", None):
            # say what the file really holds (checked by reopening it), and why nothing more was stored
            extra = "; ".join(getattr(self.file, "problems", []))
            error = (error or "writing the file failed") + (f"; {extra}" if extra else "") + (
                f"; the file holds {self.frames_written} valid frames (checked by reopening it; nothing was "
                "written after the failure, so it has no /summary)")
            summary["error"] = error
        self._summary = summary
        self.error = error
        self.state = "error" if error else "done"
        if self.progress is not None:
            try:
                self.progress(self.frames_written, self.n_frames)
            except Exception:
                pass
        if error:
            log.error("recording %s: %s", self.path, error)
        self._done.set()

    # ------------------------------------------------------------- summary
    def summary(self, error: Optional[str] = None) -> dict:
        """Drop summary of this recording (also stored in the file as ``/summary``)."""
        if self._summary is not None and error is None:
            return dict(self._summary)
        st = self._stats
        elapsed = ((self._t_end or time.monotonic()) - self._t_begin) if self._t_begin else 0.0
        written = self.file.n_written
        s = dict(
            path=str(self.path),
            frames_planned=-1 if self.n_frames is None else self.n_frames,
            frames_written=written,
            start_sequence=-1 if self.start_sequence is None else self.start_sequence,
            trigger_sequence=-1 if self.trigger_sequence is None else self.trigger_sequence,
            lost_upstream_id_gaps=st["id_gap_frames"],
            id_gap_events=st["id_gap_events"],
            missing_frame_ids=st["missing_ids"],
            time_gaps=st["time_gaps"],
            lost_by_time_estimate=st["lost_by_time"],
            incomplete=st["incomplete"],
            incomplete_missing_bytes=st["missing_bytes"],
            frame_bytes=self.file.frame_bytes,
            no_device_timestamp=st["no_timestamp"],
            lost_ring_overrun=self.lost_overrun,
            ring_overrun_events=st["overrun_events"],
            recorder_backlog_max=self.backlog_max,
            recorder_backlog_warnings=self.backlog_warnings,
            ring_frames=self.ring.n_frames,
            elapsed_s=round(elapsed, 3),
            write_rate_mb_s=round(written * self.file.frame_bytes / elapsed / 1e6, 1) if elapsed > 0 else 0.0,
            error=error or "",
        )
        if self.acquisition is not None:
            a = self.acquisition.stats()
            cs = a.get("camera_statistics", {})
            s["camera_statistics"] = cs
            s["acquisition_fps"] = round(a.get("fps", 0.0), 2)
            if a.get("delivered_rate_hz") and a.get("set_rate_hz"):  # slower than set (app.capture.acquisition)
                s["delivered_rate_hz"] = round(float(a["delivered_rate_hz"]), 3)
                s["set_rate_hz"] = round(float(a["set_rate_hz"]), 3)
            for key, name in (("n_resend_requests", "packets_resend_requests"), ("n_resent_packets", "packets_resent"),
                              ("n_missing_packets", "packets_missing")):
                if key in cs:
                    s[name] = cs[key]
        # exact counts only; timestamp gaps are an estimate (a late frame also makes one) and are reported apart
        s["total_missing"] = s["lost_upstream_id_gaps"] + s["lost_ring_overrun"]
        return s


def _keep_meta(fr: RingFrame) -> RingFrame:
    """Remember the previous frame's metadata without keeping a reference to the reused image buffer."""
    return RingFrame(None, fr.sequence, fr.frame_id, fr.device_timestamp_ns, fr.host_timestamp_ns, fr.flags)


def summary_rows(s: dict) -> List[Tuple[str, str]]:
    """A recording's summary as (what, value) rows, after its first line ``recording PATH``: the CLI prints
    them as columns (:func:`format_summary`), the window as a table whose values wrap in their cell."""
    planned = s.get("frames_planned", -1)
    rows = [
        ("frames written", f"{s.get('frames_written', 0)}" + (f" of {planned} planned" if planned and planned > 0 else "")),
        ("lost upstream", f"{s.get('lost_upstream_id_gaps', 0)} (camera frame-id gaps"
         + (f"; missing ids {_ranges(s.get('missing_frame_ids', []))}" if s.get("missing_frame_ids") else "") + ")"),
        ("timestamp gaps", f"{s.get('time_gaps', 0)} (about {s.get('lost_by_time_estimate', 0)} frames "
         "missing beyond the id gaps)"),
        ("incomplete", _incomplete_text(s)),
        ("ring overrun", f"{s.get('lost_ring_overrun', 0)} frames lost (recorder backlog max "
         f"{s.get('recorder_backlog_max', 0)} of {s.get('ring_frames', 0)})"),
        ("data rate", f"{s.get('write_rate_mb_s', 0)} MB/s on average over {s.get('elapsed_s', 0)} s"),
    ]
    if s.get("no_device_timestamp", 0) > 0:  # (by-hand trial of 7 Dec 2026: 31 of 150 frames, said nowhere)
        rows.insert(-1, ("no timestamp", f"{s['no_device_timestamp']} frames without the camera's timestamp (their "
                                         "leader packet lost): their times are the host's, less exact"))
    if s.get("delivered_rate_hz"):
        rows.insert(1, ("frame rate", f"the camera delivered {s['delivered_rate_hz']:.4g} frames/s, not the "
                                      f"{s.get('set_rate_hz', 0):.4g} it was set to (its exposure, the link's "
                                      f"bandwidth, its own limit, or its triggers): the file's times are the "
                                      f"camera's; its frame_rate_hz is the rate set"))
    pre, pre_available = s.get("pre_frames", 0), s.get("pre_available", -1)
    pre_missing = pre - pre_available if 0 <= pre_available < pre else 0
    if pre_missing:
        rows.insert(1, ("pre-trigger", f"{pre_available} of {pre} frames: the trigger came before the other "
                                       f"{pre_missing} were captured"))
    if "packets_resend_requests" in s:
        rows.insert(-1, ("network packets", f"{s.get('packets_resend_requests', 0)} resend requests, "
                                            f"{s.get('packets_resent', 0)} packets resent by the camera"))
    total = s.get("total_missing", 0)
    n_incomplete = s.get("incomplete", 0)
    suspect = s.get("lost_by_time_estimate", 0)
    if s.get("error"):
        rows.append(("ERROR", str(s["error"])))
    parts = []
    if total:
        parts.append(f"{total} frames missing")
    if pre_missing:
        parts.append(f"{pre_missing} pre-trigger frames missing (trigger too early)")
    if n_incomplete:
        parts.append(f"{n_incomplete} of {s.get('frames_written', 0)} frames incomplete")
    result = ("; ".join(parts) if parts else "no frame lost" if not s.get("error") else "incomplete recording")
    if suspect:
        result += f"; timestamp gaps suggest about {suspect} more (frames the camera ids do not show, or late frames)"
    rows.append(("result", result))
    return rows


def format_summary(s: dict) -> str:
    """Multi-line human summary of a recording (what ``tirdeflect record`` prints)."""
    return "\n".join([f"recording {s.get('path', '')}"] + [f"  {name:<16} {value}" for name, value in summary_rows(s)])


def _incomplete_text(s: dict) -> str:
    """'12 of 200 frames (1.9 % of their pixels missing, set to 0; the rest kept)' or '0'."""
    n = s.get("incomplete", 0)
    if not n:
        return "0"
    missing = s.get("incomplete_missing_bytes", 0)
    frame = s.get("frame_bytes", 0)
    share = f"{100.0 * missing / (n * frame):.2g} % of their pixels missing" if frame else "pixels missing"
    return (f"{n} of {s.get('frames_written', 0)} frames ({share}, stored as 0; the pixels that arrived are kept; "
            "per frame: frame_table missing_bytes)")


def _ranges(pairs) -> str:
    parts = []
    for first, count in pairs[:20]:
        parts.append(str(first) if count == 1 else f"{first}-{first + count - 1}")
    if len(pairs) > 20:
        parts.append(f"... ({len(pairs) - 20} more)")
    return ", ".join(parts)


def read_summary(path) -> Dict:
    """The drop summary stored in a recording (``/summary``), or one rebuilt from ``/frame_table``.

    A crashed recording has no ``/summary``; then the counts come from the
    frame table up to ``frames_written`` (flags and frame-id gaps).
    """
    import h5py

    with h5py.File(path, "r") as f:
        if "summary" in f and "summary_json" in f["summary"].attrs:
            return json.loads(f["summary"].attrs["summary_json"])
        n = int(f["frames"].attrs.get("frames_written", 0))
        t = f["frame_table"][:n]
    from app.files.imageio import frame_table_damage

    damaged = frame_table_damage(t)
    # rows overwritten on disk (e.g. zeros) would count as huge gaps: only steps between
    # two intact neighbours count, and the damaged rows' flags are not known
    intact_step = ~(damaged[1:] | damaged[:-1])
    ids = t["frame_id"].astype(np.int64)
    # and only between two known ids: -1 is a frame whose id was lost with its GigE leader (a step from it
    # to id 65402 was counted as 65402 frames lost, by-hand trial of 7 Dec 2026)
    known_step = intact_step & (ids[1:] >= 0) & (ids[:-1] >= 0)
    d_seq_all = np.diff(t["sequence"].astype(np.int64)) - 1
    lost_upstream = int(np.clip(np.diff(ids) - 1 - d_seq_all, 0, None)[known_step].sum())
    d_seq = d_seq_all[intact_step]
    t = t[~damaged]
    flags = t["flags"]
    error = ("no /summary: the recording did not end normally (crash or power loss); counts rebuilt from "
             "/frame_table")
    if damaged.any():
        error += f"; {int(damaged.sum())} of its rows are damaged and left out of the counts"
    return dict(
        path=str(path),
        frames_written=n,
        frame_table_damaged_rows=int(damaged.sum()),
        lost_upstream_id_gaps=lost_upstream,
        lost_ring_overrun=int(d_seq.clip(0).sum()),
        time_gaps=int(((flags & FrameFlags.TIME_GAP_BEFORE) != 0).sum()),
        incomplete=int(((flags & FrameFlags.INCOMPLETE) != 0).sum()),
        incomplete_missing_bytes=int(t["missing_bytes"].sum()) if "missing_bytes" in (t.dtype.names or ()) else 0,
        error=error,
    )
