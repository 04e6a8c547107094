"""Bad input to `tirdeflect process`: one clear line, exit status 2, no traceback.

Each test runs the CLI in-process (``app.cli.main([...])``) and checks the exit
status and that the message names the problem (and the offending value or
file) and what to do.
"""

from pathlib import Path

import h5py
import numpy as np
import pytest

from app.files import imageio
from app.cli import main
from tests.datapaths import TRAPPED

SIZE = 192


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    d = tmp_path_factory.mktemp("simbad")
    assert main(["simulate", "--out", str(d), "--surface", "bump", "--size", str(SIZE),
                 "--frames", "1"]) == 0
    return d


def run_cli(capsys, *argv):
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err
    return code, err


def assert_clean_error(code, err, *needles):
    assert code == 2, f"exit status {code}, stderr: {err}"
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if ln.startswith("tirdeflect: error:")]
    assert len(lines) == 1, err
    for needle in needles:
        assert needle.lower() in lines[0].lower(), f"{needle!r} not in {lines[0]!r}"
    return lines[0]


def process_args(sim, tmp_path, *frames, reference=None, geometry=None):
    return ["process", reference or sim / "reference.png", *(frames or [sim / "frame_0000.png"]),
            "--geometry", geometry or sim / "geometry.toml", "--out", tmp_path / "out.h5"]


def test_missing_frame_file(sim, tmp_path, capsys):
    missing = tmp_path / "frame_9999.png"
    code, err = run_cli(capsys, *process_args(sim, tmp_path, missing))
    assert_clean_error(code, err, "does not exist", str(missing))
    assert not (tmp_path / "out.h5").exists()  # nothing started


def test_missing_reference(sim, tmp_path, capsys):
    code, err = run_cli(capsys, *process_args(sim, tmp_path, reference=tmp_path / "nope.png"))
    assert_clean_error(code, err, "reference", "nope.png", "does not exist")


def test_folder_without_frames_gets_a_hint(sim, tmp_path, capsys):
    # a folder is read as its images in natural order; one without any says so
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.txt").write_text("no frames here\n")
    code, err = run_cli(capsys, *process_args(sim, tmp_path, empty))
    assert_clean_error(code, err, "empty", "holds no image")


def test_text_file_named_png(sim, tmp_path, capsys):
    fake = tmp_path / "x.png"
    fake.write_text("this is not an image\n")
    code, err = run_cli(capsys, *process_args(sim, tmp_path, fake))
    assert_clean_error(code, err, "x.png", "not a readable image")


def test_frame_and_reference_of_different_sizes(sim, tmp_path, capsys):
    small = imageio.read_image(sim / "frame_0000.png")[: SIZE - 32, :]
    imageio.write_image(tmp_path / "small.png", small)
    code, err = run_cli(capsys, *process_args(sim, tmp_path, tmp_path / "small.png"))
    assert_clean_error(code, err, "small.png", f"({SIZE - 32}, {SIZE})", f"({SIZE}, {SIZE})")


@pytest.mark.parametrize("kind", ["flat", "noise"])
def test_reference_without_carrier(sim, tmp_path, capsys, rng, kind):
    if kind == "flat":
        image = np.full((SIZE, SIZE), 128, np.uint8)
    else:
        image = rng.integers(0, 256, size=(SIZE, SIZE), dtype=np.uint8)
    imageio.write_image(tmp_path / f"{kind}.png", image)
    code, err = run_cli(capsys, *process_args(sim, tmp_path, reference=tmp_path / f"{kind}.png"))
    assert_clean_error(code, err, "carrier")
    assert not (tmp_path / "out.h5").exists()


def test_mismatched_real_pattern_is_refused(tmp_path, capsys):
    """ellipse_10.tif has another pattern scale/rotation than reference_df.tif."""
    geometry = tmp_path / "fsss.toml"
    from processing import Geometry

    g = Geometry.from_dict({
        "setup": "fsss", "pixel_mm": 0.207,
        "fsss_layers": [[57.0, 1.0003], [12.0, 1.48899], [43.0, 1.34]],
        "n_water": 1.34, "n_air": 1.0003, "fsss_camera_distance_mm": 800.0,
    })
    geometry.write_text(g.to_toml_text())
    code, err = run_cli(capsys, "process", TRAPPED / "reference_df.tif", TRAPPED / "ellipse_10.tif",
                        "--geometry", geometry, "--out", tmp_path / "out.h5", "--grid", "decimated")
    line = assert_clean_error(code, err, "ellipse_10.tif")
    assert "pattern" in line.lower() or "carrier" in line.lower()


