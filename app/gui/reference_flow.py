"""Reference and geometry: capture (only frames that agree), load, save, the reconstructor built
from them in the background, the geometry editor and the reference-region box.

Functions take the :class:`app.gui.window.MainWindow` (``w``); it forwards its methods here.
"""

from __future__ import annotations

import logging
import os
from typing import Optional

import numpy as np
from pyqtgraph.Qt import QtWidgets

from processing.errors import GeometryError
from processing.live_view import reference_saturation

from . import state
from .alignment import theta_mismatch
from .model.memory import live_device_for
from .model.reference import capture_failed_label, capture_failed_message
from .model.region import clamp_region, reference_crop, region_after_roi_change, region_problem, roi_of

log = logging.getLogger(__name__)


def capture_reference(w, n_frames: int):
    """Average ``n_frames`` new camera frames into the reference (in the background); moving water is refused."""
    w.geometry_panel.reference_label.setText(f"capturing {n_frames} frames…")

    def done(result, error):
        if error:
            w.geometry_panel.reference_label.setText(capture_failed_label(error, w.reference is not None))
            w.geometry_panel.reference_label.setStyleSheet("color: #c00000; font-weight: bold")
            w.show_error(capture_failed_message(error, w.reference is not None))
            return
        image, report = result
        w.geometry_panel.reference_label.setStyleSheet("")
        w.set_reference(image, report.text())
    pattern = getattr(w.geometry, "pattern", "checkerboard")
    w.run_background("reference", lambda n: w.session.capture_reference(n, pattern=pattern), done,
                        int(n_frames))


def set_reference(w, image: np.ndarray, origin: str = "", path: Optional[str] = None) -> bool:
    """Use ``image`` as the flat-surface reference: rebuild the reconstructor (background).

    ``path``: the file it came from (remembered for the next start; a captured one is kept in the cache).
    """
    w.reference = np.asarray(image)
    w.reference_path = path
    roi = roi_of(w.session.camera_settings())  # where on the sensor it was taken (None: not this camera's)
    w.reference_roi = roi if roi is not None and (roi[3], roi[2]) == w.reference.shape[:2] else None
    w._reference_text = f"reference: {origin}, {image.shape[1]}×{image.shape[0]} px"
    w.geometry_panel.reference_label.setText(w._reference_text + " — building…")
    w._rebuild_reconstructor()
    return True


def _remove_reconstructor(w) -> None:
    """The worker measures nothing from now on (maps on screen: "their reference is no longer in use")."""
    w.session.worker.set_reconstructor(None)
    w.pin_overlay.set_reconstructor(None)
    w.references.remove(w.session.newest_seq())


