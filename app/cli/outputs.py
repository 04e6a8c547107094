"""``tirdeflect movie``, ``tirdeflect probe`` and ``tirdeflect pattern``: argument
parsing and messages; the work is in :mod:`app.batch.movie`,
:mod:`app.batch.probe` and :mod:`app.batch.pattern`."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["add_movie_parser", "add_probe_parser", "add_pattern_parser"]


def _pair(text: str, what: str, sep: str = ",") -> tuple:
    parts = text.replace(" ", "").split(sep)
    try:
        if len(parts) != 2:
            raise ValueError
        return float(parts[0]), float(parts[1])
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None


def _point(text: str) -> tuple:
    return _pair(text, "X_MM,Y_MM (two numbers in mm, e.g. 3.5,-2)")


def _range(text: str) -> tuple:
    return _pair(text, "LOW,HIGH (e.g. -2,2)")


def positive_number(unit: str):
    """An argparse type: a finite number > 0, refused as ``--fps must be > 0 frames/s; got -3``
    (the range messages of every command read alike; :class:`app.cli.main.Parser`)."""
    import math

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be a number > 0 {unit}; got {text!r}") from None
        if not (value > 0 and math.isfinite(value)):
            raise argparse.ArgumentTypeError(f"must be > 0 {unit}; got {value:g}")
        return value

    parse.__name__ = "number"
    return parse


# =========================================================================== movie


def add_movie_parser(sub) -> None:
    p = sub.add_parser(
        "movie", help="make a movie of processed height (or slope) maps, for talks",
        description="Encode the maps of a `tirdeflect process` output as a movie (PyAV): "
        "colour bar in micrometres (slopes: milliradians), frame number and time stamp, one "
        "colour range for the whole movie.")
    p.add_argument("out_h5", metavar="OUT.h5", help="output of tirdeflect process")
    p.add_argument("--out", required=True, metavar="MOVIE", help="movie file (.mp4, .mkv, .mov, .avi)")
    p.add_argument("--quantity", choices=("height", "slope_x", "slope_y"), default="height")
    p.add_argument("--range", type=_range, default=None, metavar="LOW,HIGH",
                   help="colour range in um (height) or mrad (slopes); default: percentiles")
    p.add_argument("--percentile", type=float, default=1.0, metavar="P",
                   help="default colour range from the P and 100-P percentiles over the movie (1)")
    p.add_argument("--fps", type=positive_number("frames/s"), default=None,
                   help="movie frame rate (default: real time from the frames' time stamps, else 25)")
    p.add_argument("--scale", type=int, default=None, metavar="K",
                   help="magnify the map K times (default: at least 480 px wide)")
    p.add_argument("--overwrite", action="store_true", help="replace MOVIE if it exists")
    p.set_defaults(func=cmd_movie)


def cmd_movie(args) -> int:
    from app.batch.movie import make_movie

    report = make_movie(args.out_h5, args.out, quantity=args.quantity, value_range=args.range,
                        percentile=args.percentile, fps=args.fps, overwrite=args.overwrite,
                        scale=args.scale)
    lo, hi = report.value_range
    print(f"tirdeflect: wrote {report.frames} frame(s), {report.width} x {report.height} px "
          f"({report.codec}), colour range {lo:.4g} .. {hi:.4g} {report.unit}, to {report.path}",
          file=sys.stderr)
    beyond = report.beyond_range() if args.range is None else ""
    if beyond:
        print(f"tirdeflect: note: {beyond}", file=sys.stderr)
    return 0


# =========================================================================== probe


def add_probe_parser(sub) -> None:
    p = sub.add_parser(
        "probe", help="height time series at surface points (virtual wave gauges)",
        description="Write the height (mm) at surface points of a `tirdeflect process` output, "
        "for every frame, with its time in s (from the recording's time stamps), as CSV and HDF5.")
    p.add_argument("out_h5", metavar="OUT.h5", help="output of tirdeflect process")
    p.add_argument("--at", type=_point, action="append", required=True, metavar="X_MM,Y_MM",
                   help="probe position on the surface in mm (x along columns, y along rows, "
                   "as /x_mm and /y_mm of OUT.h5); repeat for several probes")
    p.add_argument("--out", default=None, metavar="PROBES.csv",
                   help="CSV file (default: OUT_probes.csv beside OUT.h5)")
    p.add_argument("--h5", default=None, metavar="PROBES.h5",
                   help="HDF5 file with the same series (default: the CSV name with .h5)")
    p.add_argument("--fps", type=positive_number("frames/s"), default=None,
                   help="frame rate for inputs without time stamps (image files): time = frame / fps")
    p.add_argument("--overwrite", action="store_true", help="replace the outputs if they exist")
    p.set_defaults(func=cmd_probe)


def cmd_probe(args) -> int:
    from app.batch.probe import probe_series, trigger_note, write_probes

    src = Path(args.out_h5)
    csv_path = Path(args.out) if args.out else src.with_name(src.stem + "_probes.csv")
    h5_path = Path(args.h5) if args.h5 else csv_path.with_suffix(".h5")
    if h5_path == src:
        from processing.errors import TirdeflectError

        raise TirdeflectError("--h5 must not be OUT.h5 itself; give another file name")
    series = probe_series(src, args.at, fps=args.fps)
    paths = write_probes(series, csv_path, h5_path, source=str(src), overwrite=args.overwrite)
    print(f"tirdeflect: {len(series.x_mm)} probe(s) x {len(series.frame_index)} frame(s), time from "
          f"{series.time_source}, written to {', '.join(map(str, paths))}", file=sys.stderr)
    if series.time_source == "none":
        print("tirdeflect: note: the inputs had no time stamps (image files): time_s is NaN; "
              "give --fps to count time from the frame index", file=sys.stderr)
    trigger = trigger_note(series)
    if trigger:
        print(f"tirdeflect: note: {trigger}", file=sys.stderr)
    back = _time_goes_back(series)
    if back:
        print(f"tirdeflect: note: {back}", file=sys.stderr)
    return 0


def _time_goes_back(series) -> str:
    """Where the probe series' time_s does not increase (several input files, each counting
    time from its own start or trigger), as a sentence; '' where it does."""
    import numpy as np

    known = np.flatnonzero(np.isfinite(series.time_s))
    t = series.time_s[known]
    back = np.flatnonzero(np.diff(t) <= 0)
    if not len(back):
        return ""
    k = back[0]
    return (f"time_s does not increase at {len(back)} place(s), first at frame "
            f"{int(series.frame_index[known[k + 1]])} ({t[k]:.9g} s, then {t[k + 1]:.9g} s): each input file "
            f"counts its times from its own start or trigger ({series.time_source}): plot against "
            f"frame_index, or shift each file's times by its start (/source names the file of each frame)")


# =========================================================================== pattern


def _camera(text: str) -> tuple:
    parts = text.lower().replace(" ", "").split("x")
    try:
        if len(parts) != 2:
            raise ValueError
        cols, rows = int(parts[0]), int(parts[1])
        if cols < 16 or rows < 16:
            raise ValueError
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT in pixels (e.g. 1024x1024), got {text!r}") from None
    return cols, rows


def _size(text: str) -> tuple:
    return _pair(text, "W,H in mm (e.g. 297,210)")


def add_pattern_parser(sub) -> None:
    p = sub.add_parser(
        "pattern", help="print the checkerboard at exact scale, or suggest its period",
        description="Write the checkerboard pattern as a vector PDF at exact printed scale (a 100 mm "
        "ruler and the parameters in the bottom margin), SVG (mm units) or PNG (--dpi); or, with "
        "--suggest, propose the period for a camera and geometry (the rule is printed).")
    p.add_argument("--period-mm", type=positive_number("mm"), default=None, metavar="P",
                   help="full period along x (one dark plus one bright square), mm")
    p.add_argument("--size-mm", type=_size, default=None, metavar="W,H",
                   help="page size in mm, e.g. 297,210 (A4 landscape); the board fills it above the margin")
    p.add_argument("--stretch-y", type=positive_number("(cell height / width)"), default=1.0, metavar="F",
                   help="cell height / width (1: square; 1/cos(theta) makes the camera see square cells; "
                   "--suggest prints it)")
    p.add_argument("--margin-mm", type=float, default=25.0, metavar="M",
                   help="bottom strip for the ruler and the parameters, mm (default 25)")
    p.add_argument("--out", default=None, metavar="BOARD", help="output file: .pdf, .svg or .png")
    p.add_argument("--dpi", type=positive_number("dots per inch"), default=600.0, help="PNG resolution (default 600)")
    p.add_argument("--overwrite", action="store_true", help="replace BOARD if it exists")
    p.add_argument("--suggest", action="store_true",
                   help="propose a period from --theta-deg, --depth-mm, --pixel-mm and --camera "
                   "(and write it to --out if given, with --size-mm)")
    p.add_argument("--theta-deg", type=float, default=None, help="incidence angle theta, deg")
    p.add_argument("--depth-mm", type=positive_number("mm"), default=None, help="pattern depth below the surface H, mm")
    p.add_argument("--pixel-mm", type=positive_number("mm"), default=None, help="surface mm per image column")
    p.add_argument("--camera", type=_camera, default=None, metavar="WxH", help="image size in pixels")
    p.add_argument("--camera-distance-mm", type=positive_number("mm"), default=None, metavar="D",
                   help="distance from the lens to the centre of the surface, mm (camera_distance_mm in the "
                   "geometry); omitted: a telecentric lens, which the suggestion then says it assumes")
    p.set_defaults(func=cmd_pattern)


def cmd_pattern(args) -> int:
    from app.batch.pattern import PatternSpec, suggest_period, write_pattern
    from processing.errors import TirdeflectError

    period, stretch, note = args.period_mm, args.stretch_y, ""
    if args.suggest:
        missing = [name for name, value in (("--theta-deg", args.theta_deg), ("--depth-mm", args.depth_mm),
                                            ("--pixel-mm", args.pixel_mm), ("--camera", args.camera))
                   if value is None]
        if missing:
            raise TirdeflectError(f"--suggest needs {', '.join(missing)}")
        s = suggest_period(args.theta_deg, args.depth_mm, args.pixel_mm, args.camera, args.camera_distance_mm)
        for line in s.lines():
            print(line)
        if period is None:
            period = s.period_mm if stretch == 1.0 else s.period_stretched_mm
        note = (f"for theta {args.theta_deg:g} deg, H {args.depth_mm:g} mm, {args.pixel_mm:g} mm/px, "
                f"{args.camera[0]}x{args.camera[1]} px, "
                + ("telecentric" if args.camera_distance_mm is None else f"camera {args.camera_distance_mm:g} mm"))
        if args.out is None:
            return 0
    if period is None or args.size_mm is None or args.out is None:
        raise TirdeflectError("give --period-mm P, --size-mm W,H and --out BOARD.pdf "
                              "(or --suggest with --theta-deg, --depth-mm, --pixel-mm, --camera)")
    spec = PatternSpec(period, args.size_mm[0], args.size_mm[1], stretch_y=stretch,
                       margin_mm=args.margin_mm, note=note)
    from app.files.h5safe import check_creatable

    # where no file can be made (/proc, a read-only mount), why, not "does not exist; check the path"
    check_creatable(args.out, "choose another --out (a folder you can write to)")
    path = write_pattern(spec, args.out, dpi=args.dpi, overwrite=args.overwrite)
    print(f"tirdeflect: wrote {spec.describe()} to {path}; print at 100 % and check the "
          f"100 mm ruler", file=sys.stderr)
    return 0
