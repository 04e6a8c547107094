"""Phase unwrapping of carrier phases, in space and in time.

Fourier demodulation reads displacement as a phase, known modulo 2 pi.
Ordinary experiments exceed pi (notes.md: a 15 um dimple at H = 300 mm,
theta = 55 deg, 2 mm period drives the y-carrier to about 5 rad), so the
phase is unwrapped:

- in space: :func:`unwrap_spatial`: compiled quality-guided path following
  over the whole map (:mod:`processing.unwrap_kernels`), accepted if every
  valid neighbour pair then differs by at most pi or its only jumps are
  sides of residues among valid samples, which no unwrapping removes;
  otherwise least squares of the wrapped phase differences (DCT Poisson
  solve, Ghiglia & Romero 1994) rounded to the congruent 2 pi multiple,
  accepted under the first test; otherwise the few
  inconsistent spots (residues next to masked samples) are cut out with a
  margin, path-followed there and re-anchored on the least-squares result,
  accepted under the same test; only if that fails, reliability-sorted path
  following of scikit-image (Herraez et al. 2002) over the whole map with
  the invalid samples masked out;
  the result is shifted by the multiple of 2 pi that puts the reference
  region's median phase nearest to 0;
- in time: :func:`unwrap_temporal` adds the wrapped change since the
  previous frame of a series (itself unwrapped spatially, which is trivial
  when frames come fast), so a phase that grew smoothly through several pi
  over a series comes out right even where space alone is ambiguous
  (islands cut off by a masked region); samples valid only in this frame
  (a masked spot moved) are path-followed from their unwrapped neighbours
  (up to 16 steps), and only those beyond reach from a spatial unwrapping.
"""

from __future__ import annotations

import functools

import numpy as np
import scipy.fft
from scipy import ndimage
from skimage.restoration import unwrap_phase

from .regions import connected_regions
from .unwrap_kernels import flood_fill, grow_into, jump_over_pi, jumps_off_residues, path_follow, scan_fill

__all__ = ["wrap", "median_turn", "unwrap_spatial", "unwrap_temporal", "has_wraps", "jumps_only_at_residues"]

TWO_PI = 2.0 * np.pi
#: :func:`median_turn`'s sparse sample: about this many values.
MEDIAN_TURN_SAMPLE = 512
_NO_MASK = np.ones((1, 1), dtype=bool)  # stands for "no mask" in jump_over_pi's signature


def wrap(phase):
    """Phase wrapped into [-pi, pi] (same dtype; +-pi may come out either way)."""
    phase = np.asarray(phase)
    two_pi = phase.dtype.type(TWO_PI) if phase.dtype.kind == "f" else TWO_PI
    return phase - two_pi * np.rint(phase / two_pi)


