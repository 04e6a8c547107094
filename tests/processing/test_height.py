"""Heights from displacement: exactness, null space, masks, grids, finite camera, FS-SS.

Linear-model tests feed the paper's displacement of an analytic surface;
end-to-end optics tests feed the exact ray-traced displacement of
processing.forward and compare with the true heights along the camera rays.
"""

import math

import numpy as np
import pytest

from processing.errors import GeometryError, ShapeMismatchError, TirdeflectError
from processing.forward import GaussianBump, SumSurface, WaveField, true_displacement, true_height
from processing.geometry import Geometry
from processing.height import HeightSolver, surface_from_displacement

SHAPE = (192, 208)


def _tir(**kw):
    d = dict(theta_deg=55.0, depth_mm=300.0, pixel_mm=0.1, rows_toward_camera=False)
    d.update(kw)
    return Geometry(**d)


def _grid(shape=SHAPE):
    return np.arange(shape[0], dtype=float), np.arange(shape[1], dtype=float)


def _xy(g, shape=SHAPE):
    """Image-frame surface coordinates of a telecentric grid (mm)."""
    x = (np.arange(shape[1]) - (shape[1] - 1) / 2) * g.pixel_mm
    y = (np.arange(shape[0]) - (shape[0] - 1) / 2) * g.pixel_mm / math.cos(g.theta)
    return np.meshgrid(x, y)


def _paper_u(h, hx, hy, g):
    """Paper eq. (displfield), telecentric, canonical frame flipped to image rows; pixels."""
    p, H, th, s = g.pixel_mm, g.depth_mm, g.theta, g.row_sign
    u_yc = -(2 * H / math.cos(th) ** 2) * (s * hy) - 2 * math.tan(th) * h
    return np.stack([s * u_yc * math.cos(th) / p, -2 * H * hx / p])


def _rel_rms(a, b, where=None):
    if where is None:
        where = np.isfinite(a)
    return float(np.sqrt(np.mean((a - b)[where] ** 2)) / np.sqrt(np.mean(b[where] ** 2)))


def _solve(u, valid, g, shape=SHAPE, **kw):
    r, c = _grid(shape)
    return surface_from_displacement(u, valid, g, rows_px=r, cols_px=c, frame_shape=shape, **kw)


BUMP = SumSurface([GaussianBump(0.005, 2.0, 1.5, -1.0), GaussianBump(-0.003, 1.2, -3.0, 2.5)])


@pytest.mark.parametrize("rows_toward_camera", [False, True])
def test_exact_on_linear_model(rows_toward_camera):
    """notes.md: least squares of exact gradients reproduces h to 0.01 %."""
    g = _tir(rows_toward_camera=rows_toward_camera)
    X, Y = _xy(g)
    h = BUMP.height(X, Y)
    u = _paper_u(h, *BUMP.gradient(X, Y), g).astype(np.float32)
    res = _solve(u, None, g)
    assert res.height_mm.dtype == np.float32 and res.height_mm.shape == SHAPE
    assert _rel_rms(res.height_mm, h) < 1e-3
    hx, hy = BUMP.gradient(X, Y)
    assert np.max(np.abs(res.slope_x - hx)) < 1e-3 * np.abs(hx).max()
    assert np.max(np.abs(res.slope_y - hy)) < 1e-3 * np.abs(hy).max()
    assert res.x_mm == pytest.approx(X[0]) and res.y_mm == pytest.approx(Y[:, 0])
    # the wrong row direction is a different physical setup: the heights come out wrong
    other = _solve(u, None, _tir(rows_toward_camera=not rows_toward_camera))
    assert _rel_rms(other.height_mm, h) > 0.01


