"""The ``tirdeflect`` console command.

::

    tirdeflect                       open the live window (same as `tirdeflect gui`)
    tirdeflect gui [--camera ID]     open the live window on a camera
    tirdeflect process REF FRAME... --geometry G.toml --out OUT.h5
    tirdeflect simulate --out DIR [--surface bump] ...
    tirdeflect compare OUT.h5 DIR/heights.h5   processed vs simulated heights
    tirdeflect movie OUT.h5 --out heights.mp4   movie of the maps, for talks
    tirdeflect probe OUT.h5 --at X_MM,Y_MM      height time series at points (CSV, HDF5)
    tirdeflect pattern --period-mm P --size-mm W,H --out board.pdf   the printed checkerboard
    tirdeflect pattern --suggest --theta-deg 55 --depth-mm 300 --pixel-mm 0.08 --camera 1024x1024
    tirdeflect cameras               list cameras
    tirdeflect record ...            record frames to HDF5 without the GUI
    tirdeflect --version

Errors the user can fix (:class:`processing.errors.TirdeflectError`,
:class:`drivers.base.CameraError`, file errors) are printed as one line
``tirdeflect: error: <message>`` with exit status 2 and no traceback;
``--debug`` shows the traceback as well. Ctrl-C exits with status 130, from the
start of the command to the end of the process: one that comes after the
command ended, while the process exits (``tirdeflect`` run as a program; see
:class:`_Ending`), is one line and status 128 + the signal's number too, not a
traceback or death by the signal.
A closed standard output (``tirdeflect compare ... | head -1``) ends the
command quietly with status 141, as a command that SIGPIPE ended (no
"[Errno 32] Broken pipe" line).
``process`` exits with 3 when it wrote its output but some frames could not
be measured or were recorded INCOMPLETE (docs/reliability.md).
"""

from __future__ import annotations

import argparse
import atexit
import logging
import os
import re
import signal
import sys
import traceback

from app import version
from app.stop_signals import STOP_SIGNALS

__all__ = ["main", "build_parser", "version"]

PROG = "tirdeflect"
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130
#: status when the reader of stdout went away (``| head``): 128 + SIGPIPE, what the shell
#: reports for a command that SIGPIPE ended
EXIT_BROKEN_PIPE = 141


def _add_gui(sub) -> None:
    # Listed for --help only: main() hands `gui ...` to app.gui.main.main unparsed,
    # so every option of the window (`tirdeflect gui --help`) works here.
    p = sub.add_parser("gui", help="open the live window (default when no command is given); "
                   "`tirdeflect gui --help` lists its options (--camera ID, --scene waves, --session FILE, "
                   "--geometry, ...; they work without `gui` too)")
    p.set_defaults(func=lambda args: _run_gui([]))


def _run_gui(gui_argv) -> int:
    try:
        from app.gui.main import main as gui_main
    except ImportError as exc:
        raise _AppUnavailable(
            f"the live window is not available ({exc}); reinstall tirdeflect (bash resources/install.sh "
            f"on Debian/Ubuntu, pip install . elsewhere), or use `tirdeflect process`"
        ) from exc
    try:
        return int(gui_main(list(gui_argv)) or 0)
    except SystemExit as exc:  # its own argparse: --help or a usage error
        return int(exc.code or 0) if not isinstance(exc.code, str) else EXIT_USAGE


# options of the live window accepted without the `gui` command
_GUI_OPTIONS = ("--scene", "--session", "--camera", "--geometry", "--reference", "--size", "--rate", "--frames",
                "--quit-after")


def _split_gui(argv):
    """(global_flags, gui_argv) if argv asks for the live window, else None."""
    flags = []
    rest = list(argv)
    while rest and rest[0] in ("--debug", "-v", "--verbose"):
        flags.append(rest.pop(0))
    if not rest:
        return flags, []
    if rest[0] == "gui":
        return flags, rest[1:]
    if rest[0].split("=", 1)[0] in _GUI_OPTIONS:  # `tirdeflect --scene waves`, `tirdeflect --session exp.toml`
        return flags, rest
    return None


