"""The stages of the Reconstructor's chains, each alone (issue 19 point 2):
the facade has the same attributes whatever the pattern, a chain run stage by
stage gives the facade's result, the series memory is a value the stages take
and return (never changed in place), and the mask stages measure what they say."""

import dataclasses

import numpy as np
import pytest

from processing import forward as F
from processing import series as S
from processing.chain_checkerboard import CheckerboardChain
from processing.geometry import Geometry
from processing.mask import dilate_invalid, drop_islands, fold_ok
from processing.reconstruct import Reconstructor

G55 = Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False)
N = 128


def _pair(pattern, surface):
    ref, _ = F.render_tir(F.FlatSurface(), G55, (N, N), pattern, supersample=2)
    img, _ = F.render_tir(surface, G55, (N, N), pattern, supersample=2)
    return F.quantize(ref, bits=8), F.quantize(img, bits=8)


@pytest.fixture(scope="module")
def board():
    return _pair(F.Checkerboard(period_mm=2.0, edge_softness_mm=0.1), F.GaussianBump(amplitude_mm=0.003, sigma_mm=2.5))


def test_every_reconstructor_has_the_same_attributes_whatever_the_pattern(board):
    ref, _ = board
    dots_ref, _ = _pair(F.RandomDots(dot_diameter_mm=0.5, density=0.3, seed=1), F.FlatSurface())
    checker = Reconstructor(ref, G55)
    dots = Reconstructor(dots_ref, G55, pattern="dots", window_px=8)
    assert set(vars(checker)) == set(vars(dots))
    # what does not apply to dots says so instead of being missing
    assert dots.demod is None and dots.carriers is None and dots.plan is None and checker.piv is None
    assert (dots.unwrap, dots.temporal, dots.refine_iterations) == (False, False, 0)
    assert dots.series_state() is None
    # interchangeable chains: the facade runs either through the same three stages
    for rec in (checker, dots):
        assert all(callable(getattr(rec.chain, stage)) for stage in ("measure", "solve", "to_grid"))
    _, img = _pair(F.RandomDots(dot_diameter_mm=0.5, density=0.3, seed=1), F.GaussianBump(0.003, 2.5))
    m, state = dots.chain.measure(img, "full", S.EMPTY, 0.0)
    res, state = dots.chain.solve(m, "full", state)
    res = dots.chain.to_grid(m, res, "full")
    assert state is S.EMPTY  # dots keep no series memory
    np.testing.assert_array_equal(res.height, dots(img).height)


def test_the_chain_stage_by_stage_gives_the_facades_result(board):
    ref, img = board
    rec = Reconstructor(ref, G55, grid="decimated")
    chain = CheckerboardChain(ref, G55, rec.options)
    m, state = chain.measure(img, "decimated", S.EMPTY, 0.0)
    assert state.phase is not None and S.EMPTY.phase is None  # a new value, EMPTY untouched
    res, state2 = chain.solve(m, "decimated", state)
    assert state.check is None and state2.check is not None and state2.phase is state.phase
    res = chain.to_grid(m, res, "decimated")
    want = rec(img)
    for field in ("height", "valid", "slope_x", "slope_y", "displacement", "amplitude", "phase"):
        np.testing.assert_array_equal(getattr(res, field), getattr(want, field), err_msg=field)
    assert S.SeriesState.agrees_with(rec.series_state(), state2)


def test_unwrap_phase_continues_from_the_state_given():
    rng = np.random.default_rng(0)
    truth = 0.6 * (np.arange(12.0) - 8.0) * np.ones((2, 12, 1)) + rng.normal(0, 0.01, (2, 12, 12))
    prev = truth - 0.3  # the previous frame, 0.3 rad below: temporal unwrapping follows it
    valid = np.ones((12, 12), bool)
    ref_mask = np.zeros((12, 12), bool)
    ref_mask[:, 6:] = True
    wrapped = np.angle(np.exp(1j * truth))
    assert np.abs(wrapped - truth).max() > 1.0  # the first columns are wrapped
    state = S.SeriesState(prev, valid, True)
    kw = dict(unwrap=True, temporal=True, ref_mask=ref_mask, ref_idx=np.flatnonzero(ref_mask))
    out = S.unwrap_phase(wrapped, valid, True, state, **kw)
    np.testing.assert_allclose(out, truth, atol=1e-9)  # the 2 pi count of the previous frame
    np.testing.assert_allclose(S.unwrap_phase(wrapped, valid, True, S.EMPTY, **kw), truth, atol=1e-9)  # in space
    masked = S.SeriesState(prev, valid, False)  # the general (masked) path: the same answer
    np.testing.assert_allclose(S.unwrap_phase(wrapped, valid, False, masked, **kw), truth, atol=1e-9)
    assert state.phase is prev and np.array_equal(prev, truth - 0.3)  # nothing changed in place


def test_series_check_flags_a_pin_that_moved():
    valid = np.ones((20, 20), bool)
    phase = np.zeros((2, 20, 20))
    pins = np.zeros((20, 20), bool)
    pins[:2] = True

    class Surf:  # what check_series reads of a SurfaceResult
        def __init__(self, h, pin):
            self.height_mm, self.pin_samples = h, pin

    h = np.linspace(0, 1e-3, 400).reshape(20, 20)
    first, state = S.check_series(phase, valid, Surf(h, pins), S.EMPTY, pins)
    assert first is None and state.check is not None
    same, _ = S.check_series(phase, valid, Surf(h, pins), state, pins)
    assert not same.flagged and same.pin_shift_mm == 0.0
    other = np.zeros_like(pins)
    other[-2:] = True
    moved, _ = S.check_series(phase, valid, Surf(h + 2e-4, other), state, pins)  # 0.2 um on 0.58 um rms
    assert moved.flagged and moved.pin_shift_mm == pytest.approx(2e-4)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])  # the chain's displacement, a script's