def test_null_space_is_pinned_by_the_reference_region():
    """h + f0 exp(-T y_c / H) produces the same u: pinning returns h, not h + f0 e^(...)."""
    g = _tir(rows_toward_camera=True, reference_region=(0, 20, 0, 30))
    X, Y = _xy(g)
    c = g.T / g.depth_mm
    yc = g.row_sign * Y
    h = BUMP.height(X, Y)
    hx, hy = BUMP.gradient(X, Y)
    f0 = 0.004
    null = f0 * np.exp(-c * yc)
    u0 = _paper_u(h, hx, hy, g)
    u1 = _paper_u(h + null, hx, hy + g.row_sign * (-c) * null, g)
    assert np.max(np.abs(u1 - u0)) < 1e-12  # the paper's operator cannot see it
    r0, r1 = _solve(u0, None, g), _solve(u1, None, g)
    np.testing.assert_allclose(r1.height_mm, r0.height_mm, atol=1e-6 * np.abs(h).max())
    assert _rel_rms(r1.height_mm, h) < 1e-3
    assert abs(float(np.mean(r1.height_mm[0:20, 0:30]))) < 1e-4 * np.abs(h).max()
    # a constant offset alone would leave 4 % of f0 tilt over the field (2.4 % of the bump)
    tilt = null - null[0:20, 0:30].mean()
    assert _rel_rms(h + tilt, h) > 0.01


def test_masked_region_does_not_pollute(rng):
    g = _tir()
    X, Y = _xy(g)
    h = BUMP.height(X, Y)
    u = _paper_u(h, *BUMP.gradient(X, Y), g)
    rr, cc = np.mgrid[: SHAPE[0], : SHAPE[1]]
    hole = ((rr - 120) ** 2 + (cc - 90) ** 2 < 22**2) | ((abs(rr - 50) < 8) & (abs(cc - 150) < 35))
    bad = u.copy()
    bad[:, hole] = rng.normal(0.0, 30.0, size=(2, int(hole.sum())))
    bad[0, hole & (rr % 7 == 0)] = np.nan
    res = _solve(bad, ~hole, g)
    assert np.isnan(res.height_mm[hole]).all() and np.isnan(res.slope_x[hole]).all()
    assert not res.valid[hole].any() and res.valid[~hole].all()
    assert _rel_rms(res.height_mm, h, ~hole) < 1e-3
    assert np.max(np.abs(res.height_mm - h)[~hole]) < 1e-3 * np.abs(h).max()
    assert 0 < res.iterations < 100


def test_spectral_equals_masked_when_all_valid(rng):
    g = _tir()
    X, Y = _xy(g)
    w = WaveField.random(6, amplitude_rms_mm=0.002, wavelength_range_mm=(4.0, 9.0), seed=4)
    u = _paper_u(w.height(X, Y), *w.gradient(X, Y), g) + rng.normal(0, 0.05, size=(2, *SHAPE))
    spec = _solve(u, None, g, solver="spectral")
    mask = _solve(u, np.ones(SHAPE, bool), g, solver="masked")
    scale = np.abs(spec.height_mm).max()
    assert np.max(np.abs(spec.height_mm - mask.height_mm)) < 1e-3 * scale
    with pytest.raises(TirdeflectError, match="solver='masked'"):
        _solve(u, np.broadcast_to(np.arange(SHAPE[1]) > 3, SHAPE), g, solver="spectral")


def test_the_compiled_edge_data_is_the_numpy_cell_average_to_the_bit(rng):
    # height_masked.edge_data (height_compiled.edge_data_into) against cell_average of g / n along each
    # axis, with no mask, specks and fragments, on grids down to the shortest with a fourth-order edge
    from processing.height import solver_for
    from processing.height_kernels import cell_average
    from processing.height_masked import edge_data

    from types import SimpleNamespace

    g = _tir(camera_distance_mm=600.0)  # n varies across the grid
    solvers = [solver_for(g, np.arange(shape[0]) * 3.7 + 2, np.arange(shape[1]) * 3.3 + 2,
                          (4 * shape[0] + 4, 4 * shape[1] + 4)) for shape in ((61, 40), (37, 53))]
    # and axes too short for a solver's reference region: 4 samples (one fourth-order edge), 3 (none)
    solvers += [SimpleNamespace(null=np.exp(rng.random(shape)), shape=shape) for shape in ((30, 4), (3, 30))]
    for s in solvers:
        shape = s.shape
        gr, gc = rng.standard_normal((2, *shape))
        for valid in (None, rng.random(shape) >= 0.05, rng.random(shape) >= 0.5):
            ec, er = edge_data(s, gr, gc, valid)
            np.testing.assert_array_equal(er, cell_average(gr / s.null, 0, valid))
            np.testing.assert_array_equal(ec, cell_average(gc / s.null, 1, valid))


