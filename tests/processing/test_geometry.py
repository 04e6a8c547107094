"""Geometry: TOML round trips, every bad-TOML error, and the camera model's scales."""

import math
from pathlib import Path

import numpy as np
import pytest

from processing.errors import GeometryError
from processing.geometry import Geometry

ROOT = Path(__file__).resolve().parents[2]

TIR_TEXT = """
setup = "tir"
theta_deg = 60.0
depth_mm = 300.0
pixel_mm = 0.1
rows_toward_camera = true
camera_distance_mm = 1500.0
reference_region = [0, 40, 0, 512]
"""

FSSS_TEXT = """
setup = "fsss"
pixel_mm = 0.207
fsss_camera_distance_mm = 800.0
fsss_layers = [[57.0, 1.0003], [12.0, 1.48899], [43.0, 1.34]]
n_water = 1.34
"""


def _tir(**kw):
    d = dict(theta_deg=55.0, depth_mm=300.0, pixel_mm=0.1, rows_toward_camera=False)
    d.update(kw)
    return Geometry(**d)


@pytest.mark.parametrize("text", [TIR_TEXT, FSSS_TEXT])
def test_toml_round_trip(text, tmp_path):
    g = Geometry.from_toml_text(text)
    assert Geometry.from_toml_text(g.to_toml_text()) == g
    assert Geometry.from_dict(g.to_dict()) == g
    path = tmp_path / "g.toml"
    path.write_text(g.to_toml_text())
    assert Geometry.from_toml(path) == g
    hash(g)  # frozen and hashable: usable as a cache key


def test_toml_text_keeps_every_digit():
    """Values that need all of a float's digits come back bit for bit (0.078125 must not become 0.07813)."""
    g = _tir(pixel_mm=0.078125, theta_deg=55.123456789012345, depth_mm=300.1 + 1e-12,
             camera_distance_mm=1234.5678901234567)
    text = g.to_toml_text()
    assert "pixel_mm = 0.078125\n" in text
    back = Geometry.from_toml_text(text)
    assert back == g
    for key in ("pixel_mm", "theta_deg", "depth_mm", "camera_distance_mm"):
        assert getattr(back, key) == getattr(g, key)  # exact, not approx


def test_toml_values_and_table():
    g = Geometry.from_toml_text("[geometry]\n" + TIR_TEXT)
    assert g.rows_toward_camera is True
    assert g.camera_distance_mm == 1500.0
    assert g.reference_region == (0, 40, 0, 512)
    assert g.n_water == 1.333


@pytest.mark.parametrize("name", ["geometry-example.toml", "geometry-fsss-example.toml"])
def test_example_files_load(name):
    g = Geometry.from_toml(ROOT / "resources" / name)
    assert Geometry.from_toml_text(g.to_toml_text()) == g


def _err(text):
    with pytest.raises(GeometryError) as exc:
        Geometry.from_toml_text(text)
    return str(exc.value)


def test_missing_key_names_it_and_shows_an_example():
    msg = _err(TIR_TEXT.replace("depth_mm = 300.0\n", ""))
    assert "depth_mm" in msg and "depth_mm = 300.0" in msg
    msg = _err(TIR_TEXT.replace("rows_toward_camera = true\n", ""))
    assert "rows_toward_camera" in msg and "rows_toward_camera = false" in msg
    msg = _err(TIR_TEXT.replace('setup = "tir"\n', ""))
    assert "setup" in msg and 'setup = "tir"' in msg
    msg = _err(FSSS_TEXT.replace("fsss_layers", "# fsss_layers"))
    assert "fsss_layers" in msg


def test_wrong_type_echoes_value():
    msg = _err(TIR_TEXT.replace("depth_mm = 300.0", 'depth_mm = "abc"'))
    assert "depth_mm must be a number of millimetres, got 'abc'" in msg
    msg = _err(TIR_TEXT.replace("rows_toward_camera = true", 'rows_toward_camera = "yes"'))
    assert "rows_toward_camera must be true or false" in msg and "'yes'" in msg
    msg = _err(TIR_TEXT.replace("theta_deg = 60.0", "theta_deg = true"))
    assert "theta_deg must be a number of degrees" in msg


