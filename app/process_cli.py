"""``tirdeflect process`` (images to heights in HDF5) and ``tirdeflect simulate``.

``process`` reads a reference and frames (PNG/BMP/TIFF/TIFF stacks/HDF5
recordings, see :mod:`app.imageio`), reconstructs each frame with
:class:`processing.Reconstructor` and writes one HDF5 file laid out as
documented in ``docs/output-format.md``. The file is written frame by frame
and flushed after each, so that a crash or a bad frame leaves every completed
frame readable, with ``frames_done`` saying how many.

``simulate`` writes a synthetic data set (reference, frames, true heights,
geometry) made by exact ray tracing (:func:`processing.forward.simulate`),
so the whole chain can be checked before going to the tank::

    tirdeflect simulate --out sim
    tirdeflect process sim/reference.png sim/frame_*.png --geometry sim/geometry.toml --out out.h5
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import logging
import math
import os
import shlex
import sys
from pathlib import Path

import numpy as np

from app import imageio
from processing.errors import (
    AllInvalidError,
    ShapeMismatchError,
    TirdeflectError,
)

__all__ = [
    "add_process_parser",
    "add_simulate_parser",
    "add_compare_parser",
    "cmd_process",
    "cmd_simulate",
    "cmd_compare",
    "compare_heights",
    "OutputExistsError",
    "DiskFullError",
    "OUTPUT_FORMAT_VERSION",
]

log = logging.getLogger(__name__)

#: Version of the layout of OUT.h5 described in docs/output-format.md.
OUTPUT_FORMAT_VERSION = 1

#: With --fft-effort auto, batches of at least this many frames plan FFTs with
#: FFTW_MEASURE (measured: 1024 x 1024 FS-SS frames 0.69 -> 0.53 s each, for
#: about 5 s of planning once; the wisdom is cached, so later runs skip it).
MEASURE_MIN_FRAMES = 20


class OutputExistsError(TirdeflectError):
    """The output file exists and ``--overwrite`` was not given."""


# =========================================================================== parsers


def _nonnegative_int(text: str) -> int:
    import argparse

    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {value}")
    return value


def _positive_int(text: str) -> int:
    import argparse

    value = _nonnegative_int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def add_process_parser(sub) -> None:
    """Add the ``process`` subcommand to an argparse subparsers object."""
    p = sub.add_parser(
        "process",
        help="reconstruct surface heights from a reference and frames, to HDF5",
        description="Reconstruct water-surface heights (mm) from a reference image and "
        "deformed frames and write them to an HDF5 file (layout: docs/output-format.md). "
        "Inputs: PNG, BMP, TIFF (8-16 bit, packed 10/12-bit, multi-page stacks) and "
        "tirdeflect HDF5 recordings.",
    )
    p.add_argument("reference", help="reference image of the flat surface (or a recording "
                   "holding a /reference)")
    p.add_argument("frames", nargs="+", metavar="FRAME",
                   help="frames to process, in order (files, stacks or recordings)")
    p.add_argument("--reference-index", type=_nonnegative_int, default=None, metavar="K",
                   help="use page/frame K (0-based) of a TIFF stack or recording as the "
                   "reference (default: a recording's stored /reference, else its frame 0)")
    p.add_argument("--geometry", default=None, metavar="G.toml",
                   help="optical geometry (TOML; see `tirdeflect simulate` for an example); "
                   "may be omitted when the reference or first input is a recording that "
                   "stores its geometry")
    p.add_argument("--out", required=True, metavar="OUT.h5", help="output HDF5 file")
    p.add_argument("--grid", choices=("full", "decimated"), default="full",
                   help="full: heights on every input pixel; decimated: faster, on a coarser "
                   "grid (coordinates in x_mm, y_mm)")
    p.add_argument("--no-unwrap", action="store_true",
                   help="do not unwrap carrier phases (only for small displacements)")
    p.add_argument("--first", type=_nonnegative_int, default=0, metavar="K",
                   help="first frame to process (0-based, counting every frame of every "
                   "input in order)")
    p.add_argument("--last", type=_nonnegative_int, default=None, metavar="K",
                   help="last frame to process (inclusive)")
    p.add_argument("--step", type=_positive_int, default=1, metavar="S",
                   help="process every S-th frame")
    p.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    p.add_argument("--compression", choices=("none", "gzip", "lzf"), default="none",
                   help="HDF5 compression of the per-frame datasets (default none)")
    p.add_argument("--fft-effort", choices=("auto", "estimate", "measure"), default="auto",
                   help="FFTW planning: measure costs seconds once (then cached as wisdom in "
                   "the cache dir) and makes each frame faster; auto measures for >= "
                   f"{MEASURE_MIN_FRAMES} frames")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_process)


def add_simulate_parser(sub) -> None:
    """Add the ``simulate`` subcommand to an argparse subparsers object."""
    p = sub.add_parser(
        "simulate",
        help="write a ray-traced synthetic data set with known heights",
        description="Write reference, frames, true heights (heights.h5, mm) and "
        "geometry.toml made by exact ray tracing, to check the processing chain.",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.add_argument("--surface", default="bump",
                   choices=("bump", "dimple", "waves", "deep-dimple"),
                   help="surface deformation to simulate")
    p.add_argument("--size", type=_positive_int, default=512, metavar="PX",
                   help="image size in pixels (square)")
    p.add_argument("--frames", type=_positive_int, default=1, metavar="N",
                   help="number of frames (time steps)")
    p.add_argument("--bits", type=int, choices=(8, 12), default=8,
                   help="bit depth of the images (12 bit: 16-bit TIFF)")
    p.add_argument("--noise", type=float, default=0.0, metavar="RMS",
                   help="camera noise, RMS in grey levels of the output bit depth")
    p.add_argument("--geometry", default=None, metavar="G.toml",
                   help="optical geometry (default: a typical TIR set-up)")
    p.add_argument("--max-phase", type=float, default=None, metavar="RAD",
                   help="scale the heights so the largest carrier phase |k.u| is RAD radians "
                   "(default: 2.3 bump/dimple, 2.6 waves, 5.0 deep-dimple, which needs "
                   "unwrapping); the same on every geometry, TIR or FS-SS")
    p.add_argument("--seed", type=int, default=0, help="random seed of the noise")
    p.add_argument("--overwrite", action="store_true",
                   help="write into DIR even if it already holds a data set")
    p.set_defaults(func=cmd_simulate)


def add_compare_parser(sub) -> None:
    """Add the ``compare`` subcommand (processed heights against simulated truth)."""
    p = sub.add_parser(
        "compare",
        help="compare processed heights (OUT.h5) with simulated truth (DIR/heights.h5)",
        description="Print, per frame, the relative RMS height error of `tirdeflect process` "
        "output against the true heights written by `tirdeflect simulate`, in the interior "
        "of the field, after removing each map's mean over the geometry's reference region.",
    )
    p.add_argument("out", metavar="OUT.h5", help="output of tirdeflect process")
    p.add_argument("truth", metavar="heights.h5", help="heights.h5 of tirdeflect simulate")
    p.add_argument("--margin", type=float, default=0.125, metavar="F",
                   help="border left out on each side, as a fraction of the size (default 0.125)")
    p.add_argument("--max-error", type=float, default=None, metavar="REL",
                   help="exit with status 1 if any frame's relative RMS error exceeds REL (e.g. 0.02)")
    p.set_defaults(func=cmd_compare)


# =========================================================================== helpers


def _check_input_file(path: str, what: str) -> None:
    p = Path(path)
    if not p.exists():
        raise TirdeflectError(f"{what} {path!r} does not exist; check the path")
    if p.is_dir():
        raise TirdeflectError(f"{what} {path!r} is a directory; give the file itself")


def _load_geometry(path: str):
    _check_input_file(path, "geometry file")
    from processing import Geometry

    return Geometry.from_toml(path)


def _resolve_geometry(args):
    """(Geometry, where it came from): --geometry, else a recording's /geometry_toml."""
    if args.geometry is not None:
        return _load_geometry(args.geometry), str(args.geometry)
    from processing import Geometry
    from processing.errors import GeometryError

    for path in (args.reference, args.frames[0]):
        text = imageio.recording_geometry_toml(path)
        if text:
            try:
                return Geometry.from_toml_text(text), f"{path}:/geometry_toml"
            except GeometryError as exc:
                raise GeometryError(
                    f"the geometry stored in {str(path)!r} is not usable: {exc}; pass --geometry G.toml"
                ) from None
    raise GeometryError(
        "no geometry given: add --geometry G.toml (the inputs are not recordings that store one); "
        "`tirdeflect simulate --out DIR` writes an example DIR/geometry.toml"
    )


