"""Small helpers that several test modules and tests/conftest.py share: whether a
process still runs, which of a process's children are its multiprocessing workers,
a machine-wide file lock with a bounded wait, how much of a file the page cache holds, and a user's
answers typed into the window's file dialogs."""

from __future__ import annotations

import fcntl
import time


def pid_alive(pid: int) -> bool:
    """Is ``pid`` running (not gone, not a zombie)?"""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            return f.read().rpartition(b")")[2].split()[0] != b"Z"
    except OSError:
        return False


#: what the command line of the app's fork server (app/worker_processes.py) and of the workers it forks holds
FORK_SERVER_COMMAND = "from multiprocessing.forkserver import main"


def worker_processes(process) -> list:
    """The multiprocessing workers a ``psutil.Process`` started and that still run: the children
    of its fork server (the app's way, app/worker_processes.py), or spawned children."""
    workers = []
    for child in process.children():
        command = " ".join(child.cmdline())
        if FORK_SERVER_COMMAND in command:
            workers += child.children()
        elif "spawn_main" in command:
            workers.append(child)
    return workers


def acquire_file_lock(path: str, timeout_s: float):
    """Open ``path`` and take an exclusive ``flock`` on it, waiting at most ``timeout_s``
    (a hang detector: another test, of this run or another run on this PC, holds it).

    Returns the open file, which holds the lock until :func:`release_file_lock`."""
    f = open(path, "w")
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return f
        except BlockingIOError:
            if time.monotonic() > deadline:
                f.close()
                raise RuntimeError(f"another test held {path} for {timeout_s:g} s; is a test hanging?") from None
            time.sleep(0.05)  # polling the lock, bounded by the deadline


def release_file_lock(f) -> None:
    """Give back a lock taken by :func:`acquire_file_lock` and close its file."""
    fcntl.flock(f, fcntl.LOCK_UN)
    f.close()


def resident_bytes(path) -> int:
    """How many bytes of ``path`` the page cache holds (whole pages; Linux ``mincore``)."""
    import ctypes
    import mmap
    import os

    import numpy as np

    size = os.path.getsize(path)
    pages = -(-size // mmap.PAGESIZE)
    with open(path, "rb") as f:
        mapping = mmap.mmap(f.fileno(), size, prot=mmap.PROT_READ)
    try:
        view = np.frombuffer(mapping, np.uint8)
        resident = np.zeros(pages, np.uint8)
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.mincore(ctypes.c_void_p(view.ctypes.data), ctypes.c_size_t(size),
                        resident.ctypes.data_as(ctypes.c_void_p)) != 0:
            raise OSError(ctypes.get_errno(), "mincore failed")
        del view
    finally:
        mapping.close()
    return int((resident & 1).sum()) * mmap.PAGESIZE


def answer_file_dialogs(qtbot, answers, seen_filters):
    """Fill each file dialog the window opens with the next path and accept it, as a user would
    (again on the next poll if the dialog is still open: a busy machine may not have taken it)."""
    from pathlib import Path

    from pyqtgraph.Qt import QtCore, QtWidgets

    answers = [Path(a) for a in answers]
    state = {"dlg": None}

    def poll():
        dlg = next((d for d in QtWidgets.QApplication.topLevelWidgets()
                    if isinstance(d, QtWidgets.QFileDialog) and d.isVisible()), None)
        if state["dlg"] is not None and dlg is not state["dlg"]:
            answers.pop(0)  # the dialog answered last time has closed
            state["dlg"] = None
        if dlg is not None and answers:
            if state["dlg"] is None:
                seen_filters.append(dlg.nameFilters())
            name_edit = dlg.findChild(QtWidgets.QLineEdit, "fileNameEdit")
            name_edit.setText(str(answers[0]))  # typed into the dialog's file name box, then Enter
            qtbot.keyClick(name_edit, QtCore.Qt.Key_Return)
            state["dlg"] = dlg
        if answers:
            QtCore.QTimer.singleShot(50, poll)

    QtCore.QTimer.singleShot(50, poll)


def stderr_until_signalled(proc, act, timeout_s: float = 120.0):
    """``(exit code, stderr text)`` of the subprocess ``proc`` (``stderr=PIPE``, text), whose stderr lines
    are read one by one and given to ``act(line)`` until it returns True (it has sent its signal; an
    ``act`` that only does something on the way returns False): then the rest is read and the process
    awaited. ``proc`` is killed after ``timeout_s`` (a hang detector far
    above need: a hung child must not hang the suite) and in any case before this returns."""
    import threading

    watchdog = threading.Timer(timeout_s, proc.kill)
    watchdog.start()
    lines = []
    try:
        for line in proc.stderr:
            lines.append(line)
            if act(line):
                break
        lines += proc.stderr.readlines()
        code = proc.wait(timeout=60)
    finally:
        watchdog.cancel()
        if proc.poll() is None:
            proc.kill()
        proc.stderr.close()
    return code, "".join(lines)
