"""Nearest-valid-sample fill (processing/fill.py): its indices and the cache of masks."""

import numpy as np
import pytest

from processing.fill import FILL_CACHE_SIZE, nearest_fill_index


def _brute(valid):
    """Index of the nearest valid sample of every sample, by exhaustive search."""
    vr, vc = np.nonzero(valid)
    rows, cols = np.indices(valid.shape)
    d2 = (rows[..., None] - vr) ** 2 + (cols[..., None] - vc) ** 2
    k = d2.argmin(axis=-1)
    return vr[k], vc[k], d2.min(axis=-1)


def test_every_sample_maps_to_a_nearest_valid_one_and_a_repeated_mask_to_the_same_answer():
    rng = np.random.default_rng(3)
    masks = [rng.random((23, 31)) > p for p in (0.1, 0.5, 0.9)]
    for valid in masks + masks:  # the second round is served from the cache
        fill = nearest_fill_index(valid)
        _, _, d2 = _brute(valid)
        got = (np.indices(valid.shape)[0] - fill[0]) ** 2 + (np.indices(valid.shape)[1] - fill[1]) ** 2
        assert valid[fill].all()
        np.testing.assert_array_equal(got, d2)  # as near as the nearest (ties may pick either)
        assert np.array_equal(fill[0][valid], np.nonzero(valid)[0])  # valid samples keep their own


def test_the_cache_tells_masks_of_one_shape_apart_and_its_indices_cannot_be_written():
    a = np.ones((8, 8), bool)
    a[2, 3] = False
    b = a.copy()
    b[2, 3], b[5, 5] = True, False
    fa, fb = nearest_fill_index(a), nearest_fill_index(b)
    assert (fa[0][2, 3], fa[1][2, 3]) != (2, 3) and (fb[0][5, 5], fb[1][5, 5]) != (5, 5)
    assert (fb[0][2, 3], fb[1][2, 3]) == (2, 3)
    with pytest.raises(ValueError):
        fa[0][0, 0] = 7
    for k in range(2 * FILL_CACHE_SIZE):  # more masks than it keeps: still right after eviction
        m = np.ones((8, 8), bool)
        m[k % 8, k // 8] = False
        f = nearest_fill_index(m)
        assert m[f].all()
    assert nearest_fill_index(np.ones((4, 4), bool)) is None
    assert nearest_fill_index(np.zeros((4, 4), bool)) is None
