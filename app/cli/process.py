"""``tirdeflect process`` (images to heights in HDF5) and ``tirdeflect simulate``.

``process`` reads a reference and frames (PNG/BMP/TIFF/TIFF stacks/HDF5
recordings, see :mod:`app.imageio`), reconstructs each frame with
:class:`processing.Reconstructor` and writes one HDF5 file laid out as
documented in ``docs/output-format.md``. The file is written frame by frame
and flushed at least every 0.5 s and at the end, so that a bad frame, an
error or a signal leaves every completed frame readable, and a crash every
frame but at most the last 0.5 s of them, with ``frames_done`` saying how many.

``simulate`` writes a synthetic data set (reference, frames, true heights,
geometry) made by exact ray tracing (:func:`processing.forward.simulate`),
so the whole chain can be checked before going to the tank::

    tirdeflect simulate --out sim
    tirdeflect process sim/reference.png sim/frame_*.png --geometry sim/geometry.toml --out out.h5

The work is done by :mod:`app.batch`; this module parses arguments and prints.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

from app.batch.compare import compare_heights, resolve_truth
from app.batch.engine import MEASURE_MIN_FRAMES, ProcessJob, check_input_file, run_process
from app.batch.simulate import run_simulate
from app.sizes import format_bytes
from app.stop_signals import STOP_SIGNALS
from processing.errors import TirdeflectError

__all__ = ["add_process_parser", "add_simulate_parser", "add_compare_parser",
           "cmd_process", "cmd_simulate", "cmd_compare"]


# =========================================================================== parsers


def whole_number(minimum: int, unit: str):
    """An argparse type: a whole number >= ``minimum``. Its refusal reads like the other
    range messages, ``--first must be >= 0 (frames count from 0); got -1``
    (:class:`app.cli.main.Parser` puts the option first)."""
    import argparse

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be a whole number >= {minimum} {unit}; got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be >= {minimum} {unit}; got {value}")
        return value

    parse.__name__ = "whole number"
    return parse


_FRAME_INDEX = whole_number(0, "(frames count from 0)")


def _frame_range(text: str) -> slice:
    import argparse

    from app.files.imageio import parse_frame_range

    try:
        return parse_frame_range(text)
    except TirdeflectError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_process_parser(sub) -> None:
    """Add the ``process`` subcommand to an argparse subparsers object."""
    p = sub.add_parser(
        "process",
        help="reconstruct surface heights from a reference and frames, to HDF5",
        description="Reconstruct water-surface heights (mm) from a reference image and "
        "deformed frames and write them to an HDF5 file (layout: docs/output-format.md). "
        "Inputs (docs/inputs.md): PNG, BMP, TIFF (8-16 bit, packed 10/12-bit, multi-page "
        "stacks), folders and globs of images (natural order), tirdeflect HDF5 recordings, "
        "video (AVI, MKV, MP4, MOV), Photron MRAW (.cih/.cihx) and Phantom CINE. "
        "A frame that cannot be measured is stored invalid with "
        "its reason and the run goes on. Exit status: 0 every frame measured; 3 OUT written but "
        "some frames invalid or recorded INCOMPLETE; 2 refused or failed (the frames measured "
        "are kept in OUT.partial.h5, named in the message); 130 interrupted.",
    )
    p.add_argument("reference", help="reference image of the flat surface (or a recording "
                   "holding a /reference, or a file whose --reference-frames are averaged)")
    p.add_argument("frames", nargs="*", metavar="FRAME",
                   help="frames to process, in order (files, stacks, recordings, videos, "
                   "camera files, folders, quoted globs); may be left out with "
                   "--reference-frames: then the reference's file is processed")
    p.add_argument("--frames", dest="frame_range", type=_frame_range, default=None,
                   metavar="START:STOP:STEP",
                   help="frames to process, as a Python slice over the whole input sequence "
                   "(0-based, STOP exclusive, negatives from the end; e.g. 20:, 0:1000:2); "
                   "replaces --first/--last/--step")
    p.add_argument("--reference-frames", type=_frame_range, default=None, metavar="START:STOP",
                   help="average these frames of the reference file (e.g. 0:20 of a recording "
                   "whose first frames show the flat surface) to make the reference")
    p.add_argument("--reference-index", type=_FRAME_INDEX, default=None, metavar="K",
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
    p.add_argument("--pattern", choices=("checkerboard", "dots"), default=None,
                   help="what the reference shows: checkerboard (Fourier demodulation) or dots (a random-dot "
                        "pattern, PIV with window deformation); default: the geometry's pattern key, "
                        "else checkerboard")
    p.add_argument("--refine", dest="refine_method", choices=("auto", "image", "fd"), default="auto",
                   help="auto (default): image matching for the height on a 4 px node grid where it applies "
                        "(full grid, CPU, frame sides multiples of 4 px; from FD's start on checkerboards, from "
                        "PIV's on dots), else fd; fd: Fourier demodulation's refinement only (dots: PIV alone), "
                        "about 5x faster, smooths features a few carrier periods (PIV windows) wide "
                        "(docs/processing.md sections 6 and 11)")
    p.add_argument("--no-unwrap", action="store_true",
                   help="do not unwrap carrier phases (only for small displacements)")
    p.add_argument("--turn-removal", choices=("none", "camera", "board"), default="none",
                   help="a turn of the pattern since the reference (camera or board knocked) is always measured "
                        "and named (/turn_mrad); none (default): left in the heights (a saddle); camera: taken out "
                        "as the camera's turn about its axis; board: as the board's turn in its plane. Taken out "
                        "as the wrong one it costs more than left in: say only what you know moved "
                        "(docs/processing.md section 5)")
    p.add_argument("--shift-removal", action="store_true",
                   help="where the whole pattern shifted alike since the reference (the water level changed, "
                        "or the camera or the board moved: always measured and named, /pin_status), solve the "
                        "heights of the displacement less that shift, as a reference taken at that frame "
                        "would; by default the shift's tilt stays in the heights (docs/processing.md section 5)")
    p.add_argument("--first", type=_FRAME_INDEX, default=0, metavar="K",
                   help="first frame to process (0-based, counting every frame of every "
                   "input in order)")
    p.add_argument("--last", type=_FRAME_INDEX, default=None, metavar="K",
                   help="last frame to process (inclusive)")
    p.add_argument("--step", type=whole_number(1, "(every S-th frame)"), default=1, metavar="S",
                   help="process every S-th frame")
    p.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    p.add_argument("--compression", choices=("none", "gzip", "lzf"), default="none",
                   help="HDF5 compression of the per-frame datasets (default none)")
    p.add_argument("--fft-effort", choices=("auto", "estimate", "measure"), default="auto",
                   help="FFTW planning: measure costs seconds once (then cached as wisdom in "
                   "the cache dir) and makes each frame faster; auto measures for >= "
                   f"{MEASURE_MIN_FRAMES} frames")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--strict", action="store_true",
                   help="stop at the first frame that cannot be measured (default: store it "
                   "invalid, with its reason in /frame_status, and go on)")
    p.add_argument("--workers", type=whole_number(1, "processes"), default=None, metavar="N",
                   help="processes reconstructing frames in parallel (default: every core for "
                   "runs of 64 frames or more; 1: all in this process); same heights as serial")
    p.add_argument("--dask", default=None, metavar="ADDRESS",
                   help="run on a Dask cluster: local[:N] (N worker processes on this machine) "
                   "or tcp://HOST:8786 (a running `dask scheduler`; see docs/cluster.md); "
                   "needs pip install 'tirdeflect[dask]'")
    p.add_argument("--dask-send-frames", dest="send_frames", action="store_true",
                   help="with --dask: read the frames here and send them with the tasks (for "
                   "workers that do not see the input files)")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu",
                   help="cuda: reconstruct batches of frames on the GPU (needs pip install "
                   "'tirdeflect[gpu]' and an NVIDIA GPU; heights checked against the CPU's on an H200, "
                   "speed goals not yet met)")
    p.add_argument("--chunk-frames", type=whole_number(1, "frames"), default=None, metavar="K",
                   help="frames per parallel chunk (default: from frames, workers and memory)")
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
    p.add_argument("--size", type=whole_number(1, "pixels"), default=512, metavar="PX",
                   help="image size in pixels (square)")
    p.add_argument("--frames", type=whole_number(1, "frames"), default=1, metavar="N",
                   help="number of frames (time steps)")
    p.add_argument("--bits", type=int, choices=(8, 12), default=8,
                   help="bit depth of the images (12 bit: 16-bit TIFF)")
    p.add_argument("--noise", type=float, default=0.0, metavar="RMS",
                   help="camera noise, RMS in grey levels of the output bit depth")
    p.add_argument("--geometry", default=None, metavar="G.toml",
                   help="optical geometry (default: a typical TIR set-up); its pattern_period_mm is the "
                   "board rendered (default: 20 px)")
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
        help="compare processed heights (OUT.h5) with simulated truth (DIR or DIR/heights.h5)",
        description="Print, per frame, the relative RMS height error of `tirdeflect process` "
        "output against the true heights written by `tirdeflect simulate`, in the interior "
        "of the field, both maps pinned alike on the reference region the heights were pinned on: "
        "each less its least-squares multiple there of the heights' null mode (exp(-T y/H) for TIR, "
        "a constant for FS-SS), the part no deflectometry measures. Frames the output marks invalid "
        "are skipped and named, as are the truth's frames the output does not hold. "
        "Exit status: 0 compared (within --max-error if given); 1 the worst compared frame exceeds "
        "--max-error; 2 refused: a file that is not a process output or simulate's truth, output and "
        "truth not of one data set, or no frame that can be compared (every frame invalid).",
    )
    p.add_argument("out", metavar="OUT.h5", help="output of tirdeflect process")
    p.add_argument("truth", metavar="DIR|heights.h5",
                   help="the folder tirdeflect simulate wrote (DIR), or its DIR/heights.h5")
    p.add_argument("--margin", type=float, default=0.125, metavar="F",
                   help="border left out on each side, as a fraction of the size (default 0.125)")
    p.add_argument("--max-error", type=float, default=None, metavar="REL",
                   help="exit with status 1 if a compared frame's relative RMS error exceeds REL (e.g. 0.02; "
                   "frames the output marks invalid are skipped, not compared)")
    p.set_defaults(func=cmd_compare)



#: Exit status of ``process`` when the output was written but not every frame
#: is a clean measurement (invalid frames, or frames recorded INCOMPLETE).
EXIT_FRAMES_INVALID = 3


def cmd_process(args) -> int:
    """Run ``tirdeflect process``; returns the exit status (errors raise).

    0: every frame measured; 3: the output is written but some frames are
    invalid or were recorded INCOMPLETE (the summary line counts them);
    errors raise (exit 2 in :func:`app.cli.main.main`, 130 interrupted).
    SIGTERM and SIGHUP stop the run like Ctrl-C: the frames written are kept
    in the partial file the message names; also while the summary below
    is printed (after "wrote N frame(s)": the output complete and in place),
    and, once this returned, while the process exits (:func:`app.cli.main.main`).
    """
    with _signals_interrupt():
        report = run_process(ProcessJob.from_namespace(args))
        return _print_report(report)


def _print_report(report) -> int:
    """The lines of a run that wrote its output, on stderr; returns the exit status (0 or 3)."""
    line = f"tirdeflect: wrote {report.frames_written} frame(s) to {report.out}"
    try:
        line += f" ({format_bytes(os.path.getsize(report.out))})"
    except OSError:  # (gone already: another program)
        pass
    if report.frames_incomplete:
        line += f", {report.frames_incomplete} recorded INCOMPLETE"
    if report.frames_invalid:
        line += (f", {report.frames_invalid} invalid (heights NaN, reason in /frame_status_text): "
                 f"{report.invalid_summary}")
    print(line, file=sys.stderr)
    if report.pin:
        print(f"tirdeflect: {report.pin}", file=sys.stderr)
    for note in report.notes:
        print(f"tirdeflect: note: {note}", file=sys.stderr)
    return 0 if report.clean else EXIT_FRAMES_INVALID


class _signals_interrupt:
    """SIGTERM (timeout, systemd, kill) and SIGHUP (closed terminal) raise
    KeyboardInterrupt in the main thread, so they end a run the way Ctrl-C
    does: file closed valid, partial result named."""

    def __enter__(self):
        import signal
        import threading

        self._old = {}
        if threading.current_thread() is not threading.main_thread():
            return self
        for sig in STOP_SIGNALS:
            self._old[sig] = signal.signal(sig, self._raise)
        return self

    @staticmethod
    def _raise(signum, frame):
        raise KeyboardInterrupt

    def __exit__(self, *exc):
        import signal

        for sig, handler in self._old.items():
            signal.signal(sig, handler)
        return False


def cmd_simulate(args) -> int:
    """Run ``tirdeflect simulate``; returns the exit status (errors raise)."""
    run_simulate(args)
    return 0


#: Exit status of ``compare`` when a compared frame's error exceeds --max-error.
EXIT_COMPARE_OVER = 1


def cmd_compare(args) -> int:
    """Run ``tirdeflect compare``: 0, or :data:`EXIT_COMPARE_OVER` (1) if the worst compared frame
    exceeds --max-error; refusals (files that are not the output and truth of one data set, no
    frame that can be compared) raise: exit 2. The truth may be given as the directory
    ``tirdeflect simulate`` wrote (its ``heights.h5``). Frames the output marks invalid are
    skipped and named, never counted as an "inf%" error."""
    args.truth = resolve_truth(args.truth)
    for path, what in ((args.out, "processed file"), (args.truth, "truth file")):
        check_input_file(path, what)
    if not 0 <= args.margin < 0.5:
        raise TirdeflectError(f"--margin must be in [0, 0.5); got {args.margin}")
    if args.max_error is not None and not (np.isfinite(args.max_error) and args.max_error > 0):
        raise TirdeflectError(f"--max-error must be a relative error > 0 (0.02 is 2 %); got {args.max_error}")
    result = compare_heights(args.out, args.truth, margin=args.margin)
    worst = result.worst
    if worst is None:
        raise TirdeflectError(
            f"no frame of {str(args.out)!r} can be compared with the truth: {_skipped_text(result.skipped)}; "
            f"compare an output with measured frames (`tirdeflect process` names why each frame failed)")
    report = result.frames
    print("frame  rel_rms_error  rms_error_um  rms_true_um  scale   valid")
    for r in report:
        print(f"{r['frame']:5d}  {r['rel_rms'] * 100:11.2f} %  {r['rms_error_mm'] * 1e3:12.4f}  "
              f"{r['rms_true_mm'] * 1e3:11.4f}  {r['scale']:.4f}  {r['valid_fraction']:.3f}")
    print(f"worst relative RMS error {worst['rel_rms']:.2%} (frame {worst['frame']}) over the {len(report)} "
          f"compared frame(s)" + (f"; {len(result.skipped)} skipped" if result.skipped else ""))
    for line in _coverage_notes(result):
        print(f"note: {line}")
    _print_pin_notes(report)
    if args.max_error is not None and worst["rel_rms"] > args.max_error:
        print(f"tirdeflect: worst relative RMS error {worst['rel_rms']:.2%} (frame {worst['frame']}) exceeds "
              f"--max-error {args.max_error:.2%}", file=sys.stderr)
        return EXIT_COMPARE_OVER
    return 0


def _skipped_text(skipped: list, shown: int = 5) -> str:
    """``frame 0 ('grey.tif'): the output marks it invalid (blank: ...)``, for the first ``shown``
    skipped frames, and how many more (a run of 1000 dark frames is not 1000 reasons on a line)."""
    parts = []
    for s in skipped[:shown]:
        where = f" ({Path(s['source']).name!r})" if s["source"] else ""
        parts.append(f"frame {s['frame']}{where}: {s['reason']}")
    if len(skipped) > shown:
        parts.append(f"and {len(skipped) - shown} more (the reasons are in the output's /frame_status_text)")
    return "; ".join(parts)


def _coverage_notes(result) -> list:
    """What was not compared: the frames skipped (with their reason) and the truth's frames the
    output does not hold (a run that stopped, or frames not selected)."""
    lines = []
    if result.skipped:
        lines.append(f"{len(result.skipped)} frame(s) skipped, not in the worst error: "
                     f"{_skipped_text(result.skipped)}")
    if result.missing:
        shown = ", ".join(str(j) for j in result.missing[:10]) + (", ..." if len(result.missing) > 10 else "")
        why = (result.stopped if result.stopped else
               "not processed: --first/--last/--step/--frames, or not every frame file given")
        lines.append(f"the output holds {result.truth_frames - len(result.missing)} of the truth's "
                     f"{result.truth_frames} frame(s); missing from the output: frame(s) {shown} ({why})")
    return lines


def _print_pin_notes(report: list) -> None:
    """The notes on what the pin left in the figures: a simulated surface not at rest on the
    reference region, and a shift of the whole pattern since the reference."""
    moving = [r for r in report if r["rms_true_mm"] > 0 and r["region_rms_mm"] > 0.05 * r["rms_true_mm"]]
    if moving:
        top = max(moving, key=lambda r: r["region_rms_mm"])
        print(f"note: the simulated surface is not at rest on the reference region in {len(moving)} of "
              f"{len(report)} frame(s) (up to {top['region_rms_mm'] * 1e3:.4f} um rms there, frame {top['frame']}); "
              "both maps were pinned alike (the null mode, exp(-T y/H) for TIR, fitted there and taken out), "
              "so the figures are the processing's; measured heights carry that region's motion as that mode: "
              "at the tank, give a reference_region where the water is still")
    shifted = [r for r in report if np.isfinite(r["shift_effect_um"])]
    if shifted:
        top = max(shifted, key=lambda r: r["shift_effect_um"])
        print(f"note: in {len(shifted)} of {len(report)} frame(s) the whole pattern shifted since the reference "
              f"(/pin_status; up to {top['shift_effect_um']:.3g} um rms put into the heights, frame {top['frame']}), "
              "part of the error above: a level or a set-up that moved, not the processing; "
              "`tirdeflect process --shift-removal` takes it out")
    turned = [r for r in report if np.isfinite(r.get("turn_mrad", np.nan))]
    if turned:
        top = max(turned, key=lambda r: abs(r["turn_mrad"]))
        print(f"note: in {len(turned)} of {len(report)} frame(s) the pattern turned since the reference (/turn_mrad; "
              f"up to {abs(top['turn_mrad']):.3g} mrad, frame {top['frame']}), a saddle in the heights that is part "
              "of the error above: the camera or the board moved, not the processing; `tirdeflect process "
              "--turn-removal camera` (or board) takes it out")
