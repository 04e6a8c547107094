"""FD's bias removal (refinement step 6 of :mod:`processing.reconstruct`):
warp the band-limited reference by the current displacement, demodulate the
frame against it and add the residual (:func:`refine_fd`), and the reference
it warps (:func:`band_limited_reference` on a grid :func:`warp_fine_factor`
times finer than the pixels)."""

from __future__ import annotations

import cv2
import numpy as np

from .fill import nearest_fill_index
from .fullgrid import resize_all
from .unwrap import wrap

__all__ = ["WARP_MAX_INTERPOLATION_ERROR_PX", "WARP_MAP_INTERPOLATION", "linear_interpolation_shift_px", "warp_fine_factor",
           "band_limited_reference", "static_phase", "refine_fd"]

#: Largest error (pixels) that linear interpolation of the refinement's warp
#: may add to the position of the pattern's shortest carrier
#: (:func:`warp_fine_factor`).
WARP_MAX_INTERPOLATION_ERROR_PX = 1e-3
#: The fine warp grid holds at most this many samples (2048^2 frames: twice as fine).
WARP_MAX_FINE_SAMPLES = 1 << 24
#: How the warp maps (u) go from the decimated grid to the pixels: cv2's
#: Lanczos4, whatever the full grid's kernel.  Measured (issue 19, accuracy
#: table): with the full grid's cubic B-spline here instead, FD's refinement
#: lost 0.02-0.06 points on the features 1-3 carrier periods long (narrow
#: bump 1.35 -> 1.38 %, short waves 2.73 -> 2.79 %, 1.5-period bump
#: 0.15 -> 0.18 %) and gained 0.01-0.02 elsewhere; on the pure cosines
#: 0.76 vs 0.77 %.  The final full grid is where the spline pays.
WARP_MAP_INTERPOLATION = cv2.INTER_LANCZOS4


def linear_interpolation_shift_px(period_px: float) -> float:
    """Largest position error (pixels) of linear interpolation on a cosine of
    period ``period_px`` samples: ``max_d |arg((1 - d) + d exp(i k)) / k - d|``.

    0.0102 px at 8 px, 0.0034 px at 11.5 px, 0.0016 px at 20 px: linear
    interpolation pulls the pattern towards the samples by a shift that is
    periodic in the sub-pixel position."""
    k = 2.0 * np.pi / float(period_px)
    frac = np.linspace(0.0, 1.0, 257)
    return float(np.max(np.abs(np.angle((1.0 - frac) + frac * np.exp(1j * k)) / k - frac)))


def warp_fine_factor(freq, shape) -> int:
    """How many times finer than the pixels the refinement warps its smooth reference.

    The warp interpolates linearly (cv2.remap); on a grid ``f`` times finer
    its position error on the shortest carrier is
    ``linear_interpolation_shift_px(f P) / f``.  The smallest ``f`` (1-4) that
    keeps it within :data:`WARP_MAX_INTERPOLATION_ERROR_PX`, and at most
    ``2^24`` fine samples: 3x for 8 px carriers, 2x for the 11.5-20 px of a
    2 mm board at 0.1 mm/px (theta 55 deg), 1x from 27 px on.  Measured
    (docs/processing.md section 6): on the pixels themselves the error of
    linear interpolation became the refinement's own bias, pure cosines of
    8 px with ring waves of 1.8 px: displacement error 1.15 % without
    refinement, 2.26 % with it, 1.08 % 2x finer, 1.00 % 3x (an exact
    quintic spline on the pixels: 1.00 %); 2 mm board, bump 2 um sigma 4 mm:
    0.26 % without, 0.34 % on the pixels, 0.25 % 2x finer.
    """
    freq = np.asarray(freq, dtype=np.float64)
    period = float(1.0 / np.max(np.hypot(freq[:, 0], freq[:, 1])))
    rows, cols = shape
    factor = 1
    while (factor < 4 and (factor + 1) ** 2 * rows * cols <= WARP_MAX_FINE_SAMPLES
           and linear_interpolation_shift_px(factor * period) / factor > WARP_MAX_INTERPOLATION_ERROR_PX):
        factor += 1
    return factor


