"""The batch engine: a reference and frames in, heights to an HDF5 file out.

One engine for every caller: ``tirdeflect process`` (:mod:`app.cli.process`),
the GUI's export and any script. :func:`run_process` reads the inputs (see
:mod:`app.files.imageio`), reconstructs each frame with
:class:`processing.Reconstructor` and writes them with
:class:`app.batch.writer.ResultWriter`, frame by frame and flushed at least
every ``writer.FLUSH_INTERVAL_S`` (0.5 s) and at the end, so that a crash
leaves every flushed frame readable, with ``frames_done`` saying how many. A
frame that cannot be measured is stored invalid with its reason and the run
goes on (:mod:`app.batch.frame_status`). The file is
written as ``NAME.partial.h5`` and renamed to the output only on success
(docs/reliability.md, "Processing").
"""

from __future__ import annotations

import dataclasses
import logging
import os
import shlex
import sys
from pathlib import Path

import numpy as np

from app.files import imageio
from processing.errors import (
    AllInvalidError,
    NoCarrierError,
    PatternMismatchError,
    ShapeMismatchError,
    TirdeflectError,
)
from processing.fullgrid import grid_surface_positions
from processing.live_view import reference_saturation
from processing.geometry import grazing_view_note
from processing.pin import band_moved, shift_alias_text, steady_shift
from processing.reference_average import departure_note, reconstructor_departure_px