def _check_output(out: Path, overwrite: bool) -> None:
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


def _selected_count(total: int, first: int, last: int | None, step: int) -> int:
    stop = total - 1 if last is None else min(last, total - 1)
    if first > stop:
        return 0
    return (stop - first) // step + 1


def _make_reconstructor(reference: np.ndarray, geometry, *, unwrap: bool, grid: str,
                        effort: str = "estimate"):
    from processing import Reconstructor

    return Reconstructor(reference, geometry, grid=grid, unwrap=unwrap,
                         planner_effort="FFTW_MEASURE" if effort == "measure" else "FFTW_ESTIMATE")


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


def _carrier_attrs(carriers) -> dict:
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


def _geometry_attrs(geometry) -> tuple[str, dict]:
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


def _utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _set_attrs(node, attrs: dict) -> None:
    for key, value in attrs.items():
        try:
            node.attrs[key] = value
        except (TypeError, ValueError) as exc:
            log.debug("attribute %s=%r not stored (%s)", key, value, exc)
            node.attrs[key] = str(value)


# =========================================================================== writer

#: Space kept free so that the output can still be closed validly after the last frame.
RESERVE_BYTES = 2 * 1024 * 1024


class DiskFullError(TirdeflectError):
    """No room left for the next frame (disk or file-size limit); the file was closed valid."""


