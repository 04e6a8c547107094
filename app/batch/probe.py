"""Virtual probes: height time series at points of OUT.h5 (``tirdeflect probe``).

A probe is a wave gauge you can move after the experiment: the height at a
surface point ``(x_mm, y_mm)``, bilinearly interpolated between the four
samples around it by :mod:`processing.probe` (the live window's probes use the
same rule; NaN when any of them is invalid), one value per processed frame, with the frame's time.
The samples are found in ``/surface_x_mm``, ``/surface_y_mm`` where OUT.h5 has them (a keystoned
grid: a TIR camera at a finite distance), else in ``/x_mm``, ``/y_mm``.
"""

from __future__ import annotations

import csv
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.batch.frame_status import FrameStatus
from app.files import h5safe, imageio
from processing.errors import TirdeflectError
from processing.probe import probe_cell, probe_cell_2d, sample_cell

__all__ = ["ProbeSeries", "probe_series", "frame_times", "write_probes", "open_output", "partial_note",
           "trigger_note", "NO_TRIGGER_INDEX"]

log = logging.getLogger(__name__)


@dataclass
class ProbeSeries:
    """Height time series at points.

    Attributes
    ----------
    x_mm, y_mm : numpy.ndarray
        ``(k,)`` probe positions on the surface, mm (image frame, docs/architecture.md).
    frame_index : numpy.ndarray
        ``(n,)`` input-sequence index of each processed frame.
    time_s : numpy.ndarray
        ``(n,)`` seconds; NaN where unknown.
    time_source : str
        Where the times come from (``"/time_s"``, ``"/device_timestamp_ns"``, ``"--fps"``, ``"none"``).
    height_mm : numpy.ndarray
        ``(n, k)`` height at each probe, mm; NaN where not measured.
    trigger_index : numpy.ndarray or None
        ``(n,)`` frames from the trigger frame (0; negative before it) of a triggered
        recording's frames, :data:`NO_TRIGGER_INDEX` where unknown; None when no frame has one.
    """

    x_mm: np.ndarray
    y_mm: np.ndarray
    frame_index: np.ndarray
    time_s: np.ndarray
    time_source: str
    height_mm: np.ndarray
    trigger_index: np.ndarray | None = None


#: ``/trigger_index`` of a frame whose source has none (image files): INT64_MIN, as OUT.h5 stores it
NO_TRIGGER_INDEX = int(np.iinfo(np.int64).min)


def open_output(path):
    """Open a ``tirdeflect process`` output for reading, with a one-line error otherwise."""
    import h5py

    p = Path(path)
    if not p.is_file():
        raise TirdeflectError(f"{str(p)!r} does not exist or is not a file; give the OUT.h5 of "
                              f"`tirdeflect process`")
    try:
        f = h5py.File(p, "r")
    except OSError as exc:
        raise imageio.h5_open_error(p, exc, what="output of `tirdeflect process`") from exc
    try:
        if "height" not in f or "x_mm" not in f:
            names = ", ".join(sorted(f.keys())) or "nothing"
            raise TirdeflectError(f"{str(p)!r} holds no /height (it holds {names}); give the output "
                                  f"of `tirdeflect process`, not a recording")
        note = partial_note(f, p)
    except (OSError, RuntimeError, KeyError) as exc:
        f.close()
        raise imageio.h5_damaged(p, "its HDF5 structure", exc) from exc
    except BaseException:
        f.close()
        raise
    if note:
        log.warning("%s", note)
    return f


