"""Bands of light along the rows (processing.banding): a rolling shutter under flickering light is
named, and nothing else is taken for it (surfaces, objects in part of the view, the real frames)."""

import numpy as np
import pytest

from processing import forward as F
from processing.banding import light_bands, row_profile
from processing.geometry import Geometry

G55 = Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False)


def _bands(image, depth, period_rows=64, phase=0):
    rows = np.arange(image.shape[0])[:, None]
    return image * (1.0 - depth * (np.sin(2 * np.pi * (rows + phase) / period_rows) < 0))


@pytest.fixture(scope="module")
def frames():
    board = F.Checkerboard(period_mm=2.0, edge_softness_mm=0.1)
    ref, _ = F.render_tir(F.FlatSurface(), G55, (256, 256), board, supersample=2)
    waves = F.WaveField.random(6, amplitude_rms_mm=0.001, wavelength_range_mm=(12, 30), seed=11)
    img, _ = F.render_tir(waves, G55, (256, 256), board, supersample=2)
    return ref * 4000, img * 4000


def test_bands_of_light_along_the_rows_are_named(frames):
    # sharp bands 30 % and 15 % darker every 32 rows (a rolling shutter under PWM-dimmed LEDs; 30 %:
    # simulate's bump and waves 0.05 / 0.20 -> about 2 % rel. RMS), over waves filling the frame (10 %:
    # agreement 0.70 here at 256^2, 0.80-0.96 at 512^2)
    ref, img = frames
    clean = light_bands(row_profile(img), row_profile(ref))
    assert not clean.flagged and clean.depth < 0.01
    for depth in (0.3, 0.15):
        found = light_bands(row_profile(_bands(img, depth, phase=17)), row_profile(ref))
        assert found.flagged and found.agreement > 0.75, found
        assert 0.3 * depth < found.depth < 0.7 * depth  # the RMS of a square wave of that depth: half of it
        assert "rolling shutter under light that flickers" in found.describe()
    # a reference taken under the bands, frames without them: the same, the other way round
    assert light_bands(row_profile(img), row_profile(_bands(ref, 0.3))).flagged


def test_what_lies_in_part_of_the_width_or_changes_slowly_is_not_taken_for_bands(frames):
    ref, img = frames
    cols = np.arange(img.shape[1])[None, :]
    rows = np.arange(img.shape[0])[:, None]
    for changed in (img * np.where(cols < 128, 0.5, 1.0),  # a shadow over the left half of every row
                    img * (0.8 + 0.3 * rows / img.shape[0]),  # light falling off along the columns
                    np.where((rows - 128) ** 2 + (cols - 128) ** 2 < 60 ** 2, 0.2 * img, img)):  # a dark disc
        assert not light_bands(row_profile(changed), row_profile(ref)).flagged


def test_the_real_frames_of_the_tests_data_show_no_bands():
    from app.files import imageio
    from tests.datapaths import NEEDLE, TRAPPED

    pairs = [(NEEDLE / "reference_2.png", NEEDLE / "202406_1457001661.bmp"),
             (TRAPPED / "prueba1_20250317_122608_C1S0001000001.tif", TRAPPED / "prueba1_20250317_122608_C1S0001000211.tif"),
             (TRAPPED / "reference_df.tif", TRAPPED / "0_5mm_circular_100ms_20250529_141304_C1S0001000001.tif"),
             (TRAPPED / "reference_df.tif", TRAPPED / "ellipse_10.tif")]  # a floating ring, an ellipse in view
    for ref, frame in pairs:
        found = light_bands(row_profile(imageio.read_image(frame)), row_profile(imageio.read_image(ref)))
        assert not found.flagged, (frame.name, found)


def test_the_row_medians_are_numpys_to_the_bit():
    """light_bands takes its row medians by sorting (5x faster than np.median's partitions on rows of a few
    dozen values, so that the live window can judge frames): the same numbers, odd and even widths."""
    from processing.banding import _median_of_rows

    rng = np.random.default_rng(5)
    for cols in (1, 2, 3, 4, 15, 16, 17, 33):
        a = rng.normal(1.0, 0.2, size=(300, cols))
        a[::7] = np.round(a[::7], 1)  # ties
        np.testing.assert_array_equal(_median_of_rows(a), np.median(a, axis=1))


