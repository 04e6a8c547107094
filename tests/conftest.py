"""Shared test set-up: headless Qt, a private cache directory, fixed seeds, a
watchdog that ends a stuck run with every thread's stack, a check at the
end of the session that the tests left nothing running and no shared memory
of an ended run behind, and what makes the suite safe to run in parallel
with pytest-xdist (tests/run.sh runs it so)."""

import faulthandler
import signal
import glob
import os
import re
import sys
import tempfile
import threading
import time

import numpy as np
import pytest

from tests.helpers import FORK_SERVER_COMMAND, pid_alive

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

# Module- and session-scoped fixtures run before the per-test directories below are set: they
# get this process's own, so that no test reads or writes the user's FFTW wisdom or settings.
# (tests/app/test_parallel.py's serial run, a module fixture, once loaded the user's wisdom,
# measured over weeks of benchmarks, while the parallel run it is compared with planned afresh:
# other FFT plans, and the region motion of /pin_status off by 2e-6 px against a 1e-6 bound.)
_SESSION_DIRS = tempfile.TemporaryDirectory(prefix="tirdeflect-test-dirs-")
os.environ["TIRDEFLECT_CACHE_DIR"] = os.path.join(_SESSION_DIRS.name, "cache")
os.environ["TIRDEFLECT_CONFIG_DIR"] = os.path.join(_SESSION_DIRS.name, "config")


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
# 1. pytest-timeout (``timeout`` in pyproject.toml, 240 s, or a test's
#    ``@pytest.mark.timeout(N)``) fails the test with its stack and the run goes
#    on -- but its SIGALRM handler is Python code: it never runs while a thread
#    holds the GIL in C (a deadlock in an extension's import or finalizer).
# 2. Then, WATCHDOG_MARGIN_S later, faulthandler's own C thread, which needs no
#    GIL, writes every thread's Python stack to the terminal and ends the
#    process (status 1 in a serial run; under xdist the worker dies and the run
#    stops with status 2, "worker crashed while running ..."). Its C thread cannot print the test's name, so that is
#    written when the test starts to the file $TIRDEFLECT_WATCHDOG_NOTE
#    (tests/run.sh sets it and prints the file after such an end; without it, a
#    file in the temporary folder, named on stderr at the start of the run).
# The slowest test but the install (which has its own 600 s mark) needs 13 s on a
# quiet 2-core machine: 240 s is 18 times that, and no test came near it in the
# full runs of issue 21 loaded to twice the cores. A deadlock that holds the GIL
# ends the run within 5 minutes: 240 + 20 s, plus the install check and the
# start of tests/run.sh. Checked from fresh clones with a throwaway test locking a
# pthread mutex twice through ctypes.PyDLL (the GIL held; tests/test_watchdog.py
# does the same on a small run): the stuck test run first, `CI=true .ci/run`
# ended 263 s after it began, 277 s with the install; run among the last, the
# run ended with it (602 of 714 tests had run) instead of going through the rest.

#: seconds past a test's pytest-timeout limit at which the GIL-free watchdog ends the run
WATCHDOG_MARGIN_S = 20.0
#: the limit when pytest-timeout is not installed (its ini default in pyproject.toml)
DEFAULT_TIMEOUT_S = 240.0


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


def _xdist_worker() -> str:
    """This process's pytest-xdist worker id (``gw0``, ``gw1``, ...); "" when not a worker
    (a plain run, or the controller of an xdist run, which runs no test itself)."""
    return os.environ.get("PYTEST_XDIST_WORKER", "")


