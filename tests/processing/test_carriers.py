"""Carrier search: sub-bin periods, rotation, theta from the aspect, refusals."""

import math

import cv2
import numpy as np
import pytest
import tifffile

from processing.carriers import (
    BOARD_PERIOD_TOLERANCE,
    check_pattern_match,
    find_carriers,
    rotation_from_carriers,
    theta_from_carriers,
)
from processing.errors import NoCarrierError, PatternMismatchError
from tests.datapaths import NEEDLE, TRAPPED


def board(shape, period_px, rotation_deg=0.0, aspect=1.0, soft=3.0):
    """Soft checkerboard with square period ``period_px`` along its edges,
    rows compressed by ``aspect`` (cos theta of a telecentric view)."""
    r, c = np.mgrid[: shape[0], : shape[1]].astype(float)
    y = r / aspect
    t = math.radians(rotation_deg)
    u = c * math.cos(t) + y * math.sin(t)
    v = -c * math.sin(t) + y * math.cos(t)
    k = 2 * np.pi / period_px
    return (0.5 + 0.4 * np.tanh(soft * np.sin(k * u) * np.sin(k * v))).astype(np.float32)


@pytest.mark.parametrize("period_px,rotation_deg", [(16.0, 0.0), (13.7, 7.0), (11.3, -20.0)])
def test_periods_and_rotation_sub_bin(period_px, rotation_deg):
    c = find_carriers(board((256, 256), period_px, rotation_deg))
    # diagonal carriers of a board with edge period p have period p / sqrt(2)
    np.testing.assert_allclose(c.periods_px, period_px / math.sqrt(2), rtol=2e-4)
    assert abs(c.rotation_deg - rotation_deg) < 0.05
    # a nearest-bin estimate would be off by up to 0.5 bin in ~25: 2 %; sub-bin is 100x better
    assert np.all(c.contrast > 100)


@pytest.mark.parametrize("theta_deg", [55.0, 62.0, 70.0])
@pytest.mark.parametrize("rotation_deg", [0.0, 12.0, 30.0, 45.0])
def test_theta_from_aspect_of_square_board(theta_deg, rotation_deg):
    c = find_carriers(board((256, 256), 18.0, rotation_deg, aspect=math.cos(math.radians(theta_deg))))
    assert abs(c.theta_deg - theta_deg) < 0.3


def test_surface_rotation_undoes_the_compression():
    c = find_carriers(board((256, 256), 18.0, 30.0, aspect=math.cos(math.radians(60))))
    assert abs(c.surface_rotation_deg(60.0) - 30.0) < 0.2
    assert abs(c.surface_rotation_deg() - 30.0) < 0.3  # with the estimated theta
    assert abs(c.rotation_deg - 30.0) > 5  # in the image the compression bends it


def test_theta_from_ray_traced_reference():
    from processing import forward as F
    from processing.geometry import Geometry

    g = Geometry(theta_deg=58, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False)
    ref, _ = F.render_tir(F.FlatSurface(), g, (256, 256), F.Checkerboard(period_mm=2.0, edge_softness_mm=0.1, rotation_deg=10))
    assert abs(find_carriers(ref).theta_deg - 58.0) < 0.3


def test_theta_helpers_degenerate():
    assert math.isnan(theta_from_carriers([[0.1, 0.0], [0.2, 0.0]]))  # collinear
    assert rotation_from_carriers([[0.05, 0.05], [-0.05, 0.05]]) == pytest.approx(0.0)


@pytest.mark.parametrize("name", ["flat", "noise", "ramp", "grating"])
def test_no_carrier_refused(name):
    rng = np.random.default_rng(0)
    r, c = np.mgrid[:256, :256].astype(float)
    image = {
        "flat": np.full((256, 256), 100.0),
        "noise": rng.normal(100, 10, (256, 256)),
        "ramp": r + 2 * c,
        "grating": 100 + 50 * np.sin(2 * np.pi * c / 9.0),
    }[name]
    with pytest.raises(NoCarrierError, match="check") as info:
        find_carriers(image)
    if name == "flat":  # says what is wrong with the image, not a peak statistic
        assert "uniform" in str(info.value)


