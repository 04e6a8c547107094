"""app.batch.writer: what OUT.h5 holds between flushes, after a crash, and from frames prepared in workers."""

import os
import signal
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from app.batch import writer as W
from app.files.imageio import FrameItem
from tests.helpers import resident_bytes

ROOT = Path(__file__).resolve().parents[2]
SHAPE = (96, 128)


class _Result:
    """What the writer reads of a processing Result."""

    def __init__(self, rng, valid_fraction=0.9):
        self.valid = rng.random(SHAPE) < valid_fraction
        # smooth, like heights (compressible), finite everywhere: the writer must mask it
        self.height = np.cumsum(rng.standard_normal(SHAPE), axis=1).astype(np.float32) * 1e-3
        self.slope_x = rng.standard_normal(SHAPE).astype(np.float32)
        self.slope_y = rng.standard_normal(SHAPE).astype(np.float32)
        self.pin = None
        self.series = None


def _writer(path, compression="none", flush_interval_s=None):
    return W.ResultWriter(path, compression=compression, attrs={}, geometry_toml="", geometry_attrs={},
                          carrier_attrs={}, reference=np.zeros(SHAPE, np.uint8), expected=8,
                          grid_coords=(np.arange(SHAPE[1]) * 0.1, np.arange(SHAPE[0]) * 0.1), grid="full",
                          flush_interval_s=flush_interval_s)


def _item(k):
    return FrameItem(image=None, source="in.tif", index_in_source=k, sequence_index=k, frames_in_source=8)


def _check_frame(f, k, result):
    h = f["height"][k]
    np.testing.assert_array_equal(np.isnan(h), ~result.valid)
    np.testing.assert_array_equal(h[result.valid], result.height[result.valid])
    np.testing.assert_array_equal(f["slope_x"][k], result.slope_x)
    np.testing.assert_array_equal(f["valid"][k], result.valid.astype(np.uint8))


@pytest.mark.parametrize("compression", ["none", "gzip", "lzf"])
def test_frames_prepared_in_a_worker_are_stored_as_the_writer_stores_results(tmp_path, rng, compression):
    """output_frame (NaN mask, uint8 mask, gzip with shuffle in the worker) gives the
    file the writer makes from the Result itself, sample for sample."""
    results = [_Result(rng) for _ in range(3)]
    with_result, prepared = tmp_path / "result.h5", tmp_path / "prepared.h5"
    for path, frames in ((with_result, results), (prepared, [W.output_frame(r, compression) for r in results])):
        w = _writer(path, compression)
        for k, frame in enumerate(frames):
            w.append(_item(k), frame)
        w.close("complete")
    with h5py.File(with_result) as a, h5py.File(prepared) as b:
        for k, r in enumerate(results):
            _check_frame(b, k, r)
            for name in W.MAPS:
                np.testing.assert_array_equal(b[name][k], a[name][k])
        if compression != "none":
            assert b["height"].compression == compression and b["height"].shuffle
        if compression == "gzip":  # compressed as HDF5 would have: the same bytes on disk
            for name in W.MAPS:
                assert a[name].id.read_direct_chunk((1, 0, 0)) == b[name].id.read_direct_chunk((1, 0, 0))


def test_frames_done_moves_only_at_a_flush(tmp_path, rng):
    results = [_Result(rng) for _ in range(3)]
    w = _writer(tmp_path / "o.h5", flush_interval_s=3600)
    w.append(_item(0), results[0])
    w.flush()
    for k in (1, 2):
        w.append(_item(k), results[k])
    assert (w.n, w.frames_done, int(w.f.attrs["frames_done"])) == (3, 1, 1)
    w.close("complete")
    assert w.frames_done == 3
    with h5py.File(tmp_path / "o.h5") as f:
        assert f.attrs["frames_done"] == 3 and f["frame_index"][()].tolist() == [0, 1, 2]
        for k, r in enumerate(results):
            _check_frame(f, k, r)
    w = _writer(tmp_path / "every.h5", flush_interval_s=0)  # the old behaviour: after every frame
    w.append(_item(0), results[0])
    assert w.frames_done == 1
    w.close("complete")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads the page cache with Linux's mincore")
def test_flushed_frames_leave_the_page_cache(tmp_path, rng):
    """OUT.h5 is written once and not read back during the run: once a flush's frames are on
    disk, the next flush drops them from the page cache, which otherwise grows by the whole
    output (13 MB a 1024^2 frame; on the test machine that growth cost a quarter of both
    cores in a 500-frame run, h5safe.drop_written_pages)."""
    from app.files.h5safe import filesystem_type

    path = tmp_path / "o.h5"
    if filesystem_type(path) in ("tmpfs", "ramfs"):
        pytest.skip("a tmpfs file lives in the page cache")
    w = _writer(path, flush_interval_s=3600)
    for k in range(16):
        w.append(_item(k), _Result(rng))
    maps_bytes = 16 * SHAPE[0] * SHAPE[1] * (3 * 4 + 1)
    written = resident_bytes(path)
    os.fsync(w.f.id.get_vfd_handle())  # on disk now, as the write-back started by a flush leaves it
    w.flush()
    flushed = resident_bytes(path)
    w.close("complete")
    assert written > 0.9 * maps_bytes, f"only {written} of the {maps_bytes} bytes written were in the page cache"
    assert flushed < 0.25 * maps_bytes, f"{flushed} bytes of OUT.h5 stayed in the page cache after the flush"


_CRASH_CHILD = """
import os, signal, sys
import numpy as np
sys.path.insert(0, {tests!r})
from test_writer import _Result, _item, _writer
rng = np.random.default_rng(7)
w = _writer({path!r}, {compression!r}, flush_interval_s=3600)
for k in range(5):
    w.append(_item(k), _Result(rng))
    if k == 1:
        w.flush()
os.kill(os.getpid(), signal.SIGKILL)  # 3 frames written since the flush, their maps in the file
"""


@pytest.mark.parametrize("compression", ["none", "gzip"])
def test_a_crash_between_flushes_leaves_the_file_of_the_last_flush(tmp_path, compression):
    """SIGKILL after frames were written but not flushed: the file opens, holds the
    frames_done frames of the last flush, whole, and nothing else."""
    path = tmp_path / "o.h5"
    proc = subprocess.run([sys.executable, "-c", _CRASH_CHILD.format(
        tests=str(Path(__file__).parent), path=str(path), compression=compression)],
        cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    assert path.stat().st_size > 4 * SHAPE[0] * SHAPE[1] * (1 if compression == "gzip" else 13)
    rng = np.random.default_rng(7)
    expected = [_Result(rng) for _ in range(2)]
    with h5py.File(path, "r") as f:
        assert f.attrs["frames_done"] == 2 and f.attrs["status"] == "running"
        for name in (*W.MAPS, *W.ResultWriter.PER_FRAME_1D):
            assert f[name].shape[0] == 2, name
        assert f["frame_index"][()].tolist() == [0, 1]
        for k, r in enumerate(expected):
            _check_frame(f, k, r)
    os.unlink(path)
