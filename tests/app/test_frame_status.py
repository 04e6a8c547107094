"""Which errors are a frame's fault (stored invalid, the run goes on) and which the run's (it stops).

A full disk is the run's: every later frame would fail the same way, and
storing them "invalid" would hide that nothing more can be written.
"""

import pytest

from app.batch import parallel
from app.batch.frame_status import FrameStatus, measure_frame, outcome_of_error
from app.capture.recorder import DiskFullError as RecorderDiskFullError
from app.files.h5safe import DiskFullError
from app.files.imageio import FrameItem
from processing import forward as F
from processing.errors import AllInvalidError, TirdeflectError
from processing.geometry import Geometry


def _disk_full():
    return DiskFullError("no room on /data for out.h5 (12 MB free); free space or give --out on another disk")


def test_a_full_disk_is_the_runs_fault_not_the_frames():
    assert outcome_of_error(_disk_full()) is None
    assert outcome_of_error(RecorderDiskFullError("the recorder's disk is full")) is None
    # the frame's own faults stay the frame's
    assert outcome_of_error(AllInvalidError("no part of the frame could be measured")).status == FrameStatus.NO_CONTRAST
    assert outcome_of_error(TirdeflectError("something about this frame")).status == FrameStatus.OTHER


def test_measuring_a_frame_lets_a_full_disk_through():
    ref, _ = F.render_tir(F.FlatSurface(), _G55, (64, 64), F.Checkerboard(period_mm=2.0), supersample=1)
    frame = F.quantize(ref, bits=8)

    def reconstruct(image, grid):
        raise _disk_full()  # e.g. the FFT wisdom or a cache written on the way

    with pytest.raises(DiskFullError, match="no room on /data"):
        measure_frame(reconstruct, frame, frame.shape, "full")
    # a frame whose reading ended in a full disk (a worker's spill) stops the run too
    item = FrameItem(image=None, source="frames.h5", index_in_source=3, sequence_index=3, error=_disk_full())
    with pytest.raises(DiskFullError):
        parallel.measure(None, item, frame.shape, "full")


_G55 = Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False)
