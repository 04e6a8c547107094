"""A TIR camera at a finite distance sees the surface keystoned: each sample's own surface position
(Geometry.grid_surface_mm), its exact inverse (pixel_of_surface_point) and the probe's cell found in
the 2-D positions (processing.probe.grid_index_of_point, probe_cell_2d)."""

import numpy as np
import pytest

from processing.errors import TirdeflectError
from processing.geometry import Geometry
from processing.probe import grid_index_of_point, probe_cell, probe_cell_2d

FSSS = dict(setup="fsss", pixel_mm=0.207, fsss_layers=[[57.0, 1.0003], [12.0, 1.48899], [43.0, 1.34]], n_water=1.34)


def _tir(**kw):
    d = dict(theta_deg=55.0, depth_mm=300.0, pixel_mm=0.1, rows_toward_camera=False)
    d.update(kw)
    return Geometry(**d)


def _bilinear(values, row, col):
    r0, c0 = int(np.floor(row)), int(np.floor(col))
    fr, fc = row - r0, col - c0
    q = values[r0:r0 + 2, c0:c0 + 2]
    return ((1 - fr) * ((1 - fc) * q[0, 0] + fc * q[0, 1]) + fr * ((1 - fc) * q[1, 0] + fc * q[1, 1]))


GEOMETRIES = [
    _tir(camera_distance_mm=400.0),
    _tir(camera_distance_mm=1500.0, rows_toward_camera=True),
    _tir(),
    _tir(rows_toward_camera=True),
    Geometry(**FSSS, fsss_camera_distance_mm=800.0),
    Geometry(**FSSS),
]
IDS = ["tir-400", "tir-1500-toward", "tir-telecentric", "tir-telecentric-toward", "fsss-finite", "fsss-telecentric"]


@pytest.mark.parametrize("g", GEOMETRIES, ids=IDS)
def test_pixel_of_surface_point_inverts_surface_point(g):
    shape = (192, 160)
    r, c = np.meshgrid(np.linspace(-3.3, 194.7, 13), np.linspace(-5.1, 163.9, 11), indexing="ij")
    x, y = g.surface_point(r, c, shape)
    r2, c2 = g.pixel_of_surface_point(x, y, shape)
    assert np.max(np.abs(r2 - r)) < 1e-8 and np.max(np.abs(c2 - c)) < 1e-8


@pytest.mark.parametrize("g", GEOMETRIES, ids=IDS)
def test_only_a_tir_camera_at_a_finite_distance_sees_the_surface_keystoned(g):
    shape = (256, 256)
    x, y = g.grid_surface_mm(np.arange(256), np.arange(256), shape)
    assert x.shape == y.shape == shape and x.dtype == np.float64
    # the x of a column along its rows, the y of a row along its columns
    x_spread, y_spread = float(np.ptp(x, axis=0).max()), float(np.ptp(y, axis=1).max())
    if g.surface_separable:
        assert x_spread < 1e-9 and y_spread < 1e-9
    else:
        assert g.setup == "tir" and g.camera_distance_mm is not None
        assert x_spread > 0.25  # mm: the edge columns' x at 400 mm from 25 mm wide: 1.16 mm, at 1500 mm 0.31 mm
        assert y_spread < 1e-9  # a row is a line of one y on the surface


