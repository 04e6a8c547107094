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
import math
import os
import time
import traceback
import weakref
from typing import Callable, Optional

import numpy as np
import pyqtgraph as pg
from pyqtgraph.Qt import QtCore, QtWidgets

from . import state
from app.capture.trigger import rms_slope

from .collector import GuiThreadCollector
from .model.memory import SessionMemory
from .model.recording import RmsHistory, slope_of_mrad
from .model.region import clamp_region, region_problem
from .model.schedule import DISPLAY_MAX_HZ, DrawClock, ExportProgress, LiveRates, ReplayQueue
from .model.staleness import STALE_AFTER_S, Shown, Staleness, derived_text, view_staleness
from .panels import CameraPanel, GeometryPanel, RecordingPanel
from .replay import RECORDING_FILTER, Recording, ReplayTab
from .session import LiveSession
from .views import HistogramView, ImageView, ProfileLine, ProfileView, SpectrumView
from .widgets import ElidedLabel

__all__ = ["MainWindow"]

log = logging.getLogger(__name__)

DISPLAY_PERIOD_MS = 16  # first tick
CONTROLS_WIDTH_PX = 330  # the Controls dock, the same for every section (fits 1280x800 beside the maps)


def line_profile(data: np.ndarray, x: np.ndarray, y: np.ndarray, p0, p1):
    """Values of ``data`` along the segment ``p0 -> p1`` (both ``(x_mm, y_mm)``), bilinear.

    Parameters
    ----------
    data : ndarray, shape (rows, cols)
        Map sampled at column coordinates ``x`` (cols,) and row coordinates ``y`` (rows,), mm, uniform.
    p0, p1 : (float, float)
        Segment ends in mm.

    Returns
    -------
    distance_mm, values : ndarray
        Distance from ``p0`` along the segment (mm) and the sampled values (NaN outside the map
        or where the map is NaN). About two samples per grid step.
    """
    from scipy.ndimage import map_coordinates

    dx = (x[-1] - x[0]) / (len(x) - 1) if len(x) > 1 else 1.0
    dy = (y[-1] - y[0]) / (len(y) - 1) if len(y) > 1 else 1.0
    c0, r0 = (p0[0] - x[0]) / dx, (p0[1] - y[0]) / dy
    c1, r1 = (p1[0] - x[0]) / dx, (p1[1] - y[0]) / dy
    n = int(max(2, 2 * np.ceil(np.hypot(c1 - c0, r1 - r0)) + 1))
    t = np.linspace(0.0, 1.0, n)
    rows, cols = r0 + t * (r1 - r0), c0 + t * (c1 - c0)
    values = map_coordinates(np.asarray(data, np.float64), [rows, cols], order=1, mode="constant", cval=np.nan)
    values[(rows < -0.5) | (rows > data.shape[0] - 0.5) | (cols < -0.5) | (cols > data.shape[1] - 0.5)] = np.nan
    length = float(np.hypot(p1[0] - p0[0], p1[1] - p0[1]))
    return t * length, values


def _nz(value, digits: int = 2) -> float:
    """Round for display without showing "-0.00"."""
    v = round(float(value), digits)
    return 0.0 if v == 0 else v


