"""What every chain over a reference builds on first use: the height solver of
its grid and the coordinates of every pixel (:class:`GridChain`)."""

from __future__ import annotations

from .fullgrid import full_coordinates

__all__ = ["GridChain"]


class GridChain:
    """Base of the chains (:class:`~processing.chain_checkerboard.CheckerboardChain`,
    :class:`~processing.chain_dots.DotsChain`): a subclass sets ``geometry``,
    ``options``, ``rows_px``, ``cols_px`` (its grid's pixel coordinates) and ``shape``
    (the frame's), and calls ``GridChain.__init__`` first."""

    def __init__(self):
        self._solver = self._coords = self._turn = None

    #: Pixels along the frame's border whose displacement the turn check leaves out (set by the subclass).
    turn_band_px = 0.0
    #: The pin region of the chain's grid for the turn check's saddle (set by the subclass; None: the geometry's).
    turn_reference_mask = None
    #: What the reference's board says of the geometry short of refusing it (a period 2-4.5 % off the
    #: geometry's, a keystone not its camera's: :func:`processing.carriers.check_board_period`); "" when nothing
    #: (the checkerboard chain's; random dots say none).
    board_note = ""

    def judge_turn(self, u, valid):
        """``(u, turn)``: the :class:`processing.turn.TurnCheck` of the grid's displacement ``u`` on its
        ``valid`` samples, and ``u`` with a flagged turn taken out as the option ``turn_removal`` says
        (what moved; "none": as given)."""
        gauge = self.turn_gauge()
        return gauge.removed(u, gauge(u, valid), self.rows_px, self.cols_px, self.options.turn_removal)

    def turn_gauge(self):
        """The grid's :class:`processing.turn.TurnGauge` (built once): has the pattern turned since the reference?"""
        if self._turn is None:
            from .turn import TurnGauge

            self._turn = TurnGauge(self.height_solver(), self.turn_band_px, self.turn_reference_mask)
        return self._turn

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
