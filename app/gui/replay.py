"""Replay tab: open a recording, scrub its frames, see raw and processed maps, export heights."""

from __future__ import annotations

import math
import os
from typing import Optional

import numpy as np
from pyqtgraph.Qt import QtCore, QtWidgets

from .model.colour_range import SURFACE
from .model.replay import ReplayMessage, lost_before, recording_notes, table_times_s, without_untriggered_index
from .views import ImageView
from .widgets import ElidedLabel, MessageArea

__all__ = ["ReplayTab", "Recording", "RECORDING_FILTER"]

#: File-dialog filter of everything :class:`Recording` opens (docs/inputs.md).
RECORDING_FILTER = ("Recordings and camera files (*.h5 *.hdf5 *.cih *.cihx *.mraw *.cine *.avi *.mkv "
                    "*.mp4 *.mov *.tif *.tiff);;HDF5 (*.h5 *.hdf5);;Photron (*.cih *.cihx *.mraw);;"
                    "Phantom (*.cine);;Video (*.avi *.mkv *.mp4 *.mov);;TIFF stacks (*.tif *.tiff)")


class Recording:
    """Read access to a recording: the app's HDF5 (:mod:`app.capture.recorder`), or a
    Photron MRAW, Phantom CINE, video or TIFF stack (through :mod:`app.files.imageio`).

    Opened read-only; frames are read one at a time (recordings can exceed RAM).
    The reference image and geometry TOML stored in an HDF5 recording are used
    when present; camera files and videos store neither.
    """

    def __init__(self, path: str):
        import h5py

        self.path = os.fspath(path)
        self._source = None
        self.time_origin = None
        self.notes: list = []  # what the Replay tab says beside the name: frames lost, ended early
        self.lost_before = None  # camera frames lost before each frame (HDF5 recordings' frame-id gaps)
        self._times_s = None
        # (reference, geometry) the Replay tab measures this file with, chosen when it is opened (its export too)
        self.inputs = (None, None)
        self.frame_time_s = math.nan  # time of the frame frame() returned last, where the file says
        if not self._is_hdf5():
            self._open_other()
            return
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
        table = self._file["frame_table"][: self.n_frames] if "frame_table" in self._file else None
        self.table = without_untriggered_index(dict(self._file.attrs), table)
        self._times_s, self.time_origin = table_times_s(self.table)
        self.lost_before = lost_before(self.table)
        self.notes = recording_notes(dict(self._file.attrs), self.table, self.n_frames)

    def _is_hdf5(self) -> bool:
        try:
            with open(self.path, "rb") as fh:
                return fh.read(8) == b"\x89HDF\r\n\x1a\n"
        except OSError:
            return True  # let h5py say what is wrong

    def _open_other(self) -> None:
        """Camera files, videos, TIFF stacks: one frame decoded at a time."""
        from app.files import formats, imageio

        from pathlib import Path

        info = imageio.image_info(self.path)  # ImageReadError: one line naming the file and the fix
        self.info = info
        self.n_frames = int(info.n_frames)
        self.reference = None
        self.geometry_toml = None
        self.table = None
        self._file = None
        if formats.kind_of(Path(self.path)) is not None:
            self._source = formats.open_source(Path(self.path))
            self.time_origin = self._source.time_origin
        self._iter = None
        self._next = 0

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
        if self._file is not None:
            self.frame_time_s = math.nan if self._times_s is None else float(self._times_s[index])
            return np.asarray(self.frames[index])
        if self._source is None:  # TIFF stack
            from app.files import imageio

            return imageio.read_image(self.path, index=index)
        # camera file or video: continue the open decoder when stepping forward
        # (a video decodes from its start otherwise)
        sequential = self._source.kind == "video"  # MRAW and CINE seek: start at the frame
        if self._iter is None or index < self._next or not sequential:
            if self._iter is not None:
                self._iter.close()
            self._iter = self._source.frames(range(index, self.n_frames))
            self._next = index
        for i, image, time_s in self._iter:
            self._next = i + 1
            if i == index:
                self.frame_time_s = float(time_s)
                return image
        self._iter = None
        raise IndexError(f"frame {index} of {self.path!r} could not be decoded (the file ends early)")

    def trigger_index(self, index: int) -> Optional[int]:
        """Trigger-relative index of frame ``index`` (negative before the trigger), if recorded."""
        if self._file is None:
            trig = getattr(getattr(self, "info", None), "trigger_index", None)
            return None if trig is None else int(index) - int(trig)
        if self.table is None:
            return None
        names = self.table.dtype.names or ()
        for name in ("trigger_index", "trigger_relative_index", "trigger_relative"):
            if name in names:
                return int(self.table[name][index])
        return None

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
        if self._source is not None:
            if self._iter is not None:
                self._iter.close()  # stop a video decoder thread before its file closes
                self._iter = None
            self._source.close()


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
        self.file_label = ElidedLabel("no recording open")  # a long file name never widens the window
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
        self.raw = ImageView("Recorded frame", "counts", cmap="CET-L1", axis_units="px", averaged=True)
        self.height = ImageView("Height", "µm", cmap="CET-D1", symmetric=True, colour_rule=SURFACE)
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
        # what the file says of itself (frames lost, stopped before the trigger), why there are no heights, the
        # export's summary, why the slider's frame could not be measured: wrapped, up to 4 lines, scrolled beyond
        # (a smallest window keeps its maps and the whole message; the full text is also the tooltip)
        self.message = MessageArea("", max_lines=4)
        self.said = ReplayMessage()  # what it says (refresh_message draws it)
        outer.addWidget(self.message)
        self.open_button.clicked.connect(self.open_requested.emit)
        self.export_button.clicked.connect(self.export_requested.emit)
        self.slider.valueChanged.connect(self.frame_changed.emit)

    def refresh_message(self) -> None:
        """Draw :attr:`said` in the message area: red where it warns."""
        self.message.setText(self.said.text)
        self.message.setStyleSheet("color: #b00000; font-weight: bold" if self.said.red else "")

    def set_recording(self, rec: Recording) -> None:
        self.file_label.setText(f"{os.path.basename(rec.path)} — {rec.n_frames} frames"
                                + ("" if rec.reference is not None else " (no reference stored)")
                                + "".join(f"; {note.split(':')[0]}" for note in rec.notes))  # in full below
        self.file_label.setStyleSheet("color: #b00000; font-weight: bold" if rec.notes else "")
        self.slider.blockSignals(True)
        self.slider.setRange(0, max(rec.n_frames - 1, 0))
        self.slider.setValue(0)
        self.slider.blockSignals(False)
        self.slider.setEnabled(rec.n_frames > 0)
        self.export_button.setEnabled(rec.n_frames > 0)
