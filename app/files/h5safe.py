"""HDF5 files that stay valid when the disk fills or a write fails (issue 7).

The one place for what both HDF5 writers of tirdeflect need to end well on a
full disk: the live recorder (:mod:`app.capture.recorder`) and the output of
``tirdeflect process`` (:mod:`app.batch.writer`).

* Room: :func:`room_bytes` -- how many bytes a file may still grow by, and
  what limits it: free space on the disk, the process's ``ulimit -f``
  (RLIMIT_FSIZE) or the file system's largest file (FAT32: 4 GiB - 1, see
  :func:`max_file_bytes`); :func:`file_size_limit` -- the largest size a file
  may reach.
* Reservation, so that closing a file never depends on space another program
  may take meanwhile: :class:`Preallocation` allocates a file's own space on
  disk ahead of the data (Linux ``fallocate``, :func:`fallocate`);
  :class:`SpaceReserve` holds spare bytes in a hidden file ``.NAME.reserve``
  beside the output, given back for the close (file systems without
  ``fallocate`` only: space given back can be taken by another program
  before the close uses it).
* Superblock: after a failed write HDF5 may leave the end-of-allocation
  address (EOA) of the superblock short of metadata it wrote, or record an
  end of file beyond what reached the disk; then the file does not open
  ("addr overflow ... eoa", "truncated file ... stored_eof").
  :func:`stored_eoa` / :func:`set_stored_eoa` read and patch the EOA in place
  (8 bytes inside the first block: needs no space), :func:`raise_eoa` raises
  it to cover what was written, :func:`repair_eof` makes such a file open
  again (or leaves it as it was), :func:`fit_to_eoa` gives back preallocated
  space beyond the EOA after a normal close.
* Creation: :func:`check_creatable` tries, before any work, whether a file
  can be created where an output is asked for (a real file, made and
  removed: ``os.access`` says yes for root in ``/proc`` and on a read-only
  mount); :func:`create_h5` opens a new HDF5 file and turns HDF5's ``Unable
  to synchronously create file (... errno = 2 ...)`` into
  :class:`OutputLocationError`, whose message (:func:`cannot_create`) says
  why from the errno (no such folder, permission denied, read-only, full)
  and what to do.
* :class:`DiskFullError` -- the one error for "no room for the next write";
  the recorder's and the batch writer's ``DiskFullError`` are this class (or
  a subclass of it), a :class:`~processing.errors.TirdeflectError`: front ends
  show its message on one line (CLI: exit 2).

Superblocks handled: versions 0 and 1 with 8-byte addresses (what h5py writes
with ``libver="earliest"``, the default); versions 2 and 3 (``libver="latest"``)
carry a checksum and are left alone (functions return None / False).

Pure functions on paths and descriptors, no h5py at import; no Qt, no cameras.
"""

from __future__ import annotations

import errno
import logging
import os
import re
import shutil
from pathlib import Path
from typing import Callable, Optional, Tuple

from processing.errors import TirdeflectError

__all__ = [
    "DiskFullError",
    "OutputLocationError",
    "cannot_create",
    "check_creatable",
    "create_h5",
    "FS_MAX_FILE_BYTES",
    "filesystem_type",
    "max_file_bytes",
    "file_size_limit",
    "room_bytes",
    "fallocate",
    "detach_descriptor",
    "descriptor_of",
    "drop_written_pages",
    "Preallocation",
    "SpaceReserve",
    "reserve_path",
    "stored_eoa",
    "set_stored_eoa",
    "raise_eoa",
    "fit_to_eoa",
    "repair_eof",
    "global_heap_damage",
]

log = logging.getLogger("tirdeflect.h5safe")


class DiskFullError(TirdeflectError):
    """The disk (or a file-size limit) has no room for the next write; the file was closed valid.

    The message names the file, what ran out and what to do.
    """


class OutputLocationError(TirdeflectError):
    """An output file cannot be created where it was asked for; the message names the file,
    the reason (from the errno) and what to do, never HDF5's own text."""


# ----------------------------------------------------------------------------- creation