def _room_bytes(path: Path) -> tuple:
    """Bytes ``path`` may still grow by, and what limits it (disk or ulimit -f)."""
    import shutil

    size = path.stat().st_size if path.exists() else 0
    room, what = shutil.disk_usage(path.parent if str(path.parent) else ".").free, "disk"
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_FSIZE)
        if soft != resource.RLIM_INFINITY and soft - size < room:
            room, what = soft - size, "file size limit (ulimit -f)"
    except (ImportError, ValueError, OSError):  # not POSIX
        pass
    return room, what


def _repair_eof(path: Path) -> bool:
    """After a failed write HDF5 may have recorded an end of file beyond what
    reached the disk; extend the file (sparse, needs no space) to that end so
    it opens again. Returns True if it did."""
    import re

    import h5py

    try:
        h5py.File(path, "r").close()
        return False
    except OSError as exc:
        m = re.search(r"stored_eof = (\d+)", str(exc))
        if not m:
            return False
        try:
            if int(m.group(1)) > path.stat().st_size:
                os.truncate(path, int(m.group(1)))
                log.warning("%s: extended to the end of file HDF5 recorded before the failed write", path)
                return True
        except OSError as err:
            log.error("%s: could not repair the end of file (%s); frames_done frames are intact", path, err)
    return False


