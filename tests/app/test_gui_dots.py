"""Aligning a random-dot set-up through the widgets (pytest-qt, offscreen).

The world: a TIR tank (theta 55 deg, H 300 mm, 0.1 mm/px, telecentric: the
geometry editor's defaults) whose pattern plane holds random Gaussian dots
(processing.forward.RandomDots), ray-traced on still water and streamed by a
SyntheticCamera with fresh camera noise per frame.  The user picks "random
dots" in the geometry editor and opens the Alignment tab; nothing about the
geometry is set in code.  Truth: a dot's FWHM is 0.5887 of its 1/e^2
diameter, seen cos(theta) shorter along the image rows.
"""

from __future__ import annotations

import re
import tomllib

import numpy as np
import pytest
from pyqtgraph.Qt import QtCore

from .test_gui_flow import _click_tab, _open_section

pytestmark = pytest.mark.gui

SHAPE = (256, 256)
PIXEL_MM = 0.1
THETA_DEG = 55.0
FWHM_PER_DIAMETER = 2.0 * np.sqrt(2.0 * np.log(2.0)) / 4.0  # 1/e^2 diameter = 4 sigma


def _dot_frames(dot_diameter_mm, density, *, blur_px=0.0, n=4):
    """Still water seen through the editor's default geometry: ``n`` 8-bit frames, 1 DN noise."""
    from scipy import ndimage

    from processing import forward as F
    from processing.geometry import Geometry

    world = Geometry(theta_deg=THETA_DEG, depth_mm=300.0, pixel_mm=PIXEL_MM, rows_toward_camera=False)
    img, _ = F.render_tir(F.FlatSurface(), world, SHAPE, F.RandomDots(dot_diameter_mm, density, seed=3),
                          supersample=2)
    if blur_px:  # a defocused lens
        img = ndimage.gaussian_filter(img, blur_px)
    rng = np.random.default_rng(7)
    return np.stack([F.quantize(img, bits=8, noise_rms=1.0, rng=rng) for _ in range(n)])


def _pick_random_dots(qtbot, w):
    """Controls ▸ Reference & geometry ▸ Pattern: "random dots", by keyboard."""
    _open_section(qtbot, w, "Reference & geometry")
    box = w.geometry_panel.pattern
    target = box.findText("random dots")
    assert target >= 0
    box.setFocus()
    while box.currentIndex() != target:
        qtbot.keyClick(box, QtCore.Qt.Key_Down if box.currentIndex() < target else QtCore.Qt.Key_Up)
    qtbot.waitUntil(lambda: getattr(w.geometry, "pattern", None) == "dots", timeout=5000)


def _shown_dots(w):
    """(dot size (vertical, horizontal) px, dots per window) as the Alignment tab shows them."""
    m = w.alignment_metrics
    size = [float(v) for v in re.match(r"([\d.]+) × ([\d.]+) px", m["dot size (FWHM)"]).groups()]
    per_window = float(m["dots per window"].split()[0])
    return np.array(size), per_window


def _dot_metrics_shown(w, reference=False):
    m = getattr(w, "alignment_metrics", None) or {}
    return "dot size (FWHM)" in m and (not reference or "reference" in m["dot size (FWHM)"])


