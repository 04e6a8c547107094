"""Binning a frame 2 x 2 for the live grid's demodulation (``Demodulator(binning=2)``,
``ReconstructOptions.live_binning``): the pyramid that bins (:func:`bin_pyramid`),
its gain (:func:`pyramid_gain`) and where what it folds leaves the carriers' bands
as they are (:func:`binned_bands_clear`).  docs/processing.md section 2 has the
measurements."""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["BINNED_BAND_EDGE", "BINNED_ALIAS_WEIGHT", "BINNED_ALIAS_CLEARANCE", "bin_pyramid",
           "binned_bands_clear", "check_binning", "pyramid_gain"]

#: A binned Demodulator's carrier bands end at most this far from DC along each
#: axis, cycles per pixel of the frame: the 2 x 2 pyramid (cv2.pyrDown) folds
#: 0.5 - f onto f, and passes 0.12 at 0.3 against 0.43 at 0.2 (so white noise
#: aliased into a band adds at most 8 % of its power at the band's edge).
BINNED_BAND_EDGE = 0.2
#: A harmonic of the pattern folded by the binning into a band is harmless when
#: the pyramid has taken it, times the largest share a harmonic of that order
#: can have (``1 / (i j)``, a checkerboard of any duty cycle), below this
#: fraction of the carrier (the filter undoes the pyramid's gain in the band).
BINNED_ALIAS_WEIGHT = 0.005
#: ... or when it lands this many filter radii from both carriers (outside the
#: band, beyond the roll-off: a 60 %-duty board's (1, 4) harmonic folded to 1.28
#: radii leaves the binned phases within 0.16 % of the unbinned, as on a 50 % board).
BINNED_ALIAS_CLEARANCE = 1.25


def pyramid_gain(f) -> np.ndarray:
    """Gain of cv2.pyrDown's 5-tap kernel ``[1 4 6 4 1] / 16`` along one axis at
    frequency ``f`` (cycles per pixel of its input): 1 at DC, 0.25 at 0.25, 0 at 0.5."""
    return np.cos(np.pi * np.asarray(f, np.float64)) ** 4  # ((1 + cos 2 pi f) / 2)^2


def binned_bands_clear(freq, radius: float, shape) -> bool:
    """Whether a frame of ``shape`` binned 2 x 2 (cv2.pyrDown) keeps both
    carriers' bands (``freq`` (2, 2) cycles/px, filter ``radius`` cycles/px)
    as they are: both sides even, every band within :data:`BINNED_BAND_EDGE`
    of DC along each axis, and every harmonic of the pattern (the lattice
    ``i a + j b``, ``a, b = (k1 +- k2) / 2``, ``|i|, |j| <= 7``) that the
    binning folds either weak enough there (:data:`BINNED_ALIAS_WEIGHT`) or
    clear of both bands (:data:`BINNED_ALIAS_CLEARANCE`).  A board of 8 px
    period puts its 3rd harmonic at 0.375 cycles/px, which folds onto the
    carrier at 0.125: not clear."""
    rows, cols = shape
    if rows % 2 or cols % 2 or min(rows, cols) < 64:
        return False
    k = np.asarray(freq, np.float64)
    if np.any(np.abs(k) + radius > BINNED_BAND_EDGE):
        return False
    a, b = 0.5 * (k[0] + k[1]), 0.5 * (k[0] - k[1])
    carriers = np.concatenate([k, -k])
    for i in range(-7, 8):
        for j in range(-7, 8):
            p = i * a + j * b
            folded = p - 0.5 * np.round(2.0 * p)
            if np.allclose(folded, p):
                continue  # not folded: the filter's own radius rule keeps it out
            leak = float(np.prod(pyramid_gain(p))) / max(float(np.prod(pyramid_gain(folded))), 1e-12)
            if leak / (max(1, abs(i)) * max(1, abs(j))) < BINNED_ALIAS_WEIGHT:
                continue
            if np.min(np.hypot(*(carriers - folded).T)) < BINNED_ALIAS_CLEARANCE * radius:
                return False
    return True


def check_binning(binning, freq, radius: float, shape) -> int:
    """``binning`` (1 or 2) where it applies; ValueError naming the value, or
    what binning 2 would fold into the carriers' bands (:func:`binned_bands_clear`)."""
    if binning not in (1, 2):
        raise ValueError(f"binning must be 1 or 2; got {binning!r}")
    if binning == 2 and not binned_bands_clear(freq, radius, shape):
        raise ValueError(
            f"binning 2 would fold the pattern into its carrier bands (carriers at "
            f"{np.round(np.asarray(freq), 4).tolist()} cycles/px, filter radius {radius:.4f}, frame "
            f"{shape[0]} x {shape[1]}); use binning 1")
    return int(binning)


def bin_pyramid(image) -> np.ndarray:
    """``image`` low-passed and sampled every 2nd row and column (cv2.pyrDown:
    ``[1 4 6 4 1] / 16`` each way, sample ``i`` centred on pixel ``2 i``, mirrored
    border).  16-bit images stay 16-bit (rounded to the grey level: 1/12 of a
    level squared of noise, under any camera's own); 8-bit ones are binned at
    256x their levels and come back float32 (rounding them to a level would add
    more noise than a noise-free 8-bit frame has: 0.0022 against 0.0014 rad
    between binned and unbinned phases, ray traced); others float32 or float64."""
    a = np.asarray(image)
    if a.dtype == np.uint8:
        wide = cv2.pyrDown(cv2.multiply(a, 256, dtype=cv2.CV_16U), borderType=cv2.BORDER_REFLECT101)
        return cv2.multiply(wide, 1.0 / 256.0, dtype=cv2.CV_32F)
    if a.dtype not in (np.uint16, np.int16, np.float32, np.float64):
        a = a.astype(np.float32)
    return cv2.pyrDown(a, borderType=cv2.BORDER_REFLECT101)
