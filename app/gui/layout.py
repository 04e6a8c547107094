"""The window's widgets: tabs, maps, Controls dock, status bar (built once, by MainWindow.__init__).

Functions take the :class:`app.gui.window.MainWindow` (``w``); it forwards its methods here.
"""

from __future__ import annotations

import os

import numpy as np
import pyqtgraph as pg
from pyqtgraph.Qt import QtCore, QtWidgets

from .model.colour_range import SURFACE
from .panels import CameraPanel, GeometryPanel, RecordingPanel
from .replay import ReplayTab
from .views import HistogramView, ImageView, ProfileLine, ProfileView, ScreenImageItem, SpectrumView
from .widgets import ElidedLabel



CONTROLS_WIDTH_PX = 330  # the Controls dock, the same for every section (fits 1280x800 beside the maps)


#: Smallest height (px) of the Alignment tab's camera image and spectrum, whatever the table below says.
MIN_ALIGNMENT_VIEW_PX = 200


def build_ui(w):
    w.banner = QtWidgets.QLabel("")
    w.banner.setWordWrap(True)
    w.banner.setSizePolicy(QtWidgets.QSizePolicy.Ignored, QtWidgets.QSizePolicy.Preferred)
    w.banner.setVisible(False)
    w.banner.setStyleSheet("background: #ffe0e0; color: #900; padding: 6px; font-weight: bold;"
                              "border: 1px solid #c00;")
    w.banner.setTextInteractionFlags(QtCore.Qt.TextSelectableByMouse)
    w.banner_close = QtWidgets.QPushButton("×")
    w.banner_close.setFixedWidth(28)
    w.banner_close.setVisible(False)
    w.banner_close.clicked.connect(w.clear_error)
    # persistent: a camera whose geometry was never confirmed measures heights to no known scale
    w.geometry_banner = QtWidgets.QLabel("geometry not set for this camera: heights not to scale — "
                                            "enter θ, H and the scale, then Confirm (or load a geometry)")
    w.geometry_banner.setWordWrap(True)
    w.geometry_banner.setSizePolicy(QtWidgets.QSizePolicy.Ignored, QtWidgets.QSizePolicy.Preferred)
    w.geometry_banner.setStyleSheet("background: #fff3c0; color: #7a4a00; padding: 5px; font-weight: bold;"
                                       "border: 1px solid #d0a000;")
    w.geometry_confirm_button = QtWidgets.QPushButton("Confirm geometry")
    w.geometry_banner.setVisible(False)
    w.geometry_confirm_button.setVisible(False)
    w.restored_bar = QtWidgets.QLabel("")
    w.restored_bar.setWordWrap(True)
    w.restored_bar.setSizePolicy(QtWidgets.QSizePolicy.Ignored, QtWidgets.QSizePolicy.Preferred)
    w.restored_bar.setStyleSheet("background: #e4eefc; color: #123; padding: 4px; border: 1px solid #8ab;")
    w.restored_bar.setVisible(False)

    w.tabs = QtWidgets.QTabWidget()
    # Live tab: the raw frame, the height map and the profile/histogram column on top, the other
    # maps below; colour bars sit under the maps so that narrow tiles (1280x800) keep the map wide
    live = QtWidgets.QWidget()
    grid = QtWidgets.QGridLayout(live)
    grid.setContentsMargins(2, 2, 2, 2)
    grid.setSpacing(4)
    w.raw_view = ImageView("Raw frame", "counts", cmap="CET-L1", axis_units="px", pan=False)
    w.raw_view.levels_row.auto_box.setToolTip("grey levels over the sensor's full range (0 … 2^bits - 1)")
    surface = dict(colour_rule=SURFACE)  # a small dimple's core is not drawn flat
    w.height_view = ImageView("Height", "µm", cmap="CET-D1", symmetric=True, pan=False, **surface)
    w.disp_view = ImageView("Displacement |u|", "px", cmap="viridis", **surface)
    w.slope_x_view = ImageView("Slope ∂h/∂x", "mrad", cmap="CET-D1", symmetric=True, **surface)
    w.slope_y_view = ImageView("Slope ∂h/∂y", "mrad", cmap="CET-D1", symmetric=True, **surface)
    mask_cmap = pg.ColorMap([0.0, 1.0], [(190, 30, 30), (215, 240, 215)])  # masked red, valid pale green
    w.valid_view = ImageView("Valid (1) / masked (0)", "", cmap=mask_cmap,
                                levels_controls=False)
    w.profile_view = ProfileView("Line profile", "height (µm)")  # short: 1280x800 gives its column ~230 px
    w.histogram = HistogramView()
    # the histogram under the raw frame: the narrow tile then has about the frame's aspect
    raw_box = QtWidgets.QWidget()
    rb = QtWidgets.QVBoxLayout(raw_box)
    rb.setContentsMargins(0, 0, 0, 0)
    rb.setSpacing(2)
    rb.addWidget(w.raw_view, 3)
    rb.addWidget(w.histogram, 1)
    grid.addWidget(raw_box, 0, 0)
    grid.addWidget(w.height_view, 0, 1, 1, 2)
    from .probes import ProbeView
    w.probe_view = ProbeView(w.height_view.plot)  # click the height map: a wave gauge
    side = QtWidgets.QSplitter(QtCore.Qt.Vertical)
    side.addWidget(w.profile_view)
    side.addWidget(w.probe_view)
    grid.addWidget(side, 0, 3)
    grid.addWidget(w.disp_view, 1, 0)
    grid.addWidget(w.slope_x_view, 1, 1)
    grid.addWidget(w.slope_y_view, 1, 2)
    grid.addWidget(w.valid_view, 1, 3)
    w.valid_view.set_levels((0.0, 1.0))
    for col in range(4):
        grid.setColumnStretch(col, 1)
    grid.setRowStretch(0, 4)
    grid.setRowStretch(1, 3)
    w.map_views = (w.height_view, w.disp_view, w.slope_x_view, w.slope_y_view, w.valid_view)
    # saturated pixels overlay on the raw view
    w.saturation_overlay = ScreenImageItem(axisOrder="row-major")
    w.saturation_overlay.setLookupTable(np.array([[0, 0, 0, 0], [255, 0, 0, 255]], np.uint8))
    w.saturation_overlay.setZValue(10)
    w.raw_view.plot.addItem(w.saturation_overlay)
    # reference region box on the raw view (pixels)
    w.region_roi = pg.RectROI([0, 0], [64, 64], pen=pg.mkPen("#00c000", width=2), movable=True)
    w.region_roi.setZValue(20)
    w.raw_view.plot.addItem(w.region_roi)
    w.region_roi.sigRegionChangeFinished.connect(w._region_dragged)
    # where the height offset is really pinned (from the reference), with its valid fraction (it labels the box
    # too: a second label for the box ran out of the view); why it is red, in words, over the raw view
    from app.gui.pinregion import PinRegionOverlay
    w.pin_overlay = PinRegionOverlay(w.raw_view.plot, note=w.raw_view.show_message)
    # profile line on the height view (mm)
    w.profile_roi = ProfileLine([[0, 0], [1, 1]])
    w.height_view.plot.addItem(w.profile_roi)
    w._profile_placed = None  # the maps' extent (mm) the profile line was last placed or checked against
    w.tabs.addTab(live, "Live")

    # Alignment tab
    align = QtWidgets.QWidget()
    ag = QtWidgets.QGridLayout(align)
    w.spectrum_view = SpectrumView()
    w.modulation_view = ImageView("Contrast (modulation)", "", cmap="viridis",
                                     axis_units="px")
    w.modulation_view.set_levels((0.0, 1.0))
    w.align_raw_view = ImageView("Camera", "counts", cmap="CET-L1", axis_units="px", averaged=True)
    w.ready_label = QtWidgets.QLabel("waiting for frames…")
    w.ready_label.setAlignment(QtCore.Qt.AlignCenter)
    w.ready_label.setWordWrap(True)
    w.ready_label.setMinimumHeight(70)
    w.metrics_label = QtWidgets.QLabel("")
    w.metrics_label.setTextFormat(QtCore.Qt.RichText)
    w.metrics_label.setAlignment(QtCore.Qt.AlignTop | QtCore.Qt.AlignLeft)
    w.metrics_label.setStyleSheet("font-size: 14px")
    w.metrics_label.setWordWrap(True)
    for lab in (w.ready_label, w.metrics_label):
        # long messages wrap instead of widening the window
        lab.setSizePolicy(QtWidgets.QSizePolicy.Ignored, QtWidgets.QSizePolicy.Preferred)
    metrics = QtWidgets.QWidget()
    ml = QtWidgets.QVBoxLayout(metrics)
    ml.addWidget(w.ready_label)
    ml.addWidget(w.metrics_label, 1)
    ag.addWidget(w.align_raw_view, 0, 0)
    ag.addWidget(w.spectrum_view, 0, 1)
    ag.addWidget(w.modulation_view, 1, 0)
    # a long table (moving water, many reasons) scrolls in its own tile instead of squeezing the camera
    # image and the spectrum above it (issue 20: they shrank to ~65 px at 1280x800)
    ag.addWidget(scroll(metrics), 1, 1)
    for view in (w.align_raw_view, w.spectrum_view):
        view.setMinimumHeight(MIN_ALIGNMENT_VIEW_PX)
    w.tabs.addTab(align, "Alignment")

    # Replay tab
    w.replay = ReplayTab()
    w.replay.open_requested.connect(w._choose_recording)
    w.replay.frame_changed.connect(w._show_replay_frame)
    w.replay.export_requested.connect(w._choose_export)
    w.tabs.addTab(w.replay, "Replay")
    w.tabs.currentChanged.connect(w._tab_changed)

    central = QtWidgets.QWidget()
    cl = QtWidgets.QVBoxLayout(central)
    cl.setContentsMargins(2, 2, 2, 2)
    bl = QtWidgets.QHBoxLayout()
    bl.addWidget(w.banner, 1)
    bl.addWidget(w.banner_close)
    cl.addLayout(bl)
    gl = QtWidgets.QHBoxLayout()
    gl.addWidget(w.geometry_banner, 1)
    gl.addWidget(w.geometry_confirm_button)
    cl.addLayout(gl)
    cl.addWidget(w.restored_bar)
    cl.addWidget(w.tabs, 1)
    w.setCentralWidget(central)

    # side panels
    w.camera_panel = CameraPanel()
    w.geometry_panel = GeometryPanel()
    w.recording_panel = RecordingPanel()
    side = QtWidgets.QToolBox()
    side.addItem(scroll(w.camera_panel), "Camera")
    side.addItem(scroll(w.geometry_panel), "Reference && geometry")
    side.addItem(scroll(w.recording_panel), "Trigger && recording")
    # one width for every section: switching sections never moves the maps
    side.setFixedWidth(CONTROLS_WIDTH_PX)
    w.side = side
    dock = QtWidgets.QDockWidget("Controls")
    dock.setObjectName("controls")
    dock.setFeatures(QtWidgets.QDockWidget.DockWidgetMovable | QtWidgets.QDockWidget.DockWidgetFloatable)
    dock.setWidget(side)
    w.addDockWidget(QtCore.Qt.LeftDockWidgetArea, dock)
    w.controls_dock = dock

    w.camera_panel.open_requested.connect(w.open_camera)
    w.camera_panel.refresh_requested.connect(w.search_cameras)
    w.camera_panel.configure_requested.connect(w.configure_camera)
    w.geometry_panel.capture_requested.connect(w.capture_reference)
    w.geometry_panel.save_reference_requested.connect(w._choose_save_reference)
    w.geometry_panel.load_reference_requested.connect(w._choose_load_reference)
    w.geometry_panel.geometry_changed.connect(w.apply_geometry_editor)
    w.geometry_panel.load_geometry_requested.connect(w._choose_load_geometry)
    w.geometry_panel.save_geometry_requested.connect(w._choose_save_geometry)
    w.recording_panel.arm_requested.connect(w.arm)
    w.recording_panel.disarm_requested.connect(w.disarm)
    w.recording_panel.trigger_requested.connect(w.trigger_now)
    w.recording_panel.browse_requested.connect(w._choose_folder)
    w.recording_panel.lengths_changed.connect(w._update_cost)
    w.recording_panel.set_from_now_requested.connect(w.threshold_from_now)
    w.recording_panel.folder.setText(os.getcwd())
    w.camera_panel.scene_requested.connect(w.set_scene)
    w.geometry_panel.confirm_geometry_requested.connect(w.confirm_geometry)
    w.geometry_confirm_button.clicked.connect(w.confirm_geometry)

    # status bar: every label elides to its room and keeps the full text as tooltip
    sb = w.statusBar()
    w.pause_box = QtWidgets.QCheckBox("Pause display")
    w.pause_box.setToolTip("Freeze the views on one frame (all maps of one frame id); acquisition, "
                              "processing and recording go on")
    w.pause_box.toggled.connect(w._pause_toggled)
    sb.addPermanentWidget(w.pause_box)
    w.message_label = ElidedLabel("")  # info() messages: where a snapshot went, what was loaded
    w.message_label.setStyleSheet("padding: 0 4px; color: #004080")
    sb.addPermanentWidget(w.message_label, 1)
    # hidden while it has nothing to say: empty, its stretch took half the room the drop counts needed
    w.message_label.setVisible(False)
    w._message_timer = QtCore.QTimer(w)
    w._message_timer.setSingleShot(True)
    w._message_timer.timeout.connect(lambda: (w.message_label.setText(""), w.message_label.setVisible(False)))
    w.status_labels = {}
    stretch = {"camera": 0, "fps": 0, "device": 0, "truth": 0, "drops": 1, "ring": 0, "latency": 0,
               "state": 0}
    for key in ("camera", "fps", "device", "truth", "drops", "ring", "latency", "state"):
        # the drops keep room for "dropped: none" (cut first, they hid the counts); a loss is red and bold
        lab = ElidedLabel("", min_text="dropped: none" if key == "drops" else "")
        lab.setStyleSheet("padding: 0 4px")
        sb.addPermanentWidget(lab, stretch[key])
        w.status_labels[key] = lab
    from .menus import build_menus
    build_menus(w)


def fit_to_screen(w, width: int, height: int) -> None:
    """Open at ``width`` x ``height`` or the screen's free area, whichever is smaller (a 1280x800 laptop)."""
    screen = QtWidgets.QApplication.primaryScreen()
    if screen is not None:
        avail = screen.availableGeometry()
        frame = 8  # window-manager border, where there is one
        width, height = min(width, avail.width() - frame), min(height, avail.height() - 2 * frame - 24)
        w.move(avail.topLeft())
    w.resize(width, height)


def scroll(widget):
    """``widget`` in a frameless scroll area that resizes it (a Controls section)."""
    area = QtWidgets.QScrollArea()
    area.setWidget(widget)
    area.setWidgetResizable(True)
    area.setFrameShape(QtWidgets.QFrame.NoFrame)
    return area