def partial_note(f, path) -> str:
    """What to know of an opened OUT.h5 that is not a finished run's output (its
    ``status`` is not ``complete...``: a run killed, interrupted or failed, whose
    ``NAME.partial.h5`` holds the frames done so far); "" for a finished one."""
    status = str(f.attrs.get("status", ""))
    if status.startswith("complete"):
        return ""
    done, expected = frames_done(f), int(f.attrs.get("frames_expected", -1))
    of = f" of the {expected} expected" if expected >= 0 else ""
    why = ("the run was killed before it ended" if status in ("", "running")
           else f"the run ended as {status!r}")
    step = int(f.attrs.get("step", 1) or 1)
    resume = (int(f["frame_index"][done - 1]) + step) if done else int(f.attrs.get("first", 0))
    return (f"{Path(path).name} is a partial output ({why}): it holds {done}{of} frames "
            f"(frames_done); what follows covers only those: process the rest with "
            f"`tirdeflect process ... --first {resume}`")


def frames_done(f) -> int:
    return int(min(f.attrs.get("frames_done", f["height"].shape[0]), f["height"].shape[0]))


def frame_times(f, n: int, fps: float | None = None) -> tuple:
    """Times (s) of the first ``n`` frames of an opened OUT.h5, and where they came from.

    The input files' own times (``/time_s``: trigger-relative for MRAW/CINE,
    stream time for video, recording time for HDF5; NaN for a frame that could not
    be read, whose heights are NaN too), else the camera clock
    (``/device_timestamp_ns``, relative to the first processed frame), else
    ``frame_index / fps`` when ``fps`` is given, else NaN.
    """
    if "time_s" in f:
        t = np.asarray(f["time_s"][:n], dtype=np.float64)
        read = (np.asarray(f["frame_status"][:n]) != FrameStatus.UNREADABLE if "frame_status" in f
                else np.ones(n, dtype=bool))
        # every frame read has its time (an unreadable one, of a cut video say, has none)
        if n and np.any(read) and np.all(np.isfinite(t[read])):
            return t, "/time_s"
    for name in ("device_timestamp_ns", "host_timestamp_ns"):
        if name in f:
            ns = np.asarray(f[name][:n], dtype=np.int64)
            if n and np.all(ns >= 0):
                return (ns - ns[0]) * 1e-9, f"/{name}"
    if fps:
        return np.asarray(f["frame_index"][:n], dtype=np.float64) / float(fps), "--fps"
    return np.full(n, np.nan), "none"


def probe_series(path, points_mm, *, fps: float | None = None) -> ProbeSeries:
    """Heights at ``points_mm`` (sequence of ``(x_mm, y_mm)``) over every frame of OUT.h5.

    Raises
    ------
    TirdeflectError
        Not an output file, no frames, or a point outside the field.
    """
    points = [(float(x), float(y)) for x, y in points_mm]
    if not points:
        raise TirdeflectError("no probe point given; add --at X_MM,Y_MM")
    with open_output(path) as f:
        n = frames_done(f)
        if n == 0:
            raise TirdeflectError(f"{str(path)!r} holds no processed frame (frames_done = 0)")
        height = f["height"]
        if "surface_x_mm" in f and "surface_y_mm" in f:  # keystoned: each sample's own position
            surface_x, surface_y = f["surface_x_mm"][()], f["surface_y_mm"][()]
            cells = [probe_cell_2d(surface_x, surface_y, x, y) for x, y in points]
        else:
            x_mm, y_mm = f["x_mm"][()], f["y_mm"][()]
            cells = [probe_cell(x_mm, y_mm, x, y) for x, y in points]
        out = np.empty((n, len(points)))
        r_lo = min(cell[0] for cell in cells)
        r_hi = max(cell[0] for cell in cells) + 2
        for k in range(n):
            band = height[k, r_lo:r_hi, :]  # one read per frame for all probes
            for j, cell in enumerate(cells):
                out[k, j] = sample_cell(band, cell, row_offset=r_lo)
        times, source = frame_times(f, n, fps)
        index = np.asarray(f["frame_index"][:n], dtype=np.int64)
        trigger = (np.asarray(f["trigger_index"][:n], dtype=np.int64) if "trigger_index" in f
                   else np.full(n, NO_TRIGGER_INDEX, dtype=np.int64))
    return ProbeSeries(np.array([p[0] for p in points]), np.array([p[1] for p in points]),
                       index, times, source, out,
                       trigger if np.any(trigger != NO_TRIGGER_INDEX) else None)


