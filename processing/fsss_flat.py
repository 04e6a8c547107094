"""FS-SS rays through the flat (resting) surface and the layer stack below it,
for :class:`processing.geometry.Geometry` (``geom``: a Geometry with
``setup="fsss"``; its ``fsss_layers``, ``n_air``, ``fsss_camera_distance_mm``)."""

from __future__ import annotations

import numpy as np

__all__ = ["fsss_layers_from_surface", "fsss_flat_trace", "fsss_invert_radial"]


def fsss_layers_from_surface(geom):
    """Layers from the surface down: list of (thickness, n)."""
    return list(reversed(geom.fsss_layers))


def fsss_flat_trace(geom, origin, d):
    """Trace FS-SS rays through a flat surface and the layer stack."""
    s = -origin[..., 2] / d[..., 2]
    x = origin[..., 0] + s * d[..., 0]
    y = origin[..., 1] + s * d[..., 1]
    sin_b = np.hypot(d[..., 0], d[..., 1])  # |d| = 1 and d_z < 0
    with np.errstate(invalid="ignore", divide="ignore"):
        ux = np.where(sin_b > 0, d[..., 0] / np.where(sin_b > 0, sin_b, 1.0), 0.0)
        uy = np.where(sin_b > 0, d[..., 1] / np.where(sin_b > 0, sin_b, 1.0), 0.0)
    rho = np.zeros_like(x)
    for t, n in fsss_layers_from_surface(geom):
        sk = geom.n_air * sin_b / n
        rho = rho + t * sk / np.sqrt(1.0 - sk**2)
    return x + rho * ux, y + rho * uy


def fsss_invert_radial(geom, rho_p):
    """tan(beta) of the air ray that lands at radius rho_p on the pattern (finite L)."""
    L = geom.fsss_camera_distance_mm
    layers = fsss_layers_from_surface(geom)
    tb = rho_p / (L + geom.fsss_apparent_depth_mm)
    for _ in range(30):
        sb = tb / np.sqrt(1 + tb**2)
        f = L * tb - rho_p
        df = L * np.ones_like(tb)
        dsb = (1 + tb**2) ** -1.5
        for t, n in layers:
            sk = geom.n_air * sb / n
            ck = np.sqrt(1.0 - sk**2)
            f = f + t * sk / ck
            df = df + t * (geom.n_air / n) * dsb / ck**3
        step = f / df
        tb = tb - step
        if np.all(np.abs(step) * L < 1e-12):
            break
    return tb
