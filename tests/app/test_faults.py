"""Faults: camera killed mid-recording, disk full, injected drops, a recorder lapped by the camera.

Each must end with a clear error within a bounded time, a file that opens and
holds every frame received, and counts that equal what really went missing.
"""

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

import drivers
from app.capture.acquisition import Acquisition
from app.capture.recorder import Recorder, format_summary
from app.capture.trigger import TriggeredCapture
from drivers.base import FrameFlags
from drivers.synthetic import SyntheticCamera
from tests.drivers.fixtures import gv_fake_camera  # noqa: F401  (pytest fixture)

ROOT = Path(__file__).resolve().parents[2]

#: a camera that vanishes must end the recording, not hang: within this many seconds. A hang detector,
#: >= 10x above need (the driver's 2.0 s lost_timeout_s plus one probe, about 2.3 s)
CAMERA_LOST_BOUND_S = 30.0


def _frames(n=97, shape=(64, 64)):
    """Frame k is uniform with value 2k (mod 256): a frame's content names its id."""
    return ((np.arange(n) * 2) % 256).astype(np.uint8)[:, None, None] * np.ones((1,) + shape, np.uint8)


def _assert_frames_match_ids(path, n_frames_src=97):
    with h5py.File(path, "r") as f:
        n = int(f["frames"].attrs["frames_written"])
        t = f["frame_table"][:n]
        # rows of pixels; none when the camera lapped the recorder on every frame (a loaded machine)
        data = f["frames"][:n].reshape(n, int(np.prod(f["frames"].shape[1:])))
    expect = (t["frame_id"] % n_frames_src * 2 % 256).astype(np.uint8)
    assert np.array_equal(data.min(axis=1), expect) and np.array_equal(data.max(axis=1), expect)
    return n, t


@pytest.mark.aravis
def test_gige_camera_killed_mid_recording(tmp_path, gv_fake_camera):
    cam = drivers.open_camera(gv_fake_camera.camera_id)
    try:
        cam.configure(frame_rate_hz=50.0, width=256, height=256)
        acq = Acquisition(cam, ring_frames=64)
        rec = Recorder(acq.ring, tmp_path / "lost.h5", n_frames=10_000, acquisition=acq)
        rec.begin(0)
        acq.start()
        assert acq.ring.wait_for(20, 10.0)
        t0 = time.monotonic()
        gv_fake_camera.kill()
        assert rec.wait(CAMERA_LOST_BOUND_S), f"recorder still waiting {CAMERA_LOST_BOUND_S} s after the camera died"
        took = time.monotonic() - t0
        assert acq.state == "error" and "lost" in acq.error
        assert rec.state == "error" and "acquisition ended with an error" in rec.error
        assert str(gv_fake_camera.camera_id) in rec.error
    finally:
        cam.close()
    with h5py.File(tmp_path / "lost.h5", "r") as f:
        n = int(f["frames"].attrs["frames_written"])
        t = f["frame_table"][:]
        assert f["frames"].shape[0] == n and f.attrs["complete"] == 0
        assert "camera" in f.attrs["error"]
    # every frame the camera thread received is in the file, in order
    assert n == acq.acquired >= 21
    assert list(t["sequence"]) == list(range(n)) and np.all(np.diff(t["frame_id"]) == 1)
    print(f"camera loss detected and file closed {took:.2f} s after the kill")


_DISK_FULL_CHILD = r"""
import json, resource, signal, sys, numpy as np
sys.path.insert(0, sys.argv[3])
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # get EFBIG like ENOSPC instead of being killed
limit = int(sys.argv[2])
resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
from drivers.synthetic import SyntheticCamera
from app.capture.acquisition import Acquisition
from app.capture.recorder import Recorder
frames = ((np.arange(97) * 2) % 256).astype(np.uint8)[:, None, None] * np.ones((1, 64, 64), np.uint8)
cam = SyntheticCamera(frames, frame_rate_hz=2000).open()
acq = Acquisition(cam, ring_frames=4096)
# the limit stands for a disk that fills during the recording: skip the up-front check
rec = Recorder(acq.ring, sys.argv[1], n_frames=2000, acquisition=acq, flush_interval_s=0.02, check_space=False,
               defer=sys.argv[4] == "burst")
rec.begin(0)
acq.stop_after(1999)
acq.start()
done = rec.wait(30)
acq.stop()
print(json.dumps(dict(done=done, error=rec.error, written=rec.frames_written)))
"""


def _try_tmpfs(mount_dir, size_bytes):
    if os.geteuid() != 0:
        return False
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_bytes}", "tmpfs", str(mount_dir)],
                       capture_output=True, timeout=10)
    return r.returncode == 0


def test_disk_full_after_the_check_hits_the_other_writer(tmp_path):
    """Another program fills a small disk (tmpfs) after the free-space check: the recording's space was reserved.

    The recorder allocates the planned file on disk at the start (fallocate), so the *other* writer gets
    "No space left on device" and the recording completes. Stops while the disk fills (no reservation
    possible, ext2 without fallocate, a second process) are in tests/faults/. Needs root to mount.
    """
    mnt = tmp_path / "small_disk"
    mnt.mkdir()
    if not _try_tmpfs(mnt, 32 * 1024 * 1024):
        pytest.skip("cannot mount a tmpfs here (not root); test_file_size_limit_mid_recording covers the path")
    try:
        frames = _frames()
        with SyntheticCamera(frames, frame_rate_hz=2000) as cam:
            acq = Acquisition(cam, ring_frames=4096)
            # 3000 frames (12 MB + 16 MB margin) pass the free-space check on the empty 32 MB disk ...
            rec = Recorder(acq.ring, mnt / "full.h5", n_frames=3000, acquisition=acq, flush_interval_s=0.02)
            # ... then something else tries to take 24 MB of it
            with pytest.raises(OSError, match="No space left"):
                with open(mnt / "ballast", "wb") as fh:
                    fh.write(b"\0" * (24 * 1024 * 1024))
            rec.begin(0)
            acq.stop_after(2999)
            with acq:
                assert rec.wait(30.0), "recorder hung"
        assert rec.state == "done" and rec.error is None, rec.error
        n, t = _assert_frames_match_ids(mnt / "full.h5")
        assert n == 3000 and list(t["sequence"]) == list(range(n))
        # the space reserved beyond the data was given back at close
        assert os.path.getsize(mnt / "full.h5") < 3000 * 64 * 64 + 2 * 1024 * 1024
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True, timeout=10)


