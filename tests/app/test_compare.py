"""`tirdeflect compare` pins both maps alike: the heights' null mode (exp(-T y/H) for TIR), which no
deflectometry measures, fitted on the reference region and taken out of each (app/batch/compare.py)."""

import re
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import tifffile

from app.cli import main
from processing import Geometry

ROOT = Path(__file__).resolve().parents[2]

GEOMETRY = dict(setup="tir", theta_deg=55.0, depth_mm=300.0, pixel_mm=0.1, rows_toward_camera=True)


def _files(tmp_path, est, truth, geometry):
    out, heights = tmp_path / "out.h5", tmp_path / "heights.h5"
    with h5py.File(out, "w") as f:
        f["height"] = est.astype(np.float32)
        f["frame_index"] = np.arange(est.shape[0])
        f.attrs["geometry_toml"] = geometry.to_toml_text()
        f.attrs["frames_done"] = est.shape[0]
        f.attrs["grid"] = "full"
    with h5py.File(heights, "w") as f:
        f["height"] = truth
    return out, heights


def test_compare_takes_the_null_mode_out_of_both_maps_and_says_when_the_region_moves(tmp_path, capsys):
    """Waves 2 um high fill a 256^2 field, the reference region (the default border band) included; the
    processed map is the truth plus a multiple of exp(-T y/H) (what a pin on moving water gives: the
    displacement is the same with or without it) and 0.2 % of noise. Compare reports the noise, not the
    null mode (a constant alone taken out left 3-4 % here), and names the region's motion."""
    geometry = Geometry.from_dict(GEOMETRY)
    n = 256
    rows = np.arange(n, dtype=np.float64)
    x_mm, y_mm = geometry.surface_point(np.full(n, n / 2.0), rows, (n, n))[0], \
        geometry.surface_point(rows, np.full(n, n / 2.0), (n, n))[1]
    _, y_canonical = geometry.to_canonical_xy(np.asarray(x_mm), np.asarray(y_mm))
    null = np.exp(-geometry.T * np.asarray(y_canonical)[:, None] / geometry.depth_mm) * np.ones((1, n))
    r, c = np.mgrid[:n, :n]
    rng = np.random.default_rng(3)
    truth = np.stack([0.002 * np.sin(2 * np.pi * (r * 0.011 + c * 0.007) + ph) for ph in (0.0, 1.3)])
    noise = 0.002 * 0.002 * rng.standard_normal(truth.shape)
    est = truth + 0.004 * null[None] * np.array([1.0, -1.5])[:, None, None] + noise
    out, heights = _files(tmp_path, est, truth, geometry)
    assert main(["compare", str(out), str(heights)]) == 0
    printed = capsys.readouterr().out
    figures = [float(x) for x in re.findall(r"^\s*\d+\s+([\d.]+) %", printed, re.M)]
    assert len(figures) == 2 and max(figures) < 0.5, printed  # the noise's 0.2 % of a 1.4 um rms field
    assert "not at rest on the reference region in 2 of 2 frame(s)" in printed
    # the same maps with the mean alone taken out over that region: the null mode stays in the error
    ref = geometry.reference_mask(rows, rows, (n, n))
    m = n // 8
    for k in range(2):
        e = (est[k] - est[k][ref].mean())[m:-m, m:-m]
        t = (truth[k] - truth[k][ref].mean())[m:-m, m:-m]
        assert np.sqrt(np.mean((e - t) ** 2)) / np.sqrt(np.mean(t ** 2)) > 0.02


