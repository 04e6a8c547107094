"""A test stuck while holding the GIL ends the whole run in minutes, with its
name and every thread's stack (tests/conftest.py, "a stuck test ends the run").

Run for real: pytest in a subprocess, two pytest-xdist workers as tests/run.sh
starts them, this project's conftest as its plugin, on a throwaway test file
in which one test deadlocks (a pthread mutex locked twice through
``ctypes.PyDLL``: the GIL stays held, pytest-timeout's SIGALRM handler never
runs) and the others are ordinary one-second tests."""

import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from tests.conftest import WATCHDOG_MARGIN_S

ROOT = Path(__file__).resolve().parents[1]
#: the ordinary tests beside the stuck one, one second each. xdist queues about half of them
#: to each worker at the start; run to the end (xdist's own shutdown lets a worker finish its
#: queue) the other worker goes on for ~N/2 s, well past the stuck test's 1 + WATCHDOG_MARGIN_S
N_ORDINARY = 100

STUCK = '''
import ctypes
import ctypes.util
import time

import pytest


@pytest.mark.slow  # run first, as tests/conftest.py orders the slow ones
@pytest.mark.timeout(1)
def test_stuck_holding_the_gil():
    libc = ctypes.PyDLL(ctypes.util.find_library("c"))
    mutex = ctypes.create_string_buffer(64)  # zeroed: PTHREAD_MUTEX_INITIALIZER on glibc
    libc.pthread_mutex_lock(mutex)
    libc.pthread_mutex_lock(mutex)  # never returns


@pytest.mark.parametrize("k", range({n}))
def test_ordinary(k):
    time.sleep(1.0)  # one second of a test's work
'''


@pytest.mark.slow
@pytest.mark.timeout(240)  # hang detector: the run below takes ~30 s on a quiet machine
def test_a_deadlocked_test_ends_the_run_with_its_name_and_every_stack(tmp_path):
    pytest.importorskip("xdist")
    (tmp_path / "test_stuck.py").write_text(textwrap.dedent(STUCK.format(n=N_ORDINARY)))
    note = tmp_path / "watchdog-note"
    env = dict(os.environ, TIRDEFLECT_WATCHDOG_NOTE=str(note))
    env.pop("PYTEST_XDIST_WORKER", None)  # the run below has workers (and a stop file) of its own
    run = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "tests.conftest",
         "--rootdir", str(ROOT), "-c", str(ROOT / "pyproject.toml"), "-n", "2", "--dist", "worksteal",
         str(tmp_path / "test_stuck.py")],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=200)
    out = run.stdout
    assert run.returncode != 0, out[-3000:]
    # the watchdog fired at the stuck test's limit plus its margin, and printed every thread's stack
    assert f"Timeout (0:00:{1 + WATCHDOG_MARGIN_S:02.0f})!" in out, out[-3000:]
    assert re.search(r'File ".*test_stuck\.py", line \d+ in test_stuck_holding_the_gil', out), out[-3000:]
    assert re.search(r"worker 'gw\d' crashed while running '[^']*test_stuck_holding_the_gil'", out), out[-3000:]
    # the stuck test's name was in the worker's note, for tests/run.sh to print
    notes = {p.name: p.read_text() for p in tmp_path.glob("watchdog-note.gw*")}
    assert any("test_stuck_holding_the_gil" in text for text in notes.values()), notes
    # the run stopped instead of going through the rest of the ordinary tests: the other worker
    # stopped after the test it was running when the stuck one's worker died
    passed = re.search(r"(\d+) passed", out)
    n_passed = int(passed.group(1)) if passed else 0
    assert n_passed <= N_ORDINARY // 2 - 10, f"{n_passed} of {N_ORDINARY} ran: the run did not stop\n{out[-3000:]}"


TRAPPED = '''
import ctypes
import threading
import time


def test_glib_fatal_error_in_a_thread():
    glib = ctypes.CDLL("{library}")
    glib.g_log.argtypes = [ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_char_p]
    G_LOG_LEVEL_ERROR = 1 << 2
    erring = threading.Thread(target=glib.g_log, args=(b"TirdeflectTest", G_LOG_LEVEL_ERROR, b"%s",
                                                       b"a fatal error raised by the test"))
    erring.start()
    time.sleep(60)  # the report ends this process long before
'''


