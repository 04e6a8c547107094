"""Export heights of a recording from the Replay tab through the batch engine (:mod:`app.batch`)."""

from __future__ import annotations

import logging
import os
from typing import Callable, Optional

import numpy as np

__all__ = ["export_heights", "describe_export", "frame_list"]

log = logging.getLogger(__name__)


#: HDF5 compression of the GUI's export: gzip (with shuffle, one frame per chunk: app.batch.writer) shrinks
#: the float32 maps of a 512^2 recording from 3.41 to 2.19 MB per frame; "none" is 3x faster to write.
EXPORT_COMPRESSION = "gzip"


def export_heights(recording_path: str, out_path: str, *, geometry_toml: Optional[str] = None,
                   reference: Optional[np.ndarray] = None, grid: str = "full",
                   progress: Optional[Callable[[int, int], None]] = None,
                   compression: str = EXPORT_COMPRESSION) -> str:
    """Process every frame of ``recording_path`` into ``out_path`` (layout: docs/output-format.md).

    Parameters
    ----------
    recording_path : str
        HDF5 recording (``/frames``; its ``/reference`` and ``/geometry_toml`` are used when present).
    out_path : str
        Output file; an existing file is an error (never overwritten).
    geometry_toml : str, optional
        Geometry to use when the recording stores none.
    reference : ndarray, optional
        Reference image to use when the recording stores none.
    grid : {"full", "decimated"}
        Output grid.
    progress : callable, optional
        ``progress(done, total)``; called at start and after every frame written.
    compression : {"gzip", "lzf", "none"}
        Of the per-frame maps and the reference (lossless; chunked one frame per chunk).

    Returns
    -------
    str
        ``out_path``.
    """
    from app.batch import ProcessJob, run_process
    from app.files import imageio

    total = imageio.frame_count(recording_path)
    if progress is not None:
        progress(0, total)
    geometry = None
    if geometry_toml is not None:
        from processing import Geometry

        geometry = Geometry.from_toml_text(geometry_toml)
    run_process(ProcessJob(reference=recording_path if reference is None else np.asarray(reference),
                           frames=[recording_path], geometry=geometry, out=out_path,
                           grid=grid, on_progress=progress, compression=compression,
                           command=f"(tirdeflect gui: Replay ▸ Export heights of {recording_path})"))
    if progress is not None:
        progress(total, total)
    return out_path


def frame_list(indices, limit: int = 12) -> str:
    """``"11, 35, 59"`` (frame indices from 0, as /height stores them), the first ``limit`` then "…"."""
    idx = [int(i) for i in indices]
    return ", ".join(str(i) for i in idx[:limit]) + (f", … ({len(idx)} in all)" if len(idx) > limit else "")


def _text(value) -> str:
    """An HDF5 string (bytes or str) as str."""
    return value.decode() if isinstance(value, bytes) else str(value)


def _setup(f) -> str:
    """The geometry's ``setup`` ("tir", "fsss") of an open OUT.h5, or "" where it holds none."""
    from processing import Geometry

    text = f.attrs.get("geometry_toml")
    if text is None:
        return ""
    try:
        return Geometry.from_toml_text(_text(text)).setup
    except ValueError:  # GeometryError or TOML's: an unreadable geometry names nothing here
        return ""


