"""Spatial and temporal phase unwrapping."""

import numpy as np
import pytest

from processing.unwrap import has_wraps, unwrap_spatial, unwrap_temporal, wrap
from processing.unwrap_kernels import path_follow


def bowl(n=64, depth=12.0):
    r, c = np.mgrid[:n, :n].astype(float)
    return -depth * np.exp(-((r - 32) ** 2 + (c - 30) ** 2) / (2 * 12.0**2))


def border(n=64, w=3):
    m = np.zeros((n, n), bool)
    m[:w], m[-w:], m[:, :w], m[:, -w:] = True, True, True, True
    return m


def test_spatial_unwraps_several_pi_with_reference_near_zero():
    true = bowl()  # 12 rad deep, reference border at ~0
    out = unwrap_spatial(wrap(true), ref_mask=border())
    np.testing.assert_allclose(out, true, atol=1e-9)


def test_spatial_ignores_masked_samples():
    true = bowl()
    valid = np.ones_like(true, bool)
    valid[20:26, 5:60] = False  # a masked stripe across the bowl
    garbage = np.where(valid, wrap(true), np.random.default_rng(0).uniform(-np.pi, np.pi, true.shape))
    out = unwrap_spatial(garbage, valid, ref_mask=border())
    assert np.all(np.isnan(out[~valid]))
    np.testing.assert_allclose(out[valid], true[valid], atol=1e-9)


def test_fast_path_when_no_wraps():
    phase = 0.1 * bowl()
    assert not has_wraps(phase)
    np.testing.assert_allclose(unwrap_spatial(phase, ref_mask=border()), phase)


def test_jump_test_matches_the_neighbour_differences(rng):
    """has_wraps (a compiled scan that stops at the first jump) says what the
    neighbour differences say: any valid pair more than pi apart, NaN pairs not."""
    for trial in range(40):
        rows, cols = rng.integers(1, 40, size=2)
        phase = rng.normal(0.0, rng.uniform(0.05, 1.5), (rows, cols)).cumsum(axis=1)
        if trial % 3 == 0:
            phase = phase.astype(np.float32)
        valid = rng.random((rows, cols)) > rng.uniform(0.0, 0.6)
        if trial % 5 == 0:
            phase[rng.random((rows, cols)) < 0.1] = np.nan
        dr, dc = np.abs(np.diff(phase, axis=0)), np.abs(np.diff(phase, axis=1))
        unmasked = bool(np.any(dr > np.pi) or np.any(dc > np.pi))
        masked = bool(np.any((dr > np.pi) & valid[1:] & valid[:-1])
                      or np.any((dc > np.pi) & valid[:, 1:] & valid[:, :-1]))
        assert has_wraps(phase) == unmasked
        assert has_wraps(phase, valid) == masked
    assert has_wraps(np.array([0.0, 3.2])) and not has_wraps(np.array([0.0, 3.1]))  # one row


def test_temporal_fixes_an_island_space_cannot():
    # an island cut off by an invalid ring: space alone cannot know its 2 pi
    # offset; the previous frame of the series can
    n = 64
    r, c = np.mgrid[:n, :n].astype(float)
    rad = np.hypot(r - 32, c - 32)
    valid = ~((rad > 10) & (rad < 14))
    prev_true = -7.0 * np.exp(-(rad**2) / (2 * 6.0**2))
    now_true = prev_true * 1.15
    spatial = unwrap_spatial(wrap(now_true), valid, ref_mask=border())
    island = rad <= 10
    assert np.max(np.abs(spatial[island] - now_true[island])) > 3  # wrong by 2 pi
    prev = np.where(valid, prev_true, np.nan)
    out = unwrap_temporal(wrap(now_true), prev, valid, valid, ref_mask=border())
    np.testing.assert_allclose(out[valid], now_true[valid], atol=1e-9)


def test_temporal_new_valid_samples_join_consistently():
    true = bowl()
    prev_valid = np.ones_like(true, bool)
    prev_valid[40:50, 40:50] = False
    prev = np.where(prev_valid, true * 0.95, np.nan)
    out = unwrap_temporal(wrap(true), prev, None, prev_valid, ref_mask=border())
    np.testing.assert_allclose(out, true, atol=1e-9)