def rebuild_reconstructor(w):
    request = w.references.request()  # any build still running is superseded (model/staleness.py)
    if w.reference is None or w.geometry is None:
        w.reference_refused = ""  # nothing refused: nothing to measure against
        _remove_reconstructor(w)
        return
    reference, geometry, use_gpu = w.reference, w.geometry, w.memory.use_gpu

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

        device, text = live_device_for(use_gpu, live_device)  # the GPU only when asked for (remembered)
        if device == "cuda":
            try:
                rec = Reconstructor(reference, geometry, planner_effort=w.planner_effort, device="cuda",
                                    window_px=DOT_WINDOW_PX)
                rec.device_text = text if rec.gpu_fallback is None else f"CPU ({rec.gpu_fallback})"
                return rec
            except TirdeflectError as exc:  # e.g. a dot pattern: the GPU reads checkerboards only
                text = f"CPU ({exc})"
        rec = Reconstructor(reference, geometry, planner_effort=w.planner_effort, window_px=DOT_WINDOW_PX)
        rec.device_text = text
        return rec

    geometry_at_fault = []  # set when the geometry does not fit the reference (the error reaches done() as text)

    def build_checked():
        from processing.reference_average import departure_note, reconstructor_departure_px

        from .alignment import periodic_pattern

        try:
            rec = build()
        except GeometryError:
            geometry_at_fault.append(True)
            raise
        problem = periodic_pattern(reference) if getattr(geometry, "pattern", "") == "dots" else None
        # a pattern that departs from a board on still water (a file averaged over waves), and what its board says
        # of the geometry (judged here, off the GUI thread): as process says them
        return rec, problem, departure_note(reconstructor_departure_px(rec)), rec.chain.board_note

    def done(built, error):
        rec, problem, departure, board = built if built is not None else (None, None, "", "")
        action = w.references.outcome(request, error is None)
        if action == "superseded":
            return  # a newer reference/geometry is being built: this one (even failed) changes nothing
        if action == "remove":
            _remove_reconstructor(w)
            w.reference_refused = str(error)  # the maps say it (model.staleness.unmeasured_messages)
            w.geometry_panel.reference_label.setText("reference NOT usable")
            w.geometry_panel.reference_label.setStyleSheet("color: #c00000; font-weight: bold")
            if geometry_at_fault:  # the geometry does not fit this reference: not "geometry OK"
                w.geometry_panel.geometry_label.setText("<span style='color:#c00'>the geometry does not fit the "
                                                        "reference (see the banner)</span>")
            w.show_error(f"Bad reference: {error}")
            return
        w.reference_refused = ""
        newest = w.session.newest_seq()  # later frames are measured against this reference
        w.references.install(request, newest if newest is not None else w.clock.last_raw_seq)
        w.session.worker.set_reconstructor(rec, reference=reference)  # the worker process builds its own
        w.pin_overlay.set_reconstructor(rec)
        w.session.reference = reference
        text = w._reference_text or "reference"
        try:
            c = rec.carriers
            periods = getattr(c, "periods_px", None)
            if periods is not None:
                text += " — periods " + ", ".join(f"{p:.2f}" for p in np.ravel(periods)) + " px"
        except Exception:  # noqa: BLE001 - information only
            pass
        if rec.mosaic is not None:  # a colour camera read raw: equalised in it and every frame (processing.mosaic)
            gains = " / ".join(f"{g:.2f}" for g in rec.mosaic.gains().ravel())
            text += f" — colour mosaic equalised (gains {gains})"
        stuck = int(rec.defects.size)
        if stuck:  # repaired in the reference and in every frame (processing.mask.defect_pixels)
            text += f" — {stuck} stuck sensor pixel{'s' if stuck > 1 else ''} repaired"
        w.pattern_problem = problem
        # what is wrong with a usable reference, the first that applies, is said where the user looks, in red and
        # without a tick; the heights still come
        camera = frame_shape(w)
        if camera is not None and tuple(np.shape(reference)) != tuple(camera):  # no height at all, until one of
            # them changes (by-hand trial of 7 Dec 2026: restored at 256^2 for a 512^2 camera, it kept its tick)
            rows, cols = np.shape(reference)
            findings = [("NOT the camera's size", f"The reference is {rows}×{cols} px but the camera gives "
                                                  f"{camera[0]}×{camera[1]}: no height can be measured against it. "
                                                  f"Capture a new reference (Ctrl+R), or set the camera's region "
                                                  f"of interest and binning back to {rows}×{cols}.")]
        elif problem:  # every height would be wrong
            findings = [("NOT the chosen pattern", f"The reference does not show random dots: {problem}")]
        else:
            # captured (Ctrl+R: the float average of the camera's integer frames), else a file as it is
            saturated = reference_saturation(reference, averaged_counts=w.reference_path is None)
            findings = [
                ("θ MISMATCH", theta_mismatch(rec.carriers, geometry)),  # the y scale and dh/dy off, heights right
                (f"{saturated[0]:.0f} % SATURATED" if saturated else "", _capital(saturated[1]) if saturated else ""),
                ("WATER MOVING?", _capital(departure)),  # every height measured against the waves it holds
                # the board 2-4.5 % off the geometry's, or a keystone not its camera's (moving water said above)
                ("CHECK THE GEOMETRY", _capital(board))]
        for label, message in findings:
            if message:
                w.geometry_panel.reference_label.setText(f"{text} — {label}")
                w.geometry_panel.reference_label.setStyleSheet("color: #c00000; font-weight: bold")
                w.show_error(message)
                state.reference_in_use(w)
                return
        w.geometry_panel.reference_label.setText(text + " ✓")
        w.geometry_panel.reference_label.setStyleSheet("")  # no longer red: a tick in red read as a warning
        w.clear_error()
        state.reference_in_use(w)
    w.run_background("reconstructor", build_checked, done)