def _add_record_commands(sub) -> None:
    """Delegate `cameras` and `record` to app.cli.record when it exists."""
    try:
        from app.cli import record as record_cli
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


class Parser(argparse.ArgumentParser):
    """argparse with the option first in a refused value: ``--first must be >= 0 (frames
    count from 0); got -1``, as ``record``'s own checks write it, not ``argument --first:
    must be ...``. Subcommand parsers are of this class too."""

    def error(self, message):
        match = re.match(r"argument (-[^:/ ]+)(?:/[^:]+)?: (must be .*)$", message, re.S)
        if match:
            message = f"{match.group(1)} {match.group(2)}"
        super().error(message)


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser (subcommands included)."""
    from app.cli import process as process_cli

    parser = Parser(
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
    process_cli.add_compare_parser(sub)
    from app.cli import outputs as outputs_cli

    outputs_cli.add_movie_parser(sub)
    outputs_cli.add_probe_parser(sub)
    outputs_cli.add_pattern_parser(sub)
    _add_record_commands(sub)
    # `tirdeflect process ... --debug` works as well as `tirdeflect --debug process ...`
    # (SUPPRESS: an absent flag does not reset the global one)
    for name, subparser in sub.choices.items():
        if name == "gui":
            continue
        subparser.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                               help="show tracebacks and debug log messages")
        subparser.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
                               help="show informational log messages")
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


def _fill_closed_std_descriptors() -> None:
    """/dev/null on standard descriptors the caller closed (``2>&-``, some launchers): else the first file the
    run opens takes descriptor 2, where C libraries (HDF5, Aravis's GLib) print their warnings, into a
    recording or an output being written. (Python has then set ``sys.stderr`` to None, which the progress bar
    and the messages allow for.)"""
    for fd in (0, 1, 2):
        try:
            os.fstat(fd)
        except OSError:
            try:
                null = os.open(os.devnull, os.O_RDWR)
            except OSError:
                return
            if null != fd:
                os.dup2(null, fd)
                os.close(null)


def main(argv=None) -> int:
    """Run the ``tirdeflect`` command.

    Parameters
    ----------
    argv : list of str, optional
        Arguments without the program name; None: ``sys.argv[1:]``, and this
        call is the program (the ``tirdeflect`` script, ``python3 -m app.cli``):
        its exit is then covered too (:class:`_Ending`; not for the live window,
        which ends its own way). A caller that passes ``argv`` (a test, a script)
        gets the status back and keeps its own process.

    Returns
    -------
    int
        Exit status: 0 success, 2 bad input / usage (message on stderr),
        3 ``process`` wrote its output but some frames are invalid or
        incomplete, 130 interrupted.
    """
    ending = _ENDING if argv is None else None
    if argv is None:
        _fill_closed_std_descriptors()
    try:
        return _main(list(sys.argv[1:] if argv is None else argv), ending)
    except KeyboardInterrupt:  # Ctrl-C before a command began (its imports, the parser): nothing was written
        print(f"{PROG}: interrupted before the command began; nothing was written", file=sys.stderr)
        return _ended(ending, EXIT_INTERRUPTED)


def _main(argv: list, ending=None) -> int:
    """:func:`main` on ``argv``; a command runs :func:`_guarded` (its own Ctrl-C handling).
    ``ending``: the :class:`_Ending` that covers the process's exit, or None."""
    gui = _split_gui(argv)
    if gui is not None:
        flags, gui_argv = gui
        debug = "--debug" in flags
        if debug and "--debug" not in gui_argv:
            gui_argv = [*gui_argv, "--debug"]
        return _guarded(lambda: _run_gui(gui_argv), debug)
    parser = build_parser()
    argv = _join_negative_pairs(argv)
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse: --help, --version, usage errors
        return _ended(ending, int(exc.code or 0) if not isinstance(exc.code, str) else EXIT_USAGE)
    except BrokenPipeError:  # `tirdeflect --help | head -3`
        if _stdout_closed():
            return _ended(ending, _quiet_broken_pipe())
        raise
    args._argv = list(argv)  # recorded in output files (process)
    level = logging.DEBUG if args.debug else logging.INFO if args.verbose else logging.WARNING
    # the handler filters too: libraries that set their own loggers' levels (Dask's distributed: INFO)
    # would otherwise print through it (34 lines of cluster start and stop on every `--dask local` run)
    handler = logging.StreamHandler()
    handler.setLevel(level)
    logging.basicConfig(level=level, format=f"{PROG}: %(levelname)s: %(message)s", handlers=[handler])
    return _guarded(lambda: args.func(args), args.debug, ending)


class _Ending:
    """The process's exit after its command, covered against Ctrl-C, SIGTERM and SIGHUP.

    Once the command has returned (its files closed: ``process``'s output renamed into place,
    ``record``'s file closed), the interpreter still tears itself down: it joins threads, runs
    the exit callbacks and frees every module (0.5 s after a ``process`` run on a 2-core PC). A
    Ctrl-C there raised KeyboardInterrupt inside that teardown (a traceback, "Exception ignored
    ...") or, once Python 3.11 had put the default handlers back before freeing the modules
    (``Py_FinalizeEx``: ``_PySignal_Fini``), killed the process by the signal (status -2 to the
    caller, without the line and the 130 the convention promises).

    :meth:`arm` (when the command returned) makes those signals only noted; :meth:`finish`, this
    module's exit callback, registered when the command's modules were not yet imported and so
    run after theirs, then ends the process with ``os._exit``: with the command's status, or,
    when a signal came, one line on stderr and 128 + its number (130 for Ctrl-C). What Python
    would still do after it (free the modules) holds nothing of the user's; C libraries' own
    exit handlers are skipped too, HDF5's included, so an HDF5 file a caller left open is
    flushed first. A second signal ends the process at once.
    """

    def __init__(self):
        self.code = None  # the command's exit status, once it returned (None: not armed)
        self.signum = None

    def arm(self, code: int) -> int:
        """The command ended with ``code``: from here to the process's end a stop signal is noted."""
        self.code = int(code)
        for sig in (signal.SIGINT, *STOP_SIGNALS):
            try:
                signal.signal(sig, self._noted)
            except (ValueError, OSError):  # not the main thread: nothing to cover
                pass
        return self.code

    def _noted(self, signum, frame) -> None:
        again = self.signum is not None
        self.signum = signum
        if again:
            self.finish()

    def finish(self) -> None:
        """End the process (after the other exit callbacks); nothing when not armed."""
        if self.code is None:
            return
        code = self.code
        if self.signum is not None:
            name = "Ctrl-C" if self.signum == signal.SIGINT else signal.Signals(self.signum).name
            code = 128 + self.signum
            _say_quietly(f"{PROG}: interrupted ({name}) while exiting, after the command had ended (status "
                         f"{self.code}) and closed its files; nothing was lost")
        logging.shutdown()
        _flush_hdf5_files()
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError, AttributeError):
                pass
        os._exit(code)


