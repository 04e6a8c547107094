"""``tirdeflect cameras`` / ``tirdeflect record`` through their functions (what app/cli/main.py calls)."""

import argparse

import h5py
import numpy as np
import pytest

from app.cli import record as record_cli
from drivers.base import FrameFlags
from tests.drivers.fixtures import gv_fake_camera, viky_cti  # noqa: F401  (pytest fixtures)


def _parse(*argv):
    p = argparse.ArgumentParser()
    record_cli.add_record_arguments(p)
    return p.parse_args(list(argv))


SMALL_SCENE = ("--synthetic-size", "64", "--synthetic-frames", "4", "--no-progress")


def test_cameras_lists_synthetic(capsys):
    p = argparse.ArgumentParser()
    record_cli.add_cameras_arguments(p)
    assert record_cli.cmd_cameras(p.parse_args(["--timeout-s", "1"])) == 0
    out = capsys.readouterr().out
    assert "camera id" in out and "\nsynthetic " in out


def test_record_frames_from_the_ray_traced_scene(tmp_path, capsys):
    out = tmp_path / "s.h5"
    rc = record_cli.cmd_record(_parse("--camera", "synthetic", "--frames", "30", "--frame-rate-hz", "300",
                                      "--out", str(out), *SMALL_SCENE))
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "frames written   30 of 30 planned" in text and "no frame lost" in text
    with h5py.File(out, "r") as f:
        assert f["frames"].shape == (30, 64, 64) and f.attrs["complete"] == 1
        assert list(f["frame_table"]["frame_id"]) == list(range(30))
        assert "theta_deg" in f["geometry_toml"][()].decode()  # the scene's geometry travels with the data
        ref = f["reference"][:]
        # the reference is the flat-surface checkerboard: full contrast, not a copy of frame 0
        assert ref.shape == (64, 64) and ref.max() - ref.min() > 100
        assert not np.array_equal(ref, f["frames"][0])


def test_record_pre_post_with_genicam_trigger(tmp_path, capsys):
    out = tmp_path / "g.h5"
    rc = record_cli.cmd_record(_parse("--camera", "synthetic", "--pre", "8", "--post", "12", "--trigger", "genicam",
                                      "--frame-rate-hz", "200", "--out", str(out), *SMALL_SCENE))
    assert rc == 0, capsys.readouterr()
    with h5py.File(out, "r") as f:
        t = f["frame_table"][:]
        assert list(t["trigger_index"]) == list(range(-8, 12)) and f.attrs["trigger_source"] == "genicam"


@pytest.mark.aravis
def test_record_pre_post_from_gige_fake_camera(tmp_path, capsys, gv_fake_camera):
    out = tmp_path / "gv.h5"
    rc = record_cli.cmd_record(_parse("--camera", gv_fake_camera.camera_id, "--pre", "5", "--post", "10",
                                      "--frame-rate-hz", "50", "--roi", "0,0,128,96", "--out", str(out),
                                      "--no-progress"))
    text = capsys.readouterr()
    assert rc == 0, text
    with h5py.File(out, "r") as f:
        assert f["frames"].shape == (15, 96, 128)
        t = f["frame_table"][:]
        assert list(t["trigger_index"]) == list(range(-5, 10)) and np.all(np.diff(t["frame_id"]) == 1)
        assert f["camera"].attrs["camera_id"] == gv_fake_camera.camera_id


@pytest.mark.parametrize(
    "argv, message",
    [
        (("--frames", "5", "--pre", "3"), "give either --frames N, or --pre/--post"),
        (("--camera", "nonsense:1", "--frames", "5"), "unknown camera id 'nonsense:1'"),
        (("--pre", "5", "--post", "5", "--trigger", "line1", "--trigger-timeout-s", "0.3"),
         "no frames before it; got pre=5"),
        (("--post", "5", "--trigger", "line1", "--trigger-timeout-s", "0.3"), "no pulse on Line1"),
        (("--frames", "5", "--exposure-us", "-3"), "--exposure-us must be > 0 microseconds; got -3"),
    ],
)
def test_errors_are_one_line_and_exit_2(tmp_path, capsys, argv, message):
    rc = record_cli.cmd_record(_parse("--out", str(tmp_path / "e.h5"), *SMALL_SCENE, *argv))
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert len(err) == 1 and err[0].startswith("tirdeflect record: error: ") and message in err[0], err


