"""Fourier demodulation of checkerboard frames against a reference.

For each carrier ``s`` the frame's spectrum is cut in a small window around
the carrier, multiplied by a band-pass filter and inverse-transformed *at the
window's size*: that yields the band-limited analytic signal ``g_s`` exactly,
sampled on a decimated grid (every ``rows / m_rows`` pixels).  The band-pass
is all the information Fourier demodulation has, so nothing is lost, and the
small transforms are what makes live speed possible.  The same is done once
to the reference (``g0_s``); then

    arg(g_s conj(g0_s)) = -k_s . u          (u: displacement, pixels)

Demodulating against the filtered reference (not against a pure carrier)
cancels print defects and lens distortion, and makes a sub-bin error in the
window's centre irrelevant to the phase.

Border treatment: both images are multiplied by the same Tukey window (flat inside, cosine taper ``taper_px`` wide at each border), so
the periodic wrap-around of the FFT does not smear the border's jump across
the spectrum; the window's own spectrum times the image mean is subtracted
from the carrier windows (exactly what removing the mean first would do, for
one pass over the image less).  ``border="none"`` switches it off (measured in
benchmarks/bench_processing.py).

Filters (``filter_shape``):

- ``"flattop"`` (default): radial Tukey in frequency around the carrier,
  gain 1 up to ``filter_flat * radius`` (0.8), cosine roll-off to 0 at
  ``radius = min(filter_radius * |k|, |k1 +- k2| / 2)`` (DC may come closer
  than the other pattern peaks: only slow lighting changes live there).
- ``"disc"``: hard disc of the same radius; with ``filter_radius=0.5`` and
  ``subbin=False`` it is the usual filter of the published method.  Its
  ringing lets borders leak (docs/processing.md has the measurements).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from .binning import bin_pyramid, check_binning, pyramid_gain
from .carriers import Carriers
from .errors import NoCarrierError
from .fft import FFTPlanner
from .plan import DemodulationPlan, read_only

__all__ = ["Demodulator", "nice_fft_size", "tukey"]


def nice_fft_size(n: int) -> int:
    """Smallest integer >= n whose prime factors are all 2, 3, 5 or 7 (fast FFTs)."""
    n = max(int(math.ceil(n)), 1)
    while True:
        m = n
        for p in (2, 3, 5, 7):
            while m % p == 0:
                m //= p
        if m == 1:
            return n
        n += 1


def tukey(n: int, taper: float) -> np.ndarray:
    """1-D window of length n, 1 inside, cosine taper ``taper`` samples wide at both ends.

    Returns float32 values in (0, 1].
    """
    x = np.arange(n, dtype=np.float64) + 0.5
    d = np.minimum(x, n - x)
    w = np.ones(n)
    if taper > 0:
        t = d < taper
        w[t] = 0.5 - 0.5 * np.cos(np.pi * d[t] / taper)
    return w.astype(np.float32)


def _check_options(ref, filter_shape, border, filter_radius, filter_flat, oversample):
    """ValueError naming the first of the Demodulator's arguments out of range."""
    if ref.ndim != 2:
        raise ValueError(f"reference must be 2-D (rows, cols); got shape {ref.shape}")
    if filter_shape not in ("flattop", "disc"):
        raise ValueError(f"filter_shape must be 'flattop' or 'disc'; got {filter_shape!r}")
    if border not in ("apodize", "none"):
        raise ValueError(f"border must be 'apodize' or 'none'; got {border!r}")
    if not 0.05 <= filter_radius <= 0.75:
        raise ValueError(f"filter_radius must be within [0.05, 0.75] of the carrier spacing; got {filter_radius}")
    if not 0.0 <= filter_flat < 1.0:
        raise ValueError(f"filter_flat must be within [0, 1); got {filter_flat}")
    if oversample < 1.0:
        raise ValueError(f"oversample must be >= 1; got {oversample}")


