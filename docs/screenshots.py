#!/usr/bin/env python3
"""Screenshots of the running live window under Xvfb, for the README.

Starts a private Xvfb display, runs the real app (``app.gui``) on it with the
synthetic ray-traced camera, and grabs the X screen with ImageMagick's
``import`` (as a person would) once each view shows live data:

* ``docs/screenshot-alignment.png`` -- Alignment tab (spectrum with carriers,
  contrast map, theta from the pattern vs configured, ready state);
* ``docs/screenshot-height.png`` -- Live tab with the reference set (height in
  um, slopes, displacement, valid mask, profile, raw frame + histogram).

Rerun: ``python3 docs/screenshots.py`` (needs Xvfb, ImageMagick and the Qt xcb
plugin's libraries: libxcb-icccm4 libxcb-keysyms1 libxcb-cursor0 ...).
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
SCREEN = (1600, 1000)


def _free_display() -> int:
    for n in range(90, 200):
        if not os.path.exists(f"/tmp/.X11-unix/X{n}") and not os.path.exists(f"/tmp/.X{n}-lock"):
            return n
    raise RuntimeError("no free X display number between :90 and :199")


def parent(out_dir: Path, size: int, timeout_s: float) -> int:
    if shutil.which("Xvfb") is None:
        print("screenshots: Xvfb is not installed (apt-get install xvfb)", file=sys.stderr)
        return 2
    n = _free_display()
    xvfb = subprocess.Popen(["Xvfb", f":{n}", "-screen", "0", f"{SCREEN[0]}x{SCREEN[1]}x24", "-nolisten", "tcp"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    child = None
    try:
        deadline = time.monotonic() + 10
        while not os.path.exists(f"/tmp/.X11-unix/X{n}"):
            if xvfb.poll() is not None or time.monotonic() > deadline:
                print(f"screenshots: Xvfb :{n} did not start", file=sys.stderr)
                return 2
            time.sleep(0.05)
        env = dict(os.environ, DISPLAY=f":{n}", QT_QPA_PLATFORM="xcb")
        child = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--child", "--size", str(size),
                                  "--out", str(out_dir)],
                                 cwd=ROOT, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        shots = 0
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            line = child.stdout.readline()
            if not line:
                break
            line = line.strip()
            print("child:", line)
            if line.startswith("SHOT "):
                name = line.split()[1]
                path = out_dir / f"screenshot-{name}.png"
                if shutil.which("import"):
                    subprocess.run(["import", "-display", f":{n}", "-window", "root", str(path)], check=True)
                else:  # let the child grab its own screen
                    child.stdin.write(f"GRAB {path}\n")
                    child.stdin.flush()
                    child.stdout.readline()
                print(f"wrote {path}")
                shots += 1
                child.stdin.write("NEXT\n")
                child.stdin.flush()
            elif line.startswith("WROTE "):
                print(f"wrote {line.split(' ', 1)[1]} (grabbed by the app from the X screen)")
                shots += 1
            elif line == "DONE":
                break
        rc = child.wait(timeout=30)
        return 0 if shots == 2 and rc == 0 else 1
    finally:
        if child is not None and child.poll() is None:
            child.kill()
        xvfb.terminate()
        try:
            xvfb.wait(5)
        except subprocess.TimeoutExpired:
            xvfb.kill()


def child(size: int, out_dir: str) -> int:
    sys.path.insert(0, str(ROOT))
    import numpy as np
    import pyqtgraph as pg

    from app.gui.window import MainWindow

    app = pg.mkQApp("tirdeflect")
    w = MainWindow("synthetic", synthetic_options={"shape": (size, size), "n_frames": 24, "frame_rate_hz": 60.0})
    w.setGeometry(0, 0, *SCREEN)
    w.show()

    def spin_until(cond, timeout_s):
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            app.processEvents()
            if cond():
                return True
            time.sleep(0.01)
        raise TimeoutError(f"screenshots: condition not met within {timeout_s} s")

    def shot(name):
        # let a few more frames draw, then hand over to the parent
        t_end = time.monotonic() + 1.5
        while time.monotonic() < t_end:
            app.processEvents()
            time.sleep(0.01)
        print(f"SHOT {name}", flush=True)
        while True:
            cmd = sys.stdin.readline().strip()
            if cmd.startswith("GRAB "):
                app.primaryScreen().grabWindow(0).save(cmd.split(" ", 1)[1])
                print("GRABBED", flush=True)
            else:
                break

    spin_until(lambda: w.session.acquisition is not None and w.geometry is not None, 120)
    scene_camera = w.session.camera
    # Alignment is done on still water, before any reference exists: stream the scene's
    # flat-surface frame (with fresh read noise per frame) through a synthetic camera.
    from app.capture.scene import synthetic_reference
    from drivers.synthetic import SyntheticCamera
    from processing.forward import quantize

    flat = synthetic_reference((size, size))
    rng = np.random.default_rng(1)
    still = np.stack([quantize(flat / 255.0, bits=8, noise_rms=0.7, rng=rng) for _ in range(8)])
    w.session.camera = None  # keep the scene camera open for later
    w.use_camera(SyntheticCamera(still, frame_rate_hz=60.0), geometry=w.geometry)
    w.tabs.setCurrentIndex(1)
    w.side.setCurrentIndex(0)
    spin_until(lambda: w.spectrum_view.updates > 2 and w.modulation_view.updates > 2, 60)
    shot("alignment")

    # then the reference (averaged still water) and the moving scene: waves and an approaching disc
    w.set_reference(flat, "synthetic scene, flat surface")
    w.use_camera(scene_camera, geometry=w.geometry, camera_id="synthetic")
    w.tabs.setCurrentIndex(0)
    w.side.setCurrentIndex(1)
    spin_until(lambda: w.last_drawn is not None and w.height_view.updates > 10, 60)
    # a frame late in the scene's loop, when the disc's dimple is deep: the live view moves on
    # within milliseconds, so grab the X screen from here the moment that frame is painted
    frames = getattr(scene_camera, "_frames", None)
    if frames is not None:
        target = frames[int(0.8 * (len(frames) - 1))]
        t_end = time.monotonic() + 1.5
        while time.monotonic() < t_end:  # let levels and status settle first
            app.processEvents()
            time.sleep(0.01)
        spin_until(lambda: w.last_drawn is not None and np.array_equal(w.last_drawn.image, target), 60)
        # part 0 (height, profile, mask) is drawn; wait until part 1 (displacement, slopes) of the same
        # result is drawn and every map has painted it
        updates = w.slope_y_view.updates
        spin_until(lambda: w.slope_y_view.updates > updates, 5)
        views = (w.height_view, w.disp_view, w.slope_x_view, w.slope_y_view, w.valid_view)
        painted = [v.graphics.painted for v in views]
        spin_until(lambda: all(v.graphics.painted > n for v, n in zip(views, painted)), 5)
        w.frozen = True  # hold this frame on screen while every pending paint reaches the X server
        t_end = time.monotonic() + 0.3
        while time.monotonic() < t_end:
            app.processEvents()
            time.sleep(0.01)
        path = Path(out_dir) / "screenshot-height.png"
        app.primaryScreen().grabWindow(0).save(str(path))
        w.frozen = False
        print(f"WROTE {path}", flush=True)
    else:
        shot("height")
    print("DONE", flush=True)
    w.close()
    app.processEvents()
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default=str(HERE), help="folder for the PNGs (default: docs/)")
    p.add_argument("--size", type=int, default=512, help="synthetic camera frame size (pixels)")
    p.add_argument("--timeout", type=float, default=300.0, help="give up after this many seconds")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        return child(args.size, args.out)
    return parent(Path(args.out), args.size, args.timeout)


if __name__ == "__main__":
    sys.exit(main())
