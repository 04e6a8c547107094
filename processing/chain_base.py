"""What every chain over a reference builds on first use: the height solver of
its grid and the coordinates of every pixel (:class:`GridChain`)."""

from __future__ import annotations

from .fullgrid import full_coordinates

__all__ = ["GridChain"]


class GridChain:
    """Base of the chains (:class:`~processing.chain_checkerboard.CheckerboardChain`,
    :class:`~processing.chain_dots.DotsChain`): a subclass sets ``geometry``,
    ``rows_px``, ``cols_px`` (its grid's pixel coordinates) and ``shape`` (the
    frame's), and calls ``GridChain.__init__`` first."""

    def __init__(self):
        self._solver = self._coords = None

    def height_solver(self):
        """Height solver of the chain's grid (built once)."""
        if self._solver is None:
            from .height import solver_for

            self._solver = solver_for(self.geometry, self.rows_px, self.cols_px, self.shape)
        return self._solver

    def full_coordinates(self):
        """``(x_mm, y_mm)`` of every pixel column and row (:func:`processing.fullgrid.full_coordinates`)."""
        if self._coords is None:
            self._coords = full_coordinates(self.geometry, self.shape)
        return self._coords
