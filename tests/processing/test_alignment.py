"""Live alignment (processing/alignment.py): the one-FFT path gives the full search's numbers.

``Reconstructor.alignment`` searches the frame's carriers only near the
reference's, in a Hann spectrum derived from the demodulator's FFT
(and in tiles batched in one FFT when the surface moves). Here its numbers
are compared with those of the full search, ``find_carriers_live(frame)``,
on ray-traced frames of the synthetic tank's setup (theta 55 deg, 12-px board,
6-px carriers, 8 bits with camera noise), within what the Alignment tab
shows: periods 0.01 px, rotation and theta 0.1 deg, focus a few %.
"""

import math

import cv2
import numpy as np
import pytest

import processing.alignment as alignment
from processing import forward
from processing.alignment import hann_stencil
from processing.half_spectrum import display_spectrum_of
from processing.carriers import display_spectrum, find_carriers_live, hann, theta_from_carriers
from processing.geometry import Geometry
from processing.reconstruct import Reconstructor

N = 512
PIXEL_MM = 40.0 / N
GEOMETRY = Geometry(theta_deg=55.0, depth_mm=300.0, pixel_mm=PIXEL_MM, rows_toward_camera=False)


def render(surface=None, *, rotation_deg=0.0, period_px=12.0, seed=0):
    board = forward.Checkerboard(period_mm=period_px * PIXEL_MM, edge_softness_mm=PIXEL_MM,
                                 rotation_deg=rotation_deg)
    img, _ = forward.render_tir(surface or forward.FlatSurface(), GEOMETRY, (N, N), board)
    return img, forward.quantize(img, bits=8, noise_rms=0.5, rng=np.random.default_rng(seed))


@pytest.fixture(scope="module")
def frames():
    flat, reference = render()
    waves = forward.WaveField(((0.0005, 2 * np.pi / 20.0, 2 * np.pi / 35.0, 0.3),
                               (0.00035, -2 * np.pi / 14.4, 2 * np.pi / 30.0, 1.1)))
    _, moving = render(waves, seed=1)
    rng = np.random.default_rng(2)
    defocused = forward.quantize(cv2.GaussianBlur(flat, (0, 0), 1.5), bits=8, noise_rms=0.5, rng=rng)
    saturated = forward.quantize(np.clip(1.7 * flat, 0.0, 1.0), bits=8, noise_rms=0.5, rng=rng)
    _, rotated = render(rotation_deg=2.0, seed=3)
    _, turned = render(rotation_deg=20.0, seed=4)  # far from the reference: the full search
    return {"reference": reference, "still": render(seed=5)[1], "waves": moving, "defocused": defocused,
            "saturated": saturated, "rotated": rotated, "turned": turned}


@pytest.fixture(scope="module")
def rec(frames):
    return Reconstructor(frames["reference"], GEOMETRY)


def full_search_calls(monkeypatch):
    calls = []

    def counting(frame):
        calls.append(1)
        return find_carriers_live(frame)

    monkeypatch.setattr(alignment, "find_carriers_live", counting)
    return calls


@pytest.mark.parametrize("name,full_search", [("still", False), ("waves", False), ("defocused", False),
                                              ("saturated", False), ("rotated", False), ("turned", True)])
def test_numbers_match_the_full_search(rec, frames, monkeypatch, name, full_search):
    frame = frames[name]
    calls = full_search_calls(monkeypatch)
    a = rec.alignment(frame)
    assert bool(calls) == full_search  # the fast path did the work (or, far off, handed it on)
    c, disturbed = find_carriers_live(frame)
    assert a["disturbed"] == disturbed == (name == "waves")
    np.testing.assert_allclose(a["periods_px"], c.periods_px, atol=0.005)  # shown to 0.01 px
    assert abs(a["rotation_deg"] - c.rotation_deg) < 0.05  # shown to 0.1 deg
    assert abs(a["theta_estimate_deg"] - theta_from_carriers(c.freq)) < 0.05
    assert a["focus"] == pytest.approx(float(np.min(c.sharpness)), rel=0.02)
    assert "error" not in a


def test_frames_tell_what_they_show(rec, frames):
    still, defocused, saturated = (rec.alignment(frames[k]) for k in ("still", "defocused", "saturated"))
    np.testing.assert_allclose(still["periods_px"], rec.carriers.periods_px, atol=0.01)
    assert abs(still["theta_estimate_deg"] - 55.0) < 0.1
    assert defocused["contrast"] < 0.8 * still["contrast"]  # blur takes contrast
    assert saturated["saturation_pct"] > 5.0 > still["saturation_pct"]
    rotated = rec.alignment(frames["rotated"])
    # 2 deg on the surface; the image compresses rows by cos(theta): atan(tan(2 deg) / cos(55 deg)) there
    assert abs(rotated["surface_rotation_deg"] - 2.0) < 0.1
    assert abs(rotated["rotation_deg"] - math.degrees(math.atan(math.tan(math.radians(2.0)) / math.cos(
        math.radians(55.0))))) < 0.1