def _capital(text: str) -> str:
    """``text`` with its first letter a capital (a note begun lower-case, said as a sentence)."""
    return text[:1].upper() + text[1:]


def choose_save_reference(w):
    if w.reference is None:
        w.show_error("No reference to save: capture one first (Reference ▸ Capture reference).")
        return
    path, _ = QtWidgets.QFileDialog.getSaveFileName(w, "Save reference", "reference.tif",
                                                    "Images (*.tif *.tiff *.png)")
    if path:
        w.save_reference(path)


def save_reference(w, path: str) -> None:
    from app.files.imageio import write_image
    image = w.reference
    if image.dtype.kind == "f":  # averaged: keep precision in a float TIFF
        import tifffile
        if not path.lower().endswith((".tif", ".tiff")):
            path += ".tif"
        tifffile.imwrite(path, image.astype(np.float32))
    else:
        write_image(path, image)
    w.info(f"reference saved to {path}")


def choose_load_reference(w):
    path, _ = QtWidgets.QFileDialog.getOpenFileName(w, "Load reference", "",
                                                    "Images (*.tif *.tiff *.png *.bmp *.h5)")
    if path:
        w.load_reference(path)


def load_reference(w, path: str) -> None:
    try:
        from app.files.imageio import read_reference
        image = read_reference(path)
    except Exception as exc:  # noqa: BLE001 - shown
        w.show_error(f"Cannot load reference {path!r}: {exc}")
        return
    w.set_reference(image, os.path.basename(path), path=os.path.abspath(path))


def set_geometry(w, geometry) -> None:
    w.geometry = geometry
    d = geometry.to_dict()
    w.geometry_panel.set_values(d)
    w._show_region(d.get("reference_region"))
    w.geometry_panel.geometry_label.setText("geometry OK")
    w._rebuild_reconstructor()
    state.geometry_in_use(w)


def apply_geometry_editor(w):
    from processing import Geometry
    try:
        values = w.geometry_panel.values()
        base = w.geometry.to_dict() if w.geometry is not None else {}
        base.update({k: v for k, v in values.items()})
        if values["setup"] != "fsss":
            for k in ("fsss_layers", "fsss_camera_distance_mm"):
                base.pop(k, None)
        else:
            base.pop("theta_deg", None)
        geometry = Geometry.from_dict(base)
        problem = region_problem(geometry.to_dict().get("reference_region"), w._frame_shape())
        if problem:
            raise ValueError(problem)
    except Exception as exc:  # noqa: BLE001 - GeometryError, ValueError
        w.geometry_panel.geometry_label.setText(f"<span style='color:#c00'>{exc}</span>")
        if w.geometry is not None:  # the box goes back where the geometry in use has it
            w._show_region(w.geometry.to_dict().get("reference_region"))
        return
    w.geometry_panel.geometry_label.setText("geometry OK")
    w.geometry = geometry
    w._show_region(geometry.to_dict().get("reference_region"))
    w._rebuild_reconstructor()
    state.geometry_in_use(w)


def show_region(w, region):
    if region is None:
        w.region_roi.setVisible(False)
        return
    r0, r1, c0, c1 = (float(v) for v in region)
    w.region_roi.blockSignals(True)
    w.region_roi.setPos([c0, r0])
    w.region_roi.setSize([c1 - c0, r1 - r0])
    w.region_roi.blockSignals(False)
    w.region_roi.setVisible(True)


def frame_shape(w):
    """(rows, cols) of the camera's frames (None: no camera)."""
    s = w.session.camera_settings()
    return (s.height, s.width) if s is not None and s.height and s.width else None


