"""FD's bias removal (refinement step 6 of :mod:`processing.reconstruct`):
warp the band-limited reference by the current displacement, demodulate the
frame against it and add the residual (:func:`refine_fd`).  The warp is exact
in the carriers (:class:`WarpReference`: each carrier's slowly varying complex
envelope is interpolated, its carrier phase computed, :func:`sample_band_limited`).
Also the rule for a linearly interpolated grid fine enough for a pattern
(:func:`warp_fine_factor`, image matching's reference) and the band-limited
reference itself (:func:`band_limited_reference`)."""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numba
import numpy as np

from .angle_kernels import angle_of_product
from .fill import nearest_fill_index
from .fullgrid import resize_all, run_pair
from .unwrap import wrap

__all__ = ["WARP_MAX_INTERPOLATION_ERROR_PX", "WARP_MAP_INTERPOLATION", "linear_interpolation_shift_px", "warp_fine_factor",
           "band_limited_reference", "WarpReference", "warp_reference", "modulate", "sample_band_limited",
           "refine_fd", "static_phase", "refine_fd_tapered"]

#: Largest error (pixels) that linear interpolation of a warped reference may
#: add to the position of the pattern's shortest carrier (:func:`warp_fine_factor`:
#: image matching's reference grid).
WARP_MAX_INTERPOLATION_ERROR_PX = 1e-3
#: A fine warp grid holds at most this many samples (2048^2 frames: twice as fine).
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
    """How many times finer than the pixels a reference must be sampled for a linear warp of it (image
    matching's reference, :func:`processing.dic_nodes.fine_factor`; FD's refinement warped its band-limited
    reference this way until :func:`warp_reference` made that warp exact in the carriers).

    A warp that interpolates linearly (cv2.remap) on a grid ``f`` times finer has
    a position error on the shortest carrier of
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


def _carrier_bands(fr, fc, freq, radius):
    """``(keep, nearest)`` on the frequency grid ``fr`` x ``fc`` (cycles/px): the
    band every carrier and its mirror keep (gain 1 to 1.1 filter radii, cosine to
    0 at 1.6) and which of +k1, +k2, -k1, -k2 (0-3) is nearest each frequency."""
    keep = np.zeros(np.broadcast_shapes(fr.shape, fc.shape))
    best = np.full(keep.shape, np.inf)
    nearest = np.zeros(keep.shape, np.int8)
    for sign, base in ((1.0, 0), (-1.0, 2)):
        for s in range(2):
            dist = np.hypot(fr - sign * freq[s, 0], fc - sign * freq[s, 1]) / radius
            t = np.clip((dist - 1.1) / 0.5, 0.0, 1.0)
            keep = np.maximum(keep, 0.5 + 0.5 * np.cos(np.pi * t))
            closer = dist < best
            nearest[closer] = base + s
            best = np.minimum(best, dist)
    return keep, nearest


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
    spec *= _carrier_bands(np.fft.fftfreq(rows)[:, None], np.fft.rfftfreq(cols)[None, :], freq, radius)[0]
    if factor == 1:
        return np.fft.irfft2(spec, s=(rows, cols)).astype(np.float32)
    # the band stays clear of Nyquist (carriers at >= 3 px): pad with zeros
    fine = np.zeros((factor * rows, factor * cols // 2 + 1), spec.dtype)
    pos = (rows + 1) // 2
    fine[:pos, : cols // 2] = spec[:pos, : cols // 2]
    fine[factor * rows - (rows - pos):, : cols // 2] = spec[pos:, : cols // 2]
    return (np.fft.irfft2(fine, s=(factor * rows, factor * cols)) * (factor * factor)).astype(np.float32)


class WarpReference(NamedTuple):
    """What FD's refinement warps, built once from the reference (:func:`warp_reference`).

    The band-limited reference is ``2 Re sum_s e_s(r) exp(i k_s . r)``: each
    carrier's band (the frequencies nearest ``+k_s``) is a complex envelope
    ``e_s``, slow where the pattern is regular, on the carrier ``k_s``.
    """

    #: (rows, cols, 4) float32: Re e_1, Im e_1, Re e_2, Im e_2.
    envelopes: np.ndarray
    #: (2, rows, cols) float32: cos(k_s . r), sin(k_s . r) per carrier, r = (row, col) px.
    carrier_cos: np.ndarray
    carrier_sin: np.ndarray
    #: (2, 2) float32: k_s = 2 pi (row, col) frequency, rad/px.
    wavevectors: np.ndarray
    #: (rows, cols) float32: the band-limited reference itself (what a zero displacement gives).
    band_limited: np.ndarray


def warp_reference(reference, freq, radius, *, continued: bool = True) -> WarpReference:
    """The reference band-limited around its carriers (:func:`band_limited_reference`'s band, mean
    removed) as carrier envelopes and carriers, for :func:`sample_band_limited`.

    Why (issue 19): warped by linear interpolation, even from a grid 3x finer
    than the pixels, the reference's 8 px carriers moved by up to 0.001 px with
    the sub-pixel position (plus cv2.remap's 1/32-sample position steps), a bias
    the refinement added to u: on ray-traced pure cosines of 8 px at 512^2 the
    FD refinement made the displacement worse than none (0.35 against 0.27 %,
    float frames, 8 % margin).  Only the envelope is interpolated now, and it
    is slow; the carrier phase at the warped point is computed: 0.24 %.

    The band is cut from the transform of the reference continued beyond its
    border (:class:`processing.continuation.PatternContinuation`), not of the
    reference alone: the FFT joins each border to the opposite one, and that
    jump rang through the envelopes near the border, where the warp then moved
    the ringing with the pattern.  With it FD's refinement went to a biased
    fixed point there (the pure cosines' displacement 0.70 % after 2
    iterations, 0.79 % after 8; continued 0.67 / 0.53 %), and was worse than
    no refinement on the deep dimple of the accuracy table.  ``continued=False``
    keeps the reference alone (image matching's start, :func:`refine_fd_tapered`).
    """
    from .continuation import PatternContinuation

    ref = np.asarray(reference, np.float64)
    rows, cols = ref.shape
    if continued:
        cont = PatternContinuation(ref.shape, freq)
        padded, (top, left) = cont(ref).astype(np.float64), cont.offset
    else:
        padded, (top, left) = ref - ref.mean(), (0, 0)
    R, C = padded.shape
    spec = np.fft.fft2(padded)
    keep, nearest = _carrier_bands(np.fft.fftfreq(R)[:, None], np.fft.fftfreq(C)[None, :], freq, radius)
    spec *= keep
    inside = (slice(top, top + rows), slice(left, left + cols))
    wavevectors = (2.0 * np.pi * np.asarray(freq, np.float64))
    r = np.arange(rows, dtype=np.float64)[:, None]
    c = np.arange(cols, dtype=np.float64)[None, :]
    envelopes = np.empty((rows, cols, 4), np.float32)
    carrier_cos = np.empty((2, rows, cols), np.float32)
    carrier_sin = np.empty((2, rows, cols), np.float32)
    band_limited = np.zeros((rows, cols), np.float64)
    for s in range(2):
        # the frequencies nearest +k_s; their mirrors (nearest -k_s) are the conjugate
        analytic = np.fft.ifft2(np.where(nearest == s, spec, 0.0))[inside]
        band_limited += 2.0 * analytic.real
        phase = wavevectors[s, 0] * r + wavevectors[s, 1] * c
        envelope = analytic * np.exp(-1j * phase)
        envelopes[..., 2 * s], envelopes[..., 2 * s + 1] = envelope.real, envelope.imag
        carrier_cos[s], carrier_sin[s] = np.cos(phase), np.sin(phase)
    return WarpReference(envelopes, carrier_cos, carrier_sin, wavevectors.astype(np.float32),
                         band_limited.astype(np.float32))


def modulate(xp, envelopes, plan: WarpReference, offset_rows, offset_cols):
    """``2 Re sum_s e_s exp(i k_s . (r + offset))``: envelopes already sampled at
    ``r + offset`` (shape ``(..., rows, cols, 4)``, offsets ``(..., rows, cols)``
    px) back on their carriers, float32; ``xp`` is numpy or cupy."""
    k = plan.wavevectors
    out = None
    for s in range(2):
        phi = k[s, 0] * offset_rows + k[s, 1] * offset_cols
        cos_phi, sin_phi = xp.cos(phi), xp.sin(phi)
        cc, cs = plan.carrier_cos[s], plan.carrier_sin[s]
        # exp(i k.(r + offset)) = (cc + i cs)(cos_phi + i sin_phi)
        re = cc * cos_phi - cs * sin_phi
        im = cc * sin_phi + cs * cos_phi
        term = envelopes[..., 2 * s] * re - envelopes[..., 2 * s + 1] * im
        out = term if out is None else out + term
    return out * np.float32(2.0)


#: Polynomial sine and cosine on [-pi/4, pi/4] (:func:`_modulate_rows`): ``sin r = r + r^3 (S0 + S1 z + S2 z^2)``,
#: ``cos r = 1 - z / 2 + z^2 (C0 + C1 z + C2 z^2)``, ``z = r^2``; coefficients fitted here by iteratively
#: reweighted least squares on Chebyshev nodes (largest error 1.8e-9 for the sine, 1e-10 for the cosine, in
#: float64: below float32's rounding).
_SIN = (-1.6666650719e-01, 8.3319815580e-03, -1.9495987503e-04)
_COS = (4.1666646840e-02, -1.3887366647e-03, 2.4438384123e-05)


@numba.njit(nogil=True, cache=True, fastmath={"contract"})
def _modulate_rows(envelopes, offset_rows, offset_cols, carrier_cos, carrier_sin, k, out, r0, r1):  # pragma: no cover
    """:func:`modulate` (the GPU chain's, written for any array module) of rows ``r0 <= i < r1``, compiled.

    Each row in two sweeps the compiler vectorises: the phase ``k . offset`` of both carriers, its sine and
    cosine (reduced to [-pi/4, pi/4] by three-part pi/2, exact for ``|k . offset|`` up to about 1e4 rad, then
    the polynomials :data:`_SIN`, :data:`_COS`, the quadrant by arithmetic, no branch), then the sum.  At
    1024^2 on a quiet machine, one thread: 5.0 ms, where the same pass with ``np.sin``/``np.cos`` a pixel took
    12.6 ms (NumPy's about 30 full-size passes 29 ms); within 1.4e-6 of the signal's largest value of it
    (float32 rounding; tests/processing/test_pure_cosine.py compares with :func:`modulate`)."""
    cols = out.shape[1]
    sines = np.empty((2, cols), np.float32)
    cosines = np.empty((2, cols), np.float32)
    two_over_pi = np.float32(0.636619772367581343)
    # pi / 2 split into its first 9 significant bits, the next 11, and the float32 rest: the products
    # of the first two with a quarter count below 2^13 (phases up to 1e4 rad) are exact in float32
    p1, p2, p3 = np.float32(1.5703125), np.float32(4.837512969970703e-4), np.float32(7.549790126404332e-8)
    s0, s1, s2 = np.float32(_SIN[0]), np.float32(_SIN[1]), np.float32(_SIN[2])
    c0, c1, c2 = np.float32(_COS[0]), np.float32(_COS[1]), np.float32(_COS[2])
    one, half, two = np.float32(1.0), np.float32(0.5), np.float32(2.0)
    for i in range(r0, r1):
        rows_i, cols_i = offset_rows[i], offset_cols[i]
        for s in range(2):
            k0, k1 = k[s, 0], k[s, 1]
            for j in range(cols):
                phi = k0 * rows_i[j] + k1 * cols_i[j]
                quarter = np.floor(phi * two_over_pi + half)
                r = ((phi - quarter * p1) - quarter * p2) - quarter * p3
                z = r * r
                sin_r = r + r * z * (s0 + z * (s1 + z * s2))
                cos_r = one - half * z + z * z * (c0 + z * (c1 + z * c2))
                q = np.int32(quarter) & 3
                odd = np.float32(q & 1)  # quadrants 1 and 3 swap sine and cosine
                sines[s, j] = (sin_r + odd * (cos_r - sin_r)) * np.float32(1 - (q & 2))
                cosines[s, j] = (cos_r + odd * (sin_r - cos_r)) * np.float32(1 - ((q + 1) & 2))
        env, out_i = envelopes[i], out[i]
        for j in range(cols):
            acc = np.float32(0.0)
            for s in range(2):
                cc, cs = carrier_cos[s, i, j], carrier_sin[s, i, j]
                er, ei = env[j, 2 * s], env[j, 2 * s + 1]
                # Re((er + i ei)(cc + i cs)(cos_phi + i sin_phi))
                a = er * cc - ei * cs
                b = er * cs + ei * cc
                acc += a * cosines[s, j] - b * sines[s, j]
            out_i[j] = two * acc


def sample_band_limited(plan: WarpReference, offset_rows, offset_cols, out, *, interpolation=cv2.INTER_LINEAR,
                        threads=1):
    """The band-limited reference at ``r + offset`` (offsets (rows, cols) float32,
    px) into ``out``: envelopes interpolated (cv2.remap, reflecting border), carriers
    exact (:func:`modulate`, compiled; two threads on large frames when ``threads`` > 1)."""
    relative = getattr(cv2, "WARP_RELATIVE_MAP", None)  # OpenCV >= 4.10: no full-size grid + offset pass
    if relative is None:
        rows, cols = offset_rows.shape
        sampled = cv2.remap(plan.envelopes, offset_cols + np.arange(cols, dtype=np.float32)[None, :],
                            offset_rows + np.arange(rows, dtype=np.float32)[:, None], interpolation,
                            borderMode=cv2.BORDER_REFLECT)
    else:
        sampled = cv2.remap(plan.envelopes, offset_cols, offset_rows, interpolation | relative,
                            borderMode=cv2.BORDER_REFLECT)
    args = (sampled, offset_rows, offset_cols, plan.carrier_cos, plan.carrier_sin, plan.wavevectors, out)
    half = out.shape[0] // 2
    run_pair(out.shape, lambda: _modulate_rows(*args, 0, half), lambda: _modulate_rows(*args, half, out.shape[0]),
             threads)
    return out


#: Decimated samples next to a masked one whose displacement FD's bias removal leaves as measured
#: (:func:`_remove_bias`): about the reach of the band-pass's impulse response. There the frame's band
#: holds what the mask hides (a blank patch has no carrier) and the warped reference's does not, so the
#: phase left between them is not the band-pass's bias. Measured (5 Dec 2026), FD's refinement:
#: ``bench_processing.py --masked 4`` (256^2, a 40 x 70 px blank patch, four placements; 0 / 1 / 2 / 3 / 4
#: samples, no refinement in brackets) 2 um bump 0.522 / 0.527 / 0.512 / 0.509 / 0.500 (0.491), 12-30 mm
#: waves 0.701 / 0.550 / 0.548 / 0.581 / 0.617 (0.673), noisy dimple 0.332 / 0.278 / 0.266 / 0.282 / 0.295
#: (0.283), 1.5-period bump 0.894 / 0.874 / 0.766 / 0.762 / 0.787 (0.748), 6-12 mm waves 2.850 / 2.738 /
#: 2.837 / 3.146 / 3.441 (6.482) %: with 0 worse than none on four of eight cases, with 2 on none by the
#: paired verdict (the two bumps within 0.02 points); ray crossings (256^2, two placements, 0 -> 2): a
#: 10 um spike 4.130 -> 3.651 % (none 4.120), a 20 um dimple 4.673 -> 4.276 % (4.667); image matching
#: started from it: 12-30 mm waves beside the patch 0.669 -> 0.614 %, the spike 2.489 -> 1.991 %. Worse on
#: the golden 128^2 deeper bump, 45 % of it masked by ray crossings (FD 12.24 -> 12.91 %), where two samples
#: are a large part of a 20-sample grid. Frames without masked samples unchanged.
MASK_REACH_SAMPLES = 2


def _remove_bias(plan: WarpReference, u, valid, iterations, up, correction, *, interpolation, threads):
    """``iterations`` times: the band-limited reference (``plan``) warped by ``u``
    and ``correction(write)`` (the displacement left between frame and warped
    reference, ``write(dst)`` putting the warped reference into ``dst``) added to
    ``u`` on the ``valid`` samples farther than :data:`MASK_REACH_SAMPLES` from an
    invalid one."""
    fill = nearest_fill_index(valid)
    corrected = valid  # beyond the band-pass's reach from masked samples (the frame's border is not one)
    if MASK_REACH_SAMPLES > 0 and not valid.all():  # (0 iterations would erode until nothing changes)
        from scipy import ndimage

        corrected = ndimage.binary_erosion(valid, iterations=MASK_REACH_SAMPLES, border_value=1)
    for _ in range(iterations):
        # invalid samples take their nearest valid neighbour's u: a jump to
        # 0 would tear the warped reference and ring through the band-pass
        uf = u if fill is None else u[:, fill[0], fill[1]]
        if fill is not None or not np.isfinite(uf).all():
            uf = np.nan_to_num(uf)
        # the reference sampled at r - u(r)
        off_c = np.empty(up.shape, np.float32)
        off_r = np.empty(up.shape, np.float32)
        resize_all(lambda src, out: up(src, WARP_MAP_INTERPOLATION, out=out),
                   [(np.negative(uf[1], dtype=np.float32), off_c), (np.negative(uf[0], dtype=np.float32), off_r)],
                   threads)
        du = correction(lambda dst: sample_band_limited(plan, off_r, off_c, dst, interpolation=interpolation,
                                                        threads=threads))
        u = u + np.where(corrected, du, 0.0)
    return u


def refine_fd(demod, plan: WarpReference, continued, frame, phase, u, valid, iterations, up, *,
              interpolation=cv2.INTER_LINEAR, threads=2):
    """FD's displacement on the frame continued beyond its border, then its band-pass bias removed.

    First the frame's phase is measured again on the frame and the reference
    continued beyond their border (``continued``, a
    :class:`processing.continuation.ContinuedSignals`), unwrapped by the
    tapered demodulation's ``phase`` (they differ by far less than pi), and
    ``u`` of the ``valid`` samples is taken from it.  Then, ``iterations``
    times: the band-limited reference (``plan``, :func:`warp_reference`) is
    warped by ``u``, demodulated continued the same way, and the phase left
    between frame and warped reference is added to ``u`` as displacement.
    At the right ``u`` what is left is the static difference between the
    reference and its band-limited copy (:meth:`ContinuedSignals.static_phase`),
    which is subtracted."""
    g_frame = continued.signals(frame)
    tapered = np.nan_to_num(np.asarray(phase, np.float32))
    measured = continued.phase_difference(g_frame, continued.g0)
    u = np.where(valid, demod.phase_to_displacement((tapered + wrap(measured - tapered)).astype(np.float32)), u)
    if iterations <= 0:
        return u
    static = continued.static_phase(plan.band_limited)
    model = np.empty(up.shape, np.float32)

    def correction(write):
        write(model)
        dphi = wrap(continued.phase_difference(g_frame, continued.signals(model)) - static)
        return demod.phase_to_displacement(dphi.astype(np.float32))

    return _remove_bias(plan, u, valid, iterations, up, correction, interpolation=interpolation, threads=threads)


def static_phase(demod, band_limited):
    """Phase of the reference against its band-limited copy (``warp_reference(...,
    continued=False)``) on the decimated grid (wrap-around leakage at the borders):
    what a right displacement leaves in :func:`refine_fd_tapered`."""
    return np.angle(demod.g0 * np.conj(demod.decimated(np.ascontiguousarray(band_limited))))


def refine_fd_tapered(demod, plan: WarpReference, static, g, u, valid, iterations, up, *,
                      interpolation=cv2.INTER_LINEAR, threads=2):
    """FD's bias removal through the demodulator's own taper: the band-limited reference of the
    reference alone (``plan``, ``warp_reference(..., continued=False)``) warped by ``u``,
    demodulated as the frame was (decimated signals ``g``), the phase left over minus ``static``
    (:func:`static_phase`) added to ``u``, ``iterations`` times.

    What image matching starts from (``processing.chain_image``): its own Gauss-Newton solve
    moves the border's heights, and the continued border (:func:`refine_fd`) cost it 21-23 % of
    its time at 1024^2 for 0.00-0.05 points of its figures (docs/processing.md section 6)."""
    d = demod

    def correction(write):
        gw = d.decimated_from_windows(d.frame_windows(write=write))
        return d.phase_to_displacement(wrap(angle_of_product(g, np.conj(gw)) - static))

    return _remove_bias(plan, u, valid, iterations, up, correction, interpolation=interpolation, threads=threads)