def test_unknown_key_lists_allowed():
    msg = _err(TIR_TEXT + "thetadeg = 3\n")
    assert "'thetadeg'" in msg and "theta_deg" in msg and "allowed keys" in msg


def test_theta_below_critical_angle():
    msg = _err(TIR_TEXT.replace("theta_deg = 60.0", "theta_deg = 40"))
    assert "no total internal reflection at theta=40 deg" in msg
    assert "raise theta above 48.6 deg" in msg
    assert "theta_deg must be below 90" in _err(TIR_TEXT.replace("theta_deg = 60.0", "theta_deg = 95.0"))


@pytest.mark.parametrize("key", ["depth_mm", "pixel_mm", "camera_distance_mm"])
def test_non_positive_lengths(key):
    import re

    text = re.sub(rf"{key} = [0-9.]+", f"{key} = -1.0", TIR_TEXT)
    msg = _err(text)
    assert f"{key} must be a positive length in mm, got -1.0" in msg


@pytest.mark.parametrize("key, value, shown", [("depth_mm", 300000.0, "300 m"), ("depth_mm", 1e12, "1e+09 m"),
                                                ("camera_distance_mm", 1e15, "1e+12 m")])
def test_lengths_beyond_any_set_up_are_refused(key, value, shown):
    """By-hand trial of 7 Dec 2026: 300 m of water (um typed as mm) gave heights 1000 times too small and
    1e12 mm gave zero heights, both with exit 0; a camera at 1e15 mm ended in a singular matrix."""
    with pytest.raises(GeometryError) as exc:
        _tir(**{key: value})
    msg = str(exc.value)
    assert f"{key} = {value:g} mm ({shown})" in msg and "lengths are in millimetres" in msg, msg
    _tir(depth_mm=2000.0, camera_distance_mm=5000.0)  # a deep tank, a far camera: accepted


def test_bad_reference_region_layers_and_syntax():
    assert "four integers" in _err(TIR_TEXT.replace("[0, 40, 0, 512]", "[0, 40]"))
    assert "row0 < row1" in _err(TIR_TEXT.replace("[0, 40, 0, 512]", "[40, 0, 0, 512]"))
    msg = _err(FSSS_TEXT.replace("[43.0, 1.34]", "[43.0, 1.33]"))
    assert "n_water=1.34" in msg and "water last" in msg
    assert "not valid TOML" in _err("setup = ")
    assert "0 < n_air < n_water" in _err(TIR_TEXT + "n_water = 0.9\n")


def test_derived_quantities():
    g = _tir(theta_deg=60.0)
    assert g.theta == pytest.approx(math.pi / 3)
    assert g.T == pytest.approx(0.5 * math.sin(2 * g.theta), rel=1e-12)
    assert g.critical_angle_deg == pytest.approx(math.degrees(math.asin(1.0003 / 1.333)))
    assert round(g.critical_angle_deg, 1) == 48.6
    f = Geometry.from_toml_text(FSSS_TEXT)
    # h_p: water-equivalent depth of the stack; alpha = 1 - n_air / n_water
    assert f.fsss_hp_mm == pytest.approx(57.0 * 1.34 / 1.0003 + 12.0 * 1.34 / 1.48899 + 43.0)
    assert f.fsss_alpha == pytest.approx(1 - 1.0003 / 1.34)