def test_spatial_repairs_residues_next_to_a_masked_spot_locally():
    """A masked spot holding a pair of phase singularities on the flank of a
    steep bowl: least squares with the dropped differences is inconsistent
    near the spot; the local path-following repair (now tried after the
    compiled whole-map path following) succeeds on it, and unwrap_spatial
    gives the phase exactly (up to 2 pi) everywhere outside the spot."""
    from processing import unwrap as U

    n = 120
    y, x = np.mgrid[0:n, 0:n].astype(float)
    bowl = 30.0 * np.exp(-((y - 60) ** 2 + (x - 60) ** 2) / 40.0 ** 2)
    cy, cx = 60, 35
    spot = (y - cy) ** 2 + (x - cx) ** 2 <= 4.0 ** 2
    truth = bowl + np.arctan2(y - cy, x - cx - 2) - np.arctan2(y - cy, x - cx + 2)
    rng = np.random.default_rng(1)
    wrapped = wrap(np.where(spot, rng.uniform(-np.pi, np.pi, (n, n)), truth))
    valid = ~spot
    work = np.where(valid, wrapped, 0.0)
    assert has_wraps(U._lsq_rounded(work, valid), valid)  # the plain LSQ result fails
    assert U._unwrap_local_repair(work, valid) is not None  # the local repair succeeds
    out = unwrap_spatial(wrapped, valid)
    assert np.all(np.isnan(out[spot]))
    d = (out - truth)[valid]
    assert np.ptp(d) < 1e-9
    assert abs(d.mean() / (2 * np.pi) - round(d.mean() / (2 * np.pi))) < 1e-9


def test_spatial_with_an_inherent_residue_matches_whole_map_path_following():
    """A single phase singularity among valid samples: no unwrapping is
    consistent; whatever path (local repair or whole map) is taken, the
    result is the whole-map path-following one up to 2 pi per region."""
    from skimage.restoration import unwrap_phase

    n = 100
    y, x = np.mgrid[0:n, 0:n].astype(float)
    truth = 25.0 * np.exp(-((y - 50) ** 2 + (x - 50) ** 2) / 35.0 ** 2) + np.arctan2(y - 30.5, x - 70.5)
    wrapped = wrap(truth)
    valid = np.ones((n, n), bool)
    valid[60:66, 20:26] = False
    out = unwrap_spatial(wrapped, valid)
    ref = unwrap_phase(np.ma.masked_array(np.where(valid, wrapped, 0.0), mask=~valid)).filled(0.0)
    d = (out - ref)[valid]
    assert np.ptp(d) < 1e-9


def test_temporal_grows_into_newly_valid_samples_far_from_the_old_ones():
    """Newly valid samples beyond the growth reach are unwrapped in space."""
    true = bowl()
    prev_valid = np.ones_like(true, bool)
    prev_valid[20:70, 20:70] = False  # 25 samples deep: beyond _GROW_STEPS
    prev = np.where(prev_valid, true * 0.97, np.nan)
    out = unwrap_temporal(wrap(true), prev, None, prev_valid, ref_mask=border())
    np.testing.assert_allclose(out, true, atol=1e-9)


def _steep_map_with_spots_and_a_seam():
    """A steep phase (up to 2.4 rad per sample) with 25 masked spots and a dry seam cutting the map
    in two: the rounded least squares is inconsistent in many places, and the local repair's boxes
    cover more than its share of the map."""
    n = 160
    y, x = np.mgrid[0:n, 0:n].astype(float)
    truth = 120.0 * np.exp(-((y - 80) ** 2 + (x - 80) ** 2) / 70.0 ** 2) + 0.9 * x
    rng = np.random.default_rng(3)
    valid = np.ones((n, n), bool)
    for cy, cx in rng.uniform(10, 150, (25, 2)):
        valid &= (y - cy) ** 2 + (x - cx) ** 2 > 3.0 ** 2
    valid[:, 100:103] = False
    return truth, valid


