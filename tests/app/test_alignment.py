"""Alignment verdicts (app/gui/alignment.py) on ray-traced frames of the simulated tank."""

import numpy as np
import pytest

from app.capture.scene import TankScene
from app.gui.alignment import assess, frame_alignment
from processing.geometry import Geometry


@pytest.fixture(scope="module")
def tank():
    t = TankScene((512, 512), n_frames=2)
    t.prepare("waves")
    return t


def test_still_water_is_ready_with_numbers(tank):
    a, spectrum = frame_alignment(tank(0), tank.geometry.theta_deg)
    ready, reasons, lines, notes = assess(a, 0.0, tank.geometry, has_reference=False)
    assert ready, reasons
    table = dict(lines)
    assert abs(a["theta_estimate_deg"] - 55.0) < 0.1 and "vs 55.00° configured" in table["θ"]
    np.testing.assert_allclose(a["periods_px"], 5.97, atol=0.02)
    assert a["disturbed"] is False and notes == ["capture the reference on still water"]
    assert len(spectrum["carriers"]) == 4


@pytest.mark.parametrize("scene, k", [("still", 0), ("waves", 5)])
def test_one_transform_serves_the_display_and_the_carriers(tank, scene, k):
    """Before a reference the alignment transforms the frame once: the carriers are
    find_carriers_live's own (to the bit on still water, the whole image's search; on waves
    the tiles, searched together near what five of them show, to 1e-5 px and deg: their
    sub-bin steps are computed otherwise) and the spectrum is the full-array display's of
    the same half spectrum (the search's Hann window) to float32 rounding."""
    from processing.carriers import display_spectrum, find_carriers_live, windowed_spectrum

    tank.set_scene(scene)
    try:
        frame = tank(k)
        a, spectrum = frame_alignment(frame, tank.geometry.theta_deg)
        c, disturbed = find_carriers_live(frame)
        assert a["disturbed"] is disturbed is (scene == "waves")
        tol = 0.0 if scene == "still" else 1e-5
        np.testing.assert_allclose(a["periods_px"], c.periods_px, rtol=0, atol=tol)
        assert abs(a["rotation_deg"] - c.rotation_deg) <= tol and abs(a["theta_estimate_deg"] - c.theta_deg) <= tol
        assert a["focus"] == pytest.approx(float(np.min(c.sharpness)), abs=tol)
        want = display_spectrum(np.abs(windowed_spectrum(frame)), frame.shape[1])
        np.testing.assert_allclose(spectrum["log_magnitude"], want["log_magnitude"], atol=1e-5)
        np.testing.assert_array_equal(spectrum["freq_x"], want["freq_x"])
        np.testing.assert_array_equal(spectrum["freq_y"], want["freq_y"])
    finally:
        tank.set_scene("still")


def test_moving_water_gives_numbers_but_no_reference(tank):
    tank.set_scene("waves")
    a, _ = frame_alignment(tank(5), tank.geometry.theta_deg)
    assert "error" not in a and a["disturbed"]
    ready, reasons, lines, _ = assess(a, 0.0, tank.geometry, has_reference=False)
    assert not ready and any("a reference needs still water" in r for r in reasons)
    table = dict(lines)
    assert {"pattern periods", "pattern rotation", "θ", "contrast (local std/mean, median)",
            "focus (carrier peak sharpness)", "saturation"} <= set(table)
    # with a reference, moving water is what is measured: ready
    ready, reasons, _, notes = assess(a, 0.0, tank.geometry, has_reference=True)
    assert ready, reasons
    tank.set_scene("still")


def _updates(frames, geometry, motion):
    """frame_alignment of each frame in turn with one FrameMotion: the last update's dict."""
    for frame in frames:
        a, _ = frame_alignment(frame, geometry.theta_deg, geometry=geometry, motion=motion)
    return a


def test_small_waves_that_one_frame_cannot_show_are_seen_between_frames():
    """By-hand trial 7 Dec 2026: the tank's waves at 256^2 before a reference read READY TO MEASURE (one
    frame's carriers are those of still water at that size), and the reference capture then refused them.
    Two frames a tenth of a second apart differ by a radian of carrier phase; still water with camera noise
    (2 counts of 8 bits, four times the tank's) by under a hundredth of what a reference allows."""
    from app.gui.alignment import FrameMotion
    from processing.reference_average import PHASE_BOUND_RAD

    small = TankScene((256, 256), n_frames=4, noise_rms=2.0)
    small.prepare("waves")
    small.set_scene("waves")
    one, _ = frame_alignment(small(0), small.geometry.theta_deg)
    assert not one["disturbed"] and assess(one, 0.0, small.geometry)[0]  # what the window showed before
    motion = FrameMotion()
    a = _updates([small(0), small(2)], small.geometry, motion)
    assert a["frame_change_rad"] > 10 * PHASE_BOUND_RAD, a["frame_change_rad"]
    ready, reasons, lines, _ = assess(a, 0.0, small.geometry, has_reference=False)
    assert not ready and any("the surface is moving" in r and "rad of carrier phase" in r for r in reasons)
    assert dict(lines)["surface"] == "moving: the pattern shifts between frames"
    small.set_scene("still")
    a = _updates([small(k) for k in range(6)], small.geometry, motion)  # the waves' updates leave its memory
    assert a["frame_change_rad"] < PHASE_BOUND_RAD / 10, a["frame_change_rad"]
    ready, reasons, lines, notes = assess(a, 0.0, small.geometry, has_reference=False)
    assert ready, reasons
    assert "capture the reference on still water" in notes


