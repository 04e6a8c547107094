"""OUT.h5 of ``tirdeflect process``: one frame at a time, flushed at least every
:data:`FLUSH_INTERVAL_S`, valid up to ``frames_done`` after any failure (layout:
docs/output-format.md; room, space reserve and superblock repair: app.files.h5safe)."""

from __future__ import annotations

import dataclasses
import functools
import datetime as _dt
import logging
import os
import time
import zlib
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from app.files import imageio
from app.files import h5safe
from app.files.h5safe import DiskFullError, Preallocation, SpaceReserve, repair_eof, room_bytes
from processing.errors import (
    ShapeMismatchError,
    TirdeflectError,
)
from processing.turn import TURN_MAX_MRAD, TURN_MIN_SIGNIFICANCE

__all__ = ["ResultWriter", "OutputFrame", "output_frame", "OutputExistsError", "DiskFullError",
           "OUTPUT_FORMAT_VERSION", "FLUSH_INTERVAL_S", "GZIP_LEVEL", "MAP_BYTES_PER_SAMPLE",
           "check_output", "check_not_an_input", "is_same_file", "partial_path", "publish", "set_attrs", "carrier_attrs", "geometry_attrs", "utc_now",
           "flatten_attrs"]

log = logging.getLogger(__name__)

#: Version of the layout of OUT.h5 described in docs/output-format.md.
OUTPUT_FORMAT_VERSION = 1

#: ``/trigger_index`` of a frame whose source has none (image files, untriggered stacks).
TRIGGER_INDEX_UNKNOWN = np.iinfo(np.int64).min


_PIN_FIELDS = (
    ("rule", "'region': pinned on the reference region; 'nearest': too few valid samples there, "
             "pinned on the valid samples nearest it (fallback); '' unknown"),
    ("region_samples", "samples of the grid in the region"),
    ("valid_samples", "of those, valid in this frame"),
    ("needed", "valid samples the pin needs: max(16, 25 % of the region)"),
    ("used_samples", "samples the offset was measured on"),
    ("unpinned_fraction", "fraction of the valid samples dropped: their piece held no pin sample"),
    ("pieces", "connected pieces of valid samples, each pinned on its own pin samples (0: unknown): from 2 on, "
               "their heights' offsets are apart by what the surface does where each is pinned"),
    ("region_motion_px", "median displacement on the pin samples, px: above 0.03 in the user's reference_region, "
                         "the surface there is not at rest or the camera or the board moved since the reference "
                         "(NaN: not measured)"),
    ("frame_motion_px", "median displacement over the whole frame's valid samples, px (NaN: not measured)"),
    ("frame_motion_row_px", "its component along the rows, px"),
    ("frame_motion_col_px", "its component along the columns, px"),
    ("frame_shift_share", "share of the frame's valid samples within 0.05 px of that median, or half its length "
                          "where that is more: from 0.2 on, with the median at 0.03 px or more, the whole pattern "
                          "shifted since the reference (camera or board moved, or the water level changed)"),
    ("shift_effect_um", "where it shifted: RMS of the heights that shift alone gives (a tilt, not the surface), um"),
    ("shift_level_um", "where it shifted: the change of water level that moves the pattern so, um up (NaN: none)"),
    ("shift_removed", "1: that shift was taken out before the heights were solved (--shift-removal)"),
    ("region_scale", "the image's scale change since the reference fitted to the pin samples' displacement, a "
                     "fraction (0.002: 0.2 % larger; NaN: not measured)"),
    ("region_scale_reach_px", "how far that scale change moves the pin samples farthest from their centre, px"),
    ("region_scale_explained", "share of the pin samples' motion it explains: from 0.5 on, with the reach at "
                               "0.1 px or more, the image's scale changed (a refocus, or the camera moved along "
                               "its axis): the heights carry a curved surface that is not there"),
    ("jump", "1: the result is not continuous with the previous frame's (see reason)"),
    ("unwrap_slip_fraction", "fraction of samples where the unwrapped phase change differs by 2 pi "
                             "from the images' wrapped one"),
    ("pin_shift_um", "change of the height offset on the previous frame's pin samples, um (NaN: not comparable)"),
    ("reason", "why the frame is flagged as a jump, '' if not"),
)


def _pin_status_dtype():
    import h5py

    s = h5py.string_dtype()
    return np.dtype([("rule", s), ("region_samples", np.int32), ("valid_samples", np.int32),
                     ("needed", np.int32), ("used_samples", np.int32), ("unpinned_fraction", np.float32),
                     ("pieces", np.int32), ("region_motion_px", np.float32), ("frame_motion_px", np.float32),
                     ("frame_motion_row_px", np.float32), ("frame_motion_col_px", np.float32),
                     ("frame_shift_share", np.float32), ("shift_effect_um", np.float32), ("shift_level_um", np.float32),
                     ("shift_removed", np.uint8), ("region_scale", np.float32),
                     ("region_scale_reach_px", np.float32), ("region_scale_explained", np.float32),
                     ("jump", np.uint8), ("unwrap_slip_fraction", np.float32), ("pin_shift_um", np.float32),
                     ("reason", s)])