def pytest_configure(config):
    # the terminal's stderr as it is now, between tests: during a test, fd 2 is pytest's capture file
    # (an xdist worker's fd 2 is the controller's stderr: the watchdog's stacks reach the terminal too)
    config._tirdeflect_watchdog_out = os.fdopen(os.dup(2), "w")
    if hasattr(signal, "SIGTRAP"):
        _report_glib_traps(config)
    path = os.environ.get("TIRDEFLECT_WATCHDOG_NOTE") or os.path.join(
        tempfile.gettempdir(), f"tirdeflect-watchdog-{os.getpid()}.txt")
    if _xdist_worker():  # one note per worker (tests/run.sh reads NOTE.gw0, NOTE.gw1, ...)
        path = f"{path}.{_xdist_worker()}"
        # every process this worker's tests start carries this in its environment: how the
        # check at the end tells this worker's orphans from a sibling worker's (below); under its
        # controller's tag, which the controller's check takes as its own
        os.environ[_RUN_TAG] = f"{os.environ.get(_RUN_TAG, '')}/{_xdist_worker()}-{os.getpid()}"
    else:
        # a plain run or a controller tags its processes too: another pytest run on the same checkout
        # (a second terminal) started after this one carries its own tag, and is not this run's to end
        # (by-hand, 7 Dec 2026: two sessions' runs ended each other's background runs)
        os.environ[_RUN_TAG] = f"run-{os.getpid()}"
    config._tirdeflect_watchdog_note = path
    config._tirdeflect_shm_seen = {}  # block of an ended run -> the test it was first seen after
    config._tirdeflect_shm_before = _blocks_of_ended_runs()  # left by something before this session
    config._tirdeflect_sem_seen = {}  # multiprocessing's named semaphores, likewise (reported only)
    config._tirdeflect_sem_before = _semaphores()
    if not _xdist_worker():
        # the controller (or a plain run) names the file through which it stops its workers; they
        # inherit the name through their environment (a pytest run inside a test names its own)
        os.environ[_STOP_FILE] = os.path.join(tempfile.gettempdir(), f"tirdeflect-stop-{os.getpid()}")
        config._tirdeflect_stop_file = os.environ[_STOP_FILE]
        try:  # one left by a killed run whose process had this number
            os.unlink(config._tirdeflect_stop_file)
        except OSError:
            pass
    if not os.environ.get("TIRDEFLECT_WATCHDOG_NOTE"):
        config._tirdeflect_watchdog_out.write(f"watchdog: a test stuck past its limit ends the run; "
                                              f"the running test's name is kept in {path}\n")
        config._tirdeflect_watchdog_out.flush()


# -- a fatal GLib error is named --------------------------------------------------------------
# GLib's fatal errors (g_error: Qt's event loop, Aravis) end the process with SIGTRAP. Its one-line
# message went to the test's capture file and was lost with the process: the CI printed "worker 'gw0'
# crashed" and nothing else, twice (6 Dec 2026, test_gui_usability; the likeliest cause, reproduced
# outside pytest: a handler that Aravis' heartbeat thread ran, docs/cameras.md). Now faulthandler
# writes every thread's Python stack into a pipe when the trap comes, without the GIL; the trap then
# returns (a Python-level handler is chained after it, so SIGTRAP no longer ends the process at once)
# and GLib's thread spins in g_error's loop. A thread of this process reads the pipe, takes GLib's
# message from pytest's capture, writes both to the terminal and the message to the note tests/run.sh
# prints last, and ends the process (status 70). Forked children get SIGTRAP's default back. If the
# erring thread holds the GIL, the watchdog ends the test later with the stacks, as before.

#: exit status of a pytest process that GLib's fatal error ended
GLIB_TRAP_STATUS = 70


def _report_glib_traps(config) -> None:
    read_fd, write_fd = os.pipe()
    signal.signal(signal.SIGTRAP, lambda signum, frame: None)
    faulthandler.register(signal.SIGTRAP, file=write_fd, all_threads=True, chain=True)

    def default_in_child():
        faulthandler.unregister(signal.SIGTRAP)
        signal.signal(signal.SIGTRAP, signal.SIG_DFL)

    os.register_at_fork(after_in_child=default_in_child)
    threading.Thread(target=_glib_trap_reporter, args=(config, read_fd), name="tirdeflect-glib-trap",
                     daemon=True).start()


