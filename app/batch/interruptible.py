"""Run a long computation where a signal can end it.

CPython runs signal handlers in the main thread, between bytecodes: while the
main thread is inside one native call (``cv2.remap`` on a diverging
refinement was seen running for more than 10 minutes), Ctrl-C and SIGTERM
wait for it to return. :func:`call_interruptibly` runs the call in a daemon
thread instead and lets the main thread wait in short, interruptible steps:
a signal's handler runs within :data:`POLL_S` and its exception
(``KeyboardInterrupt``, which ``app.cli`` raises for SIGTERM and SIGHUP too)
propagates from here while the abandoned call finishes, or not, in the
background; the process can close its files and exit (a daemon thread does
not hold the interpreter at exit). Off the main thread (the GUI's export, a
Dask task) there is nothing to gain and the call runs in place.
"""

from __future__ import annotations

import threading

__all__ = ["call_interruptibly", "abandoned_calls", "POLL_S"]

#: Longest wait of the main thread between two chances to run a signal handler, s.
POLL_S = 0.1

_abandoned: list = []  # the `done` events of calls an interrupt left behind


def abandoned_calls() -> int:
    """How many calls an interrupt left running (still inside native code, say).

    ``app.cli`` ends the process at once (``os._exit``, after its files are
    closed) when this is not 0: the interpreter's teardown would compete with
    them for the CPU, and one that returns into a half torn-down interpreter
    can crash it.
    """
    return sum(1 for done in _abandoned if not done.is_set())


def call_interruptibly(fn, *args, **kwargs):
    """``fn(*args, **kwargs)``, computed in a daemon thread while the main thread waits.

    Returns what ``fn`` returns and raises what it raises (with its
    traceback); a signal handler that raises during the wait (Ctrl-C)
    raises here at once, and ``fn`` is abandoned: it must not be needed
    afterwards (the engine's Reconstructor is not used again after an
    interrupt).
    """
    if threading.current_thread() is not threading.main_thread():
        return fn(*args, **kwargs)
    done = threading.Event()
    box = {}

    def run():
        try:
            box["value"] = fn(*args, **kwargs)
        except BaseException as exc:  # handed to the caller below
            box["error"] = exc
        finally:
            done.set()

    worker = threading.Thread(target=run, name="tirdeflect-frame", daemon=True)
    # counted as left behind from before it starts: a signal may land anywhere from here on,
    # in start() too, and a call still in native code must never meet the interpreter's teardown
    _abandoned.append(done)
    worker.start()
    while not done.wait(POLL_S):  # a signal handler that raises (Ctrl-C, SIGTERM) leaves from here
        pass
    _abandoned.remove(done)
    if "error" in box:
        error = box.pop("error")
        try:
            raise error
        finally:
            del error
    return box.pop("value")
