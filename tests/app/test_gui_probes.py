"""Live probes on the synthetic tank: placed by a mouse click on the height map, their series
against the scene's true heights at that point; moved by dragging, removed by a right-click."""

from __future__ import annotations

import numpy as np
import pytest
from pyqtgraph.Qt import QtCore, QtGui, QtWidgets

from tests.app.test_gui_flow import _capture_reference_by_hand, _choose_scene_by_hand, _click_tab, _window

pytestmark = pytest.mark.gui


def _map_pos(w, x_mm, y_mm) -> QtCore.QPoint:
    """Widget pixel of the surface point (x_mm, y_mm) on the Live height map."""
    vb = w.height_view.plot.getViewBox()
    scene_pt = vb.mapViewToScene(QtCore.QPointF(x_mm, y_mm))
    return w.height_view.graphics.mapFromScene(scene_pt)


def _drag(widget, start: QtCore.QPoint, end: QtCore.QPoint, steps=8):
    """A real left-button drag: press, moves with the button held, release (QTest's mouseMove holds no button)."""
    def send(kind, pos, buttons):
        ev = QtGui.QMouseEvent(kind, QtCore.QPointF(pos), QtCore.QPointF(widget.mapToGlobal(pos)),
                               QtCore.Qt.LeftButton, buttons, QtCore.Qt.NoModifier)
        QtWidgets.QApplication.sendEvent(widget, ev)
        QtWidgets.QApplication.processEvents()

    send(QtCore.QEvent.MouseButtonPress, start, QtCore.Qt.LeftButton)
    for k in range(1, steps + 1):
        p = start + (end - start) * (k / steps)
        send(QtCore.QEvent.MouseMove, p, QtCore.Qt.LeftButton)
    send(QtCore.QEvent.MouseButtonRelease, end, QtCore.Qt.NoButton)


