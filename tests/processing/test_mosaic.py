"""A 2 x 2 mosaic of pixel gains (processing.mosaic): a colour camera read raw is equalised, and
nothing else is taken for one (boards, random dots, stuck pixels, the real cameras of the tests' data)."""

import numpy as np
import pytest

from processing import forward as F
from processing.geometry import Geometry
from processing.mosaic import equalise_mosaic, mosaic_maps, mosaic_response
from processing.reconstruct import Reconstructor

G55 = Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False)


def _mosaic(image, gains, black=(0.0, 0.0, 0.0, 0.0)):
    out = np.asarray(image, np.float64).copy()
    for k, (i, j) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
        out[i::2, j::2] = out[i::2, j::2] * gains[k] + black[k]
    return out


def test_a_raw_colour_mosaic_is_found_and_equalised_to_the_monochrome_heights():
    # ray-traced 256^2, 12 bit: the mosaic (Bayer under white light, other black levels) left as it was
    # took the bump from 0.13 to 14 % (its bright sub-grid taken for 4,300 stuck pixels); equalised,
    # the heights are the monochrome camera's
    from benchmarks.bench_processing import rel_height_error

    bump = F.GaussianBump(0.004, 3.0)
    board = F.Checkerboard(period_mm=2.0, edge_softness_mm=0.1)
    ref, _ = F.render_tir(F.FlatSurface(), G55, (256, 256), board, supersample=2)
    img, _ = F.render_tir(bump, G55, (256, 256), board, supersample=2)
    rng = np.random.default_rng(0)
    mono_ref, mono_img = (F.quantize(a, bits=12, noise_rms=2, rng=rng) for a in (ref, img))
    gains, black = (1.0, 0.6, 0.6, 0.4), (0.0, 64.0, 64.0, 0.0)
    raw_ref, raw_img = (np.rint(_mosaic(a, gains, black)).astype(np.uint16) for a in (mono_ref, mono_img))
    found = mosaic_response(raw_ref)
    assert found is not None and mosaic_response(mono_ref) is None
    np.testing.assert_allclose(found.gains().ravel(), np.array(gains) / np.mean(gains), atol=0.02)
    mono = Reconstructor(mono_ref, G55)
    raw = Reconstructor(raw_ref, G55)
    assert raw.mosaic is not None and raw.defects.size == 0 and mono.mosaic is None
    err_mono, err_raw = rel_height_error(mono(mono_img), bump, G55), rel_height_error(raw(raw_img), bump, G55)
    assert err_raw == pytest.approx(err_mono, abs=0.02)  # percentage points
    # the equalised reference is the monochrome one up to one common affine map of its grey levels
    eq = equalise_mosaic(raw_ref, mosaic_maps(found, raw_ref.shape))
    fit = np.polyfit(mono_ref.ravel().astype(np.float64), eq.ravel().astype(np.float64), 1)
    assert np.std(eq - np.polyval(fit, mono_ref)) < 3.0  # grey levels: the noise and rounding, not the mosaic


def test_nothing_else_is_taken_for_a_mosaic():
    rng = np.random.default_rng(1)
    board = F.Checkerboard(period_mm=0.3, edge_softness_mm=0.02)  # 3 px: the finest board
    for pattern in (board, F.RandomDots(dot_diameter_mm=0.5, density=0.3, seed=2)):
        ref, _ = F.render_tir(F.FlatSurface(), G55, (128, 128), pattern, supersample=2)
        assert mosaic_response(F.quantize(ref, bits=8, noise_rms=0.5, rng=rng)) is None
    # stuck pixels at 65535 in a 12-bit reference raise one sub-grid's standard deviation, not its range
    ref, _ = F.render_tir(F.FlatSurface(), G55, (256, 256), F.Checkerboard(period_mm=2.0), supersample=2)
    stuck = F.quantize(ref, bits=12).astype(np.uint16)
    stuck.flat[rng.choice(stuck.size, 20, replace=False)] = 65535
    assert mosaic_response(stuck) is None
    # alternate rows 10 % apart (a sensor's two read-outs; the tests' real cameras: 3 %) stay as they are
    assert mosaic_response(_mosaic(F.quantize(ref, bits=12), (1.0, 1.0, 1.1, 1.1))) is None
    assert equalise_mosaic(stuck, None) is stuck


def test_the_real_cameras_of_the_tests_data_show_no_mosaic():
    from tests.datapaths import DATA

    from app.files import imageio

    paths = sorted(p for p in DATA.rglob("*") if p.suffix in (".tif", ".png", ".bmp"))
    assert len(paths) >= 5
    for p in paths:
        assert mosaic_response(imageio.read_image(p)) is None, p