def test_compare_of_a_surface_at_rest_on_the_region_prints_no_note(tmp_path, capsys):
    """A bump in the middle, still water on the border band: no note, and the figure is the noise's
    (1 nm on a 0.74 um rms interior: 0.14 %)."""
    geometry = Geometry.from_dict(GEOMETRY)
    n = 256
    r, c = np.mgrid[:n, :n]
    truth = (0.004 * np.exp(-((r - n / 2) ** 2 + (c - n / 2) ** 2) / (2 * 20.0 ** 2)))[None]
    est = truth + 1e-6 * np.random.default_rng(4).standard_normal(truth.shape)  # 1 nm: 0.14 % of its rms
    out, heights = _files(tmp_path, est, truth, geometry)
    assert main(["compare", str(out), str(heights)]) == 0
    printed = capsys.readouterr().out
    assert "not at rest" not in printed
    figures = [float(x) for x in re.findall(r"^\s*\d+\s+([\d.]+) %", printed, re.M)]
    assert len(figures) == 1 and figures[0] < 0.5, printed


# --------------------------------------------------------------------------- what a user gives compare
# (findings F4, F5 of the by-hand trial: compare on a data set of `tirdeflect simulate`, processed by
# `tirdeflect process`, as a user does; the compare commands run as the `tirdeflect` command does, in
# a subprocess, so that what it prints on stderr (NumPy's warnings, Python's errors) is what is checked)

SIM_SIZE = 128
#: what the old compare printed: HDF5's text, NumPy's warnings of an empty frame, an infinite worst error
RAW_TEXT = ("Unable to synchronously", "RuntimeWarning", "inf%", "nan %", "Traceback", "Errno")


def _cli(*args, stdout=None):
    """``tirdeflect ARGS`` as a user runs it: (exit status, stdout + stderr)."""
    r = subprocess.run([sys.executable, "-m", "app.cli", *map(str, args)], cwd=ROOT, text=True,
                       stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=300)
    return r.returncode, r.stdout


def _clean(text):
    """None of the raw texts the old compare printed."""
    for raw in RAW_TEXT:
        assert raw not in text, text


@pytest.fixture(scope="module")
def sim_set(tmp_path_factory):
    """`tirdeflect simulate` (bump, 3 frames, 12-bit TIFF) and its frames processed into out.h5."""
    d = tmp_path_factory.mktemp("compare") / "sim"
    assert main(["simulate", "--out", str(d), "--size", str(SIM_SIZE), "--frames", "3", "--bits", "12",
                 "--noise", "2"]) == 0
    out = d.parent / "out.h5"
    assert main(["process", str(d / "reference.tif"), *sorted(map(str, d.glob("frame_*.tif"))),
                 "--geometry", str(d / "geometry.toml"), "--out", str(out), "--no-progress"]) == 0
    return d, out


@pytest.fixture(scope="module")
def grey_out(sim_set):
    """The set processed with frame 0 replaced by a uniform grey image (level 2048: no light, lost
    packets): the output marks that frame invalid (status 1, blank) and measures the other two."""
    d, _ = sim_set
    grey = d.parent / "uniform_grey.tif"
    tifffile.imwrite(grey, np.full((SIM_SIZE, SIM_SIZE), 2048, np.uint16))
    out = d.parent / "grey_out.h5"
    code = main(["process", str(d / "reference.tif"), str(grey), str(d / "frame_0001.tif"),
                 str(d / "frame_0002.tif"), "--geometry", str(d / "geometry.toml"), "--out", str(out),
                 "--no-progress"])
    assert code == 3  # written, one frame invalid
    return out


def test_compare_refuses_a_truth_that_is_no_hdf5_file_and_says_what_to_give(sim_set):
    """F4: `compare OUT.h5 DIR/frame_0000.tif` printed HDF5's "Unable to synchronously open file (file
    signature not found)". It names the file and asks for the folder simulate wrote or its heights.h5."""
    d, out = sim_set
    code, text = _cli("compare", out, d / "frame_0000.tif")
    assert code == 2, text
    assert f"the truth {str(d / 'frame_0000.tif')!r} is not an HDF5 file" in text
    assert "give the folder that `tirdeflect simulate --out DIR` wrote (DIR), or its DIR/heights.h5" in text
    _clean(text)