@pytest.mark.timeout(120)  # hang detector: the run below takes ~3 s
def test_a_fatal_glib_error_ends_the_run_with_its_message_the_test_and_every_stack(tmp_path):
    """GLib's g_error (Qt's event loop, Aravis) raises SIGTRAP: its one-line message used to be lost with the
    process (pytest's capture file); now it reaches the terminal and the note tests/run.sh prints last."""
    import ctypes.util

    from tests.conftest import GLIB_TRAP_STATUS

    library = ctypes.util.find_library("glib-2.0")
    if library is None:
        pytest.skip("no GLib on this machine")
    (tmp_path / "test_trapped.py").write_text(textwrap.dedent(TRAPPED.format(library=library)))
    note = tmp_path / "watchdog-note"
    env = dict(os.environ, TIRDEFLECT_WATCHDOG_NOTE=str(note))
    env.pop("PYTEST_XDIST_WORKER", None)
    run = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "tests.conftest",
         "--rootdir", str(ROOT), "-c", str(ROOT / "pyproject.toml"), str(tmp_path / "test_trapped.py")],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=100)
    out = run.stdout
    assert run.returncode == GLIB_TRAP_STATUS, out[-3000:]
    assert re.search(r"GLib ended this process \(SIGTRAP\): .*TirdeflectTest-ERROR \*\*.*a fatal error raised "
                     r"by the test", out), out[-3000:]
    assert re.search(r'File ".*test_trapped\.py", line \d+ in test_glib_fatal_error_in_a_thread', out), out[-3000:]
    text = note.read_text()
    assert "test_glib_fatal_error_in_a_thread" in text and "a fatal error raised by the test" in text, text


def test_the_runs_own_wrapper_is_not_taken_for_a_process_the_tests_left(request, monkeypatch):
    """At the end of a run, orphans started from the checkout after the run began are taken for
    processes the tests left, and ended. The run's own wrapper is no such process, even orphaned and
    started in the same clock tick (`setsid nohup timeout 1500 python -m pytest ... &`): taken for
    one, it was ended with the run inside it, before pytest printed its summary (seen 2026-12-06).
    Here this process's parent is made such a wrapper in the process table the check reads."""
    import tests.conftest as C

    real = C._processes()
    me = os.getpid()
    if me not in real:
        pytest.skip("no /proc process table here")
    parent = real[me][0]
    table = dict(real)
    table[parent] = (1, real[me][1])  # orphaned, started in this process's clock tick
    monkeypatch.setattr(C, "_processes", lambda: table)
    monkeypatch.setattr(C, "_xdist_worker", lambda: "")  # judged as the controller of a run judges
    monkeypatch.setattr(C, "_ours", lambda pid, places: pid == parent)  # started from the checkout
    assert parent not in C._left_running(request.session)
    table[parent] = (1, real[me][1] + 1)  # the same process as a sibling, not an ancestor: still found
    table[me] = (real[me][0] + 10**9, real[me][1])
    assert parent in C._left_running(request.session)


def test_orphans_of_another_run_on_the_same_checkout_are_not_ended(request, monkeypatch):
    """Two pytest runs on one checkout (two terminals, or a background run): at the end of one, the other's
    processes (orphaned, started from the checkout after it began) were taken for its own and ended (seen
    7 Dec 2026: a run of test_formats.py ended mid-way by another's check). Every run now tags what it
    starts; an orphan under another run's tag is left alone, one under this run's (or its workers') is
    ended, an untagged one from the checkout is still this run's to end. Real processes (their environment
    read from /proc), orphaned in the process table the check reads."""
    import subprocess
    import sys

    import tests.conftest as C

    real = C._processes()
    me = os.getpid()
    if me not in real:
        pytest.skip("no /proc process table here")
    mine = os.environ.get(C._RUN_TAG, "")
    assert mine, "this run tags the processes its tests start"
    tags = {"other": "run-1", "ours": mine, "our worker": f"{mine}/gw7-1", "untagged": None}
    procs = {}
    try:
        for name, tag in tags.items():
            env = {k: v for k, v in os.environ.items() if k != C._RUN_TAG}
            if tag is not None:
                env[C._RUN_TAG] = tag
            procs[name] = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"], env=env)
        table = C._processes()
        for p in procs.values():
            table[p.pid] = (1, real[me][1] + 1)  # orphans started after this run
        monkeypatch.setattr(C, "_processes", lambda: table)
        monkeypatch.setattr(C, "_xdist_worker", lambda: "")  # judged as a plain run's or a controller's check
        monkeypatch.setattr(C, "_ours", lambda pid, places: pid in {p.pid for p in procs.values()})
        left = set(C._left_running(request.session))
        found = {name for name, p in procs.items() if p.pid in left}
        if mine.startswith("run-"):
            assert found == {"ours", "our worker", "untagged"}, found
        else:  # this test runs in an xdist worker: its tag is a worker's, under the controller's
            assert "other" not in found and "ours" in found, found
    finally:
        for p in procs.values():
            p.kill()
            p.wait(30)