def test_a_region_of_interest_too_narrow_for_the_board_says_so():
    """By-hand trial of 7 Dec 2026: a 40 x 256 px strip of a board of 20 px period (2 periods along its rows)
    was refused as "a streak or smear" and, for a reference, "if the water was moving"; the message now says
    which periods were looked for and that the region of interest is too small. A full-size image without a
    pattern does not get that hint; the same board in 128 rows is found."""
    strip = board((40, 256), 20.0)
    with pytest.raises(NoCarrierError) as info:
        find_carriers(strip)
    assert "in a 40 x 256 px image, periods up to 10 px" in str(info.value)
    assert "needs a larger region of interest" in str(info.value)
    with pytest.raises(NoCarrierError) as info:
        find_carriers(np.random.default_rng(1).normal(100, 10, (256, 256)))
    assert "region of interest" not in str(info.value)
    assert find_carriers(board((128, 256), 20.0)).periods_px == pytest.approx([20.0 / math.sqrt(2)] * 2, rel=0.02)


def test_bad_input_messages():
    with pytest.raises(ValueError, match="2-D"):
        find_carriers(np.zeros((4, 64, 64)))
    with pytest.raises(ValueError, match="NaN"):
        find_carriers(np.full((64, 64), np.nan))


def test_real_references_periods():
    needle = cv2.imread(str(NEEDLE / "reference_2.png"), cv2.IMREAD_UNCHANGED)
    c = find_carriers(needle)
    np.testing.assert_allclose(c.periods_px, 9.8, atol=0.1)  # README: about 9.8 px, +-45 deg
    assert np.all(np.abs(np.abs(c.angles_deg) - 45) < 5)
    df = tifffile.imread(TRAPPED / "reference_df.tif")
    np.testing.assert_allclose(find_carriers(df).periods_px, 13.7, atol=0.2)


def test_pattern_mismatch_real_ellipse():
    ref = tifffile.imread(TRAPPED / "reference_df.tif")
    frame = tifffile.imread(TRAPPED / "ellipse_10.tif")
    with pytest.raises(PatternMismatchError, match=r"measured periods 12\.\d+ .* expected periods 13\.\d+"):
        check_pattern_match(find_carriers(ref), frame)


def test_pattern_match_accepts_deformed_real_frame():
    ref = cv2.imread(str(NEEDLE / "reference_2.png"), cv2.IMREAD_UNCHANGED)
    frame = cv2.imread(str(NEEDLE / "202406_1457001661.bmp"), cv2.IMREAD_UNCHANGED)
    found = check_pattern_match(find_carriers(ref), frame)
    assert found is not None


def test_pattern_mismatch_rotated_synthetic():
    ref = board((256, 256), 16.0, 0.0)
    with pytest.raises(PatternMismatchError, match="rotation"):
        check_pattern_match(find_carriers(ref), board((256, 256), 16.0, 6.0))


def test_a_board_magnified_alike_is_said_to_be_a_zoom_or_a_curved_surface_not_only_another_pattern():
    """A frame whose board is the reference's magnified 6.5 % (both periods alike, directions kept): a lens refocused,
    the camera moved along its axis, or a water surface curved over the whole view (by-hand trial of 7 Dec 2026: a 5 um
    bump wider than a 128^2 field, told only "record a new reference"). Refused still (one frame cannot tell a
    curved surface from a zoom), the message names both; so for a board stretched along one axis (what a surface
    curved along the rows does in TIR); a board turned by 6 deg gets no such words."""
    ref = board((256, 256), 16.0, 0.0)
    with pytest.raises(PatternMismatchError, match=r"the same board magnified by 6\.\d %.* a water surface curved "
                                                   r"over the whole view"):
        check_pattern_match(find_carriers(ref), board((256, 256), 16.0 * 1.07, 0.0))
    with pytest.raises(PatternMismatchError, match=r"the same board shrunk by 7\.0 %"):
        check_pattern_match(find_carriers(ref), board((256, 256), 16.0 / 1.07, 0.0))
    with pytest.raises(PatternMismatchError, match=r"the same board magnified by 4\.\d % \(alike, or more along one"):
        check_pattern_match(find_carriers(ref), board((256, 256), 16.0, 0.0, aspect=1.1))
    with pytest.raises(PatternMismatchError) as err:
        check_pattern_match(find_carriers(ref), board((256, 256), 16.0, 6.0))
    assert "same board" not in str(err.value), str(err.value)


