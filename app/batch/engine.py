"""The batch engine: a reference and frames in, heights to an HDF5 file out.

One engine for every caller: ``tirdeflect process`` (:mod:`app.cli.process`),
the GUI's export and any script. :func:`run_process` reads the inputs (see
:mod:`app.files.imageio`), reconstructs each frame with
:class:`processing.Reconstructor` and writes them with
:class:`app.batch.writer.ResultWriter`, frame by frame and flushed after each,
so that a crash or a bad frame leaves every completed frame readable, with
``frames_done`` saying how many.
"""

from __future__ import annotations

import dataclasses
import logging
import shlex
import sys
from pathlib import Path

import numpy as np

from app.files import imageio
from processing.errors import (
    AllInvalidError,
    ShapeMismatchError,
    TirdeflectError,
)

from app import version as _version
from app.batch.writer import (
    OUTPUT_FORMAT_VERSION,
    ResultWriter,
    carrier_attrs,
    check_output,
    geometry_attrs,
    set_attrs,
    utc_now,
)

__all__ = ["ProcessJob", "BatchReport", "run_process", "load_geometry", "check_input_file",
           "MEASURE_MIN_FRAMES"]

log = logging.getLogger(__name__)

#: With --fft-effort auto, batches of at least this many frames plan FFTs with
#: FFTW_MEASURE (measured: 1024 x 1024 FS-SS frames 0.69 -> 0.53 s each, for
#: about 5 s of planning once; the wisdom is cached, so later runs skip it).
MEASURE_MIN_FRAMES = 20


def check_input_file(path: str, what: str) -> None:
    p = Path(path)
    if not p.exists():
        raise TirdeflectError(f"{what} {path!r} does not exist; check the path")
    if p.is_dir():
        raise TirdeflectError(f"{what} {path!r} is a directory; give the file itself")


def load_geometry(path: str):
    check_input_file(path, "geometry file")
    from processing import Geometry

    return Geometry.from_toml(path)


def _resolve_geometry(args):
    """(Geometry, where it came from): --geometry, else a recording's /geometry_toml."""
    if args.geometry is not None:
        return load_geometry(args.geometry), str(args.geometry)
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



@dataclasses.dataclass
class ProcessJob:
    """Everything one batch run needs (the fields of ``tirdeflect process``'s options).

    Attributes
    ----------
    reference : str
        Reference image file, or a recording holding a ``/reference``.
    frames : list of str
        Frame files, stacks or recordings, in order.
    out : str
        Output HDF5 file (docs/output-format.md).
    geometry : str or None
        Geometry TOML file; None takes a recording's stored geometry.
    grid : {"full", "decimated"}
    no_unwrap : bool
    first, last, step : int
        Frame selection over the whole input sequence (``last`` inclusive, None = end).
    overwrite : bool
    compression : {"none", "gzip", "lzf"}
    fft_effort : {"auto", "estimate", "measure"}
    no_progress : bool
        No progress bar on stderr.
    reference_index : int or None
        Page/frame of a stack or recording to use as the reference.
    on_progress : callable or None
        ``on_progress(done, total)`` after each frame is written and flushed (the GUI's export).
    command : str or None
        The command line, stored in the output's attributes.
    """

    reference: str
    frames: list
    out: str
    geometry: str | None = None
    grid: str = "full"
    no_unwrap: bool = False
    first: int = 0
    last: int | None = None
    step: int = 1
    overwrite: bool = False
    compression: str = "none"
    fft_effort: str = "auto"
    no_progress: bool = True
    reference_index: int | None = None
    on_progress: object = None
    command: str | None = None

    @classmethod
    def from_namespace(cls, args) -> "ProcessJob":
        """The job of an argparse namespace of ``tirdeflect process``."""
        names = {f.name for f in dataclasses.fields(cls)}
        values = {k: v for k, v in vars(args).items() if k in names}
        argv = getattr(args, "_argv", None)
        if argv:
            values["command"] = shlex.join(["tirdeflect", *argv])
        return cls(**values)


@dataclasses.dataclass
class BatchReport:
    """What a batch run wrote: ``frames_written`` frames to ``out``; ``notes`` for the user;
    ``pin``: one line naming where the height offset was pinned (empty if unknown)."""

    out: Path
    frames_written: int
    notes: list
    pin: str = ""