def _say_quietly(line: str) -> None:
    """One line on stderr; nothing when stderr is gone (a closed terminal after SIGHUP)."""
    try:
        print(line, file=sys.stderr, flush=True)
    except (OSError, ValueError, AttributeError):
        pass


def _flush_hdf5_files() -> None:
    """Flush every HDF5 file still open in this process (none, when the commands closed theirs):
    ``os._exit`` skips the HDF5 library's own exit handler, which would."""
    h5py = sys.modules.get("h5py")
    if h5py is None:
        return
    try:
        for file_id in h5py.h5f.get_obj_ids(h5py.h5f.OBJ_ALL, h5py.h5f.OBJ_FILE):
            h5py.h5f.flush(file_id)
    except Exception:  # noqa: BLE001 - a file that cannot be flushed now could not be at exit either
        pass


#: the exit of ``tirdeflect`` run as a program (:func:`main` without ``argv``); registered as this
#: module is imported, before the commands' modules register theirs: Python runs it after them
_ENDING = _Ending()
atexit.register(_ENDING.finish)


def _ended(ending, code: int) -> int:
    """``code``, with the process's exit covered from here on when ``ending`` is given."""
    return code if ending is None else ending.arm(code)


#: Options whose value (a pair X,Y or a range START:STOP) may start with a minus sign.
_PAIR_OPTIONS = ("--at", "--range", "--size-mm", "--frames", "--reference-frames")


