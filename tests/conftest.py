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
# A process or non-daemon thread that a test leaves behind keeps the test run
# from ending (the interpreter joins such threads and multiprocessing children
# at exit; a process holding the output pipe keeps CI waiting for its end).
# At the end of the session each one is named, with where it stands, and
# ended, so a leak shows up as a message instead of a run that never ends.

def _descendants(pid: int) -> list[int]:
    """Process ids below ``pid`` (Linux /proc; empty elsewhere)."""
    children: dict[int, list[int]] = {}
    try:
        names = os.listdir("/proc")
    except OSError:
        return []
    for name in names:
        if not name.isdigit():
            continue
        try:
            with open(f"/proc/{name}/stat", "rb") as f:
                stat = f.read().decode(errors="replace")
        except OSError:
            continue
        ppid = int(stat.rpartition(")")[2].split()[1])
        children.setdefault(ppid, []).append(int(name))
    found, todo = [], [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            found.append(child)
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


def pytest_sessionfinish(session, exitstatus):
    import signal
    import time
    import traceback

    problems = []
    frames = sys._current_frames()
    for t in threading.enumerate():
        if t is threading.main_thread() or t.daemon or not t.is_alive():
            continue
        where = "".join(traceback.format_stack(frames[t.ident])[-3:]) if t.ident in frames else ""
        problems.append(f"thread {t.name!r} still running (the interpreter would wait for it):\n{where}")
    # (multiprocessing's resource tracker ends with this process, by design)
    pids = [pid for pid in _descendants(os.getpid())
            if _alive(pid) and "multiprocessing.resource_tracker" not in _cmdline(pid)]
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