class _ResultWriter:
    """Write results to OUT.h5 one frame at a time (see docs/output-format.md).

    Per-frame datasets are created with the first result (its grid fixes their
    shape), grow by one frame per :meth:`append` and are flushed each time.
    """

    PER_FRAME = ("height", "slope_x", "slope_y")
    PER_FRAME_1D = ("frame_index", "source_index", "source", "camera_frame_id",
                    "device_timestamp_ns", "host_timestamp_ns", "frame_flags")

    def __init__(self, path: Path, *, overwrite: bool, compression: str, attrs: dict,
                 geometry_toml: str, geometry_attrs: dict, carrier_attrs: dict,
                 reference: np.ndarray, expected: int):
        import h5py

        self.path = path
        self.compression = None if compression == "none" else compression
        self.f = h5py.File(path, "w" if overwrite else "x")
        f = self.f
        _set_attrs(f, attrs)
        f.attrs["frames_done"] = 0
        f.attrs["frames_expected"] = int(expected)
        f.attrs["status"] = "running"
        f.attrs["geometry_toml"] = geometry_toml
        _set_attrs(f.create_group("geometry"), geometry_attrs)
        _set_attrs(f.create_group("carriers"), carrier_attrs)
        ref = f.create_dataset("reference", data=reference, compression=self.compression)
        ref.attrs["description"] = "reference image as read (unscaled samples)"
        self.n = 0
        self._shape = None
        self.failed = False
        f.flush()

    def _create(self, result) -> None:
        import h5py

        f = self.f
        height = np.asarray(result.height)
        rows, cols = height.shape
        self._shape = (rows, cols)
        kw = dict(shape=(0, rows, cols), maxshape=(None, rows, cols), chunks=(1, rows, cols),
                  compression=self.compression)
        units = {"height": "mm", "slope_x": "1 (dh/dx)", "slope_y": "1 (dh/dy)"}
        for name in self.PER_FRAME:
            ds = f.create_dataset(name, dtype=np.float32, fillvalue=np.nan, **kw)
            ds.attrs["units"] = units[name]
        f["height"].attrs["description"] = "surface height, mm, NaN where invalid"
        f["slope_x"].attrs["description"] = "dh/dx, x along increasing column"
        f["slope_y"].attrs["description"] = "dh/dy, y along increasing row"
        valid = f.create_dataset("valid", dtype=np.uint8, fillvalue=0, **kw)
        valid.attrs["description"] = "1 where the height was measured, 0 where masked"
        x = f.create_dataset("x_mm", data=np.asarray(result.x_mm, dtype=np.float64))
        y = f.create_dataset("y_mm", data=np.asarray(result.y_mm, dtype=np.float64))
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
        }
        for name, text in per_frame_meta.items():
            f.create_dataset(name, shape=(0,), maxshape=(None,), dtype=np.int64, chunks=(1024,))
            f[name].attrs["description"] = text
        f.attrs["grid"] = str(getattr(result, "grid", "full"))

    def _check_room(self, shape) -> None:
        """Refuse the next frame (DiskFullError) while the file can still be closed validly."""
        need = int(np.prod(shape)) * (3 * 4 + 1) + 4096 + RESERVE_BYTES
        room, what = _room_bytes(self.path)
        if room < need:
            raise DiskFullError(
                f"{what} full: {room / 2**20:.1f} MiB left for {str(self.path)!r}, less than one "
                f"more frame plus a reserve that keeps the file valid; free space or write --out "
                f"to another disk, then resume with --first"
            )

    def append(self, item: imageio.FrameItem, result) -> None:
        self._check_room(np.shape(result.height))
        if self._shape is None:
            self._create(result)
        f = self.f
        height = np.asarray(result.height, dtype=np.float32)
        if height.shape != self._shape:
            raise ShapeMismatchError(
                f"result grid {height.shape} differs from the first frame's {self._shape}"
            )
        valid = np.asarray(result.valid, dtype=bool)
        k = self.n
        names = (*self.PER_FRAME, "valid", *self.PER_FRAME_1D)
        try:
            for name in names:
                f[name].resize(k + 1, axis=0)
            f["height"][k] = np.where(valid, height, np.float32(np.nan))
            f["slope_x"][k] = np.asarray(result.slope_x, dtype=np.float32)
            f["slope_y"][k] = np.asarray(result.slope_y, dtype=np.float32)
            f["valid"][k] = valid.astype(np.uint8)
            f["frame_index"][k] = item.sequence_index
            f["source_index"][k] = item.index_in_source
            f["source"][k] = item.source
            f["camera_frame_id"][k] = item.camera_frame_id
            f["device_timestamp_ns"][k] = item.device_timestamp_ns
            f["host_timestamp_ns"][k] = item.host_timestamp_ns
            f["frame_flags"][k] = item.flags
        except BaseException as exc:
            # e.g. disk full: drop the half-written frame so the file holds exactly frames_done
            try:
                for name in names:
                    if f[name].shape[0] > k:
                        f[name].resize(k, axis=0)
            except Exception:
                self.failed = True
            if isinstance(exc, RuntimeError):  # HDF5 reports failed writes as RuntimeError
                self.failed = True
                raise OSError(f"writing frame {k} to {str(self.path)!r} failed: {exc}") from exc
            raise
        try:
            f.flush()  # the frame's data first ...
            f.attrs["frames_done"] = k + 1  # ... then the counter that vouches for it
            f.flush()
        except (RuntimeError, OSError) as exc:
            self.failed = True
            raise OSError(f"writing frame {k} to {str(self.path)!r} failed: {exc}; the file is valid "
                          f"up to the frames before it") from exc
        self.n = k + 1

    def close(self, status: str) -> None:
        if self.f is None:
            return
        f, self.f = self.f, None
        try:
            if not self.failed:  # after a failed write, add nothing: what was flushed stays valid
                f.attrs["status"] = status
                f.attrs["finished_utc"] = _utc_now()
                f.flush()
        except Exception as exc:
            log.error("could not record the final status in %s: %s", self.path, exc)
        finally:
            try:
                f.close()
            except Exception as exc:
                log.error("closing %s failed: %s (valid up to frame %d)", self.path, exc, self.n)
            if self.failed:
                _repair_eof(self.path)


# =========================================================================== process


