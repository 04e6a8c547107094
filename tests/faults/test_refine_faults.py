"""The default image refinement on frames a camera really gives, through the real CLI (issue 18).

``tirdeflect process`` in a subprocess on ray-traced 12-bit frames: one at the
reference's brightness, one at half of it, one float TIFF rescaled by 1e10
(which once ran 518 s inside cv2.remap, deaf to Ctrl-C and SIGTERM).
"""

import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import tifffile

from tests.app.test_cli_process import rel_error_interior

ROOT = Path(__file__).resolve().parents[2]
SIZE = 192


def test_process_by_default_ignores_the_brightness_and_refuses_a_rescaled_frame_in_seconds(tmp_path):
    from processing import Geometry, forward as F

    g = Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False)
    waves = F.WaveField.random(8, amplitude_rms_mm=0.0003, wavelength_range_mm=(6, 12), seed=1)
    board = F.Checkerboard(period_mm=2.0, edge_softness_mm=0.1)
    ref, _ = F.render_tir(F.FlatSurface(), g, (SIZE, SIZE), board, supersample=2)
    img, _ = F.render_tir(waves, g, (SIZE, SIZE), board, supersample=2)
    tifffile.imwrite(tmp_path / "reference.tif", F.quantize(ref, bits=12))
    tifffile.imwrite(tmp_path / "a_clean.tif", F.quantize(img, bits=12))
    tifffile.imwrite(tmp_path / "b_half.tif", F.quantize(0.5 * img, bits=12))
    tifffile.imwrite(tmp_path / "c_rescaled.tif", F.quantize(img, bits=12).astype(np.float32) * np.float32(1e10))
    (tmp_path / "geometry.toml").write_text(g.to_toml_text())
    out = tmp_path / "out.h5"
    t0 = time.monotonic()
    proc = subprocess.run([sys.executable, "-m", "app.cli", "process", str(tmp_path / "reference.tif"),
                           *(str(tmp_path / f) for f in ("a_clean.tif", "b_half.tif", "c_rescaled.tif")),
                           "--geometry", str(tmp_path / "geometry.toml"), "--out", str(out), "--no-progress"],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    elapsed = time.monotonic() - t0
    assert elapsed < 120, elapsed  # a hang detector: it takes 3-5 s; it ran 518 s inside cv2.remap
    assert proc.returncode == 3, proc.stderr  # output written, a frame invalid
    assert "Traceback" not in proc.stderr
    assert "c_rescaled.tif" in proc.stderr and "beyond what any camera gives" in proc.stderr
    truth = F.true_height(waves, g, (SIZE, SIZE))
    with h5py.File(out) as f:
        assert f.attrs["refine_method"] == "image"
        assert list(f["frame_status"][()]) == [0, 0, 5]  # 5: UNREADABLE
        text = f["frame_status_text"].asstr()[()]
        assert "3.69e+13" in text[2] and "pass the camera's own values" in text[2]
        assert text[0] == text[1] == ""  # no fallback was needed
        clean = rel_error_interior(f["height"][0], truth, g)
        half = rel_error_interior(f["height"][1], truth, g)
    # issue 18's goal: within 1.5x the clean error or 1.5 %; before: 8.8-11.9 % at 0.5x
    assert half <= max(1.5 * clean, 0.015), (clean, half)


def test_a_camera_a_micrometre_from_the_water_never_hangs_process(tmp_path):
    """issue 18: ``camera_distance_mm = 0.001`` ran more than 10 minutes inside cv2.remap.

    Either the geometry is refused with its reason (a physics check of the
    geometry), or the frame is measured with FD's heights and the fallback is
    said: in the file (``/frame_status_text``, ``frames_noted``) and on stderr.
    """
    from processing import Geometry, forward as F

    g = Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False)
    waves = F.WaveField.random(8, amplitude_rms_mm=0.0003, wavelength_range_mm=(6, 12), seed=1)
    board = F.Checkerboard(period_mm=2.0, edge_softness_mm=0.1)
    for name, surface in (("reference", F.FlatSurface()), ("frame", waves)):
        img, _ = F.render_tir(surface, g, (SIZE, SIZE), board, supersample=2)
        tifffile.imwrite(tmp_path / f"{name}.tif", F.quantize(img, bits=12))
    text = g.to_toml_text()
    assert "camera_distance_mm" not in text
    (tmp_path / "geometry.toml").write_text(text + "camera_distance_mm = 0.001\n")
    out = tmp_path / "out.h5"
    t0 = time.monotonic()
    proc = subprocess.run([sys.executable, "-m", "app.cli", "process", str(tmp_path / "reference.tif"),
                           str(tmp_path / "frame.tif"), "--geometry", str(tmp_path / "geometry.toml"),
                           "--out", str(out), "--no-progress"],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert time.monotonic() - t0 < 120  # a hang detector: it takes 2-4 s
    assert "Traceback" not in proc.stderr
    if proc.returncode == 2:  # refused: the message names the key
        assert "camera_distance_mm" in proc.stderr and not out.exists()
        return
    assert proc.returncode == 0, proc.stderr
    assert "image refinement stopped" in proc.stderr and "FD's heights kept" in proc.stderr
    with h5py.File(out) as f:
        assert list(f["frame_status"][()]) == [0]
        note = f["frame_status_text"].asstr()[0]
        assert note.startswith("image refinement stopped: displacement beyond the frame's size")
        assert int(f.attrs["frames_noted"]) == 1
        assert np.isfinite(f["height"][0]).mean() > 0.5
