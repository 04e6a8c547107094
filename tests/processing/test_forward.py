"""Exact ray tracing against the linear model and the optical limits of TIR.

Every number here is a physical check of the tracer (not of its own output):
the paper's linear model, the critical angle, the focal length of a curved
mirror, the cos(theta) squeeze of the pattern.
"""

import math

import numpy as np
import pytest

from processing.errors import GeometryError
from processing.forward import (
    ApproachingDiscDimple,
    Checkerboard,
    Dimple,
    FlatSurface,
    GaussianBump,
    Surface,
    SumSurface,
    TravellingWaves,
    WaveField,
    quantize,
    render_fsss,
    render_tir,
    simulate,
    true_displacement,
    true_height,
)
from processing.geometry import Geometry

FSSS = dict(setup="fsss", pixel_mm=0.2, fsss_layers=((57.0, 1.0003), (12.0, 1.48899), (43.0, 1.34)), n_water=1.34)


def _tir(**kw):
    d = dict(theta_deg=55.0, depth_mm=300.0, pixel_mm=0.1, rows_toward_camera=False)
    d.update(kw)
    return Geometry(**d)


class Plane(Surface):
    """h = sx x + sy y (image frame)."""

    def __init__(self, sx, sy):
        self.sx, self.sy = sx, sy

    def height(self, x, y):
        return self.sx * np.asarray(x, float) + self.sy * np.asarray(y, float)

    def gradient(self, x, y):
        z = np.zeros(np.broadcast(np.asarray(x), np.asarray(y)).shape)
        return z + self.sx, z + self.sy


def _paper_u(surface, g, shape, h_sign):
    """Paper eq. (displfield) for a telecentric camera, in pixels (u_row, u_col)."""
    n_rows, n_cols = shape
    p, H, th = g.pixel_mm, g.depth_mm, g.theta
    x = (np.arange(n_cols) - (n_cols - 1) / 2) * p
    y = (np.arange(n_rows) - (n_rows - 1) / 2) * p / math.cos(th)  # image frame
    X, Y = np.meshgrid(x, y)
    h = surface.height(X, Y)
    hx, hy = surface.gradient(X, Y)
    s = g.row_sign  # canonical y = s * image y
    u_yc = -(2 * H / math.cos(th) ** 2) * (s * hy) + h_sign * 2 * math.tan(th) * h
    u_col = -2 * H * hx / p
    u_row = s * u_yc * math.cos(th) / p
    return np.stack([u_row, u_col])


@pytest.mark.parametrize("rows_toward_camera", [False, True])
def test_ray_traced_displacement_matches_linear_model(rows_toward_camera):
    """notes.md: 5 um, 10 mm wide bump, H = 300 mm, theta = 55 deg -> agree to < 0.5 %."""
    g = _tir(rows_toward_camera=rows_toward_camera)
    shape = (256, 256)
    bump = GaussianBump(amplitude_mm=0.005, sigma_mm=10.0 / 2.355, x0_mm=1.0, y0_mm=-2.0)
    u, lost = true_displacement(bump, g, shape)
    assert not lost.any()

    def rel(v):
        return float(np.sqrt(np.mean((u - v) ** 2)) / np.sqrt(np.mean(u**2)))

    # canonical frame: u_y = -(2H/cos^2) h_y - 2 tan(theta) h
    good = rel(_paper_u(bump, g, shape, h_sign=-1.0))
    wrong = rel(_paper_u(bump, g, shape, h_sign=+1.0))
    assert good < 0.005
    assert wrong > 2 * good  # the vertical-shift term and its sign are resolved


@pytest.mark.parametrize("distance", [None, 900.0])
@pytest.mark.parametrize(
    "g_kw", [dict(), dict(rows_toward_camera=True), dict(FSSS)], ids=["tir", "tir-rows-to-camera", "fsss"]
)
def test_flat_surface_has_zero_displacement(g_kw, distance):
    kw = dict(g_kw)
    if kw.get("setup") == "fsss":
        kw["fsss_camera_distance_mm"] = distance
        g = Geometry(**kw)
    else:
        g = _tir(camera_distance_mm=distance, **kw)
    u, lost = true_displacement(FlatSurface(), g, (40, 50))
    assert not lost.any() and np.max(np.abs(u)) < 1e-8


