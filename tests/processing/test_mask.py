"""processing.mask's messages for frames nothing of which could be measured, and the exposure gain's decile."""

import numpy as np


def test_a_frame_far_darker_than_its_reference_says_by_how_much():
    """What an all-invalid frame's message adds (processing.mask.darker_than_reference): a reference with
    12-bit levels in the top bits of 16-bit words stands 16x above the camera's frames; a black frame says
    so; within the 4x that the exposure gain makes up for, nothing."""
    from processing.mask import darker_than_reference

    reference_mean = 16 * 2000.0
    text = darker_than_reference(np.full((64, 64), 2000, np.uint16), reference_mean)
    assert text.startswith("the frame is 16x darker than the reference") and "another bit depth" in text
    assert darker_than_reference(np.zeros((64, 64), np.uint16), reference_mean).startswith("the frame is black")
    assert darker_than_reference(np.full((64, 64), 9000, np.uint16), reference_mean) == ""  # 3.6x: made up for
    assert darker_than_reference(np.full((64, 64), 10, np.uint16), 0.0) == ""  # no reference level


def test_percentiles_are_numpys_own():
    """percentiles (one partition each: the exposure gain's decile, and what every map's colour range in
    the window takes on every frame) gives np.percentile's floats for the percentiles they use, on every
    kind of sample the views show."""
    from processing.mask import percentiles

    rng = np.random.default_rng(12)
    for trial in range(600):
        n = int(rng.integers(1, 25000))
        kind = trial % 4
        if kind < 2:
            values = (rng.normal(size=n) * rng.uniform(1e-3, 1e3)).astype((np.float32, np.float64)[kind])
        else:
            values = rng.integers(0, (255, 4095)[kind - 2], n).astype((np.uint8, np.uint16)[kind - 2])
        for pcts in ([99.9], [0.1, 99.9], [1.0, 99.0], [50.0], [90.0]):
            assert percentiles(values, pcts) == [float(v) for v in np.percentile(values, pcts)], (trial, pcts)


def test_the_upper_decile_is_numpys_90th_percentile():
    """exposure_gain's contrast decile through one partition (mask.percentiles) is np.percentile(x, 90)
    to float32 rounding, on 1 to 30,000 values, ties and constant arrays included."""
    from processing.mask import percentiles

    def upper_decile(values):
        return percentiles(values, [90])[0]

    rng = np.random.default_rng(5)
    for size in (1, 2, 3, 9, 10, 11, 100, 25600, 25601, 30000):
        for values in (rng.random(size).astype(np.float32), rng.integers(0, 4, size).astype(np.float32),
                       np.full(size, 0.7, np.float32)):
            want = float(np.percentile(values, 90))
            assert abs(upper_decile(values) - want) <= 1e-6 * max(1.0, abs(want))
    assert abs(upper_decile(rng.random((160, 160)).astype(np.float32)) - 0.9) < 0.01  # 2-D, as the mask's