#: what an errno of a failed creation means to the user, ``{folder}`` the folder it was made in
_CREATE_REASONS = {
    errno.EACCES: "permission denied: you may not create files in {folder}",
    errno.EPERM: "permission denied: you may not create files in {folder}",
    errno.EROFS: "{folder} is on a read-only file system",
    errno.ENOSPC: "the disk holding {folder} is full",
    errno.EDQUOT: "your disk quota on {folder} is used up",
    errno.ENOTDIR: "a part of its path is a file, not a folder",
    errno.ENAMETOOLONG: "the name is too long for the file system",
    errno.EISDIR: "it is a folder",
    errno.EEXIST: "a file of that name is there already",
}


def cannot_create(path, exc: OSError, remedy: str = "choose another --out",
                  folder=None) -> OutputLocationError:
    """The error for an output ``path`` whose creation failed with ``exc``: why, in words, from
    its errno, then ``remedy`` (what to do), e.g. ``cannot create the output file
    '/proc/m.h5': the folder '/proc' takes no new files (No such file or directory); choose
    another --out``. HDF5's ``Unable to synchronously create file (... flags = 15 ...)``
    told the user nothing of that. ``folder``: where the creation was tried (default: the
    folder of ``path``)."""
    path = Path(path)
    if folder is None:
        folder = path.parent if str(path.parent) else Path(".")
    folder = Path(folder)
    code = getattr(exc, "errno", None)
    if code == errno.ENOENT:
        reason = (f"the folder {str(folder)!r} takes no new files (No such file or directory)"
                  if folder.is_dir() else f"the folder {str(folder)!r} does not exist")
    elif code in _CREATE_REASONS:
        reason = _CREATE_REASONS[code].format(folder=repr(str(folder)))
    else:
        reason = os.strerror(code) if isinstance(code, int) else (str(exc) or type(exc).__name__)
    return OutputLocationError(f"cannot create the output file {str(path)!r}: {reason}; {remedy}")


def _nearest_folder(path: Path) -> Path:
    """The nearest folder above ``path`` that exists (the folders below it are made with the output)."""
    folder = path.parent if str(path.parent) else Path(".")
    while not os.path.lexists(folder) and folder != folder.parent:
        folder = folder.parent
    return folder


def check_creatable(path, remedy: str = "choose another --out") -> None:
    """Refuse, before any frame is processed or recorded, an output ``path`` that cannot be
    created: a hidden file is made beside it (in the nearest folder that exists) and removed
    again. ``os.access`` is not enough: it says yes to root in ``/proc`` and on a read-only
    mount, and the run then failed at its first write with HDF5's text. Raises
    :class:`OutputLocationError` (:func:`cannot_create`)."""
    import tempfile

    path = Path(path)
    folder = _nearest_folder(path)
    try:
        fd, probe = tempfile.mkstemp(prefix=".tirdeflect-probe-", dir=folder)
    except OSError as exc:
        raise cannot_create(path, exc, remedy, folder) from None
    os.close(fd)
    try:
        os.unlink(probe)
    except OSError:  # pragma: no cover - made a moment ago
        pass


def create_h5(path, mode: str = "x", *, remedy: str = "choose another --out", **kwargs):
    """``h5py.File(path, mode, **kwargs)`` for a new output file. An OSError HDF5 raises becomes
    :class:`OutputLocationError` (:func:`cannot_create`) naming the file, why and ``remedy``;
    :class:`FileExistsError` is raised as it is (the callers choose another name, or refuse:
    never overwrite)."""
    import h5py

    try:
        return h5py.File(path, mode, **kwargs)
    except FileExistsError:
        raise
    except OSError as exc:
        raise cannot_create(path, exc, remedy) from exc


# ----------------------------------------------------------------------------- room

#: largest file some file systems can hold, bytes (FAT32 and its kin: 4 GiB - 1)
FS_MAX_FILE_BYTES = {"vfat": 2**32 - 1, "msdos": 2**32 - 1, "fat": 2**32 - 1, "umsdos": 2**32 - 1}

#: "no limit" for :func:`file_size_limit`, bytes
NO_LIMIT_BYTES = 1 << 62