def _glib_trap_reporter(config, read_fd: int) -> None:
    import select

    stacks = os.read(read_fd, 1 << 20)  # blocks until a trap
    while select.select([read_fd], [], [], 0.5)[0]:  # the rest of the stacks, written at once
        chunk = os.read(read_fd, 1 << 20)
        if not chunk:
            break
        stacks += chunk
    header = stacks.split(b"\n", 1)[0]
    again = stacks.find(header, len(header))  # one g_log call trapped twice (seen): keep one copy
    if header and again > 0:
        stacks = stacks[:again]
    err = ""
    capman = config.pluginmanager.getplugin("capturemanager")
    try:
        err = capman.read_global_capture().err if capman is not None else ""
    except Exception:  # capture not running (pytest -s): GLib's message is on the terminal already
        pass
    lines = [line.strip() for line in (err or "").splitlines() if "-ERROR **" in line or "-CRITICAL **" in line]
    message = lines[-1] if lines else "(no GLib message in the captured output)"
    out = config._tirdeflect_watchdog_out
    out.write(f"\nGLib ended this process (SIGTRAP): {message}\nEvery thread's Python stack at the trap:\n"
              f"{stacks.decode(errors='replace')}\n")
    out.flush()
    with open(config._tirdeflect_watchdog_note, "a") as f:
        f.write(f"GLib ended it (SIGTRAP): {message}\n")
    os._exit(GLIB_TRAP_STATUS)


def _note(config, text: str) -> None:
    with open(config._tirdeflect_watchdog_note, "w") as f:
        f.write(text)


@pytest.hookimpl(hookwrapper=True, tryfirst=True)
def pytest_runtest_protocol(item, nextitem):
    limit_s = _timeout_s(item) + WATCHDOG_MARGIN_S
    # read after pytest ended in the middle of a test (the watchdog, a kill, a crash): which one was running
    _note(item.config, f"{item.nodeid} (its limit: {limit_s:g} s for setup, call and teardown; past it the "
                       "watchdog prints 'Timeout' and every thread's stack, and ends this pytest process)\n")
    faulthandler.dump_traceback_later(limit_s, exit=True, file=item.config._tirdeflect_watchdog_out)
    yield
    faulthandler.cancel_dump_traceback_later()
    _note(item.config, "")
    for kind, names in (("shm", _blocks_of_ended_runs()), ("sem", _semaphores())):
        seen = getattr(item.config, f"_tirdeflect_{kind}_seen")
        for name in names - seen.keys():
            seen[name] = item.nodeid
    why = _stop_requested()
    if why and not item.session.shouldstop:  # xdist's worker loop stops after this test
        item.session.shouldstop = why


# -- no shared memory of an ended run left behind ------------------------------------------
# The batch engine's workers hand their maps over in /dev/shm blocks named after the run
# (app.batch.shm_results.shm_name: tdf<run pid>_<hex>); when a run ends, however it ends, the
# blocks nobody took are freed by multiprocessing's resource tracker. After every test each
# pytest process notes the blocks of ended runs it had not seen yet, with the test; at the end
# of the session, once every test has ended (and with it every tracker's clean-up), the
# controller reports the ones still there with the test they were first seen after, removes
# them, and the session fails. A leak found this way (a worker ending with its run half way
# through making a block) stayed in RAM until reboot.
_SHM_DIR = "/dev/shm"
_SHM_BLOCK = re.compile(r"tdf(\d+)_[0-9a-f]+$")


def _blocks_of_ended_runs() -> set:
    """Names of the /dev/shm blocks of app.batch.shm_results whose run's process has ended."""
    try:
        names = os.listdir(_SHM_DIR)
    except OSError:
        return set()
    return {n for n in names if (m := _SHM_BLOCK.match(n)) and not pid_alive(int(m.group(1)))}


# multiprocessing's named semaphores (sem.mp-*: the locks of a worker pool's queues, from the fork
# server's processes) are freed by the same trackers. One was left now and then by a suite run (not
# found in isolation: the test a script without the main guard showed it once in eight runs of
# test_parallel.py, none in 30 runs alone); they are reported with the test they were first seen
# after, not removed (a running program's pool may still open one by name) and do not fail the run.
_SEMAPHORE = re.compile(r"sem\.mp-[0-9A-Za-z_]+$")


