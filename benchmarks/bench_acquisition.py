"""Acquisition benchmark: camera thread -> ring buffer rate, recorder throughput, memory over a soak.

Run from the repository root::

    python3 benchmarks/bench_acquisition.py                 # about 40 s
    python3 benchmarks/bench_acquisition.py --soak-s 600    # plus a 10-minute soak

Prints, all measured in this run:

1. baseline: a plain ``np.copyto`` loop into a preallocated ring array (the
   memory-bandwidth ceiling of what any camera thread can do here);
2. the synthetic camera at 1024x1024 Mono8 through :class:`app.capture.acquisition.Acquisition`
   into the ring: unpaced (``max_rate``: how fast the thread can go) and paced at
   rising frame rates, each checked for drops (camera frame-id gaps, i.e. the
   thread fell more than the camera's 16 buffers behind); the highest rate
   with 0 drops, as frames/s, GB/s and a ratio to the baseline;
3. recorder throughput to disk (``RecordingFile`` in a temporary folder, > 2 GB
   so the large-file path is exercised, read back at the end), and the camera
   + recorder pipeline at a paced rate, with its drop summary;
4. resident memory (RSS) at start and end of a soak: camera thread + a
   newest-only consumer + an every-frame cursor consumer.
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from app.capture.acquisition import Acquisition  # noqa: E402
from app.capture.recorder import Recorder, RecordingFile  # noqa: E402
from app.capture.ringbuffer import RingClosed  # noqa: E402
from drivers.synthetic import SyntheticCamera  # noqa: E402

SHAPE = (1024, 1024)
FRAME_BYTES = SHAPE[0] * SHAPE[1]


def rss_mb() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def source_frames(n=8):
    rng = np.random.default_rng(0)
    return rng.integers(0, 256, size=(n,) + SHAPE, dtype=np.uint8)


def baseline_copy(frames, seconds: float, ring_frames: int = 64) -> float:
    ring = np.empty((ring_frames,) + SHAPE, np.uint8)
    ring.fill(0)
    n = 0
    t0 = time.perf_counter()
    while True:
        for _ in range(64):
            np.copyto(ring[n % ring_frames], frames[n % len(frames)])
            n += 1
        if time.perf_counter() - t0 >= seconds:
            break
    return n / (time.perf_counter() - t0)


def run_acquisition(frames, seconds: float, *, rate_hz=None, ring_frames=64, n_buffers=16, nice=-10):
    """Returns (fps_measured, acquired, lost_upstream, cpu_s_per_frame)."""
    cam = SyntheticCamera(frames, frame_rate_hz=rate_hz or 1000.0, max_rate=rate_hz is None,
                          n_buffers=n_buffers).open()
    try:
        acq = Acquisition(cam, ring_frames=ring_frames, stall_timeout_s=None, thread_nice=nice)
        c0 = time.process_time()
        t0 = time.perf_counter()
        acq.start()
        acq.wait(seconds)
        acq.stop(10.0)
        wall = time.perf_counter() - t0
        cpu = time.process_time() - c0
        n = acq.acquired
        st = cam.statistics()
        lost = acq.lost_upstream
        # the thread's count equals the camera's own (ids skipped before the first frame belong to no frame)
        assert lost + (acq.first_frame_id or 0) == st["n_underruns"], (lost, acq.first_frame_id, st)
        return n / wall, n, lost, cpu / max(n, 1)
    finally:
        cam.close()


def recorder_throughput(folder: Path, n_frames: int) -> tuple:
    frames = source_frames(4)
    path = folder / "bench-write.h5"
    rf = RecordingFile(path, shape=SHAPE, dtype=np.uint8, n_frames=n_frames)
    t0 = time.perf_counter()
    last_flush = t0
    for i in range(n_frames):
        rf.write(frames[i % 4], (i, i, i, i, 0, i))
        now = time.perf_counter()
        if now - last_flush > 0.5:
            rf.flush()
            last_flush = now
    rf.close()
    wall = time.perf_counter() - t0
    size = os.path.getsize(path)
    import h5py

    with h5py.File(path, "r") as f:  # frames beyond the 2 GB / 4 GB offsets read back exactly
        for i in (0, n_frames // 2, n_frames - 1):
            assert np.array_equal(f["frames"][i], frames[i % 4]), f"frame {i} differs"
        assert f["frames"].attrs["frames_written"] == n_frames
    os.remove(path)
    return n_frames * FRAME_BYTES / wall / 1e6, size, wall


def pipeline(folder: Path, rate_hz: float, n_frames: int, n_buffers: int = 32, burst: bool = False):
    frames = source_frames(8)
    cam = SyntheticCamera(frames, frame_rate_hz=rate_hz, n_buffers=n_buffers).open()
    try:
        acq = Acquisition(cam, ring_frames=n_frames if burst else 256, stall_timeout_s=None)
        path = folder / "bench-pipeline.h5"
        rec = Recorder(acq.ring, path, n_frames=n_frames, acquisition=acq, defer=burst)
        rec.begin(0)
        acq.stop_after(n_frames - 1)
        t0 = time.perf_counter()
        acq.start()
        rec.wait(600)
        wall = time.perf_counter() - t0
        acq.stop()
        s = rec.summary()
        os.remove(path)
        return s, wall
    finally:
        cam.close()


def soak(frames, seconds: float, rate_hz: float, n_buffers: int = 32):
    cam = SyntheticCamera(frames, frame_rate_hz=rate_hz, n_buffers=n_buffers).open()
    acq = Acquisition(cam, ring_frames=128, stall_timeout_s=None)
    cur = acq.ring.cursor(0)
    counts = dict(cursor=0, latest=0)
    stop = threading.Event()

    def every_frame():
        buf = np.empty(SHAPE, np.uint8)
        while not stop.is_set():
            try:
                if cur.read(0.2, out=buf) is not None:
                    counts["cursor"] += 1
            except RingClosed:
                return

    def newest():
        buf = np.empty(SHAPE, np.uint8)
        while not stop.is_set():
            if acq.ring.latest(0.2, out=buf) is not None:
                counts["latest"] += 1
            time.sleep(0.01)  # a 100 Hz display

    threads = [threading.Thread(target=every_frame), threading.Thread(target=newest)]
    acq.start()
    for t in threads:
        t.start()
    time.sleep(min(2.0, seconds))  # let allocations settle before the first RSS reading
    rss0 = rss_mb()
    samples = [rss0]
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        acq.wait(min(10.0, max(0.0, t_end - time.monotonic())))
        samples.append(rss_mb())
    stop.set()
    acq.stop()
    for t in threads:
        t.join(5)
    cam.close()
    return rss0, samples[-1], max(samples), acq.acquired, acq.lost_upstream, cur.lost, counts


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=2.0, help="duration of each rate step, s")
    ap.add_argument("--trials", type=int, default=3, help="runs per rate step")
    ap.add_argument("--n-buffers", type=int, default=32, help="synthetic camera buffer pool (Aravis default 32)")
    ap.add_argument("--soak-s", type=float, default=10.0, help="soak duration, s (600 for the 10-minute soak)")
    ap.add_argument("--soak-rate-hz", type=float, default=1000.0)
    ap.add_argument("--write-gb", type=float, default=2.2, help="size of the recorder throughput file, GB")
    ap.add_argument("--tmp", default=None, help="folder for the recorder files (default: system temp)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR, format="    (log) %(message)s")

    print(f"tirdeflect acquisition benchmark: {SHAPE[0]}x{SHAPE[1]} Mono8 ({FRAME_BYTES / 1e6:.2f} MB/frame), "
          f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}, RSS at start {rss_mb():.0f} MB")
    frames = source_frames(8)

    base = baseline_copy(frames, args.seconds)
    print(f"\n[1] baseline np.copyto loop into a ring array: {base:8.0f} frames/s = {base * FRAME_BYTES / 1e9:5.2f} GB/s")

    fps, n, lost, cpu = run_acquisition(frames, args.seconds)
    print(f"\n[2] camera thread -> ring (synthetic camera, unpaced max_rate): {fps:8.0f} frames/s = "
          f"{fps * FRAME_BYTES / 1e9:5.2f} GB/s ({fps / base:.2f} x baseline), {cpu * 1e6:.0f} us CPU/frame")
    print(f"    paced free-running camera ({args.n_buffers} camera buffers, like the Aravis driver's default), "
          f"{args.trials} trials per rate; drops = frame-id gaps counted by the thread (checked equal to the "
          "camera's own underrun count):")
    best = 0.0
    for rate in (500, 1000, 1500, 2000, 3000, 4000, 6000, 8000):
        if rate > 1.5 * fps:
            break
        got, drops = [], []
        for _ in range(args.trials):
            f, n, lost, cpu = run_acquisition(frames, args.seconds, rate_hz=rate, n_buffers=args.n_buffers)
            got.append(f)
            drops.append(lost)
        clean = sum(1 for d in drops if d == 0)
        print(f"    {rate:6d} Hz asked: {min(got):8.1f} .. {max(got):8.1f} frames/s got, dropped per trial "
              f"{drops}  ({clean}/{args.trials} trials clean)")
        if clean == args.trials:
            best = max(best, min(got))
    print(f"    highest rate with 0 drops in every trial: {best:.0f} frames/s = {best * FRAME_BYTES / 1e9:.2f} GB/s "
          f"({best / base:.2f} x baseline); goal >= 1000 frames/s, 1 GB/s: {'met' if best >= 1000 else 'NOT met'}")
    print(f"    load average now: {' '.join(f'{x:.2f}' for x in os.getloadavg())} (shared machine: other "
          "programs' stalls longer than the camera's buffer pool show up as drops)")

    folder = Path(args.tmp or tempfile.gettempdir()) / f"tirdeflect-bench-{os.getpid()}"
    folder.mkdir(parents=True, exist_ok=True)
    try:
        n_write = int(args.write_gb * 1e9 / FRAME_BYTES)
        free = shutil.disk_usage(folder).free
        if free < n_write * FRAME_BYTES * 1.5:
            n_write = int(free / FRAME_BYTES / 3)
            print(f"\n(only {free / 1e9:.1f} GB free: writing {n_write} frames)")
        mbs, size, wall = recorder_throughput(folder, n_write)
        print(f"\n[3] recorder to disk ({folder}): {n_write} frames, {size / 1e9:.2f} GB file in {wall:.1f} s = "
              f"{mbs:.0f} MB/s ({mbs * 1e6 / FRAME_BYTES:.0f} frames/s; read back beyond 2**31 bytes: ok)")
        for rate, burst in ((250, False), (500, False), (1000, False), (1000, True)):
            n_rec = int(rate * args.seconds)
            s, wall = pipeline(folder, rate, n_rec, args.n_buffers, burst)
            mode = f"burst to RAM ({n_rec}-frame ring), then disk" if burst else "streaming (256-frame ring)"
            print(f"    camera {rate:4d} Hz -> ring -> recorder, {mode}: {s['frames_written']} of "
                  f"{s['frames_planned']} frames written in {wall:.1f} s, lost upstream {s['lost_upstream_id_gaps']}, "
                  f"ring overrun {s['lost_ring_overrun']}, backlog max {s['recorder_backlog_max']}")
    finally:
        shutil.rmtree(folder, ignore_errors=True)

    rss0, rss1, rss_max, n, lost, cur_lost, counts = soak(frames, args.soak_s, args.soak_rate_hz, args.n_buffers)
    print(f"\n[4] soak {args.soak_s:.0f} s at {args.soak_rate_hz:.0f} Hz (camera thread + every-frame cursor + "
          f"newest-only consumer): {n} frames, {lost} dropped upstream, cursor lost {cur_lost}, "
          f"latest() took {counts['latest']}")
    print(f"    RSS start {rss0:.1f} MB, end {rss1:.1f} MB, max {rss_max:.1f} MB, growth {rss1 - rss0:+.1f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
