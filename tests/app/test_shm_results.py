"""Shared-memory blocks between a batch run's workers and its process, filled again once written.

The worker's side and the run's side are played here by one process (the blocks are real
/dev/shm blocks; the hand-over between processes is tested end to end in test_parallel.py,
where parallel runs give the serial run's heights)."""

import os

import numpy as np
import pytest

from app.batch.shm_results import ParentBlocks, SharedFrame
from app.batch.writer import OutputFrame

pytestmark = pytest.mark.skipif(not os.path.isdir("/dev/shm"), reason="looks for the blocks in /dev/shm")


def _frame(value: float) -> OutputFrame:
    height = np.full((6, 5), value, np.float32)
    height[2, 3] = -value  # not one value: a misplaced offset shows
    return OutputFrame(shape=(6, 5), maps={"height": height, "valid": np.ones((6, 5), np.uint8)})


@pytest.fixture
def run_side():
    """The run's :class:`ParentBlocks` and a list for the frames a test makes: each handed
    back and every mapping closed at the end, and none of their names left in /dev/shm."""
    blocks, made = ParentBlocks(), []
    yield blocks, made
    for frame in made:
        frame.discard(blocks)
    blocks.close()
    assert not [f for f in made if os.path.exists(f"/dev/shm/{f.name}")]


def test_a_block_is_filled_again_only_once_the_run_has_written_its_frame(run_side):
    blocks, made = run_side
    first = SharedFrame.put(_frame(1.0), run_key="test-run")
    made.append(first)
    taken = first.take(blocks)
    assert not os.path.exists(f"/dev/shm/{first.name}"), "the name stays in /dev/shm after the take"
    np.testing.assert_array_equal(taken.maps["height"], _frame(1.0).maps["height"])

    second = SharedFrame.put(_frame(2.0), run_key="test-run")  # the first is not written yet
    made.append(second)
    assert second.name != first.name
    np.testing.assert_array_equal(taken.maps["height"], _frame(1.0).maps["height"])

    taken.done()  # written: its block is free again
    third = SharedFrame.put(_frame(3.0), run_key="test-run")
    made.append(third)
    assert third.name == first.name
    taken = third.take(blocks)
    np.testing.assert_array_equal(taken.maps["height"], _frame(3.0).maps["height"])
    np.testing.assert_array_equal(taken.maps["valid"], 1)

    kept = taken.maps["height"][2:]  # a caller keeps a view past the write
    taken.done()
    fourth = SharedFrame.put(_frame(4.0), run_key="test-run")
    made.append(fourth)
    assert fourth.name not in (first.name, second.name)
    np.testing.assert_array_equal(kept, _frame(3.0).maps["height"][2:])


def test_a_discarded_frame_frees_its_block(run_side):
    blocks, made = run_side
    first = SharedFrame.put(_frame(1.0), run_key="test-discard")
    made.append(first)
    first.discard(blocks)
    again = SharedFrame.put(_frame(5.0), run_key="test-discard")
    made.append(again)
    assert again.name == first.name
    np.testing.assert_array_equal(again.take(blocks).maps["height"], _frame(5.0).maps["height"])
