"""Side panels of the main window: camera settings, reference and geometry, trigger and recording.

Panels only hold widgets and emit what the user asked for; the main window
does the work (in background threads where it can block).
"""

from __future__ import annotations

import html
from typing import Optional

from pyqtgraph.Qt import QtCore, QtGui, QtWidgets

__all__ = ["CameraPanel", "GeometryPanel", "RecordingPanel", "ExactSpinBox", "human_bytes"]


def human_bytes(n: float) -> str:
    """``1536 -> '1.5 KiB'``."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024.0
    return f"{n:.1f} TiB"


class ExactSpinBox(QtWidgets.QDoubleSpinBox):
    """A QDoubleSpinBox that keeps the full value it is given (0.078125 stays 0.078125).

    Qt rounds a QDoubleSpinBox's value to its ``decimals``; a geometry loaded from
    TOML and saved again would then lose digits. This one holds 15 decimals and
    shows the value with up to ``shown_digits`` significant digits, never padding zeros.
    """

    def __init__(self, shown_digits: int = 10):
        super().__init__()
        self._digits = int(shown_digits)
        super().setDecimals(15)

    def setDecimals(self, _decimals: int) -> None:  # noqa: N802 - Qt name; precision is fixed at 15
        pass

    def textFromValue(self, value: float) -> str:  # noqa: N802 - Qt name
        return f"{value:.{self._digits}g}"

    def valueFromText(self, text: str) -> float:  # noqa: N802 - Qt name
        text = text.strip()
        if self.suffix() and text.endswith(self.suffix().strip()):
            text = text[: -len(self.suffix().strip())]
        try:
            return float(text.strip().replace(",", "."))
        except ValueError:
            return self.value()

    def validate(self, text: str, pos: int):
        if self.specialValueText() and text == self.specialValueText():
            return QtGui.QValidator.Acceptable, text, pos
        body = text.strip()
        if self.suffix():
            body = body.replace(self.suffix().strip(), "")
        body = body.strip().replace(",", ".")
        if body in ("", "-", "+", ".", "-.") or body.lower().endswith(("e", "e-", "e+")):
            return QtGui.QValidator.Intermediate, text, pos
        try:
            float(body)
        except ValueError:
            return QtGui.QValidator.Invalid, text, pos
        return QtGui.QValidator.Acceptable, text, pos


def _spin(lo, hi, value, *, decimals=None, step=None, suffix="", special=None, exact=False):
    if decimals is None:
        w = QtWidgets.QSpinBox()
    else:
        w = ExactSpinBox() if exact else QtWidgets.QDoubleSpinBox()
        w.setDecimals(decimals)
    w.setRange(lo, hi)
    if step is not None:
        w.setSingleStep(step)
    w.setValue(value)
    if suffix:
        w.setSuffix(suffix)
    if special:
        w.setSpecialValueText(special)
    w.setKeyboardTracking(False)
    return w


class CameraPanel(QtWidgets.QWidget):
    """Camera choice and settings; shows what the camera accepted.

    Signals
    -------
    open_requested(str)
        Camera id chosen by the user.
    configure_requested(dict)
        Settings to write (names of :class:`drivers.base.CameraSettings`).
    refresh_requested()
        Search cameras again.
    """

    open_requested = QtCore.Signal(str)
    configure_requested = QtCore.Signal(dict)
    refresh_requested = QtCore.Signal()
    scene_requested = QtCore.Signal(str)  # synthetic tank scene chosen (still, waves, drop, impact)

    def __init__(self, parent=None):
        super().__init__(parent)
        form = QtWidgets.QFormLayout(self)
        form.setRowWrapPolicy(QtWidgets.QFormLayout.WrapLongRows)
        row = QtWidgets.QVBoxLayout()
        buttons = QtWidgets.QHBoxLayout()
        self.camera_box = QtWidgets.QComboBox()
        self.camera_box.setMinimumContentsLength(8)
        self.camera_box.setSizeAdjustPolicy(QtWidgets.QComboBox.AdjustToMinimumContentsLengthWithIcon)
        self.refresh_button = QtWidgets.QPushButton("Search")
        self.open_button = QtWidgets.QPushButton("Open")
        row.addWidget(self.camera_box)
        buttons.addWidget(self.refresh_button)
        buttons.addWidget(self.open_button)
        row.addLayout(buttons)
        form.addRow("Camera", row)
        self.found_label = QtWidgets.QLabel("")
        self.found_label.setWordWrap(True)
        form.addRow(self.found_label)
        # the synthetic camera is a simulated tank: still water until a scene is chosen
        from app.capture.scene import SCENES

        self.scene_box = QtWidgets.QComboBox()
        for name, text in zip(SCENES, ("still water", "travelling waves", "drop (ring waves)",
                                       "impact (approaching disc)")):
            self.scene_box.addItem(text, name)
        self.scene_box.setToolTip("What the synthetic camera's simulated tank shows; its true heights are "
                                  "compared with the measured ones in the status bar")
        self.scene_label = QtWidgets.QLabel("")
        self.scene_label.setWordWrap(True)
        form.addRow("Tank scene", self.scene_box)
        form.addRow(self.scene_label)
        self.scene_box.activated.connect(lambda i: self.scene_requested.emit(self.scene_box.itemData(i)))
        self.set_synthetic(False)
        self.exposure = _spin(1, 10_000_000, 1000, decimals=1, suffix=" µs")
        self.gain = _spin(-20, 48, 0, decimals=2, suffix=" dB")
        self.rate = _spin(0.1, 100_000, 100, decimals=2, suffix=" Hz")
        self.offset_x = _spin(0, 100_000, 0)
        self.offset_y = _spin(0, 100_000, 0)
        self.width = _spin(1, 100_000, 512)
        self.height = _spin(1, 100_000, 512)
        self.pixel_format = QtWidgets.QComboBox()
        self.pixel_format.addItems(["Mono8", "Mono10", "Mono12", "Mono16"])
        self.trigger_mode = QtWidgets.QComboBox()
        self.trigger_mode.addItems(["Off", "On"])
        self.trigger_source = QtWidgets.QComboBox()
        self.trigger_source.addItems(["Software", "Line0", "Line1", "Line2"])
        self.trigger_activation = QtWidgets.QComboBox()
        self.trigger_activation.addItems(["RisingEdge", "FallingEdge"])
        form.addRow("Exposure", self.exposure)
        form.addRow("Gain", self.gain)
        form.addRow("Frame rate", self.rate)
        roi = QtWidgets.QGridLayout()
        roi.addWidget(QtWidgets.QLabel("x"), 0, 0)
        roi.addWidget(self.offset_x, 0, 1)
        roi.addWidget(QtWidgets.QLabel("y"), 0, 2)
        roi.addWidget(self.offset_y, 0, 3)
        roi.addWidget(QtWidgets.QLabel("w"), 1, 0)
        roi.addWidget(self.width, 1, 1)
        roi.addWidget(QtWidgets.QLabel("h"), 1, 2)
        roi.addWidget(self.height, 1, 3)
        for w in (self.offset_x, self.offset_y, self.width, self.height):
            w.setMinimumWidth(60)
            w.setMaximumWidth(90)
        form.addRow("ROI (px)", roi)
        form.addRow("Pixel format", self.pixel_format)
        form.addRow("Trigger", self.trigger_mode)
        form.addRow("Trigger source", self.trigger_source)
        form.addRow("Activation", self.trigger_activation)
        self.apply_button = QtWidgets.QPushButton("Apply settings")
        form.addRow(self.apply_button)
        self.accepted_label = QtWidgets.QLabel("accepted: –")
        self.accepted_label.setWordWrap(True)
        self.accepted_label.setTextInteractionFlags(QtCore.Qt.TextSelectableByMouse)
        form.addRow(self.accepted_label)
        self.open_button.clicked.connect(lambda: self.open_requested.emit(self.camera_id()))
        self.refresh_button.clicked.connect(self.refresh_requested.emit)
        self.apply_button.clicked.connect(lambda: self.configure_requested.emit(self.requested()))

    def set_synthetic(self, synthetic: bool) -> None:
        """Enable the tank scene chooser only for the synthetic camera."""
        self.scene_box.setEnabled(synthetic)
        if not synthetic:
            self.scene_label.setText("(scenes: synthetic camera only)")

    def show_scene(self, name: str, text: str = "") -> None:
        """Select ``name`` in the chooser (no signal) and show ``text`` (progress, state) below it."""
        i = self.scene_box.findData(name)
        if i >= 0 and i != self.scene_box.currentIndex():
            self.scene_box.blockSignals(True)
            self.scene_box.setCurrentIndex(i)
            self.scene_box.blockSignals(False)
        self.scene_label.setText(text)

    def camera_id(self) -> str:
        data = self.camera_box.currentData()
        return data if data else self.camera_box.currentText()

    def set_cameras(self, infos, note: str = "") -> None:
        """Fill the camera list from :func:`drivers.list_cameras` results."""
        self.camera_box.blockSignals(True)
        self.camera_box.clear()
        for info in infos:
            text = info.camera_id
            extra = " ".join(s for s in (getattr(info, "vendor", ""), getattr(info, "model", "")) if s)
            self.camera_box.addItem(f"{text}  {extra}".strip(), info.camera_id)
        self.camera_box.blockSignals(False)
        self.found_label.setText(note)

    def select_camera(self, camera_id: str) -> None:
        idx = self.camera_box.findData(camera_id)
        if idx < 0:
            self.camera_box.addItem(camera_id, camera_id)
            idx = self.camera_box.count() - 1
        self.camera_box.setCurrentIndex(idx)

    def requested(self) -> dict:
        values = {
            "exposure_us": self.exposure.value(),
            "gain_db": self.gain.value(),
            "frame_rate_hz": self.rate.value(),
            "offset_x": self.offset_x.value(),
            "offset_y": self.offset_y.value(),
            "width": self.width.value(),
            "height": self.height.value(),
            "pixel_format": self.pixel_format.currentText(),
            "trigger_mode": self.trigger_mode.currentText(),
        }
        if values["trigger_mode"] == "On":
            values["trigger_source"] = self.trigger_source.currentText()
            values["trigger_activation"] = self.trigger_activation.currentText()
        return values

    def show_settings(self, s) -> None:
        """Show the accepted :class:`CameraSettings` and load them into the editors."""
        for widget, value in ((self.exposure, s.exposure_us), (self.gain, s.gain_db),
                              (self.rate, s.frame_rate_hz), (self.offset_x, s.offset_x),
                              (self.offset_y, s.offset_y), (self.width, s.width), (self.height, s.height)):
            widget.blockSignals(True)
            widget.setEnabled(value is not None)
            if value is not None:
                widget.setValue(value)
            widget.blockSignals(False)
        for box, value in ((self.pixel_format, s.pixel_format), (self.trigger_mode, s.trigger_mode),
                           (self.trigger_source, s.trigger_source),
                           (self.trigger_activation, s.trigger_activation)):
            if value is None:
                continue
            if box.findText(value) < 0:
                box.addItem(value)
            box.setCurrentText(value)

        def fmt(v, unit=""):
            return "n/a" if v is None else (f"{v:g}{unit}" if isinstance(v, float) else f"{v}{unit}")

        self.accepted_label.setText(
            f"accepted: {s.width}×{s.height} at ({s.offset_x}, {s.offset_y}), {s.pixel_format} "
            f"({s.bit_depth} bit), exposure {fmt(s.exposure_us, ' µs')}, gain {fmt(s.gain_db, ' dB')}, "
            f"{fmt(s.frame_rate_hz, ' Hz')}, trigger {s.trigger_mode}"
            + (f" ({s.trigger_source}, {s.trigger_activation})" if s.trigger_mode == "On" else ""))


class GeometryPanel(QtWidgets.QWidget):
    """Reference capture/save/load and the geometry editor (TOML load/save).

    Signals
    -------
    capture_requested(int)   average this many frames into a new reference
    save_reference_requested(), load_reference_requested()
    geometry_changed()       an editor value changed (the window rebuilds the Geometry)
    load_geometry_requested(), save_geometry_requested()
    confirm_geometry_requested()  the editor's geometry is this camera's (remembered with it)
    """

    capture_requested = QtCore.Signal(int)
    save_reference_requested = QtCore.Signal()
    load_reference_requested = QtCore.Signal()
    geometry_changed = QtCore.Signal()
    load_geometry_requested = QtCore.Signal()
    save_geometry_requested = QtCore.Signal()
    confirm_geometry_requested = QtCore.Signal()

    def __init__(self, parent=None):
        super().__init__(parent)
        outer = QtWidgets.QVBoxLayout(self)
        ref = QtWidgets.QGroupBox("Reference (flat, still water)")
        rf = QtWidgets.QFormLayout(ref)
        self.n_average = _spin(1, 1000, 10)
        self.capture_button = QtWidgets.QPushButton("Capture reference")
        row = QtWidgets.QHBoxLayout()
        row.addWidget(QtWidgets.QLabel("average"))
        row.addWidget(self.n_average)
        row.addWidget(QtWidgets.QLabel("frames"), 1)
        rf.addRow(row)
        rf.addRow(self.capture_button)
        row2 = QtWidgets.QHBoxLayout()
        self.save_ref_button = QtWidgets.QPushButton("Save…")
        self.load_ref_button = QtWidgets.QPushButton("Load…")
        row2.addWidget(self.save_ref_button)
        row2.addWidget(self.load_ref_button)
        rf.addRow(row2)
        self.reference_label = QtWidgets.QLabel("no reference: heights need one")
        self.reference_label.setWordWrap(True)
        rf.addRow(self.reference_label)
        outer.addWidget(ref)

        geo = QtWidgets.QGroupBox("Geometry")
        gf = QtWidgets.QFormLayout(geo)
        gf.setRowWrapPolicy(QtWidgets.QFormLayout.WrapLongRows)
        self.setup = QtWidgets.QComboBox()
        self.setup.addItems(["tir", "fsss"])
        self.pattern = QtWidgets.QComboBox()  # Geometry.pattern: what the reference shows
        self.pattern.addItem("checkerboard", "checkerboard")
        self.pattern.addItem("random dots", "dots")
        self.pattern.setToolTip("checkerboard: Fourier demodulation; random dots: PIV (dot size, density "
                                "and focus on the Alignment tab)")
        # exact spin boxes: a geometry loaded from TOML is saved back with every digit it had
        self.theta = _spin(0, 89.9, 55, decimals=2, step=0.1, suffix=" °", exact=True)
        self.depth = _spin(0.001, 100_000, 300, decimals=3, suffix=" mm", exact=True)
        self.pixel = _spin(0.0001, 100, 0.1, decimals=5, step=0.001, suffix=" mm/px", exact=True)
        self.board_period = _spin(0, 10_000, 0, decimals=4, step=0.1, suffix=" mm", special="not checked", exact=True)
        self.board_period.setToolTip("pattern_period_mm: full period of the printed checkerboard along its x (one "
                                     "dark plus one bright square), as `tirdeflect pattern` printed it: the reference "
                                     "is then checked against the scale (a wrong scale multiplies every height by "
                                     "its square)")
        self.pixel.setToolTip("pixel_mm: surface mm per image column at the image centre")
        self.rows_toward_camera = QtWidgets.QCheckBox("rows run towards camera")
        self.rows_toward_camera.setToolTip("image rows run towards the camera (checked) or away from it")
        self.camera_distance = _spin(0, 1e6, 0, decimals=1, suffix=" mm", special="telecentric", exact=True)
        self.region = QtWidgets.QLineEdit()
        self.region.setPlaceholderText("row0, row1, col0, col1 (px) — or drag the box on the raw image")
        self.fsss_layers = QtWidgets.QLineEdit()
        self.fsss_layers.setPlaceholderText("thickness_mm:n, ... from pattern up to the surface")
        self.fsss_camera_distance = _spin(0, 1e6, 0, decimals=1, suffix=" mm", special="telecentric",
                                          exact=True)
        gf.addRow("Setup", self.setup)
        gf.addRow("Pattern", self.pattern)
        gf.addRow("θ (incidence)", self.theta)
        gf.addRow("H (pattern depth)", self.depth)
        gf.addRow("Scale", self.pixel)
        gf.addRow("Board period", self.board_period)
        gf.addRow("Orientation", self.rows_toward_camera)
        gf.addRow("Camera distance", self.camera_distance)
        gf.addRow("Reference region", self.region)
        gf.addRow("FS-SS layers", self.fsss_layers)
        gf.addRow("FS-SS camera dist.", self.fsss_camera_distance)
        row3 = QtWidgets.QHBoxLayout()
        self.load_geo_button = QtWidgets.QPushButton("Load TOML…")
        self.save_geo_button = QtWidgets.QPushButton("Save TOML…")
        self.confirm_geo_button = QtWidgets.QPushButton("Confirm for this camera")
        self.confirm_geo_button.setToolTip("These values are this camera's set-up (remembered with the camera); "
                                           "until then heights are not to scale")
        row3.addWidget(self.load_geo_button)
        row3.addWidget(self.save_geo_button)
        gf.addRow(row3)
        gf.addRow(self.confirm_geo_button)
        self.geometry_label = QtWidgets.QLabel("")
        self.geometry_label.setWordWrap(True)
        gf.addRow(self.geometry_label)
        outer.addWidget(geo)
        outer.addStretch(1)

        self.capture_button.clicked.connect(lambda: self.capture_requested.emit(self.n_average.value()))
        self.save_ref_button.clicked.connect(self.save_reference_requested.emit)
        self.load_ref_button.clicked.connect(self.load_reference_requested.emit)
        self.load_geo_button.clicked.connect(self.load_geometry_requested.emit)
        self.save_geo_button.clicked.connect(self.save_geometry_requested.emit)
        self.confirm_geo_button.clicked.connect(self.confirm_geometry_requested.emit)
        for w in (self.theta, self.depth, self.pixel, self.board_period, self.camera_distance,
                  self.fsss_camera_distance):
            w.valueChanged.connect(lambda *_: self.geometry_changed.emit())
        self.setup.currentTextChanged.connect(lambda *_: self._setup_changed())
        self.pattern.currentIndexChanged.connect(lambda *_: self.geometry_changed.emit())
        self.rows_toward_camera.toggled.connect(lambda *_: self.geometry_changed.emit())
        self.region.editingFinished.connect(self.geometry_changed.emit)
        self.fsss_layers.editingFinished.connect(self.geometry_changed.emit)
        self._setup_changed(emit=False)

    def _setup_changed(self, emit=True):
        fsss = self.setup.currentText() == "fsss"
        self.fsss_layers.setEnabled(fsss)
        self.fsss_camera_distance.setEnabled(fsss)
        self.theta.setEnabled(not fsss)
        if emit:
            self.geometry_changed.emit()

    # -- geometry <-> widgets ----------------------------------------------
    def region_tuple(self) -> Optional[tuple]:
        text = self.region.text().strip()
        if not text:
            return None
        parts = [p for p in text.replace(";", ",").split(",") if p.strip()]
        if len(parts) != 4:
            raise ValueError(f"reference region needs 4 integers 'row0, row1, col0, col1'; got {text!r}")
        return tuple(int(float(p)) for p in parts)

    def set_region(self, region) -> None:
        self.region.blockSignals(True)
        self.region.setText("" if region is None else ", ".join(str(int(v)) for v in region))
        self.region.blockSignals(False)

    def values(self) -> dict:
        """The editor's content as a dict for :meth:`processing.Geometry.from_dict`."""
        d = {
            "setup": self.setup.currentText(),
            "pattern": self.pattern.currentData(),
            "theta_deg": float(self.theta.value()),
            "depth_mm": float(self.depth.value()),
            "pixel_mm": float(self.pixel.value()),
            "rows_toward_camera": bool(self.rows_toward_camera.isChecked()),
        }
        period = self.board_period.value()
        d["pattern_period_mm"] = None if period <= 0 else float(period)
        cd = self.camera_distance.value()
        d["camera_distance_mm"] = None if cd <= 0 else float(cd)
        region = self.region_tuple()
        d["reference_region"] = None if region is None else list(region)
        if d["setup"] == "fsss":
            layers = []
            text = self.fsss_layers.text().strip()
            for item in filter(None, (p.strip() for p in text.split(","))):
                try:
                    t, n = item.split(":")
                    layers.append([float(t), float(n)])
                except ValueError:
                    raise ValueError(
                        f"FS-SS layer {item!r} is not 'thickness_mm:refractive_index' (e.g. 12:1.489)") from None
            d["fsss_layers"] = layers
            fd = self.fsss_camera_distance.value()
            d["fsss_camera_distance_mm"] = None if fd <= 0 else float(fd)
        return d

    def set_values(self, d: dict) -> None:
        widgets = [self.setup, self.pattern, self.theta, self.depth, self.pixel, self.board_period,
                   self.rows_toward_camera, self.camera_distance, self.fsss_camera_distance, self.fsss_layers]
        for w in widgets:
            w.blockSignals(True)
        try:
            self.setup.setCurrentText(str(d.get("setup", "tir")))
            self.pattern.setCurrentIndex(max(0, self.pattern.findData(str(d.get("pattern", "checkerboard")))))
            if d.get("theta_deg") is not None:
                self.theta.setValue(float(d["theta_deg"]))
            self.depth.setValue(float(d.get("depth_mm", self.depth.value())))
            self.pixel.setValue(float(d.get("pixel_mm", self.pixel.value())))
            self.board_period.setValue(float(d.get("pattern_period_mm") or 0))
            self.rows_toward_camera.setChecked(bool(d.get("rows_toward_camera", False)))
            self.camera_distance.setValue(float(d.get("camera_distance_mm") or 0))
            self.fsss_camera_distance.setValue(float(d.get("fsss_camera_distance_mm") or 0))
            layers = d.get("fsss_layers") or ()
            self.fsss_layers.setText(", ".join(f"{t:.15g}:{n:.15g}" for t, n in layers))
            self.set_region(d.get("reference_region"))
        finally:
            for w in widgets:
                w.blockSignals(False)
        self._setup_changed(emit=False)


