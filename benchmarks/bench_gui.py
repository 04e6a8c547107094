#!/usr/bin/env python3
"""GUI benchmark: frames shown per second and camera-to-screen latency with every live view open.

For each frame size the real main window runs on the synthetic camera
(ray-traced TIR frames of the app's scene) with a reference set, so the
processing worker reconstructs heights continuously, while a pre/post-trigger
recording writes every frame to disk. Measured over the recording:

* shown fps  -- repaints of the raw-frame view that showed a new camera frame, per second; the
  window draws at most ``DISPLAY_MAX_HZ`` (60, app/gui/model/schedule.py) whatever the camera
  delivers, so "shown" can never exceed 60.0 and a camera at 60 Hz or less bounds it below that:
  the measure of keeping up is ``shown / min(delivered, 60)`` (printed as "kept"), every frame
  the display could show shown at 1.00;
* latency    -- camera-to-screen: from the driver's host timestamp of a frame to
  the end of the paint that put it on screen (median and 95th percentile), for the
  raw view and for the height map (which adds the reconstruction);
* processed fps, camera fps, recorder drops (frames missing from the file: must be 0);
* where a height map's latency goes (medians over the frames the worker published): the
  frame's age when the worker took it, the reconstruction's wall and CPU time (in the
  thread that ran it: the worker process's, or this process's with ``--in-process``), the
  hand-off (shared memory, pipe, publishing) and published-to-painted; and how busy the
  GUI thread was (display ticks and paints, % of the time) and the window's process's CPU.

Baseline, measured in the same run: pyqtgraph's ``ImageView`` (histogram and
auto levels recomputed per frame, the usual peer approach) showing the same raw
frames as fast as it can, alone; the ratio compares the raw display rate.

Goal (issue 22): heights >= 30 Hz at 1024^2 and >= 50 Hz at 512^2 with every view open, height
latency p50 <= 50 ms at 1024^2; (issue 20) >= 60 fps shown at 1024^2 with all views open (read as
kept >= 0.99: the camera here delivers 100 frames/s, above the 60 Hz cap, so 60 shown means every
display tick showed a new frame), < 50 ms latency, 0 recorder drops; and launch to first frame
(``python3 -m app.gui`` spawned, first camera frame
drawn) <= 3 s, printed for a first start (camera search) and a second (the remembered camera);
random dots (``--scene dots``): heights >= 10 Hz at 512^2.

Run: ``QT_QPA_PLATFORM=offscreen python3 benchmarks/bench_gui.py`` (or under Xvfb
with ``--xvfb``). Options: ``--sizes 512 1024 --seconds 4 --rate 100``; ``--no-launch`` skips
the launch timing, ``--in-process`` reconstructs in the window's process (the worker thread, as
before the worker process), ``--switch-interval-ms`` sets the window process's GIL switch interval.
On a shared machine compare runs back to back (a ratio), with the load (``uptime``).
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import types
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def _run_loop(app, seconds):
    from pyqtgraph.Qt import QtCore

    loop = QtCore.QEventLoop()
    QtCore.QTimer.singleShot(int(1000 * seconds), loop.quit)
    loop.exec()


def baseline_imageview(app, frames, seconds):
    """pyqtgraph ImageView fed the newest frame from a 0-ms timer, as fast as it goes: shown fps."""
    import pyqtgraph as pg
    from pyqtgraph.Qt import QtCore

    view = pg.ImageView()
    view.resize(700, 600)
    view.show()
    state = {"i": 0, "n": 0}

    def tick():
        view.setImage(frames[state["i"] % len(frames)], autoLevels=True, autoHistogramRange=True)
        state["i"] += 1
        view.repaint()  # make it paint now, like a visible update would
        state["n"] += 1
        timer.start(0)

    timer = QtCore.QTimer()
    timer.setSingleShot(True)
    timer.timeout.connect(tick)
    timer.start(0)
    _run_loop(app, 0.5)
    n0, t0 = state["n"], time.monotonic()
    _run_loop(app, seconds)
    fps = (state["n"] - n0) / (time.monotonic() - t0)
    timer.stop()
    view.close()
    return fps


def worker_breakdown(processed, height_latency_ms):
    """Where a height map's camera-to-screen latency goes, medians in ms over ``processed``
    (the worker's :class:`~app.capture.worker.Processed` of the measurement): ``waited`` (the frame's
    age when the worker took it: the previous frame's work), ``reconstruction`` (wall time) and its
    ``cpu`` (CPU time in the thread that ran it, here or in the worker process), ``waiting for a
    core`` (runnable, not running: the machine's load), ``blocked (GIL)`` (the rest: in the window's
    process above all waiting for the GIL; in the worker process for its FFT threads), ``handoff``
    (taking it, the worker process's copies and pipe, publishing), ``to screen`` (published to
    painted: the display's cadence, the maps' turn, drawing)."""
    import numpy as np

    if not processed:
        return {}
    ok = [p for p in processed if p.result is not None]
    med = lambda v: float(np.median(v)) if len(v) else float("nan")  # noqa: E731
    picked = [p for p in ok if getattr(p, "picked_ns", 0)]
    out = {
        "waited": med([(p.picked_ns - p.host_timestamp_ns) / 1e6 for p in picked]),
        "reconstruction": med([1e3 * p.processing_s for p in ok]),
        "cpu": med([1e3 * getattr(p, "cpu_s", np.nan) for p in ok]),
        "waiting for a core": med([1e3 * getattr(p, "queued_s", np.nan) for p in ok]),
        "blocked (GIL)": med([1e3 * (p.processing_s - getattr(p, "cpu_s", np.nan) - getattr(p, "queued_s", np.nan))
                              for p in ok]),
        "handoff": med([(p.done_ns - p.picked_ns) / 1e6 - 1e3 * p.processing_s for p in picked]),
        "published": med([(p.done_ns - p.host_timestamp_ns) / 1e6 for p in ok]),
    }
    out["to screen"] = (float(height_latency_ms) - out["published"]) if np.isfinite(height_latency_ms) else np.nan
    return out


class GuiThreadClock:
    """Time the GUI thread spends in the window's display tick and in the views' paints (this
    benchmark wraps the two methods; the app is not changed): how busy the thread that draws is."""

    def __init__(self):
        from app.gui import views
        from app.gui.window import MainWindow

        self.ms = {"tick": 0.0, "paint": 0.0}
        self._undo = []
        for cls, name, key in ((MainWindow, "_refresh", "tick"), (views._Graphics, "paintEvent", "paint")):
            self._wrap(cls, name, key)

    def _wrap(self, cls, name, key):
        original = cls.__dict__[name]

        def timed(*args, **kwargs):
            t = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                self.ms[key] += 1e3 * (time.perf_counter() - t)

        setattr(cls, name, timed)
        self._undo.append((cls, name, original))

    def restore(self):
        for cls, name, original in self._undo:
            setattr(cls, name, original)


def _worker_process_cpu_s(worker) -> float:
    """CPU seconds (user + system, all threads) of the live worker process so far; NaN without one."""
    where = getattr(worker, "reconstructed_in", "")
    if "pid " not in where:
        return float("nan")
    pid = where.split("pid ")[1].rstrip(")")
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            fields = f.read().rpartition(b")")[2].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return float("nan")


def scene_camera(scene, size, rate_hz, n_frames):
    """``(camera, reference, geometry)`` of the benchmark's scene: "evolving" (:func:`app.capture.scene.build_scene`:
    waves and a dimple deepening over the ``n_frames`` looped frames: every frame far from the one before, the
    unwrapper's heavy case; the default, as in every earlier figure) or one of the window's synthetic tank's
    scenes (:class:`app.capture.scene.TankScene`, what a newcomer's window shows: ``n_frames`` frames of it at
    ``rate_hz``, looped)."""
    from app.capture.scene import TankScene, build_scene
    from drivers.synthetic import SyntheticCamera

    if scene == "evolving":
        sim, geometry = build_scene((size, size), n_frames, frame_rate_hz=rate_hz)
        return SyntheticCamera(sim.frames, frame_rate_hz=rate_hz), sim.reference, geometry
    if scene == "dots":  # issue 22's live random dots: ray-traced waves over 0.5 mm dots (5 px), PIV's grid
        from app.batch.simulate import DEFAULT_SIM_GEOMETRY, _sim_scene
        from processing import Geometry, forward

        geometry = Geometry.from_dict(dict(DEFAULT_SIM_GEOMETRY, pattern="dots"))
        dots = forward.RandomDots(dot_diameter_mm=0.5, density=0.3, seed=1)
        sim = forward.simulate(_sim_scene("waves", geometry, size, n_frames, 0), geometry, (size, size), n_frames,
                               pattern=dots, supersample=1)
        return SyntheticCamera(sim.frames, frame_rate_hz=rate_hz), sim.reference, geometry
    tank = TankScene((size, size), n_frames=n_frames, frame_rate_hz=rate_hz)
    tank.set_scene(tank.prepare(scene))
    return SyntheticCamera(tank, frame_rate_hz=rate_hz, bit_depth=tank.bits), tank.reference, tank.geometry


def measure_window(app, size, rate_hz, seconds, n_frames, nice=0, worker_process=None, scene="evolving"):
    import numpy as np

    from app.gui.window import MainWindow

    t = time.monotonic()
    camera, reference, geometry = scene_camera(scene, size, rate_hz, n_frames)
    build_s = time.monotonic() - t
    options = {"worker_nice": nice}
    if worker_process is not None:
        options["worker_process"] = worker_process
    clock = GuiThreadClock()  # before the window: its timer connects to the wrapped tick
    w = MainWindow(open_at_start=False, session_options=options)
    w.resize(1600, 1000)
    w.show()
    tmp = tempfile.mkdtemp(prefix="bench-gui-")
    try:
        w.use_camera(camera, geometry=geometry, reference=reference)
        t_end = time.monotonic() + 60
        while (w.session.worker.reconstructor is None or w.last_drawn is None) and time.monotonic() < t_end:
            _run_loop(app, 0.1)
        _run_loop(app, 1.0)  # warm up (plans, levels)
        rp = w.recording_panel
        rp.folder.setText(tmp)
        rp.pre.setValue(20)
        post = int(rate_hz * (seconds + 1.0))
        rp.post.setValue(post)
        w.arm()
        _run_loop(app, 0.3)
        w.trigger_now()
        raw, height = w.raw_view.graphics, w.height_view.graphics
        raw.latencies_ms.clear()
        height.latencies_ms.clear()
        acq = w.session.acquisition
        seen = []

        # each result's timings only: holding the results held every frame and its maps (4.3 MB at 1024^2, a GB
        # over a run), and the window's process then took fresh memory for every frame: 0.81-0.87 instead of
        # 0.55-0.56 cores, 34-35 instead of 42-43 heights a second (docs/acquisition.md, 7 Dec 2026)
        def note(p):
            seen.append(types.SimpleNamespace(result=None if p.result is None else True, **{
                k: getattr(p, k, 0) for k in ("host_timestamp_ns", "picked_ns", "done_ns", "processing_s", "cpu_s",
                                               "queued_s")}))

        w.session.worker.add_listener(note)
        p0, h0, k0, a0 = raw.painted, w.height_view.updates, w.session.worker.processed, acq.acquired
        lost0 = w.clock.ticks_lost
        gui0 = dict(clock.ms)
        child0 = _worker_process_cpu_s(w.session.worker)
        t0, cpu0 = time.monotonic(), os.times()
        _run_loop(app, seconds)
        dt, cpu1 = time.monotonic() - t0, os.times()
        w.session.worker.remove_listener(note)
        shown_new = len(raw.latencies_ms)  # paints that showed a new camera frame
        out = {
            "size": size,
            "build_scene_s": build_s,
            "camera_fps": (acq.acquired - a0) / dt,
            "shown_fps": shown_new / dt,
            "paints_fps": (raw.painted - p0) / dt,
            "ticks_lost": w.clock.ticks_lost - lost0,  # display ticks skipped: the GUI thread was late
            "height_fps": (w.height_view.updates - h0) / dt,
            "processed_fps": (w.session.worker.processed - k0) / dt,
            "lat_raw_ms": np.percentile(list(raw.latencies_ms), [50, 95]) if raw.latencies_ms else [np.nan] * 2,
            "lat_height_ms": (np.percentile(list(height.latencies_ms), [50, 95]) if height.latencies_ms
                              else [np.nan] * 2),
        }
        out["worker"] = worker_breakdown(seen, out["lat_height_ms"][0])
        out["gui_busy"] = {k: (clock.ms[k] - gui0[k]) / (10 * dt) for k in clock.ms}  # % of the wall time
        # the window's estimate of drawing one result's maps (s), and whether they now go in one tick
        out["maps_draw"] = (w.clock.maps_draw_s, w.clock.whole_maps())
        # this process's CPU (all its threads) and its children's that ended, in cores
        out["cpu_cores"] = (cpu1.user + cpu1.system - cpu0.user - cpu0.system) / dt
        out["worker_process_cores"] = (_worker_process_cpu_s(w.session.worker) - child0) / dt
        out["reconstructed_in"] = getattr(w.session.worker, "reconstructed_in", "this process")
        t_end = time.monotonic() + 120
        while w.recording_panel.state_label.text() not in ("done", "error") and time.monotonic() < t_end:
            _run_loop(app, 0.2)
        st = w.session.recording or {}
        s = st.get("summary", {})
        out["record_state"] = w.recording_panel.state_label.text()
        out["recorded"] = s.get("frames_written", 0)
        out["planned"] = 20 + post
        out["recorder_missing"] = s.get("total_missing", -1)
        out["ring_overrun"] = s.get("lost_ring_overrun", -1)
        out["camera_lost"] = acq.lost_upstream + acq.lost_by_time
        out["write_mb_s"] = s.get("write_rate_mb_s", 0)
        return out
    finally:
        w.shutdown()
        w.close()
        clock.restore()
        shutil.rmtree(tmp, ignore_errors=True)


def launch_to_first_frame(size: int, timeout_s: float = 60.0):
    """Seconds from starting ``python3 -m app.gui --size N`` to its first camera frame on screen.

    From a fresh settings directory: ``--camera synthetic`` (first start, no camera search), then
    with no camera named (second start: the remembered camera opens at once). The app logs the
    moment its first frame is drawn; the clock runs from the process spawn (imports included). A
    first start with no camera named adds the camera search (printed separately: it depends on
    the network, and here on other programs' fake cameras).
    """
    import tempfile

    out = {}
    with tempfile.TemporaryDirectory(prefix="bench-launch-") as cache:
        env = dict(os.environ, TIRDEFLECT_CACHE_DIR=cache, TIRDEFLECT_CONFIG_DIR=os.path.join(cache, "config"))
        env.setdefault("QT_QPA_PLATFORM", "offscreen")
        for name, extra in (("first start (--camera synthetic)", ["--camera", "synthetic"]),
                            ("second start (remembered camera)", [])):
            t0 = time.monotonic()
            proc = subprocess.Popen([sys.executable, "-m", "app.gui", "--size", str(size), "--quit-after", "8",
                                     *extra], cwd=ROOT, env=env, stderr=subprocess.PIPE,
                                    stdout=subprocess.DEVNULL, text=True)
            seconds = float("nan")
            try:
                for line in proc.stderr:
                    if "first camera frame on screen" in line:
                        seconds = time.monotonic() - t0
                        break
                proc.stderr.read()
                proc.wait(timeout_s)
            finally:
                if proc.poll() is None:
                    proc.kill()
                    proc.wait()
                proc.stderr.close()
            out[name] = seconds
    t0 = time.monotonic()
    import drivers

    drivers.list_cameras()
    out["camera search alone"] = time.monotonic() - t0
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description="GUI shown fps / latency benchmark")
    p.add_argument("--sizes", type=int, nargs="+", default=[512, 1024])
    p.add_argument("--seconds", type=float, default=5.0, help="measurement time per size (s)")
    p.add_argument("--rate", type=float, default=100.0, help="synthetic camera frame rate (Hz)")
    p.add_argument("--frames", type=int, default=None,
                   help="ray-traced frames the camera loops over (default 4 for 'evolving', 24 for the tank's)")
    p.add_argument("--scene", default="evolving", choices=("evolving", "still", "waves", "drop", "impact", "dots"),
                   help="'evolving' (default): waves and a dimple deepening fast over the looped frames, every "
                        "frame far from the last (the unwrapper's heavy case); 'dots': ray-traced waves over a "
                        "random-dot pattern (PIV, issue 22's live dots); else a scene of the window's "
                        "synthetic tank (app/capture/scene.py TankScene), what a newcomer sees")
    p.add_argument("--nice", type=int, default=0, help="nice increment of the processing worker thread")
    p.add_argument("--xvfb", action="store_true", help="run on a private Xvfb display (xcb) instead of offscreen")
    p.add_argument("--no-launch", action="store_true", help="skip the launch-to-first-frame measurement")
    p.add_argument("--switch-interval-ms", type=float, default=None,
                   help="sys.setswitchinterval of the window's process (Python's default 5 ms)")
    p.add_argument("--in-process", action="store_true",
                   help="reconstruct in the worker thread of the window's process (default: its worker process)")
    args = p.parse_args(argv)
    if args.xvfb and os.environ.get("_BENCH_GUI_CHILD") is None:
        n = next(i for i in range(90, 200) if not os.path.exists(f"/tmp/.X11-unix/X{i}"))
        xvfb = subprocess.Popen(["Xvfb", f":{n}", "-screen", "0", "1600x1000x24", "-nolisten", "tcp"],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            t_end = time.monotonic() + 10
            while not os.path.exists(f"/tmp/.X11-unix/X{n}") and time.monotonic() < t_end:
                time.sleep(0.05)
            env = dict(os.environ, DISPLAY=f":{n}", QT_QPA_PLATFORM="xcb", _BENCH_GUI_CHILD="1")
            return subprocess.call([sys.executable, __file__, *[a for a in (argv or sys.argv[1:]) if a != "--xvfb"]],
                                   env=env)
        finally:
            xvfb.terminate()
            xvfb.wait(5)
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    if "TIRDEFLECT_CONFIG_DIR" not in os.environ:  # remembered settings of the user's sessions stay out of it
        import tempfile

        os.environ["TIRDEFLECT_CONFIG_DIR"] = tempfile.mkdtemp(prefix="bench-gui-config-")
    import numpy as np
    import pyqtgraph as pg

    if args.switch_interval_ms is not None:
        sys.setswitchinterval(args.switch_interval_ms / 1e3)
    app = pg.mkQApp("bench")
    print(f"platform {app.platformName()}, {os.cpu_count()} cores, camera {args.rate:g} Hz, "
          f"{args.seconds:g} s per size, scene {args.scene}")
    rows = []
    for size in args.sizes:
        rng = np.random.default_rng(0)
        frames = [rng.integers(0, 256, (size, size), dtype=np.uint8) for _ in range(4)]
        base = baseline_imageview(app, frames, min(args.seconds, 3.0))
        n_frames = args.frames if args.frames is not None else (4 if args.scene == "evolving" else 24)
        r = measure_window(app, size, args.rate, args.seconds, n_frames, args.nice,
                           worker_process=False if args.in_process else None, scene=args.scene)
        r["baseline_fps"] = base
        rows.append(r)
    print()
    from app.gui.model.schedule import DISPLAY_MAX_HZ

    print(f"{'size':>6} {'camera':>7} {'shown':>6} {'kept':>5} {'paints':>7} {'height':>7} {'proc':>6} {'baseline':>9} "
          f"{'ratio':>6} {'lat raw p50/p95':>16} {'lat height p50/p95':>19} {'recorded':>10} {'missing':>8} "
          f"{'MB/s':>6}")
    ok = True
    for r in rows:
        showable = min(r["camera_fps"], DISPLAY_MAX_HZ)  # new frames the display could show per second
        kept = r["shown_fps"] / max(showable, 1e-9)
        print(f"{r['size']:>5}² {r['camera_fps']:7.1f} {r['shown_fps']:6.1f} {kept:5.3f} {r['paints_fps']:7.1f} "
              f"{r['height_fps']:7.1f} {r['processed_fps']:6.1f} {r['baseline_fps']:9.1f} "
              f"{r['shown_fps'] / max(r['baseline_fps'], 1e-9):5.2f}x "
              f"{r['lat_raw_ms'][0]:7.1f}/{r['lat_raw_ms'][1]:6.1f} ms {r['lat_height_ms'][0]:8.1f}/"
              f"{r['lat_height_ms'][1]:7.1f} ms {r['recorded']:>4}/{r['planned']:<5} {r['recorder_missing']:>8} "
              f"{r['write_mb_s']:6.1f}")
        if r["size"] >= 1024:
            # 60 Hz is also the display cap (views refresh at <= 60 Hz): within 1 % of it is "keeping up"
            # (one frame more or less in a 5 s window is 0.2 fps)
            goal = kept >= 0.99 and r["lat_raw_ms"][0] < 50
            print(f"goal at {r['size']}²: shown / min(delivered, {DISPLAY_MAX_HZ:g} Hz cap) >= 0.99 and < 50 ms "
                  f"latency: {'PASS' if goal else 'FAIL'} ({r['shown_fps']:.1f} fps shown of {r['camera_fps']:.1f} "
                  f"delivered, kept {kept:.3f}, {r['ticks_lost']} display ticks lost to a late GUI thread; "
                  f"{r['lat_raw_ms'][0]:.1f} ms)")
            ok &= goal
        wb = r["worker"]
        if wb:
            print(f"height latency at {r['size']}² (medians, ms; reconstruction {r['reconstructed_in']}): "
                  + ", ".join(f"{k} {v:.1f}" for k, v in wb.items()))
        print(f"GUI thread at {r['size']}²: display ticks {r['gui_busy']['tick']:.0f} % and paints "
              f"{r['gui_busy']['paint']:.0f} % of the time; the window's process used {r['cpu_cores']:.2f} cores"
              + (f", its worker process {r['worker_process_cores']:.2f}"
                 if np.isfinite(r["worker_process_cores"]) else "")
              + f"; drawing one result's maps {1e3 * r['maps_draw'][0]:.1f} ms "
              f"({'one tick' if r['maps_draw'][1] else 'two halves'})")
        goal_h = ({512: 10.0} if args.scene == "dots" else {512: 50.0, 1024: 30.0}).get(r["size"])
        if goal_h is not None:
            lat_goal = r["size"] < 1024 or r["lat_height_ms"][0] <= 50.0 or args.scene == "dots"
            print(f"heights at {r['size']}²: {r['height_fps']:.1f} Hz drawn, {r['processed_fps']:.1f} Hz "
                  f"reconstructed, latency p50 {r['lat_height_ms'][0]:.1f} ms (goal >= {goal_h:g} Hz"
                  + (", <= 50 ms" if r["size"] >= 1024 and args.scene != "dots" else "") + f"): "
                  + ("met" if r["height_fps"] >= goal_h and lat_goal else "NOT met"))
        rec_ok = r["recorder_missing"] == 0 and r["recorded"] == r["planned"] and r["camera_lost"] == 0
        print(f"recorder at {r['size']}²: {r['recorded']} of {r['planned']} frames, missing {r['recorder_missing']}, "
              f"camera lost {r['camera_lost']}: {'PASS' if rec_ok else 'FAIL'} ({r['record_state']})")
        ok &= rec_ok
    for size in ([] if args.no_launch else args.sizes):
        launch = launch_to_first_frame(size)
        starts = [v for k, v in launch.items() if "start" in k]
        print(f"launch to first frame at {size}² (python3 -m app.gui, synthetic tank): "
              + ", ".join(f"{k} {v:.2f} s" for k, v in launch.items())
              + f" (goal <= 3 s: {'met' if max(starts) <= 3.0 else 'NOT met'})")
    print("camera = frames the synthetic camera delivered per second; shown = new camera frames painted per second "
          f"(<= {DISPLAY_MAX_HZ:g} by design); kept = shown / min(camera, {DISPLAY_MAX_HZ:g}); "
          "paints = all repaints of the raw view;")
    print("height = height-map updates per second; proc = frames reconstructed per second; baseline = pyqtgraph "
          "ImageView alone, raw frames only")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
