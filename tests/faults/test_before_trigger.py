"""What ``tirdeflect record`` keeps when a triggered recording ends before its trigger came.

The pre-trigger frames wait in the ring (RAM) until the trigger; a stop signal
or a lost camera before it must not throw them away, nor file them as frames
after a trigger that never came. And a trigger that comes before all
pre-trigger frames exist must not be reported as a complete recording.

The recording runs in this process's main thread (``cmd_record``, which
installs the stop-signal handlers); a helper thread waits until the ring
really holds the frames (its head, read from the live capture), then sends
the signal to this process or kills the fake camera. Last, Ctrl-C while
writing must not be filed as an error of the recording.
"""

import argparse
import json
import os
import signal
import threading

import h5py
import numpy as np
import pytest

from app.capture import trigger as trigger_mod
from app.cli import record as record_cli
from app.files import imageio
from drivers.base import FrameFlags
from tests.drivers.fixtures import gv_fake_camera  # noqa: F401  (pytest fixture)
from tests.faults.tools import RecordProcess, wait_until

#: frames the ring must hold before the stop (more than --pre: only the last --pre are kept)
CAPTURED = 30
PRE = 12
#: hang detectors: the frames come at 50 (synthetic) / 20 (GigE) per second, a few seconds are needed
FRAMES_WITHIN_S = 120.0
END_WITHIN_S = 60.0
SYNTHETIC = ("--camera", "synthetic", "--synthetic-size", "64", "--synthetic-frames", "2", "--frame-rate-hz", "50")


def _parse(*argv):
    p = argparse.ArgumentParser()
    record_cli.add_record_arguments(p)
    return p.parse_args([*argv, "--no-progress"])


@pytest.fixture
def captures(monkeypatch):
    """The TriggeredCapture objects ``cmd_record`` creates (to read how many frames the ring holds)."""
    made = []
    init = trigger_mod.TriggeredCapture.__init__

    def spy(self, *args, **kwargs):
        init(self, *args, **kwargs)
        made.append(self)

    monkeypatch.setattr(trigger_mod.TriggeredCapture, "__init__", spy)
    return made


def _after_frames(captures, action):
    """A thread that runs ``action()`` once the capture's ring holds CAPTURED frames (errors kept for the test)."""
    failed = []

    def run():
        try:
            wait_until(lambda: captures and captures[0].acquisition.ring.head >= CAPTURED, FRAMES_WITHIN_S,
                       f"{CAPTURED} frames in the ring")
            action()
        except BaseException as exc:  # pytest.fail raises outside Exception
            failed.append(exc)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t, failed


def _pre_trigger_file(path):
    """The events of a file that holds the PRE frames before a trigger that never came (checked)."""
    with h5py.File(path, "r") as f:
        n = int(f["frames"].attrs["frames_written"])
        table = f["frame_table"][:n]
        frames = f["frames"][:n]
        events = [json.loads(e) for e in f["events"][:]]
        assert f.attrs["complete"] == 0 and "summary" in f
        error = f.attrs["error"]
        summary = json.loads(f["summary"].attrs["summary_json"])
        assert summary["error"] == error
        # no trigger came: the file claims none (docs/recording-format.md); it stored the stop's
        # sequence as `trigger_sequence` (and the frames kept as `pre_available`), a trigger frame it does not hold
        claimed = {k: f.attrs[k] for k in ("trigger_sequence", "pre_available") if k in f.attrs}
        assert claimed == {} and summary["trigger_sequence"] == -1, (claimed, summary["trigger_sequence"])
    assert not any(e["kind"] == "trigger" for e in events), events
    # what process (and the Replay tab) read of it: every frame before a trigger that never came
    assert imageio.pre_trigger_span(table) == (-PRE, -1)
    note = " ".join(imageio.recording_notes(path))
    assert f"all before its trigger (trigger_index {-PRE} to -1)" in note, note
    # the file's error is why it ended, and its end event says the same (a user's stop is no error)
    assert [e["message"] for e in events if e["kind"] == "end"] == [error or "ok"], events
    assert n == PRE, f"{n} frames kept, {PRE} pre-trigger frames asked for and captured"
    # the frames before the stop, counted back from it: none of them is (or follows) a trigger frame
    assert list(table["trigger_index"]) == list(range(-PRE, 0))
    assert not np.any(table["flags"] & FrameFlags.TRIGGER)
    assert np.all(np.diff(table["sequence"]) == 1) and np.all(frames.reshape(n, -1).max(axis=1) > 0)
    return events, error


def test_stop_signal_before_the_trigger_keeps_the_pre_trigger_frames_as_such(tmp_path, captures, capsys):
    out = tmp_path / "t.h5"
    helper, failed = _after_frames(captures, lambda: os.kill(os.getpid(), signal.SIGTERM))
    rc = record_cli.cmd_record(_parse(*SYNTHETIC, "--pre", str(PRE), "--post", "10", "--trigger-after-s", "600",
                                      "--out", str(out)))
    helper.join(END_WITHIN_S)
    assert not failed, failed
    text = capsys.readouterr()
    assert rc == 143, text
    assert f"stopped by SIGTERM; the file holds {PRE} frames" in text.err
    events, error = _pre_trigger_file(out)
    assert any(e["kind"] == "note" and "before the trigger" in e["message"] for e in events), events
    assert error == "", error  # the user's own stop


