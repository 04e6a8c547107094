"""The Replay tab on recordings that are not whole: frames lost on the way (camera frame-id gaps), a
recording stopped before its trigger, and a file opened after another; stepping frames faster than they
are measured. Driven through File ▸ Open and the keyboard (pytest-qt, offscreen), files written by the
window's recorder and by ``tirdeflect record``."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import tifffile
from pyqtgraph.Qt import QtCore, QtWidgets

from drivers.synthetic import SyntheticCamera
from tests.app.test_gui import (  # noqa: F401 - the module's fixture
    Switchable, _wait_reconstructor, arm_and_trigger, scene)
from tests.helpers import answer_file_dialogs

pytestmark = pytest.mark.gui

ROOT = Path(__file__).resolve().parents[2]


def _open_by_menu(qtbot, w, path):
    answer_file_dialogs(qtbot, [path], [])
    w.actions_by_name["open_recording"].trigger()
    assert w.replay_recording is not None and w.replay_recording.path == str(path), w.last_error


def _record_with_lost_frames(qtbot, w, scene, folder, lost):
    """Arm, trigger: 10 frames before the trigger, 20 from it; the camera never delivers ids ``lost``."""
    frames = Switchable(scene["flat"])
    w.use_camera(SyntheticCamera(frames, frame_rate_hz=50.0, n_buffers=64, drop_frames=lost),
                 geometry=scene["geometry"], reference=scene["flat"])
    _wait_reconstructor(qtbot, w)
    # armed from camera frame 35 on at the earliest, so that a recording of a reconstructor built at once (the
    # FFTW plans known) still reaches the ids lost from 40 on: armed at frame 5, it ended at frame 37, no gap
    ring = w.session.acquisition.ring
    qtbot.waitUntil(lambda: ring.head >= 35, timeout=20000)
    arm_and_trigger(qtbot, w, frames, scene["bump"], folder, 10, 20, settle=12, settle_ms=20000, end_ms=30000)
    return w.session.recording["path"]


def test_frames_lost_in_a_recording_are_said_and_each_frame_has_its_time_from_the_trigger(qtbot, window, scene,
                                                                                            tmp_path):
    """Camera ids lost after the trigger: the Replay tab names the loss, the frame after each gap says it,
    and every frame's time from the trigger is the camera's (the trigger index counts recorded frames only)."""
    # every 7th id from 40 on, however long the reconstructor takes to build on a loaded machine (ids up to
    # 400 only: a build past 8 s at 50 Hz left the recording without a gap) or how soon it is done
    path = _record_with_lost_frames(qtbot, window, scene, tmp_path, lost=range(40, 100_000, 7))
    with h5py.File(path, "r") as f:
        table = f["frame_table"][: int(f.attrs["frames_written"])]
    ids = table["frame_id"]
    gaps = np.flatnonzero(np.diff(ids) > 1) + 1  # recorded frames that come after lost ones
    assert gaps.size >= 1
    trigger_id = ids[list(table["trigger_index"]).index(0)]
    _open_by_menu(qtbot, window, path)
    assert "LOST" in window.replay.file_label.text() and "LOST" in window.replay.message.text()
    slider = window.replay.slider
    slider.setFocus()
    for k in range(1, int(gaps[0]) + 1):  # the arrow key, frame by frame, to the first frame after a gap
        qtbot.keyClick(slider, QtCore.Qt.Key_Right)
        assert slider.value() == k
        label = window.replay.index_label.text()
        t_ms = 1e3 * (ids[k] - trigger_id) / 50.0
        assert f"t = {t_ms:+.4f} ms from the trigger" in label, label
        assert ("LOST before it" in label) == (k in gaps), label


def test_frames_stepped_faster_than_measured_and_another_file_never_show_heights_of_another_frame(
        qtbot, window, scene, tmp_path):
    """Holding the arrow key: each frame on the slider has its own heights, or the map says whose it shows.
    Then a camera file without reference: no height map of the recording opened before beside its frames."""
    path = _record_with_lost_frames(qtbot, window, scene, tmp_path, lost=())
    _open_by_menu(qtbot, window, path)
    qtbot.waitUntil(lambda: window.replay_shown_index == 0, timeout=30000)
    slider, height = window.replay.slider, window.replay.height
    slider.setFocus()
    for k in range(1, 12):
        qtbot.keyClick(slider, QtCore.Qt.Key_Right)
        shown = window.replay_shown_index
        if shown == slider.value():
            assert height.stale_text is None
        else:
            assert height.stale_text == f"heights of frame {shown + 1}; frame {k + 1} is being measured"
    qtbot.waitUntil(lambda: window.replay_shown_index == 11 and height.stale_text is None, timeout=30000)
    assert height.image.image is not None

    window.reference = None  # a window without reference (the camera file brings none)
    window.geometry = None
    tifffile.imwrite(tmp_path / "cam.tif", np.stack([scene["flat"], scene["bump"]]), photometric="minisblack")
    _open_by_menu(qtbot, window, tmp_path / "cam.tif")
    assert window.replay.index_label.text() == "frame 1/2"
    assert "raw frames only" in window.replay.message.text()
    assert height.image.image is None and height.stale_text is None  # the first recording's heights are gone


def test_the_frame_the_slider_rests_on_shows_the_exported_heights_on_every_pixel(qtbot, window, scene, tmp_path):
    """The Replay tab measured only the live (decimated) grid: a physicist reading heights off it read values
    1.7-2.4 % RMS away from the export's and `process`'s of the same frame, with nothing saying the map was
    coarser (7 Dec 2026). Now the live grid comes first and says so in the map's title; once the slider rests
    on the frame, its heights on every pixel replace it, those of the scripting interface and the export."""
    from processing import Geometry, Reconstructor

    path = _record_with_lost_frames(qtbot, window, scene, tmp_path, lost=())
    _open_by_menu(qtbot, window, path)
    height = window.replay.height
    slider = window.replay.slider
    slider.setFocus()
    for _ in range(3):  # stepped on: each frame first on the live grid
        qtbot.keyClick(slider, QtCore.Qt.Key_Right)
    qtbot.waitUntil(lambda: window.replay_shown_index == 3, timeout=30000)
    with h5py.File(path, "r") as f:
        frame, reference = f["frames"][3], f["reference"][()]
        geometry = Geometry.from_toml_text(f["geometry_toml"][()].decode())
    qtbot.waitUntil(lambda: window.replay_last_result.grid == "full", timeout=60000)
    assert window.replay_shown_index == 3 and "every pixel" in height.plot.titleLabel.text
    expected = Reconstructor(reference, geometry)(frame)
    shown_um = height.image.image
    assert shown_um.shape == frame.shape
    both = np.isfinite(shown_um) & np.isfinite(expected.height)
    assert both.mean() > 0.9
    np.testing.assert_allclose(shown_um[both], 1e3 * expected.height[both], atol=1e-4)  # um: 0.1 nm
    qtbot.keyClick(slider, QtCore.Qt.Key_Right)  # moving on: the live grid again, titled as such
    qtbot.waitUntil(lambda: window.replay_shown_index == 4, timeout=30000)
    assert window.replay_last_result.grid == "decimated" and "live grid" in height.plot.titleLabel.text


def _record_stopped_before_its_trigger(tmp_path):
    """``tirdeflect record`` with an auto trigger whose run ended before the trigger (its reference is of
    another board): ``(path, frames written)``."""
    sim = tmp_path / "sim"
    cli = [sys.executable, "-m", "app.cli"]
    subprocess.run(cli + ["simulate", "--out", sim, "--size", "128", "--frames", "1"], check=True, cwd=ROOT,
                   capture_output=True, timeout=300)
    out = tmp_path / "pre.h5"
    done = subprocess.run(cli + ["record", "--camera", "synthetic", "--out", out, "--pre", "6", "--post", "10",
                                 "--trigger", "auto", "--threshold", "1000", "--region", "10,100,10,100",
                                 "--trigger-timeout-s", "3", "--synthetic-size", "128", "--synthetic-frames", "2",
                                 "--no-progress", "--geometry", sim / "geometry.toml",
                                 "--reference", sim / "reference.png"], cwd=ROOT, capture_output=True, text=True,
                          timeout=300)
    with h5py.File(out, "r") as f:
        n = int(f.attrs["frames_written"])
        assert n >= 1 and max(f["frame_table"]["trigger_index"][:n]) < 0, done.stderr
    return out, n


def test_a_recording_stopped_before_its_trigger_says_so_on_the_replay_tab(qtbot, window, tmp_path):
    """``tirdeflect record`` with an auto trigger whose run ended before the trigger (here: its reference
    is of another board): the file holds only pre-trigger frames; the Replay tab says it, in red."""
    out, n = _record_stopped_before_its_trigger(tmp_path)
    _open_by_menu(qtbot, window, out)
    assert "stopped BEFORE the trigger" in window.replay.file_label.text()
    message = window.replay.message.text()
    assert f"only the {n} frame(s) before it, no trigger frame" in message and "INCOMPLETE recording: " in message
    assert "color: #b00000" in window.replay.message.styleSheet()
    window.replay.slider.setFocus()
    qtbot.keyClick(window.replay.slider, QtCore.Qt.Key_End)
    assert window.replay.index_label.text().startswith(f"frame {n}/{n}  (trigger -1)")


def _unread_px(message) -> int:
    """Pixels of the Replay tab's message that can be neither seen nor scrolled to: its wrapped text's height
    at its width, less what is shown (not hidden by the window's edge) and what its scroll bar reaches."""
    label = message.widget() if isinstance(message, QtWidgets.QScrollArea) else message
    needed = label.heightForWidth(label.width())
    shown = label.visibleRegion().boundingRect().height()
    bar = message.verticalScrollBar() if isinstance(message, QtWidgets.QScrollArea) else None
    scrolled = bar.maximum() - bar.value() if bar is not None and bar.isVisible() else 0
    return max(needed - shown - scrolled, 0)


def test_the_whole_message_can_be_read_at_the_smallest_window(qtbot, window, tmp_path):
    """At the window's smallest size (its layout's minimum, 1002 x 423 px offscreen) a recording stopped before
    its trigger, whose run ended with a long error and whose frames cannot be measured: the message under the
    slider (the file's notes, and why the frame could not be measured) takes at most 4 lines of the maps'
    room and scrolls beyond; the height map says why in a few words that fit it, the whole sentence in its
    tooltip. Before, the message took 8 lines from the maps, and the map's own message (the whole sentence
    over a map 110 px tall) was cut at half the map, its tooltip on a label the mouse passes through."""
    out, n = _record_stopped_before_its_trigger(tmp_path)
    window.resize(1, 1)
    qtbot.waitUntil(lambda: window.size() == window.minimumSize(), timeout=3000)
    _open_by_menu(qtbot, window, out)
    height = window.replay.height
    qtbot.waitUntil(lambda: height.message.text() != "", timeout=30000)  # the first frame could not be measured
    qtbot.wait(50)
    assert window.size() == window.minimumSize(), (window.size(), window.minimumSize())
    overlay = height.message
    assert overlay.heightForWidth(overlay.width()) <= overlay.height(), (
        f"the height map's message is cut: needs {overlay.heightForWidth(overlay.width())} px, shown "
        f"{overlay.height()}: {overlay.text()!r}")
    error = height.graphics.toolTip()  # the whole sentence, where the mouse can show it
    assert error.startswith(overlay.text().split(" (")[0]) and len(error) > len(overlay.text()), (error, overlay.text())
    message = window.replay.message
    text = message.text()
    assert "stopped BEFORE the trigger" in text and "INCOMPLETE recording: " in text
    assert f"frame 1 could not be measured: {error}" in text, text
    label = message.widget() if isinstance(message, QtWidgets.QScrollArea) else message
    line = label.fontMetrics().lineSpacing()
    assert message.height() <= 4 * line + 2, f"the message takes {message.height()} px of the maps' room"
    assert message.visibleRegion().boundingRect().height() == message.height()  # inside the window
    assert _unread_px(message) == 0, f"{_unread_px(message)} px of the message can neither be seen nor scrolled to"
    message.verticalScrollBar().setValue(message.verticalScrollBar().maximum())  # scrolled to its end
    assert label.visibleRegion().boundingRect().bottom() == label.height() - 1
    assert message.toolTip() == text


def test_exported_heights_are_measured_with_the_reference_the_replay_shows_them_with(qtbot, window, scene,
                                                                                      tmp_path):
    """A camera file without reference, measured with the window's; the user then takes another reference
    (here: the live frame of the bump) and exports: the file holds the heights the Replay tab showed."""
    window.use_camera(SyntheticCamera(Switchable(scene["flat"]), frame_rate_hz=20.0), geometry=scene["geometry"],
                      reference=scene["flat"])
    _wait_reconstructor(qtbot, window)
    tifffile.imwrite(tmp_path / "cam.tif", np.stack([scene["bump"], scene["bump"]]), photometric="minisblack")
    _open_by_menu(qtbot, window, tmp_path / "cam.tif")
    qtbot.waitUntil(lambda: window.replay_shown_index == 0, timeout=30000)
    shown_max_um = float(np.nanmax(window.replay.height.image.image))
    assert shown_max_um == pytest.approx(1e3 * scene["truth_mm"].max(), rel=0.2)
    window.reference = scene["bump"]  # a newer reference in the window (Ctrl+R on the bump)
    out = tmp_path / "heights.h5"
    window.export_heights(str(out))
    qtbot.waitUntil(lambda: window.export_result is not None, timeout=120000)
    assert window.export_result == ("done", str(out)), window.export_result
    with h5py.File(out, "r") as f:
        exported_max_um = 1e3 * float(np.nanmax(f["height"][0]))
    assert exported_max_um == pytest.approx(shown_max_um, rel=0.1)
