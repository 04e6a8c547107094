"""The main window: live maps, alignment, reference and geometry, trigger and recording, replay.

Threads: the GUI thread only draws. The camera thread (``app.capture.acquisition``) fills
the ring buffer, the recorder (``app.capture.recorder``) writes every frame from its own
cursor, the processing worker (``app.capture.worker``) takes the newest frame. The GUI
thread reads the newest published result from a single-shot timer re-armed
after each draw (<= 60 Hz), so redraws never pile up and never wait on the
camera or an FFT. Anything that can block (opening a camera, capturing a
reference, exporting) runs in a background thread; its outcome comes back as
a queued Qt signal.
"""

from __future__ import annotations

import concurrent.futures
import logging
import os
import time
import traceback
import weakref
from typing import Callable, Optional

from pyqtgraph.Qt import QtCore, QtWidgets

from . import display, layout, recording_flow, reference_flow, replay_flow, state
from .alignment import FrameMotion
from .collector import GuiThreadCollector
from .model.memory import SessionMemory
from .model.recording import RmsHistory
from .model.schedule import (ALIGNMENT_TAB, LIVE_TAB, DrawClock, ExportProgress, LiveRates, RateCounter, ReplayQueue,
                             timer_ms)
from .model.staleness import STALE_AFTER_S, ReferenceEpochs, Shown, Staleness
from .replay import Recording
from .session import LiveSession

__all__ = ["MainWindow"]

log = logging.getLogger(__name__)

DISPLAY_PERIOD_MS = 16  # first tick


class _Bridge(QtCore.QObject):
    """Carries results of background threads into the GUI thread (queued signal)."""

    done = QtCore.Signal(object, object, object)  # callback, result, error message
    result_arrived = QtCore.Signal()  # the processing worker published a result (app/capture/worker.py)


