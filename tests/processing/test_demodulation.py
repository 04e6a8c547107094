"""Fourier demodulation on analytic warps I(r) = I0(r - u(r)) with known u."""

import math

import numpy as np
import pytest

from processing.carriers import find_carriers
from processing.demodulation import Demodulator, nice_fft_size, tukey
from processing.fft import FFTPlanner, export_wisdom, import_wisdom

N = 256
PERIOD = 16.0  # board edge period, px: carriers of period 11.3 px


def board(r, c, rotation_deg=5.0):
    t = math.radians(rotation_deg)
    x = c * math.cos(t) + r * math.sin(t)
    y = -c * math.sin(t) + r * math.cos(t)
    k = 2 * np.pi / PERIOD
    return 0.5 + 0.4 * np.tanh(3 * np.sin(k * x) * np.sin(k * y))


def displacement(r, c, amp_px, sigma_px):
    g = amp_px * np.exp(-((r - 120.0) ** 2 + (c - 140.0) ** 2) / (2 * sigma_px**2))
    return np.array([0.8 * g, -0.5 * g])


def warp_case(amp_px=1.0, sigma_px=25.0):
    r, c = np.mgrid[:N, :N].astype(float)
    u = displacement(r, c, amp_px, sigma_px)
    return board(r, c), board(r - u[0], c - u[1])


def rel_error(demod, frame, amp_px, sigma_px, margin=24):
    g = demod.decimated(frame)
    u = demod.phase_to_displacement(np.angle(g * np.conj(demod.g0)))
    R, C = np.meshgrid(demod.rows_px, demod.cols_px, indexing="ij")
    ut = displacement(R, C, amp_px, sigma_px)
    inner = (R > margin) & (R < N - margin) & (C > margin) & (C < N - margin)
    err = np.sqrt(np.mean((u - ut)[:, inner] ** 2))
    return err / np.sqrt(np.mean(ut[:, inner] ** 2))


def test_recovers_smooth_displacement():
    ref, frame = warp_case(1.0, 25.0)
    d = Demodulator(ref, find_carriers(ref))
    assert rel_error(d, frame, 1.0, 25.0) < 0.005  # 0.5 % of u


def test_default_filter_smooths_less_than_usual_filter():
    # features about two carrier periods wide: the usual filter (disc of half
    # the carrier spacing, nearest-bin carrier) loses several %
    ref, frame = warp_case(0.5, 9.0)
    c = find_carriers(ref)
    e_default = rel_error(Demodulator(ref, c), frame, 0.5, 9.0)
    e_flattop = rel_error(Demodulator(ref, c, filter_shape="flattop"), frame, 0.5, 9.0)
    e_usual = rel_error(Demodulator(ref, c, filter_shape="disc", filter_radius=0.5, subbin=False), frame, 0.5, 9.0)
    assert e_default < 0.03 and e_flattop < 0.03
    assert e_usual > 1.5 * max(e_default, e_flattop)


def test_nearest_bin_carrier_scales_displacement():
    # wide feature: no band-pass loss, only the carrier's scale error remains
    ref, frame = warp_case(1.0, 25.0)
    c = find_carriers(ref)
    e_sub = rel_error(Demodulator(ref, c), frame, 1.0, 25.0)
    e_bin = rel_error(Demodulator(ref, c, subbin=False), frame, 1.0, 25.0)
    assert e_sub < 0.005 and e_bin > 0.01


def test_apodization_keeps_borders_from_leaking():
    # non-periodic board (rotated, period not dividing N) plus a lighting ramp:
    # without apodization the wrap-around jump leaks into the carrier bands
    r, c = np.mgrid[:N, :N].astype(float)
    light = 1.0 + 0.6 * r / N
    u = displacement(r, c, 1.0, 25.0)
    ref = board(r, c) * light
    frame = board(r - u[0], c - u[1]) * light
    car = find_carriers(ref)
    e_apo = rel_error(Demodulator(ref, car, border="apodize"), frame, 1.0, 25.0, margin=12)
    e_none = rel_error(Demodulator(ref, car, border="none"), frame, 1.0, 25.0, margin=12)
    assert e_apo < 0.01
    assert e_apo <= e_none


def test_decimated_grid_is_pixel_centred_and_small():
    ref, _ = warp_case()
    d = Demodulator(ref, find_carriers(ref))
    m_r, m_c = d.window_shape
    assert m_r < N / 2 and m_c < N / 2  # the live speed comes from here
    np.testing.assert_allclose(d.rows_px, (np.arange(m_r) + 0.5) * N / m_r - 0.5)