def cmd_process(args) -> int:
    """Run ``tirdeflect process``; returns the exit status (errors raise).

    ``args`` is the argparse namespace of the ``process`` subcommand. Callers
    from Python (the GUI's export) may add ``args.on_progress = f(done, total)``,
    called after each frame is written and flushed.
    """
    out = Path(args.out)
    _check_output(out, args.overwrite)

    # Cheap checks of every input before any work: existence, directories,
    # stack/recording headers; decoding errors of plain images show up per frame.
    _check_input_file(args.reference, "reference")
    counts = [imageio.frame_count(path) for path in args.frames]
    total = sum(counts)
    selected = _selected_count(total, args.first, args.last, args.step)
    if total == 0:
        raise TirdeflectError(
            "the inputs hold no frames (an empty recording or stack?); give files with frames")
    if selected == 0:
        raise TirdeflectError(
            f"--first {args.first} --last {args.last} --step {args.step} selects no frame "
            f"of the {total} input frame(s); frames are counted from 0"
        )

    geometry, geometry_source = _resolve_geometry(args)
    reference_index = getattr(args, "reference_index", None)
    reference = imageio.read_reference(args.reference, index=reference_index)

    from app import cache

    cache.restore_fftw_wisdom()
    effort = getattr(args, "fft_effort", "auto")
    if effort == "auto":
        effort = "measure" if selected >= MEASURE_MIN_FRAMES else "estimate"
    reconstruct = _make_reconstructor(reference, geometry, unwrap=not args.no_unwrap, grid=args.grid,
                                      effort=effort)
    if hasattr(reconstruct, "reset_series"):
        reconstruct.reset_series()

    geometry_toml, geometry_attrs = _geometry_attrs(geometry)
    attrs = {
        "software": "tirdeflect",
        "software_version": _version(),
        "format_version": OUTPUT_FORMAT_VERSION,
        "created_utc": _utc_now(),
        "command": shlex.join(["tirdeflect", *args._argv]) if getattr(args, "_argv", None)
        else "(called from Python, not the command line)",
        "reference_file": str(args.reference),
        "reference_index": -1 if reference_index is None else reference_index,
        "geometry_file": geometry_source,
        "input_files": [str(p) for p in args.frames],
        "first": args.first,
        "last": -1 if args.last is None else args.last,
        "step": args.step,
        "unwrap": not args.no_unwrap,
        "grid_requested": args.grid,
        "fft_effort": effort,
        "height_units": "mm",
        "reference_bits": _bits_hint(args.reference, reference),
    }
    writer = _ResultWriter(
        out, overwrite=args.overwrite, compression=args.compression, attrs=attrs,
        geometry_toml=geometry_toml, geometry_attrs=geometry_attrs,
        carrier_attrs=_carrier_attrs(getattr(reconstruct, "carriers", None)),
        reference=reference, expected=selected,
    )
    status = "failed"
    flagged = _FlagCounter()
    progress = _progress(selected, disable=args.no_progress)
    on_progress = getattr(args, "on_progress", None)  # callers in Python (GUI export): f(done, total)
    try:
        item = None
        frames = imageio.iter_frames(args.frames, first=args.first, last=args.last, step=args.step)
        while True:
            try:
                item = next(frames)
            except StopIteration:
                break
            except TirdeflectError as exc:
                raise _frame_failed(exc, None, writer) from exc
            try:
                result = _process_one(reconstruct, item, reference.shape, args.grid)
                writer.append(item, result)
            except (TirdeflectError, OSError) as exc:  # bad frame; disk full while writing
                raise _frame_failed(exc, item, writer) from exc
            log.debug("frame %d (%s) written to %s", item.sequence_index, item.label, out)
            flagged.add(item)
            progress.update(1)
            if on_progress is not None:
                on_progress(writer.n, selected)
        status = "complete"
    except KeyboardInterrupt:
        status = f"interrupted after {writer.n} frame(s)"
        raise
    except BaseException as exc:
        status = f"failed after {writer.n} frame(s): {exc}"
        raise
    finally:
        progress.close()
        if writer.f is not None and not writer.failed:
            _set_attrs(writer.f, flagged.attrs())
        writer.close(status)
        if status != "complete" and writer.n == 0:
            # nothing worth keeping: do not leave a file that blocks the next attempt
            try:
                out.unlink()
            except OSError:
                pass
        cache.store_fftw_wisdom()
    print(f"tirdeflect: wrote {writer.n} frame(s) to {out}", file=sys.stderr)
    for line in flagged.notes():
        print(f"tirdeflect: note: {line}", file=sys.stderr)
    return 0


class _FlagCounter:
    """Counts the recorder's per-frame flags of the processed frames (never silent)."""

    def __init__(self):
        from drivers.base import FrameFlags

        self.INCOMPLETE = int(FrameFlags.INCOMPLETE)
        self.LOSS = int(FrameFlags.ID_GAP_BEFORE | FrameFlags.TIME_GAP_BEFORE
                        | FrameFlags.RING_OVERRUN_BEFORE)
        self.incomplete = []
        self.gaps = []

    def add(self, item) -> None:
        if item.flags & self.INCOMPLETE:
            self.incomplete.append(item.sequence_index)
            log.warning("frame %d (%s) was flagged INCOMPLETE by the camera: its heights may be wrong",
                        item.sequence_index, item.label)
        if item.flags & self.LOSS:
            self.gaps.append(item.sequence_index)

    def attrs(self) -> dict:
        return {"frames_flagged_incomplete": len(self.incomplete),
                "frames_with_loss_before": len(self.gaps)}

    def notes(self) -> list:
        out = []
        if self.incomplete:
            out.append(f"{len(self.incomplete)} processed frame(s) were recorded INCOMPLETE "
                       f"(missing packets), e.g. frame {self.incomplete[0]}: their heights may be wrong; "
                       f"see /frame_flags in the output")
        if self.gaps:
            out.append(f"the recording lost frames before {len(self.gaps)} processed frame(s), "
                       f"e.g. before frame {self.gaps[0]}: time steps are not uniform; "
                       f"see /frame_flags and /device_timestamp_ns")
        return out


