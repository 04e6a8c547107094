"""Surfaces the ray tracer (:mod:`processing.forward`) deforms the water by,
and scenes made of them (re-exported by :mod:`processing.forward`).

Defined in the *image frame* (``x`` along increasing column, ``y`` along
increasing row, mm on the water surface, origin where the central camera ray
meets the surface; see :mod:`processing.geometry`). Each surface gives
``height(x_mm, y_mm)`` and the exact ``gradient(x_mm, y_mm) -> (dh/dx,
dh/dy)``, in mm and dimensionless.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from .errors import GeometryError

__all__ = ["Surface", "FlatSurface", "GaussianBump", "Dimple", "WaveField", "SumSurface", "RingWaves", "ApproachingDiscDimple", "TravellingWaves"]


# ============================================================================ surfaces
class Surface:
    """A water surface ``z = h(x, y)`` in the image frame (mm).

    Subclasses implement :meth:`height` and :meth:`gradient`; both take
    broadcastable float arrays ``x_mm, y_mm`` and return float64 arrays.
    """

    def height(self, x_mm, y_mm) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def gradient(self, x_mm, y_mm) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
        raise NotImplementedError

    def height_and_gradient(self, x_mm, y_mm):
        """``(h, dh/dx, dh/dy)`` in one call (subclasses share the work)."""
        gx, gy = self.gradient(x_mm, y_mm)
        return self.height(x_mm, y_mm), gx, gy

    def __add__(self, other: "Surface") -> "SumSurface":
        return SumSurface([self, other])


@dataclass(frozen=True)
class FlatSurface(Surface):
    """The surface at rest, ``h = 0``."""

    def height(self, x_mm, y_mm):
        return np.zeros(np.broadcast(np.asarray(x_mm), np.asarray(y_mm)).shape)

    def gradient(self, x_mm, y_mm):
        z = self.height(x_mm, y_mm)
        return z, z.copy()


@dataclass(frozen=True)
class GaussianBump(Surface):
    """``h = A exp(-((x-x0)^2 + (y-y0)^2) / (2 sigma^2))``; A < 0 is a dimple.

    Parameters
    ----------
    amplitude_mm : float
        Peak height A in mm (5 um = 0.005).
    sigma_mm : float
        Gaussian standard deviation in mm (full width at half maximum is
        ``2.355 sigma``).
    x0_mm, y0_mm : float
        Centre in the image frame, mm.
    """

    amplitude_mm: float
    sigma_mm: float
    x0_mm: float = 0.0
    y0_mm: float = 0.0

    def __post_init__(self):
        if not self.sigma_mm > 0:
            raise GeometryError(f"sigma_mm must be positive, got {self.sigma_mm!r}")

    def height(self, x_mm, y_mm):
        dx = np.asarray(x_mm, dtype=np.float64) - self.x0_mm
        dy = np.asarray(y_mm, dtype=np.float64) - self.y0_mm
        return self.amplitude_mm * np.exp(-(dx * dx + dy * dy) / (2.0 * self.sigma_mm**2))

    def gradient(self, x_mm, y_mm):
        dx = np.asarray(x_mm, dtype=np.float64) - self.x0_mm
        dy = np.asarray(y_mm, dtype=np.float64) - self.y0_mm
        h = self.amplitude_mm * np.exp(-(dx * dx + dy * dy) / (2.0 * self.sigma_mm**2))
        k = -h / self.sigma_mm**2
        return k * dx, k * dy

    def height_and_gradient(self, x_mm, y_mm):
        dx = np.asarray(x_mm, dtype=np.float64) - self.x0_mm
        dy = np.asarray(y_mm, dtype=np.float64) - self.y0_mm
        h = self.amplitude_mm * np.exp(-(dx * dx + dy * dy) / (2.0 * self.sigma_mm**2))
        k = -h / self.sigma_mm**2
        return h, k * dx, k * dy


class Dimple(GaussianBump):
    """A Gaussian dimple of depth ``depth_mm`` (> 0 pushes the surface down)."""

    def __init__(self, depth_mm: float, sigma_mm: float, x0_mm: float = 0.0, y0_mm: float = 0.0):
        super().__init__(-abs(float(depth_mm)), sigma_mm, x0_mm, y0_mm)


@dataclass(frozen=True)
class WaveField(Surface):
    """Sum of plane waves ``sum A cos(kx x + ky y + phase)``.

    Parameters
    ----------
    components : sequence of (amplitude_mm, kx_per_mm, ky_per_mm, phase_rad)
    """

    components: tuple = ()

    def __post_init__(self):
        comps = tuple(tuple(float(v) for v in c) for c in self.components)
        for c in comps:
            if len(c) != 4:
                raise GeometryError(
                    f"each wave component is (amplitude_mm, kx_per_mm, ky_per_mm, phase_rad), got {c!r}"
                )
        object.__setattr__(self, "components", comps)

    @classmethod
    def random(
        cls,
        n_waves: int,
        *,
        amplitude_rms_mm: float,
        wavelength_range_mm: tuple[float, float],
        seed: int,
    ) -> "WaveField":
        """Seeded random field of ``n_waves`` waves, random directions and phases.

        Amplitudes are scaled so that the RMS height is ``amplitude_rms_mm``.
        """
        rng = np.random.default_rng(seed)
        lam = rng.uniform(*wavelength_range_mm, size=n_waves)
        ang = rng.uniform(0, 2 * np.pi, size=n_waves)
        ph = rng.uniform(0, 2 * np.pi, size=n_waves)
        amp = rng.uniform(0.5, 1.0, size=n_waves)
        amp *= amplitude_rms_mm / math.sqrt(0.5 * float(np.sum(amp**2)))
        k = 2 * np.pi / lam
        return cls(tuple(zip(amp, k * np.cos(ang), k * np.sin(ang), ph)))

    def height(self, x_mm, y_mm):
        x = np.asarray(x_mm, dtype=np.float64)
        y = np.asarray(y_mm, dtype=np.float64)
        h = np.zeros(np.broadcast(x, y).shape)
        for a, kx, ky, ph in self.components:
            h += a * np.cos(kx * x + ky * y + ph)
        return h

    def gradient(self, x_mm, y_mm):
        x = np.asarray(x_mm, dtype=np.float64)
        y = np.asarray(y_mm, dtype=np.float64)
        gx = np.zeros(np.broadcast(x, y).shape)
        gy = np.zeros_like(gx)
        for a, kx, ky, ph in self.components:
            s = -a * np.sin(kx * x + ky * y + ph)
            gx += kx * s
            gy += ky * s
        return gx, gy

    def height_and_gradient(self, x_mm, y_mm):
        x = np.asarray(x_mm, dtype=np.float64)
        y = np.asarray(y_mm, dtype=np.float64)
        h = np.zeros(np.broadcast(x, y).shape)
        gx = np.zeros_like(h)
        gy = np.zeros_like(h)
        for a, kx, ky, ph in self.components:
            arg = kx * x + ky * y + ph
            h += a * np.cos(arg)
            s = -a * np.sin(arg)
            gx += kx * s
            gy += ky * s
        return h, gx, gy


@dataclass(frozen=True)
class RingWaves(Surface):
    """Axisymmetric ring waves ``h = A J0(2 pi rho / wavelength)``, ``rho`` the
    distance from ``(x0_mm, y0_mm)`` (a standing capillary-gravity wave about
    a point source: crests every ``wavelength_mm``, amplitude decaying like
    ``rho^-1/2``).

    Parameters
    ----------
    amplitude_mm : float
        Height at the centre, mm.
    wavelength_mm : float
        Distance between crests, mm.
    x0_mm, y0_mm : float
        Centre in the image frame, mm.
    """

    amplitude_mm: float
    wavelength_mm: float
    x0_mm: float = 0.0
    y0_mm: float = 0.0

    def __post_init__(self):
        if not self.wavelength_mm > 0:
            raise GeometryError(f"wavelength_mm must be positive, got {self.wavelength_mm!r}")

    def height(self, x_mm, y_mm):
        from scipy.special import j0

        k = 2 * np.pi / self.wavelength_mm
        rho = np.hypot(np.asarray(x_mm, dtype=np.float64) - self.x0_mm, np.asarray(y_mm, dtype=np.float64) - self.y0_mm)
        return self.amplitude_mm * j0(k * rho)

    def gradient(self, x_mm, y_mm):
        from scipy.special import j1

        k = 2 * np.pi / self.wavelength_mm
        dx = np.asarray(x_mm, dtype=np.float64) - self.x0_mm
        dy = np.asarray(y_mm, dtype=np.float64) - self.y0_mm
        rho = np.hypot(dx, dy)
        # d/drho J0(k rho) = -k J1(k rho); J1(k rho) / rho -> k / 2 at the centre
        kr = k * rho
        ratio = np.where(rho > 0, j1(kr) / np.where(rho > 0, rho, 1.0), 0.5 * k)
        g = -self.amplitude_mm * k * ratio
        return g * dx, g * dy


@dataclass(frozen=True)
class SumSurface(Surface):
    """Sum of surfaces."""

    surfaces: tuple = ()

    def __init__(self, surfaces: Sequence[Surface]):
        object.__setattr__(self, "surfaces", tuple(surfaces))

    def height(self, x_mm, y_mm):
        h = np.zeros(np.broadcast(np.asarray(x_mm), np.asarray(y_mm)).shape)
        for s in self.surfaces:
            h = h + s.height(x_mm, y_mm)
        return h

    def gradient(self, x_mm, y_mm):
        gx = np.zeros(np.broadcast(np.asarray(x_mm), np.asarray(y_mm)).shape)
        gy = np.zeros_like(gx)
        for s in self.surfaces:
            a, b = s.gradient(x_mm, y_mm)
            gx = gx + a
            gy = gy + b
        return gx, gy

    def height_and_gradient(self, x_mm, y_mm):
        h = np.zeros(np.broadcast(np.asarray(x_mm), np.asarray(y_mm)).shape)
        gx = np.zeros_like(h)
        gy = np.zeros_like(h)
        for s in self.surfaces:
            a, b, c = s.height_and_gradient(x_mm, y_mm)
            h = h + a
            gx = gx + b
            gy = gy + c
        return h, gx, gy


# ---------------------------------------------------------------------------- scenes
@dataclass(frozen=True)
class ApproachingDiscDimple:
    """A disc approaching the surface from above pushes a growing dimple.

    ``at(t_s)`` returns the surface at time ``t_s``: a Gaussian dimple of
    width ``radius_mm / 2`` whose depth grows as ``max_depth_mm * (t/t_contact)^2``
    up to ``t_contact_s`` and stays there.
    """

    radius_mm: float = 10.0
    max_depth_mm: float = 0.015
    t_contact_s: float = 1.0
    x0_mm: float = 0.0
    y0_mm: float = 0.0

    def at(self, t_s: float) -> Surface:
        f = min(max(float(t_s) / self.t_contact_s, 0.0), 1.0)
        return GaussianBump(-self.max_depth_mm * f * f, self.radius_mm / 2.0, self.x0_mm, self.y0_mm)

    __call__ = at


@dataclass(frozen=True)
class TravellingWaves:
    """Gravity-capillary plane waves ``A cos(k.r - omega t + phase)``.

    ``omega^2 = g k + (sigma/rho) k^3`` (deep water; g = 9810 mm/s^2 and
    sigma/rho = 7.28e4 mm^3/s^2 for clean water), ``k`` in rad/mm.

    Parameters
    ----------
    components : sequence of (amplitude_mm, kx_per_mm, ky_per_mm, phase_rad)
    """

    components: tuple = ()

    def at(self, t_s: float) -> Surface:
        out = []
        for a, kx, ky, ph in self.components:
            k = math.hypot(kx, ky)
            omega = math.sqrt(9810.0 * k + 7.28e4 * k**3)
            out.append((a, kx, ky, ph - omega * float(t_s)))
        return WaveField(tuple(out))

    __call__ = at
