"""Shared test set-up: headless Qt, a private cache directory, fixed seeds,
and a check at the end of the session that the tests left nothing running."""

import os
import sys
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
    status = getattr(config, "_tirdeflect_exitstatus", None)
    if status is None:
        return
    for stream in (sys.stdout, sys.stderr, sys.__stdout__, sys.__stderr__):
        try:
            stream.flush()
        except Exception:  # noqa: BLE001 - a stream already closed
            pass
    os._exit(status)