def _semaphores() -> set:
    """Names of multiprocessing's named semaphores in /dev/shm."""
    try:
        return {n for n in os.listdir(_SHM_DIR) if _SEMAPHORE.match(n)}
    except OSError:
        return set()


def _shm_record(worker: str, kind: str = "shm") -> str:
    """The file through which xdist worker ``worker`` (a glob pattern too) hands its notes of ``kind``
    ("shm": blocks, "sem": semaphores) to the controller."""
    return f"{os.environ.get(_STOP_FILE, '')}.{kind}.{worker}"


def _shm_leaks(session, kind: str = "shm") -> list:
    """In the controller (or a plain run), after every test: ``(name, size, first seen after)``
    for every block of an ended run (``kind`` "sem": semaphore) seen during this session and still
    in /dev/shm."""
    seen = dict(getattr(session.config, f"_tirdeflect_{kind}_seen"))
    for path in glob.glob(_shm_record("gw*", kind)):
        with open(path) as f:
            for line in f:
                name, _, test = line.rstrip("\n").partition("\t")
                seen.setdefault(name, test)
        os.unlink(path)
    seen = {n: t for n, t in seen.items() if n not in getattr(session.config, f"_tirdeflect_{kind}_before")}
    # a run killed by one of the last tests: its resource tracker frees the blocks within a second
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline and any(os.path.exists(os.path.join(_SHM_DIR, n)) for n in seen):
        time.sleep(0.1)  # polling the trackers' clean-up, bounded by the deadline
    leaks = []
    for name, test in sorted(seen.items()):
        try:
            leaks.append((name, os.stat(os.path.join(_SHM_DIR, name)).st_size, test))
        except OSError:
            continue  # freed
    return leaks


#: environment variable naming the file whose existence tells xdist's workers to stop after their
#: current test (written by the controller when one of them died in the middle of a test)
_STOP_FILE = "TIRDEFLECT_TEST_STOP_FILE"


def _stop_requested() -> str:
    """Why this worker must stop after its current test; "" to go on."""
    path = os.environ.get(_STOP_FILE, "")
    try:
        with open(path) as f:
            return f.read() or "stop"
    except OSError:
        return ""


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node, error):
    """xdist's controller: a worker died in the middle of the run (the watchdog above ended it, or
    a crash). xdist has already reported its test as failed ("worker 'gw0' crashed while running
    ..."), with the stacks above it; left alone it would start a new worker and go on for the
    rest of the run. Stop it instead, as the watchdog stops a run without xdist, and the run ends
    with status 2 (interrupted).

    xdist's own shutdown lets each worker first run every test already queued to it (with
    ``--dist worksteal`` up to half the suite: a deadlock demo ran 8 minutes, the other worker going
    through 109 more tests). So the workers are also told through a file (``_STOP_FILE``) that each
    reads after every test: each stops after the test it is running, itself bounded by its limit."""
    if error is None:
        return
    why = f"worker {node.gateway.id} ended in the middle of a test ({error})"
    path = os.environ.get(_STOP_FILE)
    if path:
        with open(path, "w") as f:
            f.write(why)
    dsession = node.config.pluginmanager.getplugin("dsession")
    if dsession is not None and not dsession.shouldstop:
        dsession.shouldstop = why


# -- one test at a time: the cameras -------------------------------------------
# What a test sees of this machine's cameras must not change under it: only one
# GigE Vision fake camera can listen on 127.0.0.1:3956, and while one runs,
# Aravis' discovery in any other process finds it, so a window or command left
# to open "the first camera found" would open it. Under pytest-xdist (tests/run.sh)
# or beside another test run on the same PC, every test that starts a fake
# camera, uses a GenTL producer or Aravis, or depends on what discovery finds
# (the ``aravis``, ``gentl`` and ``cameras`` marks, the camera fixtures) holds
# the machine-wide camera lock of tests/drivers/fixtures.py from its setup to its
# teardown: those tests run one at a time, as in a plain run, while the others
# go on in parallel. (xdist's own ``--dist loadgroup`` would do it by scheduling,
# but its xdist 3.8 sets a node id attribute that pytest 9.2 no longer reads, and
# it cannot keep a second test run on the PC apart.)
_CAMERA_MARKS = ("aravis", "gentl", "cameras")
_CAMERA_FIXTURES = ("gv_fake_camera", "gv_fake_camera_lossy", "viky_cti")


