"""The pattern continued beyond the frame's border (processing/continuation.py, issue 19)."""

import math

import numpy as np

from processing import forward as F
from processing.carriers import find_carriers
from processing.continuation import ContinuedSignals, PatternContinuation
from processing.geometry import Geometry
from processing.reconstruct import Reconstructor

G55 = Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False)
K = 2 * np.pi * np.array([[1 / 8.0, 1 / 9.5], [-1 / 8.5, 1 / 10.0]])  # rad/px, (row, col) per carrier


def cosines(shape, shift=(0.0, 0.0), offset=(0, 0)):
    """Two crossed cosines on the pixels of ``shape``, moved by ``shift`` (px), the pixel (0, 0) at
    ``offset`` of an image frame (pad pixels have negative coordinates)."""
    r = np.arange(shape[0], dtype=np.float64)[:, None] - offset[0] - shift[0]
    c = np.arange(shape[1], dtype=np.float64)[None, :] - offset[1] - shift[1]
    return sum(np.cos(K[s, 0] * r + K[s, 1] * c) for s in range(2))


def test_the_pad_holds_the_pattern_itself():
    # a regular pattern's continuation is the pattern: inside the outer taper, the pad
    # equals the cosines evaluated beyond the border to 10 % of their RMS (measured 6.5 %,
    # the same at every distance from the border: the envelope measured half a period in by a
    # Gaussian window of half a period, which the border cuts; a taper puts 100 % there)
    shape = (120, 150)
    image = 100.0 + 40.0 * cosines(shape)
    cont = PatternContinuation(shape, K / (2 * np.pi))
    out = cont(image)
    (R, C), (pr, pc) = out.shape, cont.offset
    period = float(np.max(2 * np.pi / np.hypot(K[:, 0], K[:, 1])))
    assert R >= shape[0] + 8 * period and C >= shape[1] + 8 * period  # 4 periods each side at least
    truth = 40.0 * cosines((R, C), offset=(pr, pc))
    frame = (slice(pr, pr + shape[0]), slice(pc, pc + shape[1]))
    np.testing.assert_allclose(out[frame], image - image.mean(), atol=1e-3)  # the image itself, mean removed
    near = np.zeros((R, C), bool)  # the pad's inner half, before the outer taper
    near[pr // 2:pr + shape[0] + pr // 2, pc // 2:pc + shape[1] + pc // 2] = True
    near[frame] = False
    assert np.sqrt(np.mean((out - truth)[near] ** 2)) <= 0.1 * np.sqrt(np.mean(truth[near] ** 2))
    # a batch, on the array module's code path, equals each image's
    batch = np.stack([image, image[::-1, ::-1].copy()])
    both = cont(batch)
    np.testing.assert_allclose(both[0], out, atol=1e-4)
    np.testing.assert_allclose(both[1], cont(image[::-1, ::-1].copy()), atol=1e-4)


def test_a_shifted_pattern_measures_its_shift_up_to_the_border():
    # frame = reference moved by a constant (0.3, -0.45) px: the phase of the continued signals is
    # -k.shift on every sample of the decimated grid, the border included; the taper's is not
    # (it stops the pattern there). Measured: continued 0.0017 rad rms, 0.030 at worst (a corner,
    # where the envelopes are the corner's); taper 0.0088 rms, 0.22 at worst.
    shape = (160, 160)
    reference = 128 + 60 * cosines(shape)
    shift = (0.3, -0.45)
    frame = 128 + 60 * cosines(shape, shift)
    rec = Reconstructor(reference.astype(np.float32), G55)
    demod = rec.demod
    continued = ContinuedSignals(demod, reference)
    expected = -(demod.wavevectors @ np.array(shift))[:, None, None]
    off = np.abs(continued.phase_difference(continued.signals(frame), continued.g0) - expected)
    off_taper = np.abs(np.angle(demod.decimated(frame.astype(np.float32)) * np.conj(demod.g0)) - expected)
    assert np.sqrt(np.mean(off ** 2)) <= 0.003
    assert np.sqrt(np.mean(off ** 2)) <= 0.3 * np.sqrt(np.mean(off_taper ** 2))
    assert off.max() <= 0.25 * off_taper.max()


def test_fd_full_grid_is_measured_on_the_continued_frame():
    # the full grid with refine_iterations=0 is the continued phase; the live grid keeps the taper's:
    # on the pure cosines with ring waves (issue 19) the full grid's displacement is the better one
    cos = F.CrossedCosines(period_mm=0.8, rotation_deg=9.0, stretch_y=1.0 / math.cos(math.radians(55.0)))
    rings = F.RingWaves(amplitude_mm=0.00033, wavelength_mm=7.0)
    ref, _ = F.render_tir(F.FlatSurface(), G55, (192, 192), cos, supersample=1)
    img, _ = F.render_tir(rings, G55, (192, 192), cos, supersample=1)
    rec = Reconstructor(ref, G55, refine_iterations=0)
    live = rec(img, grid="decimated")
    rec.reset_series()
    full = rec(img, grid="full")

    def err(res):
        u_true = F.true_displacement(rings, G55, (192, 192), rows_px=res.rows_px, cols_px=res.cols_px)[0]
        R, C = np.meshgrid(res.rows_px, res.cols_px, indexing="ij")
        inner = res.valid & (R > 16) & (R < 176) & (C > 16) & (C < 176)
        d = (res.displacement - u_true)[:, inner]
        return float(np.sqrt(np.mean(d ** 2)) / np.sqrt(np.mean(u_true[:, inner] ** 2)))

    assert find_carriers(ref).periods_px.min() > 7
    assert err(full) <= 0.75 * err(live), (err(full), err(live))