def _join_negative_pairs(argv: list) -> list:
    """``--at -2,3`` -> ``--at=-2,3``: argparse would take ``-2,3`` for an option."""
    out = []
    i = 0
    while i < len(argv):
        token = argv[i]
        nxt = argv[i + 1] if i + 1 < len(argv) else None
        if token in _PAIR_OPTIONS and nxt is not None and len(nxt) > 1 and nxt[0] == "-" \
                and (nxt[1].isdigit() or nxt[1] == "."):
            out.append(f"{token}={nxt}")
            i += 2
            continue
        out.append(token)
        i += 1
    return out


def _exit_now_if_a_call_is_left_running() -> None:
    """After Ctrl-C or SIGTERM stopped a frame inside a native call (app/batch/interruptible.py),
    the output is closed already: end the process now instead of tearing the interpreter
    down beside a computation that may run for minutes."""
    interruptible = sys.modules.get("app.batch.interruptible")  # not imported: nothing left running
    if interruptible is not None and interruptible.abandoned_calls():
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(EXIT_INTERRUPTED)


def _stdout_closed() -> bool:
    """Whether the reader of stdout went away (``| head`` read what it wanted): poll reports an
    error on the write end of such a pipe. False where that cannot be told (no poll, no
    descriptor): a broken pipe elsewhere (a worker's, a camera's) stays an error."""
    import select

    try:
        poller = select.poll()
        poller.register(sys.stdout.fileno(), select.POLLOUT)
        return any(events & (select.POLLERR | select.POLLHUP) for _, events in poller.poll(0))
    except (AttributeError, ValueError, OSError):
        return False


def _quiet_broken_pipe() -> int:
    """After stdout's reader went away: point stdout at /dev/null, so that what is still
    buffered is not written (a second BrokenPipeError at exit), and exit 141 quietly, as
    ``grep ... | head`` does, instead of "error: [Errno 32] Broken pipe"."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError, AttributeError):
        pass
    return EXIT_BROKEN_PIPE


def _guarded(run, debug: bool, ending=None) -> int:
    """Run a command; known errors become one line on stderr and exit status 2; a closed
    stdout (``| head``) exit status 141 and nothing more. ``ending`` (an :class:`_Ending`):
    armed with the status before this returns, still inside the handling of Ctrl-C (a
    signal before it is the command's)."""
    try:
        try:
            code = int(run() or 0)
            sys.stdout.flush()  # a closed pipe shows here, not in the interpreter's flush at exit
        except BrokenPipeError:
            if not _stdout_closed():
                raise  # not stdout's: an error like any other (below)
            code = _quiet_broken_pipe()
        return _ended(ending, code)
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        _exit_now_if_a_call_is_left_running()
        return _ended(ending, EXIT_INTERRUPTED)
    except _known_errors() as exc:
        if debug:
            traceback.print_exc()
        print(f"{PROG}: error: {_format_error(exc)}", file=sys.stderr)
        return _ended(ending, EXIT_USAGE)


if __name__ == "__main__":  # python3 -m app.cli
    sys.exit(main())
