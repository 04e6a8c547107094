"""Exact ray tracing of TIR (and FS-SS) deflectometry: the truth tests check against.

A camera ray is traced to the deformed water surface ``z = h(x, y)`` (the
intersection solved by Newton iteration to 1e-9 mm), reflected about the
exact normal ``(-h_x, -h_y, 1)/|.|`` (TIR) or refracted through it and through
the layer stack below (FS-SS), and followed to the pattern plane where the
pattern is sampled. Nothing here uses the linear model of the paper; the
tests compare that model (and the reconstruction) against this tracer.

Surfaces are defined in the *image frame* (``x`` along increasing column,
``y`` along increasing row, mm on the water surface, origin where the
central camera ray meets the surface; see :mod:`processing.geometry`). Each
surface gives ``height(x_mm, y_mm)`` and the exact ``gradient(x_mm, y_mm) ->
(dh/dx, dh/dy)``, in mm and dimensionless.

Surfaces (:mod:`processing.surfaces`) and patterns (:mod:`processing.patterns`)
live in their own modules and are re-exported here.

Examples
--------
>>> from processing.geometry import Geometry
>>> g = Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False)
>>> bump = GaussianBump(amplitude_mm=0.005, sigma_mm=3.0)
>>> image, info = render_tir(bump, g, (64, 64), Checkerboard(period_mm=2.0))
>>> image.shape, image.dtype
((64, 64), dtype('float32'))
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .errors import GeometryError, ShapeMismatchError
from .geometry import Geometry
from .patterns import Checkerboard, CrossedCosines, RandomDots
from .surfaces import (ApproachingDiscDimple, Dimple, FlatSurface, GaussianBump, RingWaves, SumSurface, Surface,
                       TravellingWaves, WaveField)

__all__ = [
    "Surface",
    "FlatSurface",
    "GaussianBump",
    "Dimple",
    "WaveField",
    "SumSurface",
    "RingWaves",
    "ApproachingDiscDimple",
    "TravellingWaves",
    "Checkerboard",
    "CrossedCosines",
    "RandomDots",
    "RenderInfo",
    "trace_tir",
    "trace_fsss",
    "render_tir",
    "render_fsss",
    "render",
    "true_height",
    "true_displacement",
    "quantize",
    "simulate",
    "Simulation",
]


# ============================================================================ tracing
@dataclass
class RenderInfo:
    """Side information of a render (all arrays of the frame shape).

    Attributes
    ----------
    lost_tir : ndarray bool
        Pixels where some ray's incidence on the surface is below the critical
        angle (light escapes into the air: dark, low contrast).
    crossing : ndarray bool
        Pixels where the pixel -> pattern map folds (its Jacobian changes
        sign against the flat map): ray crossing, caustics.
    pattern_xy : ndarray, shape (2, rows, cols)
        Pattern-plane point of each pixel's central ray (mm), frame of the tracer.
    height_mm : ndarray float64
        Height where each pixel's central ray meets the surface, mm: what
        :func:`true_height` gives, from the same trace (no second one).
    """

    lost_tir: np.ndarray
    crossing: np.ndarray
    pattern_xy: np.ndarray = field(repr=False)
    height_mm: np.ndarray = field(repr=False)


def _intersect(surface: Surface, geometry: Geometry, origin, d, *, to_image, tol_mm=1e-9, max_iter=60):
    """Newton solve of ``O_z + t d_z = h(O_xy + t d_xy)``; returns point, gradient (tracer frame), height.

    On the components of the rays (``origin``, ``d``: S + (3,)), not on (S, 3) arrays: the same
    arithmetic in the same order (the same bits), without the strided passes over the last axis."""
    ysign = geometry.row_sign if geometry.setup == "tir" else 1.0
    ox, oy, oz = origin[..., 0], origin[..., 1], origin[..., 2]
    dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
    t = -oz / dz
    for _ in range(max_iter):
        px, py, pz = ox + t * dx, oy + t * dy, oz + t * dz
        xi, yi = to_image(px, py)
        h, gx, gy_i = surface.height_and_gradient(xi, yi)
        gy = gy_i * ysign
        step = (pz - h) / (dz - gx * dx - gy * dy)
        if np.max(np.abs(step)) < tol_mm:
            # the point is within tol_mm of the root: keep it and its (consistent) normal
            break
        t = t - step
    else:  # pragma: no cover - only for pathological surfaces
        raise GeometryError(
            "ray-surface intersection did not converge; the surface is too steep for the camera rays"
        )
    return np.stack([px, py, pz], axis=-1), gx, gy, h


def trace_tir(surface: Surface, geometry: Geometry, rows_px, cols_px, frame_shape, *, rays=None):
    """Trace TIR camera rays for pixels ``(rows_px, cols_px)`` (broadcast).

    ``rays``: ``geometry.camera_rays(rows_px, cols_px, frame_shape)`` where the caller
    keeps them (the same pixels traced again and again: the second-order correction).

    Returns
    -------
    pattern_xy : ndarray, shape S + (2,), float64
        Canonical-frame pattern-plane point ``(x, y)`` of each ray, mm.
    lost : ndarray bool, shape S
        Incidence below the critical angle (no TIR) or ray not going down.
    hit : ndarray, shape S + (3,)
        Canonical-frame point where the ray meets the surface, mm.
    height_mm : ndarray, shape S
        Surface height at the hit point.
    cos_incidence : ndarray, shape S
        Cosine of the incidence angle on the local normal.
    """
    if geometry.setup != "tir":
        raise GeometryError(f"trace_tir needs a TIR geometry, got setup={geometry.setup!r}")
    origin, d = geometry.camera_rays(rows_px, cols_px, frame_shape) if rays is None else rays
    s = geometry.row_sign
    P, gx, gy, h = _intersect(surface, geometry, origin, d, to_image=lambda x, y: (x, s * y))
    # the unit normal (-gx, -gy, 1) / |.|, the incidence and the reflected ray, by components
    # (norm and dot products summed x, y, z in turn, as np.linalg.norm and np.sum over the last axis)
    nx, ny = -gx, -gy
    length = np.sqrt(nx * nx + ny * ny + 1.0)
    nx, ny, nz = nx / length, ny / length, 1.0 / length
    dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
    cos_i = dx * nx + dy * ny + dz * nz
    sin_i = np.sqrt(np.clip(1.0 - cos_i**2, 0.0, None))
    twice = 2.0 * cos_i
    rx, ry, rz = dx - twice * nx, dy - twice * ny, dz - twice * nz
    lost = (sin_i <= geometry.n_air / geometry.n_water) | (rz >= 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(rz < 0, (-geometry.depth_mm - P[..., 2]) / rz, np.nan)
    pat = np.stack([P[..., 0] + t * rx, P[..., 1] + t * ry], axis=-1)
    return pat, lost, P, h, cos_i


def _refract(d, n, n1, n2):
    """Vector Snell refraction of unit rays ``d`` through unit normals ``n`` (n opposite to d)."""
    cos_i = -np.sum(d * n, axis=-1)
    eta = n1 / n2
    k = 1.0 - eta**2 * (1.0 - cos_i**2)
    tir = k < 0
    cos_t = np.sqrt(np.clip(k, 0.0, None))
    out = eta * d + (eta * cos_i - cos_t)[..., None] * n
    return out, tir


def trace_fsss(surface: Surface, geometry: Geometry, rows_px, cols_px, frame_shape):
    """Trace FS-SS camera rays (camera above) through the surface and the layers.

    Returns
    -------
    pattern_xy : ndarray, shape S + (2,)
        Image-frame pattern-plane point, mm.
    lost : ndarray bool, shape S
        Rays totally reflected somewhere on the way (none for gentle surfaces).
    hit : ndarray, shape S + (3,)
        Point on the surface (image frame).
    height_mm : ndarray, shape S
    """
    if geometry.setup != "fsss":
        raise GeometryError(f"trace_fsss needs an FS-SS geometry, got setup={geometry.setup!r}")
    origin, d = geometry.camera_rays(rows_px, cols_px, frame_shape)
    P, gx, gy, h = _intersect(surface, geometry, origin, d, to_image=lambda x, y: (x, y))
    nrm = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    d2, lost = _refract(d, nrm, geometry.n_air, geometry.n_water)
    # water layer: from the hit point down to the interface at -t_water
    layers = list(reversed(geometry.fsss_layers))
    z_level = 0.0
    pos = P.copy()
    n_prev = geometry.n_water
    up = np.array([0.0, 0.0, 1.0])
    for i, (t, n) in enumerate(layers):
        if i > 0:
            d2, tir = _refract(d2, np.broadcast_to(up, d2.shape), n_prev, n)
            lost = lost | tir
        z_level -= t
        step = (z_level - pos[..., 2]) / d2[..., 2]
        pos = pos + step[..., None] * d2
        n_prev = n
    return pos[..., :2], lost, P, h


def _sub_offsets(supersample: int):
    k = (np.arange(supersample) + 0.5) / supersample - 0.5
    return k


def _check_shape(shape):
    if len(tuple(shape)) != 2 or min(shape) < 2:
        raise ShapeMismatchError(f"shape must be (n_rows, n_cols) with both >= 2, got {tuple(shape)!r}")
    return int(shape[0]), int(shape[1])


def _fresnel_r(cos_i, n1, n2):
    """Unpolarised Fresnel reflectance from medium n1 into n2 (1 beyond the critical angle)."""
    sin_i = np.sqrt(np.clip(1 - cos_i**2, 0, None))
    sin_t = n1 / n2 * sin_i
    tir = sin_t >= 1
    cos_t = np.sqrt(np.clip(1 - sin_t**2, 0, None))
    rs = ((n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)) ** 2
    rp = ((n1 * cos_t - n2 * cos_i) / (n1 * cos_t + n2 * cos_i)) ** 2
    return np.where(tir, 1.0, 0.5 * (rs + rp))


def _jacobian_det(p):
    """Determinant of the Jacobian of pixel -> pattern point, ``p`` (rows, cols, 2)."""
    a_r = np.gradient(p[..., 0], axis=0)
    a_c = np.gradient(p[..., 0], axis=1)
    b_r = np.gradient(p[..., 1], axis=0)
    b_c = np.gradient(p[..., 1], axis=1)
    return a_r * b_c - a_c * b_r


@functools.lru_cache(maxsize=8)
def _flat_jacobian_sign(geometry: Geometry, n_rows: int, n_cols: int) -> np.ndarray:
    """Sign of the flat surface's pixel -> pattern Jacobian (the same for every frame of a
    series: computed once per geometry and frame size; read-only)."""
    rows = np.arange(n_rows, dtype=np.float64)[:, None]
    cols = np.arange(n_cols, dtype=np.float64)[None, :]
    flat = np.stack(geometry.flat_pattern_point(rows, cols, (n_rows, n_cols)), axis=-1)
    sign = np.sign(_jacobian_det(flat))
    sign.flags.writeable = False
    return sign


def _crossing_mask(pat, geometry: Geometry):
    """Pixels where the Jacobian of pixel -> pattern differs in sign from the flat map."""
    n_rows, n_cols = pat.shape[:2]
    try:
        flat_sign = _flat_jacobian_sign(geometry, n_rows, n_cols)
    except TypeError:  # a geometry holding a list (unhashable): computed, not cached
        flat_sign = _flat_jacobian_sign.__wrapped__(geometry, n_rows, n_cols)
    return ~(np.sign(_jacobian_det(pat)) == flat_sign)


def render_tir(
    surface: Surface,
    geometry: Geometry,
    shape,
    pattern: Callable,
    *,
    supersample: int = 1,
    pattern_offset_mm: tuple[float, float] = (0.0, 0.0),
    camera_turn_mrad: float = 0.0,
):
    """Render the camera image of ``pattern`` reflected by the deformed surface.

    Parameters
    ----------
    surface : Surface
        Water surface (image frame, mm).
    geometry : Geometry
        TIR geometry (telecentric or finite camera distance).
    shape : (int, int)
        Frame shape (n_rows, n_cols).
    pattern : callable
        ``pattern(x_mm, y_mm) -> intensity in [0, 1]`` on the pattern plane,
        coordinates centred under the image centre (``y`` canonical minus
        ``H tan(theta)``), e.g. :class:`Checkerboard`.
    supersample : int
        Rays per pixel along each axis (area averaging; 2-3 makes sharp
        boards realistic).
    pattern_offset_mm : (float, float)
        Shift of the pattern on its plane (x, y), mm.
    camera_turn_mrad : float
        The camera turned about its optical axis (through the image centre) by
        this angle, mrad: the image turns the other way, clockwise as shown
        (rows down) for a positive angle; each pixel sees what the unturned
        camera's pixel at its place turned back sees (a camera knocked after
        the reference was taken).

    Returns
    -------
    image : ndarray, shape (n_rows, n_cols), float32 in [0, 1]
        Where TIR is lost the light escapes: the pixel gets the Fresnel
        reflectance times the pattern (dark, low contrast).
    info : RenderInfo
    """
    n_rows, n_cols = _check_shape(shape)
    if supersample < 1:
        raise GeometryError(f"supersample must be >= 1, got {supersample!r}")
    y_off = geometry.depth_mm * math.tan(geometry.theta)
    rows = np.arange(n_rows, dtype=np.float64)[:, None]
    cols = np.arange(n_cols, dtype=np.float64)[None, :]
    if camera_turn_mrad:
        # pixel (r, c) sees the unturned camera's pixel at (r - w (c - c0), c + w (r - r0)), exactly turned
        w = 1e-3 * float(camera_turn_mrad)
        r0, c0 = (n_rows - 1) / 2.0, (n_cols - 1) / 2.0
        rows, cols = (r0 + math.cos(w) * (rows - r0) - math.sin(w) * (cols - c0),
                      c0 + math.sin(w) * (rows - r0) + math.cos(w) * (cols - c0))
    acc = np.zeros((n_rows, n_cols))
    lost_any = np.zeros((n_rows, n_cols), dtype=bool)
    centre_pat = None
    offs = _sub_offsets(supersample)
    for orow in offs:
        for ocol in offs:
            pat, lost, _, height, cos_i = trace_tir(surface, geometry, rows + orow, cols + ocol, (n_rows, n_cols))
            px = np.nan_to_num(pat[..., 0] - pattern_offset_mm[0])
            py = np.nan_to_num(pat[..., 1] - y_off - pattern_offset_mm[1])
            val = pattern(px, py)
            refl = np.ones(lost.shape)  # the Fresnel reflectance only where TIR is lost (often nowhere)
            refl[lost] = _fresnel_r(np.abs(cos_i[lost]), geometry.n_water, geometry.n_air)
            refl[np.isnan(pat[..., 0])] = 0.0
            acc += refl * val
            lost_any |= lost
    image = (acc / supersample**2).astype(np.float32)
    if supersample != 1:
        pat, _, _, height, _ = trace_tir(surface, geometry, rows, cols, (n_rows, n_cols))
    crossing = _crossing_mask(pat, geometry)
    centre_pat = np.moveaxis(pat, -1, 0)
    return np.clip(image, 0.0, 1.0), RenderInfo(lost_any, crossing, centre_pat, height)


def render_fsss(surface: Surface, geometry: Geometry, shape, pattern: Callable, *, supersample: int = 1):
    """FS-SS render: the pattern seen from above through the deformed surface.

    Same returns as :func:`render_tir`; pattern coordinates are image-frame
    pattern-plane mm centred under the image centre.
    """
    n_rows, n_cols = _check_shape(shape)
    rows = np.arange(n_rows, dtype=np.float64)[:, None]
    cols = np.arange(n_cols, dtype=np.float64)[None, :]
    acc = np.zeros((n_rows, n_cols))
    lost_any = np.zeros((n_rows, n_cols), dtype=bool)
    for orow in _sub_offsets(supersample):
        for ocol in _sub_offsets(supersample):
            pat, lost, _, height = trace_fsss(surface, geometry, rows + orow, cols + ocol, (n_rows, n_cols))
            acc += np.where(lost, 0.0, pattern(pat[..., 0], pat[..., 1]))
            lost_any |= lost
    if supersample != 1:
        pat, _, _, height = trace_fsss(surface, geometry, rows, cols, (n_rows, n_cols))
    crossing = _crossing_mask(pat, geometry)
    image = (acc / supersample**2).astype(np.float32)
    return np.clip(image, 0.0, 1.0), RenderInfo(lost_any, crossing, np.moveaxis(pat, -1, 0), height)


def render(surface: Surface, geometry: Geometry, shape, pattern: Callable, *, supersample: int = 1):
    """:func:`render_tir` or :func:`render_fsss` according to ``geometry.setup``."""
    if geometry.setup == "tir":
        return render_tir(surface, geometry, shape, pattern, supersample=supersample)
    return render_fsss(surface, geometry, shape, pattern, supersample=supersample)


def _grid(shape, rows_px=None, cols_px=None):
    n_rows, n_cols = _check_shape(shape)
    r = np.arange(n_rows, dtype=np.float64) if rows_px is None else np.asarray(rows_px, dtype=np.float64)
    c = np.arange(n_cols, dtype=np.float64) if cols_px is None else np.asarray(cols_px, dtype=np.float64)
    return r[:, None], c[None, :], (n_rows, n_cols)


def true_height(surface: Surface, geometry: Geometry, shape, *, rows_px=None, cols_px=None) -> np.ndarray:
    """Height (mm) where each pixel's central ray meets the deformed surface.

    Returns
    -------
    ndarray, shape (len(rows_px), len(cols_px)) (default: the full frame), float64
    """
    rows, cols, shape = _grid(shape, rows_px, cols_px)
    if geometry.setup == "tir":
        _, _, _, h, _ = trace_tir(surface, geometry, rows, cols, shape)
    else:
        _, _, _, h = trace_fsss(surface, geometry, rows, cols, shape)
    return h


def true_displacement(surface: Surface, geometry: Geometry, shape, *, rows_px=None, cols_px=None):
    """Exact displacement ``u`` (pixels) that FD measures: ``I(r) = I0(r - u(r))``.

    For pixel ``r`` the deformed image shows the pattern point ``P(r)``; the
    reference showed it at ``r' = P0^-1(P(r))``; ``u = r - r'``.

    Returns
    -------
    u : ndarray, shape (2, n_rows, n_cols), float64
        ``(u_row, u_col)`` in pixels; NaN where TIR is lost.
    lost : ndarray bool, shape (n_rows, n_cols)
    """
    rows, cols, shape = _grid(shape, rows_px, cols_px)
    if geometry.setup == "tir":
        pat, lost, _, _, _ = trace_tir(surface, geometry, rows, cols, shape)
    else:
        pat, lost, _, _ = trace_fsss(surface, geometry, rows, cols, shape)
    r0, c0 = geometry.pixel_of_pattern_point(pat[..., 0], pat[..., 1], shape)
    u = np.stack([rows - r0, cols - c0])
    u[:, lost] = np.nan
    return u, lost


def quantize(image, *, bits: int = 8, noise_rms: float = 0.0, rng=None, full_well_e: float | None = None):
    """Digitise a [0, 1] image with read (and optional photon) noise.

    Parameters
    ----------
    image : ndarray float in [0, 1]
    bits : int
        1..16; output uint8 for bits <= 8, else uint16 (values < 2**bits).
    noise_rms : float
        Gaussian read noise in digital numbers (DN).
    rng : numpy.random.Generator
        Required when any noise is asked for (fixed seeds in tests).
    full_well_e : float or None
        Electrons at full scale; if given adds Poisson photon noise.

    Returns
    -------
    ndarray uint8 or uint16, same shape
    """
    if not 1 <= int(bits) <= 16:
        raise GeometryError(f"bits must be between 1 and 16, got {bits!r}")
    full = 2 ** int(bits) - 1
    x = np.clip(np.asarray(image, dtype=np.float64), 0.0, 1.0)
    if (noise_rms > 0 or full_well_e) and rng is None:
        raise GeometryError("quantize needs rng=np.random.default_rng(seed) when noise is requested")
    if full_well_e:
        x = rng.poisson(x * full_well_e) / full_well_e
    x = x * full
    if noise_rms > 0:
        x = x + rng.normal(0.0, noise_rms, size=x.shape)
    out = np.clip(np.rint(x), 0, full)
    return out.astype(np.uint8 if bits <= 8 else np.uint16)


@dataclass
class Simulation:
    """Output of :func:`simulate`.

    Attributes
    ----------
    reference : ndarray (rows, cols) uint8/uint16
        Image of the flat surface.
    frames : ndarray (n_frames, rows, cols) uint8/uint16
    heights_mm : ndarray (n_frames, rows, cols) float32
        True height where each pixel's ray meets the surface.
    times_s : ndarray (n_frames,) float64
    lost : ndarray (n_frames, rows, cols) bool
        Pixels with lost TIR or ray crossing.
    """

    reference: np.ndarray
    frames: np.ndarray
    heights_mm: np.ndarray
    times_s: np.ndarray
    lost: np.ndarray


def simulate(
    surface_or_scene,
    geometry: Geometry,
    shape,
    n_frames: int = 1,
    *,
    pattern: Callable | None = None,
    fps: float = 100.0,
    bits: int = 8,
    noise_rms: float = 0.0,
    supersample: int = 2,
    seed: int = 0,
) -> Simulation:
    """Render a reference and a series of deformed frames with true heights.

    Parameters
    ----------
    surface_or_scene : Surface or object with ``at(t_s) -> Surface`` or callable
        Static surface, or a scene giving the surface at time ``t_s``.
    geometry : Geometry
    shape : (int, int)
    n_frames : int
    pattern : callable, default ``Checkerboard(period_mm=12 * geometry.pixel_mm, edge_softness_mm=pixel_mm)``
    fps : float
        Frame rate; frame i is at ``t = i / fps`` s.
    bits, noise_rms, seed : see :func:`quantize`.
    supersample : int
        Rays per pixel and axis.
    """
    if pattern is None:
        pattern = Checkerboard(period_mm=12 * geometry.pixel_mm, edge_softness_mm=geometry.pixel_mm)
    rng = np.random.default_rng(seed)
    n_rows, n_cols = _check_shape(shape)
    ref, _ = render(FlatSurface(), geometry, shape, pattern, supersample=supersample)
    reference = quantize(ref, bits=bits, noise_rms=noise_rms, rng=rng)
    times = np.arange(n_frames) / float(fps)
    frames = np.empty((n_frames, n_rows, n_cols), dtype=reference.dtype)
    heights = np.empty((n_frames, n_rows, n_cols), dtype=np.float32)
    lost = np.empty((n_frames, n_rows, n_cols), dtype=bool)
    for i, t in enumerate(times):
        if isinstance(surface_or_scene, Surface):
            surf = surface_or_scene
        elif hasattr(surface_or_scene, "at"):
            surf = surface_or_scene.at(t)
        else:
            surf = surface_or_scene(t)
        img, info = render(surf, geometry, shape, pattern, supersample=supersample)
        frames[i] = quantize(img, bits=bits, noise_rms=noise_rms, rng=rng)
        heights[i] = info.height_mm
        lost[i] = info.lost_tir | info.crossing
    return Simulation(reference, frames, heights, times, lost)