def median_turn(values) -> float:
    """``2 pi round(median(values) / 2 pi)``: the 2 pi multiple nearest the
    median of ``values`` (radians, 1-D).  Read from the two extremes when
    they round to the same multiple (the median lies between them, and
    rounding keeps the order: the same number, two reductions instead of a
    partition); else, for many values, the multiple of a sparse sample's
    median, kept when counting shows the median's two middle values inside
    that multiple's interval ``((2k - 1) pi, (2k + 1) pi)`` (the same number:
    two comparisons instead of a partition, 0.1 -> 0.03 ms on a 160^2 live
    map); else from the median itself."""
    values = np.asarray(values)
    n = values.size
    if n:
        lo = np.round(float(values.min()) / TWO_PI)
        if lo == np.round(float(values.max()) / TWO_PI):
            return TWO_PI * lo
        if n > 4 * MEDIAN_TURN_SAMPLE:
            turn = np.round(np.median(values[:: n // MEDIAN_TURN_SAMPLE]) / TWO_PI)  # the median's type
            k = float(turn)
            # sorted v: v[(n - 1) // 2] > (2k - 1) pi and v[n // 2] < (2k + 1) pi
            if (np.count_nonzero(values <= (2.0 * k - 1.0) * np.pi) <= (n - 1) // 2
                    and np.count_nonzero(values < (2.0 * k + 1.0) * np.pi) > n // 2):
                return TWO_PI * turn
    return TWO_PI * np.round(np.median(values) / TWO_PI)


def has_wraps(phase, valid=None) -> bool:
    """True if neighbouring samples (both valid) differ by more than pi.

    A phase map without such jumps is already unwrapped (up to 2 pi
    overall), which skips the unwrapper on most live frames.
    """
    phase = np.asarray(phase)
    if phase.ndim != 2 or phase.dtype.kind != "f":
        phase = np.atleast_2d(np.asarray(phase, dtype=np.float64))
    if valid is None:
        return bool(jump_over_pi(phase, _NO_MASK, False))
    return bool(jump_over_pi(phase, np.asarray(valid, dtype=bool), True))


@functools.lru_cache(maxsize=8)
def _inverse_laplacian(rows, cols):
    """1 / eigenvalues of the Neumann Laplacian in the DCT-II basis (0 for the constant mode)."""
    i = np.arange(rows)[:, None]
    j = np.arange(cols)[None, :]
    denom = 4.0 - 2.0 * np.cos(np.pi * i / rows) - 2.0 * np.cos(np.pi * j / cols)
    denom[0, 0] = 1.0
    inv = 1.0 / denom
    inv[0, 0] = 0.0
    inv.setflags(write=False)
    return inv


def _lsq_rounded(phase, valid):
    """Least-squares unwrapping (differences across invalid samples dropped)
    rounded to the congruent ``phase + 2 pi k``, unchecked."""
    dr = wrap(np.diff(phase, axis=0))
    dc = wrap(np.diff(phase, axis=1))
    dr[~(valid[1:, :] & valid[:-1, :])] = 0.0
    dc[~(valid[:, 1:] & valid[:, :-1])] = 0.0
    rows, cols = phase.shape
    rho = np.zeros_like(phase)
    rho[:-1, :] += dr
    rho[1:, :] -= dr
    rho[:, :-1] += dc
    rho[:, 1:] -= dc
    workers = 2 if rows * cols > 300_000 else 1  # threads cost more than they save on small grids
    rho = np.negative(rho, out=rho)
    sol_hat = scipy.fft.dctn(rho, type=2, norm="ortho", workers=workers, overwrite_x=True)
    sol_hat *= _inverse_laplacian(rows, cols)
    sol = scipy.fft.idctn(sol_hat, type=2, norm="ortho", workers=workers, overwrite_x=True)
    return phase + TWO_PI * np.round((sol - phase) / TWO_PI)


def _unwrap_lsq_congruent(phase, valid):
    """Least-squares unwrapping rounded to the congruent solution, or None.

    Differences across invalid samples are dropped (set to 0).  The result is
    ``phase + 2 pi k`` with integer k everywhere, and is returned only if no
    pair of valid neighbours then differs by pi or more (a residue-free,
    consistent unwrapping); None tells the caller to repair or path-follow.
    """
    out = _lsq_rounded(phase, valid)
    if has_wraps(out, valid):
        return None
    # one connected region: consistent.  Several: each got its own offset from
    # the smooth solution, which _align_components then resets.
    return out


_REPAIR_MARGIN = 6        # samples of context around an inconsistent spot
_REPAIR_MAX_FRACTION = 0.25  # beyond this, path following over the whole map


def _unwrap_local_repair(phase, valid, rough=None):
    """Least-squares unwrapping repaired by path following near its
    inconsistencies, or None.

    The rounded least-squares solution is usually right except close to
    masked spots surrounded by residues (dropped differences bias the smooth
    solution there).  Each cluster of valid neighbour pairs that differ by
    pi or more is cut out with a margin, unwrapped by path following on its
    own (scikit-image, invalid samples masked) and shifted, per connected
    piece, by the 2 pi multiple that matches the least-squares result on the
    piece's samples away from the inconsistency.  The repaired map is
    returned only if no pair of valid neighbours anywhere then differs by pi
    or more: a consistent unwrapping, which is unique up to 2 pi per
    connected region, i.e. what path following over the whole map gives
    when it succeeds.  None otherwise (the caller falls back to it).
    """
    rows, cols = phase.shape
    if rough is None:
        rough = _lsq_rounded(phase, valid)
    bad_r = (np.abs(np.diff(rough, axis=0)) >= np.pi) & valid[1:, :] & valid[:-1, :]
    bad_c = (np.abs(np.diff(rough, axis=1)) >= np.pi) & valid[:, 1:] & valid[:, :-1]
    bad = np.zeros(phase.shape, dtype=bool)
    bad[1:, :] |= bad_r
    bad[:-1, :] |= bad_r
    bad[:, 1:] |= bad_c
    bad[:, :-1] |= bad_c
    if not bad.any():
        return rough
    # invalid samples next to a bad pair belong to the same spot
    zone = ndimage.binary_dilation(bad, iterations=2) & ~valid | bad
    zone = ndimage.binary_dilation(zone, structure=np.ones((3, 3), bool), iterations=_REPAIR_MARGIN // 2)
    labels, n = ndimage.label(zone, structure=np.ones((3, 3), bool))
    out = rough.copy()
    covered = 0
    m = _REPAIR_MARGIN
    for sl in ndimage.find_objects(labels):
        r0 = max(sl[0].start - m, 0)
        r1 = min(sl[0].stop + m, rows)
        c0 = max(sl[1].start - m, 0)
        c1 = min(sl[1].stop + m, cols)
        covered += (r1 - r0) * (c1 - c0)
        if covered > _REPAIR_MAX_FRACTION * rows * cols:
            return None
        box = (slice(r0, r1), slice(c0, c1))
        v = valid[box]
        if v.all():
            patch = unwrap_phase(phase[box])
        else:
            patch = unwrap_phase(np.ma.masked_array(phase[box], mask=~v)).filled(0.0)
        # anchor each piece of the box on the least-squares result away from the spot
        anchor = v & ~zone[box]
        plab, pn = ndimage.label(v)
        target = out[box]
        for k in range(1, pn + 1):
            piece = plab == k
            sel = piece & anchor
            if not sel.any():
                continue  # no anchor: keep the least-squares values (the check below decides)
            shift = median_turn(target[sel] - patch[sel])
            target[piece] = patch[piece] + shift
    if has_wraps(out, valid) and not jumps_only_at_residues(phase, valid, out):
        return None
    return out


def jumps_only_at_residues(phase, valid, out):
    """True if every pair of valid neighbours of ``out`` that differs by more
    than pi is a side of a residue: a 2 x 2 cell of valid samples whose
    wrapped differences do not sum to 0.  No unwrapping removes those (the
    data are inconsistent around the cell); whole-map path following cannot
    do better than a jump on one of its sides.  One compiled scan
    (:func:`processing.unwrap_kernels.jumps_off_residues`)."""
    return not jumps_off_residues(np.ascontiguousarray(phase, dtype=np.float64), np.ascontiguousarray(valid),
                                  np.ascontiguousarray(out, dtype=np.float64))


def _unwrap_path_following(phase, valid):
    """Quality-guided path following over the whole map (compiled,
    :func:`processing.unwrap_kernels.path_follow`), or None.

    Accepted only when it is consistent (no pair of valid neighbours differs
    by pi or more) or its only jumps are sides of residues, the local
    repair's test; then it is what scikit-image's path following gives up to
    one 2 pi multiple per connected region (where there are no residues) at
    a seventh of the cost.  None: the caller tries the local repair, then
    scikit-image.
    """
    phase = np.ascontiguousarray(phase, dtype=np.float64)
    valid = np.ascontiguousarray(valid, dtype=bool)
    out = np.zeros(phase.shape)
    path_follow(phase, valid, out)
    if has_wraps(out, valid) and not jumps_only_at_residues(phase, valid, out):
        return None
    return out


def _align_components(phase, valid, ref_mask, regions=None):
    """Shift each connected valid region by 2 pi k: the one(s) holding the
    reference region so that its median is nearest 0, the others so that
    their median is nearest 0 as well (no other information links them).
    Each region is read through its bounding box (the live maps hold a few
    large regions and many specks of a few samples).  ``regions``: how many
    connected regions ``valid`` has, where the caller knows (one: no
    labelling)."""
    if regions == 1:
        labels, n = None, 1
    else:
        labels, n = connected_regions(valid)
    if n == 0:
        return phase
    if n == 1:
        sel = valid if ref_mask is None or not np.any(ref_mask & valid) else (ref_mask & valid)
        return phase - median_turn(phase[sel])
    out = phase.copy()
    if ref_mask is not None and np.any(ref_mask & valid):
        ref_vals = phase[ref_mask & valid]
        shift = median_turn(ref_vals)
        ref_labels = set(np.unique(labels[ref_mask & valid]).tolist())
    else:
        shift = None
        ref_labels = set()
    for lab, box in enumerate(ndimage.find_objects(labels), start=1):
        region = labels[box] == lab
        if lab in ref_labels:
            k_shift = shift
        else:
            k_shift = median_turn(phase[box][region])
        if k_shift:
            out[box][region] -= k_shift
    return out


def unwrap_spatial(phase, valid=None, *, ref_mask=None) -> np.ndarray:
    """Unwrap a wrapped phase map in space.

    Parameters
    ----------
    phase : ndarray, float, shape (rows, cols)
        Wrapped phase, radians.
    valid : ndarray, bool, shape (rows, cols), optional
        Samples to trust; others are ignored and returned as NaN.
    ref_mask : ndarray, bool, shape (rows, cols), optional
        Reference region: its median unwrapped phase is put nearest 0.

    Returns
    -------
    ndarray, float64, shape (rows, cols)
        Unwrapped phase, NaN outside ``valid``.
    """
    scan_refused = False
    if valid is not None and np.ndim(phase) == 2 and np.size(phase) and np.all(valid):
        # valid everywhere (most live frames): the scanline fill straight from the wrapped map, no
        # copies; where it refuses (residues, a sample not finite) the general path below
        out = np.empty(np.shape(phase))
        if scan_fill(np.ascontiguousarray(phase), out) > 0:
            sel = ref_mask if ref_mask is not None and np.any(ref_mask) else Ellipsis
            out -= median_turn(out[sel].reshape(-1))
            return out
        scan_refused = True
    phase = np.asarray(phase, dtype=np.float64)
    if valid is None:
        valid = np.isfinite(phase)
    valid = valid & np.isfinite(phase)
    if not valid.any():
        return np.full(phase.shape, np.nan)
    out, regions = _unwrapped(phase, valid, scan_refused=scan_refused)
    out = _align_components(out, valid, ref_mask, regions)
    return np.where(valid, out, np.nan)


def _unwrapped(phase, valid, *, scan_refused=False):
    """``(out, regions)``: ``phase`` (float64) unwrapped on ``valid`` (bool, some True; 0 elsewhere)
    up to one 2 pi multiple per connected region, by the first of :func:`unwrap_spatial`'s methods
    that is accepted; ``regions`` the number of connected regions where the flood fill counted
    them, else None.  ``scan_refused``: the scanline fill already refused this map (valid everywhere
    and finite, so the same fill would refuse it again)."""
    work = np.where(valid, phase, 0.0)
    regions = None
    if has_wraps(work, valid):
        # A plain flood fill first, taken where consistent: then the map has no residue and its
        # consistent unwrapping is unique up to one 2 pi multiple per connected region (which
        # _align_components resets), path following's at a quarter of the cost.  Then compiled path
        # following: where the rounded least squares would be consistent there are no residues, and
        # path following is consistent too, the same unwrapping; where the least squares is not
        # (residues: fast waves, noise), it was a wasted DCT solve (measured on the live 270^2 maps
        # of the app's 1024^2 tank: 72 % of the calls).
        valid = np.ascontiguousarray(valid)
        out = np.zeros(phase.shape)
        if not valid.all():
            regions = int(flood_fill(work, valid, out))
        else:
            regions = -1 if scan_refused else int(scan_fill(work, out))
        if regions < 0:
            regions = None
            out = _unwrap_path_following(work, valid)
        if out is None:
            rough = out = _lsq_rounded(work, valid)
            if has_wraps(out, valid):
                out = _unwrap_local_repair(work, valid, rough)
        if out is None:
            if valid.all():
                out = unwrap_phase(work)
            else:
                out = unwrap_phase(np.ma.masked_array(work, mask=~valid)).filled(0.0)
    else:
        out = work
    return out, regions


_GROW_STEPS = 16  # samples newly valid within this many steps of the common ones are grown into


def _grow_into(out, phase, known, todo):
    """Unwrap the samples ``todo`` from their already unwrapped neighbours.

    Each step gives every ``todo`` sample with a ``known`` 4-neighbour the
    mean of ``neighbour + wrap(phase - neighbour)`` over those neighbours
    (path following from the temporally unwrapped samples into the ones
    valid only in this frame: usually a thin seam where a masked spot
    moved).  Writes into ``out`` and returns what is still to do after
    ``_GROW_STEPS`` steps, which the caller unwraps in space.  Works on the
    ``todo`` samples only (a few hundred), not on the whole map; compiled
    (:func:`processing.unwrap_kernels.grow_into`: the NumPy steps it replaced
    took 0.7 ms of a live 1024^2 frame, the same values to the bit).
    """
    rows, cols = out.shape
    flat_out = out.reshape(-1)  # a view: written in place
    idx = grow_into(flat_out, np.ascontiguousarray(phase, dtype=np.float64).reshape(-1),
                    np.ascontiguousarray(known, dtype=bool).reshape(-1).copy(), np.flatnonzero(todo),
                    rows, cols, _GROW_STEPS)
    left = np.zeros(out.shape, dtype=bool)
    left.reshape(-1)[idx] = True
    return left


def unwrap_temporal(phase, previous, valid=None, previous_valid=None, *, ref_mask=None) -> np.ndarray:
    """Unwrap against the previous frame's unwrapped phase.

    ``result = previous + unwrap_spatial(wrap(phase - previous))`` where both
    frames are valid; where only this frame is valid, the spatially unwrapped
    phase is used, shifted by the 2 pi multiple that best matches the
    temporal result on the common samples.

    Parameters
    ----------
    phase : ndarray, shape (rows, cols)
        Wrapped phase of this frame, radians.
    previous : ndarray, shape (rows, cols)
        Unwrapped phase of the previous frame (NaN where invalid).
    valid, previous_valid : ndarray of bool, optional
    ref_mask : ndarray of bool, optional
        Reference region (see :func:`unwrap_spatial`).

    Returns
    -------
    ndarray, float64
        Unwrapped phase, NaN outside ``valid``.
    """
    phase = np.asarray(phase)
    previous = np.asarray(previous)
    if previous.shape != phase.shape:
        raise ValueError(f"previous phase has shape {previous.shape}, this frame {phase.shape}; "
                         "call reset_series() when the grid changes")
    if valid is None:
        valid = np.isfinite(phase)
    if previous_valid is None:
        previous_valid = np.isfinite(previous)
    both = valid & previous_valid
    if not both.any():
        return unwrap_spatial(phase, valid, ref_mask=ref_mask)
    prev0 = np.where(both, previous, 0.0)
    delta = wrap(np.where(both, phase, 0.0) - prev0)
    anchored = ref_mask is not None and bool(np.any(ref_mask & valid))
    if has_wraps(delta, both):
        changed = both & np.isfinite(delta)
        delta, regions = _unwrapped(delta, changed)
        # each island's median change nearest 0; one island's 2 pi multiple is the whole map's,
        # which the reference region's anchoring below sets (the same heights, a median less)
        if not (regions == 1 and anchored):
            delta = _align_components(delta, changed, None, regions)
        delta = np.where(changed, delta, np.nan)
    out = prev0 + delta
    only_now = valid & ~both
    if only_now.any():
        only_now = _grow_into(out, np.where(valid, phase, 0.0), both, only_now)
    if only_now.any():
        spatial = unwrap_spatial(phase, valid, ref_mask=ref_mask)
        diff = out[both] - spatial[both]
        spatial += median_turn(diff)
        out[only_now] = spatial[only_now]
    # keep the reference region's phase nearest 0 (its median may drift by 2 pi
    # only if the region itself jumped, which then was spatially ambiguous)
    if anchored:
        out -= median_turn(out[ref_mask & valid])
    out[~valid] = np.nan
    return out