@pytest.mark.slow  # 10-17 s: started first (tests/conftest.py, "the longest first")
def test_probe_placed_by_click_follows_the_true_waves(qtbot):
    """Click the height map -> a probe there; its series = the waves' true height at that point.

    Tolerance: RMS of (probe - truth) over 20 drawn frames <= 1 % of the truth's range at the
    point (the issue asks 2 % of the range of batch probes). The live maps' error is 1.2 % of the
    waves' RMS (~0.4 um) over the field, ~5 nm, i.e. ~0.3 % of the ~1.5 um range a point sees;
    1 % leaves room for a point worse than the field's average (measured: 1.5 nm, 0.10 %). The
    per-frame height offset (pinned by the method in its reference region, not where the truth
    has mean zero) is removed from each frame over the whole map, as ``height_error`` does.
    """
    from processing.probe import probe_cell, sample_cell

    w = _window(qtbot)
    qtbot.waitUntil(lambda: w.first_frame_s is not None, timeout=20000)
    _capture_reference_by_hand(qtbot, w)
    _choose_scene_by_hand(qtbot, w, "travelling waves")
    qtbot.waitUntil(lambda: w.session.tank.scene == "waves", timeout=60000)
    _click_tab(qtbot, w, "Live")
    qtbot.waitUntil(lambda: w.last_drawn is not None and w.last_drawn.result is not None, timeout=20000)

    r = w.last_drawn.result
    x_mm = float(r.x_mm[0] + 0.3 * (r.x_mm[-1] - r.x_mm[0]))  # away from the profile line (middle row)
    y_mm = float(r.y_mm[0] + 0.27 * (r.y_mm[-1] - r.y_mm[0]))
    viewport = w.height_view.graphics.viewport()
    qtbot.mouseClick(viewport, QtCore.Qt.LeftButton, pos=_map_pos(w, x_mm, y_mm))
    assert len(w.probe_view.probes) == 1
    probe = w.probe_view.probes[0]
    pixel_mm = abs(float(r.x_mm[1] - r.x_mm[0]))  # the click lands within a screen pixel: < one grid step
    assert abs(probe.x_mm - x_mm) < pixel_mm and abs(probe.y_mm - y_mm) < abs(float(r.y_mm[1] - r.y_mm[0]))

    rows = {}

    def collect():
        p = w.last_drawn
        if p is None or p.result is None or p.seq in rows or not probe.seqs or probe.seqs[-1] != p.seq:
            return len(rows) >= 20
        fid = w.session.frame_id_of(p.seq)
        if fid is None or w.session.tank.scene_of(fid) != "waves":
            return False
        res = p.result
        ri = np.clip(np.round(res.rows_px).astype(int), 0, None)
        ci = np.clip(np.round(res.cols_px).astype(int), 0, None)
        truth_grid = w.session.tank.truth(fid)[np.ix_(ri, ci)].astype(np.float64)
        ok = res.valid & np.isfinite(res.height)
        offset_mm = float(np.mean(res.height[ok] - truth_grid[ok]))
        cell = probe_cell(res.x_mm, res.y_mm, probe.x_mm, probe.y_mm)
        shown_um = w.height_view.image.image
        rows[p.seq] = (probe.heights_um[-1], 1e3 * (sample_cell(truth_grid, cell) + offset_mm),
                       1e3 * sample_cell(res.height, cell), float(probe.times_s[-1]))
        assert shown_um is not None
        return len(rows) >= 20

    qtbot.waitUntil(collect, timeout=60000)
    probe_um, truth_um, result_um, t_s = (np.array(v) for v in zip(*rows.values()))
    np.testing.assert_array_equal(probe_um, result_um)  # the drawn Result, read by processing.probe's rule
    assert np.all(np.diff(t_s) > 0)
    span_um = float(np.ptp(truth_um))
    assert span_um > 0.2, "the waves move the surface at the probe"
    rms_um = float(np.sqrt(np.mean((probe_um - truth_um) ** 2)))
    print(f"probe vs truth: RMS {1e3 * rms_um:.1f} nm over a {1e3 * span_um:.0f} nm range "
          f"({100 * rms_um / span_um:.2f} %), {len(rows)} frames")
    assert rms_um <= 0.01 * span_um
    # the plot holds the series (newest point last), bounded history
    xs, ys = probe.curve.getData()
    assert len(xs) == len(probe.times_s) and ys[-1] == probe.heights_um[-1]

    # drag the gauge elsewhere: it measures there, its series starts again
    x2 = float(r.x_mm[0] + 0.7 * (r.x_mm[-1] - r.x_mm[0]))
    y2 = float(r.y_mm[0] + 0.75 * (r.y_mm[-1] - r.y_mm[0]))
    w.pause_box.setChecked(True)  # a still picture while the mouse moves
    _drag(viewport, _map_pos(w, probe.x_mm, probe.y_mm), _map_pos(w, x2, y2))
    assert len(w.probe_view.probes) == 1
    assert abs(probe.x_mm - x2) < 2 * pixel_mm and abs(probe.y_mm - y2) < 2 * pixel_mm
    assert len(probe.times_s) == 0
    w.pause_box.setChecked(False)
    qtbot.waitUntil(lambda: len(probe.times_s) >= 2, timeout=20000)

    # right-click removes it (and its curve)
    w.pause_box.setChecked(True)
    qtbot.mouseClick(viewport, QtCore.Qt.RightButton, pos=_map_pos(w, probe.x_mm, probe.y_mm))
    assert w.probe_view.probes == []
    assert probe.curve not in w.probe_view.plot.getPlotItem().items


def test_probe_names_are_in_the_title_not_in_a_box_over_the_series(qtbot):
    """The probes' legend sat in the plot's corner over the series (seen at 1280x800); their names
    now stand in the title in their curves' colours, follow adds and removals, and the time axis'
    last tick label has room to be drawn whole."""
    import pyqtgraph as pg

    from app.gui.probes import ProbeView

    map_plot = pg.PlotWidget()
    qtbot.addWidget(map_plot)
    view = ProbeView(map_plot.getPlotItem())
    qtbot.addWidget(view)
    view.resize(330, 200)
    view.show()
    title = lambda: view.plot.getPlotItem().titleLabel.text  # noqa: E731
    assert "(click the map)" in title()
    p1, p2 = view.add(1.0, 2.0), view.add(3.0, 4.0)
    assert view.plot.getPlotItem().legend is None
    assert f"color:{p1.colour}'>&#9472; P1" in title() and f"color:{p2.colour}'>&#9472; P2" in title()
    view.set_stale("frame 3, 2.0 s ago")
    assert "STALE" in title() and "P2" in title()
    view.remove(p1)
    view.set_stale(None)
    assert "P1" not in title() and "P2" in title() and "STALE" not in title()
    axis = view.plot.getAxis("bottom")
    half_label_px = QtGui.QFontMetrics(axis.style.get("tickFont") or axis.font()).horizontalAdvance("40") / 2
    assert view.plot.getPlotItem().layout.getContentsMargins()[2] >= half_label_px