def filesystem_type(path, mounts_text: Optional[str] = None) -> str:
    """File-system type of the mount holding ``path`` (from /proc/mounts; "" when unknown)."""
    try:
        if mounts_text is None:
            with open("/proc/mounts") as fh:
                mounts_text = fh.read()
    except OSError:  # pragma: no cover - not Linux
        return ""
    target = os.path.realpath(str(path))
    best, kind = "", ""
    for line in mounts_text.splitlines():
        parts = line.split()
        if len(parts) < 3:
            continue
        mnt = parts[1].replace("\\040", " ")
        inside = target == mnt or target.startswith(mnt.rstrip("/") + "/")
        if inside and len(mnt) >= len(best):
            best, kind = mnt, parts[2]
    return kind


def max_file_bytes(path) -> Optional[int]:
    """The file-size limit of the file system holding ``path`` (None: none known), e.g. 4 GiB - 1 on FAT32."""
    return FS_MAX_FILE_BYTES.get(filesystem_type(path))


def _ulimit_fsize_bytes() -> Optional[int]:
    """The process's soft ``ulimit -f`` (RLIMIT_FSIZE) in bytes, None when unlimited or unknown."""
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_FSIZE)
    except (ImportError, ValueError, OSError):  # pragma: no cover - not POSIX
        return None
    return None if soft == resource.RLIM_INFINITY else int(soft)


def file_size_limit(fs_max_bytes: Optional[int] = None) -> int:
    """Largest size a file may reach, bytes: the file system's (``fs_max_bytes``) and ``ulimit -f``.

    :data:`NO_LIMIT_BYTES` when neither limits it.
    """
    limit = fs_max_bytes if fs_max_bytes is not None else NO_LIMIT_BYTES
    soft = _ulimit_fsize_bytes()
    return limit if soft is None else min(limit, soft)


def room_bytes(path, current_size: Optional[int] = None,
               fs_max_bytes: Optional[int] = None) -> Tuple[int, str]:
    """Bytes the file at ``path`` may still grow by, and what limits it.

    The smallest of: free space on the disk of ``path``'s folder ("disk"), the
    file system's largest file ``fs_max_bytes`` (see :func:`max_file_bytes`)
    and the process's ``ulimit -f``, the last two less ``current_size`` (bytes
    the file holds now; None: its size on disk, 0 if it does not exist yet).
    """
    path = Path(path)
    if current_size is None:
        current_size = path.stat().st_size if path.exists() else 0
    room, what = shutil.disk_usage(path.parent).free, "disk"
    if fs_max_bytes is not None and fs_max_bytes - current_size < room:
        from app.sizes import format_bytes  # the app's one size formatter

        room, what = fs_max_bytes - current_size, f"file system's largest file ({format_bytes(fs_max_bytes)})"
    soft = _ulimit_fsize_bytes()
    if soft is not None and soft - current_size < room:
        room, what = soft - current_size, "file size limit (ulimit -f)"
    return room, what


# ----------------------------------------------------------------------------- reservation

_libc = None


def fallocate(fd: int, offset: int, length: int) -> int:
    """Allocate ``length`` bytes of ``fd`` from ``offset`` on disk (Linux fallocate, mode 0); 0 or an errno.

    Unlike ``os.posix_fallocate`` this never falls back to writing zeros on
    file systems without fallocate (that would take as long as writing the
    data): they answer EOPNOTSUPP and the caller chooses what to do instead.
    """
    global _libc
    import ctypes

    if _libc is None:
        try:
            _libc = ctypes.CDLL(None, use_errno=True)
            _libc.fallocate.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_int64, ctypes.c_int64]
        except (OSError, AttributeError):
            _libc = False
    if not _libc:
        return errno.EOPNOTSUPP
    if _libc.fallocate(int(fd), 0, int(offset), int(length)) == 0:
        return 0
    return ctypes.get_errno()


def detach_descriptor(fd: int) -> None:
    """Point ``fd`` (an open file's descriptor, e.g. HDF5's) at /dev/null, so that
    nothing written through it afterwards reaches the file.

    /dev/null is opened read-write: what HDF5 still writes (dirty metadata
    at the close) succeeds into nothing, so HDF5 closes cleanly; a read-only
    descriptor would make its close fail and leave a half-closed library
    state behind. Raises OSError if the descriptor cannot be replaced.
    """
    sink = os.open(os.devnull, os.O_RDWR)
    try:
        os.dup2(sink, fd)
    finally:
        os.close(sink)


