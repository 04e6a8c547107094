"""processing.mask's messages for frames nothing of which could be measured."""

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