def _process_one(reconstruct, item: imageio.FrameItem, ref_shape, grid: str):
    if item.image.shape != tuple(ref_shape):
        raise ShapeMismatchError(
            f"frame has shape {item.image.shape} (rows, cols) but the reference has "
            f"{tuple(ref_shape)}; use frames and reference from the same camera and region"
        )
    result = reconstruct(item.image, grid=grid)
    valid = np.asarray(result.valid, dtype=bool)
    if not valid.any():
        raise AllInvalidError(
            "no pixel of the frame could be measured (no pattern contrast: black, "
            "saturated or fully blurred frame); check exposure and that the pattern is in view"
        )
    return result


def _frame_failed(exc: Exception, item, writer: _ResultWriter) -> TirdeflectError:
    if item is not None:
        where = f"frame {item.sequence_index} ({item.label})"
    elif getattr(exc, "sequence_index", None) is not None:
        where = f"frame {exc.sequence_index}"
    else:
        where = "reading the next frame"
    saved = (
        f"the {writer.n} frame(s) before it are saved in {str(writer.path)!r}"
        if writer.n
        else f"nothing was written ({str(writer.path)!r} not created)"
    )
    message = f"{where} failed: {exc}; {saved}"
    if isinstance(exc, TirdeflectError):
        return type(exc)(message)
    return TirdeflectError(message)


def _bits_hint(path: str, image: np.ndarray) -> int:
    try:
        return int(imageio.image_info(path).bits)
    except Exception:
        return int(image.dtype.itemsize * 8)


def _version() -> str:
    from app.cli import version

    return version()


class _NoProgress:
    def update(self, n=1):
        pass

    def close(self):
        pass


def _progress(total: int, *, disable: bool):
    if disable:
        return _NoProgress()
    try:
        from tqdm import tqdm
    except ImportError:
        return _NoProgress()
    import shutil

    # disable=None: bar only when stderr is a terminal (log files stay clean);
    # shutil falls back to 80 columns where the terminal reports a width of 0
    return tqdm(total=total, unit="frame", file=sys.stderr, disable=None,
                ncols=shutil.get_terminal_size().columns)


# =========================================================================== compare


