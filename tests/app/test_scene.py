"""The synthetic scene camera: ray-traced frames streamed in order, with truth that evolves as designed."""

import numpy as np

from app.capture.scene import EvolvingScene, open_synthetic_camera


def test_scene_camera_streams_the_rendered_frames_and_the_dimple_deepens():
    cam, ref, geometry, heights = open_synthetic_camera(shape=(64, 64), n_frames=6, frame_rate_hz=100.0, bits=10)
    try:
        s = cam.settings()
        assert (s.height, s.width, s.bit_depth, s.pixel_format) == (64, 64, 10, "Mono10")
        assert ref.dtype == np.uint16 and ref.max() < 1024 and ref.max() - ref.min() > 500  # 10-bit checkerboard
        assert heights.shape == (6, 64, 64) and heights.dtype == np.float32
        cam.start()
        got = []
        for _ in range(8):
            with cam.fetch(2.0) as f:
                got.append((f.frame_id, f.image.copy()))
        cam.stop()
    finally:
        cam.close()
    # loops over the 6 rendered frames in order: frame id k shows frame k % 6
    assert [fid for fid, _ in got] == list(range(8))
    np.testing.assert_array_equal(got[6][1], got[0][1])
    assert not np.array_equal(got[5][1], got[0][1])
    # the disc's dimple at the field centre deepens as (t / t_contact)**2 on top of the waves
    field = (64 * geometry.pixel_mm, 64 * geometry.pixel_mm)
    scene = EvolvingScene(field, t_contact_s=6 / 100.0, seed=0)
    dimple = [scene.disc.at(k / 100.0).height(0.0, 0.0) for k in range(6)]
    assert np.all(np.diff(dimple) < 0) and dimple[-1] < -0.005  # mm: a 6.9 um deep dimple at frame 5
    centre = [float(scene.at(k / 100.0).height(0.0, 0.0) - scene.waves.at(k / 100.0).height(0.0, 0.0))
              for k in range(6)]
    np.testing.assert_allclose(centre, dimple, atol=1e-12)
    # the rendered truth sees the dimple too: its deepest point goes down by several micrometres
    assert heights[5].min() < heights[0].min() - 0.003


def test_tank_session_starts_still_and_scenes_have_truth_and_sensible_amplitudes():
    """Still water first (flat truth, frames differ by camera noise only); waves, drop, impact are ray-traced
    with their true heights; carrier shifts stay within a few pixels; rays cross only at the impact."""
    from app.capture.scene import SCENES, TankScene, scene_surface
    from processing import forward

    tank = TankScene((256, 256), n_frames=6, frame_rate_hz=60.0)
    a, b = tank(0).astype(float), tank(1).astype(float)
    assert 0.2 < np.std(a - b) < 1.0  # 0.5 counts read noise per frame, nothing else moves
    assert np.all(tank.truth(0) == 0) and tank.scene_of(1) == "still"
    for name in SCENES[1:]:
        assert tank.prepare(name) == name and tank.ready(name)
    tank.set_scene("impact")
    first = 100
    frames = [tank(first + k) for k in range(6)]
    # truth of a frame id is the surface of its clip index, sampled where the pixel's ray meets it
    surf = scene_surface("impact", tank.field_mm, 5 / 60.0, 6 / 60.0)
    np.testing.assert_allclose(tank.truth(first + 5), forward.true_height(surf, tank.geometry, tank.shape),
                               atol=1e-9)
    assert tank.truth(first + 5).min() < -0.008  # the disc's dimple at contact: 9 um
    assert not np.array_equal(frames[0], frames[5])
    for name in ("waves", "drop", "impact"):
        lost, umax = 0.0, 0.0
        for k in range(6):
            s = scene_surface(name, tank.field_mm, k / 60.0, 6 / 60.0)
            _, info = forward.render_tir(s, tank.geometry, tank.shape, tank.pattern)
            lost = max(lost, float(np.mean(info.lost_tir | info.crossing)))
            u, _ = forward.true_displacement(s, tank.geometry, tank.shape)
            umax = max(umax, float(np.nanmax(np.hypot(u[0], u[1]))))
        if name != "impact":  # carrier phase 2 pi |u| / period: the 6-px pattern moves by < 1 period
            assert umax < 6.0, (name, umax)
        # rays cross (masked spots) only under the impact's dimple, and there on < 2 % of the frame
        assert (lost > 0) == (name == "impact") and lost < 0.02, (name, lost)
