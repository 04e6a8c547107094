#!/usr/bin/env python3
"""Screenshots of the running live window under Xvfb, taken through a new user's first run.

Nothing is staged: the app starts on the synthetic camera (the simulated
tank, on still water), and the script does what a user does, with mouse
clicks on the widgets: Alignment tab (waits for READY TO MEASURE and its
numbers) -> Controls ▸ Reference & geometry ▸ Capture reference -> Controls ▸
Camera ▸ tank scene "impact" -> Live tab, and grabs the screen (the height map when the
approaching disc's dimple is a few micrometres deep):

* ``docs/screenshot-alignment.png``, ``docs/screenshot-height.png`` at 1600x1000;
* ``docs/screenshot-alignment-1280x800.png``, ``docs/screenshot-height-1280x800.png`` at 1280x800.

Rerun: ``python3 docs/screenshots.py`` (runs itself under ``xvfb-run -s "-screen 0 WxHx24"`` once per
size; needs xvfb-run and the Qt xcb plugin's libraries: libxcb-icccm4 libxcb-keysyms1 libxcb-cursor0 ...).
Each settings and cache directory is fresh (temporary ``TIRDEFLECT_CONFIG_DIR`` and
``TIRDEFLECT_CACHE_DIR``), as on a first run.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
SIZES = ((1600, 1000, ""), (1280, 800, "-1280x800"))


def parent(out_dir: Path, size: int, timeout_s: float) -> int:
    if shutil.which("xvfb-run") is None:
        print("screenshots: xvfb-run is not installed (apt-get install xvfb)", file=sys.stderr)
        return 2
    ok = True
    for width, height, suffix in SIZES:
        with tempfile.TemporaryDirectory(prefix="tirdeflect-shots-") as cache:
            env = dict(os.environ, QT_QPA_PLATFORM="xcb", TIRDEFLECT_CACHE_DIR=cache,
                       TIRDEFLECT_CONFIG_DIR=os.path.join(cache, "config"))
            cmd = ["xvfb-run", "-a", "-s", f"-screen 0 {width}x{height}x24 -nolisten tcp", sys.executable,
                   str(Path(__file__).resolve()), "--child", "--size", str(size), "--out", str(out_dir),
                   "--screen", f"{width}x{height}", f"--suffix={suffix}"]
            try:
                r = subprocess.run(cmd, cwd=ROOT, env=env, timeout=timeout_s)
                ok &= r.returncode == 0
            except subprocess.TimeoutExpired:
                print(f"screenshots: {width}x{height} took longer than {timeout_s:.0f} s", file=sys.stderr)
                ok = False
    return 0 if ok else 1


def child(size: int, out_dir: str, screen: str, suffix: str) -> int:
    sys.path.insert(0, str(ROOT))
    import numpy as np
    import pyqtgraph as pg
    from pyqtgraph.Qt import QtCore, QtTest, QtWidgets

    from app.gui.window import MainWindow

    width, height = (int(v) for v in screen.split("x"))
    app = pg.mkQApp("tirdeflect")
    w = MainWindow("synthetic", synthetic_options={"shape": (size, size), "n_frames": 24, "frame_rate_hz": 30.0})
    w.setGeometry(0, 0, width, height)
    w.show()

    def spin(seconds):
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            app.processEvents()
            time.sleep(0.01)

    def spin_until(cond, timeout_s, what):
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            app.processEvents()
            if cond():
                return
            time.sleep(0.01)
        raise TimeoutError(f"screenshots: {what} not within {timeout_s} s")

    def click(widget, pos=None):
        QtTest.QTest.mouseClick(widget, QtCore.Qt.LeftButton, QtCore.Qt.NoModifier,
                                pos if pos is not None else widget.rect().center())
        app.processEvents()

    def click_tab(title):
        bar = w.tabs.tabBar()
        click(bar, bar.tabRect(next(i for i in range(bar.count()) if bar.tabText(i) == title)).center())

    def open_section(title):
        for b in w.side.findChildren(QtWidgets.QAbstractButton, "qt_toolbox_toolboxbutton"):
            if b.text().replace("&&", "&") == title:
                click(b)
                return
        raise RuntimeError(f"no section {title}")

    def grab(name):
        path = Path(out_dir) / f"screenshot-{name}{suffix}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        if not app.primaryScreen().grabWindow(0).save(str(path)):
            raise RuntimeError(f"could not write {path}")
        print(f"wrote {path} (launch to first frame {w.first_frame_s:.2f} s)", flush=True)

    spin_until(lambda: w.first_frame_s is not None, 60, "first frame")
    click_tab("Alignment")
    spin_until(lambda: getattr(w, "alignment_ready", False) and w.modulation_view.updates > 2, 60,
               "READY TO MEASURE")
    spin(1.0)
    grab("alignment")

    open_section("Reference & geometry")
    click(w.geometry_panel.capture_button)
    spin_until(lambda: w.session.worker.reconstructor is not None and not w.busy("reconstructor"), 60,
               "the reference")
    open_section("Camera")
    box = w.camera_panel.scene_box
    box.setFocus()
    while box.itemData(box.currentIndex()) != "impact":
        QtTest.QTest.keyClick(box, QtCore.Qt.Key_Down)
        app.processEvents()
    click_tab("Live")
    tank = w.session.tank
    spin_until(lambda: tank.scene == "impact", 180, "the impact scene")

    # the disc's dimple 2-3 um deep (clip index 6-8 of 24), still measured everywhere: from about 4 um
    # on (index 9) its curvature changes the pattern's period at the centre beyond the demodulation's
    # band, the carriers' amplitude there falls under min_amplitude (0.23 at 4 um, 0.10 at 5 um) and
    # the centre is masked; at contact the rays cross
    def late_in_clip():
        p = w.last_drawn
        if p is None or p.result is None:
            return False
        fid = w.session.frame_id_of(p.seq)
        k = tank.clip_index(fid) if fid is not None else None
        return (tank.scene_of(fid) == "impact" and k is not None
                and int(0.29 * tank.n_frames) <= k <= int(0.35 * tank.n_frames))

    spin(2.0)  # levels settle
    spin_until(late_in_clip, 60, "a frame near contact")
    views = (w.height_view, w.disp_view, w.slope_x_view, w.slope_y_view, w.valid_view)
    updates = w.slope_y_view.updates
    spin_until(lambda: w.slope_y_view.updates > updates, 5, "the second half of the maps")
    painted = [v.graphics.painted for v in views]
    spin_until(lambda: all(v.graphics.painted > n for v, n in zip(views, painted)), 5, "paints")
    # hold this frame while the pending paints reach the X server; the status bar keeps what it said
    # while the maps were live (frozen, it would say what a paused display does: "shown 0.0 fps")
    status_timer = w.findChild(QtCore.QTimer, "status_timer")
    status_timer.stop()
    status_timer.timeout.emit()  # the status bar of the maps on screen, then no more updates
    w.frozen = True
    spin(0.5)
    grab("height")
    w.frozen = False
    status_timer.start()
    e = w.height_error or {}
    if e:
        print(f"height error vs the scene's truth: {100 * e['rel_rms']:.1f} % rel. RMS ({e.get('scene')})")
    w.close()
    app.processEvents()
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default=str(HERE), help="folder for the PNGs (default: docs/)")
    p.add_argument("--size", type=int, default=512, help="synthetic camera frame size (pixels)")
    p.add_argument("--timeout", type=float, default=400.0, help="give up on a screen size after this many seconds")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--screen", default="1600x1000", help=argparse.SUPPRESS)
    p.add_argument("--suffix", default="", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        return child(args.size, args.out, args.screen, args.suffix)
    return parent(Path(args.out), args.size, args.timeout)


if __name__ == "__main__":
    sys.exit(main())