def _edit_toml(sim, tmp_path, edit):
    text = (sim / "geometry.toml").read_text()
    new = edit(text)
    assert new != text, "the edit did not apply: geometry.toml layout changed?"
    path = tmp_path / "g.toml"
    path.write_text(new)
    return path


def _replace_key(text, key, value):
    import re

    return re.sub(rf"(?m)^(\s*{key}\s*=\s*).*$", lambda m: m.group(1) + value, text, count=1)


def test_theta_below_critical_angle(sim, tmp_path, capsys):
    g = _edit_toml(sim, tmp_path, lambda t: _replace_key(t, "theta_deg", "40.0"))
    code, err = run_cli(capsys, *process_args(sim, tmp_path, geometry=g))
    assert_clean_error(code, err, "theta", "40")


def test_a_pixel_size_that_the_board_contradicts_is_refused(sim, tmp_path, capsys):
    # simulate writes the board's period into geometry.toml; a user who types pixel_mm twice too large
    # (which would make every height 4x too large, exit 0) is told so, with the pixel_mm the board implies
    assert "pattern_period_mm = 2.0" in (sim / "geometry.toml").read_text()
    g = _edit_toml(sim, tmp_path, lambda t: _replace_key(t, "pixel_mm", "0.2"))
    code, err = run_cli(capsys, *process_args(sim, tmp_path, geometry=g))
    line = assert_clean_error(code, err, "pattern_period_mm = 2", "period of 4 mm", "pixel_mm = 0.1 (the rest kept)")
    assert "300 % off" in line
    assert not (tmp_path / "out.h5").exists()


def test_a_reference_taken_on_moving_water_is_refused_with_what_to_do(tmp_path, capsys):
    # the user took the reference while waves still ran (a frame of simulated waves, 2.3 rad): the
    # peaks are smeared; exit 2 and the advice to take it again on still water, nothing written (since the
    # isolation test of 7 Dec 2026 the local patches find the board and the refusal names the moving water)
    d = tmp_path / "waves"
    assert main(["simulate", "--out", str(d), "--surface", "waves", "--size", "256", "--frames", "2"]) == 0
    code, err = run_cli(capsys, "process", d / "frame_0001.png", d / "frame_0000.png", "--geometry",
                        d / "geometry.toml", "--out", tmp_path / "out.h5")
    assert_clean_error(code, err, "frame_0001.png", "the water surface was moving", "again on still water")
    assert not (tmp_path / "out.h5").exists()


def test_toml_missing_key(sim, tmp_path, capsys):
    import re

    g = _edit_toml(sim, tmp_path, lambda t: re.sub(r"(?m)^\s*depth_mm\s*=.*\n", "", t))
    code, err = run_cli(capsys, *process_args(sim, tmp_path, geometry=g))
    assert_clean_error(code, err, "depth_mm")


def test_toml_wrong_type(sim, tmp_path, capsys):
    g = _edit_toml(sim, tmp_path, lambda t: _replace_key(t, "theta_deg", '"steep"'))
    code, err = run_cli(capsys, *process_args(sim, tmp_path, geometry=g))
    assert_clean_error(code, err, "theta_deg", "steep")


def test_toml_syntax_error(sim, tmp_path, capsys):
    g = tmp_path / "g.toml"
    g.write_text("theta_deg = = 55\n")
    code, err = run_cli(capsys, *process_args(sim, tmp_path, geometry=g))
    assert_clean_error(code, err, "g.toml")


def test_black_frame_is_all_invalid(sim, tmp_path, capsys):
    imageio.write_image(tmp_path / "black.png", np.zeros((SIZE, SIZE), np.uint8))
    code, err = run_cli(capsys, *process_args(sim, tmp_path, tmp_path / "black.png"))
    assert_clean_error(code, err, "black.png")


def test_unreadable_frame_mid_batch_is_invalid_and_the_run_goes_on(sim, tmp_path, capsys):
    good = sim / "frame_0000.png"
    bad = tmp_path / "frame_broken.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    code = main([str(a) for a in process_args(sim, tmp_path, good, good, bad, good)])
    err = capsys.readouterr().err
    assert code == 3, err
    assert "wrote 4 frame(s)" in err and "1 invalid" in err and "frame_broken.png" in err
    with h5py.File(tmp_path / "out.h5", "r") as f:
        assert f.attrs["frames_done"] == 4 and f.attrs["frames_invalid"] == 1
        assert list(f["frame_status"][()]) == [0, 0, 5, 0]  # 5: UNREADABLE
        assert "not a readable image" in f["frame_status_text"].asstr()[2]
        h = f["height"][()]
        assert np.isfinite(h[[0, 1, 3]]).mean() > 0.9 and not np.isfinite(h[2]).any()
        np.testing.assert_array_equal(h[0], h[1])  # same input, deterministic


