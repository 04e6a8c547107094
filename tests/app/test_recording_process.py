"""`tirdeflect process` and `probe` on recordings of the synthetic (ray-traced) camera, as a physicist
processes them: frames lost between the frames --step picks, a run interrupted by a real SIGINT and
resumed as its message says, the trigger frame in probe's series, recordings stopped before their
trigger or by a lost camera."""

from __future__ import annotations

import csv
import signal
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from drivers.base import FrameFlags
from tests.helpers import stderr_until_signalled

ROOT = Path(__file__).resolve().parents[2]
PRE, POST = 5, 35
LOSS = int(FrameFlags.ID_GAP_BEFORE | FrameFlags.TIME_GAP_BEFORE)


def _cli(*args, timeout=300):
    return subprocess.run([sys.executable, "-m", "app.cli", *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """40 frames (128 px) of the ray-traced tank, software trigger after 5 of them."""
    path = tmp_path_factory.mktemp("recs") / "rec.h5"
    r = _cli("record", "--camera", "synthetic", "--out", path, "--pre", PRE, "--post", POST,
             "--trigger", "software", "--synthetic-size", "128", "--synthetic-frames", "4", "--no-progress")
    assert r.returncode == 0, r.stderr
    with h5py.File(path) as f:
        assert list(f["frame_table"]["trigger_index"]) == list(range(-PRE, POST))
    return path


def _rewrite(src, dst, rows, *, planned=None, error=None, summary=None, blank=()):
    """A recording of ``src``'s frames ``[i for i, ...]`` with the frame-table rows given:
    ``rows`` = ``[(frame i of src, camera frame id, flags, trigger_index), ...]`` (10 ms apart by id);
    the rows at the positions ``blank`` get an all-zero frame (every packet lost, no light)."""
    from app.capture.recorder import RecordingFile

    with h5py.File(src) as f:
        frames, reference = f["frames"][()], f["reference"][()]
        geometry = f["geometry_toml"][()]
    rec = RecordingFile(dst, shape=reference.shape, dtype=np.uint8, n_frames=planned or len(rows),
                        check_space=False, camera_id="synthetic", reference_image=reference,
                        geometry_toml=geometry.decode() if isinstance(geometry, bytes) else geometry)
    for k, (i, frame_id, flags, trigger) in enumerate(rows):
        image = np.zeros_like(frames[i]) if k in blank else frames[i]
        rec.write(image, (k, frame_id, 10_000_000 * frame_id, 10_000_000 * frame_id + 5, flags, trigger))
    rec.close(summary, error)
    return dst


def _read_csv(path):
    with open(path, newline="") as fh:
        rows = list(csv.reader(ln for ln in fh if not ln.startswith("#")))
    return rows[0], rows[1:]


@pytest.mark.parametrize("workers", ["1", "2"])
def test_frames_lost_between_stepped_frames_are_said(recording, tmp_path, workers):
    """The camera lost frames 4..6 (ids 0..3, then 7..): --step 3 picks frames 0, 3, 6, 9, whose own rows
    carry no flag; the loss lay on frame 4, stepped over. It was silent (exit 0, every /frame_flags 0,
    no note) while time_s went 0.03 s then 0.06 s."""
    ids = [0, 1, 2, 3] + list(range(7, 15))
    rows = [(i, i, LOSS if i == 7 else 0, i - PRE) for i in ids]
    rec = _rewrite(recording, tmp_path / "gaps.h5", rows)
    out = tmp_path / "out.h5"
    r = _cli("process", rec, "--out", out, "--step", "3", "--no-progress", "--workers", workers,
             "--chunk-frames", "1")
    assert r.returncode == 0, r.stderr
    assert "lost frames before 1 processed frame(s), e.g. before frame 6" in r.stderr, r.stderr
    with h5py.File(out) as f:
        assert list(f["frame_index"][()]) == [0, 3, 6, 9]
        assert list(f["camera_frame_id"][()]) == [0, 3, 9, 12]
        np.testing.assert_allclose(f["time_s"][()], [0.0, 0.03, 0.09, 0.12], atol=1e-9)
        assert list(f["frame_flags"][()] & LOSS) == [0, 0, LOSS, 0]
        assert f.attrs["frames_with_loss_before"] == 1
    # step 1: the flag stays on the frame the recorder put it on, as before
    r = _cli("process", rec, "--out", tmp_path / "all.h5", "--no-progress", "--workers", "1")
    assert r.returncode == 0, r.stderr
    with h5py.File(tmp_path / "all.h5") as f:
        assert list(np.flatnonzero(f["frame_flags"][()] & LOSS)) == [4]


#: the run stops at frame 9 until it is interrupted: the signal lands mid-run, whatever the machine's speed
_STUCK_CHILD = """
import signal, sys, time
signal.signal(signal.SIGINT, signal.default_int_handler)
import app.batch.parallel as parallel
_measure = parallel.measure
def measure(recon, item, *args, **kwargs):
    if item.sequence_index == 9:
        print("stuck at frame 9", file=sys.stderr, flush=True)
        time.sleep(120)
    return _measure(recon, item, *args, **kwargs)
parallel.measure = measure
from app.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_interrupted_run_says_where_to_resume_and_resuming_completes_it(recording, tmp_path):
    """A real SIGINT after frames 1, 3, 5, 7 of --first 1 --step 2: the message named the partial file
    but not where to go on; it now says --first 9 --step 2, and that run completes the series."""
    out = tmp_path / "out.h5"
    proc = subprocess.Popen([sys.executable, "-c", _STUCK_CHILD, "process", str(recording), "--out", str(out),
                             "--first", "1", "--step", "2", "--no-progress", "--workers", "1"],
                            cwd=ROOT, stderr=subprocess.PIPE, text=True)

    def stop_at_frame_9(line):
        if line.startswith("stuck at frame 9"):
            proc.send_signal(signal.SIGINT)
            return True
        return False

    code, err = stderr_until_signalled(proc, stop_at_frame_9)
    assert code == 130, err
    partial = tmp_path / "out.partial.h5"
    assert f"the 4 frame(s) written are kept in {partial}" in err, err
    assert "--first 9 --step 2` into another --out" in err, err
    rest, full = tmp_path / "rest.h5", tmp_path / "full.h5"
    r = _cli("process", recording, "--out", rest, "--first", "9", "--step", "2", "--no-progress", "--workers", "1")
    assert r.returncode == 0, r.stderr
    r = _cli("process", recording, "--out", full, "--first", "1", "--step", "2", "--no-progress", "--workers", "1")
    assert r.returncode == 0, r.stderr
    with h5py.File(partial) as a, h5py.File(rest) as b, h5py.File(full) as c:
        n = int(a.attrs["frames_done"])
        assert n == 4
        index = np.r_[a["frame_index"][:n], b["frame_index"][()]]
        assert list(index) == list(range(1, PRE + POST, 2))  # nothing lost, nothing twice
        assert list(np.r_[a["trigger_index"][:n], b["trigger_index"][()]]) == list(index - PRE)
        heights = np.concatenate([a["height"][:n], b["height"][()]])
        # the same surface as one uninterrupted run, to well under a nanometre
        np.testing.assert_allclose(heights, c["height"][()], atol=1e-7, equal_nan=True)


def test_probe_series_carries_the_trigger_index(recording, tmp_path):
    """probe wrote frame_index and time_s (from the recording's first frame) only: where the trigger
    came was lost between `process` (/trigger_index) and the time series."""
    out = tmp_path / "out.h5"
    r = _cli("process", recording, "--out", out, "--frames", "3:12", "--no-progress", "--workers", "1")
    assert r.returncode == 0, r.stderr
    csv_path = tmp_path / "p.csv"
    r = _cli("probe", out, "--at", "0,0", "--at", "5,-5", "--out", csv_path)
    assert r.returncode == 0, r.stderr
    assert "the trigger frame (trigger_index 0) is frame 5, at time_s 0.05 s" in r.stderr, r.stderr
    header, body = _read_csv(csv_path)
    assert header[:3] == ["frame_index", "time_s", "trigger_index"] and len(header) == 5
    frame_index = [int(row[0]) for row in body]
    assert frame_index == list(range(3, 12))
    assert [int(row[2]) for row in body] == [k - PRE for k in frame_index]
    np.testing.assert_allclose([float(row[1]) for row in body], np.array(frame_index) * 0.01, atol=1e-6)
    with h5py.File(csv_path.with_suffix(".h5")) as f:
        assert list(f["trigger_index"][()]) == [k - PRE for k in frame_index]
        assert f["height_mm"].shape == (9, 2)


def test_the_export_message_names_only_the_turns_the_run_flagged(recording, tmp_path):
    """The synthetic tank's waves read up to 0.35 mrad of turn on a 128^2 frame, within three standard errors of
    their estimate: the run flags none (``frames_turned`` 0, no note), but the window's export message named
    every frame above 0.1 mrad "where the pattern turned since the reference ... capture a new reference"
    and showed the export as not clean (7 Dec 2026). Now it names the frames the run flagged (/turn_flagged)."""
    from app.gui.export import describe_export
    from processing.turn import TURN_MAX_MRAD

    out = tmp_path / "out.h5"
    r = _cli("process", recording, "--out", out, "--no-progress", "--workers", "1")
    assert r.returncode == 0, r.stderr
    with h5py.File(out) as f:
        turn, flagged = np.abs(f["turn_mrad"][()]), f["turn_flagged"][()]
        assert int(np.count_nonzero(turn > TURN_MAX_MRAD)) >= 5  # the waves' reading (what the message named)
        assert f.attrs["frames_turned"] == int(np.count_nonzero(flagged)) == 0
    text, _ = describe_export(str(out))
    assert "turned" not in text, text


def _red_in_mark_line(movie):
    """Per frame of ``movie``: how many pixels of the text band's second line (where the movie marks a
    frame in red) are red."""
    import av

    with av.open(str(movie)) as c:
        images = [frame.to_ndarray(format="rgb24").astype(int) for frame in c.decode(video=0)]
    counts = []
    for image in images:
        band = image[30:52, :512]  # under the stamp line, above the map (512 px: 128 px magnified 4x)
        counts.append(int(np.sum((band[..., 0] > 120) & (band[..., 0] - band[..., 1:].max(axis=-1) > 60))))
    return counts


def test_movie_stamps_the_trigger_index_and_marks_invalid_incomplete_and_lost_frames(recording, tmp_path):
    """`tirdeflect movie` stamped "frame K   t = T s" alone: which frame is the trigger frame, and that a
    map is grey because the frame is invalid, or came with pixels or frames before it lost, was not in
    the movie. Now each frame of a triggered recording says its index from the trigger (the recording's
    trigger_index), and the flagged frames are marked in red; a recording made without a trigger
    (`record --frames`) claims no trigger index."""
    from app.batch.movie import frame_stamps

    out = tmp_path / "trig.h5"
    r = _cli("process", recording, "--out", out, "--frames", "2:9", "--no-progress", "--workers", "1")
    assert r.returncode == 0, r.stderr
    with h5py.File(out) as f:
        stamps = frame_stamps(f, 7)
    assert stamps[0] == ("frame 2   t = 0.0200 s   trigger -3", "")
    assert [line.split("   trigger ")[-1] for line, _ in stamps] == ["-3", "-2", "-1", "0", "+1", "+2", "+3"]
    assert [mark for _, mark in stamps] == [""] * 7

    # frame 3 recorded INCOMPLETE, frames lost (camera ids 5, 6) before frame 5, frame 6 black
    rows = [(i, i if i < 5 else i + 2, {3: FrameFlags.INCOMPLETE, 5: LOSS}.get(i, 0), i - PRE) for i in range(9)]
    flagged = _rewrite(recording, tmp_path / "flagged.h5", rows, blank=(6,))
    out = tmp_path / "flagged_out.h5"
    r = _cli("process", flagged, "--out", out, "--no-progress", "--workers", "1")
    assert r.returncode == 3, r.stderr  # an invalid frame and an INCOMPLETE one
    with h5py.File(out) as f:
        stamps = frame_stamps(f, 9)
    marks = {k: mark for k, (_, mark) in enumerate(stamps) if mark}
    assert marks == {3: "INCOMPLETE", 5: "frames lost before", 6: "INVALID: blank"}, stamps
    assert stamps[5][0] == "frame 5   t = 0.0700 s   trigger 0", stamps[5]  # the trigger frame
    movie = tmp_path / "flagged.mp4"
    r = _cli("movie", out, "--out", movie)
    assert r.returncode == 0, r.stderr
    red = _red_in_mark_line(movie)
    assert len(red) == 9 and [k for k, count in enumerate(red) if count > 20] == [3, 5, 6], red
    assert all(count == 0 for k, count in enumerate(red) if k not in (3, 5, 6)), red

    plain = tmp_path / "plain.h5"  # no trigger: its frame table counts trigger_index from the first frame
    r = _cli("record", "--camera", "synthetic", "--out", plain, "--frames", 3, "--synthetic-size", 128,
             "--synthetic-frames", 4, "--no-progress")
    assert r.returncode == 0, r.stderr
    out = tmp_path / "plain_out.h5"
    r = _cli("process", plain, "--out", out, "--no-progress", "--workers", "1")
    assert r.returncode == 0, r.stderr
    with h5py.File(out) as f:
        lines = [line for line, _ in frame_stamps(f, 3)]
    assert [line.split("   ")[0] for line in lines] == ["frame 0", "frame 1", "frame 2"]
    assert not any("trigger" in line for line in lines), lines


def test_recording_stopped_before_its_trigger_is_said_by_process_and_probe(recording, tmp_path):
    """Stopped (SIGTERM) while waiting for the trigger: 8 frames, trigger_index -8..-1, no trigger frame.
    process said only 'ended early, 8 of the 18 planned frames', as if the event were in them."""
    rows = [(i, 100 + i, 0, i - 8) for i in range(8)]
    rec = _rewrite(recording, tmp_path / "pre.h5", rows, planned=18, summary={"frames_written": 8})
    out = tmp_path / "out.h5"
    r = _cli("process", rec, "--out", out, "--no-progress", "--workers", "1")
    assert r.returncode == 0, r.stderr
    assert "all before its trigger (trigger_index -8 to -1)" in r.stderr, r.stderr
    assert "no frame is the trigger frame" in r.stderr
    with h5py.File(out) as f:
        assert list(f["trigger_index"][()]) == list(range(-8, 0))
        assert list(f["frame_status"][()]) == [0] * 8
    r = _cli("probe", out, "--at", "0,0", "--out", tmp_path / "p.csv")
    assert r.returncode == 0, r.stderr
    assert "no processed frame is a trigger frame: trigger_index runs from -8 to -1" in r.stderr, r.stderr
    header, body = _read_csv(tmp_path / "p.csv")
    assert header[2] == "trigger_index" and [int(row[2]) for row in body] == list(range(-8, 0))


def test_camera_lost_error_of_a_recording_without_summary_is_named(recording, tmp_path):
    """A recording whose `error` says the camera was lost, closed without /summary: process's note said
    'stopped hard, or a copy taken while it recorded' and dropped the error the file holds."""
    error = "camera 'aravis:127.0.0.1' lost: stopped answering (no register read succeeded for 2.0 s)"
    rec = _rewrite(recording, tmp_path / "lost.h5", [(i, i, 0, i - 2) for i in range(6)], planned=12,
                   error=error)
    with h5py.File(rec) as f:
        assert "summary" not in f and f.attrs["complete"] == 0
    r = _cli("process", rec, "--out", tmp_path / "out.h5", "--no-progress", "--workers", "1")
    assert r.returncode == 0, r.stderr
    warning = [ln for ln in r.stderr.splitlines() if "WARNING" in ln and "lost.h5" in ln]
    assert len(warning) == 1 and f"its error: {error}" in warning[0], r.stderr
    assert "6 of the 12 planned frames" in warning[0]


def test_a_recording_whose_ring_overran_is_said_to_have_lost_frames_not_to_have_ended_early(tmp_path):
    """Sweep of 7 Dec 2026: 200 frames at 20 kHz through a 2-frame ring (the recorder behind the camera): the
    recording ran to its end with 144 frames lost to ring overruns, and process's first note said "ended
    early (complete = 0): it holds 56 of the 200 planned frames". Now it names the losses."""
    rec = tmp_path / "ovr.h5"
    r = _cli("record", "--camera", "synthetic", "--out", rec, "--frames", 200, "--frame-rate-hz", 20000,
             "--ring-frames", 2, "--no-burst", "--synthetic-size", 128, "--synthetic-frames", 4, "--no-progress")
    with h5py.File(rec) as f:
        import json

        summary = json.loads(f["summary"].attrs["summary_json"])
    assert r.returncode == 1 and summary["lost_ring_overrun"] > 0, (r.returncode, summary, r.stderr)  # overrun
    p = _cli("process", rec, "--out", tmp_path / "o.h5")
    assert p.returncode in (0, 3), p.stderr
    assert f"lost frames on the way ({summary['total_missing']} lost: {summary['lost_ring_overrun']} to ring " \
           "overruns" in p.stderr, p.stderr
    assert "ended early" not in p.stderr, p.stderr


def test_the_replay_tab_names_no_trigger_in_a_recording_made_without_one(tmp_path):
    """`record --frames` (no trigger) counts its frame table's trigger_index from the first frame: the
    Replay tab showed such frames as "trigger +5" and their times "from the trigger". Now it names none:
    no trigger index, times from the first frame; a triggered recording keeps both."""
    pytest.importorskip("PySide6")
    from app.gui.replay import Recording

    plain = tmp_path / "plain.h5"
    r = _cli("record", "--camera", "synthetic", "--out", plain, "--frames", 6, "--synthetic-size", 128,
             "--synthetic-frames", 4, "--no-progress")
    assert r.returncode == 0, r.stderr
    with h5py.File(plain) as f:
        assert list(f["frame_table"]["trigger_index"][:6]) == list(range(6))  # what the tab used to show
    rec = Recording(str(plain))
    try:
        assert rec.trigger_index(5) is None and rec.time_origin == "first frame"
    finally:
        rec.close()
    triggered = tmp_path / "triggered.h5"
    r = _cli("record", "--camera", "synthetic", "--out", triggered, "--pre", 3, "--post", 4, "--trigger", "software",
             "--synthetic-size", 128, "--synthetic-frames", 4, "--no-progress")
    assert r.returncode == 0, r.stderr
    rec = Recording(str(triggered))
    try:
        assert [rec.trigger_index(i) for i in range(rec.n_frames)] == list(range(-3, rec.n_frames - 3))
        assert rec.time_origin == "trigger"
    finally:
        rec.close()
