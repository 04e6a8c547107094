"""Errors raised by the numerics, each naming the problem and what to do.

All derive from :class:`TirdeflectError`, itself a :class:`ValueError`, so that
front ends (CLI, GUI) can show the message without a traceback.
"""

__all__ = [
    "TirdeflectError",
    "NoCarrierError",
    "PatternMismatchError",
    "ShapeMismatchError",
    "GeometryError",
    "AllInvalidError",
    "SampleRangeError",
]


class TirdeflectError(ValueError):
    """Base class: bad input that the user can fix; the message says how."""


class NoCarrierError(TirdeflectError):
    """The reference image shows no clear pair of carrier peaks."""


class PatternMismatchError(TirdeflectError):
    """A frame's pattern (period, rotation) does not match the reference."""


class ShapeMismatchError(TirdeflectError):
    """Frame and reference (or other arrays) have different shapes."""


class GeometryError(TirdeflectError):
    """The optical geometry is incomplete, wrongly typed or unphysical."""


class AllInvalidError(TirdeflectError):
    """No pixel of the frame could be measured (TIR lost, no contrast...)."""


class SampleRangeError(TirdeflectError):
    """An image holds samples no camera gives (NaN, infinite, or beyond 32 bits)."""
