"""Ordinary inputs that were taken wrongly in silence (issue 18, minor findings), through the CLI.

Each case runs ``tirdeflect`` as a user does (a subprocess, or ``main`` where only the
message matters) on frames made by the project's ray tracer (``tirdeflect simulate``).
"""

import re
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import tifffile

from app.cli import main
from app.files import imageio

ROOT = Path(__file__).resolve().parents[2]
SIZE = 128


def _cli(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "app.cli", *map(str, args)], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout)


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    """Ray-traced 12-bit set: reference.tif, frame_0000.tif, frame_0001.tif, geometry.toml."""
    d = tmp_path_factory.mktemp("guards")
    assert main(["simulate", "--out", str(d), "--size", str(SIZE), "--frames", "2", "--bits", "12"]) == 0
    return d


def _frames(sim):
    return sorted(sim.glob("frame_*.tif"))


def test_a_recording_alone_is_a_complete_input(sim, tmp_path):
    """docs/cluster.md's `tirdeflect process rec.h5 --out heights.h5`: frames, reference and
    geometry from the recording ("no frames given" before)."""
    from app.capture.recorder import RecordingFile

    ref = imageio.read_image(sim / "reference.tif")
    frames = [imageio.read_image(p) for p in _frames(sim)]
    rec_path = tmp_path / "rec.h5"
    rec = RecordingFile(rec_path, shape=ref.shape, dtype=ref.dtype, n_frames=2, check_space=False,
                        camera_id="synthetic", geometry_toml=(sim / "geometry.toml").read_text(),
                        reference_image=ref)
    for i, frame in enumerate(frames):
        rec.write(frame, (i, 100 + i, 5_000_000 * i, 7_000_000 * i, 0, i))
    rec.close()
    out = tmp_path / "heights.h5"
    r = _cli("process", rec_path, "--out", out, "--no-progress")
    assert r.returncode == 0, r.stderr
    direct = tmp_path / "direct.h5"
    r = _cli("process", sim / "reference.tif", *_frames(sim), "--geometry", sim / "geometry.toml",
             "--out", direct, "--no-progress")
    assert r.returncode == 0, r.stderr
    with h5py.File(out) as f, h5py.File(direct) as g:
        assert f.attrs["frames_done"] == 2 and f.attrs["geometry_file"].endswith(":/geometry_toml")
        np.testing.assert_array_equal(f["reference"][()], ref)
        np.testing.assert_allclose(f["height"][()], g["height"][()], atol=1e-7, equal_nan=True)
    # a recording without a stored reference still needs to be told where the reference is
    bare = tmp_path / "bare.h5"
    rec = RecordingFile(bare, shape=ref.shape, dtype=ref.dtype, n_frames=1, check_space=False,
                        camera_id="synthetic", geometry_toml=(sim / "geometry.toml").read_text())
    rec.write(frames[0], (0, 100, 0, 0, 0, 0))
    rec.close()
    r = _cli("process", bare, "--out", tmp_path / "bare_out.h5")
    assert r.returncode == 2 and "no frames given" in r.stderr and "--reference-frames" in r.stderr


def test_the_reference_in_the_frames_folder_is_not_a_frame(sim, tmp_path):
    folder = tmp_path / "run"
    folder.mkdir()
    for p in [sim / "reference.tif", *_frames(sim)]:
        (folder / p.name).write_bytes(p.read_bytes())
    out = tmp_path / "out.h5"
    r = _cli("process", folder / "reference.tif", folder, "--geometry", sim / "geometry.toml", "--out", out,
             "--no-progress")
    assert r.returncode == 0, r.stderr
    assert "is among the inputs" in r.stderr and "not processed as a frame (2 frame file(s) left)" in r.stderr
    with h5py.File(out) as f:
        assert f.attrs["frames_done"] == 2
        assert [Path(s).name for s in f.attrs["input_files"]] == ["frame_0000.tif", "frame_0001.tif"]
    # named on purpose, it is processed (heights 0 where it matches itself)
    out2 = tmp_path / "out2.h5"
    r = _cli("process", folder / "reference.tif", folder / "reference.tif", *_frames(sim), "--geometry",
             sim / "geometry.toml", "--out", out2, "--no-progress")
    assert r.returncode == 0, r.stderr
    with h5py.File(out2) as f:
        assert f.attrs["frames_done"] == 3
        assert np.nanmax(np.abs(f["height"][0])) < 1e-3 * np.nanmax(np.abs(f["height"][1]))


