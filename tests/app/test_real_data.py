"""Real camera images through `tirdeflect process` (no ground truth: checks what is known).

The needle pair (fsss-needle-waves) is documented: the frame is shifted as a
whole by about (0.8, 1.7) px (x, y) against the reference, and ring waves
spread from a needle whose tip is in the upper right. The packed 10-bit
trapped-modes TIFFs must read at their 10-bit scale and process end to end.
"""

import importlib.util
import re
from pathlib import Path

import h5py
import numpy as np
import pytest

from app.cli import main
from tests.datapaths import NEEDLE, TRAPPED

ROOT = Path(__file__).resolve().parents[2]

# where the needle's shadow ends in 202406_1457001661.bmp (row, col), read off the image
NEEDLE_TIP_PX = (320, 830)


def _figures():
    spec = importlib.util.spec_from_file_location("make_figures", ROOT / "docs" / "make_figures.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def fsss_toml(tmp_path_factory):
    path = tmp_path_factory.mktemp("geom") / "fsss.toml"
    path.write_text(_figures().needle_geometry().to_toml_text())
    return path


def test_needle_rings_centred_near_the_needle(tmp_path, fsss_toml, capsys):
    out = tmp_path / "needle.h5"
    code = main(["process", str(NEEDLE / "reference_2.png"), str(NEEDLE / "202406_1457001661.bmp"),
                 "--geometry", str(fsss_toml), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 0, err
    # a real board through a real lens on still water: 0.13 px RMS beyond the smooth view, no word of moving water
    assert "departs from a board seen on still water" not in err, err
    figures = _figures()
    with h5py.File(out) as f:
        height = f["height"][0].astype(np.float64)
        valid = f["valid"][0].astype(bool)
        periods = f["carriers"].attrs["periods_px"]
    # README: carrier period about 9.8 px
    np.testing.assert_allclose(periods, 9.8, atol=0.15)
    assert valid.mean() > 0.85  # needle, its shadow and thin arcs only
    flat, (_, slope_row, slope_col) = figures.remove_plane(height)
    # README: the frame is shifted as a whole; in FS-SS that is a uniform slope,
    # of the same sign along rows and columns, larger along rows (1.7 vs 0.8 px)
    assert slope_row < 0 and slope_col < 0 and 1.5 < slope_row / slope_col < 2.5
    r, c = figures.ring_centre(flat)
    assert r < 512 and c > 512, f"ring centre ({r:.0f}, {c:.0f}) is not in the upper right"
    dist_mm = np.hypot(r - NEEDLE_TIP_PX[0], c - NEEDLE_TIP_PX[1]) * 0.207
    assert dist_mm < 50.0, f"ring centre {dist_mm:.0f} mm from the needle tip"
    # capillary ring waves of tens of micrometres, not a flat map nor millimetres
    p1, p99 = np.nanpercentile(flat, [1, 99])
    assert 0.03 < p99 - p1 < 1.0


def test_packed_10bit_camera_tiffs_process_end_to_end(tmp_path, fsss_toml, capsys):
    ref = TRAPPED / "prueba1_20250317_122608_C1S0001000001.tif"
    frame = TRAPPED / "prueba1_20250317_122608_C1S0001000211.tif"
    out = tmp_path / "tm.h5"
    code = main(["process", str(ref), str(frame), "--geometry", str(fsss_toml), "--out", str(out),
                 "--grid", "decimated"])
    assert code == 0, capsys.readouterr().err
    with h5py.File(out) as f:
        assert f.attrs["reference_bits"] == 10
        # the camera's dead pixels (row 688, column 468: 691 among 925-1023; row 894, column 315: 0 among
        # 898-990, dead in the needle recording's reference too) are repaired, and said; the file keeps
        # the reference as read
        assert f.attrs["stuck_pixels_repaired"] == 2
        assert f["reference"][894, 315] == 0
        assert f["reference"].dtype == np.uint16 and f["reference"][()].max() <= 1023
        assert f["valid"][0].mean() > 0.9
        assert f["source"][0].decode().endswith("C1S0001000211.tif")


def test_the_needle_frames_overall_shift_is_named_and_taken_out_when_asked(tmp_path, fsss_toml, capsys):
    """The real needle frame is shifted by about (0.8, 1.7) px overall against its reference (the data's
    README): the camera or the board moved between the two. Its ring waves fill the frame, yet 57 % of it
    lies within half the frame's median displacement (1.89 px) of it: the whole pattern moved. FS-SS reads
    a uniform displacement as a uniform slope: by default the heights carried a tilt of 0.82 mm RMS, with
    nothing said (6 Dec 2026; the ring waves are about 0.06 mm RMS). Now the run names it, with the tilt,
    whether or not a reference_region at rest (the lower left corner, far from the needle) also sees it
    move (1.88 px there); --shift-removal takes it out (the heights' RMS then the waves' own)."""
    corner = tmp_path / "corner.toml"
    corner.write_text(fsss_toml.read_text() + "reference_region = [900, 1024, 0, 120]\n")
    rms_um = {}
    for name, toml, extra in (("default", fsss_toml, []), ("corner", corner, []),
                              ("removed", fsss_toml, ["--shift-removal"])):
        out = tmp_path / f"needle-{name}.h5"
        code = main(["process", str(NEEDLE / "reference_2.png"), str(NEEDLE / "202406_1457001661.bmp"),
                     "--geometry", str(toml), "--out", str(out), *extra])
        err = capsys.readouterr().err
        assert code == 0, err
        assert "the whole pattern shifted alike since the reference (1.9 px, e.g. frame 0): the camera or the " \
               "board moved" in err, err
        with h5py.File(out) as f:
            assert f.attrs["frames_shifted"] == 1
            st = f["pin_status"][0]
            assert st["frame_motion_px"] == pytest.approx(np.hypot(0.8, 1.7), abs=0.15) and np.isnan(st["shift_level_um"])
            h = f["height"][0].astype(np.float64)
            rms_um[name] = 1e3 * np.sqrt(np.nanmean(h ** 2))
            if name == "corner":  # the region's own motion is kept (its note gives way to the shift's)
                assert st["region_motion_px"] == pytest.approx(np.hypot(0.8, 1.7), abs=0.15)
                assert f.attrs["frames_pin_region_moving"] == 1
        if name == "removed":
            assert "taken out of the heights" in err and st["shift_removed"] == 1
        else:
            assert re.search(r"the heights carry (7|8|9)\d\d um RMS from it", err) and st["shift_removed"] == 0, err
    assert rms_um["default"] > 500 and rms_um["removed"] < 0.1 * rms_um["default"], rms_um
