"""Camera thread on the real synthetic camera: exact drop accounting, clean stop, clear errors."""

import time

import numpy as np
import pytest

from app.capture.acquisition import Acquisition, AcquisitionError
from app.capture.ringbuffer import MemoryBudgetError, RingClosed
from drivers.base import FrameFlags
from drivers.synthetic import SyntheticCamera


def _frames(n=64, shape=(32, 32)):
    """Frame k is uniform with value k (mod 256): content identifies the frame."""
    return (np.arange(n) % 256).astype(np.uint8)[:, None, None] * np.ones((1,) + shape, np.uint8)


def _read(cursor, n, timeout_s=5.0):
    out = []
    for _ in range(n):
        f = cursor.read(timeout_s)
        assert f is not None, f"no frame within {timeout_s} s"
        out.append((f.sequence, f.frame_id, int(f.flags), int(f.image[0, 0])))
    return out


def test_injected_drops_counted_exactly_with_flags():
    drops = {5, 6, 7, 40}
    with SyntheticCamera(_frames(), frame_rate_hz=400, drop_frames=drops) as cam:
        acq = Acquisition(cam, ring_frames=256)
        cur = acq.ring.cursor(0)
        with acq:
            got = _read(cur, 80)
    ids = [g[1] for g in got]
    assert [g[0] for g in got] == list(range(80))  # host sequence contiguous
    assert set(range(ids[-1] + 1)) - set(ids) == drops  # the camera ids show exactly the drops
    assert acq.lost_upstream == 4 and acq.id_gaps[:2] == [(5, 3), (40, 1)]
    flagged = [g[1] for g in got if g[2] & FrameFlags.ID_GAP_BEFORE]
    assert flagged == [8, 41]
    # images belong to their ids (copy into the ring is right)
    assert all(g[3] == g[1] % 64 for g in got)
    # the id gaps also show as timestamp jumps of (missing + 1) periods, but no extra frames are inferred
    assert acq.lost_by_time == 0
    assert acq.stats()["state"] == "stopped"


def _triggers_paused_50_ms(device_timestamps):
    """``(acquisition, 20 frames before, 5 after)``: the synthetic camera software-triggered at 200 Hz by the
    camera thread, the triggers paused for 50 ms between (the ids stay contiguous, the clock jumps)."""
    with SyntheticCamera(_frames(), frame_rate_hz=200, device_timestamps=device_timestamps) as cam:
        cam.configure(trigger_mode="On", trigger_source="Software")
        acq = Acquisition(cam, ring_frames=256)
        acq.set_software_trigger_rate(200.0)
        cur = acq.ring.cursor(0)
        with acq:
            before = _read(cur, 20)
            acq.set_software_trigger_rate(None)
            time.sleep(0.05)  # the pause *is* the stimulus (50 ms of no triggers), not a wait for a result
            acq.set_software_trigger_rate(200.0)
            after = _read(cur, 5)
    return acq, before, after

def test_timestamp_gap_with_contiguous_ids_is_flagged_and_estimated():
    """GenICam software trigger paced by the camera thread; a 50 ms pause in the triggers keeps the
    ids contiguous but makes the device clock jump: the gap detector must see it (about 10 periods)."""
    acq, before, after = _triggers_paused_50_ms(device_timestamps=True)
    ids = [g[1] for g in before + after]
    assert ids == list(range(ids[0], ids[0] + 25))  # contiguous: ids alone cannot see anything
    gaps = [g for g in before + after if g[2] & FrameFlags.TIME_GAP_BEFORE]
    assert len(gaps) >= 1 and gaps[-1][0] >= 20  # flagged on the first frame after the pause
    # the pause lasted >= 50 ms = 10 periods at 200 Hz: at least 9 frame slots were empty
    assert acq.lost_by_time >= 9



