"""Where FD's border error comes from, and what extending the frame beyond its border does (issue 19).

Run from the repository root::

    python3 benchmarks/bench_border_extension.py                 # both cases at 256^2, about 30 s
    python3 benchmarks/bench_border_extension.py --case cosines --size 512

A study, not the pipeline: a plain Fourier demodulation written here (the
project's flat-top band-pass of ``Demodulator``: gain 1 to 0.8 radii, cosine
to 0 at ``radius = min(0.7 |k|, |k1 +- k2| / 2)``; full-size inverse FFTs,
phase against the reference, ``u = -K^-1 phi``; no unwrapping, no mask, no
refinement) on ray-traced pairs made by the project's forward model, with
each border treatment applied to frame and reference alike:

* ``taper P``: the live grid's (``demodulation.tukey``, a cosine taper ``P``
  pixels wide at each border; the pipeline uses one carrier period);
* ``Gerchberg pad p it n``: the image placed in a frame ``p`` pixels larger
  on each side, then ``n`` times: band-limit the whole padded frame to the
  carriers' bands (outer taper ``p / 2``) and put the measured pixels back
  (a band-limited extrapolation of the pattern beyond the border);
* ``extend pad p d0 d it n``: the pad filled once with the pattern itself,
  each carrier's envelope from the tapered demodulation taken at the
  nearest point ``d0`` pixels inside the border and put back on its
  carrier, then ``n`` Gerchberg iterations.  The pipeline's full grid does
  this without the iterations (``processing/continuation.py``, which
  measures the envelopes by a Gaussian window over the pixels instead of
  a transform: one transform less).

Printed: the relative RMS displacement error over the interior (8 % margin,
the accuracy table's rule) and by distance from the frame's edge in carrier
periods (each band's RMS error over the interior's RMS displacement, %), and
how many full-size transforms each treatment costs per image against the
taper's one.

Cases: ``cosines`` is bench_pure_cosine.py's pair (crossed pure cosines of
8 px rotated 9 deg, Bessel-J0 ring waves 5 periods long, 1.8 px; the goal
of issue 19 is <= 0.6 % there for every full-grid method); ``board`` the
2 mm board of the accuracy table with random waves 12-30 mm, 1 um rms (the
held-out case of bench_processing.py), whose border band is where the
pipeline's heights are pinned by default.
"""

from __future__ import annotations

import argparse
import math
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from benchmarks.bench_pure_cosine import BANDS, band_errors  # noqa: E402
from processing import forward as F  # noqa: E402
from processing.carriers import find_carriers  # noqa: E402
from processing.demodulation import tukey  # noqa: E402
from processing.geometry import Geometry  # noqa: E402

GEOMETRY = Geometry(theta_deg=55, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False)


def case_pair(case, n):
    """``(reference, frame, true displacement (2, n, n) px)`` of a ray-traced case at ``n``^2."""
    if case == "cosines":
        pattern = F.CrossedCosines(period_mm=0.8, rotation_deg=9.0, stretch_y=1.0 / math.cos(math.radians(55.0)))
        surface = F.RingWaves(amplitude_mm=0.00033, wavelength_mm=7.0)
    else:
        pattern = F.Checkerboard(period_mm=2.0, edge_softness_mm=0.1)
        surface = F.WaveField.random(6, amplitude_rms_mm=0.001, wavelength_range_mm=(12, 30), seed=10)
    ref, _ = F.render_tir(F.FlatSurface(), GEOMETRY, (n, n), pattern, supersample=2)
    img, _ = F.render_tir(surface, GEOMETRY, (n, n), pattern, supersample=2)
    u_true, _ = F.true_displacement(surface, GEOMETRY, (n, n))
    return ref, img, u_true


