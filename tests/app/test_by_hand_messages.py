"""Messages and silences found by the by-hand trials of 7 Dec 2026 (a physicist's inputs, through the CLI)."""

from pathlib import Path

import numpy as np
import pytest

from app.cli import main
from app.files import imageio

TINY_BOARD = """setup = "tir"
theta_deg = 55.0
depth_mm = 300.0
pixel_mm = 0.1
rows_toward_camera = false
n_water = 1.333
n_air = 1.0003
pattern_stretch_y = 1.7434
pattern_period_mm = 0.6
"""


def _run(capsys, *argv):
    code = main([str(a) for a in argv])
    return code, capsys.readouterr().err


def test_a_64_px_frame_of_a_6_px_board_is_measured(tmp_path, capsys):
    # the reference's contrast divided by the border taper read ~7x on the outermost ring of the grid, which on
    # a 64^2 frame is 11 % of the samples: its value set the 90th percentile and the whole inside failed, and
    # every frame (the reference itself too) came back "contrast 1.00 (median; need >= 0.3)"
    (tmp_path / "g.toml").write_text(TINY_BOARD)
    sim = tmp_path / "sim"
    code, err = _run(capsys, "simulate", "--out", sim, "--size", 128, "--frames", 1, "--geometry",
                     tmp_path / "g.toml")
    assert code == 0, err
    small = tmp_path / "small"
    small.mkdir()
    for name in ("reference.png", "frame_0000.png"):
        imageio.write_image(small / name, imageio.read_image(sim / name)[32:96, 32:96])
    for frame in (small / "frame_0000.png", small / "reference.png"):
        out = tmp_path / f"{Path(frame).stem}.h5"
        code, err = _run(capsys, "process", small / "reference.png", frame, "--geometry", sim / "geometry.toml",
                         "--out", out, "--no-progress")
        assert code == 0, err
        assert "could be measured" not in err


def test_a_depth_or_pixel_size_no_tir_set_up_has_is_named_before_the_run(tmp_path, capsys):
    # depth_mm = 0.3 (or pixel_mm = 100): the frame's rows span 149 depths; the heights' null mode grew 1e30-fold
    # and the run ended "ray-surface intersection did not converge; the surface is too steep" under numpy's
    # overflow warnings, once per frame
    sim = tmp_path / "sim"
    code, err = _run(capsys, "simulate", "--out", sim, "--size", 128, "--frames", 1)
    assert code == 0, err
    text = (sim / "geometry.toml").read_text()
    for key, value in (("depth_mm", "0.3"), ("pixel_mm", "100.0")):
        lines = [f"{key} = {value}" if line.startswith(f"{key} =") else line for line in text.splitlines()]
        lines = [line for line in lines if not line.startswith("pattern_period_mm")]
        (tmp_path / "g.toml").write_text("\n".join(lines) + "\n")
        code, err = _run(capsys, "process", sim / "reference.png", sim / "frame_0000.png", "--geometry",
                         tmp_path / "g.toml", "--out", tmp_path / "out.h5", "--no-progress")
        assert code == 2
        assert "a view no TIR set-up has" in err and "check pixel_mm" in err and "depth_mm" in err, err
        assert "too steep" not in err and "Warning" not in err and "frame 0" not in err


def test_simulate_judges_the_board_as_a_close_camera_sees_it(tmp_path, capsys):
    # a camera 150 mm away and no board period: simulate's default board (20 px at pixel_mm) is 2 px across
    # there, and the run ended "the image shows no clear carrier peak: check that the checkerboard is in focus,
    # lit, ..." (advice for a real camera); a 5 mm board is 5 to 8 px across the frame (perspective)
    for period, said in (("", "below 4 px the camera cannot resolve the board"),
                         ("pattern_period_mm = 5.0\n", "a spread the carrier search cannot take as one peak")):
        (tmp_path / "g.toml").write_text("setup = \"tir\"\ntheta_deg = 55.0\ndepth_mm = 300.0\npixel_mm = 0.1\n"
                                         "rows_toward_camera = false\ncamera_distance_mm = 150.0\n" + period)
        code, err = _run(capsys, "simulate", "--out", tmp_path / "sim", "--size", 256, "--frames", 1,
                         "--geometry", tmp_path / "g.toml", "--overwrite")
        assert code == 2
        assert said in err and "camera 150 mm away" in err and "focus" not in err, err