@pytest.mark.parametrize("cols", [300, 301])
def test_display_spectrum_keeps_the_carrier_peak_where_it_is(cols):
    """A grating of known frequency peaks at that frequency in the display
    spectrum, after the block-maximum reduction, for odd and even widths."""
    from processing.carriers import display_spectrum

    rows = 280
    f_row, f_col = 0.1, -0.15  # cycles per pixel
    r, c = np.mgrid[:rows, :cols]
    img = np.cos(2 * np.pi * (f_row * r + f_col * c))
    out = display_spectrum(np.abs(np.fft.rfft2(img)), cols, size=64, max_freq=0.25)
    mag = out["log_magnitude"]
    assert mag.shape[0] <= 2 * 64 + 2 and mag.shape[1] <= 2 * 64 + 2
    i, j = np.unravel_index(np.argmax(mag), mag.shape)
    step = abs(out["freq_x"][1] - out["freq_x"][0])
    # the peak and its mirror are equally strong: accept either
    assert any(abs(out["freq_y"][i] - sy * f_row) <= step and abs(out["freq_x"][j] - sy * f_col) <= step
               for sy in (1, -1))


def test_disturbed_surface_carriers_from_local_tiles():
    """Waves smear the whole image's carrier peaks (the isolation test calls it a streak); the median of
    local tiles' carriers still gives the undisturbed periods and theta."""
    from processing import forward
    from processing.carriers import NoCarrierError, find_carriers_live, find_carriers_local
    from processing.geometry import Geometry

    shape = (512, 512)
    g = Geometry(theta_deg=55.0, depth_mm=300.0, pixel_mm=40.0 / 512, rows_toward_camera=False)
    board = forward.Checkerboard(period_mm=12 * g.pixel_mm, edge_softness_mm=g.pixel_mm)
    k = 2 * np.pi / 20.0  # a 20 mm gravity-capillary wave, 0.5 um: |u| up to 3 px on a 6-px pattern
    waves = forward.WaveField(((0.0005, k * 0.88, k * 0.48, 0.3), (0.00035, -0.5 * k, 1.3 * k, 1.1)))
    rng = np.random.default_rng(5)
    flat = forward.quantize(forward.render_tir(forward.FlatSurface(), g, shape, board)[0], bits=8,
                            noise_rms=0.5, rng=rng)
    frame = forward.quantize(forward.render_tir(waves, g, shape, board)[0], bits=8, noise_rms=0.5, rng=rng)
    still = find_carriers(flat)
    with pytest.raises(NoCarrierError, match="streak or smear"):
        find_carriers(frame)  # the root cause of "NOT READY ... streak or smear" on moving water
    c, disturbed = find_carriers_live(frame)
    assert disturbed
    # within 1 %: below the 1.5 % at which the GUI says "the pattern or the camera moved since the reference"
    np.testing.assert_allclose(np.sort(c.periods_px), np.sort(still.periods_px), rtol=0.01)
    # theta within a third of the 1 deg the GUI flags; rotation within its 0.5 deg flag
    assert abs(c.theta_deg - 55.0) < 0.33 and abs(c.rotation_deg - still.rotation_deg) < 0.5
    assert find_carriers_live(flat)[1] is False  # still water: the whole image, not tiles
    noise = np.random.default_rng(3).normal(100.0, 10.0, (512, 512))
    with pytest.raises(NoCarrierError):
        find_carriers_local(noise)


def _board(period_mm, rotation_deg, stretch_y, softness_mm):
    """A checkerboard of ``period_mm`` along its x, ``stretch_y`` times that along its y, turned by
    ``rotation_deg`` on the pattern plane (a printed board laid down at an angle)."""
    from processing import forward

    square = forward.Checkerboard(period_mm=period_mm, edge_softness_mm=softness_mm)
    c, s = math.cos(math.radians(rotation_deg)), math.sin(math.radians(rotation_deg))
    return lambda x, y: square(c * np.asarray(x) + s * np.asarray(y), (-s * np.asarray(x) + c * np.asarray(y)) / stretch_y)


@pytest.mark.parametrize("camera", [{}, {"camera_distance_mm": 3000.0},
                                    {"camera_distance_mm": 2000.0, "rows_toward_camera": True}])
@pytest.mark.parametrize("rotation_deg, stretch_y", [(0, 1.0), (9, 1.0), (0, 1 / math.cos(math.radians(55))),
                                                     (20, 1.3)])