@pytest.mark.parametrize("distance", [None, 1500.0])
@pytest.mark.parametrize("rows_toward_camera", [False, True])
def test_surface_scale_at_image_centre(distance, rows_toward_camera):
    """pixel_mm per column and pixel_mm / cos(theta) per row at the centre, y along rows."""
    g = _tir(theta_deg=60.0, camera_distance_mm=distance, rows_toward_camera=rows_toward_camera)
    shape = (101, 101)
    x0, y0 = g.surface_point(50.0, 50.0, shape)
    x1, _ = g.surface_point(50.0, 51.0, shape)
    _, y1 = g.surface_point(51.0, 50.0, shape)
    assert abs(x0) < 1e-12 and abs(y0) < 1e-12
    assert x1 - x0 == pytest.approx(0.1, rel=1e-3)
    # image-frame y increases with the row index whichever way the camera looks
    assert y1 - y0 == pytest.approx(0.1 / math.cos(g.theta), rel=2e-3)


@pytest.mark.parametrize(
    "g",
    [
        _tir(),
        _tir(camera_distance_mm=1200.0, rows_toward_camera=True),
        Geometry.from_toml_text(FSSS_TEXT),
        Geometry.from_toml_text(FSSS_TEXT.replace("fsss_camera_distance_mm = 800.0\n", "")),
    ],
    ids=["tir-telecentric", "tir-pinhole", "fsss-finite", "fsss-telecentric"],
)
def test_pattern_map_inverse(g):
    shape = (64, 80)
    r, c = np.meshgrid(np.linspace(-3, 66, 9), np.linspace(-5, 84, 11), indexing="ij")
    px, py = g.flat_pattern_point(r, c, shape)
    r2, c2 = g.pixel_of_pattern_point(px, py, shape)
    assert np.max(np.abs(r2 - r)) < 1e-8 and np.max(np.abs(c2 - c)) < 1e-8


@pytest.mark.parametrize("rows_toward_camera", [False, True])
def test_linear_response_is_the_papers_at_the_centre(rows_toward_camera):
    """Telecentric: u_x = -2H h_x, u_y = -(2H/cos^2) h_y -/+ 2 tan(theta) h, in pixels."""
    g = _tir(theta_deg=55.0, rows_toward_camera=rows_toward_camera)
    p, H, th = g.pixel_mm, g.depth_mm, g.theta
    lr = g.linear_response(31.5, 31.5, (64, 64))
    s = -1.0 if rows_toward_camera else 1.0
    # u_row per mm of h: (-s 2 tan(theta)) mm of surface y, times cos(theta)/p px per mm
    assert lr.a == pytest.approx([-s * 2 * math.sin(th) / p, 0.0], abs=1e-9)
    # per pixel-gradient: -2H/p^2 on both axes (the cos factors cancel)
    assert lr.B == pytest.approx(-2 * H / p**2 * np.eye(2), rel=1e-6)


def test_default_reference_region_is_a_border_band():
    g = _tir()
    m = g.reference_mask(np.arange(100), np.arange(200), (100, 200))
    # 4 % of the smaller side = 4 px on every edge
    assert m[:4].all() and m[-4:].all() and m[:, :4].all() and m[:, -4:].all()
    assert not m[4:-4, 4:-4].any()
    g2 = _tir(reference_region=(10, 20, 30, 40))
    m2 = g2.reference_mask(np.arange(100), np.arange(200), (100, 200))
    assert m2.sum() == 100 and m2[10, 30] and not m2[20, 30]
    with pytest.raises(GeometryError, match="outside the frame"):
        _tir(reference_region=(200, 210, 0, 10)).reference_mask(np.arange(100), np.arange(100), (100, 100))


def test_tir_quantities_refused_for_fsss():
    f = Geometry.from_toml_text(FSSS_TEXT)
    with pytest.raises(GeometryError, match="TIR setup only"):
        f.theta
    with pytest.raises(GeometryError, match="TIR setup only"):
        f.T


def test_camera_distance_of_the_other_setup_is_refused():
    """A silently ignored distance would change the heights by (1 + h_a/L), 12 % here."""
    msg = _err(FSSS_TEXT.replace("fsss_camera_distance_mm", "camera_distance_mm"))
    assert "camera_distance_mm=800 is the TIR camera distance" in msg and "fsss_camera_distance_mm" in msg
    msg = _err(TIR_TEXT.replace("camera_distance_mm", "fsss_camera_distance_mm"))
    assert "is the FS-SS camera height" in msg and "camera_distance_mm" in msg