def trigger_note(series: ProbeSeries) -> str:
    """Where the trigger frame lies in the series, as a sentence (time_s counts from each
    recording's first frame, not from its trigger); "" where no frame has a trigger index."""
    t = series.trigger_index
    if t is None:
        return ""
    at = np.flatnonzero(t == 0)
    if len(at):
        k = at[0]
        return (f"the trigger frame (trigger_index 0) is frame {int(series.frame_index[k])}, at time_s "
                f"{series.time_s[k]:.9g} s (times count from the recording's first frame); "
                f"trigger_index is in the CSV and the HDF5 file")
    known = t[t != NO_TRIGGER_INDEX]
    return (f"no processed frame is a trigger frame: trigger_index runs from {int(known.min())} to "
            f"{int(known.max())}" + (" (every frame before the trigger: the recording stopped before it "
                                     "came, or --last ended before it)" if known.max() < 0 else "")
            + "; trigger_index is in the CSV and the HDF5 file")


def write_probes(series: ProbeSeries, csv_path, h5_path=None, *, source: str = "",
                 overwrite: bool = False) -> list:
    """Write the series as CSV (one row per frame) and, if ``h5_path``, as HDF5 datasets.

    Returns the paths written. An output that cannot be created is refused before either is
    written (:func:`app.files.h5safe.check_creatable`), naming it and the option to change.
    """
    written = []
    targets = [Path(csv_path)] + ([Path(h5_path)] if h5_path else [])
    for p in targets:
        if p.exists() and not overwrite:
            raise TirdeflectError(f"{str(p)!r} already exists; choose another name or add --overwrite")
        if not (p.parent if str(p.parent) else Path(".")).is_dir():
            raise TirdeflectError(f"the folder of {str(p)!r} does not exist; create it first")
    for p, option in zip(targets, ("--out", "--h5")):  # both, before the CSV is written
        h5safe.check_creatable(p, f"choose another {option} (a folder you can write to)")
    names = [f"height_mm@x={x:g},y={y:g}" for x, y in zip(series.x_mm, series.y_mm)]
    trigger = series.trigger_index
    with open(targets[0], "w", newline="", encoding="utf-8") as fh:
        fh.write(f"# tirdeflect probe of {source}: height in mm at surface points (x_mm, y_mm); "
                 f"time in s from {series.time_source}\n")
        w = csv.writer(fh)
        w.writerow(["frame_index", "time_s", *(["trigger_index"] if trigger is not None else []), *names])
        for k in range(len(series.frame_index)):
            tk = ([] if trigger is None else ["" if trigger[k] == NO_TRIGGER_INDEX else int(trigger[k])])
            w.writerow([int(series.frame_index[k]), f"{series.time_s[k]:.9g}", *tk,
                        *(f"{v:.9g}" for v in series.height_mm[k])])
    written.append(targets[0])
    if h5_path:
        with h5safe.create_h5(targets[1], "w", remedy="choose another --h5 (a folder you can write to)") as f:
            ds = f.create_dataset("height_mm", data=series.height_mm.astype(np.float64))
            ds.attrs["description"] = "height at each probe (column) for each frame (row), mm; NaN unmeasured"
            f.create_dataset("time_s", data=series.time_s).attrs["units"] = "s"
            f["time_s"].attrs["source"] = series.time_source
            f.create_dataset("frame_index", data=series.frame_index)
            if trigger is not None:
                ds = f.create_dataset("trigger_index", data=np.asarray(trigger, dtype=np.int64))
                ds.attrs["description"] = ("frames from the trigger frame (0; negative before it); "
                                           f"{NO_TRIGGER_INDEX} where the frame's source has none")
            f.create_dataset("x_mm", data=series.x_mm).attrs["units"] = "mm"
            f.create_dataset("y_mm", data=series.y_mm).attrs["units"] = "mm"
            f.attrs["source"] = source
        written.append(targets[1])
    return written
