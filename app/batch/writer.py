"""OUT.h5 of ``tirdeflect process``: one frame at a time, flushed, valid after any failure
(layout: docs/output-format.md; room, space reserve and superblock repair: app.files.h5safe)."""

from __future__ import annotations

import dataclasses
import datetime as _dt
import logging
import os
from pathlib import Path

import numpy as np

from app.files import imageio
from app.files import h5safe
from app.files.h5safe import DiskFullError, SpaceReserve, repair_eof, room_bytes
from processing.errors import (
    ShapeMismatchError,
    TirdeflectError,
)

__all__ = ["ResultWriter", "OutputExistsError", "DiskFullError", "OUTPUT_FORMAT_VERSION",
           "check_output", "check_not_an_input", "is_same_file", "partial_path", "publish", "set_attrs", "carrier_attrs", "geometry_attrs", "utc_now"]

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
                     ("jump", np.uint8), ("unwrap_slip_fraction", np.float32), ("pin_shift_um", np.float32),
                     ("reason", s)])


def _pin_status_row(result) -> np.ndarray:
    """One row of /pin_status from a Result's ``pin`` and ``series`` (either may be None)."""
    row = np.zeros((), dtype=_pin_status_dtype())
    row["rule"] = ""
    row["reason"] = ""
    row["pin_shift_um"] = np.nan
    row["unwrap_slip_fraction"] = np.nan
    pin = getattr(result, "pin", None)
    if pin is not None:
        row["rule"] = pin.rule
        for name in ("region_samples", "valid_samples", "needed", "used_samples", "unpinned_fraction"):
            row[name] = getattr(pin, name)
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
        raise TirdeflectError(f"cannot write to {str(parent)!r}; choose another --out")



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


def _flatten(obj, prefix: str = "") -> dict:
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
            out.update(_flatten(value, name))
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
    attrs = _flatten(carriers)
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
        flat = _flatten(geometry.to_dict())
    except Exception:
        flat = _flatten(geometry)
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

#: Space kept free so that the output can still be closed validly after the last frame.
RESERVE_BYTES = 2 * 1024 * 1024


# DiskFullError: the one error for "no room for the next write" (app.files.h5safe), under the
# name this module always exported; _repair_eof: the name tests and docs know for repair_eof
_repair_eof = repair_eof