def descriptor_of(h5file) -> Optional[int]:
    """The file descriptor an open ``h5py.File`` writes through (the default sec2 driver), or
    None where its driver has none (another driver, a file in memory)."""
    try:
        fd = int(h5file.id.get_vfd_handle())
    except Exception:  # noqa: BLE001 - another HDF5 driver: no descriptor
        return None
    return fd if fd >= 0 else None


def drop_written_pages(fd: int) -> None:
    """Have the kernel write out what the page cache holds of file ``fd`` and drop
    what it has written (``posix_fadvise(DONTNEED)``: dirty pages start their
    write-back, clean ones are freed; nothing waits for the disk). Called after
    each flush, the cache holds about one flush interval of a file that is
    written once and not read back here, instead of growing by the whole file.

    Measured on the 2-core test machine (a VM), ``tirdeflect process`` of 500
    1024^2 frames: as the cache grew by 13 MB a frame, copying the maps into it
    took a quarter of both cores (``perf``: ``copy_folio_from_iter_atomic``),
    10 frames/s after the first 200; with this, 13-15 frames/s. The recorder
    (:class:`app.capture.recorder.RecordingFile`, flushed every 0.5 s): 4 GB
    at 590-700 MB/s without, 1100-1180 MB/s with (the same run, in turn). Does nothing
    where the system has no ``posix_fadvise`` (macOS, Windows) or the
    descriptor is not a plain file's."""
    if not hasattr(os, "posix_fadvise"):
        return
    try:
        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
    except OSError:
        pass


#: fallocate answers meaning "no room" (as opposed to "cannot reserve here")
_NO_ROOM = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


class Preallocation:
    """A file's own space allocated on disk ahead of its data (``fallocate``).

    Another program filling the disk then gets "disk full" instead of the
    writer, and the space to close the file is already the file's.

    Parameters
    ----------
    fd : int or None
        The open file's descriptor (None: nothing can be allocated, as when
        the file system has no fallocate).
    allocated_bytes : int
        Bytes of the file already on disk (its size now).
    limit_bytes : int
        Never allocate beyond this size (:func:`file_size_limit`; going past
        ``ulimit -f`` would raise SIGXFSZ).

    Attributes: ``allocated_bytes``, ``limit_bytes``, ``supported`` (False
    once the file system answered that it cannot allocate ahead).
    """

    def __init__(self, fd: Optional[int], allocated_bytes: int, limit_bytes: int = NO_LIMIT_BYTES):
        self.fd = fd
        self.allocated_bytes = int(allocated_bytes)
        self.limit_bytes = int(limit_bytes)
        self.supported = fd is not None

    def ensure(self, target_bytes: int) -> bool:
        """Make sure the first ``target_bytes`` of the file are allocated on disk; False when there is no room.

        True also when the file system cannot allocate ahead: then
        :attr:`supported` turns False (and stays so), and the caller checks
        free space instead (:func:`room_bytes`, :class:`SpaceReserve`).
        """
        while self.supported and target_bytes > self.allocated_bytes:
            if target_bytes > self.limit_bytes:
                return False
            err = fallocate(self.fd, self.allocated_bytes, target_bytes - self.allocated_bytes)
            if err == 0:
                self.allocated_bytes = int(target_bytes)
            elif err in _NO_ROOM:
                return False
            elif err != errno.EINTR:  # EOPNOTSUPP, ENOSYS, EINVAL ...
                self.supported = False
                log.info("fd %d: the file system cannot reserve space (errno %d)", self.fd, err)
        return True

    def make_room(self, end_bytes: int, more_bytes: int, step_bytes: int = 0) -> bool:
        """Make sure the ``more_bytes`` past ``end_bytes`` (HDF5's end of allocation) are the file's on disk.

        Allocates ahead in steps of at least ``step_bytes`` where the disk and
        the size limit allow (fewer calls), else exactly what is asked. False
        when there is no room: what was allocated before stays the file's, so
        a writer that asks for its next write plus the room to close gets
        False while it can still close. True also when the file system cannot
        allocate ahead (:attr:`supported` turns False).
        """
        need = int(end_bytes) + int(more_bytes)
        if not self.supported or need <= self.allocated_bytes:
            return True
        ahead = min(max(need, self.allocated_bytes + int(step_bytes)), self.limit_bytes)
        if ahead > need and self.ensure(ahead):
            return True
        return self.ensure(need)


