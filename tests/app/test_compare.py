"""`tirdeflect compare` pins both maps alike: the heights' null mode (exp(-T y/H) for TIR), which no
deflectometry measures, fitted on the reference region and taken out of each (app/batch/compare.py)."""

import re

import h5py
import numpy as np

from app.cli import main
from processing import Geometry

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
