"""Where the tests find the real images the project carries (tests/data/).

Paths are relative to this file, so every clone finds them wherever it lies;
the images are part of the repository, so a test that reads them fails (never
skips) if one is missing. Provenance and licence: tests/data/*/README.md."""

from pathlib import Path

#: tests/data/, the real FS-SS images (MIT, Trapped-modes-2025-LTG/Trapped-Modes-LTG)
DATA = Path(__file__).resolve().parent / "data"
#: 1024 x 1024 8-bit reference + frame, ring waves from a needle (README.md there)
NEEDLE = DATA / "fsss-needle-waves"
#: 1024 x 1024 10-bit TIFFs: floating objects, a wave pair, a mismatched pattern (README.md there)
TRAPPED = DATA / "fsss-trapped-modes"