def test_a_gap_on_the_hosts_clock_is_flagged_but_not_counted_as_lost_frames():
    """Frames without the camera's timestamp are timed by the host's clock, which jitters by tens of ms: a gap
    there is flagged (the recorder's "timestamp gaps") but is no count of lost frames, as the recording file
    says too (by-hand trial 8 Dec 2026: GigE at 90 % packet loss, every id there, the window's status bar
    "DROPPED camera 3", the file 0 lost). The 50 ms pause of the test above, on a camera without timestamps."""
    acq, before, after = _triggers_paused_50_ms(device_timestamps=False)
    ids = [g[1] for g in before + after]
    assert ids == list(range(ids[0], ids[0] + 25))
    assert all(g[2] & FrameFlags.NO_DEVICE_TIMESTAMP for g in before + after) and acq.no_timestamp >= 25
    assert any(g[2] & FrameFlags.TIME_GAP_BEFORE for g in after) and acq.time_gaps >= 1  # flagged
    assert acq.lost_by_time == 0 and acq.lost_upstream == 0  # not counted: the ids say nothing was lost


def test_stall_is_an_error_within_its_timeout_and_reaches_consumers():
    with SyntheticCamera(_frames(10), frame_rate_hz=500, loop=False) as cam:
        acq = Acquisition(cam, ring_frames=16, stall_timeout_s=0.5, fetch_timeout_s=0.1)
        cur = acq.ring.cursor(0)
        t0 = time.monotonic()
        acq.start()
        assert acq.wait(30.0), "camera thread did not end"
        took = time.monotonic() - t0
    # never before its timeout; the upper bound is a hang detector, >= 10x above need (the 10 frames
    # and the 0.5 s timeout take 0.52-0.6 s quiet; benchmarks/bench_latencies.py)
    assert 0.5 <= took < 6.0
    assert acq.state == "error" and "no frame from camera" in acq.error and "0.5 s" in acq.error
    assert len(_read(cur, 10)) == 10  # everything received is still readable
    with pytest.raises(RingClosed, match="stall"):
        cur.read(1.0)


def test_waiting_for_a_trigger_is_not_a_stall_and_stop_is_prompt():
    with SyntheticCamera(_frames(), frame_rate_hz=100) as cam:
        cam.configure(trigger_mode="On", trigger_source="Line1")  # no line here: no frames ever
        acq = Acquisition(cam, ring_frames=8, stall_timeout_s=0.2, fetch_timeout_s=0.1)
        acq.start()
        assert not acq.wait(0.6)  # still running after 3 stall timeouts
        t0 = time.monotonic()
        acq.stop(timeout_s=10.0)
        # within a few fetch slices (0.1 s): hang detector, >= 10x above need
        assert time.monotonic() - t0 < 2.0
    assert acq.state == "stopped" and acq.error is None and acq.fetch_timeouts >= 3


def test_stop_after_makes_an_exact_burst():
    with SyntheticCamera(_frames(), frame_rate_hz=1000) as cam:
        acq = Acquisition(cam, ring_frames=64)
        acq.stop_after(49)
        acq.start()
        assert acq.wait(60.0)  # hang detector: 0.05 s of frames
    assert acq.acquired == 50 and acq.ring.head == 50 and acq.state == "stopped"


def test_ring_memory_is_checked_before_allocation():
    with SyntheticCamera(_frames(2, (1024, 1024)), frame_rate_hz=10) as cam:
        with pytest.raises(MemoryBudgetError, match=r"ring buffer of 100000000 frames 1024x1024 uint8 needs"):
            Acquisition(cam, ring_frames=10**8)
        assert Acquisition.ring_bytes_for((1024, 1024), np.uint8, 10) == 10 * (1024 * 1024 + 44)
        acq = Acquisition(cam, ring_bytes=10 * (1024 * 1024 + 44))
        assert acq.ring.n_frames == 10


def test_start_twice_is_refused():
    with SyntheticCamera(_frames(), frame_rate_hz=100) as cam:
        acq = Acquisition(cam, ring_frames=8)
        with acq:
            with pytest.raises(AcquisitionError, match="already started"):
                acq.start()