def run_process(args: ProcessJob) -> BatchReport:
    """Process the frames of ``args`` (a :class:`ProcessJob`) into ``args.out``.

    Errors the user can fix raise :class:`TirdeflectError` subclasses whose
    message says which frame failed and what was saved before it.
    """
    out = Path(args.out)
    check_output(out, args.overwrite)

    # Cheap checks of every input before any work: existence, directories,
    # stack/recording headers; decoding errors of plain images show up per frame.
    check_input_file(args.reference, "reference")
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
    reference_index = args.reference_index
    reference = imageio.read_reference(args.reference, index=reference_index)

    from app.files import cache

    cache.restore_fftw_wisdom()
    effort = args.fft_effort
    if effort == "auto":
        effort = "measure" if selected >= MEASURE_MIN_FRAMES else "estimate"
    reconstruct = _make_reconstructor(reference, geometry, unwrap=not args.no_unwrap, grid=args.grid,
                                      effort=effort)
    if hasattr(reconstruct, "reset_series"):
        reconstruct.reset_series()

    geometry_toml, geometry_info = geometry_attrs(geometry)
    attrs = {
        "software": "tirdeflect",
        "software_version": _version(),
        "format_version": OUTPUT_FORMAT_VERSION,
        "created_utc": utc_now(),
        "command": args.command or "(called from Python, not the command line)",
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
    writer = ResultWriter(
        out, overwrite=args.overwrite, compression=args.compression, attrs=attrs,
        geometry_toml=geometry_toml, geometry_attrs=geometry_info,
        carrier_attrs=carrier_attrs(getattr(reconstruct, "carriers", None)),
        reference=reference, expected=selected,
    )
    pins = _PinCounter(reconstruct)
    pins.write_region(writer)
    status = "failed"
    flagged = _FlagCounter()
    progress = _progress(selected, disable=args.no_progress)
    on_progress = args.on_progress
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
            pins.add(item, result)
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
            set_attrs(writer.f, {**flagged.attrs(), **pins.attrs()})
        writer.close(status)
        if status != "complete" and writer.n == 0:
            # nothing worth keeping: do not leave a file that blocks the next attempt
            try:
                out.unlink()
            except OSError:
                pass
        cache.store_fftw_wisdom()
    return BatchReport(out=out, frames_written=writer.n, notes=flagged.notes() + pins.notes(),
                       pin=pins.summary())


class _PinCounter:
    """Where each frame's height offset was pinned, and the frames flagged as jumps
    (Result.pin, Result.series): never silent, in the summary and the file."""

    def __init__(self, reconstruct):
        self.region = getattr(reconstruct, "reference_region", None)
        self.name = getattr(reconstruct, "reference_region_name", "")
        self.reference_valid_fraction = getattr(reconstruct, "reference_region_valid_fraction", float("nan"))
        self.fallback = getattr(reconstruct, "pin_fallback", "")
        self.rows_px = getattr(reconstruct, "rows_px", None)
        self.cols_px = getattr(reconstruct, "cols_px", None)
        self.frames = 0
        self.nearest = []
        self.jumps = []  # (sequence index, reason)
        self.min_valid = None

    def write_region(self, writer) -> None:
        if self.region is None:
            return
        writer.write_pin_region(self.region, self.rows_px, self.cols_px, {
            "region": self.name,
            "region_samples": int(np.count_nonzero(self.region)),
            "reference_valid_fraction": float(self.reference_valid_fraction),
            "fallback": self.fallback,
            "rule": ("pinned on the region's valid samples when at least max(16, 25 % of the region) are "
                     "valid; else on that many valid samples nearest the region ('nearest'), the same rule "
                     "for every frame (docs/processing.md, section 5)"),
        })

    def add(self, item, result) -> None:
        pin = getattr(result, "pin", None)
        if pin is None:
            return
        self.frames += 1
        if pin.rule != "region":
            self.nearest.append(item.sequence_index)
            # the first one loudly, the rest in the summary (a long series would flood the terminal)
            (log.warning if len(self.nearest) == 1 else log.debug)(
                "frame %d (%s): %s", item.sequence_index, item.label, pin.describe())
        if self.min_valid is None or pin.valid_samples < self.min_valid[0]:
            self.min_valid = (pin.valid_samples, pin.region_samples)
        series = getattr(result, "series", None)
        if series is not None and series.flagged:
            self.jumps.append((item.sequence_index, series.reason))
            (log.warning if len(self.jumps) == 1 else log.debug)(
                "frame %d (%s) jumps against the previous frame: %s", item.sequence_index, item.label,
                series.reason)

    def attrs(self) -> dict:
        return {"pin_region": self.name, "frames_pin_fallback": len(self.nearest),
                "frames_flagged_jump": len(self.jumps)}

    def summary(self) -> str:
        if not self.frames:
            return ""
        n_region = 0 if self.region is None else int(np.count_nonzero(self.region))
        text = (f"height offset pinned on the {self.name} ({n_region} samples where the reference is valid) "
                f"in {self.frames - len(self.nearest)} of {self.frames} frame(s)")
        if self.min_valid is not None and n_region:
            text += f", at least {self.min_valid[0]} of its samples valid"
        if self.nearest:
            text += (f"; {len(self.nearest)} frame(s) on the valid samples nearest it (fallback), "
                     f"e.g. frame {self.nearest[0]}")
        return text

    def notes(self) -> list:
        out = []
        if self.nearest:
            out.append(f"{len(self.nearest)} frame(s) had too few valid samples in the {self.name} and were "
                       f"pinned on the valid samples nearest it, e.g. frame {self.nearest[0]}: choose a "
                       f"reference_region where the surface is at rest and the pattern is sharp; see /pin_status")
        if self.jumps:
            idx, reason = self.jumps[0]
            out.append(f"{len(self.jumps)} frame(s) jump against the previous frame while the images do not "
                       f"explain it, e.g. frame {idx}: {reason}; see /pin_status")
        return out


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


def _frame_failed(exc: Exception, item, writer: ResultWriter) -> TirdeflectError:
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

