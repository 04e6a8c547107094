"""Damaged, unfinished and busy HDF5 files through the CLI, as a user meets them.

A recording of ray-traced frames is written by the app's own recorder
(:class:`app.capture.recorder.RecordingFile`), then really damaged on disk
(bytes overwritten or zeroed at the offsets HDF5 itself reports for each
part); outputs of `tirdeflect process` are really being written, or really
killed (SIGKILL) midway. Each case must end in a message that names the file,
what is wrong and what to do, and never in a traceback or a silent exit 0.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import threading
from pathlib import Path

import h5py
import numpy as np
import pytest

from app.files import imageio

ROOT = Path(__file__).resolve().parents[2]
UNREADABLE = 5  # app.batch.frame_status.FrameStatus.UNREADABLE
N_FRAMES = 6


def _cli(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "app.cli", *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    out = tmp_path_factory.mktemp("simdamage")
    r = _cli("simulate", "--out", out, "--surface", "waves", "--size", "128", "--frames", N_FRAMES,
             "--bits", "12", "--noise", "1.0", "--overwrite")
    assert r.returncode == 0, r.stderr
    return out


def _record(sim: Path, path: Path, *, close: bool = True):
    """A recording of the simulation's frames by the app's recorder (reference and
    geometry inside); returns the RecordingFile (still open when ``close`` is False)."""
    from app.capture.recorder import RecordingFile

    reference = imageio.read_image(sim / "reference.tif")
    rec = RecordingFile(path, shape=reference.shape, dtype=reference.dtype, n_frames=N_FRAMES,
                        check_space=False, camera_id="synthetic", bit_depth=12,
                        geometry_toml=(sim / "geometry.toml").read_text(), reference_image=reference)
    for i in range(N_FRAMES):
        frame = imageio.read_image(sim / f"frame_{i:04d}.tif")
        # (sequence, frame_id, device_timestamp_ns, host_timestamp_ns, flags, trigger_index)
        rec.write(frame, (10 + i, 500 + i, 2_000_000 * (i + 1), 3_000_000 * (i + 1), 0, i))
    rec.flush()
    if close:
        rec.close(summary={"frames_written": N_FRAMES})
    return rec


@pytest.fixture(scope="module")
def recording(sim, tmp_path_factory):
    path = tmp_path_factory.mktemp("rec") / "rec.h5"
    _record(sim, path)
    return path


def _damaged_copy(recording: Path, tmp_path: Path, offset: int, data: bytes) -> Path:
    copy = tmp_path / "damaged.h5"
    shutil.copy(recording, copy)
    with open(copy, "r+b") as fh:
        fh.seek(offset)
        fh.write(data)
    return copy


def _process(rec: Path, out: Path):
    return _cli("process", rec, rec, "--out", out, "--no-progress")


def _one_error_line(r, *needles):
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("tirdeflect: error:")]
    assert len(lines) == 1, r.stderr
    for needle in needles:
        assert needle.lower() in lines[0].lower(), (needle, lines[0])
    return lines[0]


def test_clean_recording_processes_with_its_checksums(recording, tmp_path):
    """The undamaged recording: every frame's checksum matches, exit 0, no note but the pin's (its
    waves fill the frame: they move the default border band the heights are pinned on) and the part of
    each frame its steep waves leave unmeasured (28-41 %: app.batch.frame_status.UNMEASURED_NOTE_PCT)."""
    with h5py.File(recording) as f:
        assert f.attrs["format_version"] == "1.2"
        assert np.all(f["frame_table"]["crc32"][:N_FRAMES] != 0)
    out = tmp_path / "out.h5"
    r = _process(recording, out)
    assert r.returncode == 0, r.stderr
    notes = [ln for ln in r.stderr.splitlines() if "note" in ln]
    assert all("moved on the default border band" in ln or "were not measured on part of their area" in ln
               for ln in notes), r.stderr
    assert "damaged" not in r.stderr
    with h5py.File(out) as f:
        assert list(f["frame_status"][()]) == [0] * N_FRAMES
        assert list(f["camera_frame_id"][()]) == [500 + i for i in range(N_FRAMES)]


def test_damaged_global_heap_names_the_file_and_the_geometry(recording, tmp_path):
    """The global heap that holds /geometry_toml (its 'GCOL' signature overwritten, as
    bytes at offset 2048 of the issue's file): was HDF5's bare 'bad global heap
    collection signature'."""
    gcol = recording.read_bytes().index(b"GCOL")
    bad = _damaged_copy(recording, tmp_path, gcol, b"\xab" * 8)
    line = _one_error_line(_process(bad, tmp_path / "out.h5"), str(bad), "/geometry_toml", "damaged",
                           "--geometry")
    assert "no geometry given" not in line
    assert not (tmp_path / "out.h5").exists()


def test_damaged_geometry_text_is_said_damaged(sim, recording, tmp_path):
    """The TOML text itself overwritten (was a UnicodeDecodeError traceback, or, zeroed,
    'no geometry given')."""
    at = recording.read_bytes().index(b"theta_deg")
    bad = _damaged_copy(recording, tmp_path, at, b"\xab" * 12)
    _one_error_line(_process(bad, tmp_path / "out.h5"), str(bad), "/geometry_toml", "damaged")
    # with --geometry the frames are processed: the damage is only in the geometry
    r = _cli("process", bad, bad, "--geometry", sim / "geometry.toml", "--out", tmp_path / "ok.h5",
             "--no-progress")
    assert r.returncode == 0, r.stderr


def test_zeroed_geometry_heap_object_is_refused_not_a_hang(sim, recording, tmp_path):
    """The heap object that holds the TOML text zeroed, header included: HDF5 1.14
    loops for ever loading such a heap (SIGTERM cannot end it); the heap is now
    checked before h5py reads it. The 120 s limit only detects a hang (needed: ~2 s)."""
    text = (sim / "geometry.toml").read_bytes()
    at = recording.read_bytes().index(text[:40]) - 16  # the object's 16-byte header
    bad = _damaged_copy(recording, tmp_path, at, bytes(64))
    r = _cli("process", bad, bad, "--out", tmp_path / "out.h5", "--no-progress", timeout=120)
    _one_error_line(r, str(bad), "/geometry_toml", "damaged", "global heap")
    r = _cli("process", bad, bad, "--geometry", sim / "geometry.toml", "--out", tmp_path / "ok.h5",
             "--no-progress", timeout=120)
    assert r.returncode == 0, r.stderr


def test_zeroed_frame_table_is_detected(recording, tmp_path):
    """A zeroed /frame_table chunk: was exit 0 with every time_s and camera_frame_id 0.
    Now the rows are found damaged (sequence numbers not increasing), their times and
    ids are unknown (NaN, -1) and a note says so."""
    with h5py.File(recording) as f:
        chunk = f["frame_table"].id.get_chunk_info(0)
    bad = _damaged_copy(recording, tmp_path, chunk.byte_offset, bytes(chunk.size))
    out = tmp_path / "out.h5"
    r = _process(bad, out)
    assert "Traceback" not in r.stderr
    assert r.returncode == 0, r.stderr
    assert re.search(r"note: damaged\.h5: 6 row\(s\) of /frame_table are damaged", r.stderr), r.stderr
    with h5py.File(out) as f:
        assert np.all(np.isnan(f["time_s"][()]))
        assert list(f["camera_frame_id"][()]) == [-1] * N_FRAMES
        assert np.isfinite(f["height"][()]).mean() > 0.5  # the pixels themselves are fine


def test_zeroed_stretch_of_the_reference_is_an_error_naming_it(recording, tmp_path):
    """A tenth of /reference zeroed: heights came out 6-16 % off with no warning."""
    with h5py.File(recording) as f:
        offset, nbytes = f["reference"].id.get_offset(), f["reference"].nbytes
    bad = _damaged_copy(recording, tmp_path, offset + nbytes // 3, bytes(nbytes // 10))
    _one_error_line(_process(bad, tmp_path / "out.h5"), str(bad), "/reference", "checksum", "corrupt")


def test_zeroed_geometry_text_is_not_no_geometry(sim, recording, tmp_path):
    """The TOML text's first bytes zeroed: h5py reads an empty string, which said
    'no geometry given'."""
    text = (sim / "geometry.toml").read_bytes()
    at = recording.read_bytes().index(text[:40])
    bad = _damaged_copy(recording, tmp_path, at, bytes(32))
    line = _one_error_line(_process(bad, tmp_path / "out.h5"), str(bad), "/geometry_toml", "damaged")
    assert "no geometry given" not in line


def test_partly_zeroed_frame_is_unreadable_with_its_reason(recording, tmp_path):
    """An eighth of frame 3 zeroed: was status OK with 5-9 % error. Now frame 3 is
    UNREADABLE ('does not match the checksum'), the others measured, exit 3."""
    with h5py.File(recording) as f:
        chunk = f["frames"].id.get_chunk_info(3)
    bad = _damaged_copy(recording, tmp_path, chunk.byte_offset + chunk.size // 2, bytes(chunk.size // 8))
    out = tmp_path / "out.h5"
    r = _process(bad, out)
    assert r.returncode == 3, r.stderr
    assert "Traceback" not in r.stderr
    with h5py.File(out) as f:
        status = list(f["frame_status"][()])
        text = f["frame_status_text"][3]
    assert status == [0, 0, 0, UNREADABLE, 0, 0]
    text = text.decode() if isinstance(text, bytes) else str(text)
    assert "checksum" in text and "frame 3" in text and str(bad) in text


def _copy_while_recording(sim, tmp_path):
    """A copy of a recording taken while the recorder still writes it (complete = 0, no /summary)."""
    path = tmp_path / "live.h5"
    rec = _record(sim, path, close=False)
    try:
        copy = tmp_path / "copy.h5"
        shutil.copy(path, copy)
    finally:
        rec.close(summary={"frames_written": N_FRAMES})
    return copy


def test_copy_of_a_recording_that_never_ended_gets_a_note(sim, tmp_path):
    """A copy taken while the recorder was still writing (complete = 0, no /summary):
    processed, with a note that frames may be missing (was exit 0 and no word)."""
    copy = _copy_while_recording(sim, tmp_path)
    with h5py.File(copy) as f:
        assert int(f.attrs["complete"]) == 0 and "summary" not in f
    r = _process(copy, tmp_path / "out.h5")
    assert r.returncode == 0, r.stderr
    assert re.search(r"note: copy\.h5 is a recording that did not end normally .*may be missing", r.stderr), \
        r.stderr
    r = _process(tmp_path / "live.h5", tmp_path / "out2.h5")  # the original, closed: no such note
    assert r.returncode == 0 and "did not end normally" not in r.stderr, r.stderr


def test_movie_and_probe_on_a_running_then_killed_process_output(sim, recording, tmp_path):
    """`movie` while `process` still writes its output: 'being written by another
    process' (was 'not a readable HDF5 file ([Errno 11] ...)'); after the run is
    SIGKILLed, `movie` and `probe` on its partial file say it is partial, with
    frames_done of frames_expected (was exit 0 and no word)."""
    stack = np.stack([imageio.read_image(sim / f"frame_{i:04d}.tif") for i in range(N_FRAMES)] * 40)
    import tifffile

    tifffile.imwrite(tmp_path / "long.tif", stack, photometric="minisblack")
    out = tmp_path / "out.h5"
    partial = tmp_path / "out.partial.h5"
    proc = subprocess.Popen(
        [sys.executable, "-m", "app.cli", "process", str(sim / "reference.tif"), str(tmp_path / "long.tif"),
         "--geometry", str(sim / "geometry.toml"), "--out", str(out), "--no-progress", "--debug"],
        cwd=ROOT, stderr=subprocess.PIPE, text=True)
    watchdog = threading.Timer(300.0, proc.kill)  # a hung child must not hang the suite
    watchdog.start()
    written, busy = 0, None
    try:
        for line in proc.stderr:
            if re.search(r"frame \d+ .* written", line):
                written += 1
                if written == 2 and busy is None:
                    busy = _cli("movie", partial, "--out", tmp_path / "busy.mp4")
                if written >= 3 and busy is not None:
                    os.kill(proc.pid, signal.SIGKILL)
                    break
        proc.wait(timeout=60)
    finally:
        watchdog.cancel()
        if proc.poll() is None:
            proc.kill()
        proc.stderr.close()
    assert busy is not None and written >= 3
    if proc.returncode != -signal.SIGKILL:
        pytest.skip("the run ended before it could be killed (machine too fast for 240 frames)")
    _one_error_line(busy, str(partial), "being written by another process", "wait")
    assert not out.exists() and partial.exists()
    with h5py.File(partial) as f:
        done, expected = int(f.attrs["frames_done"]), int(f.attrs["frames_expected"])
        x_mm, y_mm = float(np.mean(f["x_mm"][()])), float(np.mean(f["y_mm"][()]))
    # (the kill lands after the third frame's line is read; a fast machine has written them all by then,
    # not yet finished the file: partial all the same; 'done < expected' failed two runs in three on
    # 6 Dec 2026, at 4425550 as well)
    assert 0 < done <= expected == 240
    needle = f"partial output (the run was killed before it ended): it holds {done} of the {expected}"
    r = _cli("movie", partial, "--out", tmp_path / "m.mp4")
    assert r.returncode == 0 and needle in r.stderr, r.stderr
    assert f"wrote {done} frame(s)" in r.stderr
    r = _cli("probe", partial, "--at", f"{x_mm},{y_mm}", "--out", tmp_path / "p.csv")
    assert r.returncode == 0 and needle in r.stderr, r.stderr
    assert f"--first {done}" in r.stderr  # where to resume


def test_recording_of_format_1_1_without_checksums_still_reads(sim, recording, tmp_path):
    """A recording written before checksums (format 1.1: no frame_table.crc32, no
    crc32 on /reference) processes as before, to the same heights as the 1.2 one."""
    from app.capture.recorder import FRAME_TABLE_DTYPE

    old_dtype = np.dtype([(name, FRAME_TABLE_DTYPE[name]) for name in FRAME_TABLE_DTYPE.names
                          if name != "crc32"])
    old = tmp_path / "old.h5"
    with h5py.File(recording) as src, h5py.File(old, "w") as dst:
        for key, value in src.attrs.items():
            dst.attrs[key] = value
        dst.attrs["format_version"] = "1.1"
        frames = dst.create_dataset("frames", data=src["frames"][()], chunks=(1,) + src["frames"].shape[1:])
        for key, value in src["frames"].attrs.items():
            frames.attrs[key] = value
        table = src["frame_table"][()]
        dst.create_dataset("frame_table", data=np.array([tuple(row[n] for n in old_dtype.names)
                                                          for row in table], dtype=old_dtype))
        dst.create_dataset("reference", data=src["reference"][()])
        dst.create_dataset("geometry_toml", data=src["geometry_toml"][()], dtype=h5py.string_dtype())
    outputs = {}
    for name, path in (("1.2", recording), ("1.1", old)):
        r = _process(path, tmp_path / f"{name}.h5")
        assert r.returncode == 0, r.stderr
        assert "corrupt" not in r.stderr and "damaged" not in r.stderr
        with h5py.File(tmp_path / f"{name}.h5") as f:
            outputs[name] = (f["height"][()], f["time_s"][()])
    np.testing.assert_array_equal(outputs["1.1"][0], outputs["1.2"][0])
    np.testing.assert_allclose(outputs["1.1"][1], 0.002 * np.arange(N_FRAMES), atol=1e-12)


def test_rebuilt_drop_summary_leaves_damaged_rows_out(sim, tmp_path):
    """A recording that never ended (no /summary) with rows 2..3 of its frame table
    zeroed on disk: the drop summary rebuilt from the table counted the zeros as
    hundreds of frames lost upstream; now those rows are left out and counted."""
    from app.capture.recorder import FRAME_TABLE_DTYPE, read_summary

    copy = _copy_while_recording(sim, tmp_path)
    with h5py.File(copy) as f:
        chunk = f["frame_table"].id.get_chunk_info(0)
    row = FRAME_TABLE_DTYPE.itemsize
    with open(copy, "r+b") as fh:
        fh.seek(chunk.byte_offset + 2 * row)
        fh.write(bytes(2 * row))
    s = read_summary(copy)
    assert s["frames_written"] == N_FRAMES
    assert s["frame_table_damaged_rows"] == 2 and "2 of its rows are damaged" in s["error"]
    assert s["lost_upstream_id_gaps"] == 0 and s["lost_ring_overrun"] == 0


def test_corrupt_frame_chosen_as_reference_is_refused(recording, tmp_path):
    """`--reference-index 3` on the recording whose frame 3 is partly zeroed: the
    reference is checked against its checksum too (an error naming the frame), not
    used to measure every other frame against."""
    with h5py.File(recording) as f:
        chunk = f["frames"].id.get_chunk_info(3)
    bad = _damaged_copy(recording, tmp_path, chunk.byte_offset + chunk.size // 2, bytes(chunk.size // 8))
    r = _cli("process", bad, bad, "--reference-index", 3, "--out", tmp_path / "out.h5", "--no-progress")
    _one_error_line(r, str(bad), "frame 3", "checksum")
