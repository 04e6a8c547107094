"""What one reconstructed frame gives: :class:`Result` (and its :class:`SeriesCheck`).

Its own module so that every chain that makes results (the CPU
:class:`processing.reconstruct.Reconstructor`, the GPU batches of
:mod:`processing.gpu`) imports it without importing the other.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np

from .carriers import Carriers
from .pin import PinStatus
from .turn import TurnCheck

__all__ = ["Result", "SeriesCheck"]


@dataclasses.dataclass(frozen=True)
class SeriesCheck:
    """Is a frame's result continuous with the previous frame of the series?

    Its images and the result are compared on the samples valid in both
    frames.  Two things can make a result jump while the images do not: the
    temporal unwrapping adds 2 pi where the images changed by less than half a
    carrier period, or the null-space pin moved to other samples.

    Attributes
    ----------
    flagged : bool
        The result is not continuous with the previous frame's (see reason).
    reason : str
        "" when not flagged, else one line saying why.
    unwrap_slip_fraction : float
        Fraction of the samples valid in both frames where, the phase having
        changed by more than pi since the previous frame, the temporally
        unwrapped phase differs by 2 pi from this frame's own spatial
        unwrapping (on the islands that reach the reference region).
    pin_shift_mm : float
        Change of the height offset, measured as the mean height change on the
        previous frame's pin samples (0 when the pin samples did not change;
        NaN when none of them is valid now).
    compared_samples : int
        Samples valid in both frames.
    unwrapped_alone : bool
        The series' count of 2 pi slipped on some samples
        (``unwrap_slip_fraction``), so this frame was unwrapped in space
        alone, as a series' first (its heights are its own; the Result's
        ``note`` says so).
    """

    flagged: bool
    reason: str
    unwrap_slip_fraction: float
    pin_shift_mm: float
    compared_samples: int
    unwrapped_alone: bool = False

    def alone_text(self) -> str:
        """The note of a frame unwrapped alone ("" for one that was not)."""
        if not self.unwrapped_alone:
            return ""
        return (f"unwrapped in space alone: since the previous frame the phase changed by more than half a carrier "
                f"period and the series' count slipped on {100 * self.unwrap_slip_fraction:.1f} % of the samples "
                f"(frames far apart in time, frames lost, or a surface too fast for the frame rate)")


@dataclasses.dataclass
class Result:
    """One reconstructed frame.

    Attributes
    ----------
    height : ndarray, float32, shape (rows, cols)
        Surface height, mm, NaN where invalid.  ``rows, cols`` is the frame
        shape (``grid == "full"``) or the decimated grid.
    valid : ndarray, bool, shape (rows, cols)
    slope_x, slope_y : ndarray, float32, shape (rows, cols)
        ``dh/dx`` (x along increasing column) and ``dh/dy`` (y along
        increasing row), dimensionless, NaN where invalid.
    displacement : ndarray, float32, shape (2, rows, cols)
        ``(u_row, u_col)`` in pixels, FD convention ``I(r) = I0(r - u(r))``.
    amplitude : ndarray, float32, shape (rows, cols)
        ``|g| / |g0|``, the smaller of both carriers (1: full contrast).
    x_mm, y_mm : ndarray, float64, shapes (cols,), (rows,)
        Surface coordinates of the grid's columns and rows.
    grid : str
        ``"full"`` or ``"decimated"``.
    rows_px, cols_px : ndarray, float64
        Pixel coordinates of the grid's rows and columns.
    carriers : Carriers
        The reference's carriers used.
    phase : ndarray, float32, shape (2, m_rows, m_cols)
        Unwrapped carrier phases on the decimated grid, radians.
    valid_fraction : float
        Fraction of valid samples.
    timings_ms : dict
        Time spent per stage.
    pin : processing.pin.PinStatus or None
        Where the height offset (the operator's null space) was pinned, how
        many valid samples it had, which rule.
    series : SeriesCheck or None
        Continuity with the previous frame of the series (None for the first
        frame, and with ``full_method="ifft"``).
    note : str
        How this frame was measured where it differs from what was asked, one
        line ("" when nothing to say): e.g. the image refinement stopped as
        diverging and FD's heights were kept (docs/processing.md, section 6).
    hot_pixels : int
        The frame's own isolated pixels brighter than anything the reference's
        pattern shows (cosmic rays, hot pixels the reference lacks:
        :func:`processing.mask.hot_pixels_above`), repaired before measuring.
    turn : processing.turn.TurnCheck or None
        How far the pattern turned since the reference (camera or board moved:
        heights carry a saddle), from the displacement's circulation on the
        decimated grid; None where not judged (the GPU chain).
    """

    height: np.ndarray
    valid: np.ndarray
    slope_x: np.ndarray
    slope_y: np.ndarray
    displacement: np.ndarray
    amplitude: np.ndarray
    x_mm: np.ndarray
    y_mm: np.ndarray
    grid: str
    rows_px: np.ndarray
    cols_px: np.ndarray
    carriers: Carriers
    phase: np.ndarray
    valid_fraction: float
    timings_ms: dict
    pin: Optional[PinStatus] = None
    series: Optional[SeriesCheck] = None
    note: str = ""
    hot_pixels: int = 0
    turn: Optional[TurnCheck] = None