def _twelve_bit(tmp_path, capsys):
    sim = tmp_path / "sim12"
    code, err = _run(capsys, "simulate", "--out", sim, "--size", 128, "--frames", 1, "--bits", 12, "--noise", 2)
    assert code == 0, err
    return sim, imageio.read_image(sim / "reference.tif"), imageio.read_image(sim / "frame_0000.tif")


def test_a_reference_at_another_depth_or_in_floats_than_its_frames_is_named_as_it_is(tmp_path, capsys):
    # trial of 7 Dec 2026: an 8-bit reference against 12-bit frames (heights right, 0.05 %) drew "frames read as
    # low contrast or saturated"; a float 0..1 reference was "8-bit" and 38 pixels of noise a frame were
    # "repaired" as hot pixels; 8-bit frames against a 12-bit reference were named, then refused frame by frame
    # "16.1x darker"; float 0..1 frames "4.1e3x darker", with no word of floats
    import h5py

    sim, ref, frame = _twelve_bit(tmp_path, capsys)
    geometry = sim / "geometry.toml"
    imageio.write_image(tmp_path / "ref8.png", np.rint(ref / 16.0).astype(np.uint8))
    tifffile = __import__("tifffile")
    tifffile.imwrite(tmp_path / "ref01.tif", (ref / 4095.0).astype(np.float32))
    for name, says in (("ref8.png", "while the reference is 8-bit (levels up to"),
                       ("ref01.tif", "while the reference holds floats from 0 to")):
        out = tmp_path / f"{name}.h5"
        code, err = _run(capsys, "process", tmp_path / name, sim / "frame_0000.tif", "--geometry", geometry,
                         "--out", out, "--no-progress")
        assert code == 0, err
        assert says in err and "x brighter than the reference; the heights (the pattern's phase) do not" in err
        assert "low contrast or saturated" not in err and "8-bit (levels up to 0" not in err
        assert "isolated pixel" not in err
        with h5py.File(out) as f:
            assert int(f["hot_pixels"][0]) == 0
    imageio.write_image(tmp_path / "frame8.png", np.rint(frame / 16.0).astype(np.uint8))
    tifffile.imwrite(tmp_path / "frame01.tif", (frame / 4095.0).astype(np.float32))
    for name, says in (("frame8.png", "are 8-bit (levels up to 255) while the reference is 12-bit"),
                       ("frame01.tif", "hold floats from 0 to")):
        code, err = _run(capsys, "process", sim / "reference.tif", tmp_path / name, "--geometry", geometry,
                         "--out", tmp_path / "o.h5", "--no-progress")
        assert code == 2
        assert says in err and "x darker than the reference, beyond the 13.3x a dimmer exposure still reads" in err
        assert err.count("darker") == 1 and "frame 0" not in err, err
    assert "the reference's levels divided by 16" in _run(
        capsys, "process", sim / "reference.tif", tmp_path / "frame8.png", "--geometry", geometry,
        "--out", tmp_path / "o.h5", "--no-progress")[1]