def reserve_path(beside) -> Path:
    """The hidden reserve file beside ``beside``: ``.NAME.reserve`` in the same folder (same disk)."""
    beside = Path(beside)
    return beside.with_name(f".{beside.name}.reserve")


class SpaceReserve:
    """``nbytes`` held on disk in a hidden file :func:`reserve_path` beside a file being written.

    Created at once (fallocate, else written as zeros and synced); given back
    with :meth:`release` when a write fails or before the close, so that the
    close has room although another program took the rest of the disk. An
    existing file of that name is never touched (then nothing is held).
    ``nbytes <= 0``: nothing is held. Attributes: ``path``, ``nbytes``,
    ``held``.
    """

    def __init__(self, beside, nbytes: int):
        self.path = reserve_path(beside)
        self.nbytes = int(nbytes)
        self.held = False
        if self.nbytes <= 0:
            return
        try:
            fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        except OSError as exc:
            log.debug("no space reserve beside %s (%s)", beside, exc)
            return
        try:
            err = fallocate(fd, 0, self.nbytes)
            if err in _NO_ROOM:
                raise OSError(err, os.strerror(err))
            if err != 0:  # no fallocate here: write the bytes
                zeros = memoryview(bytes(min(self.nbytes, 1 << 20)))
                left = self.nbytes
                while left > 0:
                    left -= os.write(fd, zeros[: min(left, len(zeros))])
                os.fsync(fd)
            self.held = True
        except OSError as exc:
            log.debug("no space reserve beside %s (%s)", beside, exc)
        finally:
            os.close(fd)
            if not self.held:
                self._unlink()

    def _unlink(self) -> bool:
        try:
            self.path.unlink()
            return True
        except OSError:
            return False

    def release(self) -> bool:
        """Give the space back to the file system; True if some was held (and is free now)."""
        if not self.held:
            return False
        self.held = False
        return self._unlink()


# ----------------------------------------------------------------------------- superblock

_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def _eoa_offset(head: bytes) -> Optional[int]:
    """Byte offset of the end-of-allocation address in a superblock starting with ``head``, None if not handled."""
    if len(head) < 14 or head[:8] != _SIGNATURE or head[8] not in (0, 1) or head[13] != 8:
        return None
    at = 40 if head[8] == 0 else 44  # version 1 has 4 more bytes (indexed storage K)
    return at if len(head) >= at + 8 else None


def stored_eoa(path) -> Optional[int]:
    """End-of-allocation address stored in the superblock, bytes; None if unreadable or not handled."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(64)
    except OSError:
        return None
    at = _eoa_offset(head)
    return None if at is None else int.from_bytes(head[at:at + 8], "little")


def set_stored_eoa(path, eoa: int) -> bool:
    """Rewrite the superblock's end-of-allocation address in place; True if done."""
    try:
        with open(path, "r+b") as fh:
            at = _eoa_offset(fh.read(64))
            if at is None:
                return False
            fh.seek(at)
            fh.write(int(eoa).to_bytes(8, "little"))
        return True
    except OSError:
        return False


