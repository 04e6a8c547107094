"""`tirdeflect process` then `tirdeflect probe` with a TIR camera at a finite distance (400 mm): the surface
is seen keystoned, OUT.h5 says where each sample lies (/surface_x_mm, /surface_y_mm) and the probe reads
the point the user names, where the central row's and column's /x_mm, /y_mm put an off-centre bump 0.5 mm
off. Ray-traced with the project's forward model, 192^2 px of 0.2 mm."""

from __future__ import annotations

import csv

import h5py
import numpy as np
import pytest
import tifffile

from app.cli import main
from processing.probe import probe_cell, sample_cell

SIZE = 192
AMPLITUDE_MM, SIGMA_MM = 0.003, 2.0


def _geometry(distance_mm):
    from processing import Geometry

    return Geometry(theta_deg=55.0, depth_mm=300.0, pixel_mm=0.2, rows_toward_camera=False,
                    pattern_period_mm=4.0, camera_distance_mm=distance_mm)


def _tank(d, geometry):
    """Reference and one frame of a Gaussian bump centred on pixel (152.8, 152.8) of the frame
    (12 bit, noise 1 count); returns the bump's true centre (x, y) mm."""
    from processing import forward as F

    shape = (SIZE, SIZE)
    x0, y0 = (float(v) for v in geometry.surface_point(np.array(0.8 * (SIZE - 1)), np.array(0.8 * (SIZE - 1)),
                                                        shape))
    board = F.Checkerboard(period_mm=4.0, edge_softness_mm=0.2)
    rng = np.random.default_rng(1)

    def render(surface):
        image, _ = F.render_tir(surface, geometry, shape, board, supersample=2)
        return F.quantize(image, bits=12, noise_rms=1.0, rng=rng)

    d.mkdir()
    tifffile.imwrite(d / "reference.tif", render(F.FlatSurface()))
    tifffile.imwrite(d / "frame_0000.tif", render(F.GaussianBump(AMPLITUDE_MM, SIGMA_MM, x0_mm=x0, y0_mm=y0)))
    (d / "geometry.toml").write_text(geometry.to_toml_text())
    return x0, y0


def _process(capsys, d, out, *extra):
    code = main(["process", str(d / "reference.tif"), str(d / "frame_0000.tif"), "--geometry",
                 str(d / "geometry.toml"), "--out", str(out), "--no-progress", *extra])
    assert code == 0, capsys.readouterr().err


def _probe(capsys, out, csv_path, x, y):
    code = main(["probe", str(out), "--at", f"{x!r},{y!r}", "--out", str(csv_path)])
    err = capsys.readouterr().err
    if code != 0:
        return code, err, None
    with open(csv_path, newline="") as fh:
        rows = list(csv.reader(ln for ln in fh if not ln.startswith("#")))
    return code, err, float(rows[1][2])


def _peak_of_fit(x, y, h):
    """Centre of the Gaussian through the samples: log h quadratic in (x, y), least squares."""
    a = np.linalg.lstsq(np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=1), np.log(h), rcond=None)[0]
    return np.linalg.solve(np.array([[2 * a[3], a[4]], [a[4], 2 * a[5]]]), -a[1:3])