def test_the_board_period_is_measured_through_the_geometry(camera, rotation_deg, stretch_y):
    # ray-traced references of a 1.2 mm board, telecentric and pinhole cameras, turned and stretched
    # boards: the carriers give the printed period back (a printer's scale is good to ~0.5 %)
    from processing import Geometry, forward

    geometry = Geometry.from_dict({"setup": "tir", "theta_deg": 55.0, "depth_mm": 300.0, "pixel_mm": 0.1,
                                   "rows_toward_camera": False, **camera,
                                   **({} if stretch_y == 1 else {"pattern_stretch_y": stretch_y})})
    image, _ = forward.render_tir(forward.FlatSurface(), geometry, (384, 384),
                                  _board(1.2, rotation_deg, stretch_y, 0.1), supersample=2)
    freq = find_carriers(image).freq
    assert geometry.board_period_mm(freq, image.shape) == pytest.approx(1.2, rel=0.002)
    # theta 2 deg off moves it by less than the check's tolerance; pixel_mm 5 % off by 5 %
    for theta in (53.0, 57.0):
        off = Geometry.from_dict({**geometry.to_dict(), "theta_deg": theta}).board_period_mm(freq, image.shape)
        assert 0.01 < abs(off / 1.2 - 1) < BOARD_PERIOD_TOLERANCE
    wrong = Geometry.from_dict({**geometry.to_dict(), "pixel_mm": 0.105})
    assert wrong.board_period_mm(freq, image.shape) == pytest.approx(1.26, rel=0.002)


@pytest.mark.parametrize("distance", [None, 800.0])
def test_the_board_period_is_measured_through_an_fsss_geometry(distance):
    # free-surface synthetic schlieren: the pattern is seen through the layers (an apparent depth),
    # telecentric and pinhole; the same measure gives the printed 3 mm board back
    from processing import Geometry, forward

    d = {"setup": "fsss", "pixel_mm": 0.207, "n_water": 1.34, "n_air": 1.0003,
         "fsss_layers": [[57.0, 1.0003], [12.0, 1.48899], [43.0, 1.34]]}
    geometry = Geometry.from_dict(d if distance is None else {**d, "fsss_camera_distance_mm": distance})
    image, _ = forward.render(forward.FlatSurface(), geometry, (384, 384),
                              forward.Checkerboard(period_mm=3.0, edge_softness_mm=0.2))
    assert geometry.board_period_mm(find_carriers(image).freq, image.shape) == pytest.approx(3.0, rel=0.002)


def test_a_wrong_pixel_size_is_refused_once_the_board_period_is_given():
    # a wrong pixel_mm scales the heights by its square and nothing in the frames shows it; with
    # pattern_period_mm the reference's carriers do
    from processing import Geometry, Reconstructor, forward
    from processing.errors import GeometryError

    right = Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False)
    bump = forward.GaussianBump(0.004, 4.0)
    ref, _ = forward.render_tir(forward.FlatSurface(), right, (256, 256), _board(1.2, 0, 1.0, 0.1), supersample=2)
    frame, _ = forward.render_tir(bump, right, (256, 256), _board(1.2, 0, 1.0, 0.1), supersample=2)
    rms = {}
    for pixel_mm in (0.1, 0.15):
        g = Geometry.from_dict({**right.to_dict(), "pixel_mm": pixel_mm})
        rms[pixel_mm] = float(np.sqrt(np.nanmean(Reconstructor(ref, g)(frame).height ** 2)))
        checked = Geometry.from_dict({**g.to_dict(), "pattern_period_mm": 1.2})
        if pixel_mm == 0.1:
            Reconstructor(ref, checked)  # the right one passes
        else:
            with pytest.raises(GeometryError) as err:
                Reconstructor(ref, checked)
            msg = str(err.value)
            assert "pattern_period_mm = 1.2" in msg and "1.8 mm" in msg and "pixel_mm = 0.1 (the rest kept)" in msg
            assert "125 % off" in msg  # 1.5^2 - 1
    assert rms[0.15] / rms[0.1] == pytest.approx(1.5 ** 2, rel=0.05)  # what the message says


