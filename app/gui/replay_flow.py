"""The Replay tab: open a recording, reconstruct the frame on the slider (newest request only),
export heights through the batch engine.

Functions take the :class:`app.gui.window.MainWindow` (``w``); it forwards its methods here.
"""

from __future__ import annotations

import logging
import os
import time

import numpy as np
from pyqtgraph.Qt import QtCore, QtWidgets

from .model.replay import ReplayMessage, frame_label, height_mark, height_title, replay_inputs, short_error
from .replay import RECORDING_FILTER, Recording

log = logging.getLogger(__name__)


def choose_recording(w):
    path, _ = QtWidgets.QFileDialog.getOpenFileName(w, "Open recording",
                                                    w.recording_panel.folder.text(), RECORDING_FILTER)
    if path:
        w.open_recording(path)


def open_recording(w, path: str) -> bool:
    try:
        rec = Recording(path)
    except Exception as exc:  # noqa: BLE001
        w.show_error(str(exc))
        return False
    if w.replay_recording is not None:
        w.replay_recording.close()
    w.replay_recording = rec
    w._replay_reconstructor = None
    # nothing of the file opened before stays on the tab: its heights, their marks, its messages
    w.replay_shown_index, w.replay_last_result = None, None
    w.replay.height.image.clear()
    w.replay.height.set_stale(None)
    w.replay.height.show_message("")
    w.replay.set_recording(rec)
    reference, geometry, message = replay_inputs(rec.reference, w.reference, rec.geometry_toml, w.geometry)
    # the export measures with what the view does, even after the window's reference or geometry changed
    rec.inputs = (reference, geometry)
    # what the file says of itself (frames lost, ended early) first, in red: no frame is mislabelled in silence
    w.replay.said = ReplayMessage()
    w.replay.said.say("\n".join(rec.notes + ([message] if message else [])), warns=bool(rec.notes))
    w.replay.refresh_message()
    if reference is not None and geometry is not None:
        def build():
            from processing import Reconstructor

            from .session import NO_OVERLAP_WITH_DISCOVERY

            with NO_OVERLAP_WITH_DISCOVERY:  # see there
                return Reconstructor(reference, geometry, planner_effort=w.planner_effort)

        def done(r, error):
            if error:
                if w.replay_recording is rec:  # (the file's own notes stay)
                    w.replay.said.say("\n".join(rec.notes + [f"cannot process this recording: {error}"]), warns=True)
                    w.replay.refresh_message()
                return
            if w.replay_recording is rec:
                w._replay_reconstructor = r
                w._show_replay_frame(w.replay.slider.value())
        w.run_background("replay-reconstructor", build, done)
    w._show_replay_frame(0)
    w.tabs.setCurrentWidget(w.replay)
    return True


def show_replay_frame(w, index: int):
    rec = w.replay_recording
    if rec is None or rec.n_frames == 0:
        return
    frame = rec.frame(int(index))
    w.replay.raw.set_data(frame, levels=(0, float(frame.max()) or 1.0) if w.replay.raw.auto_levels else None)
    # the frame's time: NaN where the file has none (recordings, TIFF stacks)
    lost = 0 if rec.lost_before is None else int(rec.lost_before[int(index)])
    w.replay.index_label.setText(frame_label(int(index), rec.n_frames, rec.trigger_index(int(index)),
                                             rec.frame_time_s, rec.time_origin, lost))
    w.replay.index_label.setStyleSheet("color: #b00000; font-weight: bold" if lost else "")
    w.replay.height.set_stale(height_mark(int(index), w.replay_shown_index))
    w.replay_queue.want(frame, int(index))
    w._process_replay_frame()


def process_replay_frame(w):
    """Reconstruct the wanted replay frame in the background (newest request only; never in the GUI thread): on
    the live grid at once, then on every pixel once the slider rested on it (:class:`ReplayQueue`)."""
    r = w._replay_reconstructor
    ready = r is not None and not w.busy("replay-frame")
    wanted = w.replay_queue.take(ready=ready, now=time.monotonic())
    if wanted is None:
        due = w.replay_queue.due_in_s(time.monotonic()) if ready else None
        if due is not None:  # (a running job looks again when it ends)
            QtCore.QTimer.singleShot(int(1e3 * due) + 1, w, lambda: None if w._closing else w._process_replay_frame())
        return
    frame, index, grid = wanted
    rec = w.replay_recording

    def job():
        r.reset_series()  # frames may be visited in any order: no temporal unwrapping across them
        return r(frame, grid=grid)

    def done(result, error):
        if w.replay_recording is not rec:
            return
        # why the frame could not be measured: a few words on its map (whose tooltip has all of them), in full
        # in the message under the slider (a map of a small window has room for two or three lines)
        w.replay.said.frame_measured(index, error or "")
        w.replay.refresh_message()
        if error:
            w.replay.height.show_message(error, short=f"{short_error(error)} (in full below)")
        else:
            w.replay.height.show_message("")
            w.replay.height.set_data(np.multiply(result.height, 1e3, dtype=np.float32),
                                        x=result.x_mm, y=result.y_mm)
            w.replay.height.set_title(height_title(result.grid, result.height.shape))
            w.replay_last_result = result
            w.replay_shown_index = index
            w.replay_queue.measured(frame, index, grid, time.monotonic())
        # the map is of the frame on the slider, or says which frame it is of
        w.replay.height.set_stale(height_mark(w.replay.slider.value(), w.replay_shown_index,
                                              index if error else None))
        w._process_replay_frame()
    w.run_background("replay-frame", job, done)


def choose_export(w):
    rec = w.replay_recording
    if rec is None:
        return
    default = os.path.splitext(rec.path)[0] + "-heights.h5"
    path, _ = QtWidgets.QFileDialog.getSaveFileName(w, "Export heights", default, "HDF5 (*.h5)")
    if path:
        w.export_heights(path)


def export_heights(w, out_path: str) -> None:
    """Process every frame of the open recording into ``out_path`` (background, with progress)."""
    rec = w.replay_recording
    if rec is None:
        w.show_error("Open a recording first (Replay ▸ Open recording).")
        return
    w.replay.progress.setRange(0, 100)  # the batch reports every frame written; _refresh shows it
    w.replay.progress.setValue(0)
    w.replay.said.say("\n".join(rec.notes + [f"exporting {rec.n_frames} frames to {out_path}…"]),
                      warns=bool(rec.notes))
    w.replay.refresh_message()
    w.export.start()
    progress = w.export.progress

    # the reference and geometry the Replay tab shows this recording's heights with (chosen when it was
    # opened): not the window's of now, which a Ctrl+R or a geometry edit since may have changed
    reference, geometry = rec.inputs
    geometry_toml = None if geometry is None else geometry.to_toml_text()

    def job():
        from . import export
        return export.export_heights(rec.path, out_path, geometry_toml=geometry_toml,
                                     reference=None if rec.reference is not None else reference,
                                     progress=progress)

    def done(result, error):
        w.export.finish(("error", error) if error else ("done", out_path))
        w.replay.progress.setRange(0, 100)
        w.replay.progress.setValue(int(100 * w.export.fraction))
        if error:
            w.show_error(f"Export failed: {error}\nFrames exported before the error are kept in {out_path}.")
            return
        from .export import describe_export

        text, clean = describe_export(out_path)
        w.replay.said.say("\n".join(rec.notes + [text]), warns=bool(rec.notes) or not clean)  # the file's notes stay
        w.replay.refresh_message()
        w.info(text, 20000)
    w.run_background("export", job, done)
