"""Processed heights against the true heights of ``tirdeflect simulate``."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from processing.errors import (
    ShapeMismatchError,
    TirdeflectError,
)

__all__ = ["Comparison", "compare_heights", "null_mode", "resolve_truth"]

#: what to give as the truth, for the messages that refuse a file
TRUTH_REMEDY = ("give the folder that `tirdeflect simulate --out DIR` wrote (DIR), or its DIR/heights.h5 "
                "(tirdeflect compare OUT.h5 DIR)")
#: what to give as the processed file
OUTPUT_REMEDY = "give the OUT.h5 that `tirdeflect process ... --out OUT.h5` wrote (tirdeflect compare OUT.h5 DIR)"


def null_mode(geometry, shape) -> np.ndarray:
    """The heights' null mode on the pixel grid of ``shape`` (the height solver's, ``exp(-Phi)``:
    ``exp(-T y / H)`` for TIR, a constant for FS-SS): what no displacement shows (notes.md)."""
    from processing.height import solver_for

    rows, cols = shape
    return solver_for(geometry, np.arange(rows, dtype=np.float64), np.arange(cols, dtype=np.float64),
                      (rows, cols)).null


def _pinned(h, n, r):
    """``h`` less its least-squares multiple of the null mode ``n`` on the samples ``r``: what
    the pin of :mod:`processing.height` does to the heights (:func:`processing.pin.null_mode_offset`)."""
    from processing.pin import null_mode_offset

    return h - null_mode_offset(h, n, r) * n


@dataclasses.dataclass
class Comparison:
    """What :func:`compare_heights` found.

    ``frames``: one dict per compared frame (see :func:`compare_heights`); ``skipped``: one dict
    per output frame that could not be compared (``frame`` the truth's index, ``output_frame``,
    ``source``, ``reason``: the output marks it invalid, with its status and reason, or it has
    no valid height in the compared interior); ``missing``: the truth's frames the output does
    not hold; ``truth_frames``: how many the truth holds; ``stopped``: how the run ended when it
    wrote fewer frames than it selected (its ``status``), else "".
    """

    frames: list
    skipped: list
    missing: list
    truth_frames: int
    stopped: str = ""

    @property
    def worst(self):
        """The compared frame with the largest relative RMS error, or None when none was compared."""
        return max(self.frames, key=lambda r: r["rel_rms"]) if self.frames else None


def resolve_truth(path) -> str:
    """The truth file that ``path`` names: itself, or the ``heights.h5`` in the folder
    ``tirdeflect simulate`` wrote; a folder without one is refused with what to give."""
    p = Path(path)
    if p.is_dir():
        if (p / "heights.h5").is_file():
            return str(p / "heights.h5")
        raise TirdeflectError(f"the truth {str(path)!r} is a folder without heights.h5; {TRUTH_REMEDY}")
    return str(path)


def _open(path, what: str, remedy: str):
    """``path`` open for reading as HDF5; a file that is no HDF5 (an image, a TOML) is refused
    naming it and what to give instead (HDF5 said only "file signature not found")."""
    import h5py

    from app.files.imageio import h5_open_error

    if not h5py.is_hdf5(path):
        kind = f" (a {Path(path).suffix[1:].upper()} file?)" if Path(path).suffix.lower() not in ("", ".h5") else ""
        raise TirdeflectError(f"the {what} {str(path)!r} is not an HDF5 file{kind}; {remedy}")
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise h5_open_error(Path(path), exc, what=what) from exc


def _strings(f, name: str, n: int) -> list:
    """The first ``n`` strings of the 1-D dataset ``name`` of ``f``, or ``n`` empty ones."""
    if name not in f:
        return [""] * n
    return [s.decode("utf-8", "replace") if isinstance(s, bytes) else str(s) for s in f[name][:n]]


def _read_output(path) -> dict:
    """The parts of a ``tirdeflect process`` output that compare needs; a file that is not one
    (the truth given first, a recording) is refused with what to give."""
    from processing import Geometry

    with _open(path, "processed file", OUTPUT_REMEDY) as f:
        if "frame_file" in f and "frame_index" not in f:
            raise TirdeflectError(f"{str(path)!r} is the truth written by tirdeflect simulate, not processed "
                                  f"heights: the arguments are swapped? {OUTPUT_REMEDY}")
        if "height" not in f or "frame_index" not in f or "geometry_toml" not in f.attrs:
            raise TirdeflectError(f"{str(path)!r} holds no processed heights (/height, /frame_index); "
                                  f"is it a tirdeflect process output? {OUTPUT_REMEDY}")
        if f.attrs.get("grid", "full") != "full":
            raise TirdeflectError(f"{str(path)!r} is on the decimated grid; process with --grid full to compare")
        n = int(f.attrs.get("frames_done", f["height"].shape[0]))
        out = dict(est=f["height"][:n].astype(np.float64), index=f["frame_index"][:n].astype(np.int64),
                   geometry=Geometry.from_toml_text(str(f.attrs["geometry_toml"])),
                   source=_strings(f, "source", n), status_text=_strings(f, "frame_status_text", n),
                   status=(f["frame_status"][:n].astype(np.int64) if "frame_status" in f
                           else np.zeros(n, np.int64)),
                   source_index=(f["source_index"][:n] if "source_index" in f else np.zeros(n, np.int64)),
                   shift_um=np.full(n, np.nan), pin_region=None, stopped="")
        expected = int(f.attrs.get("frames_expected", n))
        if n < expected:
            out["stopped"] = f"the run wrote {n} of the {expected} frame(s) it selected ({f.attrs.get('status', '')})"
        if "pin_status" in f and "shift_effect_um" in (f["pin_status"].dtype.names or ()):
            st = f["pin_status"][:n]
            out["shift_um"] = np.where(st["shift_removed"] != 0, np.nan, st["shift_effect_um"]).astype(np.float64)
        out["turn_mrad"] = np.full(n, np.nan)
        if "turn_flagged" in f and "turn_mrad" in f and str(f.attrs.get("turn_removal", "none")) == "none":
            # a turn the run flagged and left in the heights: its saddle is part of the error, not the processing's
            out["turn_mrad"] = np.where(f["turn_flagged"][:n] != 0, f["turn_mrad"][:n], np.nan).astype(np.float64)
        if "pin_region" in f:
            ds = f["pin_region"]
            out["pin_region"] = (ds[()].astype(bool), ds.attrs["rows_px"], ds.attrs["cols_px"])
    return out


def _read_truth(path) -> tuple:
    """(heights, frame file names) of the ``heights.h5`` of ``tirdeflect simulate``; a process
    output given as the truth is refused (it compared with itself: 0 % error)."""
    with _open(path, "truth", TRUTH_REMEDY) as f:
        if "frame_index" in f and "frames_done" in f.attrs:
            raise TirdeflectError(f"the truth {str(path)!r} is an output of tirdeflect process, not the true "
                                  f"heights; {TRUTH_REMEDY}")
        if "height" not in f:
            raise TirdeflectError(f"{str(path)!r} holds no /height; {TRUTH_REMEDY}")
        truth = f["height"][()].astype(np.float64)
        names = _strings(f, "frame_file", truth.shape[0]) if "frame_file" in f else []
    return truth, names


def _truth_index(out: dict, names: list, truth_count: int, out_path) -> np.ndarray:
    """The truth's frame for each output frame: the one of the same file name where the output's
    source is a frame file of the data set (``frame_0002.tif`` alone, or the frames after a
    reference that was ``frame_0000.tif``, are truth frames 2, 1...), else ``/frame_index``.
    An output frame beyond the truth's frames is refused: they are not of one data set."""
    index = out["index"].copy()
    position = {name: j for j, name in enumerate(names) if name}
    for k, source in enumerate(out["source"]):
        j = position.get(Path(source).name) if source and int(out["source_index"][k]) == 0 else None
        if j is not None:
            index[k] = j
    beyond = np.flatnonzero(index >= truth_count)
    if beyond.size:
        k = int(beyond[0])
        raise TirdeflectError(
            f"the output {str(out_path)!r} holds {len(index)} frame(s), frame {k} being input frame {int(index[k])}, "
            f"but the truth holds only {truth_count} frame(s) (0 to {truth_count - 1}): they are not of one data set; "
            f"compare the output of `tirdeflect process` on the frames of the data set that simulate wrote")
    return index