class MainWindow(QtWidgets.QMainWindow):
    """The live window.

    Parameters
    ----------
    camera_id : str, optional
        Camera to open at start ("synthetic", "aravis:...", "gentl:..."); None: the
        first camera found, the synthetic scene when none is.
    synthetic_options : dict, optional
        Keyword arguments for :func:`app.capture.scene.open_synthetic_camera` (shape, frame rate...).
    open_at_start : bool
        Open the camera at start (tests may first set options).
    session_options : dict, optional
        Keyword arguments for :class:`app.gui.session.LiveSession` (ring_bytes, stall_timeout_s, worker_nice).
    planner_effort : str
        FFTW planner effort of the reconstructors (plans are built in the background and the
        wisdom is kept on disk by ``app.files.cache``; tests use "FFTW_ESTIMATE").
    """

    def __init__(self, camera_id: Optional[str] = None, *, synthetic_options: Optional[dict] = None,
                 open_at_start: bool = True, session_options: Optional[dict] = None,
                 planner_effort: str = "FFTW_MEASURE", parent=None):
        super().__init__(parent)
        # before any background thread starts: cyclic garbage (Qt wrappers, camera handles) is
        # finalized in this thread only (app/gui/collector.py)
        self._collector = GuiThreadCollector(self)
        self.setWindowTitle("tirdeflect — live TIR deflectometry")
        self._fit_to_screen(1500, 950)
        self._executor = concurrent.futures.ThreadPoolExecutor(max_workers=2, thread_name_prefix="gui-bg")
        self._bridge = _Bridge()
        self._bridge.done.connect(self._background_done)
        self.session = LiveSession(synthetic_options=synthetic_options, **(session_options or {}))
        self.planner_effort = planner_effort
        self.command_line_settings: tuple = ()  # camera settings the command line gave (app.gui.main): they win
        self.geometry = None
        self.reference = None
        self.shown_rate = RateCounter()  # new camera frames put on screen per second (the status bar's "shown")
        self.latency_ms = float("nan")
        self.result_latency_ms = float("nan")
        self._closing = False
        self.last_error: Optional[str] = None
        self.errors: list = []  # problems shown in the banner, oldest first (cleared by its × button)
        self.replay_recording: Optional[Recording] = None
        self._replay_reconstructor = None
        self._busy = set()
        self.replay_shown_index: Optional[int] = None  # frame whose height map the Replay tab shows
        self.last_drawn = None  # the Processed whose maps are on screen
        self.frozen = False  # True: views keep what they show (scripts; the Pause box does the same)
        self._t_created = time.monotonic()
        self.first_frame_s: Optional[float] = None  # window created -> first camera frame on screen
        self.height_error: Optional[dict] = None  # synthetic tank: live heights vs the scene's truth
        # the window's state, all of it here (app/gui/model/: Qt-free, unit-tested)
        self.memory = SessionMemory.load()  # what the session remembers (app/gui/state.py fills the widgets)
        self.reference_path: Optional[str] = None  # the file of the reference in use (None: captured)
        self.reference_roi = None  # (offset_x, offset_y, width, height) the reference was taken with
        self._reference_text = ""
        self.reference_refused = ""  # why the newest reference could not be used ("": it is in use, or none)
        self.references = ReferenceEpochs()  # rebuild policy; which reference measured which frame
        self.scene_wanted: Optional[str] = None
        self.clock = DrawClock()  # what each display tick draws (model/schedule.py)
        self.rates = LiveRates(STALE_AFTER_S)
        self.replay_queue = ReplayQueue()
        self.export = ExportProgress()
        self.rms_history = RmsHistory()  # the auto-trigger's quantity on the live maps
        self.stale = Staleness()
        self.pattern_problem: Optional[str] = None  # the reference does not show the chosen pattern
        self._raw_shown: Optional[Shown] = None
        self._maps_shown: Optional[Shown] = None
        self._align_shown: Optional[Shown] = None
        self._unmeasured = None  # a newer frame the worker could not measure
        self._overlay_rect = None
        self._hist_count = 0
        self._shown_camera_error: Optional[str] = None
        self.alignment_ready = False
        self.alignment_metrics: dict = {}
        self.frame_motion = FrameMotion()  # the image's change between alignment updates (worker thread)
        self.result_motion = FrameMotion()  # the same once a reference exists, from the results (GUI thread)
        self.profile_line_mm = None
        self.camera_fps_shown = 0.0
        self.last_snapshot = None
        self.replay_last_result = None
        self.close_question = None
        self.actions_by_name: dict = {}  # app/gui/menus.py
        self.help_box = None
        self.movie_result = None  # app/gui/export.py
        # the camera to open (the given one, else the last session's) starts opening while the window is built
        camera_id = state.camera_to_open(self, camera_id)
        if open_at_start:
            self.run_background("open", self.session.open, self._camera_opened, camera_id)

        self._build_ui()
        self.session.worker.set_alignment_fn(self._frame_alignment)
        self._display_timer = QtCore.QTimer(self)
        self._retry_armed = False  # its next timeout is a look again for a late camera frame, not a tick
        self._display_timer.setSingleShot(True)
        self._display_timer.setTimerType(QtCore.Qt.PreciseTimer)
        self._display_timer.timeout.connect(self._refresh)
        self._status_timer = QtCore.QTimer(self)
        self._status_timer.setObjectName("status_timer")  # docs/screenshots.py holds it while it grabs
        self._status_timer.setInterval(250)
        self._status_timer.timeout.connect(self._update_status)
        self._status_timer.start()
        self._display_timer.start(DISPLAY_PERIOD_MS)
        # a result is drawn when it arrives if the next tick is far (DrawClock.plan_early): the worker's
        # listener runs in its thread and only posts the news to this one
        self._bridge.result_arrived.connect(self._draw_early, QtCore.Qt.QueuedConnection)
        self.session.worker.add_listener(self._result_published)
        # remembered state (app/gui/state.py): layout, recording, levels now; geometry, reference on open
        state.restore_early(self)
        if open_at_start:
            self._show_opening(camera_id)

    @property
    def export_result(self):
        """None while a replay export runs, then ``("done", path)`` or ``("error", message)``."""
        return None if self.export.state == "running" else self.export.result

    # ------------------------------------------------------------------ UI
    # layout.py
    _build_ui = layout.build_ui
    _fit_to_screen = layout.fit_to_screen

    # --------------------------------------------------------- background
    def run_background(self, name: str, fn: Callable, on_done: Callable, *args):
        """Run ``fn(*args)`` in a worker thread; ``on_done(result, error_message)`` in the GUI thread."""
        self._busy.add(name)

        def job():
            try:
                result = fn(*args)
            except BaseException as exc:  # noqa: BLE001 - shown to the user
                log.debug("background %s failed:\n%s", name, traceback.format_exc())
                msg = str(exc) or type(exc).__name__
                if not isinstance(exc, (ValueError, OSError, RuntimeError)):
                    msg = f"{type(exc).__name__}: {msg}"
                self._bridge.done.emit((name, on_done), None, msg)
                return
            self._bridge.done.emit((name, on_done), result, None)

        return self._executor.submit(job)

    @QtCore.Slot(object, object, object)
    def _background_done(self, tag, result, error):
        name, on_done = tag
        self._busy.discard(name)
        if self._closing:
            return
        on_done(result, error)

    def busy(self, name: str) -> bool:
        return name in self._busy

    # ------------------------------------------------------------- errors
    def show_error(self, text: str) -> None:
        """Show a problem in the window (banner + status bar); the app keeps running."""
        self.last_error = text
        if text not in self.errors:
            self.errors.append(text)
        self.banner.setText("\n\n".join(reversed(self.errors[-3:])))  # newest first
        self.banner.setVisible(True)
        self.banner_close.setVisible(True)
        self.statusBar().showMessage(text.splitlines()[0], 15000)
        log.warning("%s", text)

    def clear_error(self) -> None:
        self.banner.setVisible(False)
        self.banner_close.setVisible(False)
        self.last_error = None
        self.errors.clear()

    def info(self, text: str, timeout_ms: int = 8000) -> None:
        """A passing message in the status bar (full text as its tooltip)."""
        self.statusBar().showMessage(text, timeout_ms)
        self.message_label.setText(text)
        self.message_label.setVisible(bool(text))
        self._message_timer.start(timeout_ms)

    # ------------------------------------------------------------- camera
    def search_cameras(self):
        def found(result, error):
            if error:
                self.show_error(f"Searching cameras failed: {error}")
                return
            infos, note = result
            self.camera_panel.set_cameras(infos, note)
            if self.session.camera_id:  # the list may come after the camera opened: keep it selected
                self.camera_panel.select_camera(self.session.camera_id)
        self.run_background("search", self.session.list_cameras, found)

    def open_camera(self, camera_id: Optional[str] = None):
        """Open ``camera_id`` (None: first found, else the synthetic scene) and start streaming."""
        self._show_opening(camera_id)
        self.run_background("open", self.session.open, self._camera_opened, camera_id)

    def _show_opening(self, camera_id):
        text = ("searching cameras…" if camera_id is None else
                "preparing the synthetic tank (still water)…" if camera_id == "synthetic" else
                f"opening camera {camera_id}…")
        self.info(text)
        if self.session.acquisition is None:
            self.raw_view.show_message(text)

    def use_camera(self, camera, *, geometry=None, reference=None, camera_id: Optional[str] = None):
        """Stream from an already built camera (scripts, tests, benchmarks); blocks while it starts."""
        opened = self.session.use_camera(camera, camera_id=camera_id)
        opened.geometry = geometry
        opened.restore = False  # a camera handed over by a script keeps its own settings
        self._camera_opened(opened, None)
        if reference is not None:
            self.set_reference(reference, "given")
        return opened

    def _camera_opened(self, result, error):
        if error and state.remembered_camera_failed(self, error):
            return  # the last session's camera is not there: searching instead
        if error:
            self.show_error(f"Could not open the camera: {error}\nPick another camera in Controls ▸ Camera "
                            "and press Open; the synthetic camera always works.")
            return
        opened = result
        self.raw_view.show_message("")
        if opened.cameras:
            self.camera_panel.set_cameras(opened.cameras, opened.note)
        elif self.camera_panel.camera_box.count() <= 1:  # opened by id: the list fills in after the first frame
            QtCore.QTimer.singleShot(500, self, lambda: None if self._closing else self.search_cameras())
        self.camera_panel.select_camera(opened.camera_id)
        tank = self.session.tank
        self.camera_panel.set_synthetic(tank is not None)
        if tank is not None:
            self.camera_panel.show_scene(tank.scene, state.STILL_WATER_PROMPT if tank.scene == "still"
                                         else state.scene_loop_text(tank))
        self.camera_panel.show_settings(opened.settings)
        if opened.note:  # what opening it changed (a colour format set to mono): kept beside the list
            self.camera_panel.found_label.setText(opened.note)
        self.clear_error()
        # replaces "preparing…"/"opening…", which would otherwise stay up to 8 s over the new camera
        self.info(opened.note or f"camera {opened.camera_id} streaming", 8000 if opened.note else 3000)
        state.camera_opened(self, opened)
        self.session.worker.set_alignment(self.tabs.currentIndex() == 1)
        self._update_cost()
        if opened.reference is not None and self.reference is None and opened.use_scene_reference:
            self.set_reference(opened.reference, "synthetic scene's flat-surface frame")

    def configure_camera(self, values: dict):
        def done(settings, error):
            if error:
                self.show_error(f"Camera refused the settings: {error}")
                settings = self.session.camera_settings()
            if settings is not None:
                self.camera_panel.show_settings(settings)
                self._update_cost()
                state.remember_camera_settings(self, settings)
                reference_flow.follow_roi(self, settings)
        from .model.camera import settings_to_write  # the features the camera has (its greyed editors: none)
        self.run_background("configure", self.session.configure, done,
                            settings_to_write(values, self.session.camera_settings()))

    # ---------------------------------------------------------- reference
    # reference_flow.py
    capture_reference = reference_flow.capture_reference
    set_reference = reference_flow.set_reference
    _rebuild_reconstructor = reference_flow.rebuild_reconstructor
    _choose_save_reference = reference_flow.choose_save_reference
    save_reference = reference_flow.save_reference
    _choose_load_reference = reference_flow.choose_load_reference
    load_reference = reference_flow.load_reference
    set_geometry = reference_flow.set_geometry
    apply_geometry_editor = reference_flow.apply_geometry_editor
    _show_region = reference_flow.show_region
    _frame_shape = reference_flow.frame_shape
    _region_dragged = reference_flow.region_dragged
    _choose_load_geometry = reference_flow.choose_load_geometry
    load_geometry = reference_flow.load_geometry
    _choose_save_geometry = reference_flow.choose_save_geometry
    save_geometry = reference_flow.save_geometry

    # ----------------------------------------------------------- geometry

    def confirm_geometry(self) -> None:
        """The geometry in use is this camera's (remembered with it; the "not to scale" banner goes)."""
        state.confirm_geometry(self)

    # ----------------------------------------------------- scene, session
    def set_scene(self, name: str) -> None:
        """Show scene ``name`` (still, waves, drop, impact) on the synthetic camera's simulated tank.

        A scene not yet ray-traced is prepared in the background (progress in Controls ▸ Camera and the
        status bar); still water streams meanwhile.
        """
        from app.capture.scene import SCENES

        tank = self.session.tank
        if name not in SCENES:
            self.show_error(f"Unknown scene {name!r}: choose one of {', '.join(SCENES)}.")
            return
        if tank is None:
            self.show_error("Tank scenes need the synthetic camera: choose 'synthetic' in Controls ▸ Camera "
                            "and press Open.")
            return
        self.scene_wanted = name

        def done(_, error):
            if error:
                self.show_error(f"Scene {name} could not be prepared: {error}")
            elif self.session.tank is tank and self.scene_wanted == name:
                tank.set_scene(name)
                self.camera_panel.show_scene(name, "" if name != "still" else "still water")
                self.info(f"tank scene: {name}")
                log.info("synthetic tank: scene %s streaming", name)
        if tank.ready(name):
            done(None, None)
        elif not self.busy(f"scene-{name}"):
            self.run_background(f"scene-{name}", tank.prepare, done, name)

    def save_experiment(self, path: str) -> str:
        """Write geometry + reference + settings to the experiment TOML ``path``; returns the file written."""
        return state.save_experiment(self, path)

    def open_experiment(self, path: str) -> bool:
        """Use the geometry, reference and settings of the experiment TOML ``path``; False (shown) if unusable."""
        return state.open_experiment(self, path)

    # ---------------------------------------------------------- recording
    # recording_flow.py
    _update_cost = recording_flow.update_cost
    _choose_folder = recording_flow.choose_folder
    arm = recording_flow.arm
    threshold_from_now = recording_flow.threshold_from_now
    trigger_now = recording_flow.trigger_now
    disarm = recording_flow.disarm
    _update_recording = recording_flow.update_recording

    def use_gpu(self, on: bool) -> None:
        """Live reconstruction on the GPU (``on``) or the CPU; remembered, and the reconstructor rebuilt."""
        self.memory.use_gpu = bool(on)
        self._rebuild_reconstructor()
        self.info(f"live reconstruction on the {'GPU, when CuPy sees one' if on else 'CPU'}")

    def _frame_alignment(self, frame):
        """Alignment without reference (worker thread): carriers of the live frame, or its dots."""
        from .alignment import frame_alignment
        geometry = self.geometry
        return frame_alignment(frame, getattr(geometry, "theta_deg", None),
                               pattern=getattr(geometry, "pattern", "checkerboard"), geometry=geometry,
                               motion=self.frame_motion)

    # ------------------------------------------------------------- replay
    # replay_flow.py
    _choose_recording = replay_flow.choose_recording
    open_recording = replay_flow.open_recording
    _show_replay_frame = replay_flow.show_replay_frame
    _process_replay_frame = replay_flow.process_replay_frame
    _choose_export = replay_flow.choose_export
    export_heights = replay_flow.export_heights

    # ------------------------------------------------------------ refresh
    def _tab_changed(self, index: int):
        self.session.worker.set_alignment(index == 1)

    def _refresh(self):
        """Draw the newest frame/result; re-arm the single-shot timer afterwards."""
        now = time.perf_counter()
        if self.export.state == "running":  # an export is running in the background
            self.replay.progress.setValue(int(100 * self.export.fraction))
        if self._retry_armed:  # not a tick: one look again for a late camera frame (DrawClock.retry_s)
            return self._look_again()
        self.clock.tick(now)  # <= 60 Hz at a fixed cadence; a late tick never piles up (model/schedule.py)
        try:
            if not (self.pause_box.isChecked() or self.frozen):
                self._draw()
        except Exception:  # noqa: BLE001 - a drawing bug must not stop the display
            log.exception("display refresh failed")
        finally:
            if not self._closing:
                now = time.perf_counter()
                retry = self.clock.retry_s(now)
                self._retry_armed = retry is not None
                self._display_timer.start(timer_ms(retry or self.clock.wait_s(now)))

    def _draw(self):
        """One display tick: what :meth:`DrawClock.plan` says (the newest camera frame, maps in one tick or two)."""
        tab = self.tabs.currentIndex()
        frame = self.session.latest_frame() if tab in (LIVE_TAB, ALIGNMENT_TAB) else None
        p = self.session.worker.latest()
        plan = self.clock.plan(time.monotonic(), tab, None if frame is None else frame[0], p)
        if plan.raw:
            self._show_raw(frame, tab)
        self._draw_maps(plan, p)
        self.shown_rate.add(time.monotonic(), int(plan.raw))

    def _result_published(self, _processed) -> None:
        """The worker's listener (its thread): tell the GUI thread (:meth:`_draw_early`)."""
        if not self._closing:
            self._bridge.result_arrived.emit()

    def _draw_early(self):
        """A result has arrived: its maps now, between two ticks, when :meth:`DrawClock.plan_early` says so."""
        if self._closing or self.pause_box.isChecked() or self.frozen:
            return
        try:
            p = self.session.worker.latest()
            # the timer may be armed for a look again for a late frame (DrawClock.retry_s): the clock knows the tick
            to_tick_s = (self.clock.wait_s(time.perf_counter()) if self._retry_armed
                         else self._display_timer.remainingTime() / 1e3)  # negative: no tick armed (one is drawing)
            self._draw_maps(self.clock.plan_early(time.monotonic(), self.tabs.currentIndex(), p, to_tick_s), p)
        except Exception:  # noqa: BLE001 - a drawing bug must not stop the display
            log.exception("display of a new result failed")

    def _draw_maps(self, plan, p):
        """The maps part of ``plan`` (a :class:`TickPlan`), of the worker's result ``p``."""
        if plan.maps in ("all", "first half", "second half"):
            t0 = time.perf_counter()
            self._draw_result(plan.result, part={"all": -1, "first half": 0, "second half": 1}[plan.maps])
            self.clock.maps_took(plan.maps, time.perf_counter() - t0)  # one tick or two next time
        elif plan.maps == "alignment":
            self._draw_alignment(p)
        if plan.maps in ("all", "first half", "alignment"):
            self.result_latency_ms = (time.monotonic_ns() - p.host_timestamp_ns) / 1e6 if p.host_timestamp_ns \
                else float("nan")

    @property
    def displayed_fps(self) -> float:
        """New camera frames put on screen per second (the status bar's "shown")."""
        return self.shown_rate.rate

    def _bit_depth(self):
        s = self.session.camera_settings()
        return s.bit_depth if s is not None else 8

    # display.py
    _draw_raw = display.draw_raw
    _show_raw = display.show_raw
    _look_again = display.look_again
    _draw_result = display.draw_result
    _draw_profile = display.draw_profile
    _draw_alignment = display.draw_alignment
    _draw_spectrum = display.draw_spectrum
    _update_status = display.update_status
    _update_staleness = display.update_staleness
    _pause_toggled = display.pause_toggled

    def assess_alignment(self, a: dict, saturation_pct: float):
        """Decide "ready to measure": ``(ready, reasons, table lines, notes)`` (app/gui/alignment.py)."""
        from .alignment import assess

        return assess(a, saturation_pct, self.geometry, self.session.worker.reconstructor is not None,
                      self.pattern_problem)

    # ------------------------------------------------------------- status

    # ------------------------------------------- staleness, pause, snapshot
    def _shown_now(self, seq, host_ns) -> Shown:
        """What a view showing frame ``seq`` now shows (model/staleness.py decides when it is stale)."""
        acq = self.session.acquisition_of(seq)  # a result of the camera before, drawn after a switch: stale
        return Shown(seq, host_ns, weakref.ref(acq) if acq is not None else None,
                     self._camera_key() if acq is not None else None, self.references.measured_with(seq))

    def maps_shown_seq(self) -> Optional[int]:
        """The frame the processed maps on screen show (None: none yet)."""
        return None if self._maps_shown is None else self._maps_shown.seq

    def _camera_key(self):
        """The open camera and its region of interest: maps of another ROI are stale for another reason."""
        s = self.session.camera_settings()
        roi = tuple(getattr(s, k, None) for k in ("offset_x", "offset_y", "width", "height")) if s else None
        return (self.session.camera_id, id(self.session.camera)), roi  # the camera object: two of one model differ

    def _frames_acquired(self):
        """A counter that changes with every frame the camera delivers (which acquisition, how many)."""
        acq = self.session.acquisition
        return None if acq is None else (id(acq), acq.acquired)

    def snapshot(self, folder: Optional[str] = None):
        """Save the window as PNG and the maps on screen with their metadata as HDF5; returns both paths.

        ``folder`` defaults to ``snapshots/`` in the recording folder (Controls ▸ Trigger & recording);
        the status bar says where they went.
        """
        from .snapshot import write_snapshot

        if folder is None:
            folder = os.path.join(self.recording_panel.folder.text().strip() or os.getcwd(), "snapshots")
        # the maps stored are the last drawn frame's: its second half drawn first, so that each map's colour
        # range stored with them is its own, not the frame before's (as Pause does)
        display.finish_drawing(self)
        meta = {"camera_id": self.session.camera_id or "", "paused": bool(self.pause_box.isChecked()),
                "stale": self.height_view.stale_text or "",
                "reference": self._reference_text,
                "geometry_toml": self.geometry.to_toml_text() if self.geometry is not None else "",
                "colour_levels": {name: [float(v) for v in view.levels] for name, view in state.map_views(self).items()},
                "colour_units": {name: view.units for name, view in state.map_views(self).items()}}
        try:
            png, h5 = write_snapshot(folder, self.grab().toImage(), self.last_drawn, meta)
        except Exception as exc:  # noqa: BLE001 - disk full, no permission: shown
            self.show_error(f"Snapshot failed: {exc}\nChoose a writable recording folder "
                            "(Controls ▸ Trigger & recording).")
            return None
        self.last_snapshot = (png, h5)
        self.info(f"snapshot saved in {folder}: {os.path.basename(png)} (window), {os.path.basename(h5)} (maps)",
                  20000)
        return png, h5

    # -------------------------------------------------------------- close
    def recording_active(self) -> bool:
        """True while a recording is armed, capturing or saving."""
        rec = self.session.recording
        return self.session.capture is not None and rec is not None and \
            rec.get("state") in ("armed", "capturing", "saving")

    def _confirm_close(self) -> bool:
        rec = self.session.recording or {}
        box = QtWidgets.QMessageBox(
            QtWidgets.QMessageBox.Warning, "Recording in progress",
            f"A recording is {rec.get('state', 'running')} ({rec.get('path', '')}).\n"
            "Close anyway? The frames already written are kept; the rest of the recording is lost.",
            QtWidgets.QMessageBox.Close | QtWidgets.QMessageBox.Cancel, self)
        box.setDefaultButton(QtWidgets.QMessageBox.Cancel)
        self.close_question = box
        try:
            return box.exec() == QtWidgets.QMessageBox.Close
        finally:
            self.close_question = None

    def closeEvent(self, event):
        if not self._closing and self.recording_active() and not self._confirm_close():
            event.ignore()
            return
        self.shutdown()
        super().closeEvent(event)

    def shutdown(self):
        """Stop timers and threads; idempotent."""
        if self._closing:
            return
        try:
            state.save(self)
        except Exception:  # noqa: BLE001 - remembering must never stop the window from closing
            log.exception("could not remember the session")
        self._closing = True
        self.session.worker.remove_listener(self._result_published)
        self._display_timer.stop()
        self._status_timer.stop()
        try:
            self.session.close()
        finally:
            self._executor.shutdown(wait=True, cancel_futures=True)
            if self.replay_recording is not None:
                self.replay_recording.close()
                self.replay_recording = None
            self._collector.stop()
