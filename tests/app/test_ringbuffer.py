"""Ring buffer: every frame in order for the cursor, exact overrun counts, newest-only with counted skips."""

import os
import threading
import time

import numpy as np
import pytest

from app.capture.ringbuffer import MemoryBudgetError, RingBuffer, RingClosed, check_memory, committed_zeros
from drivers.base import FrameFlags


def _img(seq, shape=(8, 8)):
    return np.full(shape, seq % 251, np.uint8)


def _put(ring, seq):
    return ring.put(_img(seq, ring.shape), frame_id=1000 + seq, device_timestamp_ns=seq * 10_000,
                    host_timestamp_ns=seq * 10_000 + 7)


def test_cursor_reads_every_frame_in_order_with_metadata():
    ring = RingBuffer((8, 8), np.uint8, 16)
    cur = ring.cursor(0)
    for s in range(10):
        assert _put(ring, s) == s
    got = [cur.read(0.1) for _ in range(10)]
    assert [f.sequence for f in got] == list(range(10))
    assert [f.frame_id for f in got] == list(range(1000, 1010))
    assert [f.device_timestamp_ns for f in got] == [s * 10_000 for s in range(10)]
    assert all((f.image == s % 251).all() for s, f in enumerate(got))
    assert all(f.flags == FrameFlags.OK and f.lost_before == 0 for f in got)
    assert cur.read(0.01) is None and cur.lost == 0


def test_overrun_is_counted_exactly_and_flagged_on_the_next_frame():
    ring = RingBuffer((8, 8), np.uint8, 8)
    cur = ring.cursor(0)
    for s in range(20):  # the writer laps the idle cursor: frames 0..11 are gone
        _put(ring, s)
    f = cur.read(0.1)
    assert f.sequence == 12 and (f.image == 12).all()
    assert f.lost_before == 12 and f.flags & FrameFlags.RING_OVERRUN_BEFORE
    assert cur.lost == 12 and cur.lost_events == [(0, 12)]
    rest = [cur.read(0.1).sequence for _ in range(7)]
    assert rest == list(range(13, 20)) and cur.lost == 12


def test_missing_device_timestamp_is_flagged_not_zero():
    ring = RingBuffer((8, 8), np.uint8, 4)
    ring.put(_img(0), frame_id=5, device_timestamp_ns=None, host_timestamp_ns=123)
    f = ring.cursor(0).read(0.1)
    assert f.device_timestamp_ns is None and f.flags & FrameFlags.NO_DEVICE_TIMESTAMP


def test_latest_returns_newest_and_counts_skips():
    ring = RingBuffer((8, 8), np.uint8, 8)
    for s in range(5):
        _put(ring, s)
    assert ring.latest().sequence == 4 and ring.latest_skipped == 4
    for s in range(5, 8):
        _put(ring, s)
    assert ring.latest().sequence == 7 and ring.latest_skipped == 6
    t0 = time.monotonic()
    assert ring.latest(0.05) is None  # nothing newer: waits the timeout, returns None
    assert time.monotonic() - t0 >= 0.045


def test_wait_wakes_on_commit_not_on_timeout():
    ring = RingBuffer((8, 8), np.uint8, 4)
    t = threading.Timer(0.05, _put, (ring, 0))
    t.start()
    t0 = time.monotonic()
    assert ring.wait_for(0, 30.0)
    # woken by the commit at 0.05 s, not by the 30 s timeout: hang detector, >= 10x above need
    assert time.monotonic() - t0 < 5.0
    t.join()


def test_concurrent_writer_no_torn_frames_and_exact_accounting():
    """A fast writer and a slow cursor: every frame read is intact; read + lost == written."""
    n, shape = 4000, (64, 64)
    ring = RingBuffer(shape, np.uint8, 16)
    cur = ring.cursor(0)

    def writer():
        for s in range(n):
            ring.put(np.full(shape, s % 251, np.uint8), s, s, s)
        ring.close()

    th = threading.Thread(target=writer)
    th.start()
    seqs = []
    rng = np.random.default_rng(1)
    while True:
        try:
            f = cur.read(2.0)
        except RingClosed as exc:
            assert exc.error is None
            break
        assert f is not None, "reader starved for 2 s"
        # intact copy: uniform and equal to the sequence's value
        assert f.image.min() == f.image.max() == f.sequence % 251
        assert f.frame_id == f.sequence
        seqs.append(f.sequence)
        if rng.random() < 0.02:
            time.sleep(0.002)  # fall behind now and then
    th.join(5)
    assert all(b > a for a, b in zip(seqs, seqs[1:]))
    assert len(seqs) + cur.lost == n
    gaps = sum(b - a - 1 for a, b in zip(seqs, seqs[1:])) + seqs[0]
    assert gaps == cur.lost


def test_closed_with_error_reaches_the_consumer_after_draining():
    ring = RingBuffer((8, 8), np.uint8, 4)
    cur = ring.cursor(0)
    _put(ring, 0)
    ring.close("camera unplugged")
    assert cur.read(0.1).sequence == 0
    with pytest.raises(RingClosed, match="camera unplugged") as info:
        cur.read(0.1)
    assert info.value.error == "camera unplugged"


def test_memory_cost_is_known_before_allocation():
    need = RingBuffer.bytes_for((1024, 1024), np.uint16, 100)
    assert need == 100 * (1024 * 1024 * 2 + 44)
    assert RingBuffer.frames_for((1024, 1024), np.uint16, need) == 100
    with pytest.raises(MemoryBudgetError, match=r"needs 209\.72 MB but only 100\.00 MB"):
        check_memory(need, "ring buffer of 100 frames", available_bytes=100_000_000)


def test_bad_arguments_are_echoed():
    with pytest.raises(ValueError, match="uint8 or uint16; got float32"):
        RingBuffer((4, 4), np.float32, 4)
    with pytest.raises(ValueError, match="at least 2 frames; got n_frames=1"):
        RingBuffer((4, 4), np.uint8, 1)
    ring = RingBuffer((4, 4), np.uint8, 4)
    with pytest.raises(ValueError, match=r"frame shape \(5, 4\) does not match the ring's \(4, 4\)"):
        ring.put(np.zeros((5, 4), np.uint8), 0, 0, 0)


def _resident_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


@pytest.mark.skipif(not os.path.exists("/proc/self/statm"), reason="needs Linux's /proc")
def test_ring_memory_is_committed_when_made_not_while_the_camera_writes():
    """The ring's frames are in memory (resident) as soon as the ring exists, zeroed and writable:
    writing a frame at the camera's rate takes no page fault. 64 MiB must show in the resident
    size (a lazily mapped array adds nothing until written)."""
    before = _resident_bytes()
    ring = RingBuffer((512, 512), np.uint16, 128)  # 64 MiB
    grown = _resident_bytes() - before
    assert grown >= 0.95 * ring.nbytes, (grown, ring.nbytes)
    assert ring.frames.flags.writeable and not ring.frames.any()
    small = committed_zeros((3, 5), np.uint8)  # below a page: written zeros, same result
    assert small.shape == (3, 5) and small.dtype == np.uint8 and not small.any()