def test_full_grid_matches_decimated_at_samples():
    ref, frame = warp_case(1.0, 25.0)
    d = Demodulator(ref, find_carriers(ref))
    wins = d.windows(d.spectrum(frame))
    gd = d.decimated_from_windows(wins)
    gf = d.full_from_windows(wins).copy()
    g0f = d.full_from_windows(d.windows(d.spectrum(ref)))
    phase_full = np.angle(gf * np.conj(g0f))
    # the full grid, interpolated (cubic spline) at the decimated samples, agrees
    from scipy.ndimage import map_coordinates

    R, C = np.meshgrid(d.rows_px, d.cols_px, indexing="ij")
    inner = (R > 16) & (R < N - 16) & (C > 16) & (C < N - 16)
    pd = np.angle(gd * np.conj(d.g0))
    for s in range(2):
        pf = map_coordinates(phase_full[s], [R[inner], C[inner]], order=3)
        assert np.max(np.abs(pf - pd[s][inner])) < 0.01  # rad, of up to ~0.6 rad


def test_phase_displacement_round_trip():
    ref, _ = warp_case()
    d = Demodulator(ref, find_carriers(ref))
    u = np.random.default_rng(1).normal(size=(2, 5, 7))
    np.testing.assert_allclose(d.phase_to_displacement(d.displacement_to_phase(u)), u, atol=1e-5)


def test_options_validated():
    ref, _ = warp_case()
    c = find_carriers(ref)
    with pytest.raises(ValueError, match="filter_shape"):
        Demodulator(ref, c, filter_shape="box")
    with pytest.raises(ValueError, match="filter_radius"):
        Demodulator(ref, c, filter_radius=2.0)


def test_helpers():
    assert nice_fft_size(97) == 98 and nice_fft_size(128) == 128
    w = tukey(50, 10)
    assert w.max() == 1.0 and w[0] < 0.05 and np.all(w[10:40] == 1.0)


def test_fft_planner_and_wisdom_round_trip():
    p = FFTPlanner(threads=2, planner_effort="FFTW_MEASURE")
    x = np.random.default_rng(2).normal(size=(60, 80)).astype(np.float32)
    np.testing.assert_allclose(p.rfft2(x), np.fft.rfft2(x), rtol=1e-4, atol=1e-3)
    blob = export_wisdom()
    assert isinstance(blob, bytes) and len(blob) > 20
    assert import_wisdom(blob) is True
    with pytest.raises(ValueError, match="header"):
        import_wisdom(b"not wisdom")
    with pytest.raises(ValueError, match="truncated"):
        import_wisdom(blob[:-5])
    with pytest.raises(ValueError, match="planner_effort"):
        FFTPlanner(planner_effort="FFTW_FAST")
    y = (np.random.default_rng(3).normal(size=(32, 48)) + 1j).astype(np.complex64)
    np.testing.assert_allclose(p.ifft2(p.fft2(y).copy()), y, atol=1e-5)


def test_rfft2_of_a_column_band_is_the_spectrum_there():
    # the carrier windows' transform does the columns pass on a band of columns only; planning
    # a new band with FFTW_MEASURE (which overwrites the arrays it plans on) must keep the data
    p = FFTPlanner(threads=1, planner_effort="FFTW_MEASURE")
    x = np.random.default_rng(4).normal(size=(64, 96)).astype(np.float32)
    full = np.fft.rfft2(x.astype(np.float64))
    p.input_array("rfft2", x.shape)[...] = x
    band = p.execute("rfft2", x.shape, columns=11)  # not prepared: planned here, on the frame's data
    scale = np.abs(full).max()
    assert np.abs(band[:, :11] - full[:, :11]).max() < 1e-6 * scale
    assert np.abs(band[:, 11:] - full[:, 11:]).max() > 0.1 * scale  # the rest: not the spectrum
    with pytest.raises(ValueError, match="columns"):
        p.execute("rfft2", x.shape, columns=49 + 1)


@pytest.mark.parametrize("shape, rotation_deg", [((N, N), 0.0), ((N, N), 5.0), ((N, N), 30.0), ((N, N), 45.0),
                                                 ((192, 256), 12.0), ((256, 191), 12.0)])
def test_carrier_windows_from_the_column_band(shape, rotation_deg):
    # the windows read from the band transform are those of the whole spectrum, whatever the board's turn,
    # on a frame not square and one of an odd width too (the band's columns from that width's half spectrum)
    r, c = np.mgrid[:shape[0], :shape[1]].astype(float)
    ref = board(r, c, rotation_deg)
    u = displacement(r, c, 1.0, 25.0)
    frame = board(r - u[0], c - u[1], rotation_deg)
    d = Demodulator(ref, find_carriers(ref))
    half = shape[1] // 2 + 1
    assert d.carrier_columns is not None and d.carrier_columns < 0.6 * half
    # the band ends where the windows do
    assert d.carrier_columns - 1 == max(int(np.max(g % half)) for g in d.plan.gather_index)
    whole = d.windows(d.spectrum(frame)).copy()
    assert np.abs(d.frame_windows(frame) - whole).max() < 1e-6 * np.abs(whole).max()