class Study:
    """The plain demodulation of one reference's carriers, with the border treatments above."""

    def __init__(self, reference):
        self.n = reference.shape[0]
        self.freq = np.asarray(find_carriers(reference).freq, np.float64)
        f = self.freq
        self.k = 2.0 * np.pi * f
        self.period = float(1.0 / np.max(np.hypot(f[:, 0], f[:, 1])))
        dc = float(np.min(np.hypot(f[:, 0], f[:, 1])))
        pair = min(float(np.hypot(*(f[0] - f[1]))), float(np.hypot(*(f[0] + f[1]))))
        self.radius = min(0.7 * dc, 0.5 * pair)

    def gains(self, size):
        """Each carrier's flat-top band-pass on a ``size``^2 FFT grid."""
        fr = np.fft.fftfreq(size)[:, None]
        fc = np.fft.fftfreq(size)[None, :]
        out = []
        for s in range(2):
            d = np.hypot(fr - self.freq[s, 0], fc - self.freq[s, 1]) / self.radius
            g = np.where(d <= 0.8, 1.0, 0.0)
            roll = (d > 0.8) & (d < 1.0)
            g[roll] = 0.5 + 0.5 * np.cos(np.pi * (d[roll] - 0.8) / 0.2)
            out.append(g)
        return out

    def tapered(self, image, taper_px):
        """Both analytic signals of ``image`` (mean removed) under a Tukey taper ``taper_px`` wide."""
        n = self.n
        w = tukey(n, taper_px)[:, None] * tukey(n, taper_px)[None, :] if taper_px else 1.0
        spec = np.fft.fft2((image - image.mean()) * w)
        return [np.fft.ifft2(spec * g) for g in self.gains(n)]

    def extended(self, image, pad, iterations, d0=None):
        """Both analytic signals of ``image`` demodulated inside a frame ``pad`` px larger each side:
        the pad zero (``d0`` None) or filled with the pattern continued from ``d0`` px inside the
        border, then ``iterations`` Gerchberg steps (band-limit, put the measured pixels back)."""
        n, size = self.n, self.n + 2 * pad
        x0 = image - image.mean()
        big = np.zeros((size, size))
        if d0 is not None:
            g = self.tapered(image, self.period)
            near = np.clip(np.arange(size) - pad, d0, n - 1 - d0)
            r = np.arange(size, dtype=np.float64)[:, None] - pad
            c = np.arange(size, dtype=np.float64)[None, :] - pad
            rr, cc = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
            for s in range(2):
                envelope = g[s] * np.exp(-1j * (self.k[s, 0] * rr + self.k[s, 1] * cc))
                big += 2.0 * (envelope[np.ix_(near, near)] * np.exp(1j * (self.k[s, 0] * r + self.k[s, 1] * c))).real
        inside = (slice(pad, pad + n), slice(pad, pad + n))
        big[inside] = x0
        outer = tukey(size, pad / 2)[:, None] * tukey(size, pad / 2)[None, :]
        gains = self.gains(size)
        band = np.clip(sum(gains) + sum(np.roll(g[::-1, ::-1], 1, (0, 1)) for g in gains), 0.0, 1.0)
        x = big
        for _ in range(iterations):
            x = np.fft.ifft2(np.fft.fft2(x * outer) * band).real
            x[inside] = x0
        spec = np.fft.fft2(x * outer)
        return [np.fft.ifft2(spec * g)[inside] for g in gains]

    def displacement(self, g, g0):
        phase = np.stack([np.angle(a * np.conj(b)) for a, b in zip(g, g0)])
        return np.einsum("ij,jrc->irc", -np.linalg.inv(self.k), phase)


def errors(u, u_true, period):
    """``(8 % interior, [by band])``: relative RMS displacement errors, % (bench_pure_cosine's)."""
    interior, bands, _ = band_errors(u, u_true, period)
    return interior, bands


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", choices=("cosines", "board", "both"), default="both")
    ap.add_argument("--size", type=int, default=256)
    args = ap.parse_args(argv)
    for case in (("cosines", "board") if args.case == "both" else (args.case,)):
        ref, img, u_true = case_pair(case, args.size)
        st = Study(ref)
        p = st.period
        print(f"{case}, {args.size}^2, carrier period {p:.2f} px, max |u| {np.hypot(*u_true).max():.2f} px")
        print(f"  {'border treatment':34s} {'8 %':>6s}  by distance from the edge (carrier periods):"
              f" {'  '.join(f'{lo}-{hi}' for lo, hi in BANDS)}   FFTs")
        d0 = int(round(p / 2))
        variants = [(f"taper {t:g} px", lambda im, t=t: st.tapered(im, t), 1) for t in (0.0, p, 2 * p)]
        variants += [(f"Gerchberg pad {pad} it {it}", lambda im, pad=pad, it=it: st.extended(im, pad, it), 1 + 2 * it)
                     for pad, it in ((32, 0), (32, 10), (32, 30))]
        variants += [(f"extend pad 32 d0 {d0} it {it}", lambda im, it=it: st.extended(im, 32, it, d0), 2 + 2 * it)
                     for it in (0, 3)]
        for label, demod, ffts in variants:
            u = st.displacement(demod(img), demod(ref))
            inner, bands = errors(u, u_true, p)
            print(f"  {label:34s} {inner:6.2f}  " + " ".join(f"{b:7.2f}" for b in bands) + f"   {ffts:3d}")
        print()


if __name__ == "__main__":
    main()
