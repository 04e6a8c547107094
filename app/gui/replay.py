"""Replay tab: open a recording, scrub its frames, see raw and processed maps, export heights."""

from __future__ import annotations

import os
from typing import Optional

import numpy as np
from pyqtgraph.Qt import QtCore, QtWidgets

from .views import ImageView

__all__ = ["ReplayTab", "Recording"]


class Recording:
    """Read access to an HDF5 recording written by :mod:`app.capture.recorder`.

    Opened read-only; frames are read one at a time (recordings can exceed RAM).
    The reference image and geometry TOML stored in the file are used when present.
    """

    def __init__(self, path: str):
        import h5py

        self.path = os.fspath(path)
        try:
            self._file = h5py.File(self.path, "r")
        except OSError as exc:
            raise OSError(f"cannot open recording {self.path!r}: {exc}. Is it an HDF5 file "
                          "written by tirdeflect (record / the Record panel)?") from None
        if "frames" not in self._file:
            self._file.close()
            raise OSError(f"{self.path!r} has no /frames dataset: not a tirdeflect recording")
        self.frames = self._file["frames"]
        n_attr = self._file.attrs.get("frames_written", self._file["frames"].attrs.get("frames_written"))
        self.n_frames = int(min(self.frames.shape[0], n_attr)) if n_attr is not None else self.frames.shape[0]
        self.reference = self._read_reference()
        self.geometry_toml = self._read_text("geometry_toml", "geometry")
        self.table = self._file["frame_table"][: self.n_frames] if "frame_table" in self._file else None

    def _read_reference(self) -> Optional[np.ndarray]:
        for name in ("reference", "reference_image"):
            if name in self._file:
                return np.asarray(self._file[name][()])
        return None

    def _read_text(self, *names) -> Optional[str]:
        for name in names:
            for holder in (self._file.attrs, self._file):
                if name in holder:
                    value = holder[name]
                    value = value[()] if hasattr(value, "shape") and not isinstance(value, (str, bytes)) else value
                    if isinstance(value, bytes):
                        value = value.decode()
                    if isinstance(value, str):
                        return value
        return None

    def frame(self, index: int) -> np.ndarray:
        if not 0 <= index < self.n_frames:
            raise IndexError(f"frame index {index} out of range 0..{self.n_frames - 1}")
        return np.asarray(self.frames[index])

    def trigger_index(self, index: int) -> Optional[int]:
        """Trigger-relative index of frame ``index`` (negative before the trigger), if recorded."""
        if self.table is None:
            return None
        names = self.table.dtype.names or ()
        for name in ("trigger_index", "trigger_relative_index", "trigger_relative"):
            if name in names:
                return int(self.table[name][index])
        return None

    def close(self) -> None:
        self._file.close()


class ReplayTab(QtWidgets.QWidget):
    """Scrub a recording: raw frame and height map side by side, export all heights.

    Signals
    -------
    open_requested(), export_requested()
    frame_changed(int)
    """

    open_requested = QtCore.Signal()
    export_requested = QtCore.Signal()
    frame_changed = QtCore.Signal(int)

    def __init__(self, parent=None):
        super().__init__(parent)
        outer = QtWidgets.QVBoxLayout(self)
        bar = QtWidgets.QHBoxLayout()
        self.open_button = QtWidgets.QPushButton("Open recording…")
        self.file_label = QtWidgets.QLabel("no recording open")
        self.export_button = QtWidgets.QPushButton("Export heights…")
        self.export_button.setEnabled(False)
        self.progress = QtWidgets.QProgressBar()
        self.progress.setRange(0, 100)
        self.progress.setMaximumWidth(220)
        bar.addWidget(self.open_button)
        bar.addWidget(self.file_label, 1)
        bar.addWidget(self.export_button)
        bar.addWidget(self.progress)
        outer.addLayout(bar)
        views = QtWidgets.QHBoxLayout()
        self.raw = ImageView("Recorded frame", "counts", cmap="CET-L1", axis_units="px")
        self.height = ImageView("Height", "height (µm)", cmap="CET-D1", symmetric=True)
        views.addWidget(self.raw)
        views.addWidget(self.height)
        outer.addLayout(views, 1)
        scrub = QtWidgets.QHBoxLayout()
        self.slider = QtWidgets.QSlider(QtCore.Qt.Horizontal)
        self.slider.setEnabled(False)
        self.index_label = QtWidgets.QLabel("–")
        self.index_label.setMinimumWidth(260)
        scrub.addWidget(self.slider, 1)
        scrub.addWidget(self.index_label)
        outer.addLayout(scrub)
        self.message = QtWidgets.QLabel("")
        self.message.setWordWrap(True)
        outer.addWidget(self.message)
        self.open_button.clicked.connect(self.open_requested.emit)
        self.export_button.clicked.connect(self.export_requested.emit)
        self.slider.valueChanged.connect(self.frame_changed.emit)

    def set_recording(self, rec: Recording) -> None:
        self.file_label.setText(f"{os.path.basename(rec.path)} — {rec.n_frames} frames"
                                + ("" if rec.reference is not None else " (no reference stored)"))
        self.slider.blockSignals(True)
        self.slider.setRange(0, max(rec.n_frames - 1, 0))
        self.slider.setValue(0)
        self.slider.blockSignals(False)
        self.slider.setEnabled(rec.n_frames > 0)
        self.export_button.setEnabled(rec.n_frames > 0)