@pytest.mark.parametrize("case", ["out is an image", "swapped", "truth is an output", "folder without truth"])
def test_compare_refuses_files_that_are_not_output_and_truth_naming_them(sim_set, case):
    """The other arguments compare cannot use, each named with what to give: a TIFF as OUT.h5 (HDF5's
    text before), the truth given first (a KeyError traceback before), a process output as the truth
    (compared with itself: 0.00 % before), a folder without heights.h5."""
    d, out = sim_set
    args, needles = {
        "out is an image": ((d / "frame_0000.tif", d), ["is not an HDF5 file", "give the OUT.h5"]),
        "swapped": ((d / "heights.h5", out), ["is the truth written by tirdeflect simulate", "swapped"]),
        "truth is an output": ((out, out), ["is an output of tirdeflect process, not the true heights"]),
        "folder without truth": ((out, d.parent), ["is a folder without heights.h5", "DIR/heights.h5"]),
    }[case]
    code, text = _cli("compare", *args)
    assert code == 2, text
    for needle in needles:
        assert needle in text, text
    _clean(text)


def test_compare_skips_the_frames_the_output_marks_invalid_and_names_them(sim_set, grey_out):
    """F5: an output whose frame 0 is invalid (uniform grey) printed three NumPy RuntimeWarnings, a "nan %"
    row and "worst relative RMS error inf% exceeds --max-error", exit 1. That frame is skipped with its
    status and reason, the worst error is the compared frames' (0.1-0.2 %), within --max-error: exit 0."""
    d, _ = sim_set
    code, text = _cli("compare", grey_out, d, "--max-error", "0.02")
    assert code == 0, text
    rows = [int(m) for m in re.findall(r"^\s*(\d+)\s+[\d.]+ %", text, re.M)]
    assert rows == [1, 2], text
    assert "1 frame(s) skipped, not in the worst error: frame 0 ('uniform_grey.tif'): the output marks it " \
           "invalid (blank: every pixel of the frame is 2048" in text
    worst = re.search(r"worst relative RMS error ([\d.]+)% \(frame \d\) over the 2 compared frame\(s\); 1 skipped",
                      text)
    assert worst and float(worst.group(1)) < 2.0, text
    _clean(text)


def test_compare_with_no_frame_to_compare_says_so_and_exits_2(sim_set, grey_out, tmp_path):
    """An output that holds only invalid frames (what a run killed after the grey frame leaves: its
    partial file valid up to frames_done = 1) printed a "nan %" row and exit 0 without --max-error. Now
    it says that no frame can be compared and why, exit 2 (compare --help)."""
    partial = tmp_path / "grey_out.partial.h5"
    shutil.copy(grey_out, partial)
    with h5py.File(partial, "r+") as f:
        f.attrs["frames_done"] = 1
        f.attrs["status"] = "running"
    code, text = _cli("compare", partial, sim_set[0])
    assert code == 2, text
    assert f"no frame of {str(partial)!r} can be compared with the truth: frame 0 ('uniform_grey.tif'): " \
           "the output marks it invalid (blank" in text
    assert "compare an output with measured frames" in text
    _clean(text)
    code, help_text = _cli("compare", "--help")
    assert code == 0 and "2 refused" in " ".join(help_text.split()) and "no frame that can be compared" \
        in " ".join(help_text.split())


def test_compare_names_the_truth_frames_the_output_does_not_hold(sim_set, tmp_path):
    """An output of frame_0002.tif alone was compared with truth frame 0 (its /frame_index) and nothing
    said of frames 0 and 1; a run that stopped early likewise. Now frame_0002 is compared with truth
    frame 2 (the file names of simulate's heights.h5) and the frames missing from the output are named."""
    d, out = sim_set
    one = tmp_path / "one.h5"
    assert main(["process", str(d / "reference.tif"), str(d / "frame_0002.tif"), "--geometry",
                 str(d / "geometry.toml"), "--out", str(one), "--no-progress"]) == 0
    code, text = _cli("compare", one, d)
    assert code == 0, text
    assert [int(m) for m in re.findall(r"^\s*(\d+)\s+[\d.]+ %", text, re.M)] == [2], text
    assert "the output holds 1 of the truth's 3 frame(s); missing from the output: frame(s) 0, 1" in text
    stopped = tmp_path / "stopped.h5"
    shutil.copy(out, stopped)
    with h5py.File(stopped, "r+") as f:  # a run killed after two frames: valid up to frames_done
        f.attrs["frames_done"] = 2
        f.attrs["status"] = "running"
    code, text = _cli("compare", stopped, d)
    assert code == 0, text
    assert "missing from the output: frame(s) 2 (the run wrote 2 of the 3 frame(s) it selected (running))" in text
    _clean(text)