def describe_export(out_path: str) -> tuple:
    """What an exported OUT.h5 holds, for the message and the log: ``(text, clean)``.

    Names the frames stored invalid (``/frame_status`` non-zero), flagged as jumps (``/pin_status["jump"]``),
    whose pattern moved on the pin samples (``/pin_status["region_motion_px"]``) or shifted alike over the
    whole frame (``/pin_status["frame_shift_share"]``, ``PinStatus.shifted``), whose image's scale changed
    (``/pin_status["region_scale_explained"]``, ``PinStatus.scaled``) and recorded INCOMPLETE
    (``/frame_flags``), saturated (``/saturated_pct`` above
    :data:`processing.live_view.SATURATION_MAX_PCT`), banded along their rows (the run's
    ``frames_light_banded``: :mod:`processing.banding`) and turned since the reference (``/turn_mrad``
    above :data:`processing.turn.TURN_MAX_MRAD`), by index, and measured on less than half of the reference's
    area (the run's ``frames_partly_measured``); ``clean`` is False when there is any.
    Frames whose own hot pixels were repaired (``/hot_pixels``) are named in a note that leaves
    ``clean`` as it is.
    """
    import h5py

    from drivers.base import FrameFlags
    from processing.live_view import SATURATION_MAX_PCT
    from processing.pin import band_moved, pattern_moved, pattern_scaled, pattern_shifted
    from processing.turn import TURN_MAX_MRAD

    with h5py.File(out_path, "r") as f:
        n = int(f["height"].shape[0]) if "height" in f else 0
        parts = []
        band_note = ""
        if "frame_status" in f:
            bad = np.flatnonzero(np.asarray(f["frame_status"][:n]) != 0)
            if bad.size:
                parts.append(f"{bad.size} invalid (frames {frame_list(bad)})")
        if "pin_status" in f and "jump" in (f["pin_status"].dtype.names or ()):
            jumps = np.flatnonzero(np.asarray(f["pin_status"]["jump"][:n]) != 0)
            if jumps.size:
                parts.append(f"{jumps.size} flagged as jumps against the previous frame (frames {frame_list(jumps)})")
        if "pin_region" in f and "pin_status" in f and "region_motion_px" in (f["pin_status"].dtype.names or ()):
            region = _text(f["pin_region"].attrs.get("region", ""))
            st = f["pin_status"][:n]
            shifted = np.zeros(0, np.int64)
            if "frame_shift_share" in (st.dtype.names or ()):
                shifted = np.flatnonzero([pattern_shifted(float(m), float(share))  # PinStatus.shifted's judgement
                                          for m, share in zip(st["frame_motion_px"], st["frame_shift_share"])])
                if shifted.size:
                    effect = np.asarray(st["shift_effect_um"][shifted], np.float64)
                    carry = (f"; the heights carry up to {np.nanmax(effect):.3g} um RMS from it, a tilt"
                             if np.isfinite(effect).any() else "")
                    parts.append(f"{shifted.size} where the whole pattern shifted since the reference: the water "
                                 f"level changed, or the camera or the board moved{carry}; take the reference "
                                 f"again (frames {frame_list(shifted)}, /pin_status shift_effect_um)")
            if "region_scale_explained" in (st.dtype.names or ()):
                scaled = np.flatnonzero([pattern_scaled(float(reach), float(share))  # PinStatus.scaled's judgement
                                         for reach, share in zip(st["region_scale_reach_px"],
                                                                 st["region_scale_explained"])])
                if scaled.size:
                    pct = 100 * np.asarray(st["region_scale"][scaled], np.float64)
                    parts.append(f"{scaled.size} where the image's scale changed since the reference (up to "
                                 f"{np.max(np.abs(pct)):.2g} %): the lens refocused or the camera moved along its "
                                 f"axis, the heights carry a curved surface that is not there; take the reference "
                                 f"again (frames {frame_list(scaled)}, /pin_status region_scale)")
            moved = np.setdiff1d(np.flatnonzero([pattern_moved(region, _text(rule), float(m))  # PinStatus.still's
                                                 for rule, m in zip(st["rule"], st["region_motion_px"])]),
                                 shifted)  # (where the whole frame shifted, that is said instead)
            if moved.size:
                parts.append(f"{moved.size} where the pattern moved in the pin region: surface not at rest there, "
                             f"or camera or board moved since the reference (frames {frame_list(moved)})")
            setup = _setup(f)
            band = np.setdiff1d(np.flatnonzero([band_moved(region, _text(rule), float(m), setup)
                                                for rule, m in zip(st["rule"], st["region_motion_px"])]), shifted)
            if band.size:
                band_note = (f"in {band.size} frame(s) the pattern moved on the {region} the heights are pinned on "
                             f"by default (waves reaching it, or the camera or the board moved; frames "
                             f"{frame_list(band)}): their part along exp(-T y/H) is set by that; a reference "
                             f"region where the water is still fixes it (/pin_status region_motion_px)")
        if "frame_flags" in f:
            inc = np.flatnonzero((np.asarray(f["frame_flags"][:n]).astype(np.int64) & int(FrameFlags.INCOMPLETE)) != 0)
            if inc.size:
                parts.append(f"{inc.size} recorded INCOMPLETE (frames {frame_list(inc)})")
        if "saturated_pct" in f:
            pct = np.asarray(f["saturated_pct"][:n], np.float64)
            clipped = np.flatnonzero(pct > SATURATION_MAX_PCT)  # (NaN: not measured, not counted)
            if clipped.size:
                parts.append(f"{clipped.size} with more than {SATURATION_MAX_PCT:g} % of their pixels saturated "
                             f"(up to {pct[clipped].max():.1f} %; frames {frame_list(clipped)}): lower the "
                             f"exposure or gain")
        if "turn_mrad" in f:
            turn = np.abs(np.asarray(f["turn_mrad"][:n], np.float64))
            # the run's own judgement (processing.turn.TurnCheck.flagged: also 3 standard errors; plain waves read
            # 0.11 mrad and were named here while the run flagged none); files before /turn_flagged: the bound
            turned = (np.flatnonzero(np.asarray(f["turn_flagged"][:n]) != 0) if "turn_flagged" in f
                      else np.flatnonzero(turn > TURN_MAX_MRAD))  # (NaN: not judged, not counted)
            if turned.size:
                parts.append(f"{turned.size} where the pattern turned since the reference (up to "
                             f"{turn[turned].max():.2f} mrad; frames {frame_list(turned)}): the camera or the board "
                             f"moved; capture a new reference on still water (/turn_mrad)")
        banded = int(f.attrs.get("frames_light_banded", 0))  # (processing.banding: per run, not per frame)
        if banded:
            parts.append(f"{banded} with bands of light along the rows that the reference does not show (up to "
                         f"{float(f.attrs.get('light_bands_pct_max', 0.0)):.2g} % RMS): a rolling shutter under "
                         f"flickering light, or a shadow's edge; use DC-driven light or a global shutter")
        partly = int(f.attrs.get("frames_partly_measured", 0))  # (app.batch.frame_status.coverage: per run)
        if partly:
            parts.append(f"{partly} measured on less than half of the area the reference covers (the least "
                         f"{float(f.attrs.get('measured_pct_min', 0.0)):.1f} %): blurred, dimmed or hidden there, "
                         f"the run's log says which (/valid)")
        holed = ""
        if int(f.attrs.get("frames_partly_unmeasured", 0)):  # (app.batch.frame_status.UNMEASURED_NOTE_PCT)
            holed = (f"{int(f.attrs['frames_partly_unmeasured'])} frame(s) were not measured on part of their area "
                     f"(up to {float(f.attrs.get('unmeasured_pct_max', 0.0)):.1f} %): heights NaN there (/valid), "
                     f"where the surface was too steep, the pattern folded or was hidden")
        repaired = ""
        if "hot_pixels" in f:
            hot = np.asarray(f["hot_pixels"][:n], np.int64)
            with_hot = np.flatnonzero(hot > 0)  # (-1: not measured, not counted)
            if with_hot.size:
                repaired = (f"{with_hot.size} frame(s) had isolated pixels brighter than the pattern, repaired "
                            f"before measuring (up to {hot.max()}; frames {frame_list(with_hot)}; /hot_pixels)")
    text = f"heights of {n} frames exported to {out_path}"
    if parts:
        text += ": " + "; ".join(parts) + " — see /frame_status and /pin_status (docs/output-format.md)"
        log.warning("%s", text)
    else:
        text += ": every frame measured, none flagged"
        log.info("%s", text)
    if repaired:  # a note, not a flag: the heights are measured as without them
        text += f". Note: {repaired}"
        log.info("%s", repaired)
    if holed:  # a note: the frames are measured, but not all of their area
        text += f". Note: {holed}"
        log.info("%s", holed)
    if band_note:  # a note as well: the heights are as measured; what pins them is the user's to choose
        text += f". Note: {band_note}"
        log.info("%s", band_note)
    return text, not parts