def compare_heights(out_path, truth_path, *, margin: float = 0.125) -> list:
    """Per-frame errors of processed heights against simulated truth.

    Both maps have their mean over the geometry's reference region removed
    (the offset the method cannot measure); the comparison uses the interior,
    ``margin * size`` pixels away from each border, and the valid samples.

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
        ``valid_fraction`` (interior).
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
    with h5py.File(truth_path, "r") as f:
        if "height" not in f:
            raise TirdeflectError(f"{str(truth_path)!r} holds no /height; give the heights.h5 of tirdeflect simulate")
        truth = f["height"][()].astype(np.float64)
    if est.shape[1:] != truth.shape[1:]:
        raise ShapeMismatchError(
            f"processed heights are {est.shape[1:]} but the truth is {truth.shape[1:]}; "
            f"compare the output of the same data set")
    rows, cols = truth.shape[1:]
    ref = geometry.reference_mask(np.arange(rows), np.arange(cols), (rows, cols))
    mr, mc = int(round(margin * rows)), int(round(margin * cols))
    inner = (slice(mr, rows - mr), slice(mc, cols - mc))
    report = []
    for k in range(n):
        j = int(index[k])
        if j >= truth.shape[0]:
            raise TirdeflectError(f"output frame {k} is input frame {j} but the truth has {truth.shape[0]} frames")
        e = est[k] - np.nanmean(est[k][ref])
        t = truth[j] - np.mean(truth[j][ref])
        e, t = e[inner], t[inner]
        ok = np.isfinite(e)
        err = e[ok] - t[ok]
        rms_true = float(np.sqrt(np.mean(t[ok] ** 2))) if ok.any() else float("nan")
        rms_err = float(np.sqrt(np.mean(err ** 2))) if ok.any() else float("nan")
        scale = float(np.dot(e[ok], t[ok]) / np.dot(t[ok], t[ok])) if ok.any() and rms_true > 0 else float("nan")
        report.append(dict(frame=j, rel_rms=rms_err / rms_true if rms_true > 0 else float("nan"),
                           rms_error_mm=rms_err, rms_true_mm=rms_true, scale=scale,
                           valid_fraction=float(ok.mean())))
    return report


def cmd_compare(args) -> int:
    """Run ``tirdeflect compare``; 0, or 1 if --max-error is exceeded."""
    for path, what in ((args.out, "processed file"), (args.truth, "truth file")):
        _check_input_file(path, what)
    if not 0 <= args.margin < 0.5:
        raise TirdeflectError(f"--margin must be in [0, 0.5); got {args.margin}")
    report = compare_heights(args.out, args.truth, margin=args.margin)
    print("frame  rel_rms_error  rms_error_um  rms_true_um  scale   valid")
    worst = 0.0
    for r in report:
        print(f"{r['frame']:5d}  {r['rel_rms'] * 100:11.2f} %  {r['rms_error_mm'] * 1e3:12.4f}  "
              f"{r['rms_true_mm'] * 1e3:11.4f}  {r['scale']:.4f}  {r['valid_fraction']:.3f}")
        worst = max(worst, r["rel_rms"] if np.isfinite(r["rel_rms"]) else np.inf)
    if args.max_error is not None and worst > args.max_error:
        print(f"tirdeflect: worst relative RMS error {worst:.2%} exceeds --max-error {args.max_error:.2%}",
              file=sys.stderr)
        return 1
    return 0


# =========================================================================== simulate


#: Geometry used by `tirdeflect simulate` when no --geometry is given: a typical
#: TIR set-up (notes.md): theta 55 deg, pattern 300 mm below the surface,
#: 0.1 mm per column, telecentric camera, rows running away from the camera.
DEFAULT_SIM_GEOMETRY = {
    "setup": "tir",
    "theta_deg": 55.0,
    "depth_mm": 300.0,
    "pixel_mm": 0.1,
    "rows_toward_camera": False,
}

#: Checkerboard period in columns (x) of the simulated pattern: 20 px, i.e. 2 mm
#: at the default 0.1 mm/px (y period 20 cos(theta) px).
SIM_PATTERN_PERIOD_PX = 20.0
SIM_FPS = 100.0


#: Largest carrier phase |k . u| (rad) each --surface is scaled to reach (on any
#: geometry): below pi for all but deep-dimple, which needs unwrapping, as the
#: notes.md example (15 um deep at H = 300 mm, theta = 55 deg) does.
SIM_MAX_PHASE_RAD = {"bump": 2.3, "dimple": 2.3, "waves": 2.6, "deep-dimple": 5.0}


def _sim_scene(name: str, geometry, size: int, n_frames: int, seed: int, amplitude: float = 1.0):
    """Surface (or scene with ``at(t_s)``) for a --surface name.

    Features scale with the field (``size * pixel_mm``); heights are the
    nominal ones below times ``amplitude`` (:func:`_sim_amplitude` picks it so
    the largest carrier phase is :data:`SIM_MAX_PHASE_RAD`). Nominal, at
    512 px: bump 4 um, sigma 1/8 of the field; dimple deepening over the frames
    to 4 um; deep-dimple 15 um, sigma field/4.65; waves 0.7 um RMS, six
    travelling waves of 1/4 to 1/2 the field. Heights in mm, positions in the
    image frame (mm from the image centre).
    """
    from processing import forward

    fov_mm = size * geometry.pixel_mm  # field width along x
    scale = size / 512.0 * amplitude
    if name == "bump":
        return forward.GaussianBump(amplitude_mm=0.004 * scale, sigma_mm=fov_mm / 8.0)
    if name == "dimple":
        # a dimple that deepens over the frames (a disc approaching the surface)
        depth_mm, sigma_mm = 0.004 * scale, fov_mm / 8.0

        def at(t_s: float):
            i = int(round(t_s * SIM_FPS))
            return forward.Dimple((i + 1) / n_frames * depth_mm, sigma_mm)

        return at
    if name == "deep-dimple":
        return forward.Dimple(0.015 * scale, fov_mm / 4.65)
    if name == "waves":
        field = forward.WaveField.random(
            6, amplitude_rms_mm=0.0007 * scale, wavelength_range_mm=(fov_mm / 4.0, fov_mm / 2.0),
            seed=seed)
        return forward.TravellingWaves(field.components)
    raise TirdeflectError(f"unknown --surface {name!r}; choose bump, dimple, waves or deep-dimple")


def _surface_at(scene, t_s: float):
    from processing import forward

    if isinstance(scene, forward.Surface):
        return scene
    return scene.at(t_s) if hasattr(scene, "at") else scene(t_s)


def _sim_amplitude(name, geometry, size, n_frames, seed, pattern, target_rad) -> tuple:
    """Amplitude factor making the largest carrier phase ``target_rad``.

    The phase is ``|k_s . u|`` with ``u`` the exact displacement (ray traced,
    on a 64 x 64 subgrid) and ``k_s`` the carriers found on the rendered flat
    reference; it is evaluated at the first and last frame times (phase is
    linear in amplitude while rays do not cross). Returns (factor, phase at
    factor 1).
    """
    from processing import forward
    from processing.carriers import find_carriers

    shape = (size, size)
    flat, _ = forward.render(forward.FlatSurface(), geometry, shape, pattern)
    k = find_carriers(flat).wavevectors  # (2, 2) rad/px, (row, col)
    sub = np.linspace(0, size - 1, min(size, 64))
    scene = _sim_scene(name, geometry, size, n_frames, seed)
    phase = 0.0
    for t_s in {0.0, (n_frames - 1) / SIM_FPS}:
        u, _ = forward.true_displacement(_surface_at(scene, t_s), geometry, shape,
                                         rows_px=sub, cols_px=sub)
        phase = max(phase, float(np.nanmax(np.abs(np.tensordot(k, u, axes=([1], [0]))))))
    if not phase > 0:
        raise TirdeflectError(f"--surface {name} moves no pattern point in this geometry; "
                              f"check --geometry")
    return target_rad / phase, phase


def cmd_simulate(args) -> int:
    """Run ``tirdeflect simulate``; returns the exit status (errors raise)."""
    from processing import Geometry, forward

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise TirdeflectError(f"--out {str(out)!r} exists and is not a directory; choose a directory")
    if out.is_dir() and any(out.glob("reference.*")) and not args.overwrite:
        raise OutputExistsError(
            f"{str(out)!r} already holds a simulated data set; choose another --out or add --overwrite"
        )
    if not math.isfinite(args.noise) or args.noise < 0:
        raise TirdeflectError(f"--noise must be a finite RMS >= 0 grey levels; got {args.noise}")
    if args.size < 96:
        raise TirdeflectError(f"--size must be at least 96 px (about ten pattern periods, what the "
                              f"carrier search needs); got {args.size}")
    if args.geometry:
        geometry = _load_geometry(args.geometry)
    else:
        geometry = Geometry.from_dict(dict(DEFAULT_SIM_GEOMETRY))
    pattern = forward.Checkerboard(period_mm=SIM_PATTERN_PERIOD_PX * geometry.pixel_mm,
                                   edge_softness_mm=geometry.pixel_mm)
    target = SIM_MAX_PHASE_RAD[args.surface] if args.max_phase is None else args.max_phase
    if not (math.isfinite(target) and target > 0):
        raise TirdeflectError(f"--max-phase must be a positive number of radians; got {target}")
    factor, _ = _sim_amplitude(args.surface, geometry, args.size, args.frames, args.seed,
                               pattern, target)
    scene = _sim_scene(args.surface, geometry, args.size, args.frames, args.seed, factor)
    sim = forward.simulate(
        scene, geometry, (args.size, args.size), args.frames, pattern=pattern, fps=SIM_FPS,
        bits=args.bits, noise_rms=args.noise, seed=args.seed,
    )
    out.mkdir(parents=True, exist_ok=True)
    args.max_phase = target
    _write_simulation(out, sim, geometry, args)
    return 0


def _write_simulation(out: Path, sim, geometry, args) -> None:
    import h5py

    suffix = ".png" if args.bits <= 8 else ".tif"
    imageio.write_image(out / f"reference{suffix}", sim.reference)
    names = []
    for k, frame in enumerate(sim.frames):
        name = f"frame_{k:04d}{suffix}"
        imageio.write_image(out / name, frame)
        names.append(name)
    geometry_text = geometry.to_toml_text()
    (out / "geometry.toml").write_text(geometry_text, encoding="utf-8")
    heights = np.asarray(sim.heights_mm, dtype=np.float32)
    with h5py.File(out / "heights.h5", "w") as f:
        ds = f.create_dataset("height", data=heights, chunks=(1, *heights.shape[1:]))
        ds.attrs["units"] = "mm"
        ds.attrs["description"] = (
            "true surface height sampled where each pixel's camera ray meets the surface")
        lost = f.create_dataset("lost", data=np.asarray(sim.lost, dtype=np.uint8),
                                chunks=(1, *heights.shape[1:]))
        lost.attrs["description"] = "1 where TIR is lost or rays cross (unmeasurable)"
        f.create_dataset("time_s", data=np.asarray(sim.times_s, dtype=np.float64))
        f.create_dataset("frame_file", data=np.array(names, dtype=object),
                         dtype=h5py.string_dtype())
        f.attrs["surface"] = args.surface
        f.attrs["max_phase_rad"] = args.max_phase
        f.attrs["bits"] = args.bits
        f.attrs["noise_rms"] = args.noise
        f.attrs["seed"] = args.seed
        f.attrs["pattern_period_mm"] = SIM_PATTERN_PERIOD_PX * geometry.pixel_mm
        f.attrs["geometry_toml"] = geometry_text
        f.attrs["software_version"] = _version()
        f.attrs["created_utc"] = _utc_now()
    hmax = float(np.max(np.abs(heights))) * 1e3
    print(f"tirdeflect: wrote reference, {len(names)} frame(s) ({args.bits} bit), heights.h5 "
          f"(max |h| {hmax:.2f} um) and geometry.toml to {out}", file=sys.stderr)
