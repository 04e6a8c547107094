"""app.files.h5safe: room, space reservation and superblock repair on real files and real disks.

Superblock tests patch the end-of-allocation address (EOA) of real HDF5
files the way a failed write leaves it, and reopen them with h5py. Reserve
tests run on a small tmpfs (fallocate) and an ext2 image (no fallocate),
measuring the disk's free space with statvfs; they need root (skip otherwise).
"""

import os
import resource
import shutil

import h5py
import numpy as np
import pytest

from app.files import h5safe
from tests.faults.tools import small_disk

MiB = 1024 * 1024


def _write_h5(path, **file_kw):
    data = np.arange(64 * 256, dtype=np.float32).reshape(64, 256)
    with h5py.File(path, "w", libver="earliest", **file_kw) as f:
        f.create_dataset("height", data=data, chunks=(1, 256))
        f.attrs["frames_done"] = 64
    return data


def _free(path):
    return shutil.disk_usage(path).free


def test_eoa_is_read_where_hdf5_keeps_it(tmp_path):
    """A closed file's stored EOA is its size (superblock version 0: what h5py writes by default)."""
    v0 = tmp_path / "v0.h5"
    _write_h5(v0)
    assert v0.read_bytes()[8] == 0
    assert h5safe.stored_eoa(v0) == v0.stat().st_size

    v3 = tmp_path / "v3.h5"  # checksummed superblock: not handled, never patched
    with h5py.File(v3, "w", libver="latest") as f:
        f["x"] = 1
    assert h5safe.stored_eoa(v3) is None
    assert not h5safe.set_stored_eoa(v3, 1 << 20) and not h5safe.raise_eoa(v3, 1 << 20)
    not_hdf5 = tmp_path / "x.h5"
    not_hdf5.write_bytes(b"\0" * 100)
    assert h5safe.stored_eoa(not_hdf5) is None


def test_eoa_short_of_the_data_is_raised_and_the_file_reopens(tmp_path):
    """'addr overflow ... eoa' (issue 7): the EOA lags metadata written before a failure."""
    path = tmp_path / "out.h5"
    data = _write_h5(path)
    size = path.stat().st_size
    assert h5safe.set_stored_eoa(path, size - 4096)
    with pytest.raises(OSError, match="addr overflow|eoa"):
        h5py.File(path, "r")
    assert h5safe.repair_eof(path)
    assert h5safe.stored_eoa(path) == size == path.stat().st_size
    with h5py.File(path, "r") as f:
        assert f.attrs["frames_done"] == 64
        np.testing.assert_array_equal(f["height"][()], data)
    assert not h5safe.repair_eof(path)  # a file that opens is left alone


def test_end_of_file_beyond_the_disk_is_extended_and_the_file_reopens(tmp_path):
    """'truncated file ... stored_eof': HDF5 recorded an end the data never reached; extended sparse."""
    path = tmp_path / "out.h5"
    data = _write_h5(path)
    size = path.stat().st_size
    assert h5safe.set_stored_eoa(path, size + 64 * 1024)
    with pytest.raises(OSError, match="truncated|stored_eof|eof"):
        h5py.File(path, "r")
    assert h5safe.repair_eof(path)
    assert path.stat().st_size == size + 64 * 1024
    with h5py.File(path, "r") as f:
        np.testing.assert_array_equal(f["height"][()], data)


def test_a_check_the_repair_cannot_satisfy_leaves_the_file_as_it_was(tmp_path):
    path = tmp_path / "out.h5"
    _write_h5(path)
    size = path.stat().st_size
    assert h5safe.set_stored_eoa(path, size - 4096)
    before = path.read_bytes()
    calls = []

    def never(p):
        calls.append(h5safe.stored_eoa(p))
        raise RuntimeError("frames_written exceeds the datasets")

    assert not h5safe.repair_eof(path, check=never)
    assert calls[:2] == [size - 4096, size]  # the fallback (EOA to the file size) was tried, then undone
    assert path.read_bytes() == before


def test_fit_to_eoa_gives_back_preallocated_space(tmp_path):
    path = tmp_path / "out.h5"
    data = _write_h5(path)
    size = path.stat().st_size
    fd = os.open(path, os.O_RDWR)
    try:
        alloc = h5safe.Preallocation(fd, size)
        if not alloc.ensure(size + 3 * MiB) or not alloc.supported:
            pytest.skip(f"{tmp_path} cannot fallocate")
        assert os.fstat(fd).st_size == size + 3 * MiB == alloc.allocated_bytes
    finally:
        os.close(fd)
    h5safe.fit_to_eoa(path)
    assert path.stat().st_size == size
    with h5py.File(path, "r") as f:
        np.testing.assert_array_equal(f["height"][()], data)


