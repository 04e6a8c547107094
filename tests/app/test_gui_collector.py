"""Cyclic garbage is finalized in the GUI thread while the window is open (app/gui/collector.py).

A Qt object finalized by the garbage collector in another thread can crash
the program: a running QTimer in a reference cycle, collected from a
background thread, ends in a segmentation fault (PySide6, offscreen). The
window's background threads (opening a camera, building a Reconstructor)
allocate enough to set the collector off there; with the window open they
must not.
"""

from __future__ import annotations

import gc
import threading

import pytest

pytestmark = pytest.mark.gui


def test_cyclic_garbage_is_finalized_in_the_gui_thread(qtbot, window):
    finalized_in = []
    kept = []  # the background thread's allocations stay alive: the counts stay past the thresholds

    class Cyclic:
        def __del__(self):
            finalized_in.append(threading.current_thread().name)

    def background():
        item = Cyclic()
        item.me = item  # only the cyclic collector can free it
        del item
        kept.append([[] for _ in range(100_000)])  # far past the youngest generation's threshold

    assert not gc.isenabled()
    thread = threading.Thread(target=background, name="test-background")
    thread.start()
    thread.join()
    assert finalized_in == [], "collected in the background thread"
    qtbot.waitUntil(lambda: len(finalized_in) > 0, timeout=10000)
    assert finalized_in == [threading.main_thread().name]
    assert window._collector.collections >= 1


def test_closing_the_last_window_gives_automatic_collection_back(qtbot):
    from app.gui.window import MainWindow

    assert gc.isenabled()
    first = MainWindow(open_at_start=False, planner_effort="FFTW_ESTIMATE")
    qtbot.addWidget(first)
    second = MainWindow(open_at_start=False, planner_effort="FFTW_ESTIMATE")
    qtbot.addWidget(second)
    assert not gc.isenabled()
    first.shutdown()
    assert not gc.isenabled(), "another window is still open"
    second.shutdown()
    assert gc.isenabled()