def test_camera_that_refuses_to_start_is_a_clear_error():
    cam = SyntheticCamera(_frames(), frame_rate_hz=100).open()
    acq = Acquisition(cam, ring_frames=8)
    cam.close()  # e.g. unplugged between configuration and start
    with pytest.raises(AcquisitionError, match="camera 'synthetic' did not start: .*closed"):
        acq.start()
    assert acq.state == "error" and acq.ring.closed and acq.wait(1.0)


def test_driver_error_mid_stream_ends_the_thread_cleanly():
    base = _frames(4)

    def frames(k):  # the 21st frame comes back at another size: the driver refuses it
        return base[k % 4] if k < 20 else np.zeros((16, 16), np.uint8)

    with SyntheticCamera(frames, frame_rate_hz=500) as cam:
        acq = Acquisition(cam, ring_frames=32)
        cur = acq.ring.cursor(0)
        acq.start()
        assert acq.wait(5.0)
    assert acq.state == "error" and "failed" in acq.error and "frames(20)" in acq.error
    assert acq.acquired == 20 and len(_read(cur, 20)) == 20
    with pytest.raises(RingClosed, match=r"frames\(20\)"):
        cur.read(1.0)


def test_a_camera_slower_than_its_set_rate_is_named_not_counted_as_losses(caplog):
    """By-hand trial of 7 Dec 2026: the fake GigE camera set to 1000 Hz delivered 228 Hz; 99 of 100 frames
    were flagged as time gaps and the summary said "timestamp gaps suggest about 216 more", exit 0, with no
    word of the real rate. The camera here is paced at 200 Hz while 800 Hz is what is expected: the rate it
    delivers is measured and said, and its frames are no gaps; a real pause after it still is one."""
    from app.capture.recorder import summary_rows

    with SyntheticCamera(_frames(), frame_rate_hz=200) as cam:
        cam.configure(trigger_mode="On", trigger_source="Software")
        acq = Acquisition(cam, ring_frames=256, frame_rate_hz=800.0)
        acq.set_software_trigger_rate(200.0)
        cur = acq.ring.cursor(0)
        with caplog.at_level("WARNING", logger="tirdeflect.acquisition"), acq:
            steady = _read(cur, 40)
            acq.set_software_trigger_rate(None)
            time.sleep(0.1)  # the stimulus: 100 ms without triggers, 20 periods of the rate delivered
            acq.set_software_trigger_rate(200.0)
            after = _read(cur, 5)
    # judged by the 800 Hz set, every frame after the 8th was a gap; by the rate delivered, only a trigger the
    # loaded machine sent late is (one of 40 in a CI run)
    late = [g for g in steady if g[2] & FrameFlags.TIME_GAP_BEFORE]
    assert len(late) <= 8, late  # (a fifth; the set rate flagged 32 of the 40)
    assert acq.delivered_rate_hz == pytest.approx(200.0, rel=0.2)
    said = [r.getMessage() for r in caplog.records if "not the 800 it is set to" in r.getMessage()]
    assert len(said) == 1, [r.getMessage() for r in caplog.records]
    assert "it is triggered: its triggers set the rate" in said[0]  # (software triggers here)
    assert [g for g in after if g[2] & FrameFlags.TIME_GAP_BEFORE] and acq.lost_by_time >= 10
    rows = dict(summary_rows({"delivered_rate_hz": 201.3, "set_rate_hz": 800.0, "frames_written": 45}))
    assert rows["frame rate"].startswith("the camera delivered 201.3 frames/s, not the 800 it was set to")
    assert "no timestamp" not in rows  # (every frame had the camera's)
    rows = dict(summary_rows({"no_device_timestamp": 31, "frames_written": 150}))
    assert rows["no timestamp"].startswith("31 frames without the camera's timestamp")
