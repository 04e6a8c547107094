"""Fixtures shared by the GUI tests of tests/app."""

import pytest


@pytest.fixture
def window(qtbot):
    from app.gui.window import MainWindow

    w = MainWindow(open_at_start=False, planner_effort="FFTW_ESTIMATE")
    # shut down before pytest-qt closes it: a test that fails while recording must not leave the window's
    # "Recording in progress: close anyway?" question open (modal: the run hung until the watchdog)
    qtbot.addWidget(w, before_close_func=lambda widget: widget.shutdown())
    w.show()
    yield w
    w.shutdown()