def test_the_change_between_frames_is_the_carrier_phase_of_a_shift(tank):
    """A still frame shifted by (0.06, -0.04) px (the camera nudged): the change is the larger carrier's
    phase 2 pi |k . d| (0.05-0.06 rad on the tank's 5.97 px board), within 5 %; a turned pattern (carriers
    a bin away) starts a new run instead of reading as motion."""
    from scipy import ndimage

    from app.gui.alignment import FrameMotion

    frame = tank(0).astype(np.float32)
    shift = np.array([0.06, -0.04])
    moved = ndimage.shift(frame, shift, order=5, mode="reflect")
    motion = FrameMotion()
    a = _updates([frame, moved], tank.geometry, motion)
    from processing.carriers import find_carriers

    k = np.asarray(find_carriers(frame).freq)
    expected = float(np.max(np.abs(2 * np.pi * k @ shift)))
    assert a["frame_change_rad"] == pytest.approx(expected, rel=0.05), (a["frame_change_rad"], expected)
    turned = ndimage.rotate(frame, 3.0, reshape=False, order=3, mode="reflect")
    assert _updates([turned], tank.geometry, motion)["frame_change_rad"] is None


def test_theta_and_pattern_changes_are_flagged(tank):
    a, _ = frame_alignment(tank(0))
    g57 = Geometry.from_dict({**tank.geometry.to_dict(), "theta_deg": 56.2})  # 1.2 deg off the pattern's 55
    ready, reasons, _, _ = assess(a, 0.0, g57)
    assert not ready and any("θ from the pattern differs by -1.2°" in r for r in reasons)
    g55 = Geometry.from_dict({**tank.geometry.to_dict(), "theta_deg": 55.8})  # 0.8 deg: within tolerance
    assert assess(a, 0.0, g55)[0]
    # the stored reference was taken with a 2 % coarser, 1 deg rotated pattern: the camera or pattern moved
    moved = dict(a, reference_periods_px=np.asarray(a["periods_px"]) * 1.02,
                 reference_rotation_deg=a["rotation_deg"] + 1.0)
    ready, reasons, _, _ = assess(moved, 0.0, tank.geometry, has_reference=True)
    assert not ready
    assert any("differ by 2.0 % from the reference" in r for r in reasons)
    assert any("pattern rotated by -1.00° since the reference" in r for r in reasons)
    same = dict(a, reference_periods_px=np.asarray(a["periods_px"]) * 1.005,
                reference_rotation_deg=a["rotation_deg"] + 0.2)
    assert assess(same, 0.0, tank.geometry, has_reference=True)[0]


def test_the_board_period_through_the_scale_is_shown_and_checked(tank):
    # the tank's board: 12 px at 0.078125 mm = 0.9375 mm; frames of still water and of waves
    for frame in (tank(0), tank(1)):
        a, _ = frame_alignment(frame, tank.geometry.theta_deg, geometry=tank.geometry)
        assert a["board_period_mm"] == pytest.approx(0.9375, rel=0.003)
        ready, _, lines, _ = assess(a, 0.0, tank.geometry)  # no printed period given: shown, not checked
        assert ready and dict(lines)["board period"].endswith("(printed: not given)")
    a, _ = frame_alignment(tank(0), tank.geometry.theta_deg, geometry=tank.geometry)
    printed = Geometry.from_dict({**tank.geometry.to_dict(), "pattern_period_mm": 0.9375})
    ready, reasons, lines, _ = assess(a, 0.0, printed)
    assert ready, reasons
    assert "vs 0.9375 mm printed (Δ +0.0 %)" in dict(lines)["board period"] or "(Δ -0.0 %)" in dict(lines)["board period"]
    # the scale 8 % too large: heights 17 % too large, and the alignment says which scale the board implies
    wrong = Geometry.from_dict({**printed.to_dict(), "pixel_mm": 0.078125 * 1.08})
    a, _ = frame_alignment(tank(0), wrong.theta_deg, geometry=wrong)
    ready, reasons, _, _ = assess(a, 0.0, wrong)
    assert not ready and any("+8 % off the printed 0.9375 mm" in r and "about 0.0781" in r for r in reasons)


def test_a_reference_of_moving_water_is_refused_with_what_to_do(tank):
    # the tank's waves: the whole image's peaks are smeared, local patches still show the board
    # (the Alignment tab says "moving"); a reconstructor built on such a frame would measure every
    # height against that surface: refused, with the periods it saw and what to do
    from processing import Reconstructor
    from processing.errors import NoCarrierError

    tank.set_scene("waves")
    frame = tank(5)
    a, _ = frame_alignment(frame, tank.geometry.theta_deg)
    assert a["disturbed"]
    with pytest.raises(NoCarrierError, match=r"distorted \(periods \d+\.\d and \d+\.\d px in local patches.*surface was "
                                             r"moving when it was taken; take the reference again on still water"):
        Reconstructor(frame, tank.geometry)
    tank.set_scene("still")
    Reconstructor(tank(0), tank.geometry)  # still water: accepted


def test_a_view_near_grazing_is_noted_while_theta_is_set(tank):
    """The Alignment tab is where theta is set: a geometry at 78 deg gets the note a run prints (heights
    10-20 % off near 80 deg, ray traced), as a note, not a refusal; 55 deg gets none."""
    a, _ = frame_alignment(tank(0))
    steep = Geometry.from_dict({**tank.geometry.to_dict(), "theta_deg": 78.0})
    _, _, _, notes = assess(a, 0.0, steep)
    assert any(n.startswith("theta_deg = 78 is near grazing") for n in notes), notes
    assert not any("grazing" in n for n in assess(a, 0.0, tank.geometry)[3])