class RecordingPanel(QtWidgets.QWidget):
    """Pre/post-trigger capture: lengths with RAM cost, arm, trigger, auto-trigger, state, progress.

    Signals
    -------
    arm_requested(), disarm_requested(), trigger_requested(), browse_requested(), set_from_now_requested()
    """

    arm_requested = QtCore.Signal()
    disarm_requested = QtCore.Signal()
    trigger_requested = QtCore.Signal()
    browse_requested = QtCore.Signal()
    lengths_changed = QtCore.Signal()
    set_from_now_requested = QtCore.Signal()

    def __init__(self, parent=None):
        super().__init__(parent)
        form = QtWidgets.QFormLayout(self)
        form.setRowWrapPolicy(QtWidgets.QFormLayout.WrapLongRows)
        self.pre = _spin(0, 10_000_000, 50, suffix=" frames")
        self.post = _spin(1, 10_000_000, 100, suffix=" frames")
        form.addRow("Pre-trigger", self.pre)
        form.addRow("Post-trigger", self.post)
        self.cost_label = QtWidgets.QLabel("")
        form.addRow("Cost", self.cost_label)
        row = QtWidgets.QHBoxLayout()
        self.folder = QtWidgets.QLineEdit()
        self.browse_button = QtWidgets.QPushButton("…")
        row.addWidget(self.folder, 1)
        row.addWidget(self.browse_button)
        form.addRow("Folder", row)
        # the threshold in mrad of RMS slope, what it is compared with now, and a proposal from it
        self.auto = QtWidgets.QCheckBox("auto-trigger at RMS slope >")
        self.threshold = _spin(0.001, 1000, 1.0, decimals=3, step=0.05, suffix=" mrad")
        self.threshold.setToolTip("fires when sqrt(mean(slope_x² + slope_y²)) of the live slope maps exceeds "
                                  "this (mrad); the file stores the value and its unit")
        self.set_from_now_button = QtWidgets.QPushButton("Set from now")
        self.set_from_now_button.setToolTip("threshold = 5 × the median RMS slope of the last live maps")
        form.addRow(self.auto)
        row2 = QtWidgets.QHBoxLayout()
        row2.addWidget(self.threshold, 1)
        row2.addWidget(self.set_from_now_button)
        form.addRow(row2)
        self.rms_label = QtWidgets.QLabel("now: no slope maps yet")
        self.rms_label.setWordWrap(True)  # a stale mark makes it long: it wraps, the dock never scrolls sideways
        self.rms_label.setSizePolicy(QtWidgets.QSizePolicy.Ignored, QtWidgets.QSizePolicy.Preferred)
        self.rms_label.setToolTip("the RMS slope of the maps on screen: the quantity the threshold is compared with")
        form.addRow(self.rms_label)
        row3 = QtWidgets.QHBoxLayout()
        self.arm_button = QtWidgets.QPushButton("Arm")
        self.trigger_button = QtWidgets.QPushButton("Trigger now")
        self.disarm_button = QtWidgets.QPushButton("Disarm")
        for b in (self.arm_button, self.trigger_button, self.disarm_button):
            row3.addWidget(b)
        form.addRow(row3)
        self.state_label = QtWidgets.QLabel("idle")
        self.state_label.setStyleSheet("font-weight: bold; font-size: 14px")
        form.addRow("State", self.state_label)
        self.progress = QtWidgets.QProgressBar()
        self.progress.setRange(0, 100)
        self.progress.setValue(0)
        form.addRow(self.progress)
        self.result_label = QtWidgets.QLabel("")
        self.result_label.setWordWrap(True)
        self.result_label.setTextInteractionFlags(QtCore.Qt.TextSelectableByMouse)
        form.addRow(self.result_label)
        self.arm_button.clicked.connect(self.arm_requested.emit)
        self.disarm_button.clicked.connect(self.disarm_requested.emit)
        self.trigger_button.clicked.connect(self.trigger_requested.emit)
        self.browse_button.clicked.connect(self.browse_requested.emit)
        self.set_from_now_button.clicked.connect(self.set_from_now_requested.emit)
        self.pre.valueChanged.connect(lambda *_: self.lengths_changed.emit())
        self.post.valueChanged.connect(lambda *_: self.lengths_changed.emit())
        self.set_state("idle")

    def show_summary(self, path: str, rows) -> None:
        """A finished recording's summary (``app.capture.recorder.summary_rows``) as a two-column table whose
        values wrap inside their cell (the terminal's column layout wrapped line by line in the dock)."""
        cells = "".join(f"<tr><td style='padding-right:6px; white-space:nowrap'>{html.escape(name)}</td>"
                        f"<td>{html.escape(value)}</td></tr>" for name, value in rows)
        self.result_label.setText(f"<b>recording</b> {html.escape(str(path))}"
                                  f"<table cellspacing='0' cellpadding='1'>{cells}</table>")

    def set_cost(self, frame_bytes: int, rate_hz: Optional[float], ring_frames: Optional[int] = None) -> None:
        """Show what the capture costs: pre-trigger frames held in RAM (the ring), the file on disk."""
        pre, post = self.pre.value(), self.post.value()
        text = f"pre-trigger {human_bytes(pre * frame_bytes)} in RAM"
        if ring_frames:
            text += f" (ring holds {ring_frames} frames, {human_bytes(ring_frames * frame_bytes)})"
        text += f"; file {human_bytes((pre + post) * frame_bytes)}"
        if rate_hz:
            text += f"; {pre / rate_hz:.3g} s before, {post / rate_hz:.3g} s after"
        self.cost_label.setText(text)
        self.cost_label.setWordWrap(True)
        too_many = ring_frames is not None and pre + 1 > ring_frames
        self.cost_label.setStyleSheet("color: #c00000" if too_many else "")

    def set_state(self, state: str) -> None:
        colours = {"idle": "#444", "armed": "#b06000", "capturing": "#c00000", "saving": "#0050b0",
                   "done": "#007000", "error": "#c00000"}
        self.state_label.setText(state)
        self.state_label.setStyleSheet(
            f"font-weight: bold; font-size: 14px; color: {colours.get(state, '#444')}")
        armed = state in ("armed", "capturing")
        self.arm_button.setEnabled(state in ("idle", "done", "error"))
        self.trigger_button.setEnabled(state == "armed")
        self.disarm_button.setEnabled(armed)