def _warp_512(period_px, noise_dn=2.0, dtype=np.uint16, rotation_deg=5.0):
    """A 512^2 board of ``period_px`` (rotated), a displacement of 1 px peak plus a
    0.3 px ripple 300 px long, both as camera frames (3000 grey levels of contrast,
    ``noise_dn`` rms), and the true displacement as a function of (r, c)."""
    n = 512
    r, c = np.mgrid[:n, :n].astype(float)

    def pat(rr, cc):
        t = math.radians(rotation_deg)
        x = cc * math.cos(t) + rr * math.sin(t)
        y = -cc * math.sin(t) + rr * math.cos(t)
        k = 2 * np.pi / period_px
        return 0.5 + 0.4 * np.tanh(3 * np.sin(k * x) * np.sin(k * y))

    def u_true(rr, cc):
        g = np.exp(-((rr - 240.0) ** 2 + (cc - 280.0) ** 2) / (2 * 60.0**2)) + 0.3 * np.sin(2 * np.pi * cc / 300.0)
        return np.array([0.8 * g, -0.5 * g])

    rng = np.random.default_rng(0)
    scale = 3000.0 if dtype == np.uint16 else 200.0
    u = u_true(r, c)
    ref = (pat(r, c) * scale + rng.normal(0, noise_dn, (n, n))).astype(dtype)
    frame = (pat(r - u[0], c - u[1]) * scale + rng.normal(0, noise_dn, (n, n))).astype(dtype)
    return ref, frame, u_true


@pytest.mark.parametrize("dtype, noise_dn", [(np.uint16, 2.0), (np.uint8, 0.0)])
def test_binned_frame_gives_the_same_band_on_the_same_grid(dtype, noise_dn):
    # a frame binned 2 x 2 (cv2.pyrDown) carries the carriers' bands of a 20 px board whole: the
    # same grid, sample positions and displacement, within what the binning folds in (noise from
    # beyond half the sampling rate, 8-bit levels); a quarter of the transform
    from processing.binning import binned_bands_clear

    ref, frame, u_true = _warp_512(20.0, noise_dn, dtype)
    carriers = find_carriers(ref)
    whole = Demodulator(ref, carriers)
    binned = Demodulator(ref, carriers, binning=2)
    assert binned_bands_clear(whole.freq, whole.radius, ref.shape)
    assert binned.window_shape == whole.window_shape and binned.source_shape == (256, 256)
    np.testing.assert_array_equal(binned.rows_px, whole.rows_px)
    R, C = np.meshgrid(whole.rows_px, whole.cols_px, indexing="ij")
    ut = u_true(R, C)
    inner = (R > 24) & (R < 488) & (C > 24) & (C < 488)
    errors = []
    for d in (whole, binned):
        u = d.phase_to_displacement(np.angle(d.decimated(frame) * np.conj(d.g0)))
        errors.append(float(np.sqrt(np.mean((u - ut)[:, inner] ** 2)) / np.sqrt(np.mean(ut[:, inner] ** 2))))
    assert errors[0] < 0.015  # the method: 0.72 % of u (12 bit, noise 2 levels), 1.06 % (8 bit, none)
    assert errors[1] < errors[0] * 1.15 + 0.0005  # measured 0.73 and 1.06 %: at most 15 % more, or 0.05 % of u
    # the contrast ratio |g| / |g0| of a frame like the reference is 1 either way (the filter undoes
    # the pyramid's gain in the band)
    ratio = np.abs(binned.decimated(ref)) / np.abs(binned.g0)
    np.testing.assert_allclose(np.median(ratio), 1.0, atol=1e-3)


def test_binning_refused_where_the_pattern_would_fold_into_its_bands():
    from processing.binning import binned_bands_clear

    # 8 px board along the axes: the 3rd harmonic at 0.375 cycles/px folds onto the carrier at 0.125
    ref, _, _ = _warp_512(8.0, rotation_deg=0.0)
    carriers = find_carriers(ref)
    whole = Demodulator(ref, carriers)
    assert not binned_bands_clear(whole.freq, whole.radius, ref.shape)
    with pytest.raises(ValueError, match="fold the pattern into its carrier bands"):
        Demodulator(ref, carriers, binning=2)
    # an odd side cannot be binned in pairs; a 20 px board can
    assert not binned_bands_clear([[0.05, 0.0], [0.0, 0.05]], 0.035, (512, 511))
    assert binned_bands_clear([[0.05, 0.0], [0.0, 0.05]], 0.035, (512, 512))
    ref20, _, _ = _warp_512(20.0)
    binned = Demodulator(ref20, find_carriers(ref20), binning=2)
    with pytest.raises(ValueError, match="decimated grid only"):
        binned.full_from_windows(binned.frame_windows(ref20))
    with pytest.raises(ValueError, match="binning must be 1 or 2"):
        Demodulator(ref20, find_carriers(ref20), binning=3)
