"""What the Replay tab reconstructs a recording with, and what its frame label says.

The recording's own reference and geometry come first (they are what it was recorded with); the
window's stand in for what the file lacks, and what is still missing is said with what to do.
"""

from __future__ import annotations

import math
from typing import Optional, Tuple

__all__ = ["replay_inputs", "frame_label"]


def replay_inputs(file_reference, window_reference, file_geometry_toml: Optional[str], window_geometry
                  ) -> Tuple[object, object, Optional[str]]:
    """``(reference, geometry, message)`` for a recording: the file's, else the window's; ``message`` says
    why heights cannot be had (either missing) or that the file's geometry was unusable (None: all fine)."""
    reference = file_reference if file_reference is not None else window_reference
    geometry, message = window_geometry, None
    if file_geometry_toml:
        try:
            from processing import Geometry

            geometry = Geometry.from_toml_text(file_geometry_toml)
        except Exception as exc:  # noqa: BLE001 - GeometryError, a damaged TOML: said, the editor's used
            message = f"geometry stored in the file is unusable ({exc}); using the editor's"
    missing = [what for what, have in (("reference (still water)", reference is not None),
                                        ("geometry", geometry is not None)) if not have]
    if missing:
        message = (f"raw frames only: no {' and no '.join(missing)} in this file or the window; for heights, "
                   "load or capture them in Controls ▸ Reference & geometry, then open the file again")
    return reference, geometry, message


def frame_label(index: int, n_frames: int, trigger_rel: Optional[int], time_s: float, time_origin: str) -> str:
    """``"frame 3/60  (trigger -2)  t = +1.2345 ms from the trigger"`` (no time where the file has none: NaN)."""
    return (f"frame {index + 1}/{n_frames}" + (f"  (trigger {trigger_rel:+d})" if trigger_rel is not None else "")
            + (f"  t = {time_s * 1e3:+.4f} ms from the {time_origin}" if math.isfinite(time_s) else ""))