def _skip_reason(out: dict, k: int) -> str:
    """Why output frame ``k`` cannot be compared ("" if it can): the output marks it invalid."""
    code = int(out["status"][k])
    if code == 0:
        return ""
    from app.batch.frame_status import FrameStatus

    try:
        label = FrameStatus(code).label
    except ValueError:
        label = f"status {code}"
    text = out["status_text"][k]
    return f"the output marks it invalid ({label}{': ' + text if text else ''})"


def _region(out: dict, geometry, rows: int, cols: int) -> np.ndarray:
    """The pin samples on the pixel grid: the output's ``/pin_region`` (each pixel takes the
    membership of its nearest grid sample), else the geometry's reference region."""
    if out["pin_region"] is None:
        return geometry.reference_mask(np.arange(rows), np.arange(cols), (rows, cols))
    region, rows_px, cols_px = out["pin_region"]
    ri = np.abs(np.arange(rows)[:, None] - np.asarray(rows_px)[None, :]).argmin(axis=1)
    ci = np.abs(np.arange(cols)[:, None] - np.asarray(cols_px)[None, :]).argmin(axis=1)
    return region[np.ix_(ri, ci)]


def _frame_errors(est, truth, ref, n_mode, inner):
    """The figures of one frame (a dict without ``frame`` and ``shift_effect_um``), or the reason
    it cannot be compared (a str): no valid height in the interior, or a flat true surface."""
    finite = np.isfinite(est)
    ok = finite[inner]
    if not ok.any():
        return "no valid height in the compared interior (every sample NaN)"
    r = ref & finite  # both offsets on the same samples
    if not r.any():  # pinned by the fallback (see /pin_status): compare shapes about the mean
        r = finite
    e = _pinned(est, n_mode, r)
    t = _pinned(truth, n_mode, r)
    region_rms = float(np.sqrt(np.mean(t[r] ** 2)))
    e, t = e[inner][ok], t[inner][ok]
    rms_true = float(np.sqrt(np.mean(t ** 2)))
    if not rms_true > 0:
        return "the true surface is flat in the compared interior: no relative error to give"
    rms_err = float(np.sqrt(np.mean((e - t) ** 2)))
    return dict(rel_rms=rms_err / rms_true, rms_error_mm=rms_err, rms_true_mm=rms_true,
                scale=float(np.dot(e, t) / np.dot(t, t)), valid_fraction=float(ok.mean()),
                region_rms_mm=region_rms)


