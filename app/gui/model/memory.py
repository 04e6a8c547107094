"""What a session remembers (``settings.json``, key ``"session"``, in the settings directory of
:mod:`app.files.cache`) and what came back from it at this start.

:func:`app.gui.state` reads and writes the widgets; this holds the data, so that nothing is written
onto the window.
"""

from __future__ import annotations

import dataclasses
from typing import List, Optional

__all__ = ["KEY", "SessionMemory", "threshold_mrad"]

KEY = "session"


def threshold_mrad(rec: dict, default: float) -> float:
    """The auto-trigger threshold in mrad; settings and experiments before the unit was stated hold it
    dimensionless under ``threshold``."""
    if "threshold_mrad" in rec:
        return float(rec["threshold_mrad"])
    if "threshold" in rec:
        return 1e3 * float(rec["threshold"])
    return default


@dataclasses.dataclass
class SessionMemory:
    """``data``: the remembered dict (``cameras`` per camera id, ``camera_id``, ``reference``, ``recording``,
    ``levels``, ``window``, ``gpu``); ``restored``: what came back, for the blue bar; ``remembered_camera``:
    the last session's camera while it is being opened (None once it opened or failed)."""

    data: dict = dataclasses.field(default_factory=lambda: {"cameras": {}})
    restored: List[str] = dataclasses.field(default_factory=list)
    remembered_camera: Optional[str] = None

    @classmethod
    def load(cls) -> "SessionMemory":
        from app.files import cache

        mem = cache.load_settings().get(KEY)
        mem = dict(mem) if isinstance(mem, dict) else {}
        if not isinstance(mem.get("cameras"), dict):
            mem["cameras"] = {}
        return cls(mem)

    def save(self) -> None:
        from app.files import cache

        settings = cache.load_settings()
        settings[KEY] = self.data
        cache.save_settings(settings)

    def camera(self, camera_id: Optional[str]) -> dict:
        """The entry of ``camera_id`` (created empty); ``{}`` (not kept) without a camera."""
        return self.data["cameras"].setdefault(str(camera_id), {}) if camera_id else {}

    @property
    def use_gpu(self) -> bool:
        """The user asked for the live reconstruction on the GPU (View ▸ Live reconstruction on the GPU)."""
        return bool(self.data.get("gpu", False))

    @use_gpu.setter
    def use_gpu(self, value: bool) -> None:
        self.data["gpu"] = bool(value)