def test_the_compiled_fold_determinant_is_numpys_to_the_bit(dtype):
    # mask_kernels.fold_determinant against np.gradient's det(I - grad u), and largest_steps against
    # np.diff's largest step, on grids down to 2 samples a side
    from processing.mask_kernels import fold_determinant, largest_steps

    rng = np.random.default_rng(5)
    for shape, dr, dc in (((135, 135), 3.8, 3.8), ((37, 52), 3.7, 4.1), ((2, 3), 1.0, 2.5)):
        u = (rng.standard_normal((2, *shape)) * 2.0).astype(dtype)
        dur_dr, dur_dc = np.gradient(u[0], np.float64(dr), np.float64(dc))
        duc_dr, duc_dc = np.gradient(u[1], np.float64(dr), np.float64(dc))
        want = (1.0 - dur_dr) * (1.0 - duc_dc) - dur_dc * duc_dr
        got = np.empty(shape, dtype)
        fold_determinant(u, dr, dc, u.dtype.type(1.0), got)
        assert got.dtype == want.dtype == dtype
        np.testing.assert_array_equal(got, want)
        assert largest_steps(u) == (np.abs(np.diff(u, axis=1)).max(), np.abs(np.diff(u, axis=2)).max())


def test_fold_test_finds_crossing_rays_and_islands_are_dropped():
    rows = cols = np.arange(0.0, 40.0, 2.0)
    r = rows[:, None] * np.ones((1, 20))
    smooth = np.stack([0.1 * np.sin(r / 6.0), np.zeros((20, 20))])
    assert fold_ok(smooth, rows, cols, 0.2) is None  # |grad u| < 0.4: no test needed
    folded = np.stack([4.0 * np.exp(-((r - 20.0) / 3.0) ** 2), np.zeros((20, 20))])  # du/dr up to 1.1 / px
    ok = fold_ok(folded, rows, cols, 0.2)
    det = 1.0 - np.gradient(folded[0], 2.0, axis=0)
    np.testing.assert_array_equal(ok, det > 0.2)
    assert not ok.all() and ok.any()
    valid = np.ones((20, 20), bool)
    valid[:, 8] = False
    valid[5:7, 12:14] = True
    valid[:, 11] = valid[:, 14] = False
    valid[:4, 12:14] = valid[8:, 12:14] = False  # a 2 x 2 island between two cuts
    region = np.zeros((20, 20), bool)
    region[:, :2] = True
    kept = drop_islands(valid, region, 0.05)
    assert not kept[5:7, 12:14].any() and kept[:, :8].all()
    assert dilate_invalid(~valid, 1).sum() > (~valid).sum()


def test_the_live_grid_reads_large_frames_binned_where_the_bands_allow():
    # options.live_binning: the decimated grid without refinement reads 512^2 frames of a 2 mm board
    # binned (ray traced, waves 1 um rms 12-30 mm long, 12 bit): heights as right as from the whole
    # frame (measured 0.559 -> 0.534 % rel. RMS); the full grid is untouched to the bit; a board of
    # 0.8 mm (8 px: its harmonics fold into the bands) and small frames are read whole
    from benchmarks.bench_processing import GEOMETRY, rel_height_error

    board = F.Checkerboard(period_mm=2.0, edge_softness_mm=0.1)
    rng = np.random.default_rng(0)
    ref, _ = F.render_tir(F.FlatSurface(), GEOMETRY, (512, 512), board, supersample=1)
    waves = F.WaveField.random(6, amplitude_rms_mm=0.001, wavelength_range_mm=(12, 30), seed=11)
    img, _ = F.render_tir(waves, GEOMETRY, (512, 512), board, supersample=1)
    ref, img = F.quantize(ref, bits=12, rng=rng), F.quantize(img, bits=12, rng=rng)
    binned = Reconstructor(ref, GEOMETRY, grid="decimated")
    whole = Reconstructor(ref, GEOMETRY, grid="decimated", live_binning=False)
    err_binned, err_whole = (rel_height_error(rec(img), waves) for rec in (binned, whole))
    assert binned.chain.live_demodulation()[0].binning == 2 and whole.chain.live_demodulation()[0].binning == 1
    assert err_whole < 1.0 and err_binned < err_whole + 0.1  # percent
    # the full grid (FD's refinement: quick) is the same either way
    binned.reset_series()
    whole.reset_series()
    np.testing.assert_array_equal(binned(img, grid="full").height, whole(img, grid="full").height)
    fine = F.Checkerboard(period_mm=0.8, edge_softness_mm=0.05)
    ref8, _ = F.render_tir(F.FlatSurface(), GEOMETRY, (512, 512), fine, supersample=1)
    img8, _ = F.render_tir(waves, GEOMETRY, (512, 512), fine, supersample=1)
    ref8, img8 = F.quantize(ref8, bits=12, rng=rng), F.quantize(img8, bits=12, rng=rng)
    rec8 = Reconstructor(ref8, GEOMETRY, grid="decimated")
    assert rec8.chain.live_demodulation()[0].binning == 1
    np.testing.assert_array_equal(rec8(img8).height,
                                  Reconstructor(ref8, GEOMETRY, grid="decimated", live_binning=False)(img8).height)
    small = Reconstructor(ref[:256, :256], GEOMETRY, grid="decimated")
    assert small.chain.live_demodulation()[0].binning == 1
