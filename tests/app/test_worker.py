"""Processing worker on the real pipeline: synthetic ray-traced camera -> Acquisition -> ring -> worker."""

from __future__ import annotations

import time

import numpy as np
import pytest

from app.capture.acquisition import Acquisition
from app.capture.worker import ProcessingWorker, ring_source, saturation_percent
from drivers.synthetic import SyntheticCamera

SHAPE = (128, 128)


@pytest.fixture(scope="module")
def scene():
    from app.capture.scene import open_synthetic_camera

    cam, reference, geometry, heights = open_synthetic_camera(shape=SHAPE, n_frames=6, frame_rate_hz=200.0)
    cam.close()
    # the frames the camera streamed, to feed new cameras in each test
    return {"frames": np.asarray(cam._frames), "reference": reference, "geometry": geometry, "heights": heights}


def _pipeline(frames, rate_hz, *, reference, geometry, loop=True, ring_frames=64):
    from processing import Reconstructor

    cam = SyntheticCamera(frames, frame_rate_hz=rate_hz, loop=loop).open()
    acq = Acquisition(cam, ring_frames=ring_frames, stall_timeout_s=None)
    worker = ProcessingWorker(ring_source(acq.ring), Reconstructor(reference, geometry), grid="decimated")
    return cam, acq, worker


def test_newest_only_every_frame_processed_or_counted(scene):
    """Frames are either processed or counted as skipped, exactly; the last frame is always processed."""
    cam, acq, worker = _pipeline(scene["frames"], 400.0, reference=scene["reference"], geometry=scene["geometry"])
    try:
        acq.start()
        worker.start()
        assert worker.wait_for(lambda p: worker.processed >= 20, timeout_s=20) is not None
        acq.stop_after(acq.ring.head + 10)
        assert acq.wait(10.0)
        last = acq.ring.head - 1
        p = worker.wait_for(lambda p: p.seq == last, timeout_s=10)
        assert p is not None, f"newest frame {last} never processed (latest {worker.latest().seq})"
        assert worker.processed + worker.skipped == acq.ring.head
        assert worker.skipped == acq.ring.latest_skipped
        assert worker.failed == 0 and worker.last_error is None
    finally:
        worker.stop(5.0)
        acq.stop()
        cam.close()


def test_published_heights_are_those_of_the_published_frame(scene):
    """Each result belongs to its frame: height error against that frame's true surface, not another's."""
    cam, acq, worker = _pipeline(scene["frames"], 100.0, reference=scene["reference"], geometry=scene["geometry"])
    heights = scene["heights"]
    try:
        acq.start()
        worker.start()
        got = {}
        deadline = time.monotonic() + 20
        while len(got) < 3 and time.monotonic() < deadline:
            p = worker.wait_for(lambda p: p.result is not None and p.seq not in got, timeout_s=5)
            if p is not None:
                got[p.seq] = p
        assert len(got) >= 3
        for seq, p in got.items():
            r = p.result
            k = seq % len(heights)  # ids contiguous from 0 (no drops): frame id == ring sequence
            np.testing.assert_array_equal(p.image, scene["frames"][k])
            ri = np.round(r.rows_px).astype(int)
            ci = np.round(r.cols_px).astype(int)
            ok = r.valid
            errs = []
            for j in range(len(heights)):
                t = heights[j][np.ix_(ri, ci)]
                d = (r.height - t)[ok]
                errs.append(np.sqrt(np.mean((d - d.mean()) ** 2)))
            t = heights[k][np.ix_(ri, ci)][ok]
            scale = np.sqrt(np.mean((t - t.mean()) ** 2))
            # 128 px live (decimated) grid: about 10 % rms; any other frame's surface is much further off
            assert errs[k] < 0.2 * scale, f"frame {seq}: rms error {errs[k]:.2e} mm vs surface rms {scale:.2e} mm"
            others = [e for j, e in enumerate(errs) if j != k]
            assert errs[k] < 0.5 * min(others), (k, errs)
    finally:
        worker.stop(5.0)
        acq.stop()
        cam.close()


def test_bad_frames_report_errors_and_the_worker_goes_on(scene):
    """An unmeasurable (black) frame publishes its error; a failing listener is reported; good frames follow."""
    good = scene["frames"][0]
    black = np.zeros_like(good)
    frames = np.stack([good] * 6 + [black] * 6 + [good] * 6)
    cam, acq, worker = _pipeline(frames, 30.0, reference=scene["reference"], geometry=scene["geometry"])
    calls = []

    def bad_listener(p):
        calls.append(p.seq)
        raise RuntimeError("listener bug")

    worker.add_listener(bad_listener)
    try:
        acq.start()
        worker.start()
        p_err = worker.wait_for(lambda p: p.error is not None, timeout_s=10)
        assert p_err is not None and p_err.result is None
        assert len(p_err.error) > 20  # a message that says something, from processing.errors
        assert np.array_equal(p_err.image, black)
        p_ok = worker.wait_for(lambda p: p.result is not None and p.seq > p_err.seq, timeout_s=10)
        assert p_ok is not None, worker.counters()
        assert worker.failed >= 1
        assert len(calls) >= 2  # the listener kept being called despite raising
        assert worker.running
    finally:
        t0 = time.monotonic()
        worker.stop(30.0)
        # stops within one poll + one reconstruction (< 0.2 s quiet): hang detector, >= 10x above need
        assert time.monotonic() - t0 < 5.0
        assert not worker.running
        acq.stop()
        cam.close()


def test_saturation_percent_counts_top_code():
    img = np.zeros((64, 64), np.uint16)
    img[:16] = 4095  # a quarter at the 12-bit top code
    assert saturation_percent(img, 12, step=1) == pytest.approx(25.0)
    assert saturation_percent(img, 16, step=1) == 0.0
    assert saturation_percent(img.astype(np.uint8) * 0 + 255, step=2) == pytest.approx(100.0)


@pytest.mark.parametrize("cost_s,least,most", [(0.02, 27, 30), (0.3, 4, 5)])
def test_alignment_ten_a_second_and_a_slow_one_takes_half_the_worker(monkeypatch, cost_s, least, most):
    """Frames every 10 ms for 3 s (on a clock the test drives): an alignment costing 20 ms runs every
    0.1 s (30 times, less what the 10-ms frame steps round off); one costing 0.3 s (the full search
    before a reference) waits as long as it took (every 0.6 s: 5 times, 1.5 s of 3), so heights keep
    at least half of the worker."""
    import types

    import app.capture.worker as worker_module

    clock = [1000.0]
    fake_time = types.SimpleNamespace(monotonic=lambda: clock[0], perf_counter=time.perf_counter,
                                      monotonic_ns=time.monotonic_ns)
    monkeypatch.setattr(worker_module, "time", fake_time)
    calls = []

    def alignment_fn(frame):
        calls.append(clock[0])
        clock[0] += cost_s
        return {"periods_px": np.array([6.0, 6.0])}, None

    worker = ProcessingWorker(lambda after, timeout: None, None, alignment_fn=alignment_fn)
    worker.set_alignment(True)
    frame = np.zeros((32, 32), np.uint8)
    seq = 0
    while clock[0] < 1003.0 - 1e-9:
        worker._process(seq, frame, 0)
        seq += 1
        clock[0] += 0.01
    assert least <= len(calls) <= most
    assert len(calls) * cost_s <= 1.5 + 1e-9