def test_a_frame_of_another_size_is_not_judged(frames):
    """The live window judges a frame before the reconstructor measures it: a frame of another size (the
    ROI changed before the reference followed) is left to the reconstructor's own shape message."""
    from processing.banding import frame_light_bands, reference_light

    ref, img = frames
    assert frame_light_bands(img, reference_light(ref)) is not None
    assert frame_light_bands(img[:200], reference_light(ref)) is None
    assert frame_light_bands(img, None) is None


def test_a_clipped_frame_or_reference_is_not_taken_for_bands():
    """A checkerboard clipped in the frame or the reference (over-exposed: its bright squares flat) changes
    each row's mean with the row's place on the board, alike across the width: simulate's bump read as
    bands 2-7 % deep from 35 % of the pixels clipped on, and evened out, its heights' error doubled
    (frames 1.6x 1.46 -> 2.82 %). A clipped frame or reference is not judged (its saturation is named)."""
    from app.batch.simulate import DEFAULT_SIM_GEOMETRY, SIM_PATTERN_PERIOD_PX

    from processing.banding import clipped, frame_light_bands, reference_light
    from processing.live_view import saturation_pct

    geometry = Geometry.from_dict(dict(DEFAULT_SIM_GEOMETRY))
    board = F.Checkerboard(period_mm=SIM_PATTERN_PERIOD_PX * geometry.pixel_mm, edge_softness_mm=geometry.pixel_mm)
    ref, _ = F.render_tir(F.FlatSurface(), geometry, (256, 256), board)
    bump = F.GaussianBump(amplitude_mm=0.004, sigma_mm=2.0, x0_mm=0.0, y0_mm=0.0)
    img, _ = F.render_tir(bump, geometry, (256, 256), board)
    twelve_bit = lambda a: F.quantize(a, bits=12, rng=np.random.default_rng(2))  # noqa: E731
    plain = frame_light_bands(twelve_bit(img), reference_light(twelve_bit(ref)))
    assert plain is not None and not plain.flagged
    for gain_ref, gain_frame in ((1.0, 1.6), (1.3, 1.0)):
        r, f = twelve_bit(np.minimum(ref * gain_ref, 1.0)), twelve_bit(np.minimum(img * gain_frame, 1.0))
        assert max(saturation_pct(r), saturation_pct(f)) > 30 and (clipped(r) or clipped(f))
        assert light_bands(row_profile(f), row_profile(r)).flagged  # what judging them anyway said
        assert frame_light_bands(f, reference_light(r)) is None
    # a few glints are no clipping: still judged
    glints = twelve_bit(img)
    glints.flat[::997] = 4095
    assert not clipped(glints) and frame_light_bands(glints, reference_light(twelve_bit(ref))) is not None


