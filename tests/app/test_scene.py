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