def test_tir_lost_where_slope_exceeds_theta_minus_critical():
    g = _tir(theta_deg=55.0)
    margin = math.radians(g.theta_deg - g.critical_angle_deg)  # about 6.4 deg
    shape = (8, 8)
    flat, _ = render_tir(FlatSurface(), g, shape, Checkerboard(2.0, sinusoidal=True, contrast=0.0))
    for factor, expect_lost in ((0.95, False), (1.05, True)):
        slope = math.tan(factor * margin)
        # a surface rising towards the camera (h falling along canonical +y) turns its
        # normal towards the pattern side and lowers the incidence by atan(slope)
        img, info = render_tir(Plane(0.0, -slope), g, shape, Checkerboard(2.0, sinusoidal=True, contrast=0.0))
        assert info.lost_tir.all() == expect_lost and info.lost_tir.any() == expect_lost
        if expect_lost:  # light escapes into the air: only the Fresnel reflection remains
            assert img.mean() < 0.9 * flat.mean()
        # the other way the incidence grows: never lost
        _, info2 = render_tir(Plane(0.0, slope), g, shape, Checkerboard(2.0))
        assert not info2.lost_tir.any()
    # far below the critical angle (incidence 30 deg) the water reflects only R = 2.55 %
    # (Fresnel, unpolarised, n 1.333 -> 1.0003): the pixel goes dark
    img, info = render_tir(Plane(0.0, -math.tan(math.radians(25.0))), g, shape,
                           Checkerboard(2.0, sinusoidal=True, contrast=0.0))
    assert img.mean() / flat.mean() == pytest.approx(0.0255, rel=0.03)
    # rows towards the camera flip the image y axis: the same physical tilt is +slope there
    g2 = _tir(theta_deg=55.0, rows_toward_camera=True)
    _, info3 = render_tir(Plane(0.0, math.tan(1.05 * margin)), g2, shape, Checkerboard(2.0))
    assert info3.lost_tir.all()


@pytest.mark.parametrize("rows_toward_camera", [False, True])
def test_ray_crossing_threshold_is_the_mirror_focal_length(rows_toward_camera):
    """A crest seen from below is a concave mirror: rays cross before the pattern when
    its focal length is shorter than the path H / cos(theta) to it, i.e. tangential
    curvature -h_yy > cos^2(theta) / (2H) (sagittal: -h_xx > 1 / (2H))."""
    g = _tir(theta_deg=55.0, pixel_mm=0.05, rows_toward_camera=rows_toward_camera)
    shape = (160, 128)
    sigma = 2.0
    kappa_t = math.cos(g.theta) ** 2 / (2 * g.depth_mm)
    for factor, expect in ((0.85, False), (1.2, True)):
        amp = factor * kappa_t * sigma**2  # peak curvature of the Gaussian is amp / sigma^2
        _, info = render_tir(GaussianBump(amp, sigma), g, shape, Checkerboard(1.0))
        assert info.crossing.any() == expect
        if expect:  # folds at the crest, away from the borders
            rr, cc = np.nonzero(info.crossing)
            assert abs(rr.mean() - 79.5) < 10 and abs(cc.mean() - 63.5) < 10
        # the same dimple is convex from below: it never folds the image
        _, info_d = render_tir(Dimple(amp, sigma), g, shape, Checkerboard(1.0))
        assert not info_d.crossing.any()


def test_reference_shows_pattern_squeezed_by_cos_theta():
    """Square board of period p: x-period p/s px, y-period p cos(theta)/s px (notes.md)."""
    g = _tir(theta_deg=60.0, pixel_mm=0.1)
    shape = (256, 256)
    board = Checkerboard(period_mm=2.0, sinusoidal=True)
    img, _ = render_tir(FlatSurface(), g, shape, board)
    spec = np.abs(np.fft.rfft2(img - img.mean()))
    spec[0, 0] = 0
    kr, kc = np.unravel_index(np.argmax(spec), spec.shape)
    kr = min(kr, 256 - kr)
    assert kc == pytest.approx(256 / 20.0, abs=1.0)  # 12.8 cycles
    assert kr == pytest.approx(256 / (20.0 * math.cos(g.theta)), abs=1.0)  # 6.4 cycles