@pytest.fixture(autouse=True)
def _cameras_one_test_at_a_time(request):
    item = request.node
    if not (any(item.get_closest_marker(m) for m in _CAMERA_MARKS)
            or any(f in request.fixturenames for f in _CAMERA_FIXTURES)):
        yield
        return
    from tests.drivers.fixtures import camera_lock

    with camera_lock():
        yield


@pytest.fixture(autouse=True)
def _dask_clusters_one_at_a_time(request):
    """A test with the ``dask_cluster`` mark starts a Dask cluster: one at a time on this PC."""
    if request.node.get_closest_marker("dask_cluster") is None:
        yield
        return
    from tests.helpers import acquire_file_lock, release_file_lock

    path = os.path.join(tempfile.gettempdir(), "tirdeflect-dask-cluster.lock")
    f = acquire_file_lock(path, 240.0)  # hang detector: such a test takes about 40 s under load
    try:
        yield
    finally:
        release_file_lock(f)


# -- the longest first -----------------------------------------------------------
# The ``slow`` tests (a whole install from a fresh clone, a wheel built and run:
# minutes each, in subprocesses of their own; the GUI flows of 10-17 s that need
# no shared fixture or camera lock) run first, so that under xdist the other
# workers go through the rest meanwhile instead of waiting for them at the end.
def pytest_collection_modifyitems(config, items):
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)  # stable: else as collected


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


def _ancestors(pid: int, table: dict[int, tuple[int, int]]) -> set[int]:
    """``pid``'s parent, its parent, ... up to (not including) init."""
    found = set()
    while pid in table and table[pid][0] > 1 and table[pid][0] not in found:
        pid = table[pid][0]
        found.add(pid)
    return found