@pytest.mark.parametrize("option, value, says", [
    ("--reference-frames", "0:1000", "--reference-frames 0:1000 reaches frame 1000, but the reference file"),
    ("--frames", "0:1000", "--frames 0:1000 reaches frame 1000, but the inputs hold 15 frame(s) (0 to 14)"),
])
def test_a_frame_range_beyond_the_file_is_refused_with_the_numbers(sim, tmp_path, option, value, says):
    """0:1000 on a 15-frame stack was clamped in silence (and stored as '0:1000:')."""
    frame = imageio.read_image(_frames(sim)[0])
    stack = tmp_path / "stack.tif"
    tifffile.imwrite(stack, np.stack([frame] * 15), photometric="minisblack")
    args = ["process", stack, "--reference-frames", value if option == "--reference-frames" else "0:1"]
    if option == "--frames":
        args += ["--frames", value]
    r = _cli(*args, "--geometry", sim / "geometry.toml", "--out", tmp_path / "o.h5")
    assert r.returncode == 2 and says in r.stderr and re.search(r"holds? 15 frame\(s\) \(0 to 14\)", r.stderr), r.stderr
    assert "e.g. 0:15" in r.stderr and not (tmp_path / "o.h5").exists()


def test_eight_bit_frames_against_a_twelve_bit_reference_are_named_once(sim, tmp_path):
    """8-bit frames (as from an H.264 video) against the 12-bit reference: the run said 'no contrast'
    frame after frame and nothing of the bit depths."""
    folder = tmp_path / "frames8"
    folder.mkdir()
    for p in _frames(sim):
        imageio.write_image(folder / (p.stem + ".png"), (imageio.read_image(p) >> 4).astype(np.uint8))
    r = _cli("process", sim / "reference.tif", folder, "--geometry", sim / "geometry.toml",
             "--out", tmp_path / "o.h5", "--no-progress")
    ref_top = int(imageio.read_image(sim / "reference.tif").max())
    said = re.findall(r"bit depths differ: the frames of .* are 8-bit \(levels up to 255\) while the reference "
                      rf"is 12-bit \(levels up to {ref_top}\)", r.stderr)
    assert said, r.stderr
    # refused once at the start (7 Dec 2026: named, then 'no contrast, 16.1x darker' frame after frame)
    assert len(said) == 1 and r.returncode == 2 and "frame 0" not in r.stderr, r.stderr
    # frames and reference of one depth: no word
    r = _cli("process", sim / "reference.tif", *_frames(sim), "--geometry", sim / "geometry.toml",
             "--out", tmp_path / "o12.h5", "--no-progress")
    assert r.returncode == 0 and "bit depths differ" not in r.stderr, r.stderr


