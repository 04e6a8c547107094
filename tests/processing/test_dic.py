"""Image-domain refinement (processing.dic, ``refine_method="image"``) on ray-traced frames.

Frames from processing.forward (exact ray tracing, no linear model); error
measure as in test_reconstruct (relative RMS height error, interior, null
space removed).
"""

import numpy as np
import pytest

from processing import forward as F
from processing.reconstruct import Reconstructor

from .test_reconstruct import G55, render, rel_error

# issue 11: waves 3-6 carrier periods long (2 mm board at 0.1 mm/px), 12 bit
WAVES = F.WaveField.random(8, amplitude_rms_mm=0.0003, wavelength_range_mm=(6, 12), seed=1)


@pytest.fixture(scope="module")
def wave_frames():
    return render(WAVES, bits=12)


def test_image_refinement_halves_the_band_limit_error_on_short_waves(wave_frames):
    ref, img, _ = wave_frames
    fd = rel_error(Reconstructor(ref, G55)(img), WAVES)
    image = rel_error(Reconstructor(ref, G55, refine_method="image")(img), WAVES)
    # measured 2.90 % (FD + one refinement) -> 1.42 %
    assert fd > 0.02
    assert image <= 0.016
    assert image <= 0.6 * fd


def test_image_refinement_keeps_a_wide_bump_accurate():
    bump = F.GaussianBump(amplitude_mm=0.004, sigma_mm=5.0)
    ref, img, _ = render(bump)
    res = Reconstructor(ref, G55, refine_method="image")(img)
    assert rel_error(res, bump) <= 0.006  # FD default 0.22 % (docs/processing.md)


def test_image_refinement_only_on_the_full_grid(wave_frames):
    ref, img, _ = wave_frames
    a = Reconstructor(ref, G55, refine_method="image")(img, grid="decimated")
    b = Reconstructor(ref, G55)(img, grid="decimated")
    np.testing.assert_array_equal(a.height, b.height)


def test_bad_refine_method_named(wave_frames):
    ref, _, _ = wave_frames
    with pytest.raises(ValueError, match="refine_method must be 'fd' or 'image'; got 'dic'"):
        Reconstructor(ref, G55, refine_method="dic")