@pytest.mark.parametrize("board_stretch, declared, told", [
    (1 / math.cos(math.radians(55)), None, "set pattern_stretch_y = 1.74"),  # what `pattern --suggest` prints
    (1 / 1.5, None, "set pattern_stretch_y = 0.667"),  # rectangles, longer along x
    (1.0, 1 / math.cos(math.radians(55)), "set pattern_stretch_y = 1 "),  # a square board declared stretched
])
def test_a_board_of_another_shape_than_declared_is_told_its_shape_not_a_pixel_size(board_stretch, declared, told):
    """By-hand trial of 7 Dec 2026: a board whose cells are not of the shape pattern_stretch_y says failed the
    period check with "pixel_mm should be 0.08152"; with that pixel_mm the heights were 34 % off, exit 0. The
    refusal now names the cells' shape through the geometry and the pattern_stretch_y (or theta) to set, and no
    pixel_mm; with the shape declared, the same board passes and its aspect is the one declared."""
    from processing import Geometry, Reconstructor, forward
    from processing.errors import GeometryError

    base = {**Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False).to_dict(),
            "pattern_period_mm": 2.0}
    board = forward.Checkerboard(period_mm=2.0, edge_softness_mm=0.1, stretch_y=board_stretch)
    g = Geometry.from_dict(base if declared is None else {**base, "pattern_stretch_y": declared})
    ref, _ = forward.render_tir(forward.FlatSurface(), g, (256, 256), board, supersample=2)
    with pytest.raises(GeometryError) as err:
        Reconstructor(ref, g)
    msg = str(err.value)
    assert "is not the board the geometry describes" in msg and told in msg and "pixel_mm should be" not in msg, msg
    right = Geometry.from_dict({**base, "pattern_stretch_y": board_stretch})
    assert right.board_cell_aspect(find_carriers(ref).freq, ref.shape) == pytest.approx(board_stretch, rel=0.01)
    Reconstructor(ref, right)  # declared as it is: passes


def test_crossed_cosines_told_as_a_period_sqrt2_off_keep_their_pixel_size():
    """Crossed cosines of period P along x and y are a checkerboard of P sqrt(2) turned by 45 deg: with
    pattern_period_mm = P the check said "pixel_mm should be 0.07071" (by-hand trial of 7 Dec 2026)."""
    from processing import Geometry, Reconstructor, forward
    from processing.errors import GeometryError

    g = Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False, pattern_period_mm=2.0)
    ref, _ = forward.render_tir(forward.FlatSurface(), g, (256, 256), forward.CrossedCosines(2.0), supersample=2)
    with pytest.raises(GeometryError, match=r"sqrt\(2\) apart: if the pattern is crossed lines or cosines along x "
                                            r"and y, keep pixel_mm and set pattern_period_mm = 2\.8"):
        Reconstructor(ref, g)


@pytest.mark.parametrize("n", [160, 192, 200, 256])
@pytest.mark.parametrize("softness_px", [0.5, 1.0])
def test_a_sharp_board_gives_its_fundamental_whatever_the_frame_size(n, softness_px):
    # a sharp 20 px checkerboard at 192^2 (9.6 bins a carrier): the carriers ranked by how far they stand
    # above their ring were all harmonics and their leakage, and the (1, 5) harmonic, 3.9 px, won
    r, c = np.mgrid[:n, :n].astype(float)
    k = 2 * np.pi / 20
    eps = k * softness_px / 2
    board = (0.5 + 0.4 * np.tanh(np.sin(k * c) / eps) * np.tanh(np.sin(k * r) / eps)) * 255
    found = find_carriers(board.astype(np.uint8))
    np.testing.assert_allclose(found.periods_px, 20 / math.sqrt(2), rtol=0.002)


def test_a_long_period_board_gives_its_fundamental_not_a_harmonic():
    """By-hand trial of 7 Dec 2026: a board of 60 px period at 256^2 (about 4 periods across, rows compressed
    at theta 55 deg): its two fundamentals lie 8.5 bins apart, each within the other's isolation ring, so each
    stood only 3.1x above it and the (1, 3) harmonic (17.3 px) was taken: with pattern_period_mm the reference
    was refused blaming pixel_mm, without it a bump came out 13.7 % off in silence. The ring's third-largest
    bin is the measure now; streaks and ridges stay refused (test_no_carrier_refused)."""
    from processing import Geometry, forward

    g = Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False, pattern_period_mm=6.0)
    ref, _ = forward.render_tir(forward.FlatSurface(), g, (256, 256),
                                forward.Checkerboard(period_mm=6.0, edge_softness_mm=0.1), supersample=2)
    found = find_carriers(forward.quantize(ref, bits=8))
    expected = 1.0 / math.hypot(1.0 / (60.0 * math.cos(math.radians(55))), 1.0 / 60.0)  # px: 29.9, the diagonal
    np.testing.assert_allclose(found.periods_px, expected, rtol=0.01)
    assert g.board_period_mm(found.freq, ref.shape) == pytest.approx(6.0, rel=0.01)