@pytest.mark.parametrize("camera_distance_mm", [None, 600.0])  # telecentric, finite distance (the dk terms)
def test_the_compiled_masked_operator_is_the_numpy_one_to_the_bit(camera_distance_mm, rng):
    # the masked solve's CG operator (height_compiled.masked_normal_apply) against the NumPy
    # operators it replaced (apply_A, the edge weights, apply_AT, the sample weights)
    from processing.height import solver_for
    from processing.height_compiled import masked_normal_apply
    from processing.height_masked import apply_AT

    def apply_A(solver, f):  # the edge operator as NumPy, the form the compiled one replaced
        dr, dc = solver.grid.dr, solver.grid.dc
        ac = np.diff(f, axis=1) / dc
        ar = np.diff(f, axis=0) / dr
        if solver.dk_c is not None:
            ac += (solver.dk_c * 0.5 * (f[:, 1:] + f[:, :-1])).astype(ac.dtype, copy=False)
            ar += (solver.dk_r * 0.5 * (f[1:, :] + f[:-1, :])).astype(ar.dtype, copy=False)
        return ac, ar

    f32 = np.float32
    g = _tir(camera_distance_mm=camera_distance_mm)
    for shape in ((61, 40), (37, 53)):
        # spacings whose reciprocal is not exact in float32 (a division written as a product shows)
        s = solver_for(g, np.arange(shape[0]) * 3.7 + 2, np.arange(shape[1]) * 3.3 + 2,
                       (4 * shape[0] + 4, 4 * shape[1] + 4))
        assert (s.dk_c is None) == (camera_distance_mm is None)
        no_dk = np.zeros((0, 0))
        dk_c, dk_r = (no_dk, no_dk) if s.dk_c is None else (s.dk_c, s.dk_r)
        for invalid_share in (0.0, 0.05, 0.5):  # all valid, specks, fragments
            v = rng.random(shape) >= invalid_share
            wc = (v[:, 1:] & v[:, :-1]).astype(f32)
            wr = (v[1:, :] & v[:-1, :]).astype(f32)
            x = rng.standard_normal(shape).astype(f32)
            ac, ar = apply_A(s, x)
            want = apply_AT(s, ac * wc, ar * wr) * v.astype(f32)
            got = np.empty(shape, f32)
            masked_normal_apply(x, wc, wr, v.astype(f32), f32(s.grid.dc), f32(s.grid.dr), dk_c, dk_r,
                                np.zeros((shape[0], shape[1] + 1), f32), np.zeros((shape[0] + 1, shape[1]), f32), got)
            assert got.dtype == want.dtype
            np.testing.assert_array_equal(got, want)