def _cmdline(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().replace(b"\0", b" ").decode(errors="replace").strip()[:200]
    except OSError:
        return "?"


def _ours(pid: int, places: tuple[str, ...]) -> bool:
    """Was ``pid`` started in this checkout or the session's temporary files
    (its working directory there, or a path there on its command line)?"""
    try:
        cwd = os.readlink(f"/proc/{pid}/cwd")
    except OSError:
        cwd = ""
    words = _cmdline(pid).split()
    return any(path == p or path.startswith(p + os.sep) for p in places for path in [cwd, *words])


#: environment variable that marks the processes an xdist worker's tests started
_RUN_TAG = "TIRDEFLECT_TEST_WORKER"


def _tag_of(pid: int):
    """``pid``'s ``_RUN_TAG`` as it was started ("" without one), or None where its environment cannot be read."""
    try:
        with open(f"/proc/{pid}/environ", "rb") as f:
            entries = f.read().split(b"\0")
    except OSError:
        return None
    key = f"{_RUN_TAG}=".encode()
    return next((e[len(key):].decode(errors="replace") for e in entries if e.startswith(key)), "")


def _tagged(pid: int, tag: str) -> bool:
    """Was ``pid`` started by the run tagged ``tag``, or one of its xdist workers (``tag/gwN-pid``)?"""
    found = _tag_of(pid)
    return bool(found) and (found == tag or found.startswith(tag + "/"))


def _left_running(session) -> list[int]:
    """The tests' processes still running: those below this one, and orphans
    started after it from this checkout or the session's temporary files.

    In an xdist worker, only the orphans that carry this worker's tag in their
    environment: a sibling worker may still be running a test whose helpers
    have been orphaned on purpose (a killed run's workers), and those are not
    ours to end. The orphans without a tag (started with an environment of
    their own) are left to the controller, whose check runs after every
    worker has ended; orphans tagged by another run (:func:`_left_by_us`) are
    nobody's here."""
    table = _processes()
    me = os.getpid()
    if me not in table:
        return []
    started = table[me][1]
    tag = os.environ.get(_RUN_TAG, "")
    places = (str(session.config.rootpath),)
    try:
        places += (str(session.config._tmp_path_factory.getbasetemp()),)
    except Exception:  # noqa: BLE001 - no temporary directory was made
        pass
    below = _descendants(me, table)
    # what runs this run is not left by it: a wrapper started in the same clock tick from the
    # checkout and orphaned (`setsid nohup timeout ... pytest &`) looked like an orphan of the
    # tests, and was ended with the run inside it before its summary
    above = _ancestors(me, table)
    pids = [pid for pid, (parent, start) in table.items()
            if pid != me and pid not in above and pid_alive(pid)
            and (pid in below or (parent == 1 and start >= started and _left_by_us(pid, tag, places)))]
    # multiprocessing's resource tracker, and the app's fork server (app/worker_processes.py: its
    # workers are below it, and checked), end with this process, by design
    pids = [pid for pid in pids if "multiprocessing.resource_tracker" not in _cmdline(pid)
            and not (table[pid][0] == me and FORK_SERVER_COMMAND in _cmdline(pid))]
    # a fork server (or a worker of one) whose process has just ended (an xdist worker's, seen from
    # the controller) ends by itself a moment later, and so does a process already exiting (an xdist
    # worker seen from the controller: its memory, command line included, is already gone): given
    # 5 s, far above the milliseconds it takes
    deadline = time.monotonic() + 5.0
    while (time.monotonic() < deadline
           and any((FORK_SERVER_COMMAND in _cmdline(pid) or not _cmdline(pid)) and pid_alive(pid) for pid in pids)):
        time.sleep(0.05)  # polling their state, bounded by the deadline
    return [pid for pid in pids if pid_alive(pid)]


def _left_by_us(pid: int, tag: str, places: tuple[str, ...]) -> bool:
    """Is the orphan ``pid`` one this run's tests left: started under this run's tag (or a worker's under
    it); an xdist worker's, under its own alone. Untagged ones started in ``places`` (an environment of
    their own) are the controller's or a plain run's; another run's tagged ones are never ours."""
    if _tagged(pid, tag):
        return True
    return not _xdist_worker() and _tag_of(pid) == "" and _ours(pid, places)


@pytest.hookimpl(trylast=True)  # in xdist's controller: after its workers are ended (xdist's own hook)
def pytest_sessionfinish(session, exitstatus):
    import signal
    import traceback

    session.config._tirdeflect_exitstatus = int(exitstatus)
    if _xdist_worker():
        for kind in ("shm", "sem"):
            with open(_shm_record(_xdist_worker(), kind), "w") as f:
                f.writelines(f"{n}\t{t}\n" for n, t in getattr(session.config, f"_tirdeflect_{kind}_seen").items())
    else:
        leaks = _shm_leaks(session)
        if leaks:
            sys.stderr.write("\nshared-memory blocks of ended runs left in /dev/shm (removed now):\n" + "".join(
                f"  {name} ({size / 1024:.0f} KB), first seen after {test}\n" for name, size, test in leaks))
            for name, _, _ in leaks:
                try:
                    os.unlink(os.path.join(_SHM_DIR, name))
                except OSError:
                    pass
            if session.config._tirdeflect_exitstatus == 0:
                session.config._tirdeflect_exitstatus = 1
        semaphores = _shm_leaks(session, "sem")
        if semaphores:
            sys.stderr.write("\nmultiprocessing semaphores left in /dev/shm (reported, not removed):\n" + "".join(
                f"  {name}, first seen after {test}\n" for name, _, test in semaphores))
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
        while time.monotonic() < deadline and any(pid_alive(pid) for pid in pids):
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
    stop_file = getattr(config, "_tirdeflect_stop_file", None)
    if stop_file:
        try:
            os.unlink(stop_file)
        except OSError:
            pass
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
