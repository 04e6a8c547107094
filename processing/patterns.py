"""Patterns the ray tracer (:mod:`processing.forward`) samples on the pattern
plane: :class:`Checkerboard`, :class:`CrossedCosines` (pure cosines, no
harmonics), :class:`RandomDots` (re-exported by :mod:`processing.forward`).
Coordinates are pattern-plane mm; intensities in [0, 1].
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .errors import GeometryError

__all__ = ["Checkerboard", "CrossedCosines", "RandomDots"]


@dataclass(frozen=True)
class Checkerboard:
    """Checkerboard on the pattern plane.

    ``period_mm`` is the full period along each side (one dark plus one
    bright square, i.e. twice the square size). Values lie in
    ``mean +- contrast/2``.

    Parameters
    ----------
    period_mm : float
        Full period (2 x square side), mm.
    rotation_deg : float
        Rotation of the board about the vertical, deg.
    edge_softness_mm : float
        0: sharp edges. > 0: ``tanh`` edges about this wide (mm).
    sinusoidal : bool
        Band-limited board ``sin(k x) sin(k y)`` (only the two diagonal carriers).
    mean, contrast : float
        Mean level and peak-to-peak contrast, in [0, 1].
    sharp_radius_mm : float or None
        None: the board has its contrast everywhere. A radius: the board is
        seen sharp only inside a disk of this radius (pattern-plane mm,
        centred at ``sharp_centre_mm``) and blurred to no contrast outside it
        (a shallow depth of field: the level is ``mean`` there, so only the
        camera noise of :func:`quantize` varies).
    sharp_edge_mm : float
        Width of the cosine taper of the contrast across the disk's rim, mm.
    sharp_centre_mm : (float, float)
        Centre (x, y) of the sharp disk on the pattern plane, mm.
    stretch_y : float
        Cell height / cell width along the board's own y (a board printed
        stretched, ``Geometry.pattern_stretch_y``): the period along it is
        ``stretch_y * period_mm``; turned with the board by ``rotation_deg``.
    """

    period_mm: float
    rotation_deg: float = 0.0
    edge_softness_mm: float = 0.0
    sinusoidal: bool = False
    mean: float = 0.5
    contrast: float = 0.8
    sharp_radius_mm: float | None = None
    sharp_edge_mm: float = 2.0
    sharp_centre_mm: tuple = (0.0, 0.0)
    stretch_y: float = 1.0

    def __post_init__(self):
        if not self.period_mm > 0:
            raise GeometryError(f"period_mm must be positive, got {self.period_mm!r}")
        if not self.stretch_y > 0:
            raise GeometryError(f"stretch_y must be positive, got {self.stretch_y!r}")
        if self.edge_softness_mm < 0:
            raise GeometryError(f"edge_softness_mm must be >= 0, got {self.edge_softness_mm!r}")
        if self.sharp_radius_mm is not None and not self.sharp_radius_mm > 0:
            raise GeometryError(f"sharp_radius_mm must be positive or None, got {self.sharp_radius_mm!r}")
        if not self.sharp_edge_mm >= 0:
            raise GeometryError(f"sharp_edge_mm must be >= 0, got {self.sharp_edge_mm!r}")

    def contrast_window(self, x_mm, y_mm) -> np.ndarray | float:
        """Fraction of the contrast seen at pattern-plane (x, y): 1 inside the
        sharp disk, 0 outside, a cosine taper ``sharp_edge_mm`` wide across its rim."""
        if self.sharp_radius_mm is None:
            return 1.0
        r = np.hypot(np.asarray(x_mm, float) - self.sharp_centre_mm[0],
                     np.asarray(y_mm, float) - self.sharp_centre_mm[1])
        if self.sharp_edge_mm == 0:
            return (r <= self.sharp_radius_mm).astype(np.float64)
        t = np.clip((r - self.sharp_radius_mm) / self.sharp_edge_mm + 0.5, 0.0, 1.0)
        return 0.5 + 0.5 * np.cos(np.pi * t)

    @property
    def square_mm(self) -> float:
        return self.period_mm / 2.0

    def __call__(self, x_mm, y_mm) -> np.ndarray:
        """Intensity at pattern-plane coordinates (mm), float64 in [0, 1]."""
        c, s = math.cos(math.radians(self.rotation_deg)), math.sin(math.radians(self.rotation_deg))
        x = np.asarray(x_mm, dtype=np.float64)
        y = np.asarray(y_mm, dtype=np.float64)
        u = c * x + s * y
        v = (-s * x + c * y) / self.stretch_y
        k = 2 * np.pi / self.period_mm
        su, sv = np.sin(k * u), np.sin(k * v)
        if self.sinusoidal:
            val = su * sv
        elif self.edge_softness_mm > 0:
            eps = k * self.edge_softness_mm / 2.0
            val = np.tanh(su / eps) * np.tanh(sv / eps)
        else:
            val = np.sign(su) * np.sign(sv)
        if self.sharp_radius_mm is not None:
            val = val * self.contrast_window(x, y)
        return self.mean + 0.5 * self.contrast * val


@dataclass(frozen=True)
class CrossedCosines:
    """Two crossed pure cosines on the pattern plane: no square-wave harmonics
    and no mixing terms (``k1 +- k2``), only the two carriers.

    ``mean + contrast / 4 (cos(k u) + cos(k v))`` with ``(u, v)`` the
    pattern-plane coordinates rotated by ``rotation_deg``, ``y`` first divided
    by ``stretch_y``; values lie in ``mean +- contrast / 2``.  With
    ``stretch_y = 1 / cos(theta)`` a TIR camera sees both carriers with the
    same period (``period_mm / pixel_mm`` px) at ``rotation_deg`` in the image
    (cf. :class:`Checkerboard` with ``sinusoidal=True``, whose two carriers
    are the board's diagonals).

    Parameters
    ----------
    period_mm : float
        Period of each cosine, mm (along x; ``stretch_y`` times it along y).
    rotation_deg : float
        Direction of the first carrier from the x axis, deg.
    stretch_y : float
        Scale of the pattern along y.
    mean, contrast : float
        Mean level and peak-to-peak contrast, in [0, 1].
    """

    period_mm: float
    rotation_deg: float = 0.0
    stretch_y: float = 1.0
    mean: float = 0.5
    contrast: float = 0.8

    def __post_init__(self):
        if not self.period_mm > 0:
            raise GeometryError(f"period_mm must be positive, got {self.period_mm!r}")
        if not self.stretch_y > 0:
            raise GeometryError(f"stretch_y must be positive, got {self.stretch_y!r}")

    def __call__(self, x_mm, y_mm) -> np.ndarray:
        """Intensity at pattern-plane coordinates (mm), float64 in [0, 1]."""
        c, s = math.cos(math.radians(self.rotation_deg)), math.sin(math.radians(self.rotation_deg))
        x = np.asarray(x_mm, dtype=np.float64)
        y = np.asarray(y_mm, dtype=np.float64) / self.stretch_y
        k = 2 * np.pi / self.period_mm
        return self.mean + 0.25 * self.contrast * (np.cos(k * (c * x + s * y)) + np.cos(k * (-s * x + c * y)))


def _hash_uniform(i, j, seed, salt):
    """Deterministic uniform numbers in [0, 1) for integer cell indices (i, j)."""
    x = (np.asarray(i, np.int64) * 73856093) ^ (np.asarray(j, np.int64) * 19349663) ^ (int(seed) * 83492791 + salt * 2654435761)
    x = x.astype(np.uint64) & np.uint64(0xFFFFFFFF)
    # xorshift-multiply mixing (32 bit)
    x ^= x >> np.uint64(16)
    x = (x * np.uint64(0x7FEB352D)) & np.uint64(0xFFFFFFFF)
    x ^= x >> np.uint64(15)
    x = (x * np.uint64(0x846CA68B)) & np.uint64(0xFFFFFFFF)
    x ^= x >> np.uint64(16)
    return x.astype(np.float64) / 4294967296.0


@dataclass(frozen=True)
class RandomDots:
    """Random-dot pattern on the pattern plane (the usual FS-SS / PIV target).

    Bright Gaussian dots on a dark ground, placed by a jittered grid: the
    plane is cut in square cells ``dot_diameter_mm / sqrt(density)`` wide
    (``density``: fraction of the plane the dots' diameters would cover as
    squares), each holding one dot at a random position inside it.  The
    pattern is defined everywhere (no tiling period) and reproducible from
    ``seed``.

    Parameters
    ----------
    dot_diameter_mm : float
        ``1/e^2`` diameter of a dot (``4 sigma`` of its Gaussian profile), mm.
    density : float
        ``(dot diameter / cell size)^2`` in (0, 1].
    seed : int
    mean, contrast : float
        Ground level is ``mean - contrast / 2``; a dot's peak adds up to
        ``contrast`` (overlapping dots saturate at ``mean + contrast / 2``).
    """

    dot_diameter_mm: float
    density: float = 0.3
    seed: int = 0
    mean: float = 0.5
    contrast: float = 0.8

    def __post_init__(self):
        if not self.dot_diameter_mm > 0:
            raise GeometryError(f"dot_diameter_mm must be positive, got {self.dot_diameter_mm!r}")
        if not 0 < self.density <= 1:
            raise GeometryError(f"density must be in (0, 1], got {self.density!r}")

    @property
    def cell_mm(self) -> float:
        return self.dot_diameter_mm / math.sqrt(self.density)

    def __call__(self, x_mm, y_mm) -> np.ndarray:
        """Intensity at pattern-plane coordinates (mm), float64 in [0, 1]."""
        x = np.asarray(x_mm, dtype=np.float64)
        y = np.asarray(y_mm, dtype=np.float64)
        a = self.cell_mm
        sigma = self.dot_diameter_mm / 4.0
        ci = np.floor(x / a).astype(np.int64)
        cj = np.floor(y / a).astype(np.int64)
        acc = np.zeros(np.broadcast(x, y).shape)
        reach = int(math.ceil(3.0 * sigma / a))
        for di in range(-reach, reach + 1):
            for dj in range(-reach, reach + 1):
                i = ci + di
                j = cj + dj
                dx = (i + _hash_uniform(i, j, self.seed, 1)) * a - x
                dy = (j + _hash_uniform(i, j, self.seed, 2)) * a - y
                acc += np.exp(-(dx * dx + dy * dy) / (2.0 * sigma * sigma))
        val = np.minimum(acc, 1.0)
        return self.mean - 0.5 * self.contrast + self.contrast * val