def test_compiled_path_following_unwraps_where_least_squares_and_local_repair_fail():
    """The compiled quality-guided path following (processing/unwrap_kernels.py) gives the true phase
    on each connected region up to one 2 pi multiple, as scikit-image's whole-map path following
    does, where the rounded least squares and the local repair both fail; unwrap_spatial takes it."""
    from scipy import ndimage
    from skimage.restoration import unwrap_phase

    from processing import unwrap as U

    truth, valid = _steep_map_with_spots_and_a_seam()
    work = np.where(valid, wrap(truth), 0.0)
    rough = U._lsq_rounded(work, valid)
    assert has_wraps(rough, valid)
    assert U._unwrap_local_repair(work, valid, rough) is None
    out = U._unwrap_path_following(work, valid)
    assert out is not None and not has_wraps(out, valid)
    sk = unwrap_phase(np.ma.masked_array(work, mask=~valid)).filled(0.0)
    labels, n_regions = ndimage.label(valid)
    assert n_regions == 2
    for k in range(1, n_regions + 1):
        region = labels == k
        for other in (truth, sk):
            turns = (out[region] - other[region]) / (2 * np.pi)
            assert np.ptp(turns) < 1e-9 and abs(turns[0] - round(turns[0])) < 1e-9
    spatial = unwrap_spatial(wrap(truth), valid)
    for k in range(1, n_regions + 1):
        region = labels == k
        assert np.ptp(spatial[region] - truth[region]) < 1e-9


def test_compiled_path_following_is_refused_where_its_jumps_are_not_at_residues():
    """A single phase singularity among valid samples: every unwrapping has a 2 pi cut from it to the
    frame's edge, and the compiled path following's cut is not only sides of the residue's cell, so
    it is refused (None) and scikit-image's whole-map result decides
    (test_spatial_with_an_inherent_residue_matches_whole_map_path_following)."""
    from processing import unwrap as U

    n = 100
    y, x = np.mgrid[0:n, 0:n].astype(float)
    truth = 25.0 * np.exp(-((y - 50) ** 2 + (x - 50) ** 2) / 35.0 ** 2) + np.arctan2(y - 30.5, x - 70.5)
    valid = np.ones((n, n), bool)
    out = np.zeros((n, n))
    path_follow(wrap(truth), valid, out)
    assert has_wraps(out, valid)  # it ran and left a cut
    assert U._unwrap_path_following(wrap(truth), valid) is None


def _smooth_field(rng):
    """A phase field (rad) of 20-120 samples a side: three products of sines of 2-30 rad, periods of
    6-40 samples, and noise of 0, 0.3 or 1 rad: with residues or without."""
    rows, cols = (int(v) for v in rng.integers(20, 120, 2))
    r, c = np.mgrid[:rows, :cols]
    truth = np.zeros((rows, cols))
    for _ in range(3):
        amplitude, period_r, start = rng.uniform(2, 30), rng.uniform(6, 40), rng.uniform(0, 6)
        truth += amplitude * np.sin(r / period_r + start) * np.cos(c / rng.uniform(6, 40))
    return truth + rng.normal(0, rng.choice([0.0, 0.3, 1.0]), truth.shape)


