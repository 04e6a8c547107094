"""Replay's File ▸ Open on camera files and videos, and File ▸ Export movie, through the menu and
its file dialogs (pytest-qt, offscreen). The files are written by their own libraries (pyMRAW,
PyAV), as in tests/app/test_formats.py."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pyqtgraph.Qt import QtCore, QtWidgets

from app.gui.views import decimate_for_display
from tests.helpers import answer_file_dialogs
from tests.app.test_formats import write_mraw, write_video

pytestmark = pytest.mark.gui
av = pytest.importorskip("av")

ROOT = Path(__file__).resolve().parents[2]


def _frames(n=4, shape=(48, 64), hi=4096):
    rng = np.random.default_rng(3)
    return [rng.integers(0, hi, shape).astype(np.uint16) for _ in range(n)]


@pytest.mark.parametrize("kind", ["mraw", "ffv1", "cine"])
def test_file_open_lists_and_opens_camera_files_and_video(qtbot, window, tmp_path, kind):
    """File ▸ Open recording: the dialog offers Photron/Phantom/video, accepting a file shows its
    frames, each with its time from the file."""
    from app.files import imageio

    frames = _frames()
    if kind == "mraw":
        path = write_mraw(tmp_path / "rec.cih", frames, bits=16, fps=5000)
    elif kind == "ffv1":
        path = write_video(tmp_path / "rec.avi", frames, codec="ffv1", pix_fmt="gray16le")
    else:  # a real monochrome Phantom file (tests/app/data/cine/README.md)
        pytest.importorskip("pims")
        path = ROOT / "tests" / "app" / "data" / "cine" / "cine_781.cine"
        frames = [item.image for item in imageio.iter_frames([path], last=3)]
    times_s = [item.time_s for item in imageio.iter_frames([path], last=3)]
    filters = []
    answer_file_dialogs(qtbot, [path], filters)
    window.actions_by_name["open_recording"].trigger()
    assert filters and any("*.mraw" in f and "*.avi" in f and "*.cine" in f for f in filters[0])
    assert window.replay_recording is not None and window.replay_recording.path == str(path)
    assert window.tabs.currentWidget() is window.replay
    assert window.replay.slider.maximum() == imageio.frame_count(path) - 1
    for k in (0, 3, 1):  # forward and back: lossless files read exactly
        window.replay.slider.setValue(k)
        shown = window.replay.raw.image.image  # as the view draws the frame (averaged blocks when smaller)
        np.testing.assert_array_equal(np.asarray(shown), decimate_for_display(frames[k], window.replay.raw.stride)[0])
        label = window.replay.index_label.text()
        assert label.startswith(f"frame {k + 1}/") and f"t = {times_s[k] * 1e3:+.4f} ms" in label, label
    # a camera file holds neither reference nor geometry, and this window has none yet:
    # raw frames only, and the user is told where to get heights
    text = window.replay.message.text()
    assert "no reference (still water) and no geometry" in text and "Controls ▸ Reference & geometry" in text


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "app.cli", *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, timeout=600)


def test_export_movie_from_the_file_menu(qtbot, window, tmp_path):
    """File ▸ Export movie on a processed OUT.h5: app.batch.movie writes it in the background,
    progress in the status bar; PyAV reads back every frame at the reported size."""
    sim = tmp_path / "sim"
    n = 5
    r = _cli("simulate", "--out", sim, "--surface", "dimple", "--size", "128", "--frames", n, "--bits", "12")
    assert r.returncode == 0, r.stderr
    out_h5 = tmp_path / "out.h5"
    r = _cli("process", sim / "reference.tif", *[sim / f"frame_{k:04d}.tif" for k in range(n)],
             "--geometry", sim / "geometry.toml", "--out", out_h5, "--no-progress")
    assert r.returncode == 0, r.stderr
    movie = tmp_path / "heights.mp4"
    messages = []
    window.statusBar().messageChanged.connect(messages.append)
    answer_file_dialogs(qtbot, [out_h5, movie], [])
    window.actions_by_name["export_movie"].trigger()
    qtbot.waitUntil(lambda: getattr(window, "movie_result", None) is not None, timeout=60000)
    state, report = window.movie_result
    assert state == "done", report
    assert any(m.startswith("movie: ") and "out.h5 → heights.mp4" in m for m in messages)  # progress
    assert any(m.startswith("movie written") for m in messages)
    with av.open(str(movie)) as container:
        decoded = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    assert len(decoded) == n == report.frames
    assert decoded[0].shape == (report.height, report.width, 3) and report.width >= 480

    # a recording instead of an OUT.h5: one line saying what to give, nothing written
    import h5py

    rec = tmp_path / "recording.h5"
    with h5py.File(rec, "w") as f:
        f["frames"] = np.stack(_frames())
    answer_file_dialogs(qtbot, [rec, tmp_path / "bad.mp4"], [])
    window.actions_by_name["export_movie"].trigger()
    qtbot.waitUntil(lambda: window.movie_result is not None, timeout=20000)
    assert window.movie_result[0] == "error" and "\n" not in window.movie_result[1]
    assert "Movie not written" in window.banner.text() and not (tmp_path / "bad.mp4").exists()


def test_a_reference_file_16x_brighter_than_the_cameras_frames_is_named_on_the_maps(qtbot, window, tmp_path):
    """A 12-bit camera streams still water; the user loads (Reference ▸ Load…) a reference that another
    program stored with the 12-bit levels in the top bits of 16-bit words: 16x the frames' levels. Every
    frame read as "no contrast" and the maps said to check TIR, the light and the exposure; now they say
    the frame is 16x darker than the reference and what to do."""
    import tifffile

    from app.capture.scene import default_geometry
    from drivers.synthetic import SyntheticCamera
    from processing import forward

    shape = (256, 256)
    geometry = default_geometry(shape)
    board = forward.Checkerboard(period_mm=12 * geometry.pixel_mm, edge_softness_mm=geometry.pixel_mm)
    flat = forward.quantize(forward.render_tir(forward.FlatSurface(), geometry, shape, board)[0], bits=12,
                            noise_rms=2.0, rng=np.random.default_rng(4))
    path = tmp_path / "reference_16bit.tif"
    tifffile.imwrite(path, (flat.astype(np.uint16) << 4))  # 12-bit data in the top bits of 16-bit words
    window.use_camera(SyntheticCamera(flat, frame_rate_hz=30.0, bit_depth=12), geometry=geometry)
    qtbot.waitUntil(lambda: window.clock.last_raw_seq >= 0, timeout=10000)
    answer_file_dialogs(qtbot, [path], [])  # the file typed into the dialog the button opens
    window.geometry_panel.load_ref_button.click()
    qtbot.waitUntil(lambda: "16x darker than the reference" in window.height_view.message.text(), timeout=30000)
    text = window.height_view.message.text()
    assert "no part of the frame could be measured" in text
    assert "stored at another bit depth" in text and "take the reference with this camera" in text
    assert "check that TIR holds" not in text
