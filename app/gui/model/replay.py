"""What the Replay tab reconstructs a recording with, and what its frame label says.

The recording's own reference and geometry come first (they are what it was recorded with); the
window's stand in for what the file lacks, and what is still missing is said with what to do.
"""

from __future__ import annotations

import dataclasses
import math
import re
from typing import Optional, Tuple

import numpy as np

__all__ = ["replay_inputs", "frame_label", "height_mark", "height_title", "recording_notes", "table_times_s",
           "lost_before", "ReplayMessage", "short_error"]


def replay_inputs(file_reference, window_reference, file_geometry_toml: Optional[str], window_geometry
                  ) -> Tuple[object, object, Optional[str]]:
    """``(reference, geometry, message)`` for a recording: the file's, else the window's; ``message`` says
    why heights cannot be had (either missing) or that the file's geometry was unusable (None: all fine)."""
    reference = file_reference if file_reference is not None else window_reference
    geometry, message = window_geometry, None
    if file_geometry_toml:
        try:
            from processing import Geometry

            geometry = Geometry.from_toml_text(file_geometry_toml)
        except Exception as exc:  # noqa: BLE001 - GeometryError, a damaged TOML: said, the editor's used
            message = f"geometry stored in the file is unusable ({exc}); using the editor's"
    missing = [what for what, have in (("reference (still water)", reference is not None),
                                        ("geometry", geometry is not None)) if not have]
    if missing:
        message = (f"raw frames only: no {' and no '.join(missing)} in this file or the window; for heights, "
                   "load or capture them in Controls ▸ Reference & geometry, then open the file again")
    return reference, geometry, message


def frame_label(index: int, n_frames: int, trigger_rel: Optional[int], time_s: float, time_origin: str,
                lost: int = 0) -> str:
    """``"frame 3/60  (trigger -2)  t = +1.2345 ms from the trigger"`` (no time where the file has none: NaN);
    ``lost`` camera frames missing just before this one (a frame-id gap) are said after it: the trigger index
    counts recorded frames, so past a gap only the time tells how far from the trigger the frame is."""
    return (f"frame {index + 1}/{n_frames}" + (f"  (trigger {trigger_rel:+d})" if trigger_rel is not None else "")
            + (f"  t = {time_s * 1e3:+.4f} ms from the {time_origin}" if math.isfinite(time_s) else "")
            + (f"  — {lost} camera frame{'s' if lost > 1 else ''} LOST before it" if lost > 0 else ""))


def without_untriggered_index(attrs, table):
    """The frame table of a recording, without its ``trigger_index`` column where the recording had no
    trigger (``trigger_source`` "none": ``record --frames`` counts that column from its first frame, which
    the tab would show as "trigger +5" and take as the trigger's time)."""
    from app.files.imageio import attr_text

    names = () if table is None else (table.dtype.names or ())
    if "trigger_index" not in names or attr_text(attrs, "trigger_source") != "none":
        return table
    from numpy.lib import recfunctions

    return recfunctions.drop_fields(table, "trigger_index", usemask=False)


def table_times_s(table) -> Tuple[Optional[np.ndarray], str]:
    """Each recorded frame's time (s) from the trigger frame (from the first frame where the trigger frame is
    not in the file), from the camera's timestamps (the host's where the camera gave none); ``(None, "")``
    where the file's frame table has no timestamps."""
    names = () if table is None else (table.dtype.names or ())
    if table is None or len(table) == 0 or "host_timestamp_ns" not in names:
        return None, ""
    ns = np.asarray(table["host_timestamp_ns"], np.int64)
    if "device_timestamp_ns" in names:
        device = np.asarray(table["device_timestamp_ns"], np.int64)
        if np.all(device >= 0):
            ns = device
    origin, name = 0, "first frame"
    if "trigger_index" in names:
        at = np.flatnonzero(np.asarray(table["trigger_index"]) == 0)
        if at.size:
            origin, name = int(at[0]), "trigger"
    return (ns - ns[origin]) * 1e-9, name


