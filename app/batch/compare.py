"""Processed heights against the true heights of ``tirdeflect simulate``."""

from __future__ import annotations


import numpy as np

from processing.errors import (
    ShapeMismatchError,
    TirdeflectError,
)

__all__ = ["compare_heights", "null_mode"]


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


def compare_heights(out_path, truth_path, *, margin: float = 0.125) -> list:
    """Per-frame errors of processed heights against simulated truth.

    Both maps are pinned alike before they are compared: each less its
    least-squares multiple of the null mode (:func:`null_mode`; for TIR
    ``alpha exp(-T y / H)``, the part of the heights no deflectometry measures,
    a constant for FS-SS) over the reference region, as
    :mod:`processing.height`'s pin does: the output's ``/pin_region`` (the
    region the heights were pinned on), else the geometry's, else (a region
    with no valid sample: the fallback pinned the frame) all valid samples.
    Removing a constant alone left a TIR frame whose simulated surface is not
    at rest on the region (travelling waves filling the frame) up to 2.7 %
    off where the difference is that null mode (0.16-0.19 % without it). The
    comparison uses the interior, ``margin * size`` pixels away from each
    border, and the valid samples.

    Parameters
    ----------
    out_path : path-like
        ``tirdeflect process`` output on the full grid.
    truth_path : path-like
        ``heights.h5`` from ``tirdeflect simulate`` (``/height`` in mm).
    margin : float
        Fraction of the rows/cols left out at each border.

    Returns
    -------
    list of dict
        One per output frame: ``frame`` (index into the truth), ``rel_rms``
        (RMS error / RMS true height), ``rms_error_mm``, ``rms_true_mm``,
        ``scale`` (least-squares factor estimate ~ scale * truth),
        ``valid_fraction`` (interior), ``region_rms_mm`` (the pinned truth's RMS on the
        pin samples: 0 where the simulated surface is at rest there), ``shift_effect_um``
        (``/pin_status``: the RMS a shift of the whole pattern since the reference put into the
        heights, part of the error; NaN where none was flagged or it was taken out).
    """
    import h5py
    from processing import Geometry

    with h5py.File(out_path, "r") as f:
        if "height" not in f:
            raise TirdeflectError(f"{str(out_path)!r} holds no /height; is it a tirdeflect process output?")
        if f.attrs.get("grid", "full") != "full":
            raise TirdeflectError(f"{str(out_path)!r} is on the decimated grid; process with --grid full to compare")
        n = int(f.attrs.get("frames_done", f["height"].shape[0]))
        est = f["height"][:n].astype(np.float64)
        index = f["frame_index"][:n]
        geometry = Geometry.from_toml_text(str(f.attrs["geometry_toml"]))
        shift_um = np.full(n, np.nan)
        if "pin_status" in f and "shift_effect_um" in (f["pin_status"].dtype.names or ()):
            st = f["pin_status"][:n]
            shift_um = np.where(st["shift_removed"] != 0, np.nan, st["shift_effect_um"]).astype(np.float64)
        pin_region = None
        if "pin_region" in f:
            ds = f["pin_region"]
            pin_region = (ds[()].astype(bool), ds.attrs["rows_px"], ds.attrs["cols_px"])
    with h5py.File(truth_path, "r") as f:
        if "height" not in f:
            raise TirdeflectError(f"{str(truth_path)!r} holds no /height; give the heights.h5 of tirdeflect simulate")
        truth = f["height"][()].astype(np.float64)
    if est.shape[1:] != truth.shape[1:]:
        raise ShapeMismatchError(
            f"processed heights are {est.shape[1:]} but the truth is {truth.shape[1:]}; "
            f"compare the output of the same data set")
    rows, cols = truth.shape[1:]
    if pin_region is not None:
        # every pixel takes the region membership of its nearest grid sample
        region, rows_px, cols_px = pin_region
        ri = np.abs(np.arange(rows)[:, None] - np.asarray(rows_px)[None, :]).argmin(axis=1)
        ci = np.abs(np.arange(cols)[:, None] - np.asarray(cols_px)[None, :]).argmin(axis=1)
        ref = region[np.ix_(ri, ci)]
    else:
        ref = geometry.reference_mask(np.arange(rows), np.arange(cols), (rows, cols))
    n_mode = null_mode(geometry, (rows, cols))
    mr, mc = int(round(margin * rows)), int(round(margin * cols))
    inner = (slice(mr, rows - mr), slice(mc, cols - mc))
    report = []
    for k in range(n):
        j = int(index[k])
        if j >= truth.shape[0]:
            raise TirdeflectError(f"output frame {k} is input frame {j} but the truth has {truth.shape[0]} frames")
        r = ref & np.isfinite(est[k])  # both offsets on the same samples
        if not r.any():  # pinned by the fallback (see /pin_status): compare shapes about the mean
            r = np.isfinite(est[k])
        e = _pinned(est[k], n_mode, r)
        t = _pinned(truth[j], n_mode, r)
        region_rms = float(np.sqrt(np.mean(t[r] ** 2)))
        e, t = e[inner], t[inner]
        ok = np.isfinite(e)
        err = e[ok] - t[ok]
        rms_true = float(np.sqrt(np.mean(t[ok] ** 2))) if ok.any() else float("nan")
        rms_err = float(np.sqrt(np.mean(err ** 2))) if ok.any() else float("nan")
        scale = float(np.dot(e[ok], t[ok]) / np.dot(t[ok], t[ok])) if ok.any() and rms_true > 0 else float("nan")
        report.append(dict(frame=j, rel_rms=rms_err / rms_true if rms_true > 0 else float("nan"),
                           rms_error_mm=rms_err, rms_true_mm=rms_true, scale=scale,
                           valid_fraction=float(ok.mean()), region_rms_mm=region_rms,
                           shift_effect_um=float(shift_um[k])))
    return report