def test_supersampled_sharp_board_is_area_averaged():
    g = _tir()
    board = Checkerboard(period_mm=0.75, rotation_deg=10.0)
    one, _ = render_tir(FlatSurface(), g, (64, 64), board)
    three, _ = render_tir(FlatSurface(), g, (64, 64), board, supersample=3)
    assert set(np.unique(one)) <= {np.float32(0.1), np.float32(0.9)}
    grey = (three > 0.12) & (three < 0.88)
    assert grey.mean() > 0.2  # edges fall inside pixels and are averaged
    assert three.mean() == pytest.approx(0.5, abs=0.02)


def test_true_height_is_sampled_where_the_ray_meets_the_surface():
    g = _tir(camera_distance_mm=1500.0)
    bump = GaussianBump(0.01, 3.0)
    h = true_height(bump, g, (64, 64))
    r, c = np.arange(64.0)[:, None], np.arange(64.0)[None, :]
    x, y = g.surface_point(r, c, (64, 64))
    _, d = g.camera_rays(r, c, (64, 64))
    h0 = bump.height(x, y)
    # the ray meets the raised surface h/d_z further along itself (h tan(theta) in y)
    x1 = x + h0 * d[..., 0] / d[..., 2]
    y1 = y + g.row_sign * h0 * d[..., 1] / d[..., 2]
    shift_effect = np.max(np.abs(bump.height(x1, y1) - h0))
    assert shift_effect > 1e-5  # resolved: 2e-5 mm for this 10 um bump
    assert np.max(np.abs(h - bump.height(x1, y1))) < 1e-2 * shift_effect  # first-order prediction


def test_surfaces_give_exact_gradients():
    x, y = np.meshgrid(np.linspace(-5, 5, 41), np.linspace(-4, 6, 37))
    surfaces = [
        GaussianBump(0.01, 2.0, 0.5, -1.0),
        WaveField.random(5, amplitude_rms_mm=0.002, wavelength_range_mm=(5.0, 10.0), seed=3),
        SumSurface([Dimple(0.003, 1.5), WaveField(((0.001, 0.7, -0.4, 0.3),))]),
        ApproachingDiscDimple(radius_mm=6.0, max_depth_mm=0.01, t_contact_s=0.5).at(0.3),
        TravellingWaves(((0.001, 0.5, 0.2, 0.0),)).at(0.1),
    ]
    e = 1e-5
    for s in surfaces:
        gx, gy = s.gradient(x, y)
        nx = (s.height(x + e, y) - s.height(x - e, y)) / (2 * e)
        ny = (s.height(x, y + e) - s.height(x, y - e)) / (2 * e)
        scale = max(np.abs(gx).max(), np.abs(gy).max())
        assert np.max(np.abs(gx - nx)) < 1e-6 * scale and np.max(np.abs(gy - ny)) < 1e-6 * scale
    w = WaveField.random(8, amplitude_rms_mm=0.002, wavelength_range_mm=(5.0, 10.0), seed=1)
    big = np.linspace(-200, 200, 801)
    assert np.sqrt(np.mean(w.height(*np.meshgrid(big, big)) ** 2)) == pytest.approx(0.002, rel=0.15)
    assert ApproachingDiscDimple(max_depth_mm=0.01, t_contact_s=1.0).at(0.5).amplitude_mm == pytest.approx(-0.0025)


def test_quantize_levels_and_noise(rng):
    img = np.full((200, 200), 0.5)
    q = quantize(img, bits=12, noise_rms=3.0, rng=rng)
    assert q.dtype == np.uint16 and q.max() < 4096
    assert q.mean() == pytest.approx(0.5 * 4095, abs=0.2)
    assert q.std() == pytest.approx(3.0, rel=0.05)
    q8 = quantize(np.linspace(0, 1, 256)[None, :], bits=8)
    assert q8.dtype == np.uint8 and q8.min() == 0 and q8.max() == 255
    qp = quantize(img, bits=16, rng=rng, full_well_e=10000.0)
    assert qp.std() / qp.mean() == pytest.approx(1 / math.sqrt(5000), rel=0.1)  # shot noise
    with pytest.raises(GeometryError, match="rng"):
        quantize(img, noise_rms=1.0)