class Demodulator:
    """Band-limited analytic signals of the two carriers, decimated or full grid.

    Parameters
    ----------
    reference : ndarray, shape (rows, cols)
        Reference image (any real dtype), pattern on the flat surface.
    carriers : Carriers
        Carriers of ``reference`` (:func:`processing.carriers.find_carriers`).
    planner : FFTPlanner, optional
        Plans to use (default: a new one with FFTW_ESTIMATE).
    filter_radius : float, optional
        Filter radius as a fraction of the carrier's distance to DC (default
        0.7; 0.5 is the usual filter), never more than half the distance to
        the other carrier or the harmonics (``|k1 +- k2|``).
    filter_flat : float, optional
        Fraction of the radius where the flat-top filter has gain 1.
    filter_shape : {"flattop", "disc"}
    oversample : float, optional
        Decimated grid density relative to the filter's Nyquist rate
        (default 2: smooth enough for cubic interpolation to the full grid).
    border : {"apodize", "none"}
    taper_px : float, optional
        Width of the border taper, pixels (default one carrier period).
    subbin : bool, optional
        Centre the filter on the sub-bin carrier (default).  False rounds the
        carriers to the nearest bin (the published method); the wavevectors
        used to convert phase to displacement are rounded the same way.
    local_carriers : bool, optional
        Convert phase to displacement on the decimated grid with the
        reference's *local* wavevectors (phase gradient of ``g0``, smoothed
        over 5 x 5 samples) instead of one global pair (default; ignored
        when ``subbin`` is False).  A camera at finite distance sees the
        pattern's period change across the field (perspective, theta varying)
        and lens distortion does the same: with one global pair the
        displacement is off by that change (1.8 % at 1.5 m, theta 60 deg).
    binning : {1, 2}, optional
        2: transform the frame binned 2 x 2 by cv2.pyrDown (a quarter of the
        samples), the filters divided by the pyramid's gain (:func:`pyramid_gain`)
        so that the decimated signals are the same band; for the decimated grid
        only (:meth:`full_from_windows` refuses), and only where
        :func:`processing.binning.binned_bands_clear` (ValueError otherwise).  The same windows,
        grid and sample positions as binning 1.

    Attributes
    ----------
    shape : tuple
        ``(rows, cols)`` of frames.
    window_shape : tuple
        ``(m_rows, m_cols)`` of the decimated grid.
    rows_px, cols_px : ndarray, float64
        Pixel coordinates of the decimated samples, shapes (m_rows,), (m_cols,).
    wavevectors : ndarray, shape (2, 2)
        ``2 pi (f_row, f_col)`` of the carriers used, radians per pixel.
    g0 : ndarray, complex64, shape (2, m_rows, m_cols)
        Reference analytic signals on the decimated grid.
    carrier_columns : int or None
        The carrier windows read the real FFT's columns ``0 .. carrier_columns - 1``
        only (:meth:`carrier_spectrum` transforms just those); None: most of them.
    """

    def __init__(self, reference, carriers: Carriers, *, planner: FFTPlanner | None = None,
                 filter_radius: float = 0.7, filter_flat: float = 0.8,
                 filter_shape: str = "flattop", oversample: float = 2.0,
                 border: str = "apodize", taper_px: float | None = None, subbin: bool = True,
                 local_carriers: bool = True, binning: int = 1):
        ref = np.asarray(reference)
        _check_options(ref, filter_shape, border, filter_radius, filter_flat, oversample)
        self.shape = rows, cols = ref.shape
        if tuple(carriers.shape) != self.shape:
            raise ValueError(f"carriers were measured on shape {carriers.shape}, reference is {self.shape}")
        self.planner = planner if planner is not None else FFTPlanner(planner_effort="FFTW_ESTIMATE")
        self.filter_shape = filter_shape
        self.filter_radius = float(filter_radius)
        self.oversample = float(oversample)
        self.border = border
        freq = np.array(carriers.freq, dtype=np.float64)
        if not subbin:
            freq = np.round(freq * np.array([rows, cols])) / np.array([rows, cols])
        self.freq = freq
        self.wavevectors = 2.0 * np.pi * freq
        k1, k2 = freq
        dc_spacing = min(np.hypot(*k1), np.hypot(*k2))
        pair_spacing = min(np.hypot(*(k1 - k2)), np.hypot(*(k1 + k2)))
        # The DC band holds only slow illumination changes (the mean is removed),
        # so the filter may reach further towards DC than towards the other
        # carrier and the harmonics (at k1 +- k2 from each carrier), whose bands
        # it must never touch: at most half the distance to them.
        self.radius = float(min(filter_radius * dc_spacing, 0.5 * pair_spacing))  # cycles / px
        self.flat = float(filter_flat)
        self.binning = check_binning(binning, freq, self.radius, self.shape)
        #: (rows, cols) of what is transformed: the frame, or the frame binned 2 x 2
        self.source_shape = (rows // binning, cols // binning)
        # ---- border window
        period = float(np.max(1.0 / np.hypot(freq[:, 0], freq[:, 1])))
        self.taper_px = float(period if taper_px is None else taper_px)
        self._window2d = self._border_window() if border == "apodize" else None
        # ---- decimated windows: same size for both carriers
        m_r = nice_fft_size(max(8, oversample * 2.0 * self.radius * rows + 2))
        m_c = nice_fft_size(max(8, oversample * 2.0 * self.radius * cols + 2))
        self.window_shape = (m_r, m_c)
        # Decimated sample j sits at pixel (j + 0.5) * rows / m_r - 0.5: the
        # pixel-centre convention of cv2.resize, so that resizing the decimated
        # grid to the frame shape lands every value on its own pixel.
        shift_r = 0.5 * rows / m_r - 0.5
        shift_c = 0.5 * cols / m_c - 0.5
        self.rows_px = np.arange(m_r) * (rows / m_r) + shift_r
        self.cols_px = np.arange(m_c) * (cols / m_c) + shift_c
        self._centres = np.round(freq * np.array([rows, cols])).astype(np.int64)
        q_r = np.fft.fftfreq(m_r, 1.0 / m_r).astype(np.int64)  # ifftshift order offsets
        q_c = np.fft.fftfreq(m_c, 1.0 / m_c).astype(np.int64)
        # binned, bin k of the half-size transform is k / (rows / 2) cycles per
        # binned pixel: k / rows per pixel, the same frequency as unbinned; and
        # binned pixel i sits at pixel 2 i (the pyramid is centred), so the same
        # phase ramps put the samples at the same rows_px, cols_px
        self._build_windows(freq, q_r, q_c, shift_r, shift_c)
        self._full_index = [((self._centres[s][0] + q_r)[:, None] % rows,
                             (self._centres[s][1] + q_c)[None, :] % cols) for s in range(2)]
        shape2 = (2,) + self.window_shape
        self._gather_idx = np.stack([g[0] for g in self._gather]).reshape(shape2)
        mirror = np.stack([g[1] for g in self._gather]).reshape(shape2)
        self._gather_mirror = mirror if mirror.any() else None
        self._filter_stack = np.stack(self._filters)
        # inverse FFT normalisation 1 / (m_r m_c) times the window-size scale m_r m_c / (rows cols)
        self._dec_scale = np.float32(1.0 / (self.source_shape[0] * self.source_shape[1]))
        self.last_mean = 0.0
        self._dc_leak = None
        if self._window2d is not None:
            self._dc_leak = self.windows(np.fft.rfft2(self._window2d).astype(np.complex64), mean=0.0)
        self.carrier_columns = self._carrier_columns()
        # the carriers' band only: the whole transform (alignment, the display spectrum) is
        # planned by its first call, which batch runs never make
        self.planner.prepare("rfft2", self.source_shape, columns=self.carrier_columns)
        self.planner.prepare("ifft2", (2,) + self.window_shape)
        self.g0 = self.decimated(ref)
        self.g0_abs = np.abs(self.g0)
        self.local_carriers = bool(local_carriers) and subbin
        self._local_inv = self._local_inverse() if self.local_carriers else None

    def _border_window(self):
        """The Tukey window of what is transformed (:attr:`source_shape`: the taper
        ``taper_px / binning`` samples wide); the border strips' widths and the
        column taper that :meth:`prepare` multiplies by."""
        s_rows, s_cols = self.source_shape
        t_r = tukey(s_rows, self.taper_px / self.binning)
        t_c = tukey(s_cols, self.taper_px / self.binning)
        # the window is 1 inside: prepare() converts the image once and
        # multiplies only the border strips (rows and columns below 1)
        self._strip_r = int(np.count_nonzero(t_r[: (s_rows + 1) // 2] < 1.0))
        self._strip_c = int(np.count_nonzero(t_c[: (s_cols + 1) // 2] < 1.0))
        self._taper_c = t_c
        return t_r[:, None] * t_c[None, :]

    def _build_windows(self, freq, q_r, q_c, shift_r, shift_c):
        """Each carrier's window of bins: where it gathers them from the real
        FFT (mirrored half conjugated), its band-pass gain and the phase ramp
        that puts the samples at ``rows_px``, ``cols_px``."""
        rows, cols = self.shape
        s_rows, s_cols = self.source_shape
        m_r, m_c = self.window_shape
        filter_shape = self.filter_shape
        self._gather = []
        self._filters = []
        self._gains = []
        self._ramps = []
        half_cols = s_cols // 2 + 1
        for s in range(2):
            cr, cc = self._centres[s]
            kr = (cr + q_r)[:, None] + np.zeros((1, m_c), np.int64)
            kc = np.zeros((m_r, 1), np.int64) + (cc + q_c)[None, :]
            if np.any(np.abs(kc) >= half_cols) or np.any(np.abs(kr) > s_rows // 2):
                # the pattern itself (a board too fine for the camera's pixels): the user's to fix, said in
                # one line (a ValueError gave a traceback and exit 1: by-hand trial of 7 Dec 2026)
                period_px = 1.0 / float(np.hypot(*freq[s]))
                raise NoCarrierError(
                    f"the pattern is too fine for the camera's pixels: carrier {s} has a period of "
                    f"{period_px:.2f} px ({abs(freq[s][0]):.3f}, {abs(freq[s][1]):.3f} cycles/px along rows, "
                    f"columns), too near the pixel grid's limit of 2 px for its filter; use a coarser board, "
                    f"more pixels on it (a longer lens, the camera nearer) or a smaller theta (carrier "
                    f"periods of 4 px or more)")
            mirror = kc < 0
            ridx = np.where(mirror, -kr, kr) % s_rows
            cidx = np.where(mirror, -kc, kc)
            flat_idx = (ridx * half_cols + cidx).ravel()
            # frequency offset of each window bin from the exact carrier, cycles/px
            df_r = kr / rows - freq[s, 0]
            df_c = kc / cols - freq[s, 1]
            dist = np.hypot(df_r, df_c) / self.radius
            if filter_shape == "disc":
                filt = (dist <= 1.0).astype(np.float32)
            else:
                filt = np.zeros_like(dist)
                filt[dist <= self.flat] = 1.0
                roll = (dist > self.flat) & (dist < 1.0)
                filt[roll] = 0.5 + 0.5 * np.cos(np.pi * (dist[roll] - self.flat) / (1.0 - self.flat))
                filt = filt.astype(np.float32)
            # evaluate at the shifted sample positions: phase ramp per bin offset
            # (the common factor of the window centre cancels in g conj(g0))
            ramp = np.exp(2j * np.pi * (q_r[:, None] * shift_r / rows + q_c[None, :] * shift_c / cols))
            self._gather.append((flat_idx, mirror.ravel()))
            # binned: the pyramid's gain undone within the band (where it is >= 0.2)
            undo = 1.0 if self.binning == 1 else 1.0 / (pyramid_gain(kr / rows) * pyramid_gain(kc / cols))
            self._filters.append((filt * ramp * undo).astype(np.complex64))
            self._gains.append(filt)
            self._ramps.append(np.conj(ramp).astype(np.complex64))
            # absolute bins for the full-grid variant (full complex spectrum)

    def _carrier_columns(self):
        """How many of the real FFT's first columns (``0 .. n - 1`` of the half spectrum) the
        carrier windows gather from, or None where that is more than 3/4 of them (then the
        whole transform costs no more)."""
        half_cols = self.source_shape[1] // 2 + 1
        used = max(int(np.max(g[0] % half_cols)) for g in self._gather) + 1
        return used if used <= 0.75 * half_cols else None

    @property
    def plan(self) -> DemodulationPlan:
        """The read-only :class:`DemodulationPlan` of this reference."""
        return DemodulationPlan(window2d=read_only(self._window2d), gather_index=read_only(self._gather_idx),
                                gather_mirror=read_only(self._gather_mirror),
                                filters=read_only(self._filter_stack), dc_leak=read_only(self._dc_leak),
                                local_inverse=read_only(self._local_inv), window_centres=read_only(self._centres))

    # ------------------------------------------------------------------ core
    def prepare(self, image, out=None) -> np.ndarray:
        """Apodized float32 copy of ``image`` (what gets transformed).

        The image keeps its mean: the mean times the border window would leak
        into the carrier bands, so :meth:`windows` subtracts that leakage
        exactly (``mean * W``, the window's own spectrum) instead of a second
        pass over the full image here.  :attr:`last_mean` holds the mean used.

        Parameters
        ----------
        image : ndarray, shape (rows, cols)
        out : ndarray, float32, optional
            Where to write (e.g. the FFT plan's input array).
        """
        if self.binning == 2:
            image = bin_pyramid(image)
        if out is None:
            out = np.empty(self.source_shape, np.float32)
        # the mean of every 4th row and column is all the leakage correction needs
        self.last_mean = float(np.mean(image[::4, ::4], dtype=np.float64))
        if self._window2d is None:
            np.subtract(image, np.float32(self.last_mean), out=out, casting="unsafe")
            self.last_mean = 0.0
        else:
            a, b = self._strip_r, self._strip_c
            rows, cols = self.source_shape
            if 2 * a >= rows or 2 * b >= cols:
                np.multiply(image, self._window2d, out=out, casting="unsafe")
                return out
            # convert once; the window is 1 except in the border strips
            if out is not image:
                np.copyto(out, image, casting="unsafe")
            w = self._window2d
            out[:a] *= w[:a]
            out[rows - a:] *= w[rows - a:]
            inner = out[a:rows - a]
            inner[:, :b] *= self._taper_c[:b]
            inner[:, cols - b:] *= self._taper_c[cols - b:]
        return out

    def spectrum(self, image) -> np.ndarray:
        """rfft2 of the prepared image: complex64, (rows, cols // 2 + 1) of :attr:`source_shape`, transient."""
        inp = self.planner.input_array("rfft2", self.source_shape)
        self.prepare(image, out=inp)
        return self.planner.execute("rfft2", self.source_shape)

    def carrier_spectrum(self, image=None, *, write=None) -> np.ndarray:
        """What :meth:`windows` reads of :meth:`spectrum`: the same array, but
        only its columns ``0 .. carrier_columns - 1`` transformed (the others
        hold row transforms, not the spectrum), 1.7 instead of 2.6 ms at
        1024^2 on one thread.  Transient, like :meth:`spectrum`.

        Parameters
        ----------
        image : ndarray, shape (rows, cols), optional
        write : callable, optional
            Instead of ``image``: ``write(array)`` puts the image straight into
            the transform's float32 input array (saves a full-size copy).
        """
        inp = self.planner.input_array("rfft2", self.source_shape)
        if write is None:
            self.prepare(image, out=inp)
        else:
            if self.binning != 1:
                raise ValueError("write= puts a frame into the transform's input: not for a binned Demodulator")
            write(inp)
            self.prepare(inp, out=inp)
        return self.planner.execute("rfft2", self.source_shape, columns=self.carrier_columns)

    def frame_windows(self, image=None, *, write=None) -> np.ndarray:
        """:meth:`windows` of ``image`` (or of what ``write`` puts into the
        transform's input; see :meth:`carrier_spectrum`)."""
        return self.windows(self.carrier_spectrum(image, write=write))

    def windows(self, spec, mean=None) -> np.ndarray:
        """Filtered windows around both carriers, ifftshift order: (2, m_rows, m_cols) complex64.

        ``mean`` (default: :attr:`last_mean` of the last :meth:`prepare`) times
        the border window's spectrum is subtracted: the image's mean removed
        exactly, where it matters.
        """
        out = np.take(spec.reshape(-1), self._gather_idx)
        if self._gather_mirror is not None:
            np.conjugate(out, out=out, where=self._gather_mirror)
        out *= self._filter_stack
        m = self.last_mean if mean is None else mean
        if m and self._dc_leak is not None:
            out -= np.complex64(m) * self._dc_leak
        return out

    def decimated_from_windows(self, wins) -> np.ndarray:
        """Analytic signals on the decimated grid from :meth:`windows` output."""
        shape = (2,) + self.window_shape
        self.planner.input_array("ifft2", shape)[...] = wins
        out = self.planner.execute("ifft2", shape, normalise=False)
        # samples sit at r = j * rows / m; the scale follows the window size
        return out * self._dec_scale

    def decimated(self, image) -> np.ndarray:
        """Analytic signals ``g_s`` of ``image`` on the decimated grid.

        Returns
        -------
        ndarray, complex64, shape (2, m_rows, m_cols)
            Carrier ``s`` signal at pixels ``(rows_px[i], cols_px[j])``,
            including the factor ``exp(2 pi i c_s . r)`` of the window centre
            (it cancels in ``g conj(g0)``).
        """
        return self.decimated_from_windows(self.frame_windows(image))

    def full_from_windows(self, wins) -> np.ndarray:
        """Analytic signals on the full pixel grid (zero-padded full-size inverse FFTs).

        Returns
        -------
        ndarray, complex64, shape (2, rows, cols)
        """
        if self.binning != 1:
            raise ValueError("a binned Demodulator gives the decimated grid only; use binning 1 for the full grid")
        rows, cols = self.shape
        out = np.empty((2, rows, cols), np.complex64)
        for s in range(2):
            inp = self.planner.input_array("ifft2", self.shape)
            inp.fill(0)
            ri, ci = self._full_index[s]
            inp[ri, ci] = wins[s] * self._ramps[s]  # full grid: no sample shift
            out[s] = self.planner.execute("ifft2", self.shape)
        return out

    # --------------------------------------------------------- conversions
    def phase_to_displacement(self, phase) -> np.ndarray:
        """Displacement ``u`` (pixels, (u_row, u_col)) from carrier phases.

        Solves ``phase_s = -k_s . u`` pointwise.

        Parameters
        ----------
        phase : ndarray, shape (2, ...)
            Unwrapped phases of both carriers, radians.

        Returns
        -------
        ndarray, float32, shape (2, ...)
        """
        if self._local_inv is not None and tuple(np.shape(phase)[1:]) == self.window_shape:
            inv = self._local_inv  # (2, 2, m_rows, m_cols), decimated grid
            phase = np.asarray(phase)
            if phase.dtype == np.float32:
                # u_i = inv_i0 phase_0 + inv_i1 phase_1, both rows in two passes
                return (inv * phase[None]).sum(axis=1)
        else:
            inv = -np.linalg.inv(self.wavevectors)
        u_r = inv[0, 0] * phase[0] + inv[0, 1] * phase[1]
        u_c = inv[1, 0] * phase[0] + inv[1, 1] * phase[1]
        return np.stack([u_r, u_c]).astype(np.float32, copy=False)

    def _local_inverse(self):
        """``-K(r)^-1`` per decimated sample from the reference's local carriers.

        The decimated ``g0`` carries ``exp(-2 pi i c . r / N)`` of its window
        centre ``c``, so the local wavevector is ``2 pi c / N`` plus the phase
        gradient of ``g0``.  Gradients come from neighbour products (central,
        one-sided at the edges), box-smoothed over 5 x 5 samples; where the
        reference has little contrast or the estimate strays more than 10 %
        from the global carrier, the global one is used.
        """
        rows, cols = self.shape
        m_r, m_c = self.window_shape
        step_r, step_c = rows / m_r, cols / m_c
        K = np.empty((2, 2, m_r, m_c))
        weak = self.g0_abs.min(axis=0) < 0.25 * np.median(self.g0_abs.min(axis=0))
        for s in range(2):
            g = self.g0[s].astype(np.complex128)
            pr = np.empty_like(g)
            pc = np.empty_like(g)
            pr[1:-1] = g[2:] * np.conj(g[:-2])
            pr[0] = (g[1] * np.conj(g[0])) ** 2
            pr[-1] = (g[-1] * np.conj(g[-2])) ** 2
            pc[:, 1:-1] = g[:, 2:] * np.conj(g[:, :-2])
            pc[:, 0] = (g[:, 1] * np.conj(g[:, 0])) ** 2
            pc[:, -1] = (g[:, -1] * np.conj(g[:, -2])) ** 2
            for p in (pr, pc):
                re = cv2.blur(np.ascontiguousarray(p.real), (5, 5), borderType=cv2.BORDER_REPLICATE)
                im = cv2.blur(np.ascontiguousarray(p.imag), (5, 5), borderType=cv2.BORDER_REPLICATE)
                p[...] = re + 1j * im
            c_r, c_c = self._centres[s]
            K[s, 0] = 2 * np.pi * c_r / rows + np.angle(pr) / (2 * step_r)
            K[s, 1] = 2 * np.pi * c_c / cols + np.angle(pc) / (2 * step_c)
            glob = self.wavevectors[s]
            stray = np.hypot(K[s, 0] - glob[0], K[s, 1] - glob[1]) > 0.1 * np.hypot(*glob)
            bad = weak | stray
            K[s, 0][bad] = glob[0]
            K[s, 1][bad] = glob[1]
        det = K[0, 0] * K[1, 1] - K[0, 1] * K[1, 0]
        inv = np.empty_like(K)
        inv[0, 0] = -K[1, 1] / det
        inv[0, 1] = K[0, 1] / det
        inv[1, 0] = K[1, 0] / det
        inv[1, 1] = -K[0, 0] / det
        return inv.astype(np.float32)

    def displacement_to_phase(self, u) -> np.ndarray:
        """Carrier phases (radians) ``-k_s . u`` of a displacement (2, ...) in pixels."""
        K = self.wavevectors
        return -np.stack([K[s, 0] * u[0] + K[s, 1] * u[1] for s in range(2)])

    def filter_transfer(self) -> np.ndarray:
        """Filter gains on the decimated spectrum grid, (2, m_rows, m_cols), ifftshift order."""
        return np.stack(self._gains)

    @property
    def border_window(self):
        """The (rows, cols) float32 border window that :meth:`prepare` applies
        (1 inside, cosine taper at the borders); None for ``border="none"``
        (then :meth:`prepare` removes the mean instead)."""
        return self._window2d
