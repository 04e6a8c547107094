"""Entry point of the live window: ``main(argv=None) -> int``."""

from __future__ import annotations

import argparse
import logging
import os
import signal
import socket
import sys
from typing import Optional, Sequence

from app.stop_signals import STOP_SIGNALS

__all__ = ["main", "build_parser", "window_of"]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="tirdeflect gui", description="Live TIR deflectometry window.")
    p.add_argument("--camera", default=None,
                   help="camera id (synthetic, aravis:..., gentl:...); default: first found, else synthetic")
    p.add_argument("--geometry", default=None, help="geometry TOML to load at start")
    p.add_argument("--reference", default=None, help="reference image to load at start")
    p.add_argument("--size", type=int, default=512, help="synthetic camera frame size in pixels (square)")
    p.add_argument("--rate", type=float, default=None,
                   help="synthetic camera frame rate (Hz; default the one set last time, else 60)")
    p.add_argument("--frames", type=int, default=24,
                   help="frames per synthetic tank scene, ray-traced in the background when the scene is "
                        "chosen (it loops over them)")
    p.add_argument("--scene", choices=("still", "waves", "drop", "impact"), default=None,
                   help="synthetic camera: start this tank scene (it starts on still water, so that a "
                        "reference can be captured, and switches once the scene is ray-traced)")
    p.add_argument("--session", default=None, metavar="FILE",
                   help="experiment file (geometry + reference + settings) saved by the window")
    p.add_argument("--quit-after", type=float, default=None, metavar="S",
                   help="close the window after S seconds (smoke tests)")
    p.add_argument("--debug", action="store_true", help="log debug messages")
    return p


def _start_scene_when_open(window, scene: str, QtCore) -> None:
    """Choose ``scene`` once the synthetic camera streams (it opens in the background)."""
    timer = QtCore.QTimer(window)

    def check():
        if window.session.tank is not None:
            timer.stop()
            window.set_scene(scene)
        elif not window.busy("open") and window.session.acquisition is not None:
            timer.stop()
            window.show_error(f"--scene {scene}: the open camera is not the synthetic one; scenes are "
                              "for the synthetic camera (--camera synthetic)")
    timer.timeout.connect(check)
    timer.start(100)


#: the signals that close the window (exit status 128 + the signal's number, as a shell reports it and as
#: ``tirdeflect record`` exits: 130 Ctrl-C, 143 SIGTERM, 129 SIGHUP)
CLOSING_SIGNALS = (signal.SIGINT,) + STOP_SIGNALS


class _CloseOnSignals:
    """Ctrl-C, SIGTERM or SIGHUP (the terminal closed) close the window as its close button does, without
    the question about a recording in progress: the recording stops with every frame written so far kept.

    Python runs a signal's handler only between bytecodes, and an idle Qt event loop runs none: the
    signal's byte on a socket (``signal.set_wakeup_fd``) wakes the loop, whose notifier then lets the
    handler run. :attr:`signal` is the number of the signal that closed the window (None: none did; the
    exit status is then 128 + it). Signals ignored from the start (``nohup``, ``&``) stay ignored."""

    def __init__(self, window, app, QtCore):
        self.signal: Optional[int] = None
        self._window, self._app, self._QtCore = window, app, QtCore
        self._receive, self._send = socket.socketpair()  # kept here as long as the loop runs
        for sock in (self._receive, self._send):
            sock.setblocking(False)
        signal.set_wakeup_fd(self._send.fileno())
        self._notifier = QtCore.QSocketNotifier(self._receive.fileno(), QtCore.QSocketNotifier.Type.Read, window)
        self._notifier.activated.connect(self._drain)
        for sig in CLOSING_SIGNALS:
            if signal.getsignal(sig) is not signal.SIG_IGN:
                signal.signal(sig, self._handler)

    def _drain(self, *_):
        try:
            self._receive.recv(64)
        except OSError:
            pass

    def _handler(self, signum, _frame):
        if self.signal is not None:
            return  # closing already
        self.signal = signum
        logging.getLogger(__name__).warning("%s: closing the window (a recording in progress keeps its frames)",
                                            signal.Signals(signum).name)
        window, app = self._window, self._app
        self._QtCore.QTimer.singleShot(0, lambda: (window.shutdown(), app.quit()))


def window_of(args, window_class, **options):
    """The window the parsed command line ``args`` asks for (``window_class``: MainWindow; ``options``: more of
    its keyword arguments), before its session, geometry and reference are loaded."""
    camera = args.camera
    if camera is None and args.scene:
        camera = "synthetic"
    window = window_class(camera, synthetic_options={"shape": (args.size, args.size), "n_frames": args.frames,
                                                     "frame_rate_hz": 60.0 if args.rate is None else args.rate},
                          **options)
    # what the command line sets wins over what the camera was set to last time (by-hand trial of 7 Dec 2026:
    # --rate 100 ran at the remembered 30 Hz); read when the camera's settings are restored (app.gui.state)
    window.command_line_settings = () if args.rate is None else ("frame_rate_hz",)
    return window


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Open the live window; returns the exit status: 0 closed normally, 2 bad arguments, 128 + the signal's
    number when Ctrl-C (130), SIGTERM (143) or SIGHUP (129) closed it."""
    args = build_parser().parse_args(argv)
    if (sys.platform.startswith("linux") and not os.environ.get("QT_QPA_PLATFORM")
            and not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY")):
        print("tirdeflect: error: no display to open the window on (DISPLAY and WAYLAND_DISPLAY are unset): "
              "run it in a desktop session, with ssh -X or under xvfb-run, or use the headless commands "
              "(tirdeflect record / process)", file=sys.stderr)
        return 2
    logging.basicConfig(level=logging.DEBUG if args.debug else logging.INFO,
                        format="%(asctime)s %(name)s %(levelname)s: %(message)s")
    import pyqtgraph as pg
    from pyqtgraph.Qt import QtCore

    from .window import MainWindow

    app = pg.mkQApp("tirdeflect")
    from app.files import cache

    try:  # FFTW plans measured in earlier sessions (a corrupt file is ignored with a warning)
        cache.restore_fftw_wisdom()
    except Exception as exc:  # noqa: BLE001 - never fatal
        logging.getLogger(__name__).warning("FFTW wisdom not restored: %s", exc)
    if args.session and not os.path.exists(args.session):
        print(f"tirdeflect: error: experiment file {args.session} does not exist: give the TOML the window "
              "saved (File ▸ Save experiment)", file=sys.stderr)
        return 2
    window = window_of(args, MainWindow)
    if args.session:
        window.open_experiment(args.session)
    if args.geometry:
        window.load_geometry(args.geometry)
    if args.reference:
        window.load_reference(args.reference)
    if args.scene and args.scene != "still":
        _start_scene_when_open(window, args.scene, QtCore)
    window.show()
    if args.quit_after is not None:
        QtCore.QTimer.singleShot(int(1000 * args.quit_after), window.close)
    closed_by = _CloseOnSignals(window, app, QtCore)
    try:
        code = int(app.exec())
        return code if closed_by.signal is None else 128 + int(closed_by.signal)
    finally:
        signal.set_wakeup_fd(-1)
        window.shutdown()
        try:
            cache.store_fftw_wisdom()
        except Exception as exc:  # noqa: BLE001 - never fatal
            logging.getLogger(__name__).warning("FFTW wisdom not stored: %s", exc)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