@pytest.mark.aravis
def test_roi_past_the_sensor_edge_is_refused_before_recording(tmp_path, capsys, gv_fake_camera):
    """--roi 2000,0,100,100 on the fake GigE camera's 2048-pixel-wide sensor: its OffsetX accepted 2000 (and read
    it back) while it delivered 100 x 100 frames, and the file said offset_x 2000, a window the sensor does not
    have. Refused before a file exists, naming the sensor's width and the largest offset for that width; the
    largest allowed offset still records and is stored as such."""
    out = tmp_path / "r.h5"
    rc = record_cli.cmd_record(_parse("--camera", gv_fake_camera.camera_id, "--frames", "10", "--roi",
                                      "2000,0,100,100", "--out", str(out), "--no-progress"))
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2, err
    assert len(err) == 1 and err[0].startswith("tirdeflect record: error: offset_x=2000 with width=100"), err
    assert "2048 pixels wide" in err[0] and "offset_x may be at most 1948" in err[0], err
    assert not out.exists()
    rc = record_cli.cmd_record(_parse("--camera", gv_fake_camera.camera_id, "--frames", "3", "--roi",
                                      "1948,1948,100,100", "--out", str(out), "--no-progress"))
    assert rc == 0, capsys.readouterr()
    with h5py.File(out, "r") as f:
        assert f["frames"].shape == (3, 100, 100)
        cam = f["camera"].attrs
        assert (cam["offset_x"], cam["offset_y"], cam["width"], cam["height"]) == (1948, 1948, 100, 100)