def test_debug_shows_the_traceback(sim, tmp_path, capsys):
    code = main(["--debug", *map(str, process_args(sim, tmp_path, tmp_path / "missing.png"))])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" in err and "tirdeflect: error:" in err


def test_last_before_first(sim, tmp_path, capsys):
    code, err = run_cli(capsys, *process_args(sim, tmp_path), "--first", "3", "--last", "1")
    assert_clean_error(code, err, "--first 3", "selects no frame")


def test_failure_on_the_first_frame_leaves_no_output(sim, tmp_path, capsys):
    imageio.write_image(tmp_path / "black.png", np.zeros((SIZE, SIZE), np.uint8))
    args = process_args(sim, tmp_path, tmp_path / "black.png")
    code, err = run_cli(capsys, *args)
    assert_clean_error(code, err, "nothing was written")
    assert not (tmp_path / "out.h5").exists()
    # so the corrected rerun is not refused as "already exists"
    code, err = run_cli(capsys, *process_args(sim, tmp_path))
    assert code == 0, err


_FULL_DISK_CHILD = r"""
import resource, signal, sys
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG like a full disk, instead of being killed
limit = int(sys.argv[1])
resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
from app.cli import main
sys.exit(main(sys.argv[2:]))
"""


def test_disk_full_mid_batch_keeps_a_valid_file(sim, tmp_path):
    """The file system refuses writes after a few frames: clear error, completed frames readable."""
    import subprocess
    import sys

    frames = [str(sim / "frame_0000.png")] * 12
    out = tmp_path / "out.h5"
    from app.batch.writer import RESERVE_BYTES

    # each frame adds about rows*cols*13 bytes (3 float32 maps + uint8 mask); room for ~4
    limit = 64 * 1024 + RESERVE_BYTES + int(4.5 * SIZE * SIZE * 13)
    root = Path(__file__).resolve().parents[2]
    proc = subprocess.run(
        [sys.executable, "-c", _FULL_DISK_CHILD, str(limit), "process", str(sim / "reference.png"),
         *frames, "--geometry", str(sim / "geometry.toml"), "--out", str(out), "--no-progress"],
        cwd=root, capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    assert "full" in proc.stderr and "before it are kept in" in proc.stderr, proc.stderr
    assert not out.exists()  # only a complete run is renamed to OUT
    partial = tmp_path / "out.partial.h5"
    assert str(partial) in proc.stderr
    with h5py.File(partial, "r") as f:
        n = int(f.attrs["frames_done"])
        assert 1 <= n < 12
        assert f["height"].shape[0] == n  # the half-written frame was dropped
        assert np.isfinite(f["height"][n - 1]).mean() > 0.9


def test_a_pattern_mismatch_before_any_frame_matched_says_why_it_stops_the_run(sim, tmp_path, capsys):
    """By-hand trial of 7 Dec 2026: after blank frames, a frame of another pattern stopped the run ("nothing
    was written") where after a measured frame the same frame is only stored invalid, and the message did
    not say why. It says now that no frame before it was measured, and what they were."""
    imageio.write_image(tmp_path / "grey.png", np.full((SIZE, SIZE), 128, np.uint8))
    imageio.write_image(tmp_path / "black.png", np.zeros((SIZE, SIZE), np.uint8))
    cols = np.arange(SIZE)
    stripes = np.broadcast_to(128 + 100 * np.sin(2 * np.pi * cols / 3.4), (SIZE, SIZE)).astype(np.uint8)
    imageio.write_image(tmp_path / "stripes.png", stripes)
    good = sim / "frame_0000.png"
    code, err = run_cli(capsys, *process_args(sim, tmp_path, tmp_path / "grey.png", tmp_path / "black.png",
                                              tmp_path / "stripes.png", good))
    assert_clean_error(code, err, "frame 2", "does not match the reference", "no frame before it was measured: 2 blank",
                       "once a frame has matched, a frame that does not is only stored invalid", "nothing was written")
    code, err = run_cli(capsys, *process_args(sim, tmp_path, good, tmp_path / "stripes.png"))
    assert code == 3 and "1 pattern mismatch" in err, err  # after a measured frame: stored invalid, the run goes on