def global_heap_damage(path, address: int) -> str:
    """Why the HDF5 global heap collection at byte ``address`` of ``path`` cannot be
    read safely ("" when its layout is sound), read with plain file I/O.

    A collection holds variable-length data (strings such as ``/geometry_toml``):
    ``GCOL``, version 1, 3 reserved bytes, its size (8 bytes), then objects (index
    2, reference count 2, reserved 4, size 8 bytes, data padded to 8). HDF5 walks
    them when it loads the collection; an object of index 0 and size 0 (e.g. bytes
    zeroed on disk) does not advance that walk, and HDF5 1.14 loops there for ever
    (it cannot be interrupted), so such damage must be found before h5py reads it.
    Only 8-byte lengths (h5py's default) are handled; other layouts return "".
    """
    try:
        with open(path, "rb") as fh:
            fh.seek(int(address))
            head = fh.read(16)
            if len(head) < 16 or head[:4] != b"GCOL" or head[4] != 1:
                return f"the global heap at byte {address} has no valid 'GCOL' header"
            size = int.from_bytes(head[8:16], "little")
            if size < 16 or size > (1 << 40):
                return f"the global heap at byte {address} states an impossible size ({size} bytes)"
            body = fh.read(size - 16)
    except OSError as exc:
        return f"the global heap at byte {address} cannot be read ({exc})"
    if len(body) < size - 16:
        return f"the global heap at byte {address} runs past the end of the file"
    at = 0
    while at < len(body):
        if at + 16 > len(body):  # too small for an object header: free space, as HDF5 reads it
            break
        index = int.from_bytes(body[at:at + 2], "little")
        length = int.from_bytes(body[at + 8:at + 16], "little")
        need = 16 + ((length + 7) // 8) * 8 if index > 0 else length
        if need <= 0:
            return (f"the global heap at byte {address} holds an empty free-space entry at byte "
                    f"{address + 16 + at} (zeroed bytes?)")
        at += need
    return ""


def raise_eoa(path, end: int) -> bool:
    """Raise the end-of-allocation address to at least ``end`` and the file's size, extending the file
    (sparse, needs no space) to it; True if it changed, False if it covered that already or is not handled."""
    eoa = stored_eoa(path)
    if eoa is None:
        return False
    end = max(int(end), os.path.getsize(path))
    if end <= eoa or not set_stored_eoa(path, end):
        return False
    if end > os.path.getsize(path):
        os.truncate(path, end)
    return True


def fit_to_eoa(path) -> None:
    """Cut preallocated space beyond HDF5's end of allocation (or extend, sparse, a file HDF5 thinks is longer).

    For a file closed normally; the file stays valid if this fails (only larger than needed).
    """
    eoa = stored_eoa(path)
    try:
        if eoa is not None and 0 < eoa < (1 << 50) and os.path.getsize(path) != eoa:
            os.truncate(path, eoa)
    except OSError as exc:
        log.warning("%s: could not release the reserved space beyond the data: %s", path, exc)


def _opens(path) -> None:
    import h5py

    h5py.File(path, "r").close()


def repair_eof(path, check: Optional[Callable[[Path], object]] = None) -> bool:
    """Make a file that HDF5 left inconsistent after a failed write open again; True if it changed the file.

    ``check(path)`` raises while the file is not right (default: it does not
    open in h5py). Repairs, each followed by ``check`` again (each may uncover
    the next problem):

    * the superblock records an end of file beyond what reached the disk
      ("stored_eof = N"): extend the file (sparse) to it;
    * metadata written before the failure lies beyond the end of allocation
      ("addr overflow, addr = A, size = S, eoa = E"): raise the EOA to cover
      it and the whole file (:func:`raise_eoa`);
    * else, if the EOA is short of the file's size: raise it to the size.

    Only the superblock's 8-byte EOA and the file's length change: what was
    flushed before the failure stays as it was. If no repair makes ``check``
    pass, both are put back as they were and False is returned.
    """
    path = Path(path)
    check = _opens if check is None else check
    try:
        eoa0, size0 = stored_eoa(path), path.stat().st_size
    except OSError:
        return False
    tried_size = False
    for attempt in range(8):
        try:
            check(path)
            return attempt != 0
        except Exception as exc:  # noqa: BLE001 - whatever check raises means "not right"
            text = str(exc)
        try:
            m = re.search(r"stored_eof = (\d+)", text)
            if m and int(m.group(1)) > path.stat().st_size:
                os.truncate(path, int(m.group(1)))
                log.warning("%s: extended to the end of file HDF5 recorded before the failed write", path)
                continue
            m = re.search(r"addr overflow, addr = (\d+), size = (\d+), eoa = (\d+)", text)
            if m and raise_eoa(path, int(m.group(1)) + int(m.group(2))):
                log.warning("%s: end of allocation raised to cover what was written before the failed write", path)
                continue
            eoa, size = stored_eoa(path), path.stat().st_size
            if not tried_size and eoa is not None and eoa < size and set_stored_eoa(path, size):
                tried_size = True
                log.warning("%s: end of allocation raised to the file size", path)
                continue
        except OSError as err:
            log.error("%s: could not repair the end of file (%s)", path, err)
        break
    # nothing helped: leave the file as it was
    try:
        if eoa0 is not None and stored_eoa(path) != eoa0:
            set_stored_eoa(path, eoa0)
        if path.stat().st_size != size0:
            os.truncate(path, size0)
    except OSError:
        pass
    return False
