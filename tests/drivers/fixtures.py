"""Reusable fixtures that start and stop real GenICam endpoints for tests.

Import the ones you need in a test module (pytest then finds them)::

    from tests.drivers.fixtures import gv_fake_camera, gv_fake_camera_lossy, viky_cti  # noqa: F401

* ``gv_fake_camera`` -- ``arv-fake-gv-camera-0.8 -i 127.0.0.1`` as a subprocess
  (GigE Vision over loopback); yields a :class:`FakeGvCamera` with
  ``camera_id`` (``"aravis:127.0.0.1"``), ``process`` and :meth:`FakeGvCamera.kill`.
* ``gv_fake_camera_lossy`` -- the same with ``-r 20`` (2 % of GVSP packets lost).
* ``viky_cti`` -- path of the ``viky.cti`` GenTL producer of the genicam wheel.

Only one GigE fake camera can listen on 127.0.0.1:3956, so the fixtures take a
machine-wide file lock, :func:`camera_lock` (concurrent pytest runs and xdist
workers wait for each other, at most ``LOCK_TIMEOUT_S``; tests/conftest.py holds
it over every test that uses cameras). Every wait is bounded; the process is
always killed.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import tempfile
import time

import pytest

from tests.helpers import acquire_file_lock, release_file_lock

FAKE_GV_EXE = "arv-fake-gv-camera-0.8"
ADDRESS = "127.0.0.1"
GVCP_PORT = 3956
#: hang detector for the camera lock: the longest test that holds it takes about 20 s quiet
LOCK_TIMEOUT_S = 240.0
START_TIMEOUT_S = 5.0
LOCK_PATH = os.path.join(tempfile.gettempdir(), "tirdeflect-fake-gv-camera.lock")
_lock = {"file": None, "depth": 0}  # this process's hold on LOCK_PATH (taken again: counted)


def _acquire_camera_lock() -> None:
    if _lock["depth"] == 0:
        _lock["file"] = acquire_file_lock(LOCK_PATH, LOCK_TIMEOUT_S)
    _lock["depth"] += 1


def _release_camera_lock() -> None:
    _lock["depth"] -= 1
    if _lock["depth"] == 0:
        f, _lock["file"] = _lock["file"], None
        release_file_lock(f)


@contextlib.contextmanager
def camera_lock():
    """Hold the machine-wide camera lock: no other test (of this run or another on this PC)
    that starts a fake camera or depends on what camera discovery finds runs meanwhile.
    Re-entrant within a process (a test holding it may start a :class:`FakeGvCamera`)."""
    _acquire_camera_lock()
    try:
        yield
    finally:
        _release_camera_lock()


def _udp_bound(address: str, port: int) -> bool:
    """True when a UDP socket is bound to address:port (reads /proc/net/udp)."""
    a, b, c, d = (int(x) for x in address.split("."))
    want = f"{d:02X}{c:02X}{b:02X}{a:02X}:{port:04X}"
    try:
        with open("/proc/net/udp") as f:
            return any(line.split()[1] == want for line in f.readlines()[1:])
    except OSError:
        return False


def fake_camera_command(exe: str, loss_per_thousand: int = 0) -> list:
    """The command line of a fake camera on :data:`ADDRESS` that dies with the thread that starts it.

    A pytest run killed mid-test (Ctrl+C twice, CI's limit, ``pkill``) skips every finalizer; the fake
    camera it had started then kept 127.0.0.1:3956 and the next run's 17 camera tests failed with "already
    in use". ``setpriv --pdeathsig KILL`` (util-linux, in every Debian) execs the camera with the kernel's
    parent-death signal set, so it is SIGKILLed when its parent goes, however that goes."""
    cmd = [exe, "-i", ADDRESS]
    if loss_per_thousand:
        cmd += ["-r", str(int(loss_per_thousand))]
    setpriv = shutil.which("setpriv")
    return [setpriv, "--pdeathsig", "KILL", "--", *cmd] if setpriv else cmd


class FakeGvCamera:
    """A running ``arv-fake-gv-camera-0.8`` process on loopback.

    Parameters
    ----------
    loss_per_thousand : int
        GVSP packets dropped per thousand (the fake's ``-r``).
    """

    def __init__(self, loss_per_thousand: int = 0):
        self.loss_per_thousand = int(loss_per_thousand)
        self.address = ADDRESS
        self.camera_id = f"aravis:{ADDRESS}"
        self.process = None
        self._locked = False

    def start(self) -> "FakeGvCamera":
        exe = shutil.which(FAKE_GV_EXE)
        if exe is None:
            raise RuntimeError(f"{FAKE_GV_EXE} not found; install the aravis-tools package (Debian: aravis-tools)")
        _acquire_camera_lock()
        self._locked = True
        if _udp_bound(ADDRESS, GVCP_PORT):
            self._release_lock()
            raise RuntimeError(
                f"UDP {ADDRESS}:{GVCP_PORT} is already in use (a stray {FAKE_GV_EXE}?); stop it and rerun"
            )
        self.process = subprocess.Popen(fake_camera_command(exe, self.loss_per_thousand),
                                        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        deadline = time.monotonic() + START_TIMEOUT_S
        while not _udp_bound(ADDRESS, GVCP_PORT):
            if self.process.poll() is not None:
                err = self.process.stderr.read().decode(errors="replace")
                self.stop()
                raise RuntimeError(f"{FAKE_GV_EXE} exited with {self.process.returncode}: {err.strip()}")
            if time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(f"{FAKE_GV_EXE} did not bind {ADDRESS}:{GVCP_PORT} within {START_TIMEOUT_S:g} s")
            time.sleep(0.01)
        return self

    def kill(self) -> None:
        """SIGKILL the camera process (simulates a camera unplugged mid-stream)."""
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait(5)

    def stop(self) -> None:
        self.kill()
        if self.process is not None and self.process.stderr is not None:
            self.process.stderr.close()
        self._release_lock()

    def _release_lock(self):
        if self._locked:
            self._locked = False
            _release_camera_lock()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()


def _aravis_or_skip():
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis  # noqa: F401
    except (ImportError, ValueError) as exc:
        pytest.skip(f"Aravis GObject bindings missing: {exc}")
    if shutil.which(FAKE_GV_EXE) is None:
        pytest.skip(f"{FAKE_GV_EXE} not installed")


def _finalize_aravis_objects() -> None:
    """Free what the test left of Aravis' objects now, in this (main) thread.

    Left to the garbage collector, an Aravis device or stream is finalized in
    whatever thread happens to allocate next, holding the GIL while Aravis
    takes its own locks. A CI run froze that way (every thread waiting, no
    CPU): a later GUI test's background thread was importing scipy (for PIV)
    while the window's Aravis discovery ran; the finalization in that thread
    is the likeliest reading of the stacks, not a proven one."""
    import gc

    gc.collect()


@pytest.fixture
def gv_fake_camera():
    """A clean GigE Vision fake camera on 127.0.0.1 (killed afterwards)."""
    _aravis_or_skip()
    with FakeGvCamera() as cam:
        yield cam
    _finalize_aravis_objects()


@pytest.fixture
def gv_fake_camera_lossy():
    """A GigE Vision fake camera on 127.0.0.1 losing 20 per thousand GVSP packets."""
    _aravis_or_skip()
    with FakeGvCamera(loss_per_thousand=20) as cam:
        yield cam
    _finalize_aravis_objects()


@pytest.fixture
def viky_cti():
    """Path of viky.cti, the GenTL producer shipped in the genicam wheel."""
    genicam = pytest.importorskip("genicam")
    path = os.path.join(os.path.dirname(genicam.__file__), "viky.cti")
    if not os.path.isfile(path):
        pytest.skip(f"no viky.cti next to {genicam.__file__}")
    return path
