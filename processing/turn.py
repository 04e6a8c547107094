"""Has the pattern turned since the reference?  (:class:`TurnGauge`, :class:`TurnCheck`)

A camera turned about its axis after the reference was taken turns the whole
image: a displacement ``u = omega (c - c0, -(r - r0))`` that no water surface makes
(a board turned on the tank bottom turns it and, foreshortened, shears it).  The
height solve still fits it, as a saddle: ray-traced, 256^2, a camera turned by 1 mrad (0.06 deg) took a 2 um bump
from 0.15 to 7.95 % rms height error, 0.1 mrad to 0.84 %, and nothing said so
(6 Dec 2026; docs/processing.md section 5).  Above :data:`TURN_MAX_MRAD`, and the same
in every part of the frame (:data:`TURN_MIN_SIGNIFICANCE`), the turn is flagged.  Where the
user says what moved (the option ``turn_removal``: "camera" or "board") it is taken out of
the displacement as that one's turn (and added to image matching's warp, not solved for):
the bump at 1 mrad 0.29 %, at 0.1 mrad 0.16 %.  Not by itself: a board turned in its plane
is seen foreshortened, turned and sheared, and the shear reads as a surface; taken out as
the camera's, the board's 1 mrad cost the bump 8.70 % instead of the 1.82 % it cost left in.

What tells it from water: every surface's displacement is ``u = a h + B grad h``
(:mod:`processing.height`), so ``w = exp(Phi) B^-1 u`` is the gradient of
``exp(Phi) h`` and circulates zero around every cell of the grid (exactly, for
the discrete gradient the solver fits); a turn circulates ``omega`` times the
same amount around every cell.  The least-squares ``omega`` of the cells'
circulations is the turn.  FD's displacement is least true within a few carrier
periods of the frame's border, so only the cells farther in count
(:data:`TURN_BAND_PERIODS`).

A uniform shift of camera or board is no turn, but it circulates in ``w``: ``exp(Phi)`` changes
along the rows (the null space ``exp(-T y / H)``), so a shift along the columns circulates about
``T/H`` times itself around every cell, as a turn does (a shift along the rows nothing where, as on
a telecentric camera's grid, ``exp(Phi)`` is the same along a row).  Ray-traced, 256^2, theta 55 deg,
H 300 mm, 0.1 mm pixels, flat water with the image shifted along the columns read 0.137 mrad per px
(flagged from 0.73 px), and ``turn_removal`` then put a saddle into the heights (7 Dec 2026: shifted
3 px beside a bump, 0.33 -> 0.80 % rms error).  So the frame's uniform displacement, its mean on the
interior's samples (:meth:`TurnGauge.uniform_px`), is taken out before the circulations (on frames
valid there: the fixed weights less their mean): a shift of either component reads no turn, and a
turn about the frame's centre (mean 0 there) reads as before.  The shift itself is judged elsewhere
(:func:`processing.pin.shift_judged`, :attr:`processing.pin.PinStatus.shifted`).  The price: water
whose interior moves on average (a net slope across it) reads 0.137 mrad per px of that mean as a
turn, where a shift did before.  Measured with nothing turned (256^2, FD's decimated displacement):
26 random wave fields of 6-30 mm, 0.2-1.2 um rms moved by 0.07 mrad at most (the mean moved 0.5 px
there; the median instead of the mean: 0.14), a 2-4 um bump crossing the band's edge by 0.025,
features inside it and flat frames by less than 0.001.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

__all__ = ["TurnCheck", "TurnGauge", "TURN_MAX_MRAD", "TURN_BAND_PERIODS"]

#: Cells within this many (longest) carrier periods of the frame's border are left out of the
#: estimate. Measured with nothing turned, FD's decimated displacement (256^2, 2 mm board, 10 px
#: periods; docs/processing.md section 5): 1.5 / 2.5 / 3.5 periods, waves 12-30 mm filling the frame
#: +0.173 / -0.127 / -0.056 mrad, waves 6-12 mm -0.086 / +0.119 / -0.006 mrad; every other case of the
#: accuracy table within 0.013 mrad at 3.5.
TURN_BAND_PERIODS = 3.5

#: A frame whose pattern turned by more than this (mrad) since the reference, and by
#: :data:`TURN_MIN_SIGNIFICANCE` standard errors, is flagged (and taken out as the option
#: ``turn_removal`` says, :attr:`TurnCheck.removed`). With nothing turned the estimate stayed within 0.056 mrad on
#: the accuracy table's cases, flat frames with 1-60 DN of noise, the synthetic tank's scenes and the real
#: FS-SS needle pair (0.024 where FD's refinement ran first, as on the full grid); waves of 6-30 mm, 0.2-2
#: um rms, read up to 0.142 mrad, never at more than 1.4 standard errors. A camera turned by 0.1 mrad
#: (0.006 deg) took a 2 um bump's full-grid heights from 0.15 to 0.84 % rms error (0.16 % taken out as
#: the camera's), 1 mrad to 7.95 % (0.29 %).
TURN_MAX_MRAD = 0.1

#: Fewest interior cells the estimate needs (else it is not measured: NaN).
MIN_CELLS = 64

#: A turn above :data:`TURN_MAX_MRAD` is flagged only when it stands this many standard errors out:
#: the interior is cut into :data:`BLOCKS` x :data:`BLOCKS` blocks, each block's own estimate taken, and
#: the standard error is their spread over sqrt(blocks). A turn is the same in every block; FD's errors
#: on waves circulate one way in one block and the other way in the next. Measured 6 Dec 2026 (256^2):
#: with nothing turned, travelling waves 0.2 um rms, 6-13 mm, read up to -0.142 mrad at 0.8 standard
#: errors, the accuracy table's waves -0.056 at 1.4; a camera turned by 0.1 mrad over a bump read
#: 0.106 at 5.8, by 0.2 / 0.3 mrad over waves of 12-30 mm 0.140 / 0.240 at 3.4 / 5.7, by 1 mrad over
#: waves of 6-12 mm 1.007 at 4.9 (0.3 mrad there: 1.5, not flagged).
TURN_MIN_SIGNIFICANCE = 3.0

#: Blocks per side of the interior for the standard error (:data:`TURN_MIN_SIGNIFICANCE`).
BLOCKS = 4


@dataclasses.dataclass(frozen=True)
class TurnCheck:
    """How far a frame's pattern turned since the reference.

    Attributes
    ----------
    turn_mrad : float
        The image's turn about the frame's centre since the reference, mrad;
        positive clockwise as the frame is shown (rows down); a uniform shift
        of the image reads none (:meth:`TurnGauge.uniform_px`). NaN where not
        measured (fewer than :data:`MIN_CELLS` valid cells inside the band).
    saddle_um : float
        The rms height (um) that the turn alone puts into FD's heights (the
        height solve's answer to the camera's turn of ``turn_mrad`` on this
        grid, pinned as the frames are); image matching's heights get more
        (3.5x on the ray-traced board).
    flagged : bool
        ``|turn_mrad|`` above :data:`TURN_MAX_MRAD` and :data:`TURN_MIN_SIGNIFICANCE`
        standard errors.
    cells : int
        Cells of the grid the estimate used.
    uncertainty_mrad : float
        Standard error of ``turn_mrad`` from the spread of its estimates over the
        interior's blocks (:data:`TURN_MIN_SIGNIFICANCE`); NaN when not needed
        (``turn_mrad`` within :data:`TURN_MAX_MRAD`) or not measured.
    removed : str
        "" when the turn is left in the heights; else what it was taken out as
        ("camera" or "board", the option ``turn_removal``): out of the displacement
        before the heights were solved, and out of image matching's warp (about the
        frame's centre; a turn about another point also shifts the image, which
        reads as a tilt).
    """

    turn_mrad: float
    saddle_um: float
    flagged: bool
    cells: int
    uncertainty_mrad: float = math.nan
    removed: str = ""

    def describe(self) -> str:
        """One line for the user ("" when not flagged)."""
        if not self.flagged:
            return ""
        way = "clockwise" if self.turn_mrad > 0 else "anticlockwise"
        text = (f"the pattern turned by {abs(self.turn_mrad):.2f} +- {self.uncertainty_mrad:.2f} mrad ({way} as "
                f"shown) since the reference: the camera or the board moved")
        if self.removed:
            return text + (f"; taken out of the heights as the {self.removed}'s turn; capture a new reference on "
                           f"still water")
        return text + (f"; left in, it puts a saddle of at least {self.saddle_um:.2g} um rms into the heights; "
                       f"capture a new reference on still water, or take it out as the turn of whichever moved "
                       f"(turn_removal='camera' or 'board'; tirdeflect process --turn-removal)")


#: A turn of the image by 1 rad: ``(u_row, u_col) = T (row - r0, col - c0)``, clockwise as shown (rows down).
_IMAGE_TURN = np.array([[0.0, 1.0], [-1.0, 0.0]])


def _circulation(wr, wc, dr, dc):
    """Per cell of the grid: the circulation of ``(wr, wc)`` (per px along rows and columns, on the
    samples) around it, each edge the mean of its two samples times its length (px)."""
    along_rows = 0.5 * (wr[1:, :] + wr[:-1, :]) * dr  # edges between neighbouring rows
    along_cols = 0.5 * (wc[:, 1:] + wc[:, :-1]) * dc  # edges between neighbouring columns
    return along_cols[:-1, :] + along_rows[:, 1:] - along_cols[1:, :] - along_rows[:, :-1]


class TurnGauge:
    """The turn of a frame's displacement on one grid (built once per grid).

    Parameters
    ----------
    solver : processing.height.HeightSolver
        The grid's height solver (its optics and integrating factor).
    band_px : float
        Cells whose centre lies within this many pixels of the frame's border
        are left out (:data:`TURN_BAND_PERIODS` carrier periods for
        checkerboards).
    reference_mask : ndarray bool or None
        The pin region the frames' heights are pinned on (for
        :attr:`TurnCheck.saddle_um`; None: the geometry's).
    """

    def __init__(self, solver, band_px: float, reference_mask=None):
        grid = solver.grid
        self._solver = solver
        self._weight = np.exp(solver.phi)
        self._dr, self._dc = float(grid.dr), float(grid.dc)
        rows, cols = grid.rows_px, grid.cols_px
        rows_c, cols_c = 0.5 * (rows[1:] + rows[:-1]), 0.5 * (cols[1:] + cols[:-1])
        n_rows, n_cols = grid.frame_shape
        band = float(band_px)
        self.inner = (((rows_c >= band) & (rows_c <= n_rows - 1 - band))[:, None]
                      & ((cols_c >= band) & (cols_c <= n_cols - 1 - band))[None, :])
        corners = np.zeros((self.inner.shape[0] + 1, self.inner.shape[1] + 1), bool)  # the samples they read
        for dr_, dc_ in ((0, 0), (1, 0), (0, 1), (1, 1)):
            corners[dr_:dr_ + self.inner.shape[0], dc_:dc_ + self.inner.shape[1]] |= self.inner
        self._corners = corners
        # the circulations of a turn by 1 mrad about the frame's centre, less its uniform part (0 where the
        # interior is symmetric about the centre, as the grids are): a turn about any point reads the same
        turn = self.field(1.0, rows, cols).astype(np.float64)
        self._unit = self._circulations(turn - self.uniform_px(turn, corners)[:, None, None])
        self._reference_mask = reference_mask
        self._saddle_um_per_mrad = None
        # frames valid everywhere (most): the turn is a fixed linear map of u, two dot products
        self._all_cells = int(np.count_nonzero(self.inner))
        self._per_u = None
        if self._all_cells >= MIN_CELLS:
            # of u less its mean on the interior's samples (uniform_px): the weights less their own mean there
            per_u = self._weights(self.inner)
            mean = per_u.sum(axis=(1, 2)) / np.count_nonzero(corners)
            self._per_u = per_u - np.where(corners, mean[:, None, None], 0.0)

    def field(self, turn_mrad: float, rows_px, cols_px, kind: str = "camera"):
        """The displacement (2, rows, cols), pixels, float32, at the pixel coordinates ``rows_px``,
        ``cols_px`` (1-D) of a measured turn of ``turn_mrad`` (:attr:`TurnCheck.turn_mrad`) taken as
        ``kind``'s: "camera", the image turned about the frame's centre; "board", the board turned in
        its plane about the point under the centre, seen through the geometry's foreshortening (the
        image turned and sheared; the measured turn is its turning part)."""
        m = self._board_map() if kind == "board" else _IMAGE_TURN
        n_rows, n_cols = self._solver.grid.frame_shape
        rows = np.asarray(rows_px, np.float64)[:, None] - (n_rows - 1) / 2.0
        cols = np.asarray(cols_px, np.float64)[None, :] - (n_cols - 1) / 2.0
        w = 1e-3 * float(turn_mrad) / (0.5 * (m[0, 1] - m[1, 0]))  # the turning part of m is the turn measured
        return np.stack(np.broadcast_arrays(w * (m[0, 0] * rows + m[0, 1] * cols),
                                            w * (m[1, 0] * rows + m[1, 1] * cols))).astype(np.float32)

    def _board_map(self):
        """``J^-1 T J``: the image displacement per (row, col) offset of the board turned in its plane,
        ``J`` the surface's (y, x) mm per (row, col) px at the frame's centre (the pattern plane is the
        surface's, shifted), ``T`` a turn."""
        s = self._solver
        g, shape = s.geometry, s.grid.frame_shape
        r0, c0 = (shape[0] - 1) / 2.0, (shape[1] - 1) / 2.0
        at = np.array([[r0, c0], [r0 + 1.0, c0], [r0, c0 + 1.0]])
        x, y = (np.asarray(v, np.float64).ravel() for v in g.surface_point(at[:, :1], at[:, 1:], shape))
        jac = np.array([[y[1] - y[0], y[2] - y[0]], [x[1] - x[0], x[2] - x[0]]])
        return np.linalg.solve(jac, _IMAGE_TURN @ jac)

    def removed(self, displacement_px, check: TurnCheck, rows_px, cols_px, kind: str = "none"):
        """``(displacement, check)``: a flagged turn taken out of ``displacement_px`` (on the grid
        ``rows_px`` x ``cols_px``; NaN stays NaN) as ``kind``'s (:meth:`field`) and ``check.removed``
        set to it; both as given when not flagged or ``kind`` is "none"."""
        if not check.flagged or kind == "none":
            return displacement_px, check
        u = np.asarray(displacement_px, np.float32) - self.field(check.turn_mrad, rows_px, cols_px, kind)
        return u, dataclasses.replace(check, removed=kind)

    def _weights(self, cells):
        """``W`` (2, rows, cols) with ``turn_mrad = sum(W * u)`` for a displacement valid on every
        corner of ``cells``: the adjoint of :meth:`_circulations` applied to the least-squares weights."""
        unit = self._unit
        m = np.where(cells, unit, 0.0) / float(np.sum(unit[cells] ** 2))
        rows, cols = m.shape[0] + 1, m.shape[1] + 1
        on_rows = np.zeros((rows - 1, cols))  # d turn / d (edge value between rows i and i+1, column j)
        on_rows[:, :-1] -= m
        on_rows[:, 1:] += m
        on_cols = np.zeros((rows, cols - 1))  # d turn / d (edge value between columns j and j+1, row i)
        on_cols[:-1, :] += m
        on_cols[1:, :] -= m
        wr = np.zeros((rows, cols))
        wr[1:, :] += 0.5 * self._dr * on_rows
        wr[:-1, :] += 0.5 * self._dr * on_rows
        wc = np.zeros((rows, cols))
        wc[:, 1:] += 0.5 * self._dc * on_cols
        wc[:, :-1] += 0.5 * self._dc * on_cols
        wr, wc = self._weight * wr, self._weight * wc
        # through g = B^-1 u: gr = b00 ur + b01 uc, gc = b10 ur + b11 uc (per sample or uniform)
        b = np.asarray(self._solver.Binv, np.float64)
        b00, b01, b10, b11 = (b[..., 0, 0], b[..., 0, 1], b[..., 1, 0], b[..., 1, 1])
        return np.stack([wr * b00 + wc * b10, wr * b01 + wc * b11])

    def uniform_px(self, displacement_px, valid):
        """The frame's uniform displacement ``(u_row, u_col)`` (2,), px, taken out before the circulations:
        the mean of ``displacement_px`` (2, rows, cols) on its ``valid`` samples that the interior's cells
        read (the corners of the cells inside the band); zeros where there are none."""
        sel = self._corners & np.asarray(valid, bool)
        if not sel.any():
            return np.zeros(2)
        u = np.asarray(displacement_px)
        return np.array([np.mean(u[0][sel], dtype=np.float64), np.mean(u[1][sel], dtype=np.float64)])

    def _circulations(self, displacement_px):
        gr, gc = self._solver.gradients(displacement_px)
        return _circulation(self._weight * gr, self._weight * gc, self._dr, self._dc)

    def saddle_um_per_mrad(self) -> float:
        """RMS height (um) of the heights the solver gives a turn of 1 mrad (every sample valid; once)."""
        if self._saddle_um_per_mrad is None:
            s = self._solver
            turn = self.field(1.0, s.grid.rows_px, s.grid.cols_px).astype(np.float64)
            surf = s.solve(turn, np.ones(s.shape, bool), reference_mask=self._reference_mask)
            h = np.asarray(surf.height_mm, np.float64)
            self._saddle_um_per_mrad = 1e3 * float(np.sqrt(np.nanmean(h ** 2)))
        return self._saddle_um_per_mrad

    def __call__(self, displacement_px, valid) -> TurnCheck:
        """The :class:`TurnCheck` of a frame's displacement (2, rows, cols), pixels, on the
        grid's ``valid`` samples (a cell counts when its four corners are valid), its uniform part
        (:meth:`uniform_px`) taken out first."""
        v = np.asarray(valid, bool)
        u = np.asarray(displacement_px)
        if self._per_u is not None and (v.all() or v[self._corners].all()):
            # every interior cell counts (invalid samples, if any, lie outside the band: weight 0); the
            # weights already take the uniform part out
            n = self._all_cells
            w = self._per_u
            if not v.all():
                u = np.where(v, u, np.float32(0.0))
            # numpy's own loop, not BLAS: OpenBLAS ran this float64 dot on a second thread that then
            # spun, and the live worker took 2 cores where it has 1 (the window's raw view lost frames)
            turn = float(np.einsum("kij,kij->", w, u, dtype=np.float64))
            cells = None
        else:
            cells = self.inner & v[:-1, :-1] & v[1:, :-1] & v[:-1, 1:] & v[1:, 1:]
            n = int(np.count_nonzero(cells))
            if n < MIN_CELLS:
                return TurnCheck(math.nan, math.nan, False, n)
            circ = self._circulations(np.where(v, u - self.uniform_px(u, v)[:, None, None], 0.0))
            unit = self._unit
            turn = float(np.sum(circ[cells] * unit[cells]) / np.sum(unit[cells] ** 2))
        if not math.isfinite(turn):
            return TurnCheck(math.nan, math.nan, False, n)
        if abs(turn) <= TURN_MAX_MRAD:
            return TurnCheck(turn, math.nan, False, n)
        # large enough to matter: is it the same turn everywhere? (rare: the per-cell pass only here)
        if cells is None:
            cells = self.inner & v[:-1, :-1] & v[1:, :-1] & v[:-1, 1:] & v[1:, 1:]
            circ = self._circulations(np.where(v, u - self.uniform_px(u, v)[:, None, None], 0.0))
        error = self._standard_error(circ, cells)
        flagged = abs(turn) >= TURN_MIN_SIGNIFICANCE * error  # (NaN: too few blocks, not flagged)
        saddle = abs(turn) * self.saddle_um_per_mrad() if flagged else math.nan
        return TurnCheck(turn, saddle, flagged, n, error)

    def _standard_error(self, circ, cells) -> float:
        """The standard error of the turn (mrad): the spread of the estimates of the interior's
        :data:`BLOCKS` x :data:`BLOCKS` blocks over sqrt(blocks); NaN with fewer than 4 blocks."""
        unit = self._unit
        num = np.where(cells, circ * unit, 0.0)
        den = np.where(cells, unit * unit, 0.0)
        rows = np.flatnonzero(self.inner.any(axis=1))
        cols = np.flatnonzero(self.inner.any(axis=0))
        r_edges = np.linspace(rows[0], rows[-1] + 1, BLOCKS + 1).astype(int)
        c_edges = np.linspace(cols[0], cols[-1] + 1, BLOCKS + 1).astype(int)
        sums = np.add.reduceat(np.add.reduceat(np.stack([num, den]), r_edges[:-1], axis=1), c_edges[:-1], axis=2)
        filled = sums[1] > 0
        if np.count_nonzero(filled) < 4:
            return math.nan
        estimates = sums[0][filled] / sums[1][filled]
        return float(np.std(estimates, ddof=1) / math.sqrt(estimates.size))