class _Bridge(QtCore.QObject):
    """Carries results of background threads into the GUI thread (queued signal)."""

    done = QtCore.Signal(object, object, object)  # callback, result, error message


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
        self.geometry = None
        self.reference = None
        self._last_raw_seq = -1
        self._last_result_seq = -1
        self._shown = 0
        self._shown_t = time.monotonic()
        self.displayed_fps = 0.0
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
        self._reference_text = ""
        self._reference_epoch = 0  # counts reconstructors installed: maps of an older one are stale
        self._reference_since_seq = -1  # frames after this one are measured against the newest reference
        self.scene_wanted: Optional[str] = None
        self.clock = DrawClock()
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
        self._display_timer.setSingleShot(True)
        self._display_timer.setTimerType(QtCore.Qt.PreciseTimer)
        self._display_timer.timeout.connect(self._refresh)
        self._status_timer = QtCore.QTimer(self)
        self._status_timer.setInterval(250)
        self._status_timer.timeout.connect(self._update_status)
        self._status_timer.start()
        self._display_timer.start(DISPLAY_PERIOD_MS)
        # remembered state (app/gui/state.py): layout, recording, levels now; geometry, reference on open
        state.restore_early(self)
        if open_at_start:
            self._show_opening(camera_id)

    @property
    def export_result(self):
        """None while a replay export runs, then ``("done", path)`` or ``("error", message)``."""
        return None if self.export.state == "running" else self.export.result

    # ------------------------------------------------------------------ UI
    def _build_ui(self):
        self.banner = QtWidgets.QLabel("")
        self.banner.setWordWrap(True)
        self.banner.setSizePolicy(QtWidgets.QSizePolicy.Ignored, QtWidgets.QSizePolicy.Preferred)
        self.banner.setVisible(False)
        self.banner.setStyleSheet("background: #ffe0e0; color: #900; padding: 6px; font-weight: bold;"
                                  "border: 1px solid #c00;")
        self.banner.setTextInteractionFlags(QtCore.Qt.TextSelectableByMouse)
        self.banner_close = QtWidgets.QPushButton("×")
        self.banner_close.setFixedWidth(28)
        self.banner_close.setVisible(False)
        self.banner_close.clicked.connect(self.clear_error)
        # persistent: a camera whose geometry was never confirmed measures heights to no known scale
        self.geometry_banner = QtWidgets.QLabel("geometry not set for this camera: heights not to scale — "
                                                "enter θ, H and the scale, then Confirm (or load a geometry)")
        self.geometry_banner.setWordWrap(True)
        self.geometry_banner.setSizePolicy(QtWidgets.QSizePolicy.Ignored, QtWidgets.QSizePolicy.Preferred)
        self.geometry_banner.setStyleSheet("background: #fff3c0; color: #7a4a00; padding: 5px; font-weight: bold;"
                                           "border: 1px solid #d0a000;")
        self.geometry_confirm_button = QtWidgets.QPushButton("Confirm geometry")
        self.geometry_banner.setVisible(False)
        self.geometry_confirm_button.setVisible(False)
        self.restored_bar = QtWidgets.QLabel("")
        self.restored_bar.setWordWrap(True)
        self.restored_bar.setSizePolicy(QtWidgets.QSizePolicy.Ignored, QtWidgets.QSizePolicy.Preferred)
        self.restored_bar.setStyleSheet("background: #e4eefc; color: #123; padding: 4px; border: 1px solid #8ab;")
        self.restored_bar.setVisible(False)

        self.tabs = QtWidgets.QTabWidget()
        # Live tab: the raw frame, the height map and the profile/histogram column on top, the other
        # maps below; colour bars sit under the maps so that narrow tiles (1280x800) keep the map wide
        live = QtWidgets.QWidget()
        grid = QtWidgets.QGridLayout(live)
        grid.setContentsMargins(2, 2, 2, 2)
        grid.setSpacing(4)
        self.raw_view = ImageView("Raw frame", "counts", cmap="CET-L1", axis_units="px", pan=False)
        self.raw_view.levels_row.auto_box.setToolTip("grey levels over the sensor's full range (0 … 2^bits - 1)")
        self.height_view = ImageView("Height", "µm", cmap="CET-D1", symmetric=True, pan=False)
        self.disp_view = ImageView("Displacement |u|", "px", cmap="viridis")
        self.slope_x_view = ImageView("Slope ∂h/∂x", "mrad", cmap="CET-D1", symmetric=True)
        self.slope_y_view = ImageView("Slope ∂h/∂y", "mrad", cmap="CET-D1", symmetric=True)
        mask_cmap = pg.ColorMap([0.0, 1.0], [(190, 30, 30), (215, 240, 215)])  # masked red, valid pale green
        self.valid_view = ImageView("Valid (1) / masked (0)", "", cmap=mask_cmap,
                                    levels_controls=False)
        self.profile_view = ProfileView("Profile along the line", "height (µm)")
        self.histogram = HistogramView()
        # the histogram under the raw frame: the narrow tile then has about the frame's aspect
        raw_box = QtWidgets.QWidget()
        rb = QtWidgets.QVBoxLayout(raw_box)
        rb.setContentsMargins(0, 0, 0, 0)
        rb.setSpacing(2)
        rb.addWidget(self.raw_view, 3)
        rb.addWidget(self.histogram, 1)
        grid.addWidget(raw_box, 0, 0)
        grid.addWidget(self.height_view, 0, 1, 1, 2)
        from .probes import ProbeView
        self.probe_view = ProbeView(self.height_view.plot)  # click the height map: a wave gauge
        side = QtWidgets.QSplitter(QtCore.Qt.Vertical)
        side.addWidget(self.profile_view)
        side.addWidget(self.probe_view)
        grid.addWidget(side, 0, 3)
        grid.addWidget(self.disp_view, 1, 0)
        grid.addWidget(self.slope_x_view, 1, 1)
        grid.addWidget(self.slope_y_view, 1, 2)
        grid.addWidget(self.valid_view, 1, 3)
        self.valid_view.set_levels((0.0, 1.0))
        for col in range(4):
            grid.setColumnStretch(col, 1)
        grid.setRowStretch(0, 4)
        grid.setRowStretch(1, 3)
        self.map_views = (self.height_view, self.disp_view, self.slope_x_view, self.slope_y_view, self.valid_view)
        # saturated pixels overlay on the raw view
        self.saturation_overlay = pg.ImageItem(axisOrder="row-major")
        self.saturation_overlay.setLookupTable(np.array([[0, 0, 0, 0], [255, 0, 0, 255]], np.uint8))
        self.saturation_overlay.setZValue(10)
        self.raw_view.plot.addItem(self.saturation_overlay)
        # reference region box on the raw view (pixels)
        self.region_roi = pg.RectROI([0, 0], [64, 64], pen=pg.mkPen("#00c000", width=2), movable=True)
        self.region_roi.setZValue(20)
        self.raw_view.plot.addItem(self.region_roi)
        self.region_roi.sigRegionChangeFinished.connect(self._region_dragged)
        self._region_label = pg.TextItem("reference region (h = 0)", color="#00a000", anchor=(0, 1))
        self.raw_view.plot.addItem(self._region_label)
        # where the height offset is really pinned (from the reference), with its valid fraction
        from app.gui.pinregion import PinRegionOverlay
        self.pin_overlay = PinRegionOverlay(self.raw_view.plot)
        # profile line on the height view (mm)
        self.profile_roi = ProfileLine([[0, 0], [1, 1]])
        self.height_view.plot.addItem(self.profile_roi)
        self._profile_placed = False
        self.tabs.addTab(live, "Live")

        # Alignment tab
        align = QtWidgets.QWidget()
        ag = QtWidgets.QGridLayout(align)
        self.spectrum_view = SpectrumView()
        self.modulation_view = ImageView("Contrast (modulation)", "", cmap="viridis",
                                         axis_units="px")
        self.modulation_view.set_levels((0.0, 1.0))
        self.align_raw_view = ImageView("Camera", "counts", cmap="CET-L1", axis_units="px")
        self.ready_label = QtWidgets.QLabel("waiting for frames…")
        self.ready_label.setAlignment(QtCore.Qt.AlignCenter)
        self.ready_label.setWordWrap(True)
        self.ready_label.setMinimumHeight(70)
        self.metrics_label = QtWidgets.QLabel("")
        self.metrics_label.setTextFormat(QtCore.Qt.RichText)
        self.metrics_label.setAlignment(QtCore.Qt.AlignTop | QtCore.Qt.AlignLeft)
        self.metrics_label.setStyleSheet("font-size: 14px")
        self.metrics_label.setWordWrap(True)
        for lab in (self.ready_label, self.metrics_label):
            # long messages wrap instead of widening the window
            lab.setSizePolicy(QtWidgets.QSizePolicy.Ignored, QtWidgets.QSizePolicy.Preferred)
        metrics = QtWidgets.QWidget()
        ml = QtWidgets.QVBoxLayout(metrics)
        ml.addWidget(self.ready_label)
        ml.addWidget(self.metrics_label, 1)
        ag.addWidget(self.align_raw_view, 0, 0)
        ag.addWidget(self.spectrum_view, 0, 1)
        ag.addWidget(self.modulation_view, 1, 0)
        ag.addWidget(metrics, 1, 1)
        self.tabs.addTab(align, "Alignment")

        # Replay tab
        self.replay = ReplayTab()
        self.replay.open_requested.connect(self._choose_recording)
        self.replay.frame_changed.connect(self._show_replay_frame)
        self.replay.export_requested.connect(self._choose_export)
        self.tabs.addTab(self.replay, "Replay")
        self.tabs.currentChanged.connect(self._tab_changed)

        central = QtWidgets.QWidget()
        cl = QtWidgets.QVBoxLayout(central)
        cl.setContentsMargins(2, 2, 2, 2)
        bl = QtWidgets.QHBoxLayout()
        bl.addWidget(self.banner, 1)
        bl.addWidget(self.banner_close)
        cl.addLayout(bl)
        gl = QtWidgets.QHBoxLayout()
        gl.addWidget(self.geometry_banner, 1)
        gl.addWidget(self.geometry_confirm_button)
        cl.addLayout(gl)
        cl.addWidget(self.restored_bar)
        cl.addWidget(self.tabs, 1)
        self.setCentralWidget(central)

        # side panels
        self.camera_panel = CameraPanel()
        self.geometry_panel = GeometryPanel()
        self.recording_panel = RecordingPanel()
        side = QtWidgets.QToolBox()
        side.addItem(self._scroll(self.camera_panel), "Camera")
        side.addItem(self._scroll(self.geometry_panel), "Reference && geometry")
        side.addItem(self._scroll(self.recording_panel), "Trigger && recording")
        # one width for every section: switching sections never moves the maps
        side.setFixedWidth(CONTROLS_WIDTH_PX)
        self.side = side
        dock = QtWidgets.QDockWidget("Controls")
        dock.setObjectName("controls")
        dock.setFeatures(QtWidgets.QDockWidget.DockWidgetMovable | QtWidgets.QDockWidget.DockWidgetFloatable)
        dock.setWidget(side)
        self.addDockWidget(QtCore.Qt.LeftDockWidgetArea, dock)
        self.controls_dock = dock

        self.camera_panel.open_requested.connect(self.open_camera)
        self.camera_panel.refresh_requested.connect(self.search_cameras)
        self.camera_panel.configure_requested.connect(self.configure_camera)
        self.geometry_panel.capture_requested.connect(self.capture_reference)
        self.geometry_panel.save_reference_requested.connect(self._choose_save_reference)
        self.geometry_panel.load_reference_requested.connect(self._choose_load_reference)
        self.geometry_panel.geometry_changed.connect(self.apply_geometry_editor)
        self.geometry_panel.load_geometry_requested.connect(self._choose_load_geometry)
        self.geometry_panel.save_geometry_requested.connect(self._choose_save_geometry)
        self.recording_panel.arm_requested.connect(self.arm)
        self.recording_panel.disarm_requested.connect(self.disarm)
        self.recording_panel.trigger_requested.connect(self.trigger_now)
        self.recording_panel.browse_requested.connect(self._choose_folder)
        self.recording_panel.lengths_changed.connect(self._update_cost)
        self.recording_panel.set_from_now_requested.connect(self.threshold_from_now)
        self.recording_panel.folder.setText(os.getcwd())
        self.camera_panel.scene_requested.connect(self.set_scene)
        self.geometry_panel.confirm_geometry_requested.connect(self.confirm_geometry)
        self.geometry_confirm_button.clicked.connect(self.confirm_geometry)

        # status bar: every label elides to its room and keeps the full text as tooltip
        sb = self.statusBar()
        self.pause_box = QtWidgets.QCheckBox("Pause display")
        self.pause_box.setToolTip("Freeze the views on one frame (all maps of one frame id); acquisition, "
                                  "processing and recording go on")
        self.pause_box.toggled.connect(self._pause_toggled)
        sb.addPermanentWidget(self.pause_box)
        self.message_label = ElidedLabel("")  # info() messages: where a snapshot went, what was loaded
        self.message_label.setStyleSheet("padding: 0 4px; color: #004080")
        sb.addPermanentWidget(self.message_label, 1)
        self._message_timer = QtCore.QTimer(self)
        self._message_timer.setSingleShot(True)
        self._message_timer.timeout.connect(lambda: self.message_label.setText(""))
        self.status_labels = {}
        stretch = {"camera": 0, "fps": 0, "device": 0, "truth": 0, "drops": 1, "ring": 0, "latency": 0,
                   "state": 0}
        for key in ("camera", "fps", "device", "truth", "drops", "ring", "latency", "state"):
            lab = ElidedLabel("")
            lab.setStyleSheet("padding: 0 4px")
            sb.addPermanentWidget(lab, stretch[key])
            self.status_labels[key] = lab
        from .menus import build_menus
        build_menus(self)

    def _fit_to_screen(self, width: int, height: int) -> None:
        """Open at ``width`` x ``height`` or the screen's free area, whichever is smaller (a 1280x800 laptop)."""
        screen = QtWidgets.QApplication.primaryScreen()
        if screen is not None:
            avail = screen.availableGeometry()
            frame = 8  # window-manager border, where there is one
            width, height = min(width, avail.width() - frame), min(height, avail.height() - 2 * frame - 24)
            self.move(avail.topLeft())
        self.resize(width, height)

    @staticmethod
    def _scroll(widget):
        area = QtWidgets.QScrollArea()
        area.setWidget(widget)
        area.setWidgetResizable(True)
        area.setFrameShape(QtWidgets.QFrame.NoFrame)
        return area

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
            self.camera_panel.show_scene(tank.scene, "still water: capture the reference now" if tank.scene ==
                                         "still" else "")
        self.camera_panel.show_settings(opened.settings)
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
        self.run_background("configure", self.session.configure, done, values)

    # ---------------------------------------------------------- reference
    def capture_reference(self, n_frames: int):
        """Average ``n_frames`` new camera frames into the reference (in the background); moving water is refused."""
        self.geometry_panel.reference_label.setText(f"capturing {n_frames} frames…")

        def done(result, error):
            if error:
                kept = " (previous reference kept)" if self.reference is not None else ""
                self.geometry_panel.reference_label.setText(
                    ("REFUSED: the water is moving" if "water is moving" in error else "capture failed") + kept)
                self.geometry_panel.reference_label.setStyleSheet("color: #c00000; font-weight: bold")
                self.show_error(f"Reference capture failed: {error}")
                return
            image, report = result
            self.geometry_panel.reference_label.setStyleSheet("")
            self.set_reference(image, report.text())
        pattern = getattr(self.geometry, "pattern", "checkerboard")
        self.run_background("reference", lambda n: self.session.capture_reference(n, pattern=pattern), done,
                            int(n_frames))

    def set_reference(self, image: np.ndarray, origin: str = "", path: Optional[str] = None) -> bool:
        """Use ``image`` as the flat-surface reference: rebuild the reconstructor (background).

        ``path``: the file it came from (remembered for the next start; a captured one is kept in the cache).
        """
        self.reference = np.asarray(image)
        self.reference_path = path
        self._reference_text = f"reference: {origin}, {image.shape[1]}×{image.shape[0]} px"
        self.geometry_panel.reference_label.setText(self._reference_text + " — building…")
        self._rebuild_reconstructor()
        return True

    def _rebuild_reconstructor(self):
        if self.reference is None or self.geometry is None:
            self.session.worker.set_reconstructor(None)
            return
        reference, geometry, use_gpu = self.reference, self.geometry, self.memory.use_gpu

        if getattr(geometry, "pattern", "checkerboard") == "dots":
            # OpenPIV's first import (scipy.stats, ~1 s) here, in the GUI thread: in a background
            # thread beside the running event loop it crawled for minutes in test runs (every
            # thread waiting for the GIL, no CPU used). Likeliest cause: its allocations set the
            # garbage collector off in that thread, finalizing Qt objects there (a running QTimer
            # finalized so segfaults); app/gui/collector.py now keeps collection in this thread,
            # this import stays as a second guard until that is shown to be the whole story
            import openpiv.windef  # noqa: F401

        def build():
            from .session import NO_OVERLAP_WITH_DISCOVERY

            with NO_OVERLAP_WITH_DISCOVERY:
                return build_now()

        def build_now():
            from processing import Reconstructor, TirdeflectError
            from processing.gpu import live_device

            from .alignment import DOT_WINDOW_PX  # random dots: the windows the Alignment tab counts dots in

            # the GPU only when the user asked for it (View ▸ Live reconstruction on the GPU, remembered)
            device, text = live_device() if use_gpu else ("cpu", "CPU (GPU not asked for: View ▸ Live "
                                                                 "reconstruction on the GPU)")
            if device == "cuda":
                try:
                    rec = Reconstructor(reference, geometry, planner_effort=self.planner_effort, device="cuda",
                                        window_px=DOT_WINDOW_PX)
                    rec.device_text = text if rec.gpu_fallback is None else f"CPU ({rec.gpu_fallback})"
                    return rec
                except TirdeflectError as exc:  # e.g. a dot pattern: the GPU reads checkerboards only
                    text = f"CPU ({exc})"
            rec = Reconstructor(reference, geometry, planner_effort=self.planner_effort, window_px=DOT_WINDOW_PX)
            rec.device_text = text
            return rec

        def build_checked():
            from .alignment import periodic_pattern

            rec = build()
            return rec, (periodic_pattern(reference) if getattr(geometry, "pattern", "") == "dots" else None)

        def done(built, error):
            rec, problem = built if built is not None else (None, None)
            if error:
                self.session.worker.set_reconstructor(None)
                self.pin_overlay.set_reconstructor(None)
                self.geometry_panel.reference_label.setText("reference NOT usable")
                self.show_error(f"Bad reference: {error}")
                return
            if reference is not self.reference or geometry is not self.geometry:
                return  # superseded by a newer reference/geometry
            newest = self.session.newest_seq()  # later frames are measured against this reference
            self._reference_since_seq = newest if newest is not None else self._last_raw_seq
            self._reference_epoch += 1
            self.session.worker.set_reconstructor(rec)
            self.pin_overlay.set_reconstructor(rec)
            self.session.reference = reference
            text = self._reference_text or "reference"
            try:
                c = rec.carriers
                periods = getattr(c, "periods_px", None)
                if periods is not None:
                    text += " — periods " + ", ".join(f"{p:.2f}" for p in np.ravel(periods)) + " px"
            except Exception:  # noqa: BLE001 - information only
                pass
            self.pattern_problem = problem
            if problem:  # every height would be wrong: red where the user looks, not a tick
                self.geometry_panel.reference_label.setText(text + " — NOT the chosen pattern")
                self.geometry_panel.reference_label.setStyleSheet("color: #c00000; font-weight: bold")
                self.show_error(f"The reference does not show random dots: {problem}")
                state.reference_in_use(self)
                return
            self.geometry_panel.reference_label.setText(text + " ✓")
            self.clear_error()
            state.reference_in_use(self)
        self.run_background("reconstructor", build_checked, done)

    def _choose_save_reference(self):
        if self.reference is None:
            self.show_error("No reference to save: capture one first (Reference ▸ Capture reference).")
            return
        path, _ = QtWidgets.QFileDialog.getSaveFileName(self, "Save reference", "reference.tif",
                                                        "Images (*.tif *.tiff *.png)")
        if path:
            self.save_reference(path)

    def save_reference(self, path: str) -> None:
        from app.files.imageio import write_image
        image = self.reference
        if image.dtype.kind == "f":  # averaged: keep precision in a float TIFF
            import tifffile
            if not path.lower().endswith((".tif", ".tiff")):
                path += ".tif"
            tifffile.imwrite(path, image.astype(np.float32))
        else:
            write_image(path, image)
        self.info(f"reference saved to {path}")

    def _choose_load_reference(self):
        path, _ = QtWidgets.QFileDialog.getOpenFileName(self, "Load reference", "",
                                                        "Images (*.tif *.tiff *.png *.bmp *.h5)")
        if path:
            self.load_reference(path)

    def load_reference(self, path: str) -> None:
        try:
            from app.files.imageio import read_reference
            image = read_reference(path)
        except Exception as exc:  # noqa: BLE001 - shown
            self.show_error(f"Cannot load reference {path!r}: {exc}")
            return
        self.set_reference(image, os.path.basename(path), path=os.path.abspath(path))

    # ----------------------------------------------------------- geometry
    def set_geometry(self, geometry) -> None:
        self.geometry = geometry
        d = geometry.to_dict()
        self.geometry_panel.set_values(d)
        self._show_region(d.get("reference_region"))
        self.geometry_panel.geometry_label.setText("geometry OK")
        self._rebuild_reconstructor()
        state.geometry_in_use(self)

    def apply_geometry_editor(self):
        from processing import Geometry
        try:
            values = self.geometry_panel.values()
            base = self.geometry.to_dict() if self.geometry is not None else {}
            base.update({k: v for k, v in values.items()})
            if values["setup"] != "fsss":
                for k in ("fsss_layers", "fsss_camera_distance_mm"):
                    base.pop(k, None)
            else:
                base.pop("theta_deg", None)
            geometry = Geometry.from_dict(base)
            problem = region_problem(geometry.to_dict().get("reference_region"), self._frame_shape())
            if problem:
                raise ValueError(problem)
        except Exception as exc:  # noqa: BLE001 - GeometryError, ValueError
            self.geometry_panel.geometry_label.setText(f"<span style='color:#c00'>{exc}</span>")
            if self.geometry is not None:  # the box goes back where the geometry in use has it
                self._show_region(self.geometry.to_dict().get("reference_region"))
            return
        self.geometry_panel.geometry_label.setText("geometry OK")
        self.geometry = geometry
        self._show_region(geometry.to_dict().get("reference_region"))
        self._rebuild_reconstructor()
        state.geometry_in_use(self)

    def _show_region(self, region):
        if region is None:
            self.region_roi.setVisible(False)
            self._region_label.setVisible(False)
            return
        r0, r1, c0, c1 = (float(v) for v in region)
        self.region_roi.blockSignals(True)
        self.region_roi.setPos([c0, r0])
        self.region_roi.setSize([c1 - c0, r1 - r0])
        self.region_roi.blockSignals(False)
        self._region_label.setPos(c0, r0)
        self.region_roi.setVisible(True)
        self._region_label.setVisible(True)

    def _frame_shape(self):
        """(rows, cols) of the camera's frames (None: no camera)."""
        s = self.session.camera_settings()
        return (s.height, s.width) if s is not None and s.height and s.width else None

    def _region_dragged(self):
        """The box was dragged: kept on the frame (clamped at the edit, said so), then used."""
        pos, size = self.region_roi.pos(), self.region_roi.size()
        region = (pos.y(), pos.y() + size.y(), pos.x(), pos.x() + size.x())
        shape = self._frame_shape()
        if shape is not None:
            region, moved = clamp_region(region, shape)
            if moved:
                self.info("reference region kept inside the frame: the box cannot leave the camera image")
        r0, r1, c0, c1 = (int(round(v)) for v in region)
        self._show_region((r0, r1, c0, c1))
        self.geometry_panel.set_region((r0, r1, c0, c1))
        self.apply_geometry_editor()

    def _choose_load_geometry(self):
        path, _ = QtWidgets.QFileDialog.getOpenFileName(self, "Load geometry", "", "TOML (*.toml)")
        if path:
            self.load_geometry(path)

    def load_geometry(self, path: str) -> None:
        from processing import Geometry
        try:
            geometry = Geometry.from_toml(path)
        except Exception as exc:  # noqa: BLE001 - GeometryError, OSError
            self.show_error(f"Cannot load geometry {path!r}: {exc}")
            return
        self.set_geometry(geometry)
        self.confirm_geometry()  # a loaded geometry is this camera's set-up
        self.info(f"geometry loaded from {path}")

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

    def _choose_save_geometry(self):
        path, _ = QtWidgets.QFileDialog.getSaveFileName(self, "Save geometry", "geometry.toml", "TOML (*.toml)")
        if path:
            self.save_geometry(path)

    def save_geometry(self, path: str) -> None:
        if self.geometry is None:
            self.show_error("No valid geometry to save: fix the fields marked in red first.")
            return
        with open(path, "w", encoding="utf-8") as fh:
            fh.write(self.geometry.to_toml_text())
        self.info(f"geometry saved to {path}")

    # ---------------------------------------------------------- recording
    def _update_cost(self):
        s = self.session.camera_settings()
        if s is None:
            return
        bpp = 1 if s.bit_depth <= 8 else 2
        acq = self.session.acquisition
        self.recording_panel.set_cost(s.width * s.height * bpp, s.frame_rate_hz,
                                      acq.ring.n_frames if acq is not None else None)

    def _choose_folder(self):
        path = QtWidgets.QFileDialog.getExistingDirectory(self, "Recording folder",
                                                          self.recording_panel.folder.text())
        if path:
            self.recording_panel.folder.setText(path)

    def arm(self):
        """Arm a pre/post-trigger recording into the chosen folder."""
        rp = self.recording_panel
        folder = rp.folder.text().strip() or os.getcwd()
        threshold = slope_of_mrad(rp.threshold.value()) if rp.auto.isChecked() else None
        geometry_toml = self.geometry.to_toml_text() if self.geometry is not None else None
        try:
            path = self.session.arm(folder, rp.pre.value(), rp.post.value(), reference=self.reference,
                                    geometry_toml=geometry_toml, auto_threshold=threshold)
        except Exception as exc:  # noqa: BLE001 - disk space, RAM, no camera...
            rp.set_state("error")
            self.show_error(f"Cannot arm the recording: {exc}")
            return
        rp.result_label.setText(f"armed: will write {path}")
        rp.set_state("armed")

    def use_gpu(self, on: bool) -> None:
        """Live reconstruction on the GPU (``on``) or the CPU; remembered, and the reconstructor rebuilt."""
        self.memory.use_gpu = bool(on)
        self._rebuild_reconstructor()
        self.info(f"live reconstruction on the {'GPU, when CuPy sees one' if on else 'CPU'}")

    def threshold_from_now(self) -> Optional[float]:
        """"Set from now": the auto-trigger threshold = 5 x the recent RMS slope of the live maps (mrad)."""
        proposal = self.rms_history.propose_mrad()
        if proposal is None or self.stale.maps is not None:
            self.show_error("No live slope maps to set the threshold from: capture a reference on still water "
                            "(Controls ▸ Reference & geometry) and let the maps run, then press Set from now.")
            return None
        self.recording_panel.threshold.setValue(proposal)
        self.info(f"auto-trigger threshold {self.recording_panel.threshold.value():.3g} mrad: 5 × the recent "
                  f"RMS slope ({self.rms_history.readout()})")
        return proposal

    def trigger_now(self):
        try:
            self.session.trigger_now()
        except Exception as exc:  # noqa: BLE001
            self.show_error(f"Trigger failed: {exc}")

    def disarm(self):
        try:
            text = self.session.disarm()
        except Exception as exc:  # noqa: BLE001
            text = "disarm failed"
            self.show_error(f"Disarm failed: {exc}")
        self.recording_panel.set_state("idle")
        self.recording_panel.result_label.setText(text)

    def _update_recording(self):
        rec = self.session.recording_status()
        if rec is None:
            return
        rp = self.recording_panel
        state = rec["state"]
        if state != rp.state_label.text():
            rp.set_state(state)
        rp.progress.setValue(int(round(100 * rec.get("progress", 0.0))))
        if state in ("done", "error") and rec.get("summary_text") and not rec.get("_shown"):
            rec["_shown"] = True
            rp.result_label.setText(rec["summary_text"])
            if state == "error":
                self.show_error(f"Recording stopped: {rec.get('error')}\nEvery frame received so far is kept "
                                f"in {rec.get('path')}.")

    def _frame_alignment(self, frame):
        """Alignment without reference (worker thread): carriers of the live frame, or its dots."""
        from .alignment import frame_alignment
        geometry = self.geometry
        return frame_alignment(frame, getattr(geometry, "theta_deg", None),
                               pattern=getattr(geometry, "pattern", "checkerboard"))

    # ------------------------------------------------------------- replay
    def _choose_recording(self):
        path, _ = QtWidgets.QFileDialog.getOpenFileName(self, "Open recording",
                                                        self.recording_panel.folder.text(), RECORDING_FILTER)
        if path:
            self.open_recording(path)

    def open_recording(self, path: str) -> bool:
        try:
            rec = Recording(path)
        except Exception as exc:  # noqa: BLE001
            self.show_error(str(exc))
            return False
        if self.replay_recording is not None:
            self.replay_recording.close()
        self.replay_recording = rec
        self._replay_reconstructor = None
        self.replay.set_recording(rec)
        reference = rec.reference if rec.reference is not None else self.reference
        geometry = self.geometry
        if rec.geometry_toml:
            try:
                from processing import Geometry
                geometry = Geometry.from_toml_text(rec.geometry_toml)
            except Exception as exc:  # noqa: BLE001
                self.replay.message.setText(f"geometry stored in the file is unusable ({exc}); using the editor's")
        if reference is not None and geometry is not None:
            def build():
                from processing import Reconstructor

                from .session import NO_OVERLAP_WITH_DISCOVERY

                with NO_OVERLAP_WITH_DISCOVERY:  # see there
                    return Reconstructor(reference, geometry, planner_effort=self.planner_effort)

            def done(r, error):
                if error:
                    self.replay.message.setText(f"cannot process this recording: {error}")
                    return
                if self.replay_recording is rec:
                    self._replay_reconstructor = r
                    self._show_replay_frame(self.replay.slider.value())
            self.run_background("replay-reconstructor", build, done)
        else:
            missing = [what for what, have in (("reference (still water)", reference is not None),
                                                ("geometry", geometry is not None)) if not have]
            self.replay.message.setText(
                f"raw frames only: no {' and no '.join(missing)} in this file or the window; for heights, "
                f"load or capture them in Controls ▸ Reference & geometry, then open the file again")
        self._show_replay_frame(0)
        self.tabs.setCurrentWidget(self.replay)
        return True

    def _show_replay_frame(self, index: int):
        rec = self.replay_recording
        if rec is None or rec.n_frames == 0:
            return
        frame = rec.frame(int(index))
        self.replay.raw.set_data(frame, levels=(0, float(frame.max()) or 1.0) if self.replay.raw.auto_levels else None)
        rel = rec.trigger_index(int(index))
        when = rec.frame_time_s  # NaN where the file has no times (recordings, TIFF stacks)
        self.replay.index_label.setText(f"frame {index + 1}/{rec.n_frames}"
                                        + (f"  (trigger {rel:+d})" if rel is not None else "")
                                        + (f"  t = {when * 1e3:+.4f} ms from the {rec.time_origin}"
                                           if math.isfinite(when) else ""))
        self.replay_queue.want(frame, int(index))
        self._process_replay_frame()

    def _process_replay_frame(self):
        """Reconstruct the wanted replay frame in the background (newest request only; never in the GUI thread)."""
        r = self._replay_reconstructor
        wanted = self.replay_queue.take(ready=r is not None and not self.busy("replay-frame"))
        if wanted is None:
            return  # a running job picks up the newest wanted frame when it ends
        frame, index = wanted
        rec = self.replay_recording

        def job():
            r.reset_series()  # frames may be visited in any order: no temporal unwrapping across them
            return r(frame, grid="decimated")

        def done(result, error):
            if self.replay_recording is not rec:
                return
            if error:
                self.replay.height.show_message(error)
            else:
                self.replay.height.show_message("")
                self.replay.height.set_data(np.multiply(result.height, 1e3, dtype=np.float32),
                                            x=result.x_mm, y=result.y_mm)
                self.replay_last_result = result
                self.replay_shown_index = index
            self._process_replay_frame()
        self.run_background("replay-frame", job, done)

    def _choose_export(self):
        rec = self.replay_recording
        if rec is None:
            return
        default = os.path.splitext(rec.path)[0] + "-heights.h5"
        path, _ = QtWidgets.QFileDialog.getSaveFileName(self, "Export heights", default, "HDF5 (*.h5)")
        if path:
            self.export_heights(path)

    def export_heights(self, out_path: str) -> None:
        """Process every frame of the open recording into ``out_path`` (background, with progress)."""
        rec = self.replay_recording
        if rec is None:
            self.show_error("Open a recording first (Replay ▸ Open recording).")
            return
        self.replay.progress.setRange(0, 100)  # the batch reports every frame written; _refresh shows it
        self.replay.progress.setValue(0)
        self.replay.message.setText(f"exporting {rec.n_frames} frames to {out_path}…")
        self.export.start()
        progress = self.export.progress

        geometry_toml = rec.geometry_toml or (self.geometry.to_toml_text() if self.geometry else None)

        def job():
            from . import export
            return export.export_heights(rec.path, out_path, geometry_toml=geometry_toml,
                                         reference=None if rec.reference is not None else self.reference,
                                         progress=progress)

        def done(result, error):
            self.export.finish(("error", error) if error else ("done", out_path))
            self.replay.progress.setRange(0, 100)
            self.replay.progress.setValue(int(100 * self.export.fraction))
            if error:
                self.show_error(f"Export failed: {error}\nFrames exported before the error are kept in {out_path}.")
                return
            from .export import describe_export

            text, clean = describe_export(out_path)
            self.replay.message.setText(text)
            self.replay.message.setStyleSheet("" if clean else "color: #b00000; font-weight: bold")
            self.info(text, 20000)
        self.run_background("export", job, done)

    # ------------------------------------------------------------ refresh
    def _tab_changed(self, index: int):
        self.session.worker.set_alignment(index == 1)

    def _refresh(self):
        """Draw the newest frame/result; re-arm the single-shot timer afterwards."""
        now = time.perf_counter()
        if self.export.state == "running":  # an export is running in the background
            self.replay.progress.setValue(int(100 * self.export.fraction))
        self.clock.tick(now)  # <= 60 Hz at a fixed cadence; a late tick never piles up (model/schedule.py)
        try:
            if not (self.pause_box.isChecked() or self.frozen):
                self._draw()
        except Exception:  # noqa: BLE001 - a drawing bug must not stop the display
            log.exception("display refresh failed")
        finally:
            if not self._closing:
                wait_ms = 1e3 * self.clock.wait_s(time.perf_counter())
                self._display_timer.start(max(1, int(round(wait_ms))))

    def _draw(self):
        """One display tick: the newest camera frame, then (at <= 30 Hz) the newest processed maps.

        ``displayed_fps`` counts new camera frames put on screen per second (the status bar's "shown").
        """
        tab = self.tabs.currentIndex()
        if tab in (0, 1):
            frame = self.session.latest_frame()
            if frame is not None and frame[0] != self._last_raw_seq:
                seq, image, host_ns = frame
                if self.first_frame_s is None:
                    self.first_frame_s = time.monotonic() - self._t_created
                    log.info("first camera frame on screen %.2f s after the window was created",
                             self.first_frame_s)
                self._last_raw_seq = seq
                self._draw_raw(image, tab, host_ns, seq)
                self.latency_ms = (time.monotonic_ns() - host_ns) / 1e6 if host_ns else float("nan")
                self._shown += 1
        p = self.session.worker.latest()
        maps_due = self.clock.maps_due(time.monotonic())
        second_half = self.clock.take_second_half()
        if second_half is not None and tab == 0:
            # the other half of the maps of the result drawn on the previous tick: spreading the
            # work over two ticks keeps every tick short, so the raw view keeps its cadence
            self._draw_result(second_half, part=1)
        elif p is not None and p.seq != self._last_result_seq and tab in (0, 1) and maps_due:
            self._last_result_seq = p.seq
            if tab == 0:
                self._draw_result(p, part=0)
                self.clock.maps_drawn(time.monotonic(), p)
            else:
                self.clock.maps_drawn(time.monotonic(), None)
                self._draw_alignment(p)
            self.result_latency_ms = (time.monotonic_ns() - p.host_timestamp_ns) / 1e6 if p.host_timestamp_ns \
                else float("nan")
        t = time.monotonic()
        if t - self._shown_t >= 1.0:
            self.displayed_fps = self._shown / (t - self._shown_t)
            self._shown, self._shown_t = 0, t

    def _bit_depth(self):
        s = self.session.camera_settings()
        return s.bit_depth if s is not None else 8

    def _draw_raw(self, image, tab, host_ns=0, seq=None):
        bits = self._bit_depth()
        top = float((1 << bits) - 1)
        view = self.raw_view if tab == 0 else self.align_raw_view
        # auto: the sensor's full range (saturation visible at a glance); a typed range is kept
        view.set_data(image, levels=(0.0, top) if view.auto_levels else None, stamp_ns=host_ns, frame_id=seq)
        self._raw_shown = self._shown_now(seq, host_ns)
        view.set_stale(None)
        if tab == 0:
            k = view.stride
            sub = image[::k, ::k] if k > 1 else image
            mask = (sub >= top).view(np.uint8)
            self.saturation_overlay.setImage(mask, autoLevels=False, levels=(0, 1))
            if self.saturation_overlay.width() != sub.shape[1] or not self._overlay_rect == (image.shape, k):
                self.saturation_overlay.setRect(QtCore.QRectF(0, 0, image.shape[1], image.shape[0]))
                self._overlay_rect = (image.shape, k)
            p = self.session.worker.latest()
            sat = p.saturation_pct if p is not None else 0.0
            self._hist_count += 1
            if self._hist_count % 6 == 0:  # ~10 Hz is plenty for a histogram
                self.histogram.set_image(image, bits, sat)

    def _draw_result(self, p, part: int = -1):
        """Draw the maps of ``p``: part 0 height, profile, mask; part 1 displacement and slopes; -1 all."""
        r = p.result
        views = self.map_views
        if r is None:
            if part in (0, -1):
                text = p.error or ("no reference yet: capture one (Controls ▸ Reference & geometry)"
                                   if self.session.worker.reconstructor is None else "")
                # the full text on the height map; the small maps say what happened in a few words
                short = text.split(":")[0] + " (see Height)" if ":" in text else None
                for v in views:
                    v.show_message(text, None if v is self.height_view else short)
                self._unmeasured = p  # the maps on screen (if any) are older than this frame: stale
                self._update_staleness()
            return
        x, y = r.x_mm, r.y_mm
        seq = p.seq
        if part in (0, -1):
            for v in views:
                v.show_message("")
            self.last_drawn = p
            self.pin_overlay.update(r)
            self._unmeasured = None
            self._maps_shown = self._shown_now(seq, p.host_timestamp_ns)
            height_um = np.multiply(r.height, 1e3, dtype=np.float32)
            self.height_view.set_data(height_um, x=x, y=y, stamp_ns=p.host_timestamp_ns, frame_id=seq)
            self.valid_view.set_data(r.valid.astype(np.float32), x=x, y=y, levels=(0.0, 1.0), frame_id=seq)
            self._draw_profile(height_um, x, y)
            self.profile_view.frame_id = seq
            self.probe_view.update(p)
        if part in (1, -1):
            u = r.displacement
            self.disp_view.set_data(np.hypot(u[0], u[1]).astype(np.float32), x=x, y=y, frame_id=seq)
            self.slope_x_view.set_data(np.multiply(r.slope_x, 1e3, dtype=np.float32), x=x, y=y, frame_id=seq)
            self.slope_y_view.set_data(np.multiply(r.slope_y, 1e3, dtype=np.float32), x=x, y=y, frame_id=seq)
            self.rms_history.add(rms_slope(r.slope_x, r.slope_y), seq)  # what the auto-trigger compares
            if not self.height_view.is_stale:
                for v in views:
                    v.set_stale(None)

    def _draw_profile(self, height_um, x, y):
        if not self._profile_placed and len(x) > 1 and len(y) > 1:
            ym = float(y[len(y) // 2])
            self.profile_roi.set_ends((float(x[0]), ym), (float(x[-1]), ym))
            self._profile_placed = True
        p0, p1 = self.profile_roi.ends()
        distance_mm, values = line_profile(height_um, x, y, p0, p1)
        self.profile_line_mm = (p0, p1)
        self.profile_view.set_profile(distance_mm, values, y_range=self.height_view.levels)

    def _draw_alignment(self, p):
        a = p.alignment
        if a is None:
            return
        self._align_shown = self._shown_now(p.seq, p.host_timestamp_ns)
        for v in (self.spectrum_view, self.modulation_view):
            v.set_stale(None)
        if p.spectrum is not None:
            self._draw_spectrum(p.spectrum)
        mod = a.get("modulation") if isinstance(a, dict) else None
        if mod is None and isinstance(a, dict) and "dot_size_px" in a and p.image is not None:
            # Reconstructor.alignment of dots has no contrast map: the live frame's, as before the reference
            from .alignment import DOT_WINDOW_PX, modulation_map

            mod, rows, cols = modulation_map(p.image, window_px=DOT_WINDOW_PX, step_px=DOT_WINDOW_PX // 2)
            a = dict(a, modulation=mod, modulation_rows_px=rows, modulation_cols_px=cols)
        if mod is not None:
            self.modulation_view.set_data(np.asarray(mod, np.float32), x=a.get("modulation_cols_px"),
                                          y=a.get("modulation_rows_px"), levels=(0.0, 1.0))
        ready, reasons, lines, notes = self.assess_alignment(a, p.saturation_pct)
        self.alignment_ready = ready
        self.alignment_metrics = dict(lines)
        lines = lines + [("note", n) for n in notes]
        if ready:
            self.ready_label.setText("READY TO MEASURE")
            self.ready_label.setStyleSheet("background:#d8f5d8; color:#060; font-size:22px; font-weight:bold;"
                                           "border:2px solid #060")
        else:
            self.ready_label.setText("NOT READY: " + "; ".join(reasons))
            self.ready_label.setStyleSheet("background:#fff0d0; color:#930; font-size:16px; font-weight:bold;"
                                           "border:2px solid #c60")
        self.metrics_label.setToolTip(a.get("error") or "")  # the table shortens a long problem
        self.metrics_label.setText("<table cellpadding=3>" + "".join(
            f"<tr><td>{k}</td><td><b>{v}</b></td></tr>" for k, v in lines) + "</table>")

    def _draw_spectrum(self, spec):
        get = (lambda k, d=None: spec.get(k, d)) if isinstance(spec, dict) else \
            (lambda k, d=None: getattr(spec, k, d))
        mag = get("log_magnitude")
        if mag is None:
            mag = get("magnitude")
        if mag is None and isinstance(spec, np.ndarray):
            mag = spec
        if mag is None:
            return
        fx, fy = get("freq_x"), get("freq_y")
        carriers = get("carriers_cycles_per_px") or get("carriers") or ()
        try:
            pts = [(float(c[0]), float(c[1])) for c in carriers]
        except Exception:  # noqa: BLE001
            pts = []
        self.spectrum_view.set_spectrum(mag, fx, fy, pts)

    def assess_alignment(self, a: dict, saturation_pct: float):
        """Decide "ready to measure": ``(ready, reasons, table lines, notes)`` (app/gui/alignment.py)."""
        from .alignment import assess

        return assess(a, saturation_pct, self.geometry, self.session.worker.reconstructor is not None,
                      self.pattern_problem)

    # ------------------------------------------------------------- status
    def _update_status(self):
        st = self.session.status()
        w = self.session.worker
        lab = self.status_labels
        err = st.get("error")
        now = time.monotonic()
        # rates fall to 0 when nothing new arrives (a lost camera keeps its last measured rate otherwise)
        camera_fps = self.rates.rate("camera", self._frames_acquired(), st.get("camera_fps", 0.0), now)
        processed_fps = self.rates.rate("processed", w.processed, w.fps, now)
        if err or self.session.acquisition is None:
            camera_fps = 0.0
        if err:
            lab["camera"].setText(f"{st.get('camera_text', 'camera')} LOST")
            lab["camera"].setStyleSheet("padding: 0 4px; color: #c00000; font-weight: bold")
        else:
            lab["camera"].setText(st.get("camera_text", ""))
            lab["camera"].setStyleSheet("padding: 0 4px")
        shown_fps = 0.0 if self.pause_box.isChecked() or self.frozen else self.displayed_fps
        lab["fps"].setText(f"camera {camera_fps:.1f} · processed {processed_fps:.1f} · "
                           f"shown {shown_fps:.1f} fps")
        self.camera_fps_shown = camera_fps
        lab["drops"].setText(
            f"dropped: camera {st.get('dropped_camera', 0)} · ring→recorder {st.get('dropped_ring', 0)} · "
            f"recorder backlog {st.get('recorder_backlog', 0)} · display skipped {w.skipped} (by design)")
        fill = st.get("ring_fill")
        lab["ring"].setText(f"ring {100 * fill:.0f} %" if fill is not None else "")
        lab["ring"].setToolTip(f"ring buffer {100 * fill:.0f} % full, {st.get('ring_frames', 0)} frames"
                               if fill is not None else "")
        lab["latency"].setText(f"latency {self.latency_ms:.0f} ms" if np.isfinite(self.latency_ms) else "")
        rec = w.reconstructor  # where the live maps are computed: the GPU only when asked for
        device_text = getattr(rec, "device_text", "") if rec is not None else ""
        lab["device"].setText(f"live on {device_text.split(' (')[0]}" if device_text else "")
        lab["device"].setToolTip(f"live reconstruction on the {device_text}" if device_text else "")
        self._update_staleness()
        if err and err != self._shown_camera_error:
            self._shown_camera_error = err
            from .camera_messages import explain_open_error, is_controlled_elsewhere
            if is_controlled_elsewhere(err):  # another program holds the camera: say so, not "check the cable"
                self.show_error(f"Camera problem: {explain_open_error(self.session.camera_id, err)}")
            else:
                self.show_error(f"Camera problem: {err}\nCheck the cable, power and network, then press Open in "
                                "Controls ▸ Camera. The app keeps running; frames already recorded are kept.")
        lab["state"].setText("camera stopped" if err else "")
        self._update_recording()
        state.update_truth(self)


    # ------------------------------------------- staleness, pause, snapshot
    def _shown_now(self, seq, host_ns) -> Shown:
        """What a view showing frame ``seq`` now shows (model/staleness.py decides when it is stale)."""
        acq = self.session.acquisition
        measured_with = self._reference_epoch if seq is None or seq > self._reference_since_seq \
            else self._reference_epoch - 1
        return Shown(seq, host_ns, weakref.ref(acq) if acq is not None else None, self._camera_key(),
                     measured_with)

    def maps_shown_seq(self) -> Optional[int]:
        """The frame the processed maps on screen show (None: none yet)."""
        return None if self._maps_shown is None else self._maps_shown.seq

    def _camera_key(self):
        """The open camera and its region of interest: maps of another ROI are stale for another reason."""
        s = self.session.camera_settings()
        roi = tuple(getattr(s, k, None) for k in ("offset_x", "offset_y", "width", "height")) if s else None
        return self.session.camera_id, roi

    def _frames_acquired(self):
        """A counter that changes with every frame the camera delivers (which acquisition, how many)."""
        acq = self.session.acquisition
        return None if acq is None else (id(acq), acq.acquired)

    def _update_staleness(self) -> None:
        """Grey out and label every view whose data is not the newest the camera gave (ages refreshed 4x/s)."""
        if self.pause_box.isChecked() or self.frozen:
            return  # the user froze the views on purpose
        unmeasured = self._unmeasured
        self.stale = view_staleness(
            time.monotonic_ns(), self.session.acquisition, raw=self._raw_shown, maps=self._maps_shown,
            alignment=self._align_shown, unmeasured_seq=None if unmeasured is None else unmeasured.seq,
            frame_rate_hz=getattr(self.session.camera_settings(), "frame_rate_hz", None),
            camera_key=self._camera_key(),
            reference_key=self._reference_epoch if self.session.worker.reconstructor is not None else None)
        for v in (self.raw_view, self.align_raw_view):
            v.set_stale(self.stale.raw)
        for v in (*self.map_views, self.profile_view, self.probe_view):
            v.set_stale(self.stale.maps)
        for v in (self.spectrum_view, self.modulation_view):
            v.set_stale(self.stale.alignment)
        rp = self.recording_panel  # the auto-trigger's quantity, from the maps on screen: their age too
        text, old = derived_text(self.rms_history.readout(), self.stale.maps, measured_seq=self.rms_history.seq,
                                 maps_seq=self._maps_shown.seq if self._maps_shown is not None else None)
        rp.rms_label.setText(text)
        rp.rms_label.setStyleSheet("color: #888" if old else "")

    def _pause_toggled(self, paused: bool) -> None:
        """Pause: finish drawing the maps of the frame on screen and show its raw frame, so all views show one frame."""
        views = (*self.map_views, self.raw_view, self.profile_view)
        if not paused:
            for v in views:
                v.show_paused(None)
            return
        pending = self.clock.take_second_half()
        if pending is not None:
            self._draw_result(pending, part=1)
        p = self.last_drawn
        if p is not None and self.raw_view.frame_id != p.seq and p.image is not None \
                and not self.raw_view.is_stale:
            self._draw_raw(p.image, 0, p.host_timestamp_ns, p.seq)
        for v in views:
            if v.frame_id is not None:
                v.show_paused(f"PAUSED: frame {v.frame_id}")
        if p is not None:
            self.info(f"display paused on frame {p.seq}: the raw frame and every map show that frame")

    def snapshot(self, folder: Optional[str] = None):
        """Save the window as PNG and the maps on screen with their metadata as HDF5; returns both paths.

        ``folder`` defaults to ``snapshots/`` in the recording folder (Controls ▸ Trigger & recording);
        the status bar says where they went.
        """
        from .snapshot import write_snapshot

        if folder is None:
            folder = os.path.join(self.recording_panel.folder.text().strip() or os.getcwd(), "snapshots")
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