def test_a_keystoned_grid_gives_back_the_fractional_index():
    """A decimated grid's positions (every 8th pixel from 4, camera at 400 mm): a point between its samples
    gives back its fractional (row, col) to 1e-6, and the pixel there is the one Geometry.surface_point maps
    onto the point (to the bilinear rule's curvature error: 5e-3 px on an 8 px cell)."""
    g = _tir(camera_distance_mm=400.0)
    shape = (256, 256)
    rows_px, cols_px = np.arange(4.0, 256, 8), np.arange(4.0, 256, 8)
    sx, sy = g.grid_surface_mm(rows_px, cols_px, shape)
    rng = np.random.default_rng(7)
    for row, col in rng.uniform(0, [len(rows_px) - 1, len(cols_px) - 1], (40, 2)):
        x, y = _bilinear(sx, row, col), _bilinear(sy, row, col)
        r, c = grid_index_of_point(sx, sy, x, y)
        assert abs(r - row) < 1e-6 and abs(c - col) < 1e-6
        # round trip through the camera: the pixel whose ray meets the surface at (x, y)
        pr, pc = g.pixel_of_surface_point(x, y, shape)
        assert abs(4 + 8 * r - pr) < 1e-2 and abs(4 + 8 * c - pc) < 1e-2
        x2, y2 = g.surface_point(pr, pc, shape)
        assert abs(x2 - x) < 1e-9 and abs(y2 - y) < 1e-9
    # the corners and edges of the grid are inside it
    for row, col in ((0, 0), (len(rows_px) - 1, len(cols_px) - 1), (0, 12.5), (20.25, len(cols_px) - 1)):
        r0, c0, fr, fc = probe_cell_2d(sx, sy, _bilinear(np.pad(sx, ((0, 1), (0, 1)), mode="edge"), row, col),
                                       _bilinear(np.pad(sy, ((0, 1), (0, 1)), mode="edge"), row, col))
        assert r0 + fr == pytest.approx(row, abs=1e-6) and c0 + fc == pytest.approx(col, abs=1e-6)


def test_the_one_d_axes_miss_a_keystoned_point_that_the_two_d_positions_find():
    """The full grid of a 256^2 frame, camera at 400 mm: the 1-D axes along the central row and column put a
    point near the corner 0.3-0.6 mm off in x; the 2-D positions find its pixel."""
    g = _tir(camera_distance_mm=400.0)
    shape = (256, 256)
    sx, sy = g.grid_surface_mm(np.arange(256), np.arange(256), shape)
    x_mm, y_mm = sx[127], sy[:, 127]  # about the central row and column
    x, y = g.surface_point(230.4, 20.7, shape)
    r0, c0, fr, fc = probe_cell_2d(sx, sy, x, y)
    assert r0 + fr == pytest.approx(230.4, abs=1e-3) and c0 + fc == pytest.approx(20.7, abs=1e-3)
    r0, c0, fr, fc = probe_cell(x_mm, y_mm, x, y)
    assert abs(c0 + fc - 20.7) > 3  # columns of 0.1 mm: more than 0.3 mm off


def test_separable_positions_give_the_one_d_cell():
    g = _tir()
    shape = (64, 80)
    sx, sy = g.grid_surface_mm(np.arange(64), np.arange(80), shape)
    for x, y in ((0.0, 0.0), (1.234, -2.5), (sx[0, 0], sy[0, 0]), (sx[-1, -1], sy[-1, -1])):
        np.testing.assert_allclose(probe_cell_2d(sx, sy, x, y), probe_cell(sx[0], sy[:, 0], x, y), atol=1e-9)


@pytest.mark.parametrize("point", [(500.0, 0.0), (0.0, -500.0), (1e9, 1e9)])
def test_a_point_outside_the_keystoned_field_is_a_clear_error(point):
    g = _tir(camera_distance_mm=400.0)
    shape = (128, 128)
    sx, sy = g.grid_surface_mm(np.arange(128), np.arange(128), shape)
    with pytest.raises(TirdeflectError, match="outside the measured field"):
        probe_cell_2d(sx, sy, *point)


def test_a_point_just_outside_a_keystoned_edge_is_outside():
    """0.05 mm beyond the last column's first sample: outside, though inside the range of that column's x over
    the rows and inside the 1-D axes' range (which take the last column at its central row's x)."""
    g = _tir(camera_distance_mm=400.0)
    shape = (128, 128)
    sx, sy = g.grid_surface_mm(np.arange(128), np.arange(128), shape)
    x, y = sx[0, -1] + 0.05, sy[0, -1]
    assert x < sx[:, -1].max() and x < sx[63, -1]
    probe_cell(sx[63], sy[:, 63], x, y)  # the 1-D axes take it for inside
    with pytest.raises(TirdeflectError, match="outside the measured field"):
        probe_cell_2d(sx, sy, x, y)