@pytest.mark.parametrize("mode", ["streaming", "burst"])
def test_file_size_limit_mid_recording(tmp_path, mode):
    """The same failure through RLIMIT_FSIZE (works without root): EFBIG mid-recording, file valid. In burst
    mode every frame was in RAM already: the ones there was no room for are said to be lost (by-hand trial of
    7 Dec 2026: "stopped after 23 frames of 100" and nothing of the other 77)."""
    path = tmp_path / "full.h5"
    limit = 8 * 1024 * 1024  # 4 MB reserve + about 1000 frames of 4 kB
    out = subprocess.run([sys.executable, "-c", _DISK_FULL_CHILD, str(path), str(limit), str(ROOT), mode],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    res = json.loads(out.stdout.strip().splitlines()[-1])
    assert res["done"] and "file size limit (ulimit -f) full" in res["error"]
    assert "raise the limit (ulimit -f)" in res["error"]
    n, t = _assert_frames_match_ids(path)
    assert 500 < n < 2000 and list(t["sequence"]) == list(range(n))
    lost = f"the other {2000 - n} frames were captured into RAM (--burst) but there was no room to write them"
    assert (lost in res["error"]) == (mode == "burst"), res["error"]


def test_injected_drops_summary_equals_the_injected_set(tmp_path):
    drops = {17, 18, 50, 51, 52, 99, 130}
    frames = _frames()
    # 200 Hz and 2000 camera buffers: a camera thread held up by a loaded machine loses no frame of its own
    # (at 1000 Hz with the default 16, underruns added gaps to the injected ones in a loaded run)
    with SyntheticCamera(frames, frame_rate_hz=200, drop_frames=drops, n_buffers=2000) as cam:
        acq = Acquisition(cam, ring_frames=256)
        cap = TriggeredCapture(acq, tmp_path / "d.h5", pre_frames=60, post_frames=80)
        with acq:
            assert acq.ring.wait_for(70, 60.0)  # hang detectors: 0.4 s and 0.7 s of frames
            cap.trigger_now()
            assert cap.wait(60.0)
    s = cap.summary()
    n, t = _assert_frames_match_ids(tmp_path / "d.h5")
    assert n == 140
    ids = t["frame_id"]
    missing = set(range(ids[0], ids[-1] + 1)) - set(ids)
    assert missing == {d for d in drops if ids[0] <= d <= ids[-1]} and len(missing) == 7
    pairs = [(a, c) for a, c in s["missing_frame_ids"]]
    assert {a + k for a, c in pairs for k in range(c)} == missing
    assert s["lost_upstream_id_gaps"] == 7 and s["lost_ring_overrun"] == 0 and s["total_missing"] == 7
    flagged = set(ids[(t["flags"] & FrameFlags.ID_GAP_BEFORE) != 0])
    assert flagged == {19, 53, 100, 131}
    text = format_summary(s)
    assert "lost upstream    7" in text and "17-18, 50-52, 99, 130" in text
    with h5py.File(tmp_path / "d.h5", "r") as f:  # the same summary is in the file
        assert json.loads(f["summary"].attrs["summary_json"])["lost_upstream_id_gaps"] == 7
        # every planned frame written, but 7 lost on the way (by-hand trial of 7 Dec 2026: `complete` 1 alone)
        assert f.attrs["complete"] == 1 and f.attrs["lossless"] == 0


def test_recorder_lapped_by_camera_counts_every_lost_frame(tmp_path):
    """Camera at full speed into a 4-frame ring, recorder writing: overruns are counted exactly."""
    frames = _frames(97, (256, 256))
    with SyntheticCamera(frames, max_rate=True) as cam:
        acq = Acquisition(cam, ring_frames=4)
        rec = Recorder(acq.ring, tmp_path / "o.h5", n_frames=3000, acquisition=acq)
        rec.begin(0)
        with acq:
            assert rec.wait(60.0)
            acq.stop()
    with h5py.File(tmp_path / "o.h5", "r") as f:
        t = f["frame_table"][:]
        n = len(t)
    seq = t["sequence"]
    assert np.all(np.diff(seq) >= 1)
    lost_in_file = int((np.diff(seq) - 1).sum())
    # rows + lost == the 3000 planned sequence numbers [0, 3000); beside stress-ng the camera can lap the
    # recorder on every one of them (a fresh-clone loaded run wrote no row): all 3000 are then counted lost
    if n:
        assert seq[-1] <= 2999 and n + lost_in_file + (2999 - seq[-1]) + seq[0] == 3000
    assert rec.lost_overrun == 3000 - n > 0
    s = rec.summary()
    assert s["lost_ring_overrun"] == rec.lost_overrun and s["total_missing"] >= rec.lost_overrun
    # every frame after a loss carries the flag
    after_loss = np.flatnonzero(np.diff(seq) > 1) + 1
    assert np.all(t["flags"][after_loss] & FrameFlags.RING_OVERRUN_BEFORE)
    n_ok, _ = _assert_frames_match_ids(tmp_path / "o.h5")
    assert n_ok == n
