"""A second ``tirdeflect record`` on a camera another process streams from (issue 7, case 6).

The first recording must go on untouched; the second must be refused within
seconds (not hang, not segfault), say that another program controls the
camera, and leave no file behind.
"""

import signal
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest

from tests.drivers.fixtures import gv_fake_camera  # noqa: F401  (pytest fixture)
from tests.faults.tools import ROOT, RecordProcess, wait_until

#: the refusal must come, not a wait for the camera: within this many seconds (Python start-up and
#: one open attempt, about 1.5 s quiet). A hang detector, >= 10x above need
REFUSE_WITHIN_S = 20.0


@pytest.mark.aravis
def test_second_record_on_a_busy_gige_camera_is_refused(tmp_path, gv_fake_camera):
    first = RecordProcess("--camera", gv_fake_camera.camera_id, "--frames", "2000", "--frame-rate-hz", "20",
                          "--out", str(tmp_path / "first.h5"))
    try:
        wait_until(lambda: first.progress() >= 5 or first.proc.poll() is not None, 60, "first recording under way")
        second_out = tmp_path / "second.h5"
        t0 = time.monotonic()
        second = subprocess.run([sys.executable, "-m", "app.cli", "record", "--camera", gv_fake_camera.camera_id,
                                 "--frames", "100", "--out", str(second_out), "--no-progress"], cwd=ROOT,
                                capture_output=True, text=True, timeout=60)
        took = time.monotonic() - t0
        n_before = first.progress()
        wait_until(lambda: first.progress() >= n_before + 10, 30, "first recording goes on after the refusal")
        first.proc.send_signal(signal.SIGTERM)
        code, stdout, stderr = first.wait(30)
    finally:
        first.kill()
    assert second.returncode == 2, f"exit {second.returncode}\n{second.stdout}\n{second.stderr}"
    lines = second.stderr.strip().splitlines()
    assert len(lines) == 1 and "controlled by another program" in lines[0], second.stderr
    assert took < REFUSE_WITHIN_S, f"refused only after {took:.1f} s"
    assert not second_out.exists(), "the refused recording left a file"
    # the first recording was not disturbed: contiguous frames, closed properly
    assert code == 143, stderr
    with h5py.File(tmp_path / "first.h5", "r") as f:
        n = int(f["frames"].attrs["frames_written"])
        table = f["frame_table"][:]
        assert "summary" in f and len(table) == n >= n_before + 10
    assert list(table["sequence"]) == list(range(n))
    print(f"second record refused after {took:.2f} s: {lines[0]}")
