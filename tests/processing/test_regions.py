"""Connected regions of a mask (processing/regions.py): ndimage.label's labels, once per mask."""

import cv2
import numpy as np
import pytest
from scipy import ndimage

from processing.mask_memo import MaskMemo
from processing.regions import REGIONS_CACHE_SIZE, connected_regions


def _masks(rng, count):
    """Random masks as the live grid has them: scattered specks, holes grown by a dilation, thin
    rows and columns, every density from a few valid samples to nearly all."""
    for k in range(count):
        shape = (int(rng.integers(1, 300)), int(rng.integers(1, 300)))
        valid = rng.random(shape) < rng.uniform(0.05, 0.995)
        if k % 3 == 1:
            valid = cv2.erode(valid.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        elif k % 3 == 2:
            valid = cv2.dilate(valid.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        yield valid


@pytest.mark.parametrize("threads", [1, 2])
def test_the_labels_are_ndimage_labels_on_every_kind_of_mask(threads):
    rng = np.random.default_rng(11 + threads)
    before = cv2.getNumThreads()
    cv2.setNumThreads(threads)
    try:
        masks = list(_masks(rng, 400)) + [np.ones((512, 700), bool), np.zeros((40, 3), bool),
                                           np.eye(64, dtype=bool), rng.random((1024, 1024)) < 0.9]
        for valid in masks:
            want, n_want = ndimage.label(valid)
            got, n_got = connected_regions(valid)
            assert n_got == n_want
            np.testing.assert_array_equal(got, want)
            assert got.dtype == np.int32
    finally:
        cv2.setNumThreads(before)


def test_a_mask_asked_for_again_gets_the_same_read_only_answer_and_others_theirs():
    rng = np.random.default_rng(5)
    a = rng.random((30, 40)) < 0.7
    labels, n = connected_regions(a)
    assert connected_regions(a.copy())[0] is labels  # the same mask, another array: served once
    with pytest.raises(ValueError):
        labels[0, 0] = 99
    b = a.copy()
    b[a.nonzero()[0][0], a.nonzero()[1][0]] = False  # one sample less: its own labelling
    assert connected_regions(b)[0] is not labels
    np.testing.assert_array_equal(connected_regions(b)[0], ndimage.label(b)[0])
    for k in range(2 * REGIONS_CACHE_SIZE):  # more masks than it keeps: still right after eviction
        m = np.ones((6, 6), bool)
        m[:, k % 6] = False
        np.testing.assert_array_equal(connected_regions(m)[0], ndimage.label(m)[0])
    assert connected_regions(np.zeros((0, 5), bool))[1] == 0
    with pytest.raises(ValueError, match="2-D"):
        connected_regions(np.ones((2, 3, 4), bool))


def test_the_memo_computes_each_mask_once_and_keeps_only_its_size():
    calls = []
    memo = MaskMemo(2)

    def compute(valid):
        calls.append(valid.sum())
        return int(valid.sum())

    masks = [np.eye(5, dtype=bool), np.ones((5, 5), bool), np.zeros((5, 5), bool)]
    assert [memo(m, compute) for m in masks[:2] * 2] == [5, 25, 5, 25]
    assert len(calls) == 2  # the second round from the memo
    memo(masks[2], compute)  # a third mask drops the least recently used (the eye)
    assert len(memo) == 2
    memo(masks[0], compute)
    assert len(calls) == 4
    assert memo(np.ones((25, 1), bool), compute) == 25 and len(calls) == 5  # same bits, other shape