def test_random_dots_alignment_by_hand_ready_and_measured(qtbot, window, tmp_path):
    """Dots of 0.65 mm (2.2 x 3.8 px), density 0.6: the tab shows their size within 0.5 px, ~6 per window, READY."""
    from drivers.synthetic import SyntheticCamera

    diameter_mm, density = 0.65, 0.6
    window.use_camera(SyntheticCamera(_dot_frames(diameter_mm, density), frame_rate_hz=20.0), camera_id="dot-tank")
    _pick_random_dots(qtbot, window)
    _click_tab(qtbot, window, "Alignment")
    qtbot.waitUntil(lambda: _dot_metrics_shown(window), timeout=20000)

    fwhm_px = FWHM_PER_DIAMETER * diameter_mm / PIXEL_MM
    truth = np.array([fwhm_px * np.cos(np.radians(THETA_DEG)), fwhm_px])  # 2.20, 3.83 px
    size, per_window = _shown_dots(window)
    assert np.all(np.abs(size - truth) < 0.5), f"shown {size} px, rendered {np.round(truth, 2)} px"
    # one dot per jittered cell (0.84 mm, i.e. 8.4 x 4.8 px): 6.3 per 16 x 16 px window; merging ones count once
    cell_px = diameter_mm / np.sqrt(density) / PIXEL_MM
    expected = 16 * 16 / (cell_px**2 * np.cos(np.radians(THETA_DEG)))
    assert abs(per_window - expected) < 0.25 * expected, (per_window, expected)
    assert window.alignment_ready and window.ready_label.text() == "READY TO MEASURE"
    assert window.alignment_metrics["pattern"] == "random dots (PIV)"
    assert float(window.alignment_metrics["contrast"]) > 0.6  # dots 0.1 -> 0.9 of full scale

    # the reference: the worker's Reconstructor (PIV) now gives the numbers, with the reference's beside them
    qtbot.mouseClick(window.geometry_panel.capture_button, QtCore.Qt.LeftButton)
    qtbot.waitUntil(lambda: window.session.worker.reconstructor is not None and not window.busy("reconstructor"),
                    timeout=30000)
    assert window.session.worker.reconstructor.pattern == "dots"
    qtbot.waitUntil(lambda: _dot_metrics_shown(window, reference=True), timeout=20000)
    size_ref, _ = _shown_dots(window)
    assert np.all(np.abs(size_ref - truth) < 0.5) and window.alignment_ready

    # the choice is part of the geometry: saved in its TOML and remembered with the camera
    path = tmp_path / "geometry.toml"
    window.save_geometry(str(path))
    assert tomllib.loads(path.read_text())["pattern"] == "dots"
    experiment = window.save_experiment(str(tmp_path / "dots-tank.toml"))
    with open(experiment, "rb") as f:  # closed: with the live PIV in the worker process, OpenPIV's
        # global warnings.filterwarnings("ignore") no longer hides an unclosed file in this process
        assert tomllib.load(f)["geometry"]["pattern"] == "dots"
    frames = _dot_frames(diameter_mm, density, n=2)
    window.close()

    from app.gui.window import MainWindow

    # the next start with this camera: the editor shows random dots again
    w2 = MainWindow(open_at_start=False, planner_effort="FFTW_ESTIMATE")
    qtbot.addWidget(w2)
    w2.use_camera(SyntheticCamera(frames, frame_rate_hz=20.0), camera_id="dot-tank")
    assert w2.geometry.pattern == "dots" and w2.geometry_panel.pattern.currentText() == "random dots"
    w2.shutdown()
    # a fresh window (another settings directory's worth of nothing): the experiment file brings the dots
    w3 = MainWindow(open_at_start=False, planner_effort="FFTW_ESTIMATE")
    qtbot.addWidget(w3)
    assert w3.geometry_panel.pattern.currentText() == "checkerboard"
    assert w3.open_experiment(str(experiment))
    assert w3.geometry.pattern == "dots" and w3.geometry_panel.pattern.currentText() == "random dots"
    w3.shutdown()


@pytest.mark.parametrize("case, diameter_mm, density, blur_px, reason", [
    ("small", 0.3, 0.3, 0.0, "below 2 px: peak locking"),  # 1.0 x 1.8 px dots
    ("blurred", 0.65, 0.6, 2.5, "out of focus"),  # the same dots as above through a defocused lens
])
def test_random_dots_alignment_not_ready_says_why(qtbot, window, case, diameter_mm, density, blur_px, reason):
    from drivers.synthetic import SyntheticCamera

    frames = _dot_frames(diameter_mm, density, blur_px=blur_px)
    window.use_camera(SyntheticCamera(frames, frame_rate_hz=20.0), camera_id="dot-tank")
    _pick_random_dots(qtbot, window)
    _click_tab(qtbot, window, "Alignment")
    qtbot.waitUntil(lambda: _dot_metrics_shown(window), timeout=20000)
    assert not window.alignment_ready
    text = window.ready_label.text()
    assert text.startswith("NOT READY") and reason in text, text
    size, _ = _shown_dots(window)
    if case == "small":  # the size shown is still the dots' own
        fwhm_px = FWHM_PER_DIAMETER * diameter_mm / PIXEL_MM
        truth = np.array([fwhm_px * np.cos(np.radians(THETA_DEG)), fwhm_px])
        assert np.all(np.abs(size - truth) < 0.5), (size, truth)
        assert "vertically" in text and "horizontally" in text
    else:
        assert float(window.alignment_metrics["focus (1 − autocorrelation at 1 px)"]) < 0.08