# ---------------------------------------------------------------------- against the frame
@pytest.mark.parametrize("distance", [1.0, 0.001])
def test_camera_closer_than_the_field_is_refused_with_the_numbers(distance):
    """camera_distance_mm = 1 (or 0.001) on a 19 mm field: the keys pass, the frame refuses it."""
    g = _tir(theta_deg=60.0, camera_distance_mm=distance)  # each key is plausible on its own
    with pytest.raises(GeometryError) as exc:
        g.check_frame((190, 190))
    msg = str(exc.value)
    assert f"camera_distance_mm = {distance:g} mm is too short" in msg
    assert "190 x 190 px" in msg and "19 x 38 mm" in msg  # the field it was measured against
    need = 0.5 * math.hypot(189 * 0.1, 189 * 0.1) / math.tan(math.radians(60.0))
    assert f"at least {need:.4g} mm" in msg and "telecentric" in msg


def test_rays_that_are_not_totally_reflected_are_refused():
    """A camera 20 mm from a 19 mm field at theta 60: the near rows see through the surface."""
    g = _tir(theta_deg=60.0, camera_distance_mm=20.0)
    with pytest.raises(GeometryError) as exc:
        g.check_frame((190, 190))
    msg = str(exc.value)
    assert "below the critical angle 48.6 deg" in msg and "pixel (row 0," in msg
    # the angle it names is the ray's own: the ray tracer's direction at that pixel
    _, d = g.camera_rays(0.0, 94.5, (190, 190))
    assert f"at {math.degrees(math.acos(d[2])):.1f} deg" in msg
    # the same camera with rows towards the camera: the far row is the near one now
    with pytest.raises(GeometryError, match=r"pixel \(row 189,"):
        _tir(theta_deg=60.0, camera_distance_mm=20.0, rows_toward_camera=True).check_frame((190, 190))


@pytest.mark.parametrize("kw, shape", [
    (dict(), (1024, 1024)),                                          # telecentric
    (dict(theta_deg=60.0, camera_distance_mm=1500.0), (1024, 1280)),  # resources/geometry-example.toml
    (dict(camera_distance_mm=900.0), (40, 50)),                       # tests/processing/test_forward.py
    (dict(theta_deg=60.0, camera_distance_mm=1500.0), (192, 208)),    # tests/processing/test_height.py
])
def test_ordinary_geometries_pass_the_frame_check(kw, shape):
    _tir(**kw).check_frame(shape)


@pytest.mark.parametrize("name", ["geometry-example.toml", "geometry-fsss-example.toml"])
def test_shipped_examples_pass_the_frame_check(name):
    Geometry.from_toml(ROOT / "resources" / name).check_frame((1024, 1024))


def test_fsss_camera_too_close_is_refused():
    g = Geometry.from_toml_text(FSSS_TEXT.replace("800.0", "1.0"))
    with pytest.raises(GeometryError, match="fsss_camera_distance_mm = 1 mm is too short"):
        g.check_frame((160, 176))
    Geometry.from_toml_text(FSSS_TEXT).check_frame((160, 176))


def test_reconstructor_refuses_the_absurd_camera_before_any_frame():
    """The one place that knows both the geometry and the frame: the Reconstructor."""
    from processing.forward import Checkerboard, FlatSurface, render_tir
    from processing.reconstruct import Reconstructor

    shape = (128, 128)
    good = _tir(theta_deg=60.0)
    ref, _ = render_tir(FlatSurface(), good, shape, Checkerboard(1.2, sinusoidal=True))
    Reconstructor(ref, good)  # the telecentric geometry it was rendered with is fine
    with pytest.raises(GeometryError, match="camera_distance_mm = 1 mm is too short"):
        Reconstructor(ref, _tir(theta_deg=60.0, camera_distance_mm=1.0))