def test_unreferenced_pieces_are_invalid_and_an_empty_reference_falls_back_or_refuses():
    g = _tir()
    X, Y = _xy(g)
    h = BUMP.height(X, Y)
    u = _paper_u(h, *BUMP.gradient(X, Y), g)
    rr, cc = np.mgrid[: SHAPE[0], : SHAPE[1]]
    ring = (np.hypot(rr - 96, cc - 104) > 30) & (np.hypot(rr - 96, cc - 104) < 34)
    res = _solve(u, ~ring, g)
    island = np.hypot(rr - 96, cc - 104) <= 30  # cut off from the border band: offset unknown
    assert not res.valid[island].any() and np.isnan(res.height_mm[island]).all()
    assert _rel_rms(res.height_mm, h, res.valid) < 1e-3
    assert res.pin.rule == "region" and res.pin.used_samples == res.pin.valid_samples
    assert res.pin.unpinned_fraction == pytest.approx(island.sum() / (~ring).sum(), rel=1e-6)
    band = g.reference_mask(*_grid(), SHAPE)
    # the border band holds no valid sample: the documented fallback pins on the
    # valid samples nearest it, and says so
    res = _solve(u, ~band, g)
    assert res.pin.rule == "nearest" and res.pin.valid_samples == 0 and not res.pin.ok
    assert res.pin.used_samples >= res.pin.needed >= 16
    nearest = res.pin_samples
    assert not (nearest & band).any() and res.valid[nearest].all()
    # the nearest samples hug the band: every valid sample nearer than the
    # farthest one used is used (a quarter of the band's count: its first rings)
    from scipy import ndimage

    dist = ndimage.distance_transform_edt(~band)
    cut = dist[nearest].max()
    assert cut <= 3.0 and np.array_equal(nearest, ~band & (dist <= cut))
    # the offset is measured there (the null mode varies by < 1 % across the ring)
    assert abs(float(np.mean(res.height_mm[nearest]))) < 0.01 * np.abs(h).max()
    with pytest.raises(GeometryError, match=f"0 valid samples.*needs {res.pin.needed}"):
        _solve(u, ~band, g, pin_fallback="refuse")


def test_decimated_grid():
    g = _tir()
    shape = (256, 256)
    surf = GaussianBump(0.005, 3.0, 1.0, -1.0)
    r, c = _grid(shape)
    u, _ = true_displacement(surf, g, shape)
    ht = true_height(surf, g, shape)
    rs, cs = np.arange(3, 256, 4, dtype=float), np.arange(1, 256, 4, dtype=float)
    res = surface_from_displacement(u[:, 3::4, 1::4], None, g, rows_px=rs, cols_px=cs, frame_shape=shape)
    assert res.height_mm.shape == (64, 64)
    assert res.x_mm == pytest.approx((cs - 127.5) * 0.1)
    assert res.y_mm == pytest.approx((rs - 127.5) * 0.1 / math.cos(g.theta))
    assert _rel_rms(res.height_mm, ht[3::4, 1::4]) < 0.005
    with pytest.raises(ShapeMismatchError, match="evenly spaced"):
        surface_from_displacement(u[:, :3, :3], None, g, rows_px=[0, 1, 3], cols_px=[0, 1, 2], frame_shape=shape)
    with pytest.raises(ShapeMismatchError, match="displacement_px must have shape"):
        surface_from_displacement(u, None, g, rows_px=rs, cols_px=cs, frame_shape=shape)


@pytest.mark.parametrize("rows_toward_camera", [False, True])
def test_ray_traced_telecentric(rows_toward_camera):
    g = _tir(rows_toward_camera=rows_toward_camera)
    u, lost = true_displacement(BUMP, g, SHAPE)
    res = _solve(u.astype(np.float32), None, g)
    assert _rel_rms(res.height_mm, true_height(BUMP, g, SHAPE)) < 0.01


@pytest.mark.parametrize("rows_toward_camera", [False, True])
def test_ray_traced_finite_camera_distance(rows_toward_camera):
    """Camera at 1.5 m, theta 60 deg: two magnifications and a varying theta -> <= 3 %."""
    g = _tir(theta_deg=60.0, camera_distance_mm=1500.0, rows_toward_camera=rows_toward_camera)
    u, _ = true_displacement(BUMP, g, SHAPE)
    ht = true_height(BUMP, g, SHAPE)
    res = _solve(u, None, g)
    assert _rel_rms(res.height_mm, ht) < 0.03
    assert res.surface_xy_mm.shape == (2, *SHAPE)
    # the same displacement read as if telecentric is far off: the test can fail
    tele = _solve(u, None, _tir(theta_deg=60.0, rows_toward_camera=rows_toward_camera))
    assert _rel_rms(tele.height_mm, ht) > 0.1
    # and with a masked hole (variable-coefficient masked solver)
    rr, cc = np.mgrid[: SHAPE[0], : SHAPE[1]]
    hole = np.hypot(rr - 60, cc - 150) < 15
    u2 = u.copy()
    u2[:, hole] = 99.0
    res2 = _solve(u2, ~hole, g)
    assert _rel_rms(res2.height_mm, ht, ~hole) < 0.03