def lost_before(table) -> Optional[np.ndarray]:
    """Camera frames lost just before each recorded frame (frame-id gaps; 0 where the ids are unknown)."""
    if table is None or "frame_id" not in (table.dtype.names or ()):
        return None
    ids = np.asarray(table["frame_id"], np.int64)
    gaps = np.zeros(ids.size, np.int64)
    if ids.size > 1:
        step = np.diff(ids) - 1
        known = (ids[1:] >= 0) & (ids[:-1] >= 0)
        gaps[1:] = np.where(known & (step > 0), step, 0)
    return gaps


def recording_notes(attrs, table, n_frames: int) -> list:
    """What the Replay tab says about a recording beside its name: frames lost (camera frame-id gaps), a
    recording that ended before the trigger or early (``complete`` 0), and the error it ended with."""
    notes = []
    gaps = lost_before(table)
    if gaps is not None and gaps.sum():
        at = np.flatnonzero(gaps)
        notes.append(f"{int(gaps.sum())} camera frame(s) LOST, before frame(s) "
                     + ", ".join(str(int(i) + 1) for i in at[:8]) + (" …" if at.size > 8 else ""))
    from app.files.imageio import pre_trigger_span  # what `process` says of such a recording too

    if n_frames and pre_trigger_span(table) is not None:
        notes.append(f"stopped BEFORE the trigger: only the {n_frames} frame(s) before it, no trigger frame")
    if "complete" in attrs and not int(attrs["complete"]):
        error = attrs.get("error", "")
        error = error.decode() if isinstance(error, bytes) else str(error)
        notes.append("INCOMPLETE recording" + (f": {error}" if error else ""))
    return notes


def height_mark(slider_index: int, shown_index: Optional[int], failed_index: Optional[int] = None
                ) -> Optional[str]:
    """What the Replay tab's height map says when it is not of the frame on the slider (None: it is):
    the frame it is of, and whether the slider's frame is being measured or could not be."""
    if shown_index is None or shown_index == slider_index:
        return None
    why = "could not be measured" if failed_index == slider_index else "is being measured"
    return f"heights of frame {shown_index + 1}; frame {slider_index + 1} {why}"


def height_title(grid: str, shape) -> str:
    """The Replay tab's height map's title for a result on ``grid`` of ``shape``: the live grid's coarser samples
    (while the slider moves) or every pixel, as ``tirdeflect process`` and the export measure the frame."""
    if grid == "full":
        return "Height, every pixel (as exported)"
    return f"Height, live grid {shape[1]} x {shape[0]} (every pixel once the slider rests)"


def short_error(error: str, words: int = 8) -> str:
    """A few words of why a frame could not be measured, for a map too small for all of them: ``error`` up to
    its first ``:``, ``;`` or ``(`` and at most ``words`` words ("the frame's pattern does not match the
    reference" of "the frame's pattern does not match the reference: measured period about 4.9 px ...")."""
    head = re.split(r"[:;(]", str(error), maxsplit=1)[0].split()
    return " ".join(head[:words]) + (" …" if len(head) > words else "")


@dataclasses.dataclass
class ReplayMessage:
    """What the Replay tab's message says: what was said of the open file (what it says of itself: frames lost,
    stopped before the trigger; why there are no heights; an export's progress or summary) and, after it, why
    the frame on the slider could not be measured (in full: its map has room for a few words only)."""

    said: str = ""
    #: whether what was said is a warning (drawn red)
    warns: bool = False
    #: why the last frame measured could not be, and which frame (0-based); "" while it was measured
    frame_error: str = ""
    frame_index: Optional[int] = None

    def say(self, text: str, warns: bool = False) -> None:
        self.said, self.warns = str(text), bool(warns)

    def frame_measured(self, index: int, error: str = "") -> None:
        """The frame ``index`` was measured (``error`` "") or could not be (why)."""
        self.frame_index, self.frame_error = int(index), str(error)

    @property
    def text(self) -> str:
        frame = (f"frame {self.frame_index + 1} could not be measured: {self.frame_error}"
                 if self.frame_error and self.frame_index is not None else "")
        return "\n".join(part for part in (self.said, frame) if part)

    @property
    def red(self) -> bool:
        return self.warns or bool(self.frame_error)
