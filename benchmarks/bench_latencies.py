"""Latencies the tests only bound loosely (their bounds are hang detectors, >= 10x above need).

Run from the repository root (about 20 s; the GigE part needs arv-fake-gv-camera-0.8)::

    python3 benchmarks/bench_latencies.py

Prints, all measured in this run, each with a ratio to the baseline or to the
timeout it is bounded by:

1. baseline: a ``threading.Condition`` notified from a ``threading.Timer``
   thread, the time until the waiting thread runs (what any wake-up costs here);
2. the synthetic camera: software trigger from another thread -> the waiting
   ``fetch`` returns (tests/drivers/test_synthetic.py bounds it at 1 s);
3. :class:`app.capture.acquisition.Acquisition`: a camera that stops sending ->
   the stall error, against ``stall_timeout_s`` (tests/app/test_acquisition.py);
   ``stop()`` while waiting for a trigger;
4. the GigE fake camera killed mid-stream -> ``CameraLost`` from ``fetch``, against
   the driver's bound (``lost_timeout_s`` + one probe + one fetch slice), the
   close that follows, and the garbage collection after the exception is dropped
   (tests/drivers/test_aravis.py).
"""

from __future__ import annotations

import gc
import statistics
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from app.capture.acquisition import Acquisition  # noqa: E402
from drivers.base import CameraLost, FetchTimeout  # noqa: E402
from drivers.synthetic import SyntheticCamera  # noqa: E402

N = 50


def _row(name: str, values_s, reference_s: float, reference_name: str) -> None:
    values = np.asarray(values_s, float)
    med = float(np.median(values))
    print(f"{name:<48} median {med * 1e3:9.3f} ms  max {values.max() * 1e3:9.3f} ms  "
          f"= {med / reference_s:7.2f} x {reference_name}")


def baseline_wake() -> list[float]:
    cond = threading.Condition()
    out = []
    for _ in range(N):
        fired = []

        def notify():
            with cond:
                fired.append(time.monotonic_ns())
                cond.notify()

        with cond:
            t = threading.Timer(0.002, notify)
            t.start()
            cond.wait_for(lambda: fired, 5.0)
            out.append((time.monotonic_ns() - fired[0]) * 1e-9)
        t.join()
    return out


def synthetic_trigger_wake() -> list[float]:
    frames = np.random.default_rng(1).integers(0, 255, size=(8, 48, 64)).astype(np.uint8)
    out = []
    with SyntheticCamera(frames) as cam:
        cam.configure(trigger_mode="On", trigger_source="Software")
        cam.start()
        for _ in range(N):
            t = threading.Timer(0.002, cam.trigger_software)
            t.start()
            frame = cam.fetch(10.0)
            t.join()
            out.append((frame.host_timestamp_ns - frame.timestamp_ns) * 1e-9)
    return out


def acquisition_stall_and_stop(trials: int = 3) -> tuple[list[float], list[float]]:
    frames = (np.arange(10) % 256).astype(np.uint8)[:, None, None] * np.ones((1, 32, 32), np.uint8)
    stalls, stops = [], []
    for _ in range(trials):
        with SyntheticCamera(frames, frame_rate_hz=500, loop=False) as cam:
            acq = Acquisition(cam, ring_frames=16, stall_timeout_s=0.5, fetch_timeout_s=0.1)
            t0 = time.monotonic()
            acq.start()
            acq.wait(30.0)
            stalls.append(time.monotonic() - t0)
        with SyntheticCamera(frames, frame_rate_hz=100) as cam:
            cam.configure(trigger_mode="On", trigger_source="Line1")  # never a frame
            acq = Acquisition(cam, ring_frames=8, stall_timeout_s=0.2, fetch_timeout_s=0.1)
            acq.start()
            acq.wait(0.3)
            t0 = time.monotonic()
            acq.stop(timeout_s=10.0)
            stops.append(time.monotonic() - t0)
    return stalls, stops


def gige_camera_lost() -> dict | None:
    try:
        from drivers import aravis
        from tests.drivers.fixtures import FakeGvCamera
        if not aravis.available():
            return None
        fake = FakeGvCamera().start()
    except Exception as exc:  # noqa: BLE001 - no Aravis or no fake camera here: say so
        print(f"GigE fake camera: not measured ({exc})")
        return None
    lost_timeout_s = 1.0
    try:
        with aravis.AravisCamera("127.0.0.1", lost_timeout_s=lost_timeout_s, probe_period_s=0.1) as cam:
            cam.configure(width=64, height=64, frame_rate_hz=100.0)
            cam.start()
            for _ in range(10):
                cam.fetch(2.0)
            fake.kill()
            t_kill = time.monotonic()
            exc = None
            while exc is None and time.monotonic() - t_kill < 30.0:
                try:
                    cam.fetch(0.3)
                except FetchTimeout:
                    continue
                except CameraLost as e:
                    exc = e
            lost_s = time.monotonic() - t_kill
            t_close = time.monotonic()
        close_s = time.monotonic() - t_close
        del exc
        t0 = time.monotonic()
        gc.collect()
        gc_s = time.monotonic() - t0
    finally:
        fake.stop()
    return dict(lost_s=lost_s, bound_s=lost_timeout_s + 0.1 + 0.1, close_s=close_s, gc_s=gc_s)


def main() -> int:
    base = baseline_wake()
    base_med = statistics.median(base)
    _row("baseline: Condition notify -> waiter runs", base, base_med, "baseline")
    _row("synthetic: software trigger -> fetch returns", synthetic_trigger_wake(), base_med, "baseline")
    stalls, stops = acquisition_stall_and_stop()
    _row("Acquisition: stall error (stall_timeout_s 0.5)", stalls, 0.5, "stall_timeout_s")
    _row("Acquisition: stop() while waiting for a trigger", stops, 0.1, "fetch slice 0.1 s")
    gige = gige_camera_lost()
    if gige:
        print(f"{'GigE fake killed -> CameraLost':<48} {gige['lost_s']:.3f} s = "
              f"{gige['lost_s'] / gige['bound_s']:.2f} x the driver's bound ({gige['bound_s']:.1f} s)")
        print(f"{'  close after CameraLost':<48} {gige['close_s']:.3f} s")
        print(f"{'  gc.collect() after the exception is dropped':<48} {gige['gc_s']:.3f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
