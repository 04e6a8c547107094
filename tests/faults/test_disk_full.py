"""A GigE recording while another process fills the disk (issue 7, case 1).

The fake GigE camera streams 512x512 frames at 20 fps into ``tirdeflect record``
on a 24 MB disk; once the recording is under way, ``dd`` (a second process)
takes every byte left. What the user must get: exit 2 within seconds (no
hang, no segfault), a one-line error naming the full disk, and a file that
h5py opens, holding exactly the number of frames the summary prints, with a
frame table that agrees with them.

* tmpfs reserves space (fallocate): the recorder stops while the space to
  close the file is still in hand, so the file is closed properly (trimmed,
  with ``/summary``).
* ext2 cannot reserve space: HDF5 itself meets the full disk; the close path
  writes nothing more and the file is what the last flush left.
"""

import h5py
import numpy as np
import pytest

from tests.drivers.fixtures import gv_fake_camera  # noqa: F401  (pytest fixture)
from tests.faults.tools import fill_disk, frames_written_line, small_disk, start_record, wait_until

FRAME_BYTES = 512 * 512
#: bound for the whole run after the disk filled: the camera sends 20 frames/s, the recorder stops at the next one
END_WITHIN_S = 30.0


@pytest.mark.aravis
@pytest.mark.parametrize("fs", ["tmpfs", "ext2"])
def test_gige_recording_disk_filled_by_another_process(tmp_path, gv_fake_camera, fs):
    with small_disk(tmp_path, fs, 24) as mnt:
        out = mnt / "r.h5"
        # 400 frames (105 MB) never fit: the recording must stop on the full disk
        proc = start_record("--camera", gv_fake_camera.camera_id, "--frames", "400", "--frame-rate-hz", "20",
                            "--no-space-check", "--out", str(out))
        try:
            # some frames are on disk (file beyond 6 frames; on tmpfs beyond the 4 MB kept for closing too)
            grown = 6 * FRAME_BYTES + (4 * 1024 * 1024 if fs == "tmpfs" else 0)
            wait_until(lambda: out.exists() and out.stat().st_size > grown, 60, "recording under way")
            dd = fill_disk(mnt)
            assert "No space left on device" in dd.stderr
            stdout, stderr = proc.communicate(timeout=END_WITHIN_S)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
        assert proc.returncode == 2, f"exit {proc.returncode}\n{stdout}\n{stderr}"
        error_lines = [line for line in stderr.splitlines() if line.startswith("tirdeflect record: error:")]
        assert len(error_lines) == 1 and ("disk full" in error_lines[0] or "No space left" in error_lines[0]), stderr
        assert "Traceback" not in stderr
        n_said = frames_written_line(stdout)
        with h5py.File(out, "r") as f:
            n = int(f["frames"].attrs["frames_written"])
            table = f["frame_table"][:n]
            frames = f["frames"][:n]
            assert f.attrs["complete"] == 0
            if fs == "tmpfs":  # closed properly inside the reserve
                assert f["frames"].shape[0] == n and len(f["frame_table"]) == n and "summary" in f
                assert "disk full" in f.attrs["error"]
        # what the summary says is what the file holds, and the frames are really there
        assert n == n_said >= 6
        assert list(table["sequence"]) == list(range(n)) and np.all(np.diff(table["frame_id"]) >= 1)
        assert np.all(frames.reshape(n, -1).max(axis=1) > 0), "a frame the file vouches for holds no pixels"
        print(f"{fs}: {n} frames kept, file {out.stat().st_size} bytes; {error_lines[0]}")


def test_write_failure_leaves_the_last_flushed_file(tmp_path, monkeypatch):
    """The last resort: HDF5 itself fails to write (no reservation, no reserve file, no stop before full).

    The safety nets are switched off so that the disk (ext2, no fallocate) fills under the recorder's own
    writes. Then nothing more may reach the file: no trim, no ``/events``, no ``/summary``; the file opens
    and holds exactly the frames of the last successful flush, which the recorder reports.
    """
    import app.capture.recorder as recorder_module
    from app.capture.acquisition import Acquisition
    from app.capture.recorder import Recorder, RecordingFile
    from drivers.synthetic import SyntheticCamera

    monkeypatch.setattr(recorder_module, "RESERVE_BYTES", -(1 << 40))  # never stop before the disk is full
    monkeypatch.setattr(RecordingFile, "_make_reserve_file", lambda self: None)
    frames = ((np.arange(97) * 2) % 256).astype(np.uint8)[:, None, None] * np.ones((1, 128, 128), np.uint8)
    with small_disk(tmp_path, "ext2", 8) as mnt:
        out = mnt / "io.h5"
        with SyntheticCamera(frames, frame_rate_hz=4000) as cam:
            acq = Acquisition(cam, ring_frames=2048)
            rec = Recorder(acq.ring, out, n_frames=2000, acquisition=acq, flush_interval_s=0.01, check_space=False)
            rec.begin(0)
            acq.stop_after(1999)
            with acq:
                assert rec.wait(30.0), "recorder hung on a failed write"
        assert rec.state == "error" and "No space left on device" in rec.error, rec.error
        assert f"holds {rec.frames_written} valid frames" in rec.error
        with h5py.File(out, "r") as f:
            n = int(f["frames"].attrs["frames_written"])
            assert f["frames"].shape[0] == 2000 and len(f["frame_table"]) == 2000  # not trimmed: nothing written
            assert "summary" not in f and "events" not in f and f.attrs["complete"] == 0
            table = f["frame_table"][:n]
            data = f["frames"][:n].reshape(n, -1)
        assert n == rec.frames_written and 50 < n < 2000
        assert list(table["sequence"]) == list(range(n))
        expect = (table["frame_id"] % 97 * 2 % 256).astype(np.uint8)
        assert np.array_equal(data.min(axis=1), expect) and np.array_equal(data.max(axis=1), expect)
