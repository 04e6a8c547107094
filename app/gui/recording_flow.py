"""Trigger and recording: arm, trigger, disarm, the auto-trigger's threshold and its readout.

Functions take the :class:`app.gui.window.MainWindow` (``w``); it forwards its methods here.
"""

from __future__ import annotations

import logging
import os
from typing import Optional

from pyqtgraph.Qt import QtWidgets

from app.capture.recorder import summary_rows

from .model.recording import progress_line, slope_of_mrad

log = logging.getLogger(__name__)


def update_cost(w):
    s = w.session.camera_settings()
    if s is None:
        return
    bpp = 1 if s.bit_depth <= 8 else 2
    acq = w.session.acquisition
    w.recording_panel.set_cost(s.width * s.height * bpp, s.frame_rate_hz,
                                  acq.ring.n_frames if acq is not None else None)


def choose_folder(w):
    path = QtWidgets.QFileDialog.getExistingDirectory(w, "Recording folder",
                                                      w.recording_panel.folder.text())
    if path:
        w.recording_panel.folder.setText(path)


def arm(w):
    """Arm a pre/post-trigger recording into the chosen folder."""
    rp = w.recording_panel
    folder = rp.folder.text().strip() or os.getcwd()
    threshold = slope_of_mrad(rp.threshold.value()) if rp.auto.isChecked() else None
    geometry_toml = w.geometry.to_toml_text() if w.geometry is not None else None
    try:
        path = w.session.arm(folder, rp.pre.value(), rp.post.value(), reference=w.reference,
                                geometry_toml=geometry_toml, auto_threshold=threshold)
    except Exception as exc:  # noqa: BLE001 - disk space, RAM, no camera...
        rp.set_state("error")
        w.show_error(f"Cannot arm the recording: {exc}")
        return
    rp.result_label.setText(f"armed: will write {path}")
    rp.set_state("armed")


def threshold_from_now(w) -> Optional[float]:
    """"Set from now": the auto-trigger threshold = 5 x the recent RMS slope of the live maps (mrad)."""
    proposal = w.rms_history.propose_mrad(live=w.stale.maps is None)
    if proposal is None:
        w.show_error("No live slope maps to set the threshold from: capture a reference on still water "
                        "(Controls ▸ Reference & geometry) and let the maps run, then press Set from now.")
        return None
    w.recording_panel.threshold.setValue(proposal)
    w.info(f"auto-trigger threshold {w.recording_panel.threshold.value():.3g} mrad: 5 × the recent "
              f"RMS slope ({w.rms_history.readout()})")
    return proposal


def trigger_now(w):
    try:
        w.session.trigger_now()
    except Exception as exc:  # noqa: BLE001
        w.show_error(f"Trigger failed: {exc}")


def disarm(w):
    try:
        text = w.session.disarm()
    except Exception as exc:  # noqa: BLE001
        text = "disarm failed"
        w.show_error(f"Disarm failed: {exc}")
    w.recording_panel.set_state("idle")
    w.recording_panel.result_label.setText(text)


def update_recording(w):
    rec = w.session.recording_status()
    if rec is None:
        return
    rp = w.recording_panel
    state = rec["state"]
    if state != rp.state_label.text():
        rp.set_state(state)
        rp.result_label.setText(progress_line(state, rec.get("path"), rp.result_label.text(),
                                              rec.get("summary_text", "")))
    rp.progress.setValue(int(round(100 * rec.get("progress", 0.0))))
    if state in ("done", "error") and rec.get("summary_text") and not rec.get("_shown"):
        rec["_shown"] = True
        if rec.get("summary"):
            rp.show_summary(rec.get("path", ""), summary_rows(rec["summary"]))
        else:
            rp.result_label.setText(rec["summary_text"])
        if state == "error":
            w.show_error(f"Recording stopped: {rec.get('error')}\nEvery frame received so far is kept "
                            f"in {rec.get('path')}.")