@pytest.fixture(scope="module")
def keystoned(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("keystone")
    geometry = _geometry(400.0)
    centre = _tank(tmp / "tank", geometry)
    return tmp, geometry, centre


def test_a_keystoned_output_says_where_each_sample_lies_and_probe_reads_the_named_point(keystoned, tmp_path, capsys):
    """Measured: the fit's peak at 0.022 mm from the bump's true centre in /surface_x_mm, /surface_y_mm, 0.50 mm
    off in x in /x_mm, /y_mm; probe at the true centre reads 99.8 % of the map's peak sample, where the 1-D
    axes' cell (the lookup before) read 96.5 %."""
    tmp, geometry, (x0, y0) = keystoned
    out = tmp_path / "out.h5"
    _process(capsys, tmp / "tank", out)
    with h5py.File(out) as f:
        h = f["height"][0].astype(np.float64)
        x_mm, y_mm = f["x_mm"][()], f["y_mm"][()]
        sx, sy = f["surface_x_mm"], f["surface_y_mm"]
        assert sx.shape == sy.shape == (SIZE, SIZE) and sx.dtype == sy.dtype == np.float32
        assert sx.attrs["units"] == "mm" and "keystoned" in sx.attrs["description"]
        assert "central row" in f["x_mm"].attrs["description"]
        sx, sy = sx[()].astype(np.float64), sy[()].astype(np.float64)
    want_x, want_y = geometry.grid_surface_mm(np.arange(SIZE), np.arange(SIZE), (SIZE, SIZE))
    np.testing.assert_allclose(sx, want_x, atol=1e-5)
    np.testing.assert_allclose(sy, want_y, atol=1e-5)
    assert np.ptp(sx[:, 0]) > 0.9  # the first column's x changes by 1.1 mm along the rows
    np.testing.assert_allclose(x_mm, want_x[SIZE // 2 - 1:SIZE // 2 + 1].mean(axis=0), atol=1e-3)  # central row

    top = np.isfinite(h) & (h > 0.6 * np.nanmax(h))
    fx, fy = _peak_of_fit(sx[top], sy[top], h[top])
    assert np.hypot(fx - x0, fy - y0) < 0.03
    one_d_x, _ = _peak_of_fit(np.broadcast_to(x_mm, h.shape)[top], np.broadcast_to(y_mm[:, None], h.shape)[top], h[top])
    assert abs(one_d_x - x0) > 0.3  # what /x_mm alone says

    peak = float(np.nanmax(h))
    code, err, reading = _probe(capsys, out, tmp_path / "p.csv", x0, y0)
    assert code == 0, err
    assert reading == pytest.approx(peak, rel=0.02)
    before = sample_cell(h, probe_cell(x_mm, y_mm, x0, y0))
    assert before < 0.975 * peak  # the 1-D axes' cell lies 0.5 mm off the bump's centre
    assert abs(reading - peak) < 0.25 * abs(before - peak)

    # past the last column's first sample, inside the range of /x_mm: outside the field, one line
    code, err, _ = _probe(capsys, out, tmp_path / "q.csv", float(sx[0, -1]) + 0.1, float(sy[0, -1]))
    assert code == 2 and "outside the measured field" in err and err.strip().count("\n") == 0
    assert float(sx[0, -1]) + 0.1 < x_mm[-1]


def test_the_decimated_grid_has_its_samples_positions_and_a_telecentric_output_none(keystoned, tmp_path, capsys):
    tmp, geometry, (x0, y0) = keystoned
    out = tmp_path / "dec.h5"
    _process(capsys, tmp / "tank", out, "--grid", "decimated")
    with h5py.File(out) as f:
        rows_px, cols_px = f["pin_region"].attrs["rows_px"], f["pin_region"].attrs["cols_px"]
        sx, sy = f["surface_x_mm"][()], f["surface_y_mm"][()]
        assert sx.shape == f["height"].shape[1:] == (len(rows_px), len(cols_px))
    want_x, want_y = geometry.grid_surface_mm(rows_px, cols_px, (SIZE, SIZE))
    np.testing.assert_allclose(sx, want_x, atol=1e-5)
    np.testing.assert_allclose(sy, want_y, atol=1e-5)
    code, err, reading = _probe(capsys, out, tmp_path / "p.csv", x0, y0)
    assert code == 0 and np.isfinite(reading), err

    telecentric = tmp_path / "telecentric"
    _tank(telecentric, _geometry(None))
    out = tmp_path / "tel.h5"
    _process(capsys, telecentric, out, "--grid", "decimated")
    with h5py.File(out) as f:
        assert "surface_x_mm" not in f and "surface_y_mm" not in f
