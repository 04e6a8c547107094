"""Python's cyclic garbage collected in the GUI thread only, while a window is open.

CPython runs its cyclic collector in whichever thread happens to allocate
past a threshold. In the live window that is often a background thread
(opening a camera, building a Reconstructor: a first import of SciPy or
OpenPIV allocates hundreds of thousands of objects), and the collector
then runs the finalizers of whatever cyclic garbage is waiting: Qt
wrappers of closed dialogs and views, Aravis (GObject) handles. Qt objects
must be destroyed in the thread they live in; finalized elsewhere they can
crash or wait forever on a lock the GUI thread holds while it waits for
the GIL. (Test runs of the window froze with every thread waiting while a
background thread imported OpenPIV; pyqtgraph documents the same hazard
for its GarbageCollector.)

So while a window is open, automatic collection is off and a timer in the
GUI thread collects each generation when its count passes the threshold
the interpreter had, as automatic collection would, only in the right
thread. The last window to close switches automatic collection back on.
"""

from __future__ import annotations

import gc
import threading

from pyqtgraph.Qt import QtCore

__all__ = ["GuiThreadCollector"]

#: How often the GUI thread looks at the collector's counts (ms).
CHECK_INTERVAL_MS = 500

_lock = threading.Lock()
_holders = 0  # collectors alive (windows open)
_was_enabled = True


class GuiThreadCollector:
    """Collect cyclic garbage from the GUI thread (create and :meth:`stop` it there)."""

    def __init__(self, parent: QtCore.QObject, interval_ms: int = CHECK_INTERVAL_MS):
        global _holders, _was_enabled
        with _lock:
            if _holders == 0:
                _was_enabled = gc.isenabled()
                gc.disable()
            _holders += 1
        self.thresholds = gc.get_threshold()
        self.collections = 0
        self._stopped = False
        self._timer = QtCore.QTimer(parent)
        self._timer.setInterval(int(interval_ms))
        self._timer.timeout.connect(self.check)
        self._timer.start()

    def check(self) -> int:
        """Collect the generations whose counts passed their thresholds; the oldest collected, or -1."""
        counts = gc.get_count()
        oldest = -1
        for generation, (count, threshold) in enumerate(zip(counts, self.thresholds)):
            if threshold <= 0 or count <= threshold:
                break
            oldest = generation
        if oldest >= 0:
            gc.collect(oldest)
            self.collections += 1
        return oldest

    def stop(self) -> None:
        """Stop the timer; the last collector stopped gives automatic collection back."""
        global _holders
        if self._stopped:
            return
        self._stopped = True
        self._timer.stop()
        with _lock:
            _holders -= 1
            if _holders == 0:
                gc.collect()  # what waited, finalized here, in the GUI thread
                if _was_enabled:
                    gc.enable()