def band_limited_reference(reference, freq, radius, factor: int = 1) -> np.ndarray:
    """The reference band-limited around its two carriers, sampled ``factor``
    times finer than the pixels (sample ``i`` at pixel ``i / factor``), float32.

    The band (each carrier and its mirror: gain 1 to 1.1 filter radii, cosine
    to 0 at 1.6) holds everything the band-pass can see after warping; being
    band-limited, the finer samples are exact (zero-padded spectrum), no
    interpolation kernel.  No apodization: the warp must not move a border
    window.
    """
    ref = np.asarray(reference, np.float32)
    ref = ref - np.float32(ref.mean())
    rows, cols = ref.shape
    spec = np.fft.rfft2(ref)
    fr = np.fft.fftfreq(rows)[:, None]
    fc = np.fft.rfftfreq(cols)[None, :]
    keep = np.zeros(spec.shape)
    for s in range(2):
        for sign in (1.0, -1.0):
            dist = np.hypot(fr - sign * freq[s, 0], fc - sign * freq[s, 1]) / radius
            t = np.clip((dist - 1.1) / 0.5, 0.0, 1.0)
            keep = np.maximum(keep, 0.5 + 0.5 * np.cos(np.pi * t))
    spec *= keep
    if factor == 1:
        return np.fft.irfft2(spec, s=(rows, cols)).astype(np.float32)
    # the band stays clear of Nyquist (carriers at >= 3 px): pad with zeros
    fine = np.zeros((factor * rows, factor * cols // 2 + 1), spec.dtype)
    pos = (rows + 1) // 2
    fine[:pos, : cols // 2] = spec[:pos, : cols // 2]
    fine[factor * rows - (rows - pos):, : cols // 2] = spec[pos:, : cols // 2]
    return (np.fft.irfft2(fine, s=(factor * rows, factor * cols)) * (factor * factor)).astype(np.float32)



def static_phase(demod, smooth, factor):
    """Phase of the reference against its band-limited copy on the decimated
    grid (wrap-around leakage at the borders): what a right displacement leaves."""
    return np.angle(demod.g0 * np.conj(demod.decimated(np.ascontiguousarray(smooth[::factor, ::factor]))))


def refine_fd(demod, warp_ref, static, g, u, valid, iterations, up, *, interpolation=cv2.INTER_LINEAR, threads=2):
    """Remove the band-pass bias: warp the smooth reference ``warp_ref``
    (``(fine, factor)``) by ``u``, demodulate the frame (decimated signals
    ``g``) against it and add the residual displacement, ``iterations`` times."""
    d = demod
    smooth, factor = warp_ref
    fill = nearest_fill_index(valid)
    relative = getattr(cv2, "WARP_RELATIVE_MAP", None) if factor == 1 else None
    rows, cols = up.shape
    for _ in range(iterations):
        # invalid samples take their nearest valid neighbour's u: a jump to
        # 0 would tear the warped reference and ring through the band-pass
        uf = u if fill is None else u[:, fill[0], fill[1]]
        if fill is not None or not np.isfinite(uf).all():
            uf = np.nan_to_num(uf)
        # sample the smooth reference at r - u(r), written straight into
        # the FFT's input array; relative maps save two full-size passes
        map_c = np.empty(up.shape, np.float32)
        map_r = np.empty(up.shape, np.float32)
        resize_all(lambda src, out: up(src, WARP_MAP_INTERPOLATION, out=out),
                   [(np.float32(-factor) * uf[1], map_c), (np.float32(-factor) * uf[0], map_r)], threads)
        if relative is not None:
            flags = interpolation | relative
        else:
            map_c += np.arange(0, factor * cols, factor, dtype=np.float32)[None, :]
            map_r += np.arange(0, factor * rows, factor, dtype=np.float32)[:, None]
            flags = interpolation

        def warp(dst):
            cv2.remap(smooth, map_c, map_r, flags, dst=dst, borderMode=cv2.BORDER_REFLECT)

        gw = d.decimated_from_windows(d.windows(d.spectrum_of(warp)))
        # minus the static difference between the smooth and the real
        # reference (wrap-around leakage at the borders, where the
        # reference region usually is): zero residual when u is right
        dphi = wrap(np.angle(g * np.conj(gw)) - static)
        du = d.phase_to_displacement(dphi)
        u = u + np.where(valid, du, 0.0)
    return u
