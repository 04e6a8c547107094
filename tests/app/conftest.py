"""Fixtures shared by the GUI tests of tests/app."""

import pytest


@pytest.fixture
def window(qtbot):
    from app.gui.window import MainWindow

    w = MainWindow(open_at_start=False, planner_effort="FFTW_ESTIMATE")
    qtbot.addWidget(w)
    w.show()
    yield w
    w.shutdown()
