"""Snapshot of the live window: a PNG of what is on screen and the maps behind it (HDF5, with metadata).

``<folder>/snapshot-YYYYmmdd-HHMMSS[-k].png`` and ``.h5`` beside it. The HDF5 file holds the maps of one
frame (the one whose height map is on screen) on the worker's grid, in physical units:

======================  ===================  ==========================================================
``/height``             (rows, cols) float32 surface height, mm, NaN where masked
``/slope_x, /slope_y``  (rows, cols) float32 dh/dx, dh/dy (dimensionless)
``/displacement``       (2, rows, cols)      apparent pattern displacement (u_x, u_y), camera px
``/valid``              (rows, cols) uint8   1 measured, 0 masked
``/x_mm, /y_mm``        (cols,), (rows,)     surface coordinates of the columns and rows, mm
``/raw``                (rows, cols)         the camera frame these maps come from (unscaled counts)
======================  ===================  ==========================================================

Root attributes: ``frame_id`` (the window's frame number), ``host_timestamp_ns``,
``created_utc``, ``software_version``, ``camera_id``, ``geometry_toml``, ``reference``,
``paused``, ``stale`` (why the maps were marked stale, "" if live) and, per map,
``colour_levels.height``, ``colour_levels.displacement``, ``colour_levels.slope_x``,
``colour_levels.slope_y``: ``[low, high]`` of the colour range on screen, in ``colour_units.<map>``.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

__all__ = ["write_snapshot"]


def _free_name(folder: Path) -> Path:
    stem = time.strftime("snapshot-%Y%m%d-%H%M%S")
    base, k = folder / stem, 1
    while base.with_suffix(".png").exists() or base.with_suffix(".h5").exists():
        k += 1
        base = folder / f"{stem}-{k}"
    return base


def write_snapshot(folder, window_image, processed, meta: dict):
    """Write ``window_image`` (a QImage) as PNG and ``processed`` (a worker ``Processed``) as HDF5.

    Parameters
    ----------
    folder : path-like
        Created if missing.
    window_image : QtGui.QImage
        The window as drawn.
    processed : app.capture.worker.Processed or None
        The result on screen; None (no maps yet): the HDF5 file holds the metadata only.
    meta : dict
        Extra root attributes (camera id, geometry TOML, colour levels ...).

    Returns
    -------
    (str, str)
        Paths of the PNG and the HDF5 file.
    """
    import h5py

    from app import version
    from app.batch.writer import set_attrs, utc_now
    from app.batch.writer import flatten_attrs  # one flattening of nested metadata for every HDF5 file

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    base = _free_name(folder)
    png, h5 = base.with_suffix(".png"), base.with_suffix(".h5")
    if not window_image.save(str(png), "PNG"):
        raise OSError(f"could not write {png} (disk full or no permission?)")
    attrs = {"software": "tirdeflect", "software_version": version(), "created_utc": utc_now(),
             "description": "maps of one frame as shown in the live window (tirdeflect snapshot)"}
    attrs.update(flatten_attrs(meta))
    gz = dict(compression="gzip", shuffle=True)
    with h5py.File(h5, "x") as f:
        if processed is not None and processed.result is not None:
            r = processed.result
            attrs["frame_id"] = int(processed.seq)
            attrs["host_timestamp_ns"] = int(processed.host_timestamp_ns or -1)
            f.create_dataset("height", data=np.asarray(r.height, np.float32), **gz).attrs["units"] = "mm"
            f.create_dataset("slope_x", data=np.asarray(r.slope_x, np.float32), **gz).attrs["units"] = "1 (dh/dx)"
            f.create_dataset("slope_y", data=np.asarray(r.slope_y, np.float32), **gz).attrs["units"] = "1 (dh/dy)"
            f.create_dataset("displacement", data=np.asarray(r.displacement, np.float32),
                             **gz).attrs["units"] = "camera px (u_x, u_y)"
            f.create_dataset("valid", data=np.asarray(r.valid, np.uint8), **gz)
            f.create_dataset("x_mm", data=np.asarray(r.x_mm, np.float64)).attrs["units"] = "mm"
            f.create_dataset("y_mm", data=np.asarray(r.y_mm, np.float64)).attrs["units"] = "mm"
            if processed.image is not None:
                f.create_dataset("raw", data=np.asarray(processed.image), **gz).attrs["units"] = "counts"
        else:
            attrs["frame_id"] = -1
            attrs["note"] = "no maps on screen yet (no reference, or nothing measured): metadata only"
        set_attrs(f, attrs)
    return os.fspath(png), os.fspath(h5)