def test_the_plain_flood_fill_is_path_followings_unwrapping_wherever_it_accepts():
    """The flood fill that unwrap_spatial tries before path following (no reliability order, a few
    times cheaper) is accepted only when consistent, and then gives path following's result on every
    connected region up to one 2 pi multiple, and counts the regions as ndimage.label does; a map
    with a residue it refuses (-1).  Smooth fields of 2-30
    rad with masks, stripes and noise of 0-1 rad, some with residues and some without."""
    from scipy import ndimage

    from processing.unwrap_kernels import flood_fill

    rng = np.random.default_rng(7)
    accepted = refused = 0
    for _ in range(60):
        truth = _smooth_field(rng)
        rows, cols = truth.shape
        valid = rng.random(truth.shape) > rng.choice([0.0, 0.05, 0.3])
        valid[rows // 3: rows // 2] &= rng.random() < 0.5  # sometimes a masked stripe: two regions
        work = np.where(valid, wrap(truth), 0.0)
        fill = np.zeros(truth.shape)
        regions = flood_fill(work, valid, fill)
        if regions < 0:
            refused += 1
            continue
        accepted += 1
        assert not has_wraps(fill, valid)
        followed = np.zeros(truth.shape)
        path_follow(work, valid, followed)
        labels, n_regions = ndimage.label(valid)
        assert regions == n_regions
        for k in range(1, n_regions + 1):
            turns = (fill - followed)[labels == k] / (2 * np.pi)
            assert np.ptp(turns) < 1e-9 and abs(turns[0] - round(turns[0])) < 1e-9
    assert accepted >= 10 and refused >= 10

    n = 100  # one phase singularity: no consistent unwrapping exists
    y, x = np.mgrid[0:n, 0:n].astype(float)
    spiral = np.arctan2(y - 30.5, x - 70.5)
    assert flood_fill(wrap(spiral), np.ones((n, n), bool), np.zeros((n, n))) == -1


def test_the_scanline_fill_of_a_map_valid_everywhere_is_the_flood_fills_unwrapping():
    """unwrap_spatial's fill of a map valid everywhere (scan_fill: the first column down, then each row,
    no stack) accepts and refuses exactly the maps the flood fill does, and where it accepts gives its
    values (seeded at the same sample: a consistent unwrapping is unique) to rounding.  Smooth fields
    of 2-30 rad with noise of 0-1 rad, with and without residues, and the spiral that has one; float32
    maps as float64 ones; unwrap_spatial's path for a map valid everywhere as its general one."""
    from processing.unwrap_kernels import flood_fill, scan_fill

    rng = np.random.default_rng(17)
    accepted = refused = 0
    for _ in range(60):
        truth = _smooth_field(rng)
        rows, cols = truth.shape
        work = wrap(truth)
        everywhere = np.ones(truth.shape, bool)
        flood, scan = np.zeros(truth.shape), np.zeros(truth.shape)
        verdict = flood_fill(work, everywhere, flood)
        assert scan_fill(work, scan) == verdict
        if verdict < 0:
            refused += 1
            continue
        accepted += 1
        assert np.max(np.abs(scan - flood)) < 1e-9
        assert np.max(np.abs(scan - truth - (scan - truth).flat[0])) < 1e-9 or has_wraps(truth)
        single = np.zeros(truth.shape)
        assert scan_fill(work.astype(np.float32), single) == 1  # the live maps' float32, differenced in float64
        assert np.array_equal(single, scan_fill_of(work.astype(np.float32).astype(np.float64)))
        # unwrap_spatial's path for a map valid everywhere is its general one's (valid=None)
        ref = np.zeros(truth.shape, bool)
        ref[: rows // 4] = True
        general = unwrap_spatial(work, ref_mask=ref)
        assert np.max(np.abs(unwrap_spatial(work, everywhere, ref_mask=ref) - general)) < 1e-9
    assert accepted >= 10 and refused >= 10
    n = 100
    y, x = np.mgrid[0:n, 0:n].astype(float)
    assert scan_fill(wrap(np.arctan2(y - 30.5, x - 70.5)), np.zeros((n, n))) == -1
    smooth = wrap(0.3 * x)
    smooth[40, 50] = np.nan  # a sample not finite: refused, the general path masks it
    assert scan_fill(smooth, np.zeros((n, n))) == -1
    assert np.isnan(unwrap_spatial(smooth, np.ones((n, n), bool))[40, 50])


def scan_fill_of(phase):
    from processing.unwrap_kernels import scan_fill

    out = np.zeros(phase.shape)
    scan_fill(phase, out)
    return out


def test_the_median_turn_is_the_2pi_multiple_nearest_the_median():
    """median_turn reads the multiple from the extremes when they agree, or (many values) from a
    sparse sample's median confirmed by counting; it is always 2 pi round(median / 2 pi), whether the
    values span one multiple or several, float64 or float32, half of them exactly on an interval's
    end (pi) or not."""
    from processing.unwrap import median_turn

    rng = np.random.default_rng(11)
    for t in range(1500):
        dtype = (np.float64, np.float32)[t % 2]
        size = int(rng.integers(1, 400)) if t < 300 else int(rng.integers(2000, 30000))
        values = rng.normal(rng.uniform(-20, 20), rng.choice([0.1, 1.0, 5.0, 20.0]), size).astype(dtype)
        if t % 5 == 0:
            values[: size // 2] = dtype(np.pi)
        # the same multiple (float32 medians round 2 pi k in float32)
        assert median_turn(values) == pytest.approx(2 * np.pi * np.round(np.median(values) / (2 * np.pi)),
                                                    abs=1e-5)

