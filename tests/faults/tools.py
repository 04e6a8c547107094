"""Real small disks for fault tests, and a real ``tirdeflect record`` subprocess.

* :func:`small_disk` -- a tmpfs (reserves space with fallocate) or an ext2 image
  on a loop device (no fallocate: HDF5 itself meets the full disk), mounted for
  the test and unmounted afterwards. Needs root; skips with the reason otherwise.
* :func:`fill_disk` -- a second process (``dd``) takes all the space left.
* :func:`start_record` -- ``python3 -m app.cli record ...`` from this checkout;
  :class:`RecordProcess` the same with its progress bar read as it goes.
* :func:`wait_until` -- a condition with a bounded deadline (no sleep-and-hope).
"""

from __future__ import annotations

import contextlib
import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def wait_until(condition, timeout_s: float, what: str, interval_s: float = 0.02):
    """Poll ``condition()`` until true; fail the test naming ``what`` after ``timeout_s`` seconds."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"{what}: not within {timeout_s:g} s")
        time.sleep(interval_s)


@contextlib.contextmanager
def small_disk(tmp_path: Path, kind: str, size_mb: int):
    """Mount a ``size_mb`` MB ``kind`` ("tmpfs" or "ext2") disk at ``tmp_path/kind``; yields the mount point."""
    if os.geteuid() != 0:
        pytest.skip("mounting a small disk needs root")
    mnt = tmp_path / kind
    mnt.mkdir()
    if kind == "tmpfs":
        cmd = ["mount", "-t", "tmpfs", "-o", f"size={size_mb}m", "tmpfs", str(mnt)]
    else:
        image = tmp_path / f"{kind}.img"
        with open(image, "wb") as fh:
            fh.truncate(size_mb * 1024 * 1024)
        r = subprocess.run([f"mkfs.{kind}", "-q", "-F", str(image)], capture_output=True, timeout=30)
        if r.returncode != 0:
            pytest.skip(f"mkfs.{kind} failed: {r.stderr.decode(errors='replace').strip()}")
        cmd = ["mount", "-o", "loop", str(image), str(mnt)]
    r = subprocess.run(cmd, capture_output=True, timeout=30)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a {kind} disk here: {r.stderr.decode(errors='replace').strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True, timeout=30)


def fill_disk(mnt: Path) -> subprocess.CompletedProcess:
    """Another process writes until the disk is full (``dd`` ends with "No space left on device")."""
    return subprocess.run(["dd", "if=/dev/zero", f"of={mnt / 'filler'}", "bs=256k"], capture_output=True,
                          text=True, timeout=60)


def start_record(*args: str) -> subprocess.Popen:
    """``tirdeflect record ARGS --no-progress`` from this checkout, as a real subprocess (own session)."""
    return subprocess.Popen([sys.executable, "-m", "app.cli", "record", *args, "--no-progress"], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)


def frames_written_line(stdout: str) -> int:
    """The count the summary prints on its "frames written" line."""
    m = re.search(r"frames written\s+(\d+)", stdout)
    assert m, f"no 'frames written' line in:\n{stdout}"
    return int(m.group(1))


class RecordProcess:
    """A real ``tirdeflect record`` subprocess whose progress bar (stderr) is read while it runs.

    :meth:`progress` is the largest "N/TOTAL" count the bar has shown so far
    (frames written; with --burst frames captured into RAM).
    """

    def __init__(self, *args: str):
        self.proc = subprocess.Popen([sys.executable, "-m", "app.cli", "record", *args], cwd=ROOT,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
        self._err = bytearray()
        self._out = bytearray()
        self._threads = [threading.Thread(target=self._pump, args=(self.proc.stderr, self._err), daemon=True),
                         threading.Thread(target=self._pump, args=(self.proc.stdout, self._out), daemon=True)]
        for t in self._threads:
            t.start()

    @staticmethod
    def _pump(stream, sink):
        while True:
            chunk = os.read(stream.fileno(), 4096)
            if not chunk:
                return
            sink.extend(chunk)

    def progress(self) -> int:
        counts = [int(m) for m in re.findall(rb"(\d+)/\d+ \[", bytes(self._err))]
        return max(counts, default=0)

    def wait(self, timeout_s: float):
        """(returncode, stdout, stderr) once the process ended; kills it and fails after ``timeout_s``."""
        try:
            self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(10)
            pytest.fail(f"tirdeflect record still running {timeout_s:g} s later (hang)")
        self._close_pipes()
        return self.proc.returncode, self._out.decode(errors="replace"), self._err.decode(errors="replace")

    def kill(self):
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)
        self._close_pipes()

    def _close_pipes(self):
        for t in self._threads:
            t.join(10)
        for stream in (self.proc.stdout, self.proc.stderr):
            if not stream.closed:
                stream.close()
