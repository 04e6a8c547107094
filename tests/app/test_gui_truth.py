"""Issue 20 through the widgets: the live window refuses states that make heights wrong, and says why.

pytest-qt, offscreen, the synthetic tank (ray-traced frames, app/capture/scene.py) at 256^2 so that
the moving scenes are ray-traced in seconds. Each test starts from a clean settings directory.
"""

from __future__ import annotations

import numpy as np
import pytest
from pyqtgraph.Qt import QtCore, QtTest

from tests.app.test_gui_flow import _choose_scene_by_hand

pytestmark = pytest.mark.gui

SHAPE = (256, 256)


def _window(qtbot, **kw):
    from app.gui.window import MainWindow

    w = MainWindow("synthetic", synthetic_options={"shape": SHAPE, "n_frames": 12, "frame_rate_hz": 30.0},
                   planner_effort="FFTW_ESTIMATE", **kw)
    qtbot.addWidget(w)
    w.resize(1600, 1000)
    w.show()
    qtbot.waitUntil(lambda: w.first_frame_s is not None, timeout=20000)
    w.activateWindow()
    qtbot.waitUntil(w.isActiveWindow, timeout=3000)  # keys go to the active window
    return w


def _ctrl(w, key):
    QtTest.QTest.keyClick(w, key, QtCore.Qt.ControlModifier)


def test_reference_on_moving_water_is_refused_and_still_water_accepted(qtbot):
    """Finding 1: Ctrl+R on the waves says "the water is moving" with the figure, keeps no reference, no tick."""
    w = _window(qtbot)
    w.geometry_panel.n_average.setValue(5)
    _choose_scene_by_hand(qtbot, w, "travelling waves")
    qtbot.waitUntil(lambda: w.session.tank.scene == "waves", timeout=60000)
    w.activateWindow()
    qtbot.waitUntil(w.isActiveWindow, timeout=3000)
    before = w.reference
    _ctrl(w, QtCore.Qt.Key_R)
    qtbot.waitUntil(lambda: w.last_error is not None and not w.busy("reference"), timeout=30000)
    assert "the water is moving: wait and capture again" in w.last_error, w.last_error
    figure = float(w.last_error.split("(frame ")[1].split(": ")[1].split(" rad")[0])
    assert figure > 0.2  # waves move the carrier phase by about a radian from frame to frame
    label = w.geometry_panel.reference_label.text()
    assert "REFUSED" in label and "✓" not in label
    assert w.reference is before  # nothing replaced, nothing half-built
    # still water: accepted, with how well its frames agreed
    _choose_scene_by_hand(qtbot, w, "still water")
    qtbot.waitUntil(lambda: w.session.tank.scene == "still", timeout=10000)
    w.activateWindow()
    qtbot.waitUntil(w.isActiveWindow, timeout=3000)
    w.clear_error()
    _ctrl(w, QtCore.Qt.Key_R)
    qtbot.waitUntil(lambda: "✓" in w.geometry_panel.reference_label.text(), timeout=30000)
    assert w.last_error is None
    assert "5 of 5 frames averaged" in w.geometry_panel.reference_label.text()