def test_room_is_the_smallest_of_disk_ulimit_and_largest_file(tmp_path):
    path = tmp_path / "out.h5"
    path.write_bytes(b"\0" * MiB)
    free = _free(tmp_path)
    room, what = h5safe.room_bytes(path)
    assert what == "disk" and abs(room - free) < MiB  # other writers share this disk
    room, what = h5safe.room_bytes(path, fs_max_bytes=3 * MiB)
    assert (room, what) == (2 * MiB, "file system's largest file (3.15 MB)")
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (5 * MiB, hard))
    try:
        room, what = h5safe.room_bytes(path, 2 * MiB, fs_max_bytes=8 * MiB)
        limit = h5safe.file_size_limit(8 * MiB)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    assert (room, what) == (3 * MiB, "file size limit (ulimit -f)")
    assert limit == 5 * MiB


def test_reserve_holds_and_gives_back_space_on_tmpfs(tmp_path):
    """fallocate: 4 MiB leave the disk's free space at once and come back with release()."""
    with small_disk(tmp_path, "tmpfs", 16) as mnt:
        out = mnt / "run.h5"
        free0 = _free(mnt)
        reserve = h5safe.SpaceReserve(out, 4 * MiB)
        assert reserve.held and reserve.path == mnt / ".run.h5.reserve"
        held = free0 - _free(mnt)
        assert 4 * MiB <= held < 4 * MiB + 64 * 1024  # the bytes, give or take a few pages
        # another program fills the disk: the reserve's space is still ours to give back
        with open(mnt / "ballast", "wb") as fh:
            with pytest.raises(OSError):
                while True:
                    fh.write(b"\1" * MiB)
                    fh.flush()
        assert _free(mnt) < MiB
        assert h5safe.SpaceReserve(mnt / "other.h5", 4 * MiB).held is False  # no room: nothing held ...
        assert not (mnt / ".other.h5.reserve").exists()  # ... and nothing left behind
        assert reserve.release() and not reserve.path.exists()
        assert _free(mnt) >= 4 * MiB
        assert not reserve.release()  # once


def test_reserve_writes_its_bytes_where_there_is_no_fallocate(tmp_path):
    """ext2 cannot fallocate: the reserve is written (zeros) and the Preallocation says it cannot help."""
    with small_disk(tmp_path, "ext2", 16) as mnt:
        out = mnt / "run.h5"
        with open(out, "wb") as fh:
            alloc = h5safe.Preallocation(fh.fileno(), 0)
            assert alloc.ensure(8 * MiB) and not alloc.supported and alloc.allocated_bytes == 0
        free0 = _free(mnt)
        reserve = h5safe.SpaceReserve(out, 4 * MiB)
        assert reserve.held and reserve.path.stat().st_size == 4 * MiB
        assert free0 - _free(mnt) >= 4 * MiB
        reserve.release()
        assert _free(mnt) >= free0 - 64 * 1024


def test_an_existing_reserve_file_is_never_touched(tmp_path):
    out = tmp_path / "run.h5"
    stale = h5safe.reserve_path(out)
    stale.write_bytes(b"someone else's")
    reserve = h5safe.SpaceReserve(out, MiB)
    assert not reserve.held and not reserve.release()
    assert stale.read_bytes() == b"someone else's"


def test_preallocation_stops_at_the_limit_and_at_a_full_disk(tmp_path):
    with small_disk(tmp_path, "tmpfs", 8) as mnt:
        with open(mnt / "run.h5", "wb") as fh:
            alloc = h5safe.Preallocation(fh.fileno(), 0, limit_bytes=6 * MiB)
            assert alloc.ensure(2 * MiB) and alloc.allocated_bytes == 2 * MiB
            assert os.fstat(fh.fileno()).st_blocks * 512 >= 2 * MiB
            assert not alloc.ensure(7 * MiB)  # beyond the limit: not even asked (no SIGXFSZ)
            alloc.limit_bytes = 1 << 40
            assert not alloc.ensure(9 * MiB)  # more than the disk holds
            assert alloc.supported and alloc.allocated_bytes == 2 * MiB


def test_the_one_disk_full_error():
    """Recorder and batch writer raise the same error type (a subclass for the recorder), which the CLI
    shows as a one-line message (TirdeflectError), and the recorder's stays a RecorderError."""
    from app.batch import writer
    from app.capture import recorder
    from processing.errors import TirdeflectError

    assert writer.DiskFullError is h5safe.DiskFullError
    err = recorder.DiskFullError("disk full: only 3.9 MB left")
    assert isinstance(err, h5safe.DiskFullError) and isinstance(err, TirdeflectError)
    assert isinstance(err, recorder.DiskSpaceError) and isinstance(err, recorder.RecorderError)
