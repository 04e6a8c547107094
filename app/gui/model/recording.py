"""The auto-trigger threshold in physical units, the live readout beside it, "set from now", and the
recording panel's line of what the recording is doing.

The auto-trigger (:class:`app.capture.trigger.AutoTrigger`) compares the RMS slope magnitude of each
live slope map (dimensionless, mm/mm) with its threshold. The panel shows and takes it in mrad
(1 mrad = 0.001), with the quantity it is compared with, measured on the maps on screen, next to it;
"set from now" proposes :data:`PROPOSE_FACTOR` times the recent RMS (the surface's present noise or
motion), so that the trigger fires on an event and not on the noise.
"""

from __future__ import annotations

import collections
import dataclasses
import math
from typing import Deque, Optional

from app.capture.trigger import THRESHOLD_UNIT, threshold_attrs

__all__ = ["THRESHOLD_UNIT", "PROPOSE_FACTOR", "HISTORY_N", "mrad", "slope_of_mrad", "RmsHistory",
           "threshold_attrs", "progress_line", "armed_camera_lost_text"]

#: "Set from now" proposes this many times the recent RMS slope.
PROPOSE_FACTOR = 5.0
#: Values of the recent RMS kept (the live maps' last few seconds).
HISTORY_N = 60


def mrad(slope: float) -> float:
    """A dimensionless slope (mm/mm) in mrad."""
    return 1e3 * float(slope)


def slope_of_mrad(value_mrad: float) -> float:
    """A slope in mrad as the dimensionless value :class:`~app.capture.trigger.AutoTrigger` takes."""
    return 1e-3 * float(value_mrad)


@dataclasses.dataclass
class RmsHistory:
    """The RMS slope (dimensionless) of the recent live maps, newest last, with the frame each came from."""

    values: Deque[float] = dataclasses.field(default_factory=lambda: collections.deque(maxlen=HISTORY_N))
    seq: Optional[int] = None

    def add(self, rms: float, seq: Optional[int]) -> None:
        if math.isfinite(rms):
            self.values.append(float(rms))
            self.seq = seq

    @property
    def latest(self) -> float:
        return self.values[-1] if self.values else float("nan")

    def propose_mrad(self, factor: float = PROPOSE_FACTOR, *, live: bool = True) -> Optional[float]:
        """``factor`` x the median recent RMS, in mrad (None: no measurement yet, or the maps are not ``live``:
        stale maps say nothing of the surface's present noise)."""
        if not self.values or not live:
            return None
        ordered = sorted(self.values)
        return mrad(factor * ordered[len(ordered) // 2])

    def readout(self) -> str:
        """``"now 0.153 mrad"`` (the compared quantity) or ``"now: no slopes yet"``."""
        return f"now {mrad(self.latest):.3g} mrad" if self.values else "now: no slope maps yet"


def armed_camera_lost_text(error: str) -> str:
    """The panel's line when the camera of an armed recording was lost before its trigger: the recording is
    disarmed (nothing could ever trigger it) and its empty file removed. It used to stay "armed: will write
    ..." with Trigger now enabled, and after the camera was opened again "idle" beside that same line (by-hand
    trial with the fake GigE camera killed while armed, 7 Dec 2026)."""
    return (f"disarmed: the camera was lost before the trigger ({error.splitlines()[0]}); nothing recorded, "
            "no file written. Open the camera again and press Arm.")


def progress_line(state: str, path: Optional[str], shown: str, summary: str = "") -> str:
    """The panel's line under the state for a recording in ``state`` writing ``path``; ``shown`` is the
    line on screen now. Once the trigger fired, "armed: will write ..." is no longer true (the by-hand trial
    of 2 Dec 2026 saw it beside "capturing"): the line says what is being written. The summary of a
    recording that ended (done, error) is written by the window itself and is kept. ``summary``: what the
    session says happened to a recording it disarmed itself (idle: the camera was lost or changed)."""
    if state == "idle" and summary:
        return summary
    if state == "capturing":
        return f"capturing: writing {path}"
    if state == "saving":
        return f"saving {path}: every frame is captured, the last ones are being written"
    return shown
