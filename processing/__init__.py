"""tirdeflect numerics: checkerboard frames to surface heights.

Pure numerics: arrays and a :class:`Geometry` in, arrays out. No Qt, no
cameras, no files (``Geometry.from_toml`` reads its one small text file).

>>> from processing import Geometry, Reconstructor          # doctest: +SKIP
>>> reconstruct = Reconstructor(reference_image, geometry)   # doctest: +SKIP
>>> result = reconstruct(frame)                              # doctest: +SKIP
"""

from .errors import (  # noqa: F401
    AllInvalidError,
    GeometryError,
    NoCarrierError,
    PatternMismatchError,
    ShapeMismatchError,
    TirdeflectError,
)

__all__ = [
    "Geometry",
    "Reconstructor",
    "ReconstructOptions",
    "Result",
    "TirdeflectError",
    "NoCarrierError",
    "PatternMismatchError",
    "ShapeMismatchError",
    "GeometryError",
    "AllInvalidError",
]


def __getattr__(name):
    # Lazy so that each submodule can be developed and imported on its own.
    if name == "Geometry":
        from .geometry import Geometry

        return Geometry
    if name == "ReconstructOptions":
        from .options import ReconstructOptions

        return ReconstructOptions
    if name in ("Reconstructor", "Result"):
        from . import reconstruct

        return getattr(reconstruct, name)
    raise AttributeError(f"module 'processing' has no attribute {name!r}")