def region_dragged(w):
    """The box was dragged: kept on the frame (clamped at the edit, said so), then used."""
    pos, size = w.region_roi.pos(), w.region_roi.size()
    region = (pos.y(), pos.y() + size.y(), pos.x(), pos.x() + size.x())
    shape = w._frame_shape()
    moved = False
    if shape is not None:
        region, moved = clamp_region(region, shape)
        if moved:
            w.info("reference region kept inside the frame: the box cannot leave the camera image")
    r0, r1, c0, c1 = (int(round(v)) for v in region)
    w._show_region((r0, r1, c0, c1))
    w.geometry_panel.set_region((r0, r1, c0, c1))
    w.apply_geometry_editor()
    if moved and w.geometry_panel.geometry_label.text() == "geometry OK":  # also where the user edits it: the
        # status bar cuts the message at 1280x800
        w.geometry_panel.geometry_label.setText("geometry OK — the reference region was kept inside the frame "
                                                "(the box cannot leave the camera image)")


def choose_load_geometry(w):
    path, _ = QtWidgets.QFileDialog.getOpenFileName(w, "Load geometry", "", "TOML (*.toml)")
    if path:
        w.load_geometry(path)


def load_geometry(w, path: str) -> None:
    from processing import Geometry
    try:
        geometry = Geometry.from_toml(path)
    except Exception as exc:  # noqa: BLE001 - GeometryError, OSError
        w.show_error(f"Cannot load geometry {path!r}: {exc}")
        return
    w.set_geometry(geometry)
    w.confirm_geometry()  # a loaded geometry is this camera's set-up
    w.info(f"geometry loaded from {path}")


def choose_save_geometry(w):
    path, _ = QtWidgets.QFileDialog.getSaveFileName(w, "Save geometry", "geometry.toml", "TOML (*.toml)")
    if path:
        w.save_geometry(path)


def save_geometry(w, path: str) -> None:
    if w.geometry is None:
        w.show_error("No valid geometry to save: fix the fields marked in red first.")
        return
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(w.geometry.to_toml_text())
    w.info(f"geometry saved to {path}")


def _region_follows_roi(w, old_roi, new_roi) -> str:
    """A reference region of the geometry in use, moved to the same place on the water in the new ROI's
    pixels (or cut, or dropped for the default); before the reference is set, so that one rebuild uses it."""
    from processing import Geometry

    if w.geometry is None:
        return ""
    d = w.geometry.to_dict()
    region, note = region_after_roi_change(d.get("reference_region"), old_roi, new_roi)
    if note:
        d["reference_region"] = None if region is None else list(region)
        w.geometry = Geometry.from_dict(d)
        w.geometry_panel.set_region(region)
        w._show_region(region)
        state.geometry_in_use(w)
        w.info(note)
    return note


def follow_roi(w, settings) -> None:
    """The camera now delivers ``settings``' ROI: crop the reference to it (and rebuild, the pin band
    with it), or, when it is not inside the reference's, say that a new reference is needed."""
    new_roi = roi_of(settings)
    if w.reference is None or w.reference_roi is None or new_roi is None or new_roi == w.reference_roi:
        return
    crop = reference_crop(w.reference_roi, new_roi)
    if crop is not None:
        old = w.reference_roi
        note = _region_follows_roi(w, old, new_roi)
        set_reference(w, w.reference[crop], f"cropped to the new ROI {new_roi[2]}×{new_roi[3]} at "
                                            f"({new_roi[0]}, {new_roi[1]}) from the one taken at ({old[0]}, {old[1]})"
                                            + (f"; {note}" if note else ""))
        return
    _region_follows_roi(w, w.reference_roi, new_roi)  # for the next reference, at the same place on the water
    w.references.request()  # a build still running must not install a reference of the old ROI
    _remove_reconstructor(w)
    w.geometry_panel.reference_label.setText(
        f"the reference ({w.reference_roi[2]}×{w.reference_roi[3]} at ({w.reference_roi[0]}, {w.reference_roi[1]})) "
        f"does not cover the new ROI: capture a new reference")
    w.geometry_panel.reference_label.setStyleSheet("color: #c00000; font-weight: bold")