def _pin_status_row(result) -> np.ndarray:
    """One row of /pin_status from a Result's ``pin`` and ``series`` (either may be None)."""
    row = np.zeros((), dtype=_pin_status_dtype())
    row["rule"] = ""
    row["reason"] = ""
    row["pin_shift_um"] = np.nan
    row["unwrap_slip_fraction"] = np.nan
    shift_fields = ("frame_motion_px", "frame_motion_row_px", "frame_motion_col_px", "frame_shift_share",
                    "shift_effect_um", "shift_level_um", "region_scale", "region_scale_reach_px",
                    "region_scale_explained")
    for name in ("region_motion_px",) + shift_fields:
        row[name] = np.nan
    pin = getattr(result, "pin", None)
    if pin is not None:
        row["rule"] = pin.rule
        for name in ("region_samples", "valid_samples", "needed", "used_samples", "unpinned_fraction", "pieces",
                     "region_motion_px") + shift_fields:
            row[name] = getattr(pin, name)
        row["shift_removed"] = int(pin.shift_removed)
    series = getattr(result, "series", None)
    if series is not None:
        row["jump"] = int(series.flagged)
        row["unwrap_slip_fraction"] = series.unwrap_slip_fraction
        row["pin_shift_um"] = 1e3 * series.pin_shift_mm
        row["reason"] = series.reason
    return row


class OutputExistsError(TirdeflectError):
    """The output file exists and ``--overwrite`` was not given."""



def check_output(out: Path, overwrite: bool) -> None:
    """Refuse, before any input is read, an ``--out`` that cannot be written: a folder, an
    existing file without ``overwrite``, a folder that does not exist, or one where no file can
    be created (:func:`app.files.h5safe.check_creatable`: read-only, permission denied, ``/proc``;
    the run used to fail there only at its first write, with HDF5's own text)."""
    if out.is_dir():
        raise TirdeflectError(
            f"--out {str(out)!r} is a directory; give a file name, e.g. {str(out / 'heights.h5')!r}"
        )
    if out.exists() and not overwrite:
        raise OutputExistsError(
            f"output {str(out)!r} already exists; choose another --out or add --overwrite"
        )
    parent = out.parent if str(out.parent) else Path(".")
    if not parent.is_dir():
        raise TirdeflectError(
            f"the directory of --out {str(out)!r} does not exist; create {str(parent)!r} first"
        )
    if not os.access(parent, os.W_OK):
        raise h5safe.OutputLocationError(f"cannot write to {str(parent)!r} (permission denied); "
                                         f"choose another --out in a folder you can write to")
    h5safe.check_creatable(out, "choose another --out (a folder you can write to)")



def is_same_file(a, b) -> bool:
    """Whether paths ``a`` and ``b`` name the same file (same path, a symbolic
    link to it, or a hard link: same device and inode)."""
    if a is None or b is None:
        return False
    try:
        if os.path.samefile(a, b):
            return True
    except OSError:
        pass
    return os.path.realpath(a) == os.path.realpath(b)


def check_not_an_input(out: Path, inputs, what: str = "--out") -> None:
    """Refuse an output that is one of the ``inputs`` (same path, a link to it,
    or the same file under another name), before anything is written."""
    if not os.path.lexists(out):
        return
    for path in inputs:
        if is_same_file(out, path):
            raise TirdeflectError(
                f"{what} {str(out)!r} is the input {str(path)!r}; choose another {what}: "
                f"tirdeflect never writes over its inputs"
            )


def _attr_value(value):
    """Convert a value to something HDF5 stores as an attribute, or None to skip."""
    if value is None:
        return None
    if isinstance(value, (bool, np.bool_)):
        return np.bool_(value)
    if isinstance(value, (int, float, str, np.integer, np.floating)):
        return value
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, complex):
        return np.array([value.real, value.imag])
    try:
        arr = np.asarray(value)
    except Exception:
        return str(value)
    if arr.dtype == object:
        return str(value)
    if np.iscomplexobj(arr):
        arr = np.stack([arr.real, arr.imag], axis=-1)
    if arr.dtype.kind in "US":
        return arr.astype(str).tolist()
    return arr


def flatten_attrs(obj, prefix: str = "") -> dict:
    """Flatten a dataclass / dict / object of scalars and arrays to ``{dotted.key: value}``."""
    out: dict = {}
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        items = ((f.name, getattr(obj, f.name)) for f in dataclasses.fields(obj))
    elif isinstance(obj, dict):
        items = obj.items()
    elif hasattr(obj, "_asdict"):
        items = obj._asdict().items()
    elif hasattr(obj, "__dict__"):
        items = ((k, v) for k, v in vars(obj).items() if not k.startswith("_"))
    else:
        value = _attr_value(obj)
        if value is not None:
            out[prefix or "value"] = value
        return out
    for key, value in items:
        name = f"{prefix}.{key}" if prefix else str(key)
        if isinstance(value, dict) or (dataclasses.is_dataclass(value) and not isinstance(value, type)):
            out.update(flatten_attrs(value, name))
            continue
        if isinstance(value, (list, tuple)) and value and all(isinstance(v, (list, tuple)) for v in value):
            # e.g. fsss_layers ((thickness_mm, n), ...): a 2-D array if rectangular
            try:
                arr = np.asarray(value, dtype=float)
                out[name] = arr
                continue
            except (TypeError, ValueError):
                pass
        converted = _attr_value(value)
        if converted is not None:
            out[name] = converted
    return out


def carrier_attrs(carriers) -> dict:
    """Carrier information (periods, rotation, wavevectors...) as attributes."""
    if carriers is None:
        return {}
    attrs = flatten_attrs(carriers)
    # Properties are not dataclass fields: pick up the documented ones explicitly.
    for name in ("periods_px", "angles_deg", "rotation_deg", "wavevectors",
                 "theta_deg", "describe"):
        if name not in attrs and hasattr(carriers, name):
            try:
                value = getattr(carriers, name)
                value = _attr_value(value() if callable(value) else value)
            except Exception:
                value = None
            if value is not None:
                attrs[name] = value
    return attrs