def compare_heights(out_path, truth_path, *, margin: float = 0.125) -> Comparison:
    """Per-frame errors of processed heights against simulated truth.

    Both maps are pinned alike before they are compared: each less its least-squares multiple
    of the null mode (:func:`null_mode`; for TIR ``alpha exp(-T y / H)``, the part of the
    heights no deflectometry measures, a constant for FS-SS) over the reference region, as
    :mod:`processing.height`'s pin does: the output's ``/pin_region`` (the region the heights
    were pinned on), else the geometry's, else (a region with no valid sample: the fallback
    pinned the frame) all valid samples. Removing a constant alone left a TIR frame whose
    simulated surface is not at rest on the region (travelling waves filling the frame) up to
    2.7 % off where the difference is that null mode (0.16-0.19 % without it). The comparison
    uses the interior, ``margin * size`` pixels away from each border, and the valid samples.
    Frames the output marks invalid, or without a valid height there, are skipped with their
    reason (they gave NumPy warnings and an "inf%" worst error).

    ``out_path``: ``tirdeflect process`` output on the full grid; ``truth_path``: ``heights.h5``
    from ``tirdeflect simulate`` (``/height`` in mm; :func:`resolve_truth` takes its folder);
    ``margin``: fraction of the rows/cols left out at each border.

    Returns a :class:`Comparison`; each of its ``frames`` has ``frame`` (index into the truth),
    ``rel_rms`` (RMS error / RMS true height), ``rms_error_mm``, ``rms_true_mm``, ``scale``
    (least-squares factor estimate ~ scale * truth), ``valid_fraction`` (interior),
    ``region_rms_mm`` (the pinned truth's RMS on the pin samples: 0 where the simulated surface
    is at rest there), ``shift_effect_um`` (``/pin_status``: the RMS a shift of the whole
    pattern since the reference put into the heights, part of the error; NaN where none was
    flagged or it was taken out), ``turn_mrad`` (``/turn_mrad`` where the run flagged the frame's turn and left
    it in the heights, its saddle part of the error; else NaN).
    """
    out = _read_output(out_path)
    truth, names = _read_truth(truth_path)
    est = out["est"]
    if est.shape[1:] != truth.shape[1:]:
        raise ShapeMismatchError(
            f"processed heights are {est.shape[1:]} but the truth is {truth.shape[1:]}; "
            f"compare the output of the same data set")
    index = _truth_index(out, names, truth.shape[0], out_path)
    rows, cols = truth.shape[1:]
    ref = _region(out, out["geometry"], rows, cols)
    n_mode = null_mode(out["geometry"], (rows, cols))
    mr, mc = int(round(margin * rows)), int(round(margin * cols))
    inner = (slice(mr, rows - mr), slice(mc, cols - mc))
    result = Comparison([], [], sorted(set(range(truth.shape[0])) - set(index.tolist())), truth.shape[0],
                        out["stopped"])
    for k in range(len(index)):
        j = int(index[k])
        figures = _skip_reason(out, k) or _frame_errors(est[k], truth[j], ref, n_mode, inner)
        if isinstance(figures, str):
            result.skipped.append(dict(frame=j, output_frame=k, source=out["source"][k], reason=figures))
        else:
            result.frames.append(dict(frame=j, shift_effect_um=float(out["shift_um"][k]),
                                      turn_mrad=float(out["turn_mrad"][k]), **figures))
    return result