@pytest.mark.parametrize("distance", [None, 800.0])
def test_fsss_through_layer_stack(distance):
    """Refraction through air / glass / water (README setup) -> heights within 1.5 %."""
    g = Geometry(setup="fsss", pixel_mm=0.207, fsss_layers=((57.0, 1.0003), (12.0, 1.48899), (43.0, 1.34)),
                 n_water=1.34, fsss_camera_distance_mm=distance)
    surf = GaussianBump(0.02, 4.0, 2.0, -3.0)
    shape = (160, 176)
    u, lost = true_displacement(surf, g, shape)
    assert not lost.any() and np.nanmax(np.abs(u)) > 0.3  # a measurable displacement
    res = _solve(u, None, g, shape=shape)
    ht = true_height(surf, g, shape)
    assert _rel_rms(res.height_mm, ht) < 0.015
    X, Y = np.meshgrid(res.x_mm, res.y_mm)
    hx, hy = surf.gradient(X, Y)
    assert np.max(np.abs(res.slope_x - hx)) < 0.03 * np.abs(hx).max()


def test_solver_object_reuse_and_errors():
    g = _tir()
    r, c = _grid((64, 64))
    s = HeightSolver(g, r, c, (64, 64))
    zero = s.solve(np.zeros((2, 64, 64), np.float32))
    assert np.all(zero.height_mm == 0)
    with pytest.raises(GeometryError, match=r"reference_region \[10, 11, 10, 11\] contains no sample"):
        HeightSolver(_tir(reference_region=(10, 11, 10, 11)), r[::4], c[::4], (64, 64))
    with pytest.raises(TirdeflectError, match="solver must be"):
        s.solve(np.zeros((2, 64, 64)), solver="fast")


def test_fsss_off_axis_rays_are_oblique():
    """Wide field (200 mm at 0.8 m): a bump 100 mm off-axis, seen 7 deg obliquely.

    One central scale (Moisy's constant h*) would misread it by 2.7 %; the per-pixel refraction model
    keeps it within 0.3 %."""
    g = Geometry(setup="fsss", pixel_mm=1.6, fsss_layers=((57.0, 1.0003), (12.0, 1.48899), (43.0, 1.34)),
                 n_water=1.34, fsss_camera_distance_mm=800.0, reference_region=(0, 20, 0, 20))
    shape = (128, 128)
    surf = GaussianBump(0.05, 12.0, 70.0, 70.0)
    u, _ = true_displacement(surf, g, shape)
    ht = true_height(surf, g, shape)
    res = _solve(u, None, g, shape=shape)
    bump = np.abs(ht) > 0.01 * np.abs(ht).max()
    assert _rel_rms(res.height_mm, ht, bump) < 0.003


def test_concurrent_solves_agree_with_serial():
    """The GUI thread and the processing worker share the solver cache."""
    import threading

    g = _tir(theta_deg=58.0)
    X, Y = _xy(g)
    u = _paper_u(BUMP.height(X, Y), *BUMP.gradient(X, Y), g)
    grids = [(slice(None), slice(None)), (slice(1, None, 2), slice(0, None, 2)), (slice(0, None, 3), slice(2, None, 3))]
    r, c = _grid()
    serial = [
        surface_from_displacement(u[:, a, b], None, g, rows_px=r[a], cols_px=c[b], frame_shape=SHAPE).height_mm
        for a, b in grids
    ]
    from processing import height as hmod

    with hmod._CACHE_LOCK:
        hmod._CACHE.clear()
    out, errors = {}, []

    def work(i):
        try:
            a, b = grids[i % 3]
            out[i] = surface_from_displacement(u[:, a, b], None, g, rows_px=r[a], cols_px=c[b], frame_shape=SHAPE)
        except Exception as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(i,)) for i in range(9)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert not errors and len(out) == 9
    for i, res in out.items():
        np.testing.assert_array_equal(res.height_mm, serial[i % 3])