class ResultWriter:
    """Write results to OUT.h5 one frame at a time (see docs/output-format.md).

    The file is created (never replaced: mode "x") at ``path``, which the
    engine chooses beside the final output (:func:`partial_path`) and renames
    into place with :func:`publish` only when the run succeeded. Per-frame
    datasets are created with the file (``grid_coords`` fixes their shape),
    grow by one frame per :meth:`append` and are flushed each time.
    """

    PER_FRAME = ("height", "slope_x", "slope_y")
    PER_FRAME_1D = ("frame_index", "source_index", "source", "camera_frame_id",
                    "device_timestamp_ns", "host_timestamp_ns", "frame_flags", "trigger_index",
                    "frame_status", "frame_status_text", "time_s")

    def __init__(self, path: Path, *, compression: str, attrs: dict,
                 geometry_toml: str, geometry_attrs: dict, carrier_attrs: dict,
                 reference: np.ndarray, expected: int, grid_coords: tuple, grid: str):
        import h5py

        self.path = path
        self.compression = None if compression == "none" else compression
        # no chunk cache: every frame is one chunk, written through at once, so a
        # failed write (disk full) raises here instead of being lost when h5py
        # closes a dataset handle and HDF5 flushes its cache (errors ignored there)
        self.f = h5py.File(path, "x", rdcc_nbytes=0)
        self._reserve = SpaceReserve(path, RESERVE_BYTES)
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
        ref = f.create_dataset("reference", data=reference, **self._filters)
        ref.attrs["description"] = "reference image as read (unscaled samples)"
        self.n = 0
        self.failed = False
        x_mm, y_mm = grid_coords
        self._create(np.asarray(x_mm, np.float64), np.asarray(y_mm, np.float64), grid)
        f.flush()

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
        x.attrs["description"] = "surface x of each column (increasing column)"
        y.attrs["description"] = "surface y of each row (increasing row)"
        x.make_scale("x_mm")
        y.make_scale("y_mm")
        for name in (*self.PER_FRAME, "valid"):
            f[name].dims[1].attach_scale(y)
            f[name].dims[2].attach_scale(x)
        f.create_dataset("frame_index", shape=(0,), maxshape=(None,), dtype=np.int64, chunks=(1024,))
        f["frame_index"].attrs["description"] = (
            "0-based index of each output frame in the whole input sequence")
        f.create_dataset("source_index", shape=(0,), maxshape=(None,), dtype=np.int64, chunks=(1024,))
        f["source_index"].attrs["description"] = "page / recording frame within its source file"
        f.create_dataset("source", shape=(0,), maxshape=(None,), dtype=h5py.string_dtype(),
                         chunks=(1024,))
        f["source"].attrs["description"] = "input file of each output frame"
        per_frame_meta = {
            "camera_frame_id": "camera block/frame id from the recording's frame table; -1 unknown",
            "device_timestamp_ns": "camera clock of the frame, ns; -1 unknown",
            "host_timestamp_ns": "host monotonic clock at reception, ns; -1 unknown",
            "frame_flags": "drivers.base.FrameFlags of the recorded frame (0 for image files)",
            "trigger_index": ("frames from the recording's trigger frame (0), negative before it; "
                              f"{TRIGGER_INDEX_UNKNOWN} for frames of sources without one (image files)"),
        }
        for name, text in per_frame_meta.items():
            f.create_dataset(name, shape=(0,), maxshape=(None,), dtype=np.int64, chunks=(1024,))
            f[name].attrs["description"] = text
        status_type = h5py.enum_dtype({s.name: int(s) for s in FrameStatus}, basetype="u1")
        f.create_dataset("frame_status", shape=(0,), maxshape=(None,), dtype=status_type,
                         chunks=(1024,))
        f["frame_status"].attrs["description"] = (
            "why a frame has no heights: " + ", ".join(f"{int(s)} {s.name}" for s in FrameStatus)
            + " (app.batch.frame_status.FrameStatus); 0 = measured")
        f.create_dataset("frame_status_text", shape=(0,), maxshape=(None,), dtype=h5py.string_dtype(),
                         chunks=(1024,))
        f["frame_status_text"].attrs["description"] = "the reason of a non-zero frame_status; empty if 0"
        f.create_dataset("time_s", shape=(0,), maxshape=(None,), dtype=np.float64, chunks=(1024,),
                         fillvalue=np.nan)
        f["time_s"].attrs["units"] = "s"
        f["time_s"].attrs["description"] = (
            "time of the frame from its file: relative to the trigger (MRAW, CINE), the stream "
            "start (video) or the recording's first frame (HDF5); NaN unknown (image files)")
        f.attrs["grid"] = str(grid)
        self._create_pin_status()

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

    def _check_room(self, shape) -> None:
        """Refuse the next frame (DiskFullError) while the file can still be closed validly."""
        # the reserve is held in its own file while it can be: not counted twice
        need = int(np.prod(shape)) * (3 * 4 + 1) + 4096 + (0 if self._reserve.held else RESERVE_BYTES)
        room, what = room_bytes(self.path)
        if room < need:
            raise DiskFullError(
                f"{what} full: {room / 2**20:.1f} MiB left for {str(self.path)!r}, less than one "
                f"more frame plus a reserve that keeps the file valid; free space or write --out "
                f"to another disk, then resume with --first"
            )

    def append(self, item: imageio.FrameItem, result, outcome=None) -> None:
        """Append one frame: ``result`` (a processing Result), or None for a frame
        that could not be measured (all-NaN heights, ``valid`` 0, ``outcome``'s
        status and reason stored)."""
        from app.batch.frame_status import FrameOutcome

        outcome = FrameOutcome() if outcome is None else outcome
        self._check_room(self._shape)
        f = self.f
        if result is None:
            nan = np.full(self._shape, np.nan, np.float32)
            height = slope_x = slope_y = nan
            valid = np.zeros(self._shape, bool)
        else:
            height = np.asarray(result.height, dtype=np.float32)
            if height.shape != self._shape:
                raise ShapeMismatchError(
                    f"result grid {height.shape} differs from the output's {self._shape}"
                )
            valid = np.asarray(result.valid, dtype=bool)
            slope_x = np.asarray(result.slope_x, dtype=np.float32)
            slope_y = np.asarray(result.slope_y, dtype=np.float32)
        k = self.n
        names = (*self.PER_FRAME, "valid", *self.PER_FRAME_1D, "pin_status")
        try:
            for name in names:
                f[name].resize(k + 1, axis=0)
            f["height"][k] = np.where(valid, height, np.float32(np.nan))
            f["slope_x"][k] = slope_x
            f["slope_y"][k] = slope_y
            f["valid"][k] = valid.astype(np.uint8)
            f["frame_index"][k] = item.sequence_index
            f["source_index"][k] = item.index_in_source
            f["source"][k] = item.source
            f["camera_frame_id"][k] = item.camera_frame_id
            f["device_timestamp_ns"][k] = item.device_timestamp_ns
            f["host_timestamp_ns"][k] = item.host_timestamp_ns
            f["frame_flags"][k] = item.flags
            f["trigger_index"][k] = TRIGGER_INDEX_UNKNOWN if item.trigger_index is None else item.trigger_index
            f["pin_status"][k] = _pin_status_row(result)
            f["frame_status"][k] = int(outcome.status)
            f["frame_status_text"][k] = outcome.reason
            f["time_s"][k] = item.time_s
        except BaseException as exc:
            # e.g. disk full: drop the half-written frame so the file holds exactly frames_done
            self.failed = not self._recover(k, names)
            if isinstance(exc, (RuntimeError, OSError)):  # HDF5 reports failed writes as RuntimeError
                raise self._write_error(k, exc) from exc
            raise
        try:
            f.flush()  # the frame's data first ...
            f.attrs["frames_done"] = k + 1  # ... then the counter that vouches for it
            f.flush()
        except (RuntimeError, OSError) as exc:
            self.failed = not self._recover(k, names)
            raise self._write_error(k, exc) from exc
        self.n = k + 1

    def _write_error(self, k: int, exc: BaseException) -> OSError:
        text = _one_line(exc)
        if "errno = 28" in text or "No space left" in text or getattr(exc, "errno", None) == 28:
            return DiskFullError(
                f"disk full while writing frame {k} to {str(self.path)!r} (No space left on device: "
                f"another program took the space); free space or write --out to another disk, "
                f"then resume with --first")
        if "errno = 27" in text or getattr(exc, "errno", None) == 27:
            return DiskFullError(
                f"file size limit (ulimit -f) reached while writing frame {k} to {str(self.path)!r}; "
                f"raise the limit or write --out elsewhere, then resume with --first")
        return OSError(f"writing frame {k} to {str(self.path)!r} failed: {text}")

    def _recover(self, k: int, names) -> bool:
        """After a failed write of frame ``k``: write nothing more through this
        handle (:meth:`_abandon`), so the file stays as the flush after frame
        ``k - 1`` left it: consistent, ``frames_done = k``. True if that worked."""
        return self._abandon()

    def _abandon(self) -> bool:
        """Point HDF5's file descriptor at /dev/null opened read-only: every
        write it still attempts (dirty metadata at the close) fails instead of
        reaching the file half-way. Returns True if it could."""
        try:
            h5safe.detach_descriptor(self.f.id.get_vfd_handle(), writable=False)
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
        f, self.f = self.f, None
        reserved = self._reserve.held
        self._reserve.release()  # the room the status and the close need
        if getattr(self, "abandoned", False):
            try:
                f.close()
            except Exception:  # noqa: BLE001 - expected: its writes go nowhere now
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
                log.error("closing %s failed: %s (valid up to frame %d)", self.path, exc, self.n)
            if self.failed:
                repair_eof(self.path)

    def _record_status(self, status: str, attrs: dict | None) -> None:
        import h5py

        try:
            with h5py.File(self.path, "r+") as f:
                set_attrs(f, attrs or {})
                f.attrs["frames_done"] = self.n
                f.attrs["status"] = status
                f.attrs["finished_utc"] = utc_now()
        except Exception as exc:  # noqa: BLE001
            log.error("could not record the final status in %s: %s (valid up to frame %d)",
                      self.path, _one_line(exc), self.n)


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