def test_a_frame_the_camera_sent_twice_is_counted_and_named(tmp_path, capsys):
    # trial of 7 Dec 2026: a byte-identical repeated frame (a camera's repeat) was measured and stored with no word
    import shutil

    import h5py

    sim = tmp_path / "sim"
    code, err = _run(capsys, "simulate", "--out", sim, "--size", 128, "--frames", 2, "--noise", 1)
    assert code == 0, err
    run = tmp_path / "run"
    run.mkdir()
    for k, name in enumerate(("frame_0000.png", "frame_0000.png", "frame_0001.png")):
        shutil.copy(sim / name, run / f"frame_{k:04d}.png")
    for workers in (1, 2):
        out = tmp_path / f"out{workers}.h5"
        code, err = _run(capsys, "process", sim / "reference.png", *sorted(run.glob("frame_*.png")), "--geometry",
                         sim / "geometry.toml", "--out", out, "--no-progress", "--workers", workers)
        assert code == 0, err
        assert "1 frame(s) identical to the one before, sample for sample (first frame 1, as frame 0): the camera " \
               "repeated a frame" in err, err
        with h5py.File(out) as f:
            assert f.attrs["frames_repeated"] == 1
    code, err = _run(capsys, "process", sim / "reference.png", sim / "frame_0000.png", sim / "frame_0001.png",
                     "--geometry", sim / "geometry.toml", "--out", tmp_path / "distinct.h5", "--no-progress")
    assert code == 0 and "identical" not in err, err


def test_the_reference_given_among_the_frames_is_named(tmp_path, capsys):
    """By-hand trial of 7 Dec 2026: the reference file given as a frame too came out as heights of exactly 0,
    exit 0 and no word. Now counted (frames_as_reference) and said: 0 by definition, not a measurement."""
    import h5py

    sim = tmp_path / "sim"
    assert _run(capsys, "simulate", "--out", sim, "--size", 128, "--frames", 1)[0] == 0
    out = tmp_path / "out.h5"
    code, err = _run(capsys, "process", sim / "reference.png", sim / "reference.png", sim / "frame_0000.png",
                     "--geometry", sim / "geometry.toml", "--out", out, "--no-progress")
    assert code == 0, err
    assert "1 frame(s) are the reference image itself, sample for sample (first frame 0): their heights are 0 by " \
           "definition" in err, err
    with h5py.File(out) as f:
        assert f.attrs["frames_as_reference"] == 1
        assert np.nanmax(np.abs(f["height"][0])) < 1e-6 < np.nanmax(np.abs(f["height"][1]))  # mm: under 1 nm


def test_frames_measured_on_all_but_part_of_their_area_are_named(tmp_path, capsys):
    """By-hand trial of 7 Dec 2026 (the window's impact scene): the impact's centre was NaN in 63 frames, up to
    11 % of the field where its depth lies, and the export said "every frame measured, none flagged" (the run
    names frames measured on less than half of their area only). A frame with a blank patch (a splash, a
    shadow) is now counted and said, by the run and by the window's export message."""
    import h5py

    from app.gui.export import describe_export

    sim = tmp_path / "sim"
    assert _run(capsys, "simulate", "--out", sim, "--size", 128, "--frames", 1)[0] == 0
    frame = imageio.read_image(sim / "frame_0000.png").copy()
    yy, xx = np.mgrid[:128, :128]
    frame[np.hypot(yy - 64, xx - 64) < 14] = int(frame.mean())  # a blank disc, 3.8 % of the frame
    imageio.write_image(tmp_path / "patch.png", frame)
    out = tmp_path / "out.h5"
    code, err = _run(capsys, "process", sim / "reference.png", tmp_path / "patch.png", "--geometry",
                     sim / "geometry.toml", "--out", out, "--no-progress")
    assert code == 0, err
    with h5py.File(out) as f:
        unmeasured = 100.0 * (1.0 - f["valid"][0].mean())
        assert f.attrs["frames_partly_unmeasured"] == 1
        assert f.attrs["unmeasured_pct_max"] == pytest.approx(unmeasured, abs=1.5)
    assert 3 < unmeasured < 20
    assert "1 measured frame(s) were not measured on part of their area (up to" in err, err
    text, clean = describe_export(str(out))
    assert "Note: 1 frame(s) were not measured on part of their area" in text and clean, text
