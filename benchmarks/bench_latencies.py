"""Latencies the tests only bound loosely (their bounds are hang detectors, >= 10x above need).

Run from the repository root (about 40 s; the GigE parts need arv-fake-gv-camera-0.8)::

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
   (tests/drivers/test_aravis.py);
5. the GUI thread's longest pause (a 10 ms QTimer, the window's collector running,
   app/gui/collector.py) while a background thread's first import of OpenPIV runs,
   in a fresh interpreter: with no dead camera (baseline) and with two cameras
   dropped right after they died, left in cyclic garbage (docs/architecture.md,
   "Threads, imports and the garbage collector"; before RELEASE_WAIT_S: 20.1 s).
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


#: run in a fresh interpreter (OpenPIV's first import): argv = repository root, number of dead cameras
GUI_PAUSE_CHILD = r"""
import sys, threading, time
sys.path.insert(0, sys.argv[1])
n_dead = int(sys.argv[2])
from pyqtgraph.Qt import QtCore, QtWidgets
from app.gui.collector import GuiThreadCollector
app = QtWidgets.QApplication([])
root = QtCore.QObject()
collector = GuiThreadCollector(root)
if n_dead:
    from drivers import aravis
    from tests.drivers.fixtures import FakeGvCamera
    for _ in range(n_dead):
        fake = FakeGvCamera().start()
        cam = aravis.AravisCamera("127.0.0.1", lost_timeout_s=1.0, probe_period_s=0.1)
        cam.open(); cam.configure(width=64, height=64, frame_rate_hz=100.0); cam.start()
        for _ in range(5):
            cam.fetch(2.0)
        fake.kill()
        holder = [cam]; holder.append(holder)  # dropped at once, in a cycle: its __del__ closes it
        del cam, holder
        fake.stop()
ticks = [time.monotonic()]
tick = QtCore.QTimer(); tick.setInterval(10); tick.timeout.connect(lambda: ticks.append(time.monotonic())); tick.start()
done = {}
def build():
    t0 = time.monotonic()
    import openpiv.windef  # noqa: F401
    done["s"] = time.monotonic() - t0
threading.Thread(target=build, daemon=True).start()
poll = QtCore.QTimer(); poll.setInterval(100)
poll.timeout.connect(lambda: app.quit() if "s" in done and time.monotonic() - ticks[0] > 3.0 else None); poll.start()
app.exec()
print(max(b - a for a, b in zip(ticks, ticks[1:])), done["s"])
"""


def gui_pause(n_dead: int) -> tuple[float, float] | None:
    """(the GUI thread's longest pause, the import's duration) in s, or None when it cannot run here."""
    import os
    import subprocess

    env = dict(os.environ, QT_QPA_PLATFORM=os.environ.get("QT_QPA_PLATFORM", "offscreen"))
    r = subprocess.run([sys.executable, "-c", GUI_PAUSE_CHILD, str(ROOT), str(n_dead)], env=env,
                       capture_output=True, text=True, timeout=300)
    if r.returncode != 0:
        print(f"GUI pause with {n_dead} dead camera(s): not measured ({r.stderr.strip().splitlines()[-1:]})")
        return None
    pause_s, import_s = map(float, r.stdout.split()[-2:])
    return pause_s, import_s


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
    base = gui_pause(0)
    dead = gui_pause(2) if gige else None
    if base:
        print(f"{'GUI thread, first import of OpenPIV beside it':<48} longest pause {base[0]:.3f} s "
              f"(import {base[1]:.1f} s) = 1.00 x")
    if base and dead:
        print(f"{'  and 2 dead cameras collected meanwhile':<48} longest pause {dead[0]:.3f} s "
              f"(import {dead[1]:.1f} s) = {dead[0] / base[0]:.2f} x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