def test_a_recording_that_failed_before_its_first_frame_leaves_no_file(tmp_path, capsys):
    """No line pulse came: the error says no file was written, and the same --out works for the next try."""
    out = tmp_path / "l.h5"
    argv = ("--out", str(out), *SMALL_SCENE, "--post", "5", "--trigger", "line1", "--trigger-timeout-s", "0.3")
    assert record_cli.cmd_record(_parse(*argv)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no pulse on Line1" in err[0] and "no file was written" in err[0], err
    assert not out.exists()
    assert record_cli.cmd_record(_parse("--out", str(out), *SMALL_SCENE, "--frames", "3")) == 0, capsys.readouterr()


def test_existing_file_is_kept_or_numbered(tmp_path, capsys):
    out = tmp_path / "x.h5"
    out.write_bytes(b"keep")
    assert record_cli.cmd_record(_parse("--frames", "3", "--out", str(out), *SMALL_SCENE)) == 2
    assert "already exists" in capsys.readouterr().err and out.read_bytes() == b"keep"
    assert record_cli.cmd_record(_parse("--frames", "3", "--out", str(out), "--auto-name", *SMALL_SCENE)) == 0
    with h5py.File(tmp_path / "x-001.h5", "r") as f:
        assert f["frames"].shape[0] == 3


def test_main_entry_runs_record(tmp_path):
    out = tmp_path / "m.h5"
    assert record_cli.main(["record", "--frames", "4", "--out", str(out), *SMALL_SCENE]) == 0
    assert out.exists()


def test_record_with_auto_trigger_on_the_growing_dimple(tmp_path, capsys):
    """The scene's dimple deepens frame by frame; the RMS slope the reconstruction measures crosses the
    threshold and the trigger frame is stored with the RMS that fired it, in the unit the file gives its
    threshold (soak trial, 8 Dec 2026: the window's file said rms 5.47e-05 beside a threshold of 0.001
    "mrad RMS slope", as if it had fired at 1/20 of it)."""
    import json

    out = tmp_path / "auto.h5"
    rc = record_cli.cmd_record(_parse("--camera", "synthetic", "--synthetic-size", "128", "--synthetic-frames", "16",
                                      "--frame-rate-hz", "50", "--pre", "5", "--post", "5", "--trigger", "auto",
                                      "--threshold", "0.0005", "--trigger-timeout-s", "60", "--out", str(out),
                                      "--no-progress"))
    assert rc == 0, capsys.readouterr()
    with h5py.File(out, "r") as f:
        ev = json.loads(f["events"][0])
        t = f["frame_table"][:]
        threshold, unit = float(f.attrs["auto_trigger_threshold"]), str(f.attrs["auto_trigger_threshold_unit"])
    assert ev["kind"] == "trigger" and ev["source"] == "auto" and ev["rms"] > 0.0005
    assert unit == "mrad RMS slope" and threshold == pytest.approx(0.5)  # --threshold 0.0005 (mm/mm)
    assert ev["rms_mrad"] == pytest.approx(1e3 * ev["rms"]) and ev["rms_mrad"] > threshold
    assert list(t["trigger_index"]) == list(range(-5, 5)) and t["sequence"][5] == ev["sequence"]


@pytest.mark.gentl
def test_record_from_a_gentl_producer(tmp_path, capsys, viky_cti):
    """viky.cti (the genicam wheel's producer) has no trigger and no offset features: still records."""
    out = tmp_path / "v.h5"
    rc = record_cli.cmd_record(_parse("--camera", f"gentl:{viky_cti}:1", "--frames", "10", "--roi", "0,0,128,112",
                                      "--pixel-format", "Mono8", "--frame-rate-hz", "50", "--out", str(out),
                                      "--no-progress"))
    assert rc == 0, capsys.readouterr()
    with h5py.File(out, "r") as f:
        assert f["frames"].shape == (10, 112, 128) and f.attrs["complete"] == 1
        t = f["frame_table"][:]
    assert np.all(np.diff(t["frame_id"]) == 1) and np.all(np.diff(t["host_timestamp_ns"]) > 0)
    # this producer gives no device timestamps: stored as -1 and flagged, never a silent 0
    assert np.all(t["device_timestamp_ns"] == -1) and np.all(t["flags"] & FrameFlags.NO_DEVICE_TIMESTAMP)


@pytest.mark.gentl
def test_camera_left_in_a_colour_format_is_refused_naming_the_option(tmp_path, capsys, viky_cti):
    """viky.cti starts in RGBa8: refused before a file is made, with the option that fixes it."""
    out = tmp_path / "c.h5"
    rc = record_cli.cmd_record(_parse("--camera", f"gentl:{viky_cti}:1", "--frames", "3", "--out", str(out),
                                      "--no-progress"))
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert "'RGBa8'" in err[0] and "--pixel-format Mono8" in err[0] and "configure(" not in err[0], err
    assert not out.exists()


@pytest.mark.parametrize("stderr_to", ["a pipe its reader quits", "closed"])
def test_a_recording_goes_on_when_its_terminal_output_goes_away(tmp_path, stderr_to):
    """By-hand trial of 7 Dec 2026: `tirdeflect record ... 2>&1 | head` stopped the recording at 9-11 of
    50 frames with "[Errno 32] Broken pipe", said only to the pipe that had gone (the progress bar's write
    failed and ended the recording); with stderr closed (`2>&-`) it ended at once, exit 1, no file. The
    display is now never what stops a recording: every frame is written, exit 0."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    out = tmp_path / "r.h5"
    cmd = [sys.executable, "-m", "app.cli", "record", "--camera", "synthetic", "--synthetic-size", "64",
           "--synthetic-frames", "4", "--frames", "150", "--frame-rate-hz", "100", "--out", str(out)]
    root = Path(__file__).resolve().parents[2]
    if stderr_to == "closed":
        proc = subprocess.Popen(cmd, cwd=root, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                preexec_fn=lambda: os.close(2))
    else:
        proc = subprocess.Popen(cmd, cwd=root, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        proc.stderr.read(20)  # the first characters of the bar, then the reader is gone
        proc.stderr.close()
    assert proc.wait(timeout=120) == 0
    with h5py.File(out) as f:
        assert f["frames"].shape[0] == 150 and not f.attrs.get("error")


def test_recordings_started_together_with_auto_name_each_get_a_file(tmp_path):
    """By-hand trial of 7 Dec 2026: three `record --auto-name --out same.h5` started at once: one failed,
    "'same-001.h5' already exists ... (or let tirdeflect number it: --auto-name)": each chose the first free
    name before opening its camera, and the first to create it won. A name taken meanwhile now moves the
    recording to the next free one."""
    import subprocess
    import sys
    from pathlib import Path

    (tmp_path / "same.h5").write_bytes(b"an earlier recording")
    cmd = [sys.executable, "-m", "app.cli", "record", "--camera", "synthetic", "--synthetic-size", "64",
           "--synthetic-frames", "4", "--frames", "20", "--no-progress", "--auto-name", "--out",
           str(tmp_path / "same.h5")]
    procs = [subprocess.Popen(cmd, cwd=Path(__file__).resolve().parents[2], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for _ in range(3)]
    results = [(p.wait(timeout=180), p.communicate()[1]) for p in procs]
    assert [code for code, _ in results] == [0, 0, 0], results
    made = sorted(p.name for p in tmp_path.glob("same-*.h5"))
    assert made == ["same-001.h5", "same-002.h5", "same-003.h5"], made
    for name in made:
        with h5py.File(tmp_path / name) as f:
            assert f["frames"].shape[0] == 20
    assert (tmp_path / "same.h5").read_bytes() == b"an earlier recording"