def test_simulate_series_matches_direct_renders():
    g = _tir()
    scene = ApproachingDiscDimple(radius_mm=2.0, max_depth_mm=0.002, t_contact_s=0.02)
    sim = simulate(scene, g, (48, 40), 3, fps=100.0, bits=10, noise_rms=0.0, supersample=1, seed=0)
    assert sim.reference.dtype == np.uint16 and sim.frames.shape == (3, 48, 40)
    assert sim.times_s == pytest.approx([0.0, 0.01, 0.02])
    np.testing.assert_array_equal(sim.frames[0], sim.reference)  # t = 0: flat
    assert np.allclose(sim.heights_mm[2], true_height(scene.at(0.02), g, (48, 40)), atol=1e-9)
    assert sim.heights_mm[2].min() == pytest.approx(-0.002, rel=0.05)
    assert not np.array_equal(sim.frames[2], sim.reference)


def test_fsss_render_of_flat_water_shows_the_board():
    g = Geometry(**FSSS)
    img, info = render_fsss(FlatSurface(), g, (32, 32), Checkerboard(period_mm=1.6, sinusoidal=True))
    assert not info.lost_tir.any() and not info.crossing.any()
    assert img.min() < 0.2 and img.max() > 0.8


def _trace_tir_vectors(surface, geometry, rows_px, cols_px, frame_shape):
    """The tracer as it was written on (S, 3) vectors before it ran on their components (6 Dec
    2026): the reference that :func:`processing.forward.trace_tir` must give bit for bit."""
    origin, d = geometry.camera_rays(rows_px, cols_px, frame_shape)
    s = geometry.row_sign
    t = -origin[..., 2] / d[..., 2]
    for _ in range(60):
        P = origin + t[..., None] * d
        h, gx, gy_i = surface.height_and_gradient(P[..., 0], s * P[..., 1])
        gy = gy_i * s
        step = (P[..., 2] - h) / (d[..., 2] - gx * d[..., 0] - gy * d[..., 1])
        if np.max(np.abs(step)) < 1e-9:
            break
        t = t - step
    nrm = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    cos_i = np.sum(d * nrm, axis=-1)
    sin_i = np.sqrt(np.clip(1.0 - cos_i**2, 0.0, None))
    r = d - 2.0 * cos_i[..., None] * nrm
    lost = (sin_i <= geometry.n_air / geometry.n_water) | (r[..., 2] >= 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(r[..., 2] < 0, (-geometry.depth_mm - P[..., 2]) / r[..., 2], np.nan)
    return P[..., :2] + t[..., None] * r[..., :2], lost, P, h, cos_i


@pytest.mark.parametrize("distance", [None, 1500.0])
@pytest.mark.parametrize("surface", [WaveField.random(6, amplitude_rms_mm=0.01, wavelength_range_mm=(5, 30), seed=3),
                                     GaussianBump(0.4, 2.0)], ids=["waves", "steep bump"])
def test_tracer_on_ray_components_gives_the_vector_form_bit_for_bit(surface, distance):
    # the components' arithmetic is the vectors' in the same order: every output the same bits,
    # TIR lost (the steep bump) included; with rays passed in as the second-order correction does
    from processing.forward import trace_tir

    g = _tir(depth_mm=20.0, camera_distance_mm=distance)
    rows, cols = np.meshgrid(np.arange(96.0), np.arange(128.0), indexing="ij")
    want = _trace_tir_vectors(surface, g, rows, cols, (96, 128))
    for got in (trace_tir(surface, g, rows, cols, (96, 128)),
                trace_tir(surface, g, rows, cols, (96, 128), rays=g.camera_rays(rows, cols, (96, 128)))):
        for a, b in zip(got, want):
            assert np.array_equal(a, b, equal_nan=True)
    assert want[1].any() == (surface.__class__ is GaussianBump)  # the steep bump loses TIR somewhere
