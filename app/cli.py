"""The ``tirdeflect`` console command.

::

    tirdeflect                       open the live window (same as `tirdeflect gui`)
    tirdeflect gui [--camera ID]     open the live window on a camera
    tirdeflect process REF FRAME... --geometry G.toml --out OUT.h5
    tirdeflect simulate --out DIR [--surface bump] ...
    tirdeflect cameras               list cameras
    tirdeflect record ...            record frames to HDF5 without the GUI
    tirdeflect --version

Errors the user can fix (:class:`processing.errors.TirdeflectError`,
:class:`drivers.base.CameraError`, file errors) are printed as one line
``tirdeflect: error: <message>`` with exit status 2 and no traceback;
``--debug`` shows the traceback as well. Ctrl-C exits with status 130.
"""

from __future__ import annotations

import argparse
import logging
import sys
import traceback

__all__ = ["main", "build_parser", "version"]

PROG = "tirdeflect"
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130


def version() -> str:
    """The installed tirdeflect version, or the source tree's pyproject version."""
    try:
        from importlib.metadata import PackageNotFoundError, version as _v

        try:
            return _v("tirdeflect")
        except PackageNotFoundError:
            pass
    except ImportError:  # pragma: no cover
        pass
    try:
        import tomllib
        from pathlib import Path

        data = tomllib.loads((Path(__file__).resolve().parent.parent / "pyproject.toml").read_text())
        return str(data["project"]["version"])
    except Exception:
        return "unknown"


def _add_gui(sub) -> None:
    p = sub.add_parser("gui", help="open the live window (default when no command is given)")
    p.add_argument("--camera", metavar="ID", default=None,
                   help="camera to open, e.g. synthetic, aravis:Fake_1 (see `tirdeflect cameras`)")
    p.set_defaults(func=_cmd_gui)


def _cmd_gui(args) -> int:
    try:
        from app.gui.main import main as gui_main
    except ImportError as exc:
        raise _AppUnavailable(
            f"the live window is not available ({exc}); install PySide6-Essentials and "
            f"pyqtgraph (bash resources/install.sh), or use `tirdeflect process`"
        ) from exc
    argv = []
    if getattr(args, "camera", None):
        argv += ["--camera", args.camera]
    return int(gui_main(argv) or 0)


def _add_record_commands(sub) -> None:
    """Delegate `cameras` and `record` to app.record_cli when it exists."""
    try:
        from app import record_cli
    except ImportError as exc:
        reason = str(exc)

        def missing(args, _reason=reason) -> int:
            raise _AppUnavailable(f"recording commands are not available ({_reason})")

        for name, text in (("cameras", "list cameras"), ("record", "record frames to HDF5")):
            p = sub.add_parser(name, help=text + " (unavailable)")
            p.set_defaults(func=missing)
        return
    p = sub.add_parser("cameras", help="list the cameras tirdeflect can open")
    record_cli.add_cameras_arguments(p)
    p.set_defaults(func=record_cli.cmd_cameras)
    p = sub.add_parser("record", help="record frames losslessly to HDF5, without the GUI")
    record_cli.add_record_arguments(p)
    p.set_defaults(func=record_cli.cmd_record)


class _AppUnavailable(RuntimeError):
    """A part of the app (GUI, recorder) cannot be imported here."""


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser (subcommands included)."""
    from app import process_cli

    parser = argparse.ArgumentParser(
        prog=PROG,
        description="Live total-internal-reflection deflectometry: checkerboard images "
        "to water-surface heights (mm). With no command, opens the live window.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {version()}")
    parser.add_argument("--debug", action="store_true",
                        help="show tracebacks and debug log messages")
    parser.add_argument("-v", "--verbose", action="store_true", help="show informational log messages")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    _add_gui(sub)
    process_cli.add_process_parser(sub)
    process_cli.add_simulate_parser(sub)
    _add_record_commands(sub)
    return parser


def _known_errors() -> tuple:
    from processing.errors import TirdeflectError

    errors = [TirdeflectError, OSError, _AppUnavailable]
    try:
        from drivers.base import CameraError

        errors.append(CameraError)
    except ImportError:  # pragma: no cover
        pass
    return tuple(errors)


def _format_error(exc: BaseException) -> str:
    if isinstance(exc, FileNotFoundError) and exc.filename:
        return f"file {exc.filename!r} does not exist; check the path"
    if isinstance(exc, IsADirectoryError) and exc.filename:
        return f"{exc.filename!r} is a directory; give a file path"
    if isinstance(exc, PermissionError) and exc.filename:
        return f"no permission to access {exc.filename!r}; check the file's permissions"
    if isinstance(exc, OSError) and exc.strerror and exc.filename:
        return f"{exc.filename!r}: {exc.strerror}"
    message = str(exc).strip() or type(exc).__name__
    return " ".join(message.splitlines())


def main(argv=None) -> int:
    """Run the ``tirdeflect`` command.

    Parameters
    ----------
    argv : list of str, optional
        Arguments without the program name; ``sys.argv[1:]`` when None.

    Returns
    -------
    int
        Exit status: 0 success, 2 bad input / usage (message on stderr),
        130 interrupted.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse: --help, --version, usage errors
        return int(exc.code or 0) if not isinstance(exc.code, str) else EXIT_USAGE
    level = logging.DEBUG if args.debug else logging.INFO if args.verbose else logging.WARNING
    logging.basicConfig(level=level, format=f"{PROG}: %(levelname)s: %(message)s")
    func = getattr(args, "func", None) or _cmd_gui
    try:
        return int(func(args) or 0)
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except _known_errors() as exc:
        if args.debug:
            traceback.print_exc()
        print(f"{PROG}: error: {_format_error(exc)}", file=sys.stderr)
        return EXIT_USAGE


if __name__ == "__main__":  # python3 -m app.cli
    sys.exit(main())
