"""`tirdeflect movie` and `tirdeflect probe` on `tirdeflect simulate` output processed
by `tirdeflect process`: probes against the simulated truth, the movie reopened with PyAV."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from app.files import imageio

av = pytest.importorskip("av")

ROOT = Path(__file__).resolve().parents[2]
N_FRAMES = 6
POINTS = [(0.0, 0.0), (1.5, -2.0), (-2.37, 3.1)]  # mm; the last one between samples


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "app.cli", *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def processed(tmp_path_factory):
    """A deepening dimple (6 frames at 100 frames/s, 12 bit) processed twice: from the
    TIFF files (no time stamps) and from a Photron MRAW of the same frames (time stamps)."""
    tmp = tmp_path_factory.mktemp("outputs")
    sim = tmp / "sim"
    r = _cli("simulate", "--out", sim, "--surface", "dimple", "--size", "256", "--frames", N_FRAMES,
             "--bits", "12")
    assert r.returncode == 0, r.stderr
    frames = [str(sim / f"frame_{k:04d}.tif") for k in range(N_FRAMES)]
    out_tif = tmp / "out_tif.h5"
    r = _cli("process", sim / "reference.tif", *frames, "--geometry", sim / "geometry.toml",
             "--out", out_tif, "--no-progress")
    assert r.returncode == 0, r.stderr
    pyMRAW = pytest.importorskip("pyMRAW")
    _, cih = pyMRAW.save_mraw(np.stack([imageio.read_image(p) for p in frames]), str(tmp / "rec.cih"),
                              bit_depth=16, info_dict={"Record Rate(fps)": 100})
    out_mraw = tmp / "out_mraw.h5"
    r = _cli("process", sim / "reference.tif", cih, "--geometry", sim / "geometry.toml",
             "--out", out_mraw, "--no-progress")
    assert r.returncode == 0, r.stderr
    return sim, out_tif, out_mraw


def _truth_at(sim: Path, out_h5: Path, x_mm: float, y_mm: float):
    """True height series at a point (bilinear on the pixel grid), both the truth and
    the processed offsets removed over the geometry's reference region (the offset the
    method cannot measure), as `tirdeflect compare` does."""
    from processing import Geometry

    with h5py.File(sim / "heights.h5", "r") as f:
        truth = f["height"][()].astype(np.float64)
        times = f["time_s"][()]
    with h5py.File(out_h5, "r") as f:
        est = f["height"][()].astype(np.float64)
        x, y = f["x_mm"][()], f["y_mm"][()]
        geometry = Geometry.from_toml_text(str(f.attrs["geometry_toml"]))
    rows, cols = truth.shape[1:]
    ref = geometry.reference_mask(np.arange(rows), np.arange(cols), (rows, cols))
    c = np.interp(x_mm, x, np.arange(cols))
    r = np.interp(y_mm, y, np.arange(rows))
    r0, c0 = int(r), int(c)
    fr, fc = r - r0, c - c0
    w = np.array([[(1 - fr) * (1 - fc), (1 - fr) * fc], [fr * (1 - fc), fr * fc]])
    true_p = np.array([np.sum(t[r0:r0 + 2, c0:c0 + 2] * w) - t[ref].mean() for t in truth])
    est_offset = np.array([np.nanmean(e[ref]) for e in est])
    return true_p, est_offset, times


def _read_csv(path: Path):
    with open(path, newline="") as fh:
        lines = [ln for ln in fh if not ln.startswith("#")]
    rows = list(csv.reader(lines))
    header, body = rows[0], np.array(rows[1:], dtype=float)
    return header, body


@pytest.mark.parametrize("which", ["tif", "mraw"])
def test_probe_matches_simulated_truth(processed, tmp_path, which):
    sim, out_tif, out_mraw = processed
    out = out_tif if which == "tif" else out_mraw
    csv_path = tmp_path / "probes.csv"
    args = ["probe", out, "--out", csv_path]
    for x, y in POINTS:
        args += ["--at", f"{x},{y}"]
    if which == "tif":
        args += ["--fps", "100"]  # image files carry no time: count it from the frame index
    r = _cli(*args)
    assert r.returncode == 0, r.stderr
    header, body = _read_csv(csv_path)
    assert header[:2] == ["frame_index", "time_s"] and len(header) == 2 + len(POINTS)
    assert body.shape == (N_FRAMES, 2 + len(POINTS))
    with h5py.File(csv_path.with_suffix(".h5"), "r") as f:
        np.testing.assert_allclose(f["height_mm"][()], body[:, 2:], rtol=1e-8)  # CSV: 9 digits
        np.testing.assert_array_equal(f["x_mm"][()], [p[0] for p in POINTS])
        assert f["time_s"].attrs["source"] == ("--fps" if which == "tif" else "/time_s")
    for j, (x, y) in enumerate(POINTS):
        true_p, est_offset, times = _truth_at(sim, out, x, y)
        span = true_p.max() - true_p.min()
        assert span > 1e-4  # the dimple deepens by > 0.1 um here: a real series
        err = (body[:, 2 + j] - est_offset) - true_p
        assert np.max(np.abs(err)) <= 0.02 * span, (x, y, err / span)
        # times from the MRAW's header (100 frames/s) or from --fps, equal to the simulation's
        np.testing.assert_allclose(body[:, 1], times, atol=1e-9)


def test_probe_outside_the_field_is_one_line_error(processed, tmp_path):
    _, out_tif, _ = processed
    r = _cli("probe", out_tif, "--at", "500,0", "--out", tmp_path / "p.csv")
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "outside the measured field" in r.stderr
    assert not (tmp_path / "p.csv").exists()


def test_movie_reopens_with_pyav(processed, tmp_path):
    _, _, out_mraw = processed
    movie = tmp_path / "heights.mp4"
    r = _cli("movie", out_mraw, "--out", movie)
    assert r.returncode == 0, r.stderr
    with av.open(str(movie)) as c:
        s = c.streams.video[0]
        images = [f.to_ndarray(format="rgb24") for f in c.decode(s)]
        rate = float(s.average_rate)
    assert len(images) == N_FRAMES
    rows, cols = images[0].shape[:2]
    with h5py.File(out_mraw, "r") as f:
        aspect = np.diff(f["y_mm"][:2])[0] / np.diff(f["x_mm"][:2])[0]  # 1/cos(theta) for TIR
    map_rows = int(round(256 * 2 * aspect))
    # 256 px map magnified 2x to >= 480 px (rows at the true surface aspect), plus the
    # colour-bar panel and the text band (two lines: the stamp, the mark), rounded up to even sizes for yuv420p
    band = 52
    assert (cols, rows) == (256 * 2 + 110, band + map_rows + 10 + (band + map_rows + 10) % 2)
    assert rate == pytest.approx(100.0)  # real time from the MRAW's 100 frames/s
    # one colour range for the whole movie: the colour bar is the same in every frame,
    # while the map (the deepening dimple) changes
    bar = np.s_[band + 8:band + map_rows - 8, 256 * 2 + 14:256 * 2 + 34]
    centre = np.s_[band + map_rows // 2 - 40:band + map_rows // 2 + 40, 216:296]
    for k in range(1, N_FRAMES):
        assert np.abs(images[k][bar].astype(int) - images[0][bar]).mean() < 3
    assert np.abs(images[-1][centre].astype(int) - images[0][centre]).mean() > 20


def test_movie_with_fixed_range_and_slope(processed, tmp_path):
    _, out_tif, _ = processed
    movie = tmp_path / "slope.mkv"
    r = _cli("movie", out_tif, "--out", movie, "--quantity", "slope_x", "--range", "-0.5,0.5",
             "--fps", "10")
    assert r.returncode == 0, r.stderr
    assert "-0.5 .. 0.5 mrad" in r.stderr
    with av.open(str(movie)) as c:
        assert sum(1 for _ in c.decode(video=0)) == N_FRAMES
    r = _cli("movie", out_tif, "--out", movie, "--range", "1,0")
    assert r.returncode == 2 and "already exists" in r.stderr


def test_movie_names_peaks_far_beyond_its_colour_range(processed, tmp_path):
    """By-hand trial of 7 Dec 2026: a drop's peaks, a few samples among many quiet ones, lay beyond the colour
    range the percentiles gave and showed as its end colour, in silence. The movie names what they reach, in
    which frame, and the --range that shows them (so does the deepening dimple: its last frames' bottom lies
    beyond the 1 % percentile of all the frames); with a --range given, nothing is said."""
    import shutil

    _, out_tif, _ = processed
    r = _cli("movie", out_tif, "--out", tmp_path / "dimple.mp4")
    assert r.returncode == 0 and f"(frame {N_FRAMES - 1}), beyond the colour range" in r.stderr, r.stderr
    r = _cli("movie", out_tif, "--out", tmp_path / "whole.mp4", "--range", "-2.1,0.1")
    assert r.returncode == 0 and "note:" not in r.stderr, r.stderr
    dropped = tmp_path / "drop.h5"
    shutil.copy(out_tif, dropped)
    with h5py.File(dropped, "r+") as f:  # a drop's narrow peak in frame 3: 3 x 3 samples, 10x the dimple's depth
        h = f["height"]
        peak = 10 * float(np.nanmax(np.abs(h[()])))
        frame = h[3]
        frame[120:123, 120:123] = peak
        h[3] = frame
    r = _cli("movie", dropped, "--out", tmp_path / "drop.mp4")
    assert r.returncode == 0, r.stderr
    note = [ln for ln in r.stderr.splitlines() if ln.startswith("tirdeflect: note: the values reach")]
    assert note and f"{1e3 * peak:.4g} um (frame 3)" in note[0] and "--range " in note[0], r.stderr


def test_probe_and_movie_keep_the_times_of_a_cut_video(processed, tmp_path):
    """A 100 frames/s FFV1 video cut short: its last frames are UNREADABLE rows (no time,
    no heights); the frames read keep their stream times in the probe series (not NaN
    for all, said 'no time stamps'), and the movie runs at their 100 frames/s."""
    sim = processed[0]
    frames = [imageio.read_image(sim / f"frame_{k:04d}.tif") for k in range(N_FRAMES)]
    whole = tmp_path / "whole.avi"
    with av.open(str(whole), "w") as container:
        stream = container.add_stream("ffv1", rate=100)
        stream.width, stream.height, stream.pix_fmt = 256, 256, "gray16le"
        for image in frames:
            container.mux(stream.encode(av.VideoFrame.from_ndarray(image, format="gray16le")))
        container.mux(stream.encode())
    cut = tmp_path / "cut.avi"
    cut.write_bytes(whole.read_bytes()[:int(whole.stat().st_size * 0.7)])
    out = tmp_path / "out.h5"
    r = _cli("process", sim / "reference.tif", cut, "--geometry", sim / "geometry.toml", "--out", out,
             "--no-progress", "--workers", "1")
    assert r.returncode == 3, r.stderr  # some frames unreadable
    with h5py.File(out, "r") as f:
        read = f["frame_status"][()] == 0
    assert 2 <= read.sum() < N_FRAMES and read[:2].all()
    csv_path = tmp_path / "probes.csv"
    r = _cli("probe", out, "--at", "0,0", "--out", csv_path)
    assert r.returncode == 0, r.stderr
    assert "no time stamps" not in r.stderr and "time from /time_s" in r.stderr
    _, body = _read_csv(csv_path)
    np.testing.assert_allclose(body[read, 1], np.flatnonzero(read) / 100.0, atol=1e-9)
    assert np.isnan(body[~read, 1:]).all()
    movie = tmp_path / "cut.mp4"
    r = _cli("movie", out, "--out", movie)
    assert r.returncode == 0, r.stderr
    with av.open(str(movie)) as c:
        assert float(c.streams.video[0].average_rate) == pytest.approx(100.0)


def test_probe_names_where_time_goes_back_over_two_camera_files(processed, tmp_path):
    """Two MRAW files of one series, each counting time from its own first frame: the
    probe's time_s goes back at the second file's first frame, which the probe says, and since
    the by-hand trial of 7 Dec 2026 (files given out of order: only `probe` said it) the run too."""
    pyMRAW = pytest.importorskip("pyMRAW")
    sim = processed[0]
    frames = np.stack([imageio.read_image(sim / f"frame_{k:04d}.tif") for k in range(N_FRAMES)])
    parts = []
    for name, chunk in (("a", frames[:3]), ("b", frames[3:])):
        _, cih = pyMRAW.save_mraw(chunk, str(tmp_path / f"{name}.cih"), bit_depth=16,
                                  info_dict={"Record Rate(fps)": 100})
        parts.append(cih)
    out = tmp_path / "out.h5"
    r = _cli("process", sim / "reference.tif", *parts, "--geometry", sim / "geometry.toml", "--out", out,
             "--no-progress", "--workers", "1")
    assert r.returncode == 0, r.stderr
    said = [line for line in r.stderr.splitlines() if "goes back" in line]
    assert len(said) == 1 and "first at frame 3 (0.02 s, then 0 s: " in said[0], r.stderr
    assert f"{parts[1]} after {parts[0]}" in said[0], said[0]
    with h5py.File(out) as f:
        assert f.attrs["frames_time_back"] == 1
    r = _cli("probe", out, "--at", "0,0", "--out", tmp_path / "p.csv")
    assert r.returncode == 0, r.stderr
    _, body = _read_csv(tmp_path / "p.csv")
    np.testing.assert_allclose(body[:, 1], [0, 0.01, 0.02, 0, 0.01, 0.02], atol=1e-9)
    notes = [line for line in r.stderr.splitlines() if "does not increase" in line]
    assert len(notes) == 1 and "first at frame 3 (0.02 s, then 0 s)" in notes[0], r.stderr
