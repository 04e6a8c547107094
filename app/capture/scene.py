"""A realistic synthetic camera: ray-traced TIR frames of an evolving water surface.

The scene is computed once (exact ray tracing by :mod:`processing.forward`),
at the chosen size, bit depth and number of frames, and then streamed by
:class:`drivers.synthetic.SyntheticCamera` in a loop at the chosen frame rate,
so the GUI and ``tirdeflect record --camera synthetic`` work without hardware
and show something a physicist recognises: travelling capillary-gravity
waves plus the dimple pushed by a disc approaching the surface, reflected
checkerboard and all.

>>> camera, reference, geometry, heights = open_synthetic_camera(shape=(64, 64), n_frames=4)
>>> camera.settings().width, reference.dtype, heights.shape
(64, dtype('uint8'), (4, 64, 64))
>>> camera.close()
"""

from __future__ import annotations

from typing import Optional, Tuple

import numpy as np

__all__ = ["EvolvingScene", "default_geometry", "build_scene", "open_synthetic_camera"]


class EvolvingScene:
    """Surface at time ``t_s``: travelling waves plus an approaching-disc dimple (mm, image frame).

    Parameters
    ----------
    field_mm : (float, float)
        Size of the imaged surface (rows, cols) in mm; sets the scales.
    wave_amplitude_mm : float
        Amplitude of each of the two travelling waves (mm).
    dimple_depth_mm : float
        Final depth of the dimple (mm); it grows as ``(t / t_contact_s)**2``.
    t_contact_s : float
        Time at which the disc touches (dimple at full depth).
    seed : int
        Wave directions and phases.
    """

    def __init__(self, field_mm: Tuple[float, float], *, wave_amplitude_mm: float = 0.002,
                 dimple_depth_mm: float = 0.010, t_contact_s: float = 0.5, seed: int = 0):
        from processing.forward import ApproachingDiscDimple, TravellingWaves

        rng = np.random.default_rng(seed)
        size = float(min(field_mm))
        comps = []
        for lam_frac in (0.5, 0.33):
            lam = lam_frac * size
            k = 2 * np.pi / lam
            ang = rng.uniform(0, 2 * np.pi)
            comps.append((wave_amplitude_mm, k * np.cos(ang), k * np.sin(ang), rng.uniform(0, 2 * np.pi)))
        self.waves = TravellingWaves(tuple(comps))
        self.disc = ApproachingDiscDimple(radius_mm=0.3 * size, max_depth_mm=dimple_depth_mm,
                                          t_contact_s=t_contact_s)

    def at(self, t_s: float):
        from processing.forward import SumSurface

        return SumSurface([self.waves.at(t_s), self.disc.at(t_s)])

    __call__ = at


def default_geometry(shape: Tuple[int, int] = (512, 512)):
    """TIR geometry of the synthetic tank: theta 55 deg, pattern 300 mm deep, 40 mm field, telecentric."""
    from processing.geometry import Geometry

    pixel_mm = 40.0 / max(shape)
    return Geometry(theta_deg=55.0, depth_mm=300.0, pixel_mm=pixel_mm, rows_toward_camera=False)


def build_scene(shape: Tuple[int, int] = (512, 512), n_frames: int = 32, *, frame_rate_hz: float = 100.0,
                bits: int = 8, noise_rms: float = 0.5, seed: int = 0, supersample: int = 1):
    """Render the scene once.

    Returns
    -------
    simulation : processing.forward.Simulation
        ``reference`` (rows, cols), ``frames`` (n_frames, rows, cols) uint8/uint16,
        ``heights_mm`` (n_frames, rows, cols) float32, ``times_s``, ``lost``.
    geometry : processing.geometry.Geometry
    """
    from processing.forward import Checkerboard, simulate

    shape = (int(shape[0]), int(shape[1]))
    if min(shape) < 16:
        raise ValueError(f"synthetic scene needs at least 16x16 pixels; got {shape}")
    if n_frames < 1:
        raise ValueError(f"n_frames must be >= 1; got {n_frames}")
    geometry = default_geometry(shape)
    field = (shape[0] * geometry.pixel_mm, shape[1] * geometry.pixel_mm)
    scene = EvolvingScene(field, t_contact_s=max(n_frames / float(frame_rate_hz), 1e-3), seed=seed)
    pattern = Checkerboard(period_mm=12 * geometry.pixel_mm, edge_softness_mm=geometry.pixel_mm)
    sim = simulate(scene, geometry, shape, n_frames, pattern=pattern, fps=frame_rate_hz, bits=bits,
                   noise_rms=noise_rms, supersample=supersample, seed=seed)
    return sim, geometry


def open_synthetic_camera(shape: Tuple[int, int] = (512, 512), n_frames: int = 16, frame_rate_hz: float = 100.0,
                          bits: int = 8, seed: int = 0, **camera_options):
    """A :class:`~drivers.synthetic.SyntheticCamera` streaming the ray-traced scene in a loop (opened).

    Parameters
    ----------
    shape : (rows, cols)
        Frame size in pixels.
    n_frames : int
        Frames rendered once (the camera loops over them); about 0.5 s each at 512x512 on one core.
    frame_rate_hz : float
        Camera frame rate; the scene's time axis uses it too.
    bits : int
        8 (uint8) or 10/12/16 (uint16).
    seed : int
        Waves and noise.
    **camera_options
        Passed on to SyntheticCamera (``drop_frames``, ``n_buffers``, ``camera_id`` ...).

    Returns
    -------
    camera : SyntheticCamera (opened; close it)
    reference_image : ndarray (rows, cols), the flat surface's image
    geometry : processing.geometry.Geometry
    true_heights : ndarray (n_frames, rows, cols) float32 in mm, or None
        Height where each pixel's ray meets the surface, frame ``k`` shown as frame id ``k % n_frames``.
    """
    from drivers.synthetic import SyntheticCamera

    if bits not in (8, 10, 12, 16):
        raise ValueError(f"bits must be 8, 10, 12 or 16 like a camera's pixel format; got {bits!r}")
    sim, geometry = build_scene(shape, n_frames, frame_rate_hz=frame_rate_hz, bits=bits, seed=seed)
    camera_options.setdefault("camera_id", "synthetic")
    cam = SyntheticCamera(sim.frames, frame_rate_hz=frame_rate_hz, bit_depth=bits, loop=True, **camera_options)
    return cam.open(), sim.reference, geometry, sim.heights_mm


def synthetic_reference(shape: Tuple[int, int], bits: int = 8, seed: int = 0) -> Optional[np.ndarray]:
    """Only the reference image of the scene (flat surface)."""
    sim, _ = build_scene(shape, 1, bits=bits, seed=seed)
    return sim.reference