def geometry_attrs(geometry) -> tuple[str, dict]:
    toml_text = ""
    try:
        toml_text = geometry.to_toml_text()
    except Exception as exc:  # keep processing; the flattened attrs still describe it
        log.warning("could not render the geometry as TOML (%s)", exc)
    try:
        flat = flatten_attrs(geometry.to_dict())
    except Exception:
        flat = flatten_attrs(geometry)
    return toml_text, flat


def utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def set_attrs(node, attrs: dict) -> None:
    for key, value in attrs.items():
        try:
            node.attrs[key] = value
        except (TypeError, ValueError) as exc:
            log.debug("attribute %s=%r not stored (%s)", key, value, exc)
            node.attrs[key] = str(value)


# =========================================================================== writer

#: Space kept for closing the output validly after the last frame: allocated to the file itself ahead of
#: its data (fallocate), so that another program filling the disk cannot take it; where the file system
#: cannot allocate ahead, held in a hidden reserve file beside it and given back for the close.
RESERVE_BYTES = 2 * 1024 * 1024

#: The output's space is allocated ahead in steps of at least this (fewer calls), where the disk has it.
ALLOCATE_STEP_BYTES = 32 * 1024 * 1024

#: Bytes a frame's maps take per sample of the grid, uncompressed: height and two slopes (float32) and
#: the valid mask (uint8).
MAP_BYTES_PER_SAMPLE = 3 * 4 + 1

#: Longest time between two flushes of OUT.h5, seconds. ``frames_done`` moves only at a
#: flush, so a crash (SIGKILL, power cut) or a failed write loses at most the frames
#: written in this time; the end of a run, any error and Ctrl-C/SIGTERM/SIGHUP flush
#: every frame written. 0: flush after every frame (what the writer did before).
FLUSH_INTERVAL_S = 0.5

#: gzip level of ``--compression gzip`` (h5py's default), the one the workers compress with.
GZIP_LEVEL = 4

#: The maps of a frame, in the order the writer writes them.
MAPS = ("height", "slope_x", "slope_y", "valid")


@dataclasses.dataclass
class OutputFrame:
    """One measured frame as OUT.h5 stores it, made by :func:`output_frame` where the
    frame was reconstructed (a worker process), so that the writer only writes.

    ``maps``: ``{name: array}`` for :data:`MAPS`: ``height`` (float32, NaN where not
    valid), ``slope_x``, ``slope_y`` (float32), ``valid`` (uint8, 1 where measured),
    each C-contiguous of shape ``shape``; or, with ``compression`` set, each a uint8
    array holding the map's chunk already compressed as OUT.h5's filters would
    (shuffle, then gzip at :data:`GZIP_LEVEL`), written as it is. ``pin`` and
    ``series``: as the Result's (``/pin_status``). ``note``: the Result's (stored in
    ``/frame_status_text`` of a measured frame). ``release``: called once the
    writer is done with the maps (frees the shared memory they are views of).
    """

    shape: tuple
    maps: dict
    pin: object = None
    series: object = None
    note: str = ""
    compression: Optional[str] = None
    release: Optional[Callable] = None

    @property
    def height(self) -> np.ndarray:
        return self._map("height")

    @property
    def slope_x(self) -> np.ndarray:
        return self._map("slope_x")

    @property
    def slope_y(self) -> np.ndarray:
        return self._map("slope_y")

    @property
    def valid(self) -> np.ndarray:
        return self._map("valid").view(bool)

    def _map(self, name: str) -> np.ndarray:
        if self.compression is not None:
            raise TirdeflectError(f"the {name} map of this frame is compressed ({self.compression}) "
                                  f"for OUT.h5; read it from the file")
        return self.maps[name]

    def done(self) -> None:
        """Drop the maps (and free what they are views of); the pin and series stay."""
        self.maps = {}
        release, self.release = self.release, None
        if release is not None:
            release()


def _shuffled_gzip(a: np.ndarray) -> np.ndarray:
    """``a``'s bytes as HDF5's shuffle then deflate filters store them (one chunk)."""
    b = np.ascontiguousarray(a).view(np.uint8)
    if a.itemsize > 1:  # the shuffle filter: byte k of every element together
        b = np.ascontiguousarray(b.reshape(-1, a.itemsize).T)
    return np.frombuffer(zlib.compress(b, GZIP_LEVEL), np.uint8)


def output_frame(result, compression: Optional[str] = None) -> OutputFrame:
    """``result`` (a processing Result) as OUT.h5 stores it: the height NaN where
    not valid, the mask as uint8; with ``compression="gzip"`` the maps compressed
    here (in the worker that measured the frame) instead of in the writer."""
    valid = np.ascontiguousarray(result.valid, dtype=bool)
    height = np.where(valid, np.asarray(result.height, np.float32), np.float32(np.nan))
    maps = {"height": height,
            "slope_x": np.ascontiguousarray(result.slope_x, dtype=np.float32),
            "slope_y": np.ascontiguousarray(result.slope_y, dtype=np.float32),
            "valid": valid.view(np.uint8)}
    shape = height.shape
    for name, a in maps.items():
        if a.shape != shape:
            raise ShapeMismatchError(f"result {name} has shape {a.shape}, its height {shape}")
    compression = "gzip" if compression == "gzip" else None  # lzf: compressed by HDF5 in the writer
    if compression:
        maps = {name: _shuffled_gzip(a) for name, a in maps.items()}
    return OutputFrame(shape=shape, maps=maps, pin=getattr(result, "pin", None),
                       series=getattr(result, "series", None), note=getattr(result, "note", ""),
                       compression=compression)


# DiskFullError: the one error for "no room for the next write" (app.files.h5safe), under the
# name this module always exported; _repair_eof: the name tests and docs know for repair_eof
_repair_eof = repair_eof


