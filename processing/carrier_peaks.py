"""Carrier wavevectors of a checkerboard image (the core of :mod:`processing.carriers`).

A checkerboard's Fourier fundamentals are its two diagonals: two
non-collinear peaks ``k1``, ``k2`` in the half-plane of the real FFT.
:func:`find_carriers` finds them in the reference image to sub-bin precision
and refuses images without a clear pattern
(:class:`~processing.errors.NoCarrierError`); :class:`Carriers` derives what
live alignment shows (periods in pixels, rotation of the board, viewing angle
theta from the aspect of a square pattern).

Frequencies are in cycles per pixel, ``(f_row, f_col)``, with ``f_col >= 0``.

Theta from the aspect (notes.md): a telecentric camera looking at the
surface under incidence theta sees a square board compressed along the image
rows by cos(theta).  Scaling the row frequency by cos(theta) maps the image
carriers into the surface frame, where a square board's two diagonal
carriers are orthogonal and of equal length.  Both conditions are linear in
``C = cos(theta)**2`` and are solved together by least squares.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import scipy.fft

from .errors import NoCarrierError
from .half_spectrum import display_bins, display_spectrum_of

__all__ = ["Carriers", "find_carriers", "hann", "theta_from_carriers", "rotation_from_carriers", "display_spectrum",
           "frame_spectrum", "windowed_spectrum", "as_float_image", "MIN_PEAK_CONTRAST", "MIN_ISOLATION", "ISOLATION_RING_BINS"]

# A peak must stand this many times (in amplitude) above the spectrum's
# typical level at the same radius.  Measured: sharp or soft checkerboards
# give 10^3-10^4, white noise about 5-8, photos without a pattern < 30.
MIN_PEAK_CONTRAST = 40.0
# ... and this many times above anything 4-7 bins around it (a compact peak,
# not a streak from straight edges or a ridge).
MIN_ISOLATION = 4.0


@dataclasses.dataclass(frozen=True)
class Carriers:
    """The two carriers of a checkerboard image.

    Attributes
    ----------
    freq : ndarray, float64, shape (2, 2)
        ``freq[s] = (f_row, f_col)`` of carrier ``s`` in cycles per pixel,
        ``f_col >= 0``; sub-bin precision.
    shape : tuple of int
        ``(rows, cols)`` of the image they were measured on.
    contrast : ndarray, shape (2,)
        Peak amplitude over the spectrum's typical level at that radius.
    sharpness : ndarray, shape (2,)
        Fraction of the peak's neighbourhood energy (5 x 5 bins) in its
        central 3 x 3 bins (Hann-windowed image): near 1 for a crisp, in-focus,
        undistorted pattern, lower when blurred or distorted.
    """

    freq: np.ndarray
    shape: tuple
    contrast: np.ndarray
    sharpness: np.ndarray

    @property
    def wavevectors(self) -> np.ndarray:
        """(2, 2) array of ``2 pi (f_row, f_col)``: radians per pixel."""
        return 2.0 * np.pi * np.asarray(self.freq)

    @property
    def bins(self) -> np.ndarray:
        """(2, 2) carrier positions in FFT bins ``(f_row * rows, f_col * cols)``."""
        return np.asarray(self.freq) * np.asarray(self.shape, dtype=float)

    @property
    def periods_px(self) -> np.ndarray:
        """(2,) carrier periods ``1 / |f|`` in pixels (along each carrier)."""
        return 1.0 / np.hypot(self.freq[:, 0], self.freq[:, 1])

    @property
    def angles_deg(self) -> np.ndarray:
        """(2,) carrier directions in the image, degrees from the column axis
        towards increasing row, in (-90, 90]."""
        return np.degrees(np.arctan2(self.freq[:, 0], self.freq[:, 1]))

    @property
    def rotation_deg(self) -> float:
        """Rotation of the board's edges in the image, degrees in (-45, 45]
        (0: edges along rows and columns)."""
        return rotation_from_carriers(self.freq)

    def surface_rotation_deg(self, theta_deg: float | None = None) -> float:
        """Rotation (deg, (-45, 45]) of the board on the surface: row
        frequencies scaled by cos(theta) first (default theta: the estimate
        from the aspect; NaN if there is none).  0: edges along and across
        the plane of incidence."""
        theta = self.theta_deg if theta_deg is None else float(theta_deg)
        if not np.isfinite(theta):
            return float("nan")
        f = np.array(self.freq, dtype=float)
        f[:, 0] *= math.cos(math.radians(theta))
        return rotation_from_carriers(f)

    @property
    def theta_deg(self) -> float:
        """Viewing angle theta estimated from the aspect of a square board
        (telecentric view, rows along the plane of incidence), degrees; NaN
        if the carriers admit no such angle.  0 means no compression."""
        return theta_from_carriers(self.freq)

    @property
    def min_spacing(self) -> float:
        """Smallest distance (cycles/px) from a carrier to DC, to the other
        carrier or to its mirror image: what a band-pass filter must not reach."""
        k1, k2 = np.asarray(self.freq)
        return float(min(np.hypot(*k1), np.hypot(*k2),
                         np.hypot(*(k1 - k2)), np.hypot(*(k1 + k2))))

    def describe(self) -> str:
        """One line for messages: periods, angles, rotation."""
        p = self.periods_px
        a = self.angles_deg
        return (f"periods {p[0]:.2f} and {p[1]:.2f} px, carrier angles "
                f"{a[0]:.1f} and {a[1]:.1f} deg, rotation {self.rotation_deg:.1f} deg")


def theta_from_carriers(freq, stretch_y: float = 1.0) -> float:
    """Viewing angle (deg) that makes the two carriers orthogonal and equally long.

    Parameters
    ----------
    freq : array_like, shape (2, 2)
        ``(f_row, f_col)`` of both carriers, cycles per pixel.
    stretch_y : float
        Cell height / width of the printed board (``Geometry.pattern_stretch_y``):
        a board stretched by ``s`` along y shows row frequencies ``1/s`` of a
        square board's, so they are multiplied by ``s`` first.

    Returns
    -------
    float
        theta in degrees, in [0, 90); NaN if no real angle fits (the pattern
        is not square, or rows do not run along the plane of incidence).
    """
    (a1, b1), (a2, b2) = np.asarray(freq, dtype=float)
    a1, a2 = a1 * float(stretch_y), a2 * float(stretch_y)
    # surface frame: (a * c, b), c = cos(theta); unknown C = c^2:
    # orthogonal:   a1 a2 C + b1 b2 = 0
    # equal length: (a1^2 - a2^2) C = b2^2 - b1^2
    A = np.array([a1 * a2, a1 * a1 - a2 * a2])
    B = np.array([-b1 * b2, b2 * b2 - b1 * b1])
    den = float(A @ A)
    scale = (a1 * a1 + a2 * a2) ** 2
    if den <= 1e-12 * scale:
        return float("nan")
    C = float(A @ B) / den
    if not (0.0 < C <= 1.05):  # up to 1.05: an uncompressed (theta = 0) view, within error
        return float("nan")
    return float(np.degrees(np.arccos(min(1.0, math.sqrt(C)))))


def rotation_from_carriers(freq) -> float:
    """Rotation (deg, in (-45, 45]) of a checkerboard's edges in the image.

    The edge directions of the board are ``k1 + k2`` and ``k1 - k2``; the one
    closer to the column axis gives the rotation, measured from the column
    axis towards increasing row.
    """
    k1, k2 = np.asarray(freq, dtype=float)
    best = None
    for e in (k1 + k2, k1 - k2):
        ang = math.degrees(math.atan2(e[0], e[1]))
        ang = (ang + 90.0) % 180.0 - 90.0  # direction, not orientation
        if best is None or abs(ang) < abs(best):
            best = ang
    best = (best + 45.0) % 90.0 - 45.0
    if best == -45.0:
        best = 45.0
    return float(best)


def hann(n):
    """Hann window ``0.5 - 0.5 cos(2 pi (j + 1/2) / n)``, float32 (n,): what the carrier search applies."""
    return (0.5 - 0.5 * np.cos(2.0 * np.pi * (np.arange(n) + 0.5) / n)).astype(np.float32)


def as_float_image(image, name):
    a = np.asarray(image)
    if a.ndim != 2:
        raise ValueError(f"{name} must be a 2-D grey image (rows, cols); got shape {a.shape}")
    if a.dtype.kind not in "uif":
        raise ValueError(f"{name} must be an integer or float image; got dtype {a.dtype}")
    if min(a.shape) < 32:
        raise NoCarrierError(f"{name} is too small to hold a pattern: shape {a.shape}, need >= 32 x 32 "
                             f"pixels; use the camera's full region of interest")
    a = a.astype(np.float32, copy=False)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains NaN or infinite pixels; pass the raw camera image")
    return a


def windowed_spectrum(image) -> np.ndarray:
    """rfft2 half spectrum, complex64 (rows, cols // 2 + 1), of the mean-free image times
    :func:`hann` along both axes: what :func:`find_carriers` searches and
    :func:`frame_spectrum` shows.  A caller that needs both computes it once and
    passes it to each (``half_spectrum=``): the live alignment before a reference.

    Parameters
    ----------
    image : ndarray, float32 (rows, cols)
    """
    image = np.asarray(image, np.float32)
    rows, cols = image.shape
    w = hann(rows)[:, None] * hann(cols)[None, :]
    return scipy.fft.rfft2((image - image.mean()) * w, workers=2)


def _spectrum(image, half_spectrum=None):
    """:func:`windowed_spectrum` of the image (or ``half_spectrum``, that of the
    same image) and the frequency grids."""
    rows, cols = image.shape
    spec = windowed_spectrum(image) if half_spectrum is None else half_spectrum
    if spec.shape != (rows, cols // 2 + 1):
        raise ValueError(f"half spectrum of shape {spec.shape} does not belong to a {rows} x {cols} image")
    fr = scipy.fft.fftfreq(rows)[:, None]
    fc = scipy.fft.rfftfreq(cols)[None, :]
    return spec, fr, fc


def display_spectrum(half_magnitude, cols: int, *, size: int = 256, max_freq: float = 0.25) -> dict:
    """Centred log-magnitude spectrum for display, from an rfft2 magnitude: what the
    Alignment tab shows, written out on the whole array (the definition; the app reads
    the same from the bins shown alone, :func:`processing.half_spectrum.display_spectrum_of`,
    which the tests hold to this).

    Parameters
    ----------
    half_magnitude : ndarray, shape (rows, cols // 2 + 1)
        ``|rfft2(image)|`` of a (rows, cols) image, any real dtype.
    cols : int
        Width of that image (the half spectrum cannot tell odd from even).
    size : int
        At most about this many samples per axis: the spectrum is reduced by
        block maxima, so that carrier peaks stay visible.
    max_freq : float
        Show frequencies up to this many cycles per pixel (0.25: periods >= 4 px).

    Returns
    -------
    dict
        ``log_magnitude`` float32 (n_rows, n_cols): log10 |FFT|; ``freq_x``
        (n_cols,), ``freq_y`` (n_rows,): cycles per pixel (columns, rows),
        increasing, the centres of the blocks.
    """
    spec = np.asarray(half_magnitude, np.float32)
    rows, h = spec.shape
    cols = int(cols)
    if h != cols // 2 + 1:
        raise ValueError(f"half spectrum of width {h} does not belong to an image {cols} pixels wide")
    full = np.empty((rows, cols), np.float32)
    full[:, :h] = spec
    # negative column frequencies: conjugate symmetry |X(-k)| = |X(k)|
    neg_c = np.arange(h, cols)
    full[:, h:] = spec[(-np.arange(rows)) % rows][:, cols - neg_c]
    full = np.fft.fftshift(full)
    fy, fx, keep_r, keep_c, step_r, step_c = display_bins((rows, cols), size, max_freq)
    nr, nc = len(keep_r) // step_r, len(keep_c) // step_c
    sub = full[np.ix_(keep_r, keep_c)]
    sub = sub.reshape(nr, step_r, nc, step_c).max(axis=(1, 3))
    mag = np.log10(sub + 1e-6 * float(sub.max() or 1.0)).astype(np.float32)
    fr_k = fy[keep_r].reshape(nr, step_r).mean(axis=1)
    fc_k = fx[keep_c].reshape(nc, step_c).mean(axis=1)
    return {"log_magnitude": mag, "freq_x": fc_k, "freq_y": fr_k}


def frame_spectrum(frame, *, size: int = 256, max_freq: float = 0.25, half_spectrum=None) -> dict:
    """:func:`display_spectrum` of a raw frame's :func:`windowed_spectrum` (mean removed,
    Hann window; ``half_spectrum``: that spectrum, if already computed), reading only the
    bins shown (:func:`processing.half_spectrum.display_spectrum_of`): the live spectrum
    before any reference, and that of a random-dot pattern."""
    img = np.asarray(frame, np.float32)
    half = windowed_spectrum(img) if half_spectrum is None else half_spectrum
    return display_spectrum_of(half, img.shape, size=size, max_freq=max_freq)


def _gather(spec, rr, cc, rows):
    """spec[rr, cc] of an rfft half-spectrum, mirrored (conjugated) for cc < 0."""
    rr = np.asarray(rr) % rows
    cc = np.asarray(cc)
    rr, cc = np.broadcast_arrays(rr, cc)
    out = np.zeros(rr.shape, dtype=spec.dtype)
    neg = cc < 0
    inside = (~neg) & (cc < spec.shape[1])
    out[inside] = spec[rr[inside], cc[inside]]
    mir = neg & (-cc < spec.shape[1])
    vals = spec[(-rr[mir]) % rows, -cc[mir]]
    out[mir] = np.conj(vals) if np.iscomplexobj(spec) else vals
    return out


#: A peak's isolation is judged against the bins this far (inclusive, in bins) from it.
ISOLATION_RING_BINS = (4, 7)
_D_R, _D_C = np.mgrid[-7:8, -7:8]
_RING = (np.hypot(_D_R, _D_C) >= ISOLATION_RING_BINS[0]) & (np.hypot(_D_R, _D_C) <= ISOLATION_RING_BINS[1])
#: (row, col) bin offsets of that ring.
ISOLATION_RING_DR, ISOLATION_RING_DC = _D_R[_RING], _D_C[_RING]
_RING_DR, _RING_DC = ISOLATION_RING_DR, ISOLATION_RING_DC


#: A peak's isolation is judged against the ring's this-th largest amplitude: the flank of one other compact
#: peak reaches one or two of its bins (the board's other fundamental, 8.5 bins away when the board's period
#: is long and its rows compressed: by-hand trial of 7 Dec 2026, a 60 px board at 256^2 isolated 3.1 against
#: the other's flank, and its (1, 3) harmonic was taken, heights 13.7 % off), while a streak or a ridge
#: through the peak raises bins on both sides of the ring.
ISOLATION_RANK = 3


def _isolation(spec, r, c, rows):
    """Peak amplitude over the :data:`ISOLATION_RANK`-th largest amplitude 4 to 7 bins away.

    A carrier peak of a Hann-windowed image is a compact blob (> 10); a
    streak (straight edges, image borders) or a ridge continues at the same
    level (about 1).
    """
    vals = _gather(spec, r + _RING_DR, c + _RING_DC, rows)
    return float(spec[r, c] / max(float(np.partition(vals, -ISOLATION_RANK)[-ISOLATION_RANK]), 1e-300))


def _refine(spec_c, r, c, rows, cols, half=4):
    """Sub-bin carrier frequency (cycles/px) from the mean phase slope of the
    demodulated peak: cut +-half bins around the peak, inverse-transform the
    small window and average the phase increment between neighbours.

    The Hann window (real, positive) does not bend the phase, so the slope is
    the exact offset of the carrier from bin (r, c); unbiased, unlike
    interpolating the magnitude.
    """
    m = 2 * half + 1
    q = np.arange(-half, half + 1)
    win = _gather(spec_c, r + q[:, None], c + q[None, :], rows)
    field = np.fft.ifft2(np.fft.ifftshift(win))
    # phase advance per coarse step: rows step rows/m pixels
    a_r = np.sum(field[1:, :] * np.conj(field[:-1, :]))
    a_c = np.sum(field[:, 1:] * np.conj(field[:, :-1]))
    d_r = np.angle(a_r) * m / (2.0 * np.pi)
    d_c = np.angle(a_c) * m / (2.0 * np.pi)
    r_s = r if r <= rows // 2 else r - rows
    return np.array([(r_s + d_r) / rows, (c + d_c) / cols])


def _sharpness(spec, r, c, rows):
    cols = spec.shape[1]
    rr = (np.arange(r - 2, r + 3)) % rows
    cc = np.arange(c - 2, c + 3)
    sub = np.zeros((5, 5))
    for j, ci in enumerate(cc):
        if ci < 0:
            sub[:, j] = spec[(-rr) % rows, -ci]
        elif ci < cols:
            sub[:, j] = spec[rr, ci]
    e = sub ** 2
    return float(e[1:4, 1:4].sum() / max(e.sum(), 1e-300))


def _check_not_uniform(img):
    """NoCarrierError for an image without any pattern (uniform)."""
    level = float(np.mean(np.abs(img)))
    spread = float(np.std(img))
    if spread <= 1e-3 * max(level, 1e-30) or spread == 0.0:
        raise NoCarrierError(
            f"the image is uniform (standard deviation {spread:.3g} around a mean of {level:.3g}): "
            "no pattern, hence no carrier peak, is visible; check that the checkerboard is lit, in view and that the "
            "exposure is not zero or saturated")


def _ring_excess(spec, radius, allowed, rows, cols):
    """log of ``spec`` above its typical level at the same radius, -inf outside ``allowed``."""
    # Typical level at each radius: geometric mean over rings one bin wide.
    ring = np.minimum((radius * max(rows, cols)).astype(np.int64), max(rows, cols))
    logspec = np.log(spec + 1e-30)
    counts = np.bincount(ring.ravel(), minlength=max(rows, cols) + 1)
    sums = np.bincount(ring.ravel(), weights=logspec.ravel(), minlength=max(rows, cols) + 1)
    ring_mean = sums / np.maximum(counts, 1)
    # smooth the ring profile over +-3 rings so that one strong peak does not lift its own ring
    kernel = np.ones(7) / 7.0
    ring_mean = np.convolve(np.pad(ring_mean, 3, mode="edge"), kernel, mode="valid")
    return np.where(allowed, logspec - ring_mean[ring], -np.inf)


def _best_peak(score, spec, rows, min_contrast):
    """Among isolated peaks standing ``min_contrast`` above their ring, the
    strongest in amplitude (a fundamental, not a harmonic that merely
    stands higher above a weaker ring).  Negative contrast: the best
    candidate was not isolated (a streak or a smear)."""
    flat = score.ravel()
    # the strongest bins in amplitude among those standing min_contrast above their ring, first: the
    # bins ranked by contrast alone can all be a sharp board's harmonics and their leakage (a 20 px
    # board at 192^2, 9.6 bins: the fundamental was not among the 64 and the (1, 5) harmonic won)
    tall = np.flatnonzero(flat >= math.log(min_contrast))
    amp = spec.ravel()
    for idx in tall[np.argsort(-amp[tall])][:64]:
        r, c = divmod(int(idx), score.shape[1])
        if _isolation(spec, r, c, rows) >= MIN_ISOLATION:
            return r, c, float(np.exp(flat[idx]))
    # none: the best candidates by contrast, for the message (a smear, or too weak)
    n_cand = min(64, flat.size)
    cand = np.argpartition(-flat, n_cand - 1)[:n_cand]
    cand = cand[np.argsort(-flat[cand])]
    best = None
    fallback = (0, 0, float("-inf"))
    for idx in cand:
        if not np.isfinite(flat[idx]):
            break
        r, c = divmod(int(idx), score.shape[1])
        if best is not None and spec[r, c] <= spec[best[0], best[1]]:
            continue  # cannot beat the best isolated peak (the fallback only matters without one)
        contrast = float(np.exp(flat[idx]))
        if _isolation(spec, r, c, rows) < MIN_ISOLATION:
            if fallback[2] == float("-inf"):
                fallback = (r, c, -contrast)
            continue
        if contrast < min_contrast:
            if fallback[2] == float("-inf") or fallback[2] < 0:
                fallback = (r, c, contrast)
            continue
        if best is None or spec[r, c] > spec[best[0], best[1]]:
            best = (r, c, contrast)
    return best if best is not None else fallback


def _ordered(f1, f2, peak1, peak2, spec, rows, cols) -> Carriers:
    """The two carriers, the first with f_row <= the second's (stable display)."""
    (r1, c1, contrast1), (r2, c2, contrast2) = peak1, peak2
    freq = np.array([f1, f2])
    # order: first carrier has f_row <= the second's (stable display)
    if freq[0, 0] > freq[1, 0]:
        freq = freq[::-1].copy()
        contrast = np.array([contrast2, contrast1])
        sharp = np.array([_sharpness(spec, r2, c2, rows), _sharpness(spec, r1, c1, rows)])
    else:
        contrast = np.array([contrast1, contrast2])
        sharp = np.array([_sharpness(spec, r1, c1, rows), _sharpness(spec, r2, c2, rows)])
    return Carriers(freq=freq, shape=(rows, cols), contrast=contrast, sharpness=sharp)


#: Below this many pixels along its smaller side, an image without a clear carrier peak is told how long a
#: period was looked for: by-hand trial of 7 Dec 2026, a 40 x 256 region of interest over a 20 px board was
#: refused as "a streak or smear ... if the water was moving", where 2 periods along its rows were the cause.
NARROW_IMAGE_PX = 128


def _no_clear_peak(contrast, min_contrast, max_period_px, shape) -> NoCarrierError:
    """The error for a best first peak of ``contrast`` (negative: not isolated) in an image of ``shape``
    (rows, cols) searched up to periods of ``max_period_px``."""
    if contrast >= 0 or -contrast < min_contrast:
        what = f"the strongest stands {abs(contrast):.1f}x above the background, need {min_contrast:.0f}x"
    else:
        what = (f"a candidate {-contrast:.1f}x above the background is a streak or smear, "
                "not an isolated peak")
    narrow = ""
    if min(shape) < NARROW_IMAGE_PX:
        narrow = (f"; in a {shape[0]} x {shape[1]} px image, periods up to {max_period_px:.0f} px (a quarter of its "
                  f"smaller side) are looked for: a board whose period is longer needs a larger region of interest")
    return NoCarrierError(
        f"the image shows no clear carrier peak ({what}): check that the "
        f"checkerboard is in focus, lit, fills the view and that this is the pattern image{narrow}")


def find_carriers(reference, *, min_period_px: float = 2.5, max_period_px: float | None = None,
                  min_contrast: float = MIN_PEAK_CONTRAST, min_angle_deg: float = 15.0,
                  half_spectrum=None) -> Carriers:
    """Find the two carrier peaks of a checkerboard image.

    Parameters
    ----------
    reference : ndarray, shape (rows, cols)
        Grey image (uint8/uint16/float) of the undisturbed pattern.
    min_period_px, max_period_px : float, optional
        Carrier periods searched, in pixels; ``max_period_px`` defaults to a
        quarter of the smaller image side.
    min_contrast : float, optional
        How far (amplitude ratio) a peak must stand above the spectrum's
        typical level at its radius.
    min_angle_deg : float, optional
        Smallest angle between the two carriers (the second peak must not be
        a harmonic of the first).
    half_spectrum : ndarray, complex (rows, cols // 2 + 1), optional
        The image's :func:`windowed_spectrum`, where the caller has it already.

    Returns
    -------
    Carriers

    Raises
    ------
    NoCarrierError
        If no pair of clear, non-collinear peaks exists (flat or noisy image,
        pattern out of focus, unlit or not in view).
    ValueError
        If the image is not 2-D, too small or not finite.

    Examples
    --------
    >>> import numpy as np
    >>> r, c = np.mgrid[:128, :128]
    >>> board = np.sign(np.sin(2 * np.pi * r / 16) * np.sin(2 * np.pi * c / 16))
    >>> find_carriers(board).periods_px.round(2)
    array([11.31, 11.31])
    """
    img = as_float_image(reference, "reference image")
    rows, cols = img.shape
    _check_not_uniform(img)
    if max_period_px is None:
        max_period_px = min(rows, cols) / 4.0
    spec_c, fr, fc = _spectrum(img, half_spectrum)
    spec = np.abs(spec_c).astype(np.float64)
    # floor at float32 round-off of the largest component: exact zeros (synthetic
    # separable images) must not make every non-zero bin look like a peak
    spec = np.maximum(spec, 1e-6 * spec.max() + 1e-30)
    radius = np.hypot(fr, fc)
    allowed = (radius >= 1.0 / max_period_px) & (radius <= 1.0 / min_period_px)
    if not allowed.any():
        raise NoCarrierError(
            f"no frequencies between periods {min_period_px} and {max_period_px} px "
            f"in a {rows} x {cols} image; check min_period_px/max_period_px")
    excess = _ring_excess(spec, radius, allowed, rows, cols)

    r1, c1, contrast1 = _best_peak(excess, spec, rows, min_contrast)
    if not np.isfinite(contrast1) or contrast1 < min_contrast:
        raise _no_clear_peak(contrast1, min_contrast, max_period_px, (rows, cols))
    f1 = _refine(spec_c, r1, c1, rows, cols)
    # second carrier: not collinear with k1 (harmonics), not too different in length
    fr_b = np.broadcast_to(fr, spec.shape)
    fc_b = np.broadcast_to(fc, spec.shape)
    cosang = np.abs(fr_b * f1[0] + fc_b * f1[1]) / (np.maximum(radius, 1e-12) * np.hypot(*f1))
    ok2 = cosang < math.cos(math.radians(min_angle_deg))
    ratio = radius / np.hypot(*f1)
    ok2 &= (ratio > 1.0 / 6.0) & (ratio < 6.0)
    r2, c2, contrast2 = _best_peak(np.where(ok2, excess, -np.inf), spec, rows, min_contrast)
    if not np.isfinite(contrast2) or contrast2 < min_contrast:
        p1 = 1.0 / np.hypot(*f1)
        raise NoCarrierError(
            f"the image shows one carrier (period {p1:.2f} px) but no second, "
            f"non-collinear one (best stands {abs(contrast2):.1f}x above background, need "
            f"{min_contrast:.0f}x{'' if contrast2 >= 0 else ', and is not isolated'}): tirdeflect needs a checkerboard (two crossing periodic "
            "directions); check the pattern, focus and lighting")
    f2 = _refine(spec_c, r2, c2, rows, cols)
    return _ordered(f1, f2, (r1, c1, contrast1), (r2, c2, contrast2), spec, rows, cols)