def test_frames_of_another_gamma_are_no_bands_but_bands_under_it_are():
    """Frames whose response is not the reference's (a camera's gamma changed between them) scale the
    board's bright and dark parts apart, which changes each row's mean with its place on the board, alike
    across the width: on simulate's board at 512^2 read as bands 0.02-0.04 deep, and evened out the bump's
    error went 0.11 -> 0.52 / 1.38 % (gamma 0.6 / 1.5). The board's row harmonics (k1 - k2 and its
    multiples) are notched out of the judgement; bands of light keep their depth."""
    from app.batch.simulate import DEFAULT_SIM_GEOMETRY, SIM_PATTERN_PERIOD_PX

    from processing.banding import BANDS_MIN_DEPTH, board_row_frequencies, frame_light_bands, reference_light
    from processing.carriers import find_reference_carriers

    geometry = Geometry.from_dict(dict(DEFAULT_SIM_GEOMETRY))
    board = F.Checkerboard(period_mm=SIM_PATTERN_PERIOD_PX * geometry.pixel_mm, edge_softness_mm=geometry.pixel_mm)
    shape = (512, 512)
    ref = F.quantize(F.render_tir(F.FlatSurface(), geometry, shape, board)[0], bits=12, rng=np.random.default_rng(3))
    bump = F.GaussianBump(amplitude_mm=0.004, sigma_mm=3.0, x0_mm=0.0, y0_mm=0.0)
    img = F.render_tir(bump, geometry, shape, board)[0]
    carriers = find_reference_carriers(ref)
    notch = board_row_frequencies(carriers.freq, shape[1])
    k1_k2 = abs(float(carriers.freq[0, 0] - carriers.freq[1, 0]))  # k1 - k2: along the rows only
    assert min(abs(f - k1_k2) for f in notch) < 1e-5, (notch, k1_k2)
    twelve_bit = lambda a: F.quantize(a, bits=12, rng=np.random.default_rng(4))  # noqa: E731
    for gamma in (0.6, 1.5):
        frame = twelve_bit(img ** gamma)
        assert light_bands(row_profile(frame), row_profile(ref)).flagged  # judged without the notch
        found = frame_light_bands(frame, reference_light(ref), carriers)
        assert not found.flagged and found.depth < BANDS_MIN_DEPTH, (gamma, found)
        for depth in (0.1, 0.3):
            plain = frame_light_bands(twelve_bit(_bands(img, depth, phase=17)), reference_light(ref), carriers)
            under = frame_light_bands(twelve_bit(_bands(img ** gamma, depth, phase=17)), reference_light(ref), carriers)
            assert plain.flagged and under.flagged, (gamma, depth, plain, under)
            assert abs(under.depth - plain.depth) < 0.01 + 0.05 * depth, (gamma, depth, plain, under)


def test_bands_on_a_board_whose_stripes_run_along_the_rows_are_named_not_evened():
    """A board turned about 45 deg against the image (seen as diamonds) has a carrier along the rows: each
    row's gain then holds the pattern's own motion, and evened out a 2 um bump under bands 30 % deep came
    out at 31 % instead of the 5 % the bands cost (256^2). Named, with why it was not evened; a board
    turned 30 deg is still evened."""
    from app.batch.simulate import DEFAULT_SIM_GEOMETRY

    from processing.banding import frame_light_bands, reference_light
    from processing.carriers import find_reference_carriers

    geometry = Geometry.from_dict(dict(DEFAULT_SIM_GEOMETRY))
    bump = F.GaussianBump(amplitude_mm=0.002, sigma_mm=3.2)
    for turn_deg, evenable in ((45.0, False), (43.0, False), (30.0, True), (0.0, True)):
        board = F.Checkerboard(period_mm=20 * geometry.pixel_mm, edge_softness_mm=geometry.pixel_mm,
                               rotation_deg=turn_deg)
        ref = F.quantize(F.render_tir(F.FlatSurface(), geometry, (256, 256), board)[0], bits=12,
                         rng=np.random.default_rng(5))
        img = F.render_tir(bump, geometry, (256, 256), board)[0]
        banded = F.quantize(_bands(img, 0.3, phase=17), bits=12, rng=np.random.default_rng(6))
        found = frame_light_bands(banded, reference_light(ref), find_reference_carriers(ref))
        assert found.flagged and found.evenable == evenable and found.evened == evenable, (turn_deg, found)
        assert ("NOT evened out" in found.describe()) == (not evenable)


def _vignette(shape, corner, kind):
    """Light falling off from the middle to ``corner`` at the corners: cos^4 of the angle off the lens' axis
    (natural vignetting) or a Gaussian."""
    rows, cols = shape
    y, x = np.mgrid[:rows, :cols]
    r2 = (((x - (cols - 1) / 2) / ((cols - 1) / 2)) ** 2 + ((y - (rows - 1) / 2) / ((rows - 1) / 2)) ** 2) / 2
    if kind == "cos4":  # tan^2 of the angle off the axis grows as r^2
        return 1.0 / (1.0 + (np.sqrt(1.0 / corner) - 1.0) * r2) ** 2
    return np.exp(np.log(corner) * r2)