def _per_frame_rows(f, name: str, dtype, description: str, *, units=None, fillvalue=None) -> None:
    """``f[name]``: a per-frame 1-D dataset of OUT.h5, empty, grown at each flush (chunks of
    1024 rows), with its ``units`` (if any) and ``description``."""
    fill = {} if fillvalue is None else {"fillvalue": fillvalue}
    ds = f.create_dataset(name, shape=(0,), maxshape=(None,), dtype=dtype, chunks=(1024,), **fill)
    if units is not None:
        ds.attrs["units"] = units
    ds.attrs["description"] = description


class ResultWriter:
    """Write results to OUT.h5 one frame at a time (see docs/output-format.md).

    The file is created (never replaced: mode "x") at ``path``, which the
    engine chooses beside the final output (:func:`partial_path`) and renames
    into place with :func:`publish` only when the run succeeded. Per-frame
    datasets are created with the file (``grid_coords`` fixes their shape), and
    with them ``surface_positions`` (each sample's ``(x_mm, y_mm)``, 2-D, where the
    grid is not separable: :func:`processing.fullgrid.grid_surface_positions`).
    Each :meth:`append` writes a frame's maps at once; its row of the 1-D
    datasets waits for the next :meth:`flush`, which writes the rows, flushes
    and only then moves ``frames_done`` (the count that vouches for the file).
    A flush happens when ``flush_interval_s`` (default :data:`FLUSH_INTERVAL_S`)
    has passed since the last one, and in :meth:`close`.

    ``n``: frames written; ``frames_done``: frames flushed (what the file holds
    after a crash). After a failed write the frames since the last flush are
    dropped: ``n`` becomes ``frames_done`` and ``lost`` says how many.
    """

    PER_FRAME = ("height", "slope_x", "slope_y")
    PER_FRAME_1D = ("frame_index", "source_index", "source", "camera_frame_id",
                    "device_timestamp_ns", "host_timestamp_ns", "frame_flags", "trigger_index",
                    "frame_status", "frame_status_text", "time_s", "saturated_pct", "hot_pixels",
                    "turn_mrad", "turn_flagged", "pin_status")

    def __init__(self, path: Path, *, compression: str, attrs: dict,
                 geometry_toml: str, geometry_attrs: dict, carrier_attrs: dict,
                 reference: np.ndarray, expected: int, grid_coords: tuple, grid: str,
                 flush_interval_s: Optional[float] = None, surface_positions: Optional[tuple] = None):
        self.path = path
        self.compression = None if compression == "none" else compression
        self.flush_interval_s = FLUSH_INTERVAL_S if flush_interval_s is None else float(flush_interval_s)
        # no chunk cache: every frame is one chunk, written through at once, so a
        # failed write (disk full) raises here instead of being lost when h5py
        # closes a dataset handle and HDF5 flushes its cache (errors ignored there)
        self.f = h5safe.create_h5(path, "x", rdcc_nbytes=0,
                                  remedy="choose another --out (a folder you can write to)")
        self._fd = h5safe.descriptor_of(self.f)  # for dropping flushed pages (None: another driver)
        _hold_metadata_until_flush(self.f)
        fs_max = h5safe.max_file_bytes(Path(path).parent)
        self._alloc = Preallocation(self._fd, os.path.getsize(path), h5safe.file_size_limit(fs_max))
        self._reserve = SpaceReserve(path, 0 if self._alloc.supported else RESERVE_BYTES)
        f = self.f
        set_attrs(f, attrs)
        f.attrs["frames_done"] = 0
        f.attrs["frames_expected"] = int(expected)
        f.attrs["status"] = "running"
        f.attrs["geometry_toml"] = geometry_toml
        set_attrs(f.create_group("geometry"), geometry_attrs)
        set_attrs(f.create_group("carriers"), carrier_attrs)
        # shuffle before compressing: float32 maps shrink ~1.6x with gzip instead of ~1.2x
        self._filters = dict(compression=self.compression, shuffle=self.compression is not None)
        if self.compression == "gzip":
            self._filters["compression_opts"] = GZIP_LEVEL
        ref = f.create_dataset("reference", data=reference, **self._filters)
        ref.attrs["description"] = "reference image as read (unscaled samples)"
        self.n = 0
        self.measured = 0  # frames appended as measured (status OK): what the file holds worth keeping
        self.frames_done = 0
        self.lost = 0
        self.failed = False
        self.abandoned = False
        self._rows = {name: [] for name in self.PER_FRAME_1D}
        self._labels = []  # (sequence index, label) of the frames written since the last flush
        x_mm, y_mm = grid_coords
        self._create(np.asarray(x_mm, np.float64), np.asarray(y_mm, np.float64), grid)
        if surface_positions is not None:
            self._create_surface_positions(*surface_positions)
        self._maps = [f[name] for name in MAPS]
        self._row_datasets = [f[name] for name in self.PER_FRAME_1D]
        f.flush()
        self._flushed_at = time.monotonic()

    def _create(self, x_mm: np.ndarray, y_mm: np.ndarray, grid: str) -> None:
        import h5py

        from app.batch.frame_status import FrameStatus

        f = self.f
        rows, cols = len(y_mm), len(x_mm)
        self._shape = (rows, cols)
        kw = dict(shape=(0, rows, cols), maxshape=(None, rows, cols), chunks=(1, rows, cols), **self._filters)
        units = {"height": "mm", "slope_x": "1 (dh/dx)", "slope_y": "1 (dh/dy)"}
        for name in self.PER_FRAME:
            ds = f.create_dataset(name, dtype=np.float32, fillvalue=np.nan, **kw)
            ds.attrs["units"] = units[name]
        f["height"].attrs["description"] = "surface height, mm, NaN where invalid"
        f["slope_x"].attrs["description"] = "dh/dx, x along increasing column"
        f["slope_y"].attrs["description"] = "dh/dy, y along increasing row"
        valid = f.create_dataset("valid", dtype=np.uint8, fillvalue=0, **kw)
        valid.attrs["description"] = "1 where the height was measured, 0 where masked"
        x = f.create_dataset("x_mm", data=x_mm)
        y = f.create_dataset("y_mm", data=y_mm)
        x.attrs["units"] = "mm"
        y.attrs["units"] = "mm"
        x.attrs["description"] = ("surface x of each column (increasing column) along the central row; "
                                  "/surface_x_mm, where present, has each sample's own")
        y.attrs["description"] = ("surface y of each row (increasing row) along the central column; "
                                  "/surface_y_mm, where present, has each sample's own")
        x.make_scale("x_mm")
        y.make_scale("y_mm")
        for name in (*self.PER_FRAME, "valid"):
            f[name].dims[1].attach_scale(y)
            f[name].dims[2].attach_scale(x)
        per_frame = functools.partial(_per_frame_rows, f)
        per_frame("frame_index", np.int64, "0-based index of each output frame in the whole input sequence")
        per_frame("source_index", np.int64, "page / recording frame within its source file")
        per_frame("source", h5py.string_dtype(), "input file of each output frame")
        per_frame_meta = {
            "camera_frame_id": "camera block/frame id from the recording's frame table; -1 unknown",
            "device_timestamp_ns": "camera clock of the frame, ns; -1 unknown",
            "host_timestamp_ns": "host monotonic clock at reception, ns; -1 unknown",
            "frame_flags": "drivers.base.FrameFlags of the recorded frame (0 for image files)",
            "trigger_index": ("frames from the recording's trigger frame (0), negative before it; "
                              f"{TRIGGER_INDEX_UNKNOWN} for frames of sources without one (image files)"),
        }
        for name, text in per_frame_meta.items():
            per_frame(name, np.int64, text)
        per_frame("frame_status", h5py.enum_dtype({s.name: int(s) for s in FrameStatus}, basetype="u1"),
             "why a frame has no heights: " + ", ".join(f"{int(s)} {s.name}" for s in FrameStatus)
             + " (app.batch.frame_status.FrameStatus); 0 = measured")
        per_frame("frame_status_text", h5py.string_dtype(),
             "the reason of a non-zero frame_status; if 0, a note on how the frame was measured "
             "(e.g. the image refinement's fallback to FD), else empty")
        per_frame("time_s", np.float64,
             "time of the frame from its file: relative to the trigger (MRAW, CINE), the stream "
             "start (video) or the recording's first frame (HDF5); NaN unknown (image files)",
             units="s", fillvalue=np.nan)
        per_frame("saturated_pct", np.float32,
             "percentage of the frame's pixels at its bit depth's top code (clipped: over 1 % costs "
             "accuracy); NaN for a frame that could not be measured", units="%", fillvalue=np.nan)
        per_frame("hot_pixels", np.int32,
             "the frame's own isolated pixels brighter than anything the reference's pattern shows "
             "(cosmic rays, hot pixels the reference lacks), repaired before measuring; -1 for a frame "
             "that could not be measured", fillvalue=-1)
        per_frame("turn_mrad", np.float32,
             "how far the frame's pattern turned since the reference about the frame's centre (the camera or "
             "the board moved; positive clockwise as shown, rows down): a turn puts a saddle-shaped error into "
             f"the heights; frames above {TURN_MAX_MRAD:g} mrad and {TURN_MIN_SIGNIFICANCE:g} standard errors are "
             "flagged (/turn_flagged) "
             "and named in the run's summary; NaN for a frame not judged", units="mrad", fillvalue=np.nan)
        per_frame("turn_flagged", np.uint8,
             f"1 where the frame's turn (/turn_mrad) is flagged: above {TURN_MAX_MRAD:g} mrad and "
             f"{TURN_MIN_SIGNIFICANCE:g} standard errors "
             "of its estimate (processing.turn.TurnCheck.flagged; waves alone can read 0.1 mrad), else 0",
             fillvalue=0)
        f.attrs["grid"] = str(grid)
        self._create_pin_status()

    def _create_surface_positions(self, x_mm, y_mm) -> None:
        """``/surface_x_mm``, ``/surface_y_mm`` ``(rows, cols)`` float32: each sample's own surface position,
        where the grid is not separable (a TIR camera at a finite distance: the image is keystoned, and
        ``/x_mm``, ``/y_mm`` hold the central row's and column's positions only)."""
        f = self.f
        for name, values, along in (("surface_x_mm", x_mm, "x"), ("surface_y_mm", y_mm, "y")):
            values = np.asarray(values, dtype=np.float64)
            if values.shape != self._shape:
                raise ValueError(f"{name} has the shape {values.shape}, not the grid's {self._shape}")
            ds = f.create_dataset(name, data=values.astype(np.float32), **self._filters)
            ds.attrs["units"] = "mm"
            ds.attrs["description"] = (
                f"surface {along} of each sample (row, column), where its camera ray meets the resting surface: "
                f"the camera at a finite distance sees the surface keystoned, and /x_mm, /y_mm give the "
                f"positions along the central row and column only")
            ds.dims[0].attach_scale(f["y_mm"])
            ds.dims[1].attach_scale(f["x_mm"])

    # ------------------------------------------------------------------ pin (issue 13)
    def _create_pin_status(self) -> None:
        """``/pin_status``: where each frame's height offset was pinned, and whether
        its result is continuous with the previous frame's (one row per frame)."""
        ds = self.f.create_dataset("pin_status", shape=(0,), maxshape=(None,), dtype=_pin_status_dtype(),
                                   chunks=(256,))
        ds.attrs["description"] = (
            "per frame: where the height offset (the operator's null space) was pinned and whether the "
            "result jumps against the previous frame; the region is /pin_region")
        ds.attrs["fields"] = [f"{name}: {text}" for name, text in _PIN_FIELDS]

    def write_pin_region(self, mask, rows_px, cols_px, attrs: dict) -> None:
        """``/pin_region``: the reference region (chosen once for the series) on the grid
        of ``rows_px`` x ``cols_px`` (the decimated grid), 1 inside."""
        ds = self.f.create_dataset("pin_region", data=np.asarray(mask, dtype=np.uint8))
        ds.attrs["description"] = "reference region the height offset is pinned on (1 inside), chosen once"
        ds.attrs["rows_px"] = np.asarray(rows_px, dtype=np.float64)
        ds.attrs["cols_px"] = np.asarray(cols_px, dtype=np.float64)
        set_attrs(ds, attrs)
        self.f.flush()

    def _resume_hint(self, next_index=None, pending_kept: bool = False) -> str:
        """``--first K``: the first selected frame not yet safely in the file (the oldest
        frame waiting for a flush, else ``next_index``, the frame being written); with
        ``pending_kept`` (the frames waiting for a flush are written at the close, in room
        held for it) ``next_index``."""
        pending = self._rows["frame_index"]
        k = pending[0] if pending and not pending_kept else next_index
        if k is None:
            return "then resume with --first set to the first frame missing from the file (its /frame_index)"
        return f"then resume with --first {int(k)} (and the same --last and --step) into another --out"

    @property
    def grid_shape(self) -> tuple:
        """``(rows, cols)`` of the maps stored."""
        return self._shape

    @property
    def frame_bytes(self) -> int:
        """Bytes one frame's maps take in the file, uncompressed (:data:`MAP_BYTES_PER_SAMPLE` a sample)."""
        return int(np.prod(self._shape)) * MAP_BYTES_PER_SAMPLE

    def frames_room(self) -> tuple:
        """``(bytes, what)``: how much the frames may still take (what the disk or the file size limit
        has left, less the room kept for the close) and what limits it (:func:`room_bytes`)."""
        room, what = room_bytes(self.path)
        return room - (0 if self._reserve.held else RESERVE_BYTES), what

    def _check_room(self, shape, next_index=None) -> None:
        """Refuse the next frame (DiskFullError) while the file can still be closed validly.

        The next frame and ``RESERVE_BYTES`` for the close are allocated to the
        file ahead of HDF5 (:class:`~app.files.h5safe.Preallocation`): what was
        allocated stays the file's, whoever fills the disk meanwhile. Where the
        file system cannot allocate ahead, the free space is compared instead
        and the reserve file holds the room to close.
        """
        frame = int(np.prod(shape)) * MAP_BYTES_PER_SAMPLE + 4096
        alloc = self._alloc
        if alloc.supported:
            end = int(self.f.id.get_filesize())  # HDF5's end of allocation
            if not alloc.make_room(end, frame + RESERVE_BYTES, ALLOCATE_STEP_BYTES):
                # no room: what is free plus what the file holds ahead of its end
                room, what = room_bytes(self.path, alloc.allocated_bytes)
                raise self._disk_full(room + alloc.allocated_bytes - end, what, next_index)
            if alloc.supported:
                return
            # this file system cannot allocate ahead: a reserve file holds the room to close
            log.info("%s: the file system cannot allocate ahead; checking free space instead", self.path)
            self._reserve = SpaceReserve(self.path, RESERVE_BYTES)
        room, what = room_bytes(self.path)
        if room < frame + (0 if self._reserve.held else RESERVE_BYTES):  # (the held reserve not counted twice)
            raise self._disk_full(room, what, next_index)

    def _disk_full(self, room: int, what: str, next_index) -> DiskFullError:
        return DiskFullError(
            f"{what} full: {room / 2**20:.1f} MiB left for {str(self.path)!r}, less than one "
            f"more frame plus a reserve that keeps the file valid; free space or write --out "
            f"to another disk, {self._resume_hint(next_index, pending_kept=next_index is not None)}")

    def append(self, item: imageio.FrameItem, result, outcome=None) -> None:
        """Append one frame: ``result`` (an :class:`OutputFrame`, made in the worker,
        or a processing Result, made into one here), or None for a frame that could
        not be measured (all-NaN heights, ``valid`` 0, ``outcome``'s status and
        reason stored). An OutputFrame's maps are released once written. Flushes
        when :attr:`flush_interval_s` has passed since the last flush. ``/saturated_pct``
        ``/hot_pixels``, ``/turn_mrad`` and ``/turn_flagged`` are the outcome's (NaN, -1, NaN and 0 when no outcome is
        given or the frame was not measured)."""
        from app.batch.frame_status import FrameOutcome

        measured = outcome is not None and outcome.ok  # (no outcome given: not known)
        outcome = FrameOutcome() if outcome is None else outcome
        frame = result if isinstance(result, OutputFrame) or result is None else output_frame(result)
        k = self.n
        try:
            self._check_room(self._shape, item.sequence_index)
            if frame is not None and tuple(frame.shape) != self._shape:
                raise ShapeMismatchError(
                    f"result grid {tuple(frame.shape)} differs from the output's {self._shape}")
            self._write_maps(k, frame)
        except BaseException as exc:
            self._drop_frame(k, exc)
            if isinstance(exc, (RuntimeError, OSError)) and not isinstance(exc, TirdeflectError):
                raise self._write_error(k, exc, item.sequence_index) from exc  # HDF5: RuntimeError
            raise
        finally:
            if frame is not None:
                frame.done()
        rows = self._rows
        rows["frame_index"].append(item.sequence_index)
        rows["source_index"].append(item.index_in_source)
        rows["source"].append(item.source)
        rows["camera_frame_id"].append(item.camera_frame_id)
        rows["device_timestamp_ns"].append(item.device_timestamp_ns)
        rows["host_timestamp_ns"].append(item.host_timestamp_ns)
        rows["frame_flags"].append(item.flags)
        rows["trigger_index"].append(TRIGGER_INDEX_UNKNOWN if item.trigger_index is None else item.trigger_index)
        rows["frame_status"].append(int(outcome.status))
        rows["frame_status_text"].append(outcome.reason or ("" if frame is None else frame.note))
        rows["time_s"].append(item.time_s)
        rows["saturated_pct"].append(outcome.saturated_pct if measured else np.nan)
        rows["hot_pixels"].append(outcome.hot_pixels if measured else -1)
        rows["turn_mrad"].append(outcome.turn.turn_mrad if measured and outcome.turn is not None else np.nan)
        rows["turn_flagged"].append(int(measured and outcome.turn is not None and outcome.turn.flagged))
        rows["pin_status"].append(_pin_status_row(frame))
        if log.isEnabledFor(logging.DEBUG):
            self._labels.append((item.sequence_index, item.label))
        self.n = k + 1
        self.measured += int(measured)
        if time.monotonic() - self._flushed_at >= self.flush_interval_s:
            self.flush()

    def _write_maps(self, k: int, frame: Optional[OutputFrame]) -> None:
        for ds in self._maps:
            ds.resize(k + 1, axis=0)
        if frame is None:
            return  # never written: the chunks read as the fill values, NaN and valid 0
        for ds, name in zip(self._maps, MAPS):
            if frame.compression is not None:
                if frame.compression != self.compression:
                    raise TirdeflectError(f"a frame compressed with {frame.compression} for an output "
                                          f"written with {self.compression or 'none'}")
                ds.id.write_direct_chunk((k, 0, 0), frame.maps[name])
            elif self.compression is None:
                # a map is one whole chunk and nothing filters it: its bytes are the chunk. Written
                # through as they are, not through h5py's selection (``ds[k] = map``: 7.0 CPU-ms a
                # 1024^2 float32 map, this 0.8; 22 of the parent's 41 CPU-ms a frame at 2 workers)
                ds.id.write_direct_chunk((k, 0, 0), np.ascontiguousarray(frame.maps[name], ds.dtype))
            else:  # lzf: HDF5 compresses here
                ds[k] = frame.maps[name]

    def _drop_frame(self, k: int, exc: BaseException) -> None:
        """Frame ``k`` failed half-way. After a failed write (HDF5's error: disk full)
        write nothing more through this handle (:meth:`_abandon`): the file stays as
        the last flush left it. Otherwise (Ctrl-C between two calls, a bad frame)
        the handle is sound: shrink the maps back to ``k`` frames and go on."""
        if isinstance(exc, (RuntimeError, OSError)) and not isinstance(exc, TirdeflectError):
            self.failed = not self._abandon()
            return
        try:
            for ds in self._maps:
                if ds.shape[0] > k:
                    ds.resize(k, axis=0)
        except BaseException:  # noqa: BLE001 - then the last flush is what stays
            self.failed = not self._abandon()

    def flush(self) -> None:
        """Write the rows of the frames since the last flush, flush, then set
        ``frames_done`` and flush again: a file cut off anywhere holds
        ``frames_done`` complete frames. A failed write abandons the handle."""
        if self.f is None or self.abandoned:
            return
        done, n = self.frames_done, self.n
        f = self.f
        try:
            if n > done:
                for ds, name in zip(self._row_datasets, self.PER_FRAME_1D):
                    ds.resize(n, axis=0)
                    values = self._rows[name]
                    ds[done:n] = np.stack(values) if name == "pin_status" else values
            f.flush()  # the frames' data first ...
            f.attrs["frames_done"] = n  # ... then the counter that vouches for them
            f.flush()
        except (RuntimeError, OSError) as exc:
            self.failed = not self._abandon()
            raise self._write_error(done, exc) from exc
        # (KeyboardInterrupt between two calls: the handle is sound and the next flush writes it all)
        self.frames_done = n
        if self._fd is not None:  # written once, not read back here: out of the page cache
            h5safe.drop_written_pages(self._fd)
        for values in self._rows.values():
            values.clear()
        for index, label in self._labels:
            log.debug("frame %d (%s) written to %s", index, label, self.path)
        self._labels.clear()
        self._flushed_at = time.monotonic()

    def _write_error(self, k: int, exc: BaseException, next_index=None) -> OSError:
        text = _one_line(exc)
        if "errno = 28" in text or "No space left" in text or getattr(exc, "errno", None) == 28:
            return DiskFullError(
                f"disk full while writing frame {k} to {str(self.path)!r} (No space left on device: "
                f"another program took the space); free space or write --out to another disk, "
                f"{self._resume_hint(next_index)}")
        if "errno = 27" in text or getattr(exc, "errno", None) == 27:
            return DiskFullError(
                f"file size limit (ulimit -f) reached while writing frame {k} to {str(self.path)!r}; "
                f"raise the limit or write --out elsewhere, {self._resume_hint(next_index)}")
        return OSError(f"writing frame {k} to {str(self.path)!r} failed: {text}")

    def _abandon(self) -> bool:
        """Point HDF5's file descriptor at /dev/null (:func:`h5safe.detach_descriptor`):
        every write it still attempts (dirty metadata at the close) goes nowhere
        instead of reaching the file half-way, which stays as the last flush
        left it (``frames_done`` frames; the ones written since are dropped
        from ``n``). Returns True if it could."""
        self.lost = self.n - self.frames_done
        self.n = self.frames_done
        try:
            h5safe.detach_descriptor(self.f.id.get_vfd_handle())
        except Exception as exc:  # noqa: BLE001 - another file driver: repaired at the close
            log.error("%s: could not stop writing after the failed write (%s)", self.path, _one_line(exc))
            return False
        self.abandoned = True
        return True

    def close(self, status: str, attrs: dict | None = None) -> None:
        """Record ``status`` (and ``attrs``) and close.

        After a failed write the handle writes nothing more (it was
        abandoned); the status is then recorded by reopening the file, with
        the space reserve freed. If that fails too (another program took the
        space), the file keeps ``status = running`` and stays valid up to
        ``frames_done``; a file HDF5 still left inconsistent is repaired."""
        if self.f is None:
            return
        # room to record the status: the reserve file, or the file's own space allocated past its end
        reserved = self._reserve.held or (self._alloc.supported and RESERVE_BYTES > 0)
        self._reserve.release()  # the room the last flush, the status and the close need
        if not self.failed and not self.abandoned:
            try:
                self.flush()  # every frame written
            except BaseException as exc:  # noqa: BLE001 - the file stays as the last flush left it
                log.error("%s: the last %d frame(s) could not be flushed (%s); valid up to frame %d",
                          self.path, self.lost, _one_line(exc), self.frames_done)
        f, self.f = self.f, None
        if self.abandoned:
            try:
                f.close()
            except Exception:  # noqa: BLE001 - its writes go nowhere now; the reopen below records the status
                pass
            if reserved:
                self._record_status(status, attrs)
            if repair_eof(self.path):
                log.warning("%s: repaired after the failed write; valid up to frames_done", self.path)
            return
        try:
            if not self.failed:  # after a failed write, add nothing: what was flushed stays valid
                set_attrs(f, attrs or {})
                f.attrs["status"] = status
                f.attrs["finished_utc"] = utc_now()
                f.flush()
        except Exception as exc:
            self.failed = True
            log.error("could not record the final status in %s: %s", self.path, exc)
        finally:
            try:
                f.close()
            except Exception as exc:
                self.failed = True
                log.error("closing %s failed: %s (valid up to frame %d)", self.path, exc, self.frames_done)
            if self.failed:
                repair_eof(self.path)
            elif self._alloc.supported:  # closed normally: the space allocated ahead given back
                h5safe.fit_to_eoa(self.path)

    def _record_status(self, status: str, attrs: dict | None) -> None:
        import h5py

        try:
            with h5py.File(self.path, "r+") as f:
                set_attrs(f, attrs or {})
                f.attrs["frames_done"] = self.frames_done
                f.attrs["status"] = status
                f.attrs["finished_utc"] = utc_now()
        except Exception as exc:  # noqa: BLE001
            log.error("could not record the final status in %s: %s (valid up to frame %d)",
                      self.path, _one_line(exc), self.frames_done)


