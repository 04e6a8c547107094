"""Where the app's worker processes come from: one fork server per process, ready to reconstruct.

The window's live reconstruction process (:mod:`app.capture.live_process`) and the batch engine's
pool (:mod:`app.batch.parallel`) each need a fresh Python beside a program that runs Qt and
threads, where a plain ``fork`` is unsafe. They were spawned: a new interpreter that imports
NumPy, SciPy, pyFFTW, Numba, OpenCV and the processing chain and loads Numba's compiled kernels
before its first frame, about 1.2 s of CPU on a quiet 2-core PC (0.7 s of imports, 0.4 s for
Numba's first cached kernel), 2-3 s on a loaded one, again for every worker of every run and
export and for every restart of the live process.

:func:`context` gives multiprocessing's ``forkserver`` start method instead: the first worker
asked for starts one server process (a new interpreter, by exec, like spawn: nothing of the
asking process's threads or Qt state), which imports :data:`PRELOAD` once (that module also runs
one small reconstruction with one thread, so that Numba's kernels are loaded); every worker is
then forked from the server, ready in milliseconds, its modules' memory shared with the server.
The server ends once the process that started it and every worker forked for it have ended.

What differs for a worker, and how the callers deal with it:

* its parent is the server, not the process that asked for it, and the server lives as long as
  its workers: a worker that must end with its run watches the run's own process (the batch
  pool's initializer in :mod:`app.batch.parallel` is given its pid);
* its environment and working directory are the server's, as they were when the server started,
  not the asking process's of now: :func:`parent_state` is those, to hand to the worker, and
  :func:`adopt_parent_state` makes them the worker's (the batch pool's initializer does, so that
  the cache directory a run was given is the one its workers use, and relative paths mean the
  same in the workers as in the run).

On Linux only (where the app and its tests run every day): elsewhere :func:`context` is spawn's, as
before, and nothing of this applies (Windows has no fork server; on macOS a fork of a process that has
loaded Apple's frameworks, which NumPy's and OpenCV's wheels link there, can abort in the child).
"""

from __future__ import annotations

import multiprocessing
import os
import sys
from typing import NamedTuple

__all__ = ["PRELOAD", "ParentState", "adopt_parent_state", "context", "parent_state"]

#: What the fork server imports before it forks any worker: the reconstruction's modules and a
#: warm-up (:mod:`app.worker_preload`). A module that fails to import is skipped by the server;
#: the workers then import it themselves, as a spawned process did.
PRELOAD = ("app.worker_preload",)


def context():
    """The multiprocessing context the app's worker processes are started with (see the module docstring)."""
    if not sys.platform.startswith("linux") or "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(list(PRELOAD))  # used when the server starts; no effect once it runs
    return ctx


class ParentState(NamedTuple):
    """What a spawned worker got from the process that started it and a forked one must be handed."""

    environ: dict
    cwd: str


def parent_state() -> ParentState:
    """This process's environment and working directory now, for a worker to take over."""
    return ParentState(dict(os.environ), os.getcwd())


def adopt_parent_state(state: ParentState) -> None:
    """Make ``state`` (from :func:`parent_state` in the asking process) this worker's own."""
    if state.environ != os.environ:
        os.environ.clear()
        os.environ.update(state.environ)
    if state.cwd != os.getcwd():
        os.chdir(state.cwd)