@pytest.mark.parametrize("name", ["still", "waves", "defocused", "saturated", "rotated", "turned"])
def test_without_a_reference_the_numbers_are_the_full_searchs(frames, name):
    """carriers_without_reference (the Alignment tab before a reference): find_carriers_live's
    numbers; on waves its tiles searched together near what five of them show (within 1e-5 px and
    deg: the same peaks, their sub-bin steps computed otherwise), elsewhere the same search."""
    frame = frames[name]
    c, disturbed = alignment.carriers_without_reference(frame)
    want, want_disturbed = find_carriers_live(frame)
    assert disturbed == want_disturbed == (name == "waves")
    tol = 1e-5 if name == "waves" else 0.0
    np.testing.assert_allclose(c.periods_px, want.periods_px, rtol=0, atol=tol)
    assert abs(c.rotation_deg - want.rotation_deg) <= tol and abs(c.theta_deg - want.theta_deg) <= tol
    np.testing.assert_allclose(c.sharpness, want.sharpness, rtol=0, atol=tol)


@pytest.mark.parametrize("rotation_deg", [45.0, 15.0])
def test_without_a_reference_carriers_near_the_mirror_line_keep_the_full_searchs_numbers(rotation_deg):
    """A board turned 45 deg on the surface puts its carriers on the image axes, on the half spectrum's
    mirror line (f_col 0), where tiles give either sign and either order: there the full search's
    tiles are kept (before that guard the seeds' median put the period 0.47 px and the rotation 1.7 deg
    off); at 15 deg the tiles are searched together, to 1e-5."""
    waves = forward.WaveField(((0.0005, 2 * np.pi / 20.0, 2 * np.pi / 35.0, 0.3),
                               (0.00035, -2 * np.pi / 14.4, 2 * np.pi / 30.0, 1.1)))
    _, frame = render(waves, rotation_deg=rotation_deg, seed=7)
    c, disturbed = alignment.carriers_without_reference(frame)
    want, want_disturbed = find_carriers_live(frame)
    assert disturbed and want_disturbed
    np.testing.assert_allclose(c.periods_px, want.periods_px, rtol=0, atol=1e-5)
    assert abs(c.rotation_deg - want.rotation_deg) <= 1e-5


@pytest.mark.parametrize("image", [np.full((N, N), 120, np.uint8),
                                   np.random.default_rng(6).integers(0, 255, (N, N), dtype=np.uint8)])
def test_without_a_reference_no_pattern_gives_the_full_search_message(image):
    from processing.errors import NoCarrierError

    with pytest.raises(NoCarrierError) as got:
        alignment.carriers_without_reference(image)
    with pytest.raises(NoCarrierError) as want:
        find_carriers_live(image)
    assert str(got.value) == str(want.value)


def test_no_pattern_gives_the_full_search_message(rec):
    a = rec.alignment(np.full((N, N), 120, np.uint8))
    assert "uniform" in a["error"] and np.all(np.isnan(a["periods_px"]))


def test_spectrum_is_the_display_of_the_demodulator_fft(rec, frames):
    frame = frames["waves"]
    d = rec.demod
    spec = d.spectrum(frame)
    leak = np.fft.rfft2(d.border_window).astype(np.complex64)
    slow = display_spectrum(np.abs(spec - np.complex64(d.last_mean) * leak), N)
    fresh = rec.spectrum(frame)  # no alignment of this frame before: its own FFT
    rec.alignment(frame)
    shared = rec.spectrum(frame)  # right after alignment(frame): the same FFT's
    for s in (fresh, shared):
        np.testing.assert_array_equal(s["log_magnitude"], slow["log_magnitude"])
        np.testing.assert_array_equal(s["freq_x"], slow["freq_x"])
        np.testing.assert_array_equal(s["freq_y"], slow["freq_y"])
    other = rec.spectrum(frames["still"])  # another frame: not the cached one
    assert np.abs(other["log_magnitude"] - slow["log_magnitude"]).max() > 0.1


@pytest.mark.parametrize("shape", [(48, 37), (40, 64)])
def test_hann_stencil_is_the_hann_window(shape):
    x = np.random.default_rng(0).normal(size=shape)
    direct = np.fft.fft2(x * hann(shape[0])[:, None] * hann(shape[1])[None, :])
    kr, kc = np.mgrid[-30:30, -40:40]
    idx, conj, w = hann_stencil(shape, kr, kc)
    vals = np.fft.rfft2(x).reshape(-1)[idx]
    vals = np.where(conj, np.conj(vals), vals)
    got = np.tensordot(w, vals, axes=1)
    # exact but for the float32 window of processing.carriers.hann
    assert np.abs(got - direct[kr % shape[0], kc % shape[1]]).max() < 1e-6 * np.abs(direct).max()


@pytest.mark.parametrize("shape", [(64, 64), (50, 37)])
def test_display_of_the_half_spectrum(shape):
    x = np.random.default_rng(1).normal(size=shape)
    half = np.fft.rfft2(x).astype(np.complex64)
    for size in (8, 256):
        want = display_spectrum(np.abs(half), shape[1], size=size, max_freq=0.3)
        got = display_spectrum_of(half, shape, size=size, max_freq=0.3)
        for k in want:
            np.testing.assert_array_equal(got[k], want[k])
