"""Shared test set-up: headless Qt, a private cache directory, fixed seeds, a
watchdog that ends a stuck run with every thread's stack, and a check at the
end of the session that the tests left nothing running."""

import faulthandler
import os
import sys
import tempfile
import threading

import numpy as np
import pytest

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")


@pytest.fixture(autouse=True)
def _private_cache_dir(tmp_path, monkeypatch):
    """Keep FFTW wisdom, remembered settings and configuration away from the user's and from other
    tests: each test starts from a clean settings directory (the window remembers its session there)."""
    monkeypatch.setenv("TIRDEFLECT_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setenv("TIRDEFLECT_CONFIG_DIR", str(tmp_path / "config"))


@pytest.fixture
def rng():
    """A seeded random generator: tests are repeatable."""
    return np.random.default_rng(12345)


# -- a stuck test ends the run --------------------------------------------------
# Two limits per test, both over its setup, call and teardown:
# 1. pytest-timeout (``timeout`` in pyproject.toml, 270 s, or a test's
#    ``@pytest.mark.timeout(N)``) fails the test with its stack and the run goes
#    on -- but its SIGALRM handler is Python code: it never runs while a thread
#    holds the GIL in C (a deadlock in an extension's import or finalizer).
# 2. Then, WATCHDOG_MARGIN_S later, faulthandler's own C thread, which needs no
#    GIL, writes every thread's Python stack to the terminal and ends pytest
#    with exit status 1. Its C thread cannot print the test's name, so that is
#    written when the test starts to the file $TIRDEFLECT_WATCHDOG_NOTE
#    (tests/run.sh sets it and prints the file after such an end; without it, a
#    file in the temporary folder, named on stderr at the start of the run).
# No test came near the former 300 s in the full runs of issue 21, quiet or
# loaded to twice the cores (the install test has its own 600 s mark); a
# deadlock now ends the run within 5 minutes (270 + 20 s).

#: seconds past a test's pytest-timeout limit at which the GIL-free watchdog ends the run
WATCHDOG_MARGIN_S = 20.0
#: the limit when pytest-timeout is not installed (its ini default in pyproject.toml)
DEFAULT_TIMEOUT_S = 270.0


def _timeout_s(item) -> float:
    """pytest-timeout's limit for ``item``: its ``timeout`` mark, else the ini value."""
    mark = item.get_closest_marker("timeout")
    if mark is not None:
        value = mark.args[0] if mark.args else mark.kwargs.get("timeout")
        if value is not None:
            return float(value)
    try:
        value = item.config.getini("timeout")
    except ValueError:  # pytest-timeout not installed: no such ini key
        return DEFAULT_TIMEOUT_S
    return float(value) if value not in (None, "") else DEFAULT_TIMEOUT_S


def pytest_configure(config):
    # the terminal's stderr as it is now, between tests: during a test, fd 2 is pytest's capture file
    config._tirdeflect_watchdog_out = os.fdopen(os.dup(2), "w")
    path = os.environ.get("TIRDEFLECT_WATCHDOG_NOTE") or os.path.join(
        tempfile.gettempdir(), f"tirdeflect-watchdog-{os.getpid()}.txt")
    config._tirdeflect_watchdog_note = path
    if not os.environ.get("TIRDEFLECT_WATCHDOG_NOTE"):
        config._tirdeflect_watchdog_out.write(f"watchdog: a test stuck past its limit ends the run; "
                                              f"the running test's name is kept in {path}\n")
        config._tirdeflect_watchdog_out.flush()


def _note(config, text: str) -> None:
    with open(config._tirdeflect_watchdog_note, "w") as f:
        f.write(text)


@pytest.hookimpl(hookwrapper=True, tryfirst=True)
def pytest_runtest_protocol(item, nextitem):
    limit_s = _timeout_s(item) + WATCHDOG_MARGIN_S
    # read after pytest ended in the middle of a test (the watchdog, a kill, a crash): which one was running
    _note(item.config, f"{item.nodeid} (its limit: {limit_s:g} s for setup, call and teardown; past it the "
                       "watchdog prints 'Timeout' and every thread's stack, and ends pytest with status 1)\n")
    faulthandler.dump_traceback_later(limit_s, exit=True, file=item.config._tirdeflect_watchdog_out)
    yield
    faulthandler.cancel_dump_traceback_later()
    _note(item.config, "")


# -- nothing left running ----------------------------------------------------
# A process or non-daemon thread that a test leaves behind can keep the test
# run from ending: the interpreter joins non-daemon threads and
# multiprocessing children at exit, and CI waits for every process that
# holds its output. (A CI run once printed "454 passed" and then never
# ended.) At the end of the session each one left is named, with where it
# stands, and ended: the tests' own processes (below this one, or orphans
# whose working directory or command line is in this checkout or in the
# session's temporary directory) and the threads that are not idle pool
# workers (named only: a thread cannot be ended). Then the process leaves
# without the interpreter's own clean-up (pytest_unconfigure below), which
# nothing can hold up.


def _processes() -> dict[int, tuple[int, int]]:
    """pid -> (parent pid, start time in clock ticks since boot) of every
    process (Linux /proc; empty elsewhere)."""
    table = {}
    try:
        names = os.listdir("/proc")
    except OSError:
        return table
    for name in names:
        if name.isdigit():
            try:
                with open(f"/proc/{name}/stat", "rb") as f:
                    fields = f.read().rpartition(b")")[2].split()
                table[int(name)] = (int(fields[1]), int(fields[19]))
            except (OSError, ValueError, IndexError):
                continue
    return table


def _descendants(pid: int, table: dict[int, tuple[int, int]]) -> set[int]:
    children: dict[int, list[int]] = {}
    for child, (parent, _) in table.items():
        children.setdefault(parent, []).append(child)
    found, todo = set(), [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            found.add(child)
            todo.append(child)
    return found


def _cmdline(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().replace(b"\0", b" ").decode(errors="replace").strip()[:200]
    except OSError:
        return "?"


def _alive(pid: int) -> bool:
    """Is ``pid`` running (not gone, not a zombie)?"""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            return f.read().rpartition(b")")[2].split()[0] != b"Z"
    except OSError:
        return False


def _ours(pid: int, places: tuple[str, ...]) -> bool:
    """Was ``pid`` started in this checkout or the session's temporary files
    (its working directory there, or a path there on its command line)?"""
    try:
        cwd = os.readlink(f"/proc/{pid}/cwd")
    except OSError:
        cwd = ""
    words = _cmdline(pid).split()
    return any(path == p or path.startswith(p + os.sep) for p in places for path in [cwd, *words])


def _left_running(session) -> list[int]:
    """The tests' processes still running: those below this one, and orphans
    started after it from this checkout or the session's temporary files."""
    table = _processes()
    me = os.getpid()
    if me not in table:
        return []
    started = table[me][1]
    places = (str(session.config.rootpath),)
    try:
        places += (str(session.config._tmp_path_factory.getbasetemp()),)
    except Exception:  # noqa: BLE001 - no temporary directory was made
        pass
    below = _descendants(me, table)
    pids = [pid for pid, (parent, start) in table.items()
            if pid != me and _alive(pid)
            and (pid in below or (parent == 1 and start >= started and _ours(pid, places)))]
    # multiprocessing's resource tracker ends with this process, by design
    return [pid for pid in pids if "multiprocessing.resource_tracker" not in _cmdline(pid)]


def pytest_sessionfinish(session, exitstatus):
    import signal
    import time
    import traceback

    session.config._tirdeflect_exitstatus = int(exitstatus)
    problems = []
    frames = sys._current_frames()
    for t in threading.enumerate():
        if t is threading.main_thread() or t.daemon or not t.is_alive():
            continue
        stack = traceback.format_stack(frames[t.ident]) if t.ident in frames else []
        if stack and "work_queue.get(block=True)" in stack[-1]:
            continue  # an idle worker of a thread pool: woken and joined at exit
        problems.append(f"thread {t.name!r} still running (the interpreter would wait for it):\n"
                        + "".join(stack[-4:]))
    pids = _left_running(session)
    for pid in pids:
        problems.append(f"process {pid} still running: {_cmdline(pid)}")
    if not problems:
        return
    sys.stderr.write("\ntests left these running; ending them:\n" + "\n".join(problems) + "\n")
    for sig in (signal.SIGTERM, signal.SIGKILL):
        for pid in pids:
            try:
                os.kill(pid, sig)
            except OSError:
                pass
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and any(_alive(pid) for pid in pids):
            time.sleep(0.1)  # polling the processes' state, bounded by the deadline


@pytest.hookimpl(trylast=True)
def pytest_unconfigure(config):
    """The last thing pytest does: leave at once with the session's status.

    Whatever the hundreds of tests left in this one interpreter (thread pools,
    Qt, HDF5, GenTL producers and Aravis with their own threads and C-level
    clean-up) cannot then keep the process from ending after the summary.
    The program's own exits are tested where they happen, in subprocesses
    (``tirdeflect`` commands and the window with ``--quit-after``)."""
    faulthandler.cancel_dump_traceback_later()
    out = getattr(config, "_tirdeflect_watchdog_out", None)
    if out is not None:
        out.close()
    note = getattr(config, "_tirdeflect_watchdog_note", None)
    if note and not os.environ.get("TIRDEFLECT_WATCHDOG_NOTE"):
        try:
            os.unlink(note)
        except OSError:
            pass
    status = getattr(config, "_tirdeflect_exitstatus", None)
    if status is None:
        return
    for stream in (sys.stdout, sys.stderr, sys.__stdout__, sys.__stderr__):
        try:
            stream.flush()
        except Exception:  # noqa: BLE001 - a stream already closed
            pass
    os._exit(status)