def test_compare_refuses_an_output_with_more_frames_than_the_truth(sim_set, tmp_path):
    """Output and truth of two data sets (3 frames processed, a truth of 1 frame, the same size): said
    to be of two data sets, naming both counts."""
    d, out = sim_set
    other = tmp_path / "other"
    assert main(["simulate", "--out", str(other), "--size", str(SIM_SIZE), "--frames", "1", "--bits", "12"]) == 0
    code, text = _cli("compare", out, other)
    assert code == 2, text
    assert "holds 3 frame(s), frame 1 being input frame 1, but the truth holds only 1 frame(s) (0 to 0): they " \
           "are not of one data set" in text
    _clean(text)


def test_compare_into_a_closed_pipe_ends_quietly(sim_set):
    """`tirdeflect compare ... | head -1` printed "error: [Errno 32] Broken pipe" (exit 2): a reader that
    went away ends the command quietly, exit 141 as for SIGPIPE (app/cli/main.py)."""
    d, out = sim_set
    proc = subprocess.Popen([sys.executable, "-m", "app.cli", "compare", str(out), str(d)], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    proc.stdout.close()  # the reader is gone before anything is written
    err = proc.stderr.read()
    proc.stderr.close()
    assert proc.wait(timeout=300) == 141, err
    assert err == "", err


def test_compare_says_that_a_turn_the_run_flagged_is_part_of_the_error(tmp_path, capsys):
    """A frame whose pattern turned 0.2 deg since the reference (the camera knocked; its image turned about the
    centre): `process` flags it and leaves the turn in the heights (a saddle); compare put its 40-50 % down to the
    processing, saying nothing of the turn (7 Dec 2026). Now compare says the turn is part of the error and what
    takes it out; the straight frame is not named."""
    import cv2

    from app.files import imageio

    sim = tmp_path / "sim"
    assert main(["simulate", "--out", str(sim), "--surface", "bump", "--size", "256", "--frames", "2",
                 "--bits", "12"]) == 0
    frame = imageio.read_image(sim / "frame_0001.tif").astype(np.float32)
    turn = cv2.getRotationMatrix2D(((frame.shape[1] - 1) / 2, (frame.shape[0] - 1) / 2), 0.2, 1.0)
    turned = cv2.warpAffine(frame, turn, frame.shape[::-1], flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    tifffile.imwrite(sim / "frame_0001.tif", np.clip(np.rint(turned), 0, 4095).astype(np.uint16))
    out = tmp_path / "out.h5"
    assert main(["process", str(sim / "reference.tif"), str(sim / "frame_0000.tif"), str(sim / "frame_0001.tif"),
                 "--geometry", str(sim / "geometry.toml"), "--out", str(out)]) == 0
    with h5py.File(out) as f:
        assert list(f["turn_flagged"][()]) == [0, 1]
    capsys.readouterr()
    assert main(["compare", str(out), str(sim)]) == 0
    text = capsys.readouterr().out
    said = re.search(r"note: in 1 of 2 frame\(s\) the pattern turned since the reference \(/turn_mrad; up to "
                     r"([0-9.]+) mrad, frame 1\), a saddle in the heights that is part of the error above", text)
    assert said is not None and float(said.group(1)) == pytest.approx(np.deg2rad(0.2) * 1e3, rel=0.15), text
    assert "--turn-removal camera" in text