@pytest.fixture(scope="module")
def sim_frames():
    """simulate's board at 256^2, 12 bit: the reference, a 4 um bump's frame without quantisation, carriers."""
    from app.batch.simulate import DEFAULT_SIM_GEOMETRY, SIM_PATTERN_PERIOD_PX
    from processing.carriers import find_reference_carriers

    geometry = Geometry.from_dict(dict(DEFAULT_SIM_GEOMETRY))
    board = F.Checkerboard(period_mm=SIM_PATTERN_PERIOD_PX * geometry.pixel_mm, edge_softness_mm=geometry.pixel_mm)
    ref_img = F.render_tir(F.FlatSurface(), geometry, (256, 256), board)[0]
    img = F.render_tir(F.GaussianBump(amplitude_mm=0.004, sigma_mm=3.0), geometry, (256, 256), board)[0]
    ref = F.quantize(ref_img, bits=12, rng=np.random.default_rng(1))
    return ref_img, ref, img, find_reference_carriers(ref)


@pytest.mark.parametrize("kind", ["cos4", "gaussian"])
def test_a_vignette_is_named_vignetting_not_bands_and_bands_over_it_still_bands(sim_frames, kind):
    """Frames darkened towards their corners against the reference (corners at 5 % of the middle's light: the
    lens opened up, the light moved) were named "bands of light along the rows ... a rolling shutter" and
    evened row by row (depth 0.24-0.33 at 256^2 and 512^2): the quarters' row gains bend alike and the 64-row
    trend cannot follow the bend near the top and bottom. Now: vignetting, with its darkest corner, not
    evened; the reference vignetted instead says so; bands 30 % deep over the vignette are bands; a mild
    vignette (corners at 70 %) is neither (it costs nothing)."""
    from processing.banding import evened_frame, frame_light_bands, reference_light

    ref_img, ref, img, carriers = sim_frames
    light = _vignette(img.shape, 0.05, kind)
    twelve_bit = lambda a: F.quantize(a, bits=12, rng=np.random.default_rng(2))  # noqa: E731
    frame = twelve_bit(img * light)
    found = frame_light_bands(frame, reference_light(ref), carriers)
    assert not found.flagged and not found.evened, found.describe()
    assert evened_frame(frame, found) is frame  # measured as it is
    assert found.named and found.vignetted and not found.vignette.in_reference, found
    assert 0.03 < found.vignette.corner < 0.12, found.vignette  # (5 % at the very corner pixel)
    text = found.describe()
    assert text.startswith("the image darkens towards its edges and corners against the reference (vignetting")
    assert "rolling shutter" not in text and "not evened out" in text and "not measured" in text
    # the reference taken under the vignette, the frames not
    under = frame_light_bands(twelve_bit(img), reference_light(F.quantize(ref_img * light, bits=12)), carriers)
    assert not under.flagged and under.vignetted and under.vignette.in_reference, under
    assert under.describe().startswith("the reference darkens towards its edges and corners")
    # bands of light over the vignette: bands, evened (over the vignette), and the vignette said after them
    banded = frame_light_bands(twelve_bit(_bands(img * light, 0.3, phase=17)), reference_light(ref), carriers)
    assert banded.flagged and banded.evened and banded.vignetted and banded.agreement > 0.75, banded
    assert 0.3 * 0.3 < banded.depth < 0.7 * 0.3, banded
    assert "rolling shutter under light that flickers" in banded.describe()
    assert "Besides, the image darkens towards its edges and corners" in banded.describe()
    # bands alone: as before, no word of a vignette
    plain = frame_light_bands(twelve_bit(_bands(img, 0.3, phase=17)), reference_light(ref), carriers)
    assert plain.flagged and plain.evened and plain.vignette is None and "vignetting" not in plain.describe()
    # a mild vignette: nothing to say, and no bands (before: bands 0.026 deep, named and evened)
    mild = frame_light_bands(twelve_bit(img * _vignette(img.shape, 0.7, kind)), reference_light(ref), carriers)
    assert not mild.named and not mild.flagged, mild