def _hold_metadata_until_flush(f) -> None:
    """No eviction from HDF5's metadata cache: between two flushes nothing but the
    new frames' chunks (past the end of allocation the last flush recorded)
    reaches the file, so a crash leaves the metadata of the last flush, whole."""
    try:
        config = f.id.get_mdc_config()
        config.evictions_enabled = False
        config.incr_mode = 0  # H5C_incr__off, H5C_flash_incr__off, H5C_decr__off: what
        config.flash_incr_mode = 0  # HDF5 requires with evictions off (the cache grows instead)
        config.decr_mode = 0
        f.id.set_mdc_config(config)
    except Exception as exc:  # noqa: BLE001 - an older HDF5: evictions stay possible, rare
        log.debug("metadata cache evictions left on (%s)", exc)


def _one_line(exc: BaseException) -> str:
    """An HDF5 error message on one line."""
    return " ".join(str(exc).split())


# =========================================================================== publishing


def partial_path(out: Path) -> Path:
    """A name beside ``out`` that no file has: ``NAME.partial.h5``, else
    ``NAME.partial-2.h5``, ... (the run writes there; :func:`publish` renames
    it to ``out`` on success, a failed run leaves it there, named in its
    message)."""
    stem, suffix = out.stem, out.suffix or ".h5"
    for k in range(1, 10_000):
        candidate = out.with_name(f"{stem}.partial{'' if k == 1 else f'-{k}'}{suffix}")
        if not os.path.lexists(candidate):
            return candidate
    raise TirdeflectError(f"too many {stem}.partial-*{suffix} files beside {str(out)!r}; remove "
                          f"the ones you do not need")


def publish(partial: Path, out: Path, *, overwrite: bool) -> None:
    """Rename the finished ``partial`` to ``out`` (same directory: atomic).

    Without ``overwrite`` an ``out`` that appeared meanwhile is never
    replaced (OutputExistsError; ``partial`` stays). With it, the old ``out``
    is replaced in one step, only now that the new one is complete.
    """
    if overwrite:
        os.replace(partial, out)
        return
    try:
        os.link(partial, out)  # fails if out exists: never replaces a file
    except FileExistsError:
        raise OutputExistsError(
            f"output {str(out)!r} appeared while processing; the result is kept as "
            f"{str(partial)!r}") from None
    except OSError:  # no hard links on this file system (FAT, some network disks)
        if os.path.lexists(out):
            raise OutputExistsError(
                f"output {str(out)!r} appeared while processing; the result is kept as "
                f"{str(partial)!r}") from None
        os.replace(partial, out)
        return
    os.unlink(partial)