def test_a_reference_stored_sixteen_times_higher_than_its_frames_is_named(sim, tmp_path):
    """The reference saved with its 12-bit levels in the top bits of 16-bit words (x16), the frames not:
    every frame read 'no contrast' (0.06 of the reference's), and the run said nothing of the levels
    before 7 Dec 2026 (only 8-bit frames against a 12-bit reference were named). Now the run says the
    frames are 16x darker than the reference, beyond what a dimmer exposure still reads (13.3x), and what
    to do; frames 10x darker, within that, are measured with no word. The other way round (frames x16)
    it said '0.0625x brighter': now 16x."""
    ref = imageio.read_image(sim / "reference.tif")
    tifffile.imwrite(tmp_path / "ref16.tif", (ref.astype(np.uint32) * 16).astype(np.uint16))
    r = _cli("process", tmp_path / "ref16.tif", *_frames(sim), "--geometry", sim / "geometry.toml",
             "--out", tmp_path / "o.h5", "--no-progress")
    assert r.returncode == 2, r.stderr
    assert re.search(r"the frames are 1[56](\.\d)?x darker, beyond the 13.3x a dimmer exposure still reads", r.stderr), r.stderr
    assert "top bits of 16-bit words" in r.stderr
    dim = tmp_path / "dim"
    dim.mkdir()
    for p in _frames(sim):
        tifffile.imwrite(dim / p.name, np.rint(imageio.read_image(p) * 0.1).astype(np.uint16))
    r = _cli("process", sim / "reference.tif", *sorted(dim.glob("*.tif")), "--geometry", sim / "geometry.toml",
             "--out", tmp_path / "dim.h5", "--no-progress")
    assert r.returncode == 0 and "darker" not in r.stderr, r.stderr
    high = tmp_path / "high"
    high.mkdir()
    for p in _frames(sim):
        tifffile.imwrite(high / p.name, (imageio.read_image(p).astype(np.uint32) * 16).astype(np.uint16))
    r = _cli("process", sim / "reference.tif", *sorted(high.glob("*.tif")), "--geometry", sim / "geometry.toml",
             "--out", tmp_path / "high.h5", "--no-progress")
    assert r.returncode == 0 and re.search(r"the frames are 1[56](\.\d)?x brighter than the reference", r.stderr), r.stderr


def test_workers_beyond_the_chunks_store_and_say_what_runs(sim, tmp_path):
    """--workers 1000 on 16 frames: two chunks of 8, so two processes run; it stored '16 processes'."""
    frame = imageio.read_image(_frames(sim)[0])
    stack = tmp_path / "stack.tif"
    tifffile.imwrite(stack, np.stack([frame] * 16), photometric="minisblack")
    out = tmp_path / "o.h5"
    r = _cli("process", sim / "reference.tif", stack, "--geometry", sim / "geometry.toml", "--out", out,
             "--workers", "1000", "--no-progress")
    assert r.returncode == 0, r.stderr
    assert "--workers 1000: 2 process(es) run, one per chunk of frames" in r.stderr
    with h5py.File(out) as f:
        assert str(f.attrs["parallel"]).startswith("2 processes x ")
        assert f.attrs["frames_done"] == 16


@pytest.mark.parametrize("args, says", [
    (("process", "r.tif", "f.tif", "--out", "o.h5", "--first", "-1"), "--first must be >= 0 (frames count from 0); got -1"),
    (("process", "r.tif", "f.tif", "--out", "o.h5", "--workers", "0"), "--workers must be >= 1 processes; got 0"),
    (("process", "r.tif", "f.tif", "--out", "o.h5", "--step", "0"), "--step must be >= 1 (every S-th frame); got 0"),
    (("process", "r.tif", "f.tif", "--out", "o.h5", "--last", "x"), "--last must be a whole number >= 0"),
    (("pattern", "--period-mm", "-2", "--size-mm", "200,200", "--out", "b.pdf"), "--period-mm must be > 0 mm; got -2"),
    (("movie", "o.h5", "--out", "m.mp4", "--fps", "0"), "--fps must be > 0 frames/s; got 0"),
])
def test_range_messages_name_the_option_and_the_range_alike(tmp_path, capsys, args, says):
    """'must be >= 1, got 0' beside 'must be >= 0, got -1': every range message now reads
    'OPTION must be RANGE; got VALUE', as record's (tests/faults/test_arguments.py)."""
    assert main(list(args)) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.endswith(f"error: {says}") or says in err, err
    assert "argument " not in err