def choose_movie(window) -> None:
    """File ▸ Export movie: pick a processed OUT.h5 (default: the last export) and the movie to write."""
    from pyqtgraph.Qt import QtWidgets

    done = getattr(window, "export_result", None)
    default = done[1] if isinstance(done, tuple) and done[0] == "done" else ""
    out_h5, _ = QtWidgets.QFileDialog.getOpenFileName(window, "Movie of which processed heights (OUT.h5)?",
                                                      default, "Processed heights (*.h5 *.hdf5)")
    if not out_h5:
        return
    movie, _ = QtWidgets.QFileDialog.getSaveFileName(window, "Export movie", os.path.splitext(out_h5)[0] + ".mp4",
                                                     "Movie (*.mp4 *.mkv *.mov *.avi)")
    if movie:
        export_movie(window, out_h5, movie)


def export_movie(window, out_h5: str, movie_path: str, **options) -> None:
    """Write a movie of ``out_h5`` through :func:`app.batch.movie.make_movie` in the background.

    Progress shows in the status bar ("movie: k/n frames"); the outcome lands in
    ``window.movie_result`` (``("done", MovieReport)`` or ``("error", text)``).
    """
    from pyqtgraph.Qt import QtCore

    if window.busy("movie"):
        window.show_error("A movie is being written already; wait for it to finish.")
        return
    window.movie_result = None
    state = {"done": 0, "total": 0}

    def progress(done, total):  # worker thread: only numbers; the timer shows them
        state["done"], state["total"] = done, total

    def show():
        window.info(f"movie: {state['done']}/{state['total'] or '?'} frames of {os.path.basename(out_h5)} → "
                    f"{os.path.basename(movie_path)}", 2000)

    timer = QtCore.QTimer(window)
    timer.setInterval(200)
    timer.timeout.connect(show)
    timer.start()
    show()

    def job():
        from app.batch.movie import make_movie
        return make_movie(out_h5, movie_path, on_progress=progress, **options)

    def done(report, error):
        timer.stop()
        timer.deleteLater()
        if error:
            window.movie_result = ("error", error)
            window.show_error(f"Movie not written: {error}")
            return
        window.movie_result = ("done", report)
        window.info(f"movie written: {report.path} ({report.frames} frames, {report.width}x{report.height}, "
                    f"{report.value_range[0]:.3g} … {report.value_range[1]:.3g} {report.unit})", 15000)
    window.run_background("movie", job, done)
