"""Live alignment metrics of a checkerboard frame against a reference, at the cost of one FFT.

What the Alignment tab shows (carrier periods, rotation, theta from the
pattern's aspect, contrast, focus, saturation and the spectrum) used to cost
three full-size FFTs and a search over the whole spectrum
(:func:`processing.carriers.find_carriers_live`): 3-8x the live heights. With a
reference the frame's carriers lie near the reference's, so here:

- **One FFT**: the demodulator's spectrum of the frame (its border window,
  mean removed through the window's own spectrum). The modulation map comes
  from its carrier windows exactly as the reconstruction's analytic signals do;
  :func:`processing.half_spectrum.display_spectrum_of` reads only the part of it that is shown.
- **The carrier search's spectrum from that one**: multiplying an image by the
  Hann window ``0.5 - 0.5 cos(2 pi (j + 1/2) / n)`` is, exactly, the 3-tap
  stencil ``X_h[k] = X[k] / 2 - e^(i pi/n) X[k-1] / 4 - e^(-i pi/n) X[k+1] / 4``
  along each axis (:func:`hann_stencil`). The demodulator's border window is 1
  except within one period of the border, where the Hann window is already
  below 1e-2, so the product is the Hann-windowed frame of
  :func:`~processing.carriers.find_carriers` to that border's weight.
- **The same tests, near the reference's carriers only**: in a patch around
  each reference carrier (:class:`CarrierSearch`: +-12 % of its frequency, at
  least 3 bins) the strongest bin must be isolated (:data:`~processing.carriers.MIN_ISOLATION`)
  and stand :data:`~processing.carriers.MIN_PEAK_CONTRAST` above the mean
  log level of its rings, then the same phase-slope refinement and peak
  sharpness (focus) as ``find_carriers``.
- **Moving water**: where those peaks are smeared, the same tiles as
  :func:`~processing.carriers.find_carriers_local`, all in one batched FFT,
  searched the same way near the reference's carriers (:func:`tile_carriers_near`).

Anything else (no peak within the patch: another pattern, a moved camera, no
pattern at all) falls back to ``find_carriers_live`` on the frame: the numbers
and messages of the slow path, at its cost. Measured in
``benchmarks/bench_alignment.py``; tests/processing/test_alignment.py compares
both paths on ray-traced frames.

Frequencies are cycles per pixel ``(f_row, f_col)``, bins are
``(f_row * rows, f_col * cols)``.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import zlib
from typing import Optional

import numpy as np
import scipy.fft

from .carriers import (ISOLATION_RING_BINS, ISOLATION_RING_DC, ISOLATION_RING_DR, MIN_ISOLATION, MIN_PEAK_CONTRAST,
                       Carriers, find_carriers, find_carriers_live, find_carriers_local, hann, match_error,
                       theta_from_carriers, tile_origins)
from .errors import NoCarrierError
from .half_spectrum import display_spectrum_of, half_spectrum_index

__all__ = ["CarrierSearch", "carrier_search", "carriers_without_reference", "checkerboard_alignment", "frame_carriers",
           "frame_key", "hann_stencil", "patch_peaks", "tile_carriers_near", "modulation_map", "whole_image_carriers"]

#: Half width of the search around each reference carrier, as a fraction of
#: its distance to DC (at least :data:`MIN_SEARCH_BINS`): a pattern or camera
#: moved by more (periods 12 % off, or rotated by about 7 deg) is found by the
#: full search instead.
SEARCH_FRACTION = 0.12
MIN_SEARCH_BINS = 3
#: Bins of the floor under the magnitude, relative to the peak (as find_carriers' floor).
_FLOOR = 1e-6
_REFINE_HALF = 4  # +-bins of the phase-slope refinement (find_carriers' _refine)
_MARGIN = max(ISOLATION_RING_BINS[1], _REFINE_HALF)


# ------------------------------------------------------------------ spectra
def hann_stencil(shape, kr, kc) -> tuple:
    """Indices, conjugation flags and weights of the Hann window as a 3 x 3 stencil in frequency.

    ``sum_j weights[j] * X[index[j]]`` (conjugated where ``conj[j]``) is the
    DFT at bins ``(kr, kc)`` of the image times ``hann(rows) x hann(cols)``
    (:func:`processing.carriers.hann`), given the rfft2 half spectrum ``X`` of
    the image (exact: the window is a sum of three complex exponentials).

    Returns
    -------
    (index (9, ...), conj (9, ...), weights (9,) complex128)
    """
    rows, cols = shape

    def taps(n):
        return ((0, 0.5), (-1, -0.25 * np.exp(1j * np.pi / n)), (1, -0.25 * np.exp(-1j * np.pi / n)))

    idx, conj, w = [], [], []
    for a, wa in taps(rows):
        for b, wb in taps(cols):
            i, c = half_spectrum_index(shape, np.asarray(kr) + a, np.asarray(kc) + b)
            idx.append(i)
            conj.append(c)
            w.append(wa * wb)
    return np.stack(idx), np.stack(conj), np.array(w)


def _apply_stencil(half_flat, stencil) -> np.ndarray:
    idx, conj, w = stencil
    vals = half_flat[idx]
    np.conjugate(vals, out=vals, where=conj)
    # a plain weighted sum: tensordot would call BLAS, whose threads spin on a loaded machine
    out = vals[0] * w[0]
    for j in range(1, len(w)):
        out += vals[j] * w[j]
    return out


# ------------------------------------------------------------ peak tests
def patch_peaks(patches, search_bins: int) -> dict:
    """The carrier tests of :func:`~processing.carriers.find_carriers` on patches of a Hann spectrum.

    Parameters
    ----------
    patches : ndarray, complex, shape (T, n, n)
        Hann-windowed spectra around the expected carrier bin (at the centre
        ``n // 2``), ``n >= 2 * (search_bins + 7) + 1``.
    search_bins : int
        The strongest bin within +-this of the centre is the candidate.

    Returns
    -------
    dict of (T,) arrays
        ``d_row``, ``d_col`` (int, its offset from the centre), ``inside``
        (not on the edge of the search: a peak beyond it may be stronger),
        ``amplitude`` (floored magnitude), ``isolation`` (over the largest
        magnitude 4-7 bins away), ``offset`` (T, 2): sub-bin offset of the
        carrier from that bin (mean phase slope of the +-4-bin window),
        ``sharpness`` (energy in the central 3 x 3 of the 5 x 5 bins).
    """
    patches = np.asarray(patches)
    T, n, _ = patches.shape
    h, s = n // 2, int(search_bins)
    mag = np.abs(patches).astype(np.float64)
    top = mag.reshape(T, -1).max(axis=1)
    mag = np.maximum(mag, (_FLOOR * top + 1e-30)[:, None, None])
    region = mag[:, h - s:h + s + 1, h - s:h + s + 1].reshape(T, -1)
    k = np.argmax(region, axis=1)
    d_row, d_col = np.divmod(k, 2 * s + 1)
    d_row, d_col = d_row - s, d_col - s
    inside = (np.abs(d_row) < s) & (np.abs(d_col) < s)
    t = np.arange(T)[:, None]
    pr, pc = h + d_row, h + d_col
    amp = mag[np.arange(T), pr, pc]
    ring = mag[t, pr[:, None] + ISOLATION_RING_DR[None], pc[:, None] + ISOLATION_RING_DC[None]]
    isolation = amp / np.maximum(ring.max(axis=1), 1e-300)
    # sub-bin frequency: phase slope of the demodulated +-4-bin window (find_carriers' _refine)
    q = np.arange(-_REFINE_HALF, _REFINE_HALF + 1)
    m = q.size
    win = patches[t[:, :, None], pr[:, None, None] + q[None, :, None], pc[:, None, None] + q[None, None, :]]
    field = np.fft.ifft2(np.fft.ifftshift(win, axes=(-2, -1)))
    a_r = np.sum(field[:, 1:, :] * np.conj(field[:, :-1, :]), axis=(1, 2))
    a_c = np.sum(field[:, :, 1:] * np.conj(field[:, :, :-1]), axis=(1, 2))
    offset = np.stack([np.angle(a_r), np.angle(a_c)], axis=1) * m / (2.0 * np.pi)
    q5 = np.arange(-2, 3)
    e = mag[t[:, :, None], pr[:, None, None] + q5[None, :, None], pc[:, None, None] + q5[None, None, :]] ** 2
    sharpness = e[:, 1:4, 1:4].sum(axis=(1, 2)) / np.maximum(e.sum(axis=(1, 2)), 1e-300)
    return {"d_row": d_row, "d_col": d_col, "inside": inside, "amplitude": amp, "isolation": isolation,
            "offset": offset, "sharpness": sharpness}


def _ring_of(shape, kr, kc):
    """find_carriers' ring index (one bin wide, in units of the longer side) of bins (kr, kc)."""
    rows, cols = shape
    big = max(rows, cols)
    return np.minimum((np.hypot(np.asarray(kr) / rows, np.asarray(kc) / cols) * big).astype(np.int64), big)


def _allowed(shape, freq, min_period_px=2.5):
    """find_carriers' band: periods from ``min_period_px`` to a quarter of the smaller side."""
    radius = float(np.hypot(*freq))
    return 4.0 / min(shape) <= radius <= 1.0 / min_period_px


# ------------------------------------------------------------ whole image
@dataclasses.dataclass(frozen=True)
class CarrierSearch:
    """What the fast search needs that depends only on the reference (built once).

    Attributes
    ----------
    shape : tuple
        Frame (rows, cols).
    centres : ndarray, int (2, 2)
        Reference carrier bins ``(kr, kc)``, the centres of the patches.
    search_bins : ndarray, int (2,)
        Half width of the search of each carrier.
    patch_stencils : list of 2
        :func:`hann_stencil` of each carrier's patch.
    patch_leak : list of 2 ndarrays or None
        The Hann stencil applied to the border window's spectrum on each patch
        (times the frame's mean: what the demodulator's spectrum still holds of it).
    rings : list of 2 dicts
        Per carrier, the half-plane bins of the rings its peak's level may
        need, sorted by ring: ``first`` (ring of ``start[0]``), ``start``
        (offsets of each ring), ``stencil``, ``leak``.
    window_spectrum : ndarray or None
        rfft2 of the border window, complex64.
    """

    shape: tuple
    reference_freq: np.ndarray
    centres: np.ndarray
    search_bins: np.ndarray
    patch_stencils: list
    patch_leak: Optional[list]
    rings: list
    window_spectrum: Optional[np.ndarray]


def carrier_search(shape, reference_freq, border_window=None) -> CarrierSearch:
    """Build the :class:`CarrierSearch` of frames of ``shape`` around ``reference_freq`` (2, 2)."""
    rows, cols = shape
    freq = np.asarray(reference_freq, float)
    wspec = None if border_window is None else np.fft.rfft2(border_window).astype(np.complex64)
    wflat = None if wspec is None else wspec.reshape(-1)
    centres = np.round(freq * np.array([rows, cols])).astype(np.int64)
    search = np.maximum(MIN_SEARCH_BINS, np.ceil(SEARCH_FRACTION * np.hypot(*(freq * np.array([rows, cols])).T)))
    search = search.astype(np.int64)
    stencils, leaks, rings = [], [] if wflat is not None else None, []
    fr_all = np.fft.fftfreq(rows) * rows  # signed row bins, fftfreq order
    big = max(rows, cols)
    for s in range(2):
        h = int(search[s]) + _MARGIN
        q = np.arange(-h, h + 1)
        st = hann_stencil(shape, centres[s, 0] + q[:, None], centres[s, 1] + q[None, :])
        stencils.append(st)
        if leaks is not None:
            leaks.append(_apply_stencil(wflat, st))
        # rings of every bin the search may pick, +-3 for the smoothing of the ring profile
        ring_patch = _ring_of(shape, centres[s, 0] + q[:, None], centres[s, 1] + q[None, :])
        lo, hi = max(int(ring_patch.min()) - 3, 0), min(int(ring_patch.max()) + 3, big)
        r_keep = fr_all[np.abs(fr_all) * big / rows <= hi + 1].astype(np.int64)
        c_keep = np.arange(cols // 2 + 1)
        c_keep = c_keep[c_keep * big / cols <= hi + 1]
        kr, kc = np.meshgrid(r_keep, c_keep, indexing="ij")
        ring = _ring_of(shape, kr, kc)
        sel = (ring >= lo) & (ring <= hi)
        kr, kc, ring = kr[sel], kc[sel], ring[sel]
        order = np.argsort(ring, kind="stable")
        kr, kc, ring = kr[order], kc[order], ring[order]
        start = np.searchsorted(ring, np.arange(lo, hi + 2))
        st_r = hann_stencil(shape, kr, kc)
        rings.append({"first": lo, "start": start, "stencil": st_r,
                      "leak": None if wflat is None else _apply_stencil(wflat, st_r)})
    return CarrierSearch(shape=(rows, cols), reference_freq=freq, centres=centres, search_bins=search,
                         patch_stencils=stencils, patch_leak=leaks, rings=rings, window_spectrum=wspec)


def _ring_level(search: CarrierSearch, s: int, half_flat, mean: float, ring: int, amp_floor: float) -> float:
    """find_carriers' background at ``ring``: mean over rings ring-3..ring+3 of
    each ring's mean log magnitude (Hann spectrum)."""
    tab = search.rings[s]
    i0 = ring - 3 - tab["first"]
    a, b = tab["start"][i0], tab["start"][i0 + 7]
    idx, conj, w = tab["stencil"]
    vals = _apply_stencil(half_flat, (idx[:, a:b], conj[:, a:b], w))
    if tab["leak"] is not None and mean:
        vals = vals - mean * tab["leak"][a:b]
    logs = np.log(np.maximum(np.abs(vals), amp_floor) + 1e-30)
    starts = tab["start"][i0:i0 + 7] - a
    per_ring = np.add.reduceat(logs, starts) / np.diff(np.append(starts, b - a))
    return float(per_ring.mean())


def _order(freq, sharp):
    """find_carriers' order: the first carrier has the smaller f_row; f_col >= 0."""
    freq = np.array(freq, float)
    flip = freq[:, 1] < 0
    freq[flip] *= -1.0
    if freq[0, 0] > freq[1, 0]:
        return freq[::-1].copy(), np.asarray(sharp)[::-1].copy()
    return freq, np.asarray(sharp)


def _order_tiles(freq, sharp):
    """:func:`_order` of every tile: ``freq`` (T, 2, 2), ``sharp`` (T, 2) -> new arrays."""
    freq = np.array(freq, float)
    sharp = np.array(sharp, float)
    freq *= np.where(freq[:, :, 1:] < 0, -1.0, 1.0)
    swap = freq[:, 0, 0] > freq[:, 1, 0]
    freq[swap] = freq[swap][:, ::-1]
    sharp[swap] = sharp[swap][:, ::-1]
    return freq, sharp


def whole_image_carriers(search: CarrierSearch, half_spectrum, mean: float = 0.0):
    """Carriers of a frame from the demodulator's half spectrum, near the reference's.

    Parameters
    ----------
    search : CarrierSearch
    half_spectrum : ndarray, complex (rows, cols // 2 + 1)
        rfft2 of the frame times the border window (mean kept).
    mean : float
        The mean the border window's spectrum is to be scaled by (the
        demodulator's ``last_mean``).

    Returns
    -------
    (Carriers or None, why)
        None with ``why`` = ``"smeared"`` (peaks near the reference's that are
        not isolated or too weak: the surface moves) or ``"elsewhere"`` (the
        strongest bin is at the edge of the search, or out of band).
    """
    flat = np.asarray(half_spectrum).reshape(-1)
    freqs, sharps, why = [], [], None
    for s in range(2):
        patch = _apply_stencil(flat, search.patch_stencils[s])
        if search.patch_leak is not None and mean:
            patch = patch - mean * search.patch_leak[s]
        p = patch_peaks(patch[None], int(search.search_bins[s]))
        kr = int(search.centres[s, 0] + p["d_row"][0])
        kc = int(search.centres[s, 1] + p["d_col"][0])
        f = np.array([(kr + p["offset"][0, 0]) / search.shape[0], (kc + p["offset"][0, 1]) / search.shape[1]])
        if not p["inside"][0] or not _allowed(search.shape, f):
            return None, "elsewhere"
        amp = float(p["amplitude"][0])
        floor = _FLOOR * float(np.abs(patch).max()) + 1e-30
        level = _ring_level(search, s, flat, mean, int(_ring_of(search.shape, kr, kc)), floor)
        contrast = amp / math.exp(level)
        if p["isolation"][0] < MIN_ISOLATION or contrast < MIN_PEAK_CONTRAST:
            why = "smeared"
        freqs.append(f)
        sharps.append(float(p["sharpness"][0]))
    if why is not None:
        return None, why
    freq, sharp = _order(freqs, sharps)
    return Carriers(freq=freq, shape=tuple(search.shape), contrast=np.full(2, np.nan), sharpness=sharp), None


@functools.lru_cache(maxsize=16)
def _tile_rings(size: int, centres, searches):
    """``(ring, sel, lo, counts)`` of :func:`tile_carriers_near`'s ``size`` px tiles: every
    half-spectrum bin's ring (flat), the bins of the rings ``lo .. hi`` that the searches
    around ``centres`` (bins, one per carrier) with ``searches`` bins can read, smoothing
    included (+-3 rings), and each of those rings' bin count."""
    fr = np.fft.fftfreq(size) * size
    ring = _ring_of((size, size), fr[:, None], np.arange(size // 2 + 1)[None, :]).ravel()
    reach = []
    for (r0, c0), search in zip(centres, searches):
        q = np.arange(-search, search + 1)
        reach.append(_ring_of((size, size), r0 + q[:, None], c0 + q[None, :]))
    n_rings = size + 1
    lo = max(0, min(int(r.min()) for r in reach) - 3)
    hi = min(n_rings - 1, max(int(r.max()) for r in reach) + 3)
    sel = np.flatnonzero((ring >= lo) & (ring <= hi))
    counts = np.bincount(ring[sel] - lo, minlength=hi - lo + 1)
    return ring, sel, lo, counts


# ------------------------------------------------------------ tiles
def tile_carriers_near(frame, reference_freq, *, max_tiles: int = 64, min_fraction: float = 1.0 / 3.0):
    """:func:`~processing.carriers.find_carriers_local` near known carriers, all tiles in one FFT.

    The same tiles (:func:`~processing.carriers.tile_origins`, 64 px, else
    128 px), each Hann-windowed and mean-free; in each, near each reference
    carrier, the tests of :func:`patch_peaks` against the tile's own ring
    levels; the component-wise median of the tiles where both carriers pass.

    Returns
    -------
    Carriers or None
        None if too few tiles (below ``min_fraction``) show both carriers.
        ``contrast`` is NaN; ``sharpness`` the tiles' median.
    """
    img = np.asarray(frame, np.float32)
    rows, cols = img.shape
    freq_ref = np.asarray(reference_freq, float)
    for size in (s for s in (64, 128) if s <= min(rows, cols)):
        r0s, c0s = tile_origins((rows, cols), size, max_tiles)
        tiles = np.stack([img[r0:r0 + size, c0:c0 + size] for r0 in r0s for c0 in c0s])
        tiles = tiles - tiles.mean(axis=(1, 2), keepdims=True)
        w = hann(size)
        tiles *= w[:, None] * w[None, :]
        spec = scipy.fft.rfft2(tiles, axes=(-2, -1), workers=2)
        T = spec.shape[0]
        flat = spec.reshape(T, -1)
        mag = np.abs(flat)
        floor = (_FLOOR * mag.max(axis=1).astype(np.float64) + 1e-30)[:, None]
        searches = [max(MIN_SEARCH_BINS, int(math.ceil(SEARCH_FRACTION * np.hypot(*(freq_ref[s] * size)))))
                    for s in range(2)]
        # each tile's ring profile, smoothed over +-3 rings (find_carriers), of the rings the
        # carriers' searches can read (the others are not needed: measured 2 of 7 ms at 512^2)
        ring, sel, lo, counts = _tile_rings(size, tuple(map(tuple, np.round(freq_ref * size).astype(int))),
                                            tuple(searches))
        logs = np.log(np.maximum(mag[:, sel].astype(np.float64), floor) + 1e-30)
        n_rings = counts.size
        lab = (np.arange(T)[:, None] * n_rings + (ring[sel] - lo)[None, :]).ravel()
        sums = np.bincount(lab, weights=logs.ravel(), minlength=T * n_rings).reshape(T, n_rings)
        prof = np.pad(sums / np.maximum(counts, 1), ((0, 0), (3, 3)), mode="edge")
        c = np.cumsum(np.pad(prof, ((0, 0), (1, 0))), axis=1)
        level = (c[:, 7:] - c[:, :-7]) / 7.0  # (T, rings lo .. hi)
        ok = np.ones(T, bool)
        freqs = np.empty((T, 2, 2))
        sharps = np.empty((T, 2))
        for s in range(2):
            centre = np.round(freq_ref[s] * size).astype(np.int64)
            search = searches[s]
            h = search + _MARGIN
            q = np.arange(-h, h + 1)
            idx, conj = half_spectrum_index((size, size), centre[0] + q[:, None], centre[1] + q[None, :])
            patch = flat[:, idx]
            np.conjugate(patch, out=patch, where=conj[None])
            p = patch_peaks(patch, search)
            kr, kc = centre[0] + p["d_row"], centre[1] + p["d_col"]
            f = np.stack([kr + p["offset"][:, 0], kc + p["offset"][:, 1]], axis=1) / size
            radius = np.hypot(f[:, 0], f[:, 1])
            contrast = p["amplitude"] / np.exp(level[np.arange(T), _ring_of((size, size), kr, kc) - lo])
            ok &= (p["inside"] & (p["isolation"] >= MIN_ISOLATION) & (contrast >= MIN_PEAK_CONTRAST)
                   & (radius >= 4.0 / size) & (radius <= 1.0 / 2.5))
            freqs[:, s] = f
            sharps[:, s] = p["sharpness"]
        if np.count_nonzero(ok) and np.count_nonzero(ok) >= min_fraction * T:
            f, sh = _order_tiles(freqs[ok], sharps[ok])
            return Carriers(freq=np.median(f, axis=0), shape=(rows, cols), contrast=np.full(2, np.nan),
                            sharpness=np.median(sh, axis=0))
    return None


def _seed_tiles(r0s, c0s) -> list:
    """Five of :func:`~processing.carriers.tile_origins`' tiles: the centre one, one in each quarter."""
    def at(origins, quarter):
        return int(origins[min(len(origins) - 1, (quarter * len(origins)) // 4)])

    return [(at(r0s, 2), at(c0s, 2)), (at(r0s, 1), at(c0s, 1)), (at(r0s, 1), at(c0s, 3)),
            (at(r0s, 3), at(c0s, 1)), (at(r0s, 3), at(c0s, 3))]


def _agreed_seed(seeds, size):
    """The median of the tiles' carriers ``seeds`` (k, 2, 2) if each is within 2 bins (of a ``size``-px tile)
    of it and it lies 2 bins or more off the mirror line ``f_col`` 0 (either sign, either order there)."""
    seed = np.median(seeds, axis=0)
    if np.abs(seeds - seed).max() * size > 2.0 or np.abs(seed[:, 1]).min() * size < 2.0:
        return None
    return seed


def carriers_without_reference(frame, half_spectrum=None) -> tuple:
    """``(Carriers, disturbed)`` of a live frame before a reference: :func:`~processing.carriers.find_carriers_live`'s
    numbers. The whole image's search (on ``half_spectrum``, its ``windowed_spectrum``, if given); where
    its peaks are smeared, five tiles' full search gives carriers to look near (:func:`_agreed_seed`) and
    all tiles are searched there in one FFT (:func:`tile_carriers_near`); else ``find_carriers_local``.
    The tank's waves: within 6e-7 px and 6e-6 deg, 16-17 instead of 57-61 ms at 512^2, 33-36 instead of
    79-89 ms at 1024^2. Raises NoCarrierError as ``find_carriers_live``."""
    img = np.asarray(frame, np.float32)
    try:
        return find_carriers(img, half_spectrum=half_spectrum), False
    except NoCarrierError as whole:
        for size in (s for s in (64, 128) if s <= min(img.shape)):
            seeds = []
            for r0, c0 in _seed_tiles(*tile_origins(img.shape, size)):
                try:
                    seeds.append(find_carriers(img[r0:r0 + size, c0:c0 + size]).freq)
                except NoCarrierError:
                    continue
            if seeds:
                seed = _agreed_seed(np.array(seeds), size)
                local = None if seed is None else tile_carriers_near(img, seed)
                if local is not None:
                    return local, True
                break
        try:
            return find_carriers_local(img), True
        except NoCarrierError:
            raise whole from None


def frame_carriers(search: CarrierSearch, frame, half_spectrum, mean: float = 0.0) -> tuple:
    """``(Carriers, disturbed)`` of a live frame, as :func:`~processing.carriers.find_carriers_live`.

    The whole image's peaks near the reference's (:func:`whole_image_carriers`);
    if they are smeared, local tiles (:func:`tile_carriers_near`,
    ``disturbed=True``); otherwise, or if the tiles fail too,
    ``find_carriers_live(frame)`` itself (its numbers, its errors).

    Raises
    ------
    NoCarrierError
        The frame shows no checkerboard.
    """
    found, why = whole_image_carriers(search, half_spectrum, mean)
    if found is not None:
        return found, False
    if why == "smeared":
        local = tile_carriers_near(frame, search.reference_freq)
        if local is not None:
            return local, True
    return find_carriers_live(frame)


# ------------------------------------------------------------ modulation
@functools.lru_cache(maxsize=8)
def _local_mean_layout(shape, window_shape, radius: float) -> tuple:
    """Bins of the DC window (ifftshift order) and its radial low-pass, for :func:`modulation_map`."""
    rows, cols = shape
    m_r, m_c = window_shape
    q_r = np.fft.fftfreq(m_r, 1.0 / m_r).astype(np.int64)
    q_c = np.fft.fftfreq(m_c, 1.0 / m_c).astype(np.int64)
    idx, conj = half_spectrum_index(shape, q_r[:, None], q_c[None, :])
    f = np.hypot(q_r[:, None] / rows, q_c[None, :] / cols) / radius
    lp = (np.clip(1.0 - f, 0.0, 1.0) ** 2).astype(np.float32)
    return idx, conj, lp


def modulation_map(demod, half_spectrum, frame) -> tuple:
    """``(modulation, amplitude)`` on the decimated grid from the demodulator's spectrum of ``frame``.

    ``modulation``: fundamental-band contrast ``sqrt(2 (|g1|^2 + |g2|^2))`` over
    the local mean (the DC band through a radial low-pass of the filter's
    radius), about 0.8 for full-scale sharp squares; ``amplitude``:
    ``min_s |g_s| / |g0_s|``. Both float32 (m_rows, m_cols).
    """
    d = demod
    wins = d.windows(half_spectrum)
    g = d.decimated_from_windows(wins)
    m_r, m_c = d.window_shape
    rows, cols = d.shape
    idx, conj, lp = _local_mean_layout(tuple(d.shape), tuple(d.window_shape), float(d.radius))
    vals = np.asarray(half_spectrum).reshape(-1)[idx]
    np.conjugate(vals, out=vals, where=conj)
    vals *= lp
    # the demodulator's planner: FFTW, one thread for this small transform (pocketfft's two threads
    # took 5x longer on a loaded machine)
    mean = d.planner.ifft2(vals.astype(np.complex64, copy=False)).real * np.float32(m_r * m_c / (rows * cols))
    if d.border_window is None:
        # prepare() removed the mean (no border window to leak): add it back
        mean = mean + float(np.mean(frame, dtype=np.float64))
    # with a border window both g and the local mean carry it: it cancels in the ratio
    std = np.sqrt(2.0 * (np.abs(g[0]) ** 2 + np.abs(g[1]) ** 2))
    mod = (std / np.maximum(mean, 1e-6 * max(float(np.abs(mean).max()), 1e-30))).astype(np.float32)
    amplitude = (np.abs(g) / np.maximum(d.g0_abs, 1e-30)).min(axis=0).astype(np.float32)
    return mod, amplitude


# ------------------------------------------------------------ all of it
def frame_key(frame) -> tuple:
    """``(shape, dtype, crc32 of the pixels)``: tells whether two calls got the same frame."""
    a = np.ascontiguousarray(frame)
    return a.shape, a.dtype.str, zlib.crc32(a.reshape(-1).view(np.uint8))


def checkerboard_alignment(demod, search: CarrierSearch, reference: Carriers, frame, *,
                           theta_configured_deg: Optional[float], pattern_stretch_y: float = 1.0,
                           spectrum_size: int = 256, spectrum_max_freq: float = 0.25) -> tuple:
    """The Alignment tab's numbers and spectrum of a checkerboard frame (one FFT; see the module doc).

    Parameters
    ----------
    demod : processing.demodulation.Demodulator
        Of the reference.
    search : CarrierSearch
        :func:`carrier_search` of the reference's carriers.
    reference : Carriers
        The reference's carriers.
    frame : ndarray (rows, cols)
    theta_configured_deg : float or None
        The geometry's theta (None: FS-SS, no theta).
    pattern_stretch_y : float
        The geometry's board aspect (theta from the aspect divides it out).

    spectrum_size, spectrum_max_freq : int, float
        Of the display spectrum (:func:`display_spectrum_of`).

    Returns
    -------
    (metrics, spectrum)
        ``metrics``: the keys of :meth:`processing.reconstruct.Reconstructor.alignment`
        but ``saturation_pct``; ``spectrum``: :func:`display_spectrum_of` of
        the same FFT (the mean's peak at DC removed).
    """
    out = {
        "reference_periods_px": np.asarray(reference.periods_px, float),
        "reference_rotation_deg": float(reference.rotation_deg),
        "theta_configured_deg": theta_configured_deg,
    }
    # the plan's output is transient: read it (modulation, carriers) before any other FFT of that plan
    spec = demod.spectrum(frame)
    leak = None if search.window_spectrum is None else (demod.last_mean, search.window_spectrum)
    shown = display_spectrum_of(spec, demod.shape, leak=leak, size=spectrum_size, max_freq=spectrum_max_freq)
    mod, amplitude = modulation_map(demod, spec, frame)
    out.update(modulation=mod, modulation_rows_px=demod.rows_px, modulation_cols_px=demod.cols_px,
               contrast=float(np.median(mod)), amplitude=amplitude)
    try:
        c, disturbed = frame_carriers(search, frame, spec, float(demod.last_mean))
    except NoCarrierError as exc:
        out.update(periods_px=np.full(2, np.nan), rotation_deg=float("nan"),
                   theta_estimate_deg=float("nan"), focus=0.0, error=str(exc))
        return out, shown
    theta = theta_configured_deg if theta_configured_deg is not None else 0.0
    out.update(periods_px=np.asarray(c.periods_px, float), carrier_freq=np.asarray(c.freq, float),
               rotation_deg=float(c.rotation_deg),
               surface_rotation_deg=c.surface_rotation_deg(theta),
               theta_estimate_deg=theta_from_carriers(c.freq, pattern_stretch_y or 1.0),
               focus=float(np.min(c.sharpness)), disturbed=disturbed,
               pattern_mismatch=dict(zip(("period_rel", "angle_deg"), match_error(reference, c.freq))))
    return out, shown
