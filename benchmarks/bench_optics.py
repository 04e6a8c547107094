"""Optics figures: accuracy of the height maps against the exact ray tracer, and
solver speed against a sparse direct least-squares baseline (the paper's
intgrad2-style approach) measured in the same run.

    python3 benchmarks/bench_optics.py
"""

import os
import sys
import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from processing.forward import GaussianBump, SumSurface, true_displacement, true_height  # noqa: E402
from processing.geometry import Geometry  # noqa: E402
from processing.height import surface_from_displacement  # noqa: E402


def rel_rms(a, b, where=None):
    w = np.isfinite(a) if where is None else where
    return float(np.sqrt(np.mean((a - b)[w] ** 2)) / np.sqrt(np.mean(b[w] ** 2)))


def best_ms(fn, repeat=5):
    fn()
    t = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        t.append(time.perf_counter() - t0)
    return 1e3 * min(t)


def accuracy():
    surf = SumSurface([GaussianBump(0.005, 2.0, 1.5, -1.0), GaussianBump(-0.003, 1.2, -3.0, 2.5)])
    shape = (256, 256)
    r, c = np.arange(256.0), np.arange(256.0)
    cases = [
        ("TIR telecentric, theta 55, H 300", Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False)),
        ("TIR rows towards camera", Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=True)),
        ("TIR camera at 1.5 m, theta 60", Geometry(theta_deg=60, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False,
                                                   camera_distance_mm=1500.0)),
        ("FS-SS README stack, camera 0.8 m", Geometry(setup="fsss", pixel_mm=0.207, n_water=1.34,
                                                      fsss_layers=((57.0, 1.0003), (12.0, 1.48899), (43.0, 1.34)),
                                                      fsss_camera_distance_mm=800.0)),
    ]
    print("ray-traced displacement -> surface_from_displacement vs true heights (256^2, relative RMS)")
    for name, g in cases:
        s = surf if g.setup == "tir" else GaussianBump(0.02, 4.0, 2.0, -3.0)
        u, _ = true_displacement(s, g, shape)
        res = surface_from_displacement(u, None, g, rows_px=r, cols_px=c, frame_shape=shape)
        print(f"  {name:36s} {100 * rel_rms(res.height_mm, true_height(s, g, shape)):7.3f} %")
    g = cases[2][1]
    u, _ = true_displacement(surf, g, shape)
    tele = Geometry(theta_deg=60, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False)
    res = surface_from_displacement(u, None, tele, rows_px=r, cols_px=c, frame_shape=shape)
    print(f"  {'(same 1.5 m data read as telecentric)':36s} {100 * rel_rms(res.height_mm, true_height(surf, g, shape)):7.3f} %")


def ray_vs_linear():
    """notes.md check: ray-traced u against the paper's linear model."""
    bump = GaussianBump(0.005, 10.0 / 2.355, 1.0, -2.0)  # 5 um, 10 mm FWHM
    shape = (256, 256)
    print("ray-traced u vs paper linear model (5 um, 10 mm FWHM bump, H 300, theta 55, relative RMS)")
    for rows_toward_camera in (False, True):
        g = Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=rows_toward_camera)
        u, _ = true_displacement(bump, g, shape)
        p, H, th, s = g.pixel_mm, g.depth_mm, g.theta, g.row_sign
        x = (np.arange(256) - 127.5) * p
        y = (np.arange(256) - 127.5) * p / np.cos(th)
        X, Y = np.meshgrid(x, y)
        h = bump.height(X, Y)
        hx, hy = bump.gradient(X, Y)
        for sign, label in ((-1, "-2 tan(theta) h (canonical)"), (1, "+2 tan(theta) h (wrong sign)")):
            u_yc = -(2 * H / np.cos(th) ** 2) * (s * hy) + sign * 2 * np.tan(th) * h
            lin = np.stack([s * u_yc * np.cos(th) / p, -2 * H * hx / p])
            err = np.sqrt(np.mean((u - lin) ** 2)) / np.sqrt(np.mean(u**2))
            print(f"  rows_toward_camera={str(rows_toward_camera):5s} {label:30s} {100 * err:7.3f} %")


def sparse_baseline(gr, gc, n):
    """Direct sparse least squares of the Neumann Poisson normal equations."""
    e = np.ones(n)
    D = sp.diags([-e[:-1], e[:-1]], [0, 1], shape=(n - 1, n))
    I = sp.identity(n)
    A = sp.vstack([sp.kron(I, D), sp.kron(D, I)]).tocsc()
    b = np.concatenate([(0.5 * (gc[:, 1:] + gc[:, :-1])).ravel(), (0.5 * (gr[1:] + gr[:-1])).ravel()])
    N = (A.T @ A + 1e-12 * sp.identity(n * n)).tocsc()
    return spla.spsolve(N, A.T @ b)


def speed():
    g = Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False)
    rng = np.random.default_rng(0)
    print("solver speed (best of 5, ms; 2 FFT workers)")
    for n in (128, 256, 512, 1024):
        grid = np.arange(float(n))
        u = (rng.normal(size=(2, n, n)) * 0.1).astype(np.float32)
        rr, cc = np.mgrid[:n, :n]
        hole = np.hypot(rr - 0.6 * n, cc - 0.4 * n) > 0.1 * n
        t_s = best_ms(lambda: surface_from_displacement(u, None, g, rows_px=grid, cols_px=grid, frame_shape=(n, n)))
        t_m = best_ms(lambda: surface_from_displacement(u, hole, g, rows_px=grid, cols_px=grid, frame_shape=(n, n)),
                      repeat=2 if n >= 512 else 5)
        line = f"  {n:5d}^2  spectral {t_s:8.2f}   masked (one hole) {t_m:8.1f}"
        if n <= 256:
            t_b = best_ms(lambda: sparse_baseline(u[0].astype(float), u[1].astype(float), n), repeat=2)
            line += f"   sparse direct baseline {t_b:8.1f}  (spectral {t_b / t_s:6.0f}x faster)"
        print(line)


if __name__ == "__main__":
    ray_vs_linear()
    accuracy()
    speed()