@pytest.mark.aravis
def test_camera_lost_before_the_trigger_keeps_the_frames_captured(tmp_path, captures, capsys, gv_fake_camera):
    out = tmp_path / "g.h5"
    helper, failed = _after_frames(captures, gv_fake_camera.kill)
    rc = record_cli.cmd_record(_parse("--camera", gv_fake_camera.camera_id, "--roi", "0,0,64,64", "--frame-rate-hz",
                                      "20", "--pre", str(PRE), "--post", "10", "--trigger-after-s", "600",
                                      "--out", str(out)))
    helper.join(END_WITHIN_S)
    assert not failed, failed
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2, err
    said = [line for line in err if line.startswith("tirdeflect record: error:")]
    assert len(said) == 1 and "lost" in said[0] and f"holds the {PRE} frames captured before it" in said[0], err
    _, error = _pre_trigger_file(out)
    # a user opening the file later sees why it is incomplete: the camera was lost, before the trigger
    assert "lost" in error and "before the trigger" in error and f"only the {PRE} frames" in error, error


def test_trigger_before_the_pre_trigger_frames_exist_is_not_a_complete_recording(tmp_path, capsys):
    """--trigger-after-s 0 with 50 pre-trigger frames at 10 frames/s: the trigger comes about 5 s too early."""
    out = tmp_path / "e.h5"
    rc = record_cli.cmd_record(_parse(*SYNTHETIC[:-2], "--frame-rate-hz", "10", "--pre", "50", "--post", "3",
                                      "--trigger-after-s", "0", "--out", str(out)))
    text = capsys.readouterr().out
    with h5py.File(out, "r") as f:
        n = int(f["frames"].attrs["frames_written"])
        have = int(f.attrs["pre_available"])
        assert f.attrs["complete"] == 0 and list(f["frame_table"]["trigger_index"]) == list(range(-have, 3))
    assert have < 50 and n == have + 3
    assert rc == 1, text
    assert f"frames written   {n} of 53 planned" in text
    assert f"pre-trigger      {have} of 50 frames" in text and f"{50 - have} pre-trigger frames missing" in text
    assert "no frame lost" not in text



def test_timeout_is_stored_as_the_files_error(tmp_path, capsys):
    """--timeout-s 1 on a recording of 5000 frames at 50 frames/s (100 s): it stops after about 1 s with
    exit 2, and the file's error and end event say that the time limit ended it."""
    out = tmp_path / "late.h5"
    rc = record_cli.cmd_record(_parse(*SYNTHETIC, "--frames", "5000", "--timeout-s", "1", "--out", str(out)))
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "error: recording did not finish within 1 s" in err
    with h5py.File(out, "r") as f:
        n = int(f["frames"].attrs["frames_written"])
        error = f.attrs["error"]
        events = [json.loads(e) for e in f["events"][:]]
        assert f.attrs["complete"] == 0 and 0 < n < 5000
        assert json.loads(f["summary"].attrs["summary_json"])["error"] == error
    assert error.startswith("recording did not finish within 1 s (--timeout-s)"), error
    assert [e["message"] for e in events if e["kind"] == "end"] == [error], events


@pytest.mark.aravis
def test_ctrl_c_is_a_stop_not_an_error_of_the_recording(tmp_path, gv_fake_camera):
    """Ctrl-C (a real SIGINT to a real ``tirdeflect record``) while writing: neither the file nor the
    log may call the user's own stop an error.

    The camera used to be stopped first; a recorder that had caught up then met the end of the frames
    before it was told to stop, and filed "acquisition stopped after N of M frames" as the error."""
    out = tmp_path / "c.h5"
    rec = RecordProcess("--camera", gv_fake_camera.camera_id, "--roi", "0,0,64,64", "--frame-rate-hz", "20",
                        "--frames", "5000", "--out", str(out))
    try:
        wait_until(lambda: rec.progress() >= 10 or rec.proc.poll() is not None, FRAMES_WITHIN_S, "10 frames written")
        rec.proc.send_signal(signal.SIGINT)
        code, stdout, stderr = rec.wait(END_WITHIN_S)
    finally:
        rec.kill()
    assert code == 130, f"exit {code}\n{stdout}\n{stderr}"
    assert "ERROR" not in stderr and "ERROR" not in stdout, stdout + stderr
    with h5py.File(out, "r") as f:
        n = int(f["frames"].attrs["frames_written"])
        assert f.attrs["complete"] == 0 and f.attrs["error"] == "" and 10 <= n < 5000
        assert list(f["frame_table"]["sequence"]) == list(range(n))