from app import version as _version
from app.batch import parallel
from app.batch.frame_status import FrameStatus, FrameTally, frame_digest
from app.batch.writer import (
    MAP_BYTES_PER_SAMPLE,
    OUTPUT_FORMAT_VERSION,
    ResultWriter,
    carrier_attrs,
    check_not_an_input,
    check_output,
    geometry_attrs,
    partial_path,
    publish,
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
    from processing import Geometry
    from processing.errors import GeometryError

    if isinstance(args.geometry, Geometry):
        return args.geometry, "(given by the caller)"
    if args.geometry is not None:
        return load_geometry(args.geometry), str(args.geometry)
    files = [] if _given_image(args.reference) else [args.reference]
    for path in (*files, *imageio.expand_inputs(args.frames[:1])[:1]):
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


REFINE_METHODS = ("auto", "image", "fd")


def batch_refine_method(requested: str, shape, pattern: str, grid: str, device: str = "cpu") -> str:
    """The refinement a batch run uses: ``"image"`` (image matching for the
    height, :mod:`processing.dic`) or ``"fd"``, as
    :func:`processing.options.full_grid_refinement` chooses for every caller
    (``"auto"``, the default: image matching where it applies).  An explicit
    ``"image"`` where it cannot apply raises :class:`TirdeflectError` saying why.
    """
    from processing.options import ReconstructOptions, full_grid_refinement

    if requested not in REFINE_METHODS:
        raise TirdeflectError(f"refine method must be one of {', '.join(REFINE_METHODS)}; got {requested!r}")
    options = ReconstructOptions(grid=grid, device=device, refine_method=requested)
    method, why = full_grid_refinement(options, shape, pattern)
    if requested == "image" and why is not None:
        raise TirdeflectError(f"--refine image cannot be used here: {why}; use --refine fd (or auto)")
    return method


def job_options(args, shape, geometry, effort: str):
    """The :class:`processing.ReconstructOptions` of a batch job (``args``: a
    :class:`ProcessJob`), refinement resolved (:func:`batch_refine_method`),
    one FFT thread per core of this process: the one value the engine, its
    worker processes, Dask tasks and GPU batches build their Reconstructors from."""
    from processing import ReconstructOptions

    pattern = args.pattern or geometry.pattern or "checkerboard"
    refine_method = batch_refine_method(args.refine_method, shape, pattern, args.grid, args.device)
    return ReconstructOptions(grid=args.grid, unwrap=not args.no_unwrap, pattern=args.pattern,
                              refine_method=refine_method, turn_removal=args.turn_removal,
                              shift_removal=bool(args.shift_removal),
                              planner_effort="FFTW_MEASURE" if effort == "measure" else "FFTW_ESTIMATE",
                              threads=parallel.fft_threads(1))


@dataclasses.dataclass
class ProcessJob:
    """Everything one batch run needs (the fields of ``tirdeflect process``'s options).

    Attributes
    ----------
    reference : str or ndarray
        Reference image file, or a recording holding a ``/reference``; or the
        reference image itself (e.g. the one the GUI captured; counts).
    frames : list of str
        Frame files, stacks or recordings, in order.
    out : str
        Output HDF5 file (docs/output-format.md).
    geometry : str, Geometry or None
        Geometry TOML file, or a :class:`processing.Geometry`; None takes a
        recording's stored geometry.
    grid : {"full", "decimated"}
    no_unwrap : bool
    turn_removal : {"none", "camera", "board"}
        A flagged turn since the reference left in, or taken out as the camera's or the board's
        (:class:`processing.ReconstructOptions`).
    shift_removal : bool
        A shift of the whole pattern since the reference (a water level that changed, a camera or
        board that moved) taken out of the heights where flagged (:class:`processing.ReconstructOptions`).
    first, last, step : int
        Frame selection over the whole input sequence (``last`` inclusive, None = end).
    frame_range : slice or None
        ``--frames START:STOP:STEP`` (Python slice over the whole input sequence,
        STOP exclusive, negatives from the end); replaces first/last/step.
    reference_frames : slice or None
        ``--reference-frames 0:20``: the reference is the mean of these frames of
        ``reference`` (which may be the same file as the frames).
    overwrite : bool
    compression : {"none", "gzip", "lzf"}
    fft_effort : {"auto", "estimate", "measure"}
    no_progress : bool
        No progress bar on stderr.
    strict : bool
        Stop at the first frame that cannot be measured (default: store it
        invalid with its reason and go on).
    reference_index : int or None
        Page/frame of a stack or recording to use as the reference.
    on_progress : callable or None
        ``on_progress(done, total)`` after each frame is written (the GUI's export); the file's
        ``frames_done`` follows at the next flush, at most ``writer.FLUSH_INTERVAL_S`` later.
    command : str or None
        The command line, stored in the output's attributes.
    pattern : {"checkerboard", "dots"} or None
        What the reference shows; None takes the geometry's ``pattern`` key.
    workers : int or None
        Processes reconstructing frames (:mod:`app.batch.parallel`): None = all cores
        for long runs, 1 = in this process.
    dask : str or None
        ``local[:N]`` or ``tcp://HOST:8786``: on a Dask cluster instead (docs/cluster.md).
    send_frames : bool
        With ``dask``: read frames here and send them with the tasks (workers
        without the input files); otherwise workers read the files themselves.
    chunk_frames : int or None
        Frames per parallel chunk (None: chosen from frames, workers and memory).
    device : {"cpu", "cuda"}
        "cuda": batches of frames on the GPU (processing/gpu.py, needs CuPy).
    refine_method : {"auto", "image", "fd"}
        "auto" (default): image matching for the height (``refine_method="image"``
        of :class:`processing.Reconstructor`) where it applies, else FD's
        refinement (:func:`batch_refine_method`); "fd": FD's refinement only
        (about 5x faster, less accurate on features a few carrier periods wide).
    """

    reference: object  # str (a file) or ndarray (the image)
    frames: list
    out: str
    geometry: object = None  # str (a TOML file), Geometry, or None
    grid: str = "full"
    no_unwrap: bool = False
    turn_removal: str = "none"
    shift_removal: bool = False
    first: int = 0
    last: int | None = None
    step: int = 1
    overwrite: bool = False
    compression: str = "none"
    fft_effort: str = "auto"
    no_progress: bool = True
    strict: bool = False
    reference_index: int | None = None
    on_progress: object = None
    command: str | None = None
    frame_range: slice | None = None
    reference_frames: slice | None = None
    pattern: str | None = None
    workers: int | None = None
    dask: str | None = None
    send_frames: bool = False
    chunk_frames: int | None = None
    device: str = "cpu"
    refine_method: str = "auto"

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
    """What a batch run wrote: ``frames_written`` frames to ``out``, of which
    ``frames_invalid`` could not be measured (``invalid_summary`` says why);
    ``frames_incomplete`` were recorded INCOMPLETE; ``notes`` for the user;
    ``pin``: one line naming where the height offset was pinned (empty if unknown)."""

    out: Path
    frames_written: int
    notes: list
    pin: str = ""
    frames_invalid: int = 0
    invalid_summary: str = ""
    frames_incomplete: int = 0

    @property
    def clean(self) -> bool:
        """Every frame measured and none recorded INCOMPLETE."""
        return self.frames_invalid == 0 and self.frames_incomplete == 0


def run_process(args: ProcessJob) -> BatchReport:
    """Process the frames of ``args`` (a :class:`ProcessJob`) into ``args.out``.

    The output is written to ``NAME.partial.h5`` beside ``args.out`` and
    renamed to ``args.out`` only when the run succeeded (with ``overwrite``
    the old file is replaced then, not before). A frame that cannot be
    measured is stored invalid with its reason (:mod:`app.batch.frame_status`)
    and the run goes on, unless ``args.strict``.

    Errors the user can fix raise :class:`TirdeflectError` subclasses whose
    message says which frame failed and where the frames before it are kept:
    a run that fails or is interrupted leaves them in ``NAME.partial.h5``,
    or nothing when no frame was measured. Refused before anything is
    written: an ``out`` that is one of the inputs, a pattern that does not
    match the reference before any frame matched it.
    """
    out = Path(args.out)
    check_output(out, args.overwrite)
    reference_given = _given_image(args.reference)
    check_not_an_input(out, [p for p in (args.reference, *args.frames, args.geometry)
                             if isinstance(p, (str, os.PathLike))])

    # Cheap checks of every input before any work: existence, directories,
    # stack/recording headers; decoding errors of plain images show up per frame.
    if reference_given:
        if args.reference_frames is not None or args.reference_index is not None:
            raise TirdeflectError("reference_frames and reference_index choose frames of a reference "
                                  "file; the reference given is an image")
    elif args.reference_frames is None:
        check_input_file(args.reference, "reference")
    if not args.frames:
        # a recording that stores its reference is a complete input (docs/cluster.md)
        if args.reference_frames is None and (reference_given or not imageio.recording_has_reference(args.reference)):
            raise TirdeflectError("no frames given: add the FRAME files after the reference (or "
                                  "--reference-frames A:B to take the reference from the frames' file)")
        args.frames = [args.reference]
    paths, reference_notes = _frames_without_the_reference(args, imageio.expand_inputs(args.frames))
    if args.reference_frames is not None:
        _check_range_within(args.reference_frames, imageio.count_frames(imageio.expand_inputs([args.reference])),
                            "--reference-frames", f"the reference file {str(args.reference)!r}")
    # an image or TIFF that cannot be opened (empty, header damaged) is one unreadable frame
    # of the run, stored invalid with its reason (imageio.stands_for_one_frame)
    counts = [imageio.frame_count(path, unreadable_as_frame=True) for path in paths]
    total = sum(counts)
    _apply_frame_range(args, total)
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
    if reference_given:  # as given: stored as read, its saturation judged at its own depth (below)
        reference = np.asarray(args.reference)
        if reference.dtype.kind not in "uif":
            reference = reference.astype(np.float64)
    else:
        reference = imageio.read_reference(args.reference, index=reference_index, frames=args.reference_frames,
                                           pattern=args.pattern or geometry.pattern or "checkerboard")
    input_notes = reference_notes + imageio.input_notes(paths)
    depth_note = _bit_depth_note(reference, paths[0])
    if depth_note:
        input_notes.append(depth_note)
    for line in input_notes:
        log.warning("%s", line)
    timing = _timing_attrs(paths[0])

    from app.files import cache

    cache.restore_fftw_wisdom()
    effort = args.fft_effort
    if effort == "auto":
        effort = "measure" if selected >= MEASURE_MIN_FRAMES else "estimate"
    from processing import Reconstructor

    options = job_options(args, np.shape(reference), geometry, effort)
    refine_method = options.refine_method
    try:
        reconstruct = Reconstructor(reference, geometry, options)
    except NoCarrierError as exc:  # which input: the reference
        where = "the reference" if reference_given else f"the reference {str(args.reference)!r}"
        raise NoCarrierError(f"{where}: {exc}") from None
    reconstruct.reset_series()
    # a float reference given (the window's: frames averaged) or averaged from an integer file is judged as the
    # camera's counts; the window's 8-bit reference had read 20 % saturated (its 229 taken as the top code)
    reference_saturated = reference_saturation(
        reference, averaged_counts=(reference.dtype.kind == "f") if reference_given else _integer_file(args.reference))

    def say(note: str) -> None:  # a note on the inputs: warned now, and again among the run's closing notes
        if note:
            log.warning("%s", note)
            input_notes.append(note)

    say(reference_saturated[1] if reference_saturated else "")
    # a reference taken while the water moved: every height is measured against its waves
    say(departure_note(reconstructor_departure_px(reconstruct)))
    if reconstruct.pattern == "dots":  # too few dots a window: PIV's heights degrade, said once
        from processing.piv import sparse_dots_note

        say(sparse_dots_note(reference, window_px=options.window_px))
    if reconstruct.mosaic is not None:  # a colour camera read raw: equalised, said once
        input_notes.append(reconstruct.mosaic.describe())
    say(reconstruct.chain.board_note)  # the board 2-4.5 % off the geometry's, a keystone not its camera's
    say(grazing_view_note(geometry))

    geometry_toml, geometry_info = geometry_attrs(geometry)
    attrs = {
        "software": "tirdeflect",
        "software_version": _version(),
        "format_version": OUTPUT_FORMAT_VERSION,
        "created_utc": utc_now(),
        "command": args.command or "(called from Python, not the command line)",
        "reference_file": "(an image given by the caller)" if reference_given else str(args.reference),
        "reference_index": -1 if reference_index is None else reference_index,
        "reference_frames": _slice_text(args.reference_frames),
        "geometry_file": geometry_source,
        "input_files": [str(p) for p in paths],
        "first": args.first,
        "last": -1 if args.last is None else args.last,
        "step": args.step,
        "unwrap": not args.no_unwrap,
        "turn_removal": args.turn_removal,
        "shift_removal": bool(args.shift_removal),
        "grid_requested": args.grid,
        "refine_method": refine_method,
        "fft_effort": effort,
        "strict": bool(args.strict),
        "height_units": "mm",
        "reference_bits": (_bits_of_counts(args.reference) if reference_given
                           else _bits_hint(args.reference, reference)),
        "stuck_pixels_repaired": int(reconstruct.defects.size),
        "reference_saturated_pct": reference_saturated[0] if reference_saturated else 0.0,
        "mosaic_gains": ([] if reconstruct.mosaic is None
                         else [float(g) for g in reconstruct.mosaic.gains().ravel()]),
        **timing,
    }
    for attempt in range(5):  # another run beside this one may take the name first
        partial = partial_path(out)
        try:
            writer = ResultWriter(
                partial, compression=args.compression, attrs=attrs,
                geometry_toml=geometry_toml, geometry_attrs=geometry_info,
                carrier_attrs=carrier_attrs(getattr(reconstruct, "carriers", None)),
                reference=reference, expected=selected,
                grid_coords=reconstruct.grid_coordinates(args.grid), grid=args.grid,
                surface_positions=grid_surface_positions(reconstruct.geometry, reconstruct.shape, args.grid,
                                                         reconstruct.rows_px, reconstruct.cols_px),
            )
            break
        except FileExistsError:
            if attempt == 4:
                raise
    room_note = output_room_note(writer, selected, args.grid, args.compression, reconstruct)
    if room_note:  # said before the run, which will stop when the disk is full
        log.warning("%s", room_note)
    pins = _PinCounter(reconstruct)
    pins.write_region(writer)
    status = "failed"
    tally = FrameTally(reference_digest=frame_digest(reference))
    progress = _progress(selected, disable=args.no_progress)
    on_progress = args.on_progress
    frames = None
    try:
        # (item, measured) in order: here, over processes or on Dask (app/batch/parallel.py)
        frames = parallel.frame_results(args, reconstruct, reference, geometry, selected, paths)
        while True:
            try:
                item, measured = next(frames)
            except StopIteration:
                break
            except TirdeflectError as exc:  # a whole file became unreadable
                raise _frame_failed(exc, None, writer, out) from exc
            result, outcome = measured()  # (Result, OK), or (None, why the frame is invalid)
            if outcome.status == FrameStatus.PATTERN_MISMATCH and tally.valid == 0:
                # no frame has matched the reference yet: it is the reference that is wrong
                raise _frame_failed(PatternMismatchError(outcome.reason + _none_matched_before(tally)), item,
                                    writer, out)
            if not outcome.ok and args.strict:
                raise _frame_failed(_error_of(outcome), item, writer, out, strict=True)
            try:
                writer.append(item, result, outcome)
            except (TirdeflectError, OSError) as exc:  # disk full while writing
                raise _frame_failed(exc, item, writer, out) from exc
            if result is None and hasattr(reconstruct, "reset_series"):
                reconstruct.reset_series()  # no temporal unwrapping across a hole
            tally.add(item, outcome)  # (the writer logs "frame K ... written" once it is flushed)
            pins.add(item, result)
            progress.update(1)
            if on_progress is not None:
                on_progress(writer.n, selected)
        if tally.valid == 0:
            raise _frame_failed(_error_of_none_valid(tally), None, writer, out, whole_run=True)
        status = "complete" if tally.n_invalid == 0 else f"complete, {tally.n_invalid} frame(s) invalid"
    except KeyboardInterrupt:
        status = f"interrupted after {writer.n} frame(s)"
        raise
    except BaseException as exc:
        status = f"failed after {writer.n} frame(s): {exc}"
        raise
    finally:
        progress.close()
        if frames is not None:
            frames.close()
        writer.close(status, {**tally.attrs(), **pins.attrs(), **(frames.attrs if frames is not None else {})})
        if status.startswith("complete"):
            publish(partial, out, overwrite=args.overwrite)
        else:
            _keep_or_drop(args, status, writer, selected, out)
        cache.store_fftw_wisdom()
    return BatchReport(out=out, frames_written=writer.n, notes=input_notes + tally.notes() + pins.notes(),
                       frames_invalid=tally.n_invalid, invalid_summary=tally.invalid_summary(),
                       frames_incomplete=len(tally.incomplete), pin=pins.summary())


def output_room_note(writer: ResultWriter, selected: int, grid: str, compression: str, reconstruct) -> str:
    """What the output will take where that is more than its disk (or file size limit) has left, with
    what to do (``reconstruct``: the run's Reconstructor, for the decimated grid's size); "" where it fits. The maps are stored on every sample of the grid (a full-grid
    frame of 512^2 takes 3.4 MB, 13x a recorded 8-bit frame); the run itself stops, keeping what
    it wrote, when the room is gone (:class:`app.batch.writer.DiskFullError`): this says so before
    it starts, not after minutes of measuring."""
    from app.sizes import format_bytes

    frame = writer.frame_bytes
    projected = frame * int(selected)
    room, what = writer.frames_room()
    if projected <= room:
        return ""
    rows, cols = writer.grid_shape
    packed = compression not in (None, "none")
    smaller = []
    if grid != "decimated":
        x_mm, y_mm = reconstruct.grid_coordinates("decimated")
        n_dec = len(x_mm) * len(y_mm)
        smaller.append(f"--grid decimated ({format_bytes(n_dec * MAP_BYTES_PER_SAMPLE)} a frame)")
    if not packed:
        smaller.append("--compression gzip (a third smaller on the synthetic tank's maps)")
    smaller.append("fewer frames (--step, --first, --last)")
    return (f"the output will take {'up to ' if packed else ''}{format_bytes(projected)} ({selected} frame(s) of "
            f"{format_bytes(frame)}: height, two slopes and the valid mask on the {rows} x {cols} samples of "
            f"the {grid} grid), more than the {format_bytes(room)} left ({what}, {str(writer.path.parent)!r}): "
            f"the run will stop when it is full, keeping the frames written and saying how to go on; write "
            f"--out to a disk with room, or a smaller output: {', '.join(smaller)}")


def _keep_or_drop(args, status: str, writer: ResultWriter, selected: int, out: Path) -> None:
    """After a run that did not complete: keep its partial file where it holds a measured frame,
    and say where it is (after an interrupt, also where to go on); else remove it (no file that
    blocks the next attempt) and, after an interrupt, say that none was kept. An error's own
    message says the same (:func:`_frame_failed`). Alike for frames measured here and for frames
    that come back from worker processes a chunk at a time."""
    interrupted = status.startswith("interrupted")
    # the writer's own count, not the run's tally: an interrupt can land between a frame's append and its tally
    if writer.measured:
        log.warning("the %d frame(s) written are kept in %s%s", writer.n, writer.path,
                    _resume_text(args, writer.n, selected) if interrupted else "")
        return
    try:
        writer.path.unlink()
    except OSError:
        pass
    if interrupted:
        done = ("before any frame was written" if writer.n == 0
                else f"after {writer.n} frame(s), none of them measured")
        log.warning("interrupted %s: none is kept, %s; run the command again", done, _nothing_written(out))


def _nothing_written(out: Path) -> str:
    """What became of ``out`` when a run keeps nothing."""
    return (f"nothing was written ({str(out)!r} left as it was)" if os.path.lexists(out)
            else f"nothing was written ({str(out)!r} not created)")


def _resume_text(args, written: int, selected: int) -> str:
    """How to process the selected frames an interrupted run did not write: every selected
    frame has its row in the output (an unmeasured one too), so the first missing one is
    ``first + written * step``."""
    if written >= selected:
        return ""
    last = "" if args.last is None else f" --last {args.last}"
    step = "" if args.step == 1 else f" --step {args.step}"
    return (f"; process the rest with `tirdeflect process ... --first {args.first + written * args.step}"
            f"{last}{step}` into another --out")


def _slice_text(s) -> str:
    if s is None:
        return ""
    return ":".join("" if v is None else str(v) for v in (s.start, s.stop, s.step))


def _apply_frame_range(args, total: int) -> None:
    """Turn ``--frames START:STOP:STEP`` into first/last/step over ``total`` frames."""
    sl = args.frame_range
    if sl is None:
        return
    if args.first != 0 or args.last is not None or args.step != 1:
        raise TirdeflectError("give either --frames START:STOP:STEP or --first/--last/--step, not both")
    _check_range_within(sl, total, "--frames", "the inputs")
    picked = range(total)[sl]
    if len(picked) == 0:
        raise TirdeflectError(
            f"--frames {_slice_text(sl)} selects no frame of the {total} input frame(s); "
            f"frames count from 0, STOP is exclusive")
    args.first, args.last, args.step = picked.start, picked[-1], picked.step


def _check_range_within(sl: slice, total: int, option: str, what: str) -> None:
    """Refuse a START:STOP whose explicit ends lie beyond ``total`` frames (Python's slice
    would clamp them in silence: 0:1000 of 15 frames would average 15 and store '0:1000:')."""
    beyond = [v for v in (sl.start, sl.stop) if v is not None and (v > total or v < -total)]
    if beyond and len(range(total)[sl]):  # (a range that selects nothing has its own message)
        raise TirdeflectError(
            f"{option} {_slice_text(sl).rstrip(':')} reaches frame {beyond[0]}, but {what} "
            f"hold{'s' if what.startswith('the reference') else ''} {total} frame(s) (0 to {total - 1}); "
            f"give a range within them, e.g. 0:{total} (or leave STOP out: 0: is every frame)")


def _frames_without_the_reference(args, paths: list) -> tuple:
    """The expanded inputs without the reference file where a folder or glob brought it in
    (a folder holding reference.png and the frames: the reference is not a frame of the series;
    listed by name, it stays). Returns (paths, notes)."""
    if _given_image(args.reference) or args.reference_frames is not None or args.reference_index is not None:
        return paths, []
    try:
        ref = Path(args.reference).resolve()
        named = {Path(p).resolve() for p in args.frames if isinstance(p, (str, os.PathLike))}
    except (OSError, TypeError):
        return paths, []
    if ref in named:
        return paths, []
    kept = [p for p in paths if Path(p).resolve() != ref]
    if len(kept) == len(paths) or not kept:
        return paths, []
    return kept, [f"the reference {str(args.reference)!r} is among the inputs (a folder or pattern brought it "
                  f"in): it is not processed as a frame ({len(kept)} frame file(s) left); name it after the "
                  f"reference to process it too"]


def _bit_depth_note(reference: np.ndarray, first_input) -> str:
    """A note when the frames' levels cannot match the reference's: frames brighter than the reference's
    depth holds (a 12-bit reference against 16-bit words, a float 0..1 reference), or a reference whose
    levels sit 16x higher than a frame's (12-bit data in the top bits of 16-bit words); else ''.  Where
    the frames' depth (their file's, or floats 0..1) keeps every frame darker than the quality mask reads
    (8-bit video frames against a 12-bit reference), TirdeflectError once: each frame had read 'no contrast'."""
    from processing.mask import MIN_EXPOSURE_GAIN
    from processing.options import ReconstructOptions

    # the darkest frames the quality mask still reads: contrast min_amplitude of the reference's, scaled
    # down by the exposure's gain to at most MIN_EXPOSURE_GAIN (0.3 x 0.25: 13x darker)
    readable = MIN_EXPOSURE_GAIN * ReconstructOptions().min_amplitude
    try:
        info = imageio.image_info(first_input)
    except TirdeflectError:
        return ""  # the reader says what is wrong with the file, frame by frame
    ref_top = float(np.nanmax(reference)) if np.size(reference) else 0.0
    ref_bits = _bits_of_counts(np.asarray(reference, dtype=np.float64))
    ref_name = (f"holds floats from 0 to {ref_top:.3g} (no camera's counts)"
                if np.asarray(reference).dtype.kind == "f" and 0 < ref_top <= 1.0 else
                f"is {ref_bits}-bit (levels up to {ref_top:.0f})")
    frame_float = np.dtype(info.dtype).kind == "f" or not info.bits
    if not frame_float and ref_top > 2 * (2 ** int(info.bits) - 1):  # frames cannot even hold its level
        top, frame_bits, known = 2.0 ** int(info.bits) - 1, int(info.bits), True
    else:
        try:
            sample = imageio.read_image(first_input, index=0 if info.n_frames > 1 else None)
        except Exception:  # noqa: BLE001 -- a first frame that cannot be read is reported as such later
            return ""
        top = float(np.nanmax(sample)) if sample.size else 0.0
        frame_bits, known = _bits_of_counts(sample.astype(np.float64)), frame_float and 0 < top <= 1.0
        if not (ref_top > 0 and top > 0 and (top > 2 * 2 ** ref_bits or ref_top * readable > top)):
            return ""
    ratio = ref_top / top
    frame_name = (f"hold floats from 0 to {top:.3g} (no camera's counts)" if frame_float and top <= 1.0 else
                  f"are {frame_bits}-bit (levels up to {top:.0f})")
    depths = f"bit depths differ: the frames of {str(first_input)!r} {frame_name} while the reference {ref_name}"
    if ratio < 1:
        return (f"{depths}: on one scale the frames are {1 / ratio:.3g}x brighter than the reference; the heights "
                f"(the pattern's phase) do not depend on it, but contrasts relative to the reference read "
                f"{1 / ratio:.3g}x high; for one scale take the reference from the frames' own file or camera "
                f"settings (e.g. --reference-frames 0:20)")
    if ref_top * readable <= top:
        return ""
    if known:  # every frame of this depth is darker than the quality mask reads: said once, not per frame
        scale = ("the frames as the camera's counts, or the reference scaled to 0..1 as well" if frame_float else
                 f"the reference's levels divided by {2 ** (ref_bits - frame_bits)}" if ref_bits > frame_bits else
                 "reference and frames at one depth")
        raise TirdeflectError(
            f"{depths}: on one scale the frames are {ratio:.3g}x darker than the reference, beyond the "
            f"{1 / readable:.3g}x a dimmer exposure still reads, so no frame could be measured; take the reference "
            f"from the frames' own file or camera settings (e.g. --reference-frames 0:20), or give {scale}")
    return (f"the frames of {str(first_input)!r} reach only level {top:.0f} ({frame_bits}-bit) while the reference "
            f"{ref_name}: the frames are {ratio:.3g}x darker, beyond the {1 / readable:.3g}x a dimmer exposure still "
            f"reads, so they read as low contrast; a reference stored with its levels shifted (12-bit data in the "
            f"top bits of 16-bit words: 16x) or taken at another exposure or gain? Take the reference from the "
            f"frames' own file or camera settings (e.g. --reference-frames 0:20)")


def _timing_attrs(path) -> dict:
    """Frame rate and trigger of the first input (video, MRAW, CINE), for the output's attrs."""
    try:
        info = imageio.image_info(path) if imageio.formats.kind_of(Path(path)) else None
    except TirdeflectError:
        return {}
    if info is None:
        return {}
    return {"input_frame_rate_hz": float(info.frame_rate_hz),
            "input_trigger_index": -1 if info.trigger_index is None else int(info.trigger_index),
            "input_codec": info.codec, "input_lossless": bool(info.lossless)}


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
        self.noted = []  # (sequence index, Result.note): e.g. the image refinement fell back to FD
        # (sequence index, PinStatus.region_motion_px, PinStatus.shifted) where the pattern moved on the pin
        # samples of the user's region (the shifted ones are said by the whole frame's shift)
        self.moving = []
        # the same on the default border band (processing.pin.band_moved: TIR only)
        self.setup = getattr(getattr(reconstruct, "geometry", None), "setup", "")
        self.band_moving = []  # (sequence index, PinStatus.region_motion_px)
        self.pieced = []  # (sequence index, PinStatus.pieces) of band_moving frames pinned in several pieces
        self.shifted = []  # (sequence index, PinStatus) where the whole pattern shifted (PinStatus.shifted)
        self.scaled = []  # (sequence index, PinStatus) where the image's scale changed (PinStatus.scaled)
        # every frame's median displacement (row, col px) not flagged alone: a recording shifted for its
        # whole length under waves that hide it frame by frame (processing.pin.steady_shift)
        self.medians = []
        self.height_solver = getattr(reconstruct, "height_solver", None)
        self.min_valid = None
        carriers = getattr(reconstruct, "carriers", None)  # None for random dots
        self.carrier_freq = None if carriers is None else carriers.freq

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
        elif self.min_valid is None or pin.valid_samples < self.min_valid[0]:  # of the frames pinned on the region
            self.min_valid = (pin.valid_samples, pin.region_samples)
        if pin.shifted:  # says more than the pin samples' motion, which it explains (their notes leave it out)
            self.shifted.append((item.sequence_index, pin))
            alias = self._alias(pin)
            (log.warning if len(self.shifted) == 1 else log.debug)(
                "frame %d (%s): %s%s", item.sequence_index, item.label, pin.shift_text(),
                f" ({alias})" if alias else "")
        elif np.isfinite(pin.frame_motion_row_px) and np.isfinite(pin.frame_motion_col_px):
            self.medians.append((pin.frame_motion_row_px, pin.frame_motion_col_px))
        if pin.scaled:
            self.scaled.append((item.sequence_index, pin))
            (log.warning if len(self.scaled) == 1 else log.debug)(
                "frame %d (%s): %s", item.sequence_index, item.label, pin.scale_text())
        if not pin.still:
            self.moving.append((item.sequence_index, pin.region_motion_px, pin.shifted))
            first = not pin.shifted and sum(not shifted for _, _, shifted in self.moving) == 1
            (log.warning if first else log.debug)(
                "frame %d (%s): %s", item.sequence_index, item.label, pin.describe())
        elif band_moved(pin.region, pin.rule, pin.region_motion_px, self.setup) and not pin.shifted:
            self.band_moving.append((item.sequence_index, pin.region_motion_px))
            if pin.pieces > 1:
                self.pieced.append((item.sequence_index, pin.pieces))
            log.debug("frame %d (%s): the pattern moved on the %s by %.3g px", item.sequence_index, item.label,
                      pin.region, pin.region_motion_px)
        note = getattr(result, "note", "")
        if note:
            self.noted.append((item.sequence_index, note))
            (log.warning if len(self.noted) == 1 else log.debug)(
                "frame %d (%s): %s", item.sequence_index, item.label, note)
        series = getattr(result, "series", None)
        if series is not None and series.flagged:
            self.jumps.append((item.sequence_index, series.reason))
            (log.warning if len(self.jumps) == 1 else log.debug)(
                "frame %d (%s) jumps against the previous frame: %s", item.sequence_index, item.label,
                series.reason)

    def _steady(self):
        """``(mean, spread, level_um, effect_um)`` where the frames not flagged alone were shifted for the
        whole recording (:func:`processing.pin.steady_shift`), else None."""
        found = steady_shift(self.medians)
        if found is None:
            return None
        mean, spread = found
        level_um = effect_um = float("nan")
        if self.height_solver is not None:
            hs = self.height_solver()
            level_um = hs.shift_level_um(mean)
            region = self.region if self.region is not None and np.shape(self.region) == hs.shape else None
            effect_um = hs.shift_effect_um(mean, None, region)
        return mean, spread, level_um, effect_um

    def _steady_px(self) -> float:
        found = steady_shift(self.medians)
        return float(np.hypot(*found[0])) if found is not None else 0.0

    def attrs(self) -> dict:
        return {"pin_region": self.name, "frames_pin_fallback": len(self.nearest),
                "frames_flagged_jump": len(self.jumps), "frames_noted": len(self.noted),
                "frames_pin_region_moving": len(self.moving), "frames_pin_band_moving": len(self.band_moving),
                "frames_pin_band_pieces": len(self.pieced),
                "frames_shifted": len(self.shifted), "steady_shift_px": self._steady_px(),
                "frames_scaled": len(self.scaled),
                "scale_pct_max": max((100 * abs(p.region_scale) for _, p in self.scaled), default=0.0)}

    def _alias(self, pin) -> str:
        """:func:`processing.pin.shift_alias_text` of a shifted frame's ``pin`` (PinStatus)."""
        return shift_alias_text((pin.frame_motion_row_px, pin.frame_motion_col_px), self.carrier_freq,
                                pin.shift_level_um)

    def summary(self) -> str:
        if not self.frames:
            return ""
        n_region = 0 if self.region is None else int(np.count_nonzero(self.region))
        text = (f"height offset pinned on the {self.name} ({n_region} samples where the reference is valid) "
                f"in {self.frames - len(self.nearest)} of {self.frames} frame(s)")
        if self.min_valid is not None and self.min_valid[1]:
            # a share: each frame was pinned on its own grid (the image refinement's nodes: finer than /pin_region's)
            valid, region = self.min_valid
            text += f", at least {100 * valid / region:.0f} % of it measured in each"
        if self.nearest:
            text += (f"; {len(self.nearest)} frame(s) on the valid samples nearest it (fallback), "
                     f"e.g. frame {self.nearest[0]}")
        return text

    def _pieced_text(self) -> str:
        """Of the frames whose band moved, those measured in pieces pinned apart (by-hand trial of 7 Dec 2026:
        steep waves in 6-9 pieces each pinned on its own part of the moving band, 19-49 % off, said only as
        "their heights hold there only")."""
        if not self.pieced:
            return ""
        k, most = max(self.pieced, key=lambda row: row[1])
        return (f". In {len(self.pieced)} of them the measured area fell into pieces (up to {most}, frame {k}), "
                f"each pinned on its own part of the band: their heights are offset from each other by the water's "
                f"motion there, besides that mode (/pin_status pieces)")

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
        unexplained = [(i, m) for i, m, shifted in self.moving if not shifted]
        if unexplained:
            moved = [m for _, m in unexplained]
            span = _span(moved)
            out.append(f"in {len(unexplained)} frame(s) the pattern moved in the {self.name}, where the geometry "
                       f"says the surface is at rest and the heights are pinned (median displacement there {span} "
                       f"px, e.g. frame {unexplained[0][0]}; at rest it is 0): the surface there is not at rest, or "
                       f"the camera or the board moved since the reference, which reads as a tilt of the heights "
                       f"(0.1 px: 10 % on a 4 um bump). Take the reference again if the set-up moved, or move the "
                       f"reference_region to where the surface is at rest; see /pin_status region_motion_px")
        if self.shifted:
            motion = [p.frame_motion_px for _, p in self.shifted]
            effect = [p.shift_effect_um for _, p in self.shifted if np.isfinite(p.shift_effect_um)]
            level = [p.shift_level_um for _, p in self.shifted if np.isfinite(p.shift_level_um)]
            text = (f"in {len(self.shifted)} of {self.frames} frame(s) the whole pattern shifted alike since the "
                    f"reference ({_span(motion)} px, e.g. frame {self.shifted[0][0]})")
            if level:
                text += (f", as a water level {_span(np.abs(level), '.3g')} um {_up_or_down(level)} "
                         f"would move it (evaporation, filling, displaced water), or a camera or board that moved")
            else:
                text += ": the camera or the board moved"
            alias = self._alias(self.shifted[0][1])
            alias = f" ({alias[0].upper()}{alias[1:]}.)" if alias else ""
            removed = all(p.shift_removed for _, p in self.shifted)
            if removed:
                out.append(text + "; taken out of the heights (--shift-removal: heights as a reference taken at each "
                           "frame would give, the level's change in /pin_status shift_level_um)" + alias)
            else:
                if effect:
                    text += (f"; the heights carry {_span(effect, '.3g')} um RMS from it, a tilt that is not the "
                             f"surface (/pin_status shift_effect_um)")
                settled = " (once the level has settled)" if level else ""
                out.append(text + f". Take the reference again as the set-up is now{settled}, or process with "
                           f"--shift-removal" + alias)
        if self.scaled:
            pct = [100 * p.region_scale for _, p in self.scaled]
            out.append(f"in {len(self.scaled)} of {self.frames} frame(s) the image's SCALE changed since the reference "
                       f"({_span(pct, '+.2g')} %, e.g. frame {self.scaled[0][0]}; the {self.name}'s samples moved "
                       f"outward or inward alike with their distance from its centre, where the surface is at "
                       f"rest): the lens refocused or zoomed, or the camera moved along its axis, and the heights "
                       f"carry a curved surface that is not there (a paraboloid: 0.2 % over a 512^2 frame put 120 % "
                       f"of a 4 um bump's heights into them; take the reference again as the camera is now), "
                       f"unless a wave far longer than the frame curves all of it; see /pin_status region_scale")
        steady = self._steady()
        if steady is not None:
            mean, spread, level_um, effect_um = steady
            text = (f"over {len(self.medians)} frame(s) the whole frame's median displacement sat at ({mean[0]:.2f}, "
                    f"{mean[1]:.2f}) px (rows, columns), {spread:.2f} px apart from frame to frame: what fills the "
                    f"frame moves it about 0, a shift since the reference keeps it there. ")
            if np.isfinite(level_um):
                text += (f"The water level is {abs(level_um):.3g} um {'higher' if level_um > 0 else 'lower'} than at "
                         f"the reference (evaporation, filling), or the camera or the board moved, ")
            else:
                text += "The camera or the board moved, "
            text += "or a wave longer than the frame tilted all of it for the whole recording"
            if np.isfinite(effect_um):
                text += f"; a shift puts {effect_um:.3g} um RMS into the heights, a tilt"
            out.append(text + ". Take the reference again as the set-up is now (/pin_status frame_motion_row_px)")
        if self.band_moving:
            moved = [m for _, m in self.band_moving]
            out.append(f"in {len(self.band_moving)} of {self.frames} frame(s) the pattern moved on the {self.name}, "
                       f"where the heights are pinned by default (median displacement there {min(moved):.2g}-"
                       f"{max(moved):.2g} px, e.g. frame {self.band_moving[0][0]}; features inside the frame leave it "
                       f"at 0): waves reaching it, or the camera or the board moved since the reference. The heights' "
                       f"part along exp(-T y/H), which no deflectometry measures, is then set by that motion: a few "
                       f"per cent of their RMS where waves reach it; where the set-up moved, a tilt that can be as "
                       f"large as the heights (waves filling the frame hide such a shift from the whole-frame test, "
                       f"/pin_status frame_shift_share). Give a reference_region where the water is still; see "
                       f"/pin_status region_motion_px" + self._pieced_text())
        if self.noted:
            idx, note = self.noted[0]
            out.append(f"{len(self.noted)} frame(s) carry a note on how they were measured, e.g. frame {idx}: "
                       f"{note}; see /frame_status_text")
        return out


def _span(values, fmt: str = ".2g") -> str:
    """``"lo-hi"`` of ``values`` at ``fmt`` (one number where both read the same)."""
    lo, hi = format(float(min(values)), fmt), format(float(max(values)), fmt)
    return lo if lo == hi else f"{lo}-{hi}"


def _up_or_down(levels) -> str:
    """"higher", "lower" or "higher or lower" of water level changes ``levels`` (um, up)."""
    return "higher" if min(levels) > 0 else "lower" if max(levels) < 0 else "higher or lower"


def _none_matched_before(tally: FrameTally) -> str:
    """Why a pattern mismatch stops the run where later it only makes the frame invalid: no frame before it
    matched the reference (by-hand trial of 7 Dec 2026: after four blank frames a stripes frame stopped the
    run, "nothing was written", with no word of why this frame and not the next)."""
    if tally.frames == 0:
        return " (the run's first frame: the reference is judged by it, and refused)"
    return (f" (no frame before it was measured: {tally.invalid_summary().split(' (first')[0]}; so the first "
            f"pattern seen is the one the reference is judged by, and the run stops; once a frame has matched, "
            f"a frame that does not is only stored invalid)")


def _error_of(outcome) -> TirdeflectError:
    """The error to raise for a bad frame under --strict."""
    kind = {FrameStatus.PATTERN_MISMATCH: PatternMismatchError,
            FrameStatus.NO_PATTERN: NoCarrierError,
            FrameStatus.SHAPE_MISMATCH: ShapeMismatchError,
            FrameStatus.UNREADABLE: imageio.ImageReadError}.get(outcome.status, AllInvalidError)
    return kind(f"{outcome.status.label}: {outcome.reason}")


def _error_of_none_valid(tally: FrameTally) -> TirdeflectError:
    k, label, reason = tally.first_invalid()
    kinds = {status.label for status in tally.invalid}
    more = "" if tally.frames == 1 else f" (all {tally.frames}: " + tally.invalid_summary().split(" (first")[0] + ")"
    exc = AllInvalidError(f"no frame could be measured{more}; frame {k} ({label}): {reason}")
    if kinds == {FrameStatus.UNREADABLE.label}:
        exc = imageio.ImageReadError(str(exc))
    return exc


def _frame_failed(exc: Exception, item, writer: ResultWriter, out: Path, *,
                  strict: bool = False, whole_run: bool = False) -> TirdeflectError:
    """The error to raise for a run that stops at ``item``: where, why, and what is kept."""
    if whole_run:
        where = None
    elif item is not None:
        where = f"frame {item.sequence_index} ({item.label})"
    elif getattr(exc, "sequence_index", None) is not None:
        where = f"frame {exc.sequence_index}"
    else:
        where = "reading the next frame"
    if writer.measured:
        saved = (f"the {writer.n} frame(s) before it are kept in {str(writer.path)!r} "
                 f"(valid up to frames_done; rename it to use it)")
        if writer.lost:
            saved += (f"; the {writer.lost} frame(s) written after the last flush are lost with the "
                      f"failed write")
    else:
        saved = _nothing_written(out)
    head = f"{where} failed: " if where else ""
    tail = " (--strict stops at the first bad frame)" if strict else ""
    message = f"{head}{exc}{tail}; {saved}"
    if isinstance(exc, TirdeflectError):
        return type(exc)(message)
    return TirdeflectError(message)


def _given_image(reference) -> bool:
    """Whether ``ProcessJob.reference`` is the image itself rather than a file."""
    return isinstance(reference, np.ndarray)


def _bits_of_counts(image: np.ndarray) -> int:
    """Sample bits of a reference given as an image: its integer type's, else the
    fewest of 8, 10, 12, 14, 16 that hold its largest count (a float average of frames)."""
    image = np.asarray(image)
    if image.dtype.kind in "ui":
        return int(image.dtype.itemsize * 8)
    top = float(np.nanmax(image)) if image.size else 0.0
    return next((b for b in (8, 10, 12, 14) if top < 2 ** b), 16)


def _integer_file(path) -> bool:
    """Whether the reference file ``path`` holds integer camera frames (those ``--reference-frames``
    averages into a float reference: :func:`processing.live_view.reference_saturation` judges it as
    their counts); False where that cannot be told (the file's own errors are reported elsewhere)."""
    try:
        return np.dtype(imageio.image_info(imageio.expand_inputs([path])[0]).dtype).kind in "ui"
    except Exception:  # noqa: BLE001
        return False


def _bits_hint(path: str, image: np.ndarray) -> int:
    try:
        path = imageio.expand_inputs([path])[0]
        return int(imageio.image_info(path).bits)
    except Exception:
        return int(image.dtype.itemsize * 8)



def _progress(total: int, *, disable: bool):
    import shutil

    from app.progress import progress_bar

    # a bar only when stderr is a terminal (log files stay clean); shutil falls back to 80 columns where the
    # terminal reports a width of 0
    return progress_bar(total, disable=disable, ncols=shutil.get_terminal_size().columns)

