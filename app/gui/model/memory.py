"""What a session remembers (``settings.json``, key ``"session"``, in the settings directory of
:mod:`app.files.cache`) and what came back from it at this start.

:func:`app.gui.state` reads and writes the widgets; this holds the data, so that nothing is written
onto the window.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, List, Optional, Tuple

__all__ = ["KEY", "SETTING_NAMES", "SessionMemory", "threshold_mrad", "live_device_for"]

KEY = "session"
#: The camera settings remembered per camera (what it accepted), and restored when it opens again.
SETTING_NAMES = ("exposure_us", "gain_db", "frame_rate_hz", "offset_x", "offset_y", "width", "height",
                 "pixel_format", "trigger_mode", "trigger_source", "trigger_activation")
#: Not restored on the synthetic tank: its size is the one it was started with (``--size``).
TANK_OWN_SETTINGS = ("offset_x", "offset_y", "width", "height", "pixel_format")


def threshold_mrad(rec: dict, default: float) -> float:
    """The auto-trigger threshold in mrad; settings and experiments before the unit was stated hold it
    dimensionless under ``threshold``."""
    if "threshold_mrad" in rec:
        return float(rec["threshold_mrad"])
    if "threshold" in rec:
        return 1e3 * float(rec["threshold"])
    return default


def live_device_for(use_gpu: bool, probe: Callable[[], Tuple[str, str]]) -> Tuple[str, str]:
    """``(device, text)`` of the live reconstruction: the GPU only when the user asked for it (``use_gpu``,
    remembered) and ``probe`` (:func:`processing.gpu.live_device`, not called otherwise) finds one."""
    if not use_gpu:
        return "cpu", "CPU (GPU not asked for: View ▸ Live reconstruction on the GPU)"
    return probe()


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

    def camera_to_open(self, camera_id: Optional[str]) -> Optional[str]:
        """The camera to open at a start: ``camera_id`` if given, else the last session's (noted as restored)."""
        self.restored.clear()
        self.remembered_camera = None
        if camera_id is None and self.data.get("camera_id"):
            camera_id = self.remembered_camera = str(self.data["camera_id"])
            self.restored.append(f"camera {camera_id}")
        return camera_id

    def remembered_camera_failed(self, error: str) -> bool:
        """The last session's camera did not open: True (once) when cameras are to be searched instead; the
        restored list then says why, in place of "camera ID"."""
        cid = self.remembered_camera
        if not cid:
            return False
        self.remembered_camera = None
        self.restored[:] = [f"camera {cid} not available ({error.splitlines()[0]}); searching cameras instead"
                            ] + [i for i in self.restored if not i.startswith(f"camera {cid}")]
        return True

    def settings_to_restore(self, camera_id: str, now: dict, synthetic: bool) -> dict:
        """The settings ``camera_id`` accepted last time that differ from ``now`` (its present ones)."""
        stored = self.camera(camera_id).get("settings") or {}
        names = [k for k in SETTING_NAMES if not (synthetic and k in TANK_OWN_SETTINGS)]
        return {k: stored[k] for k in names if stored.get(k) is not None and stored[k] != now.get(k)}

    def reference_of(self, camera_id: Optional[str]) -> Optional[str]:
        """The file of the reference remembered for ``camera_id`` (None: none, or another camera's)."""
        ref = self.data.get("reference") or {}
        return ref["path"] if camera_id and ref.get("camera") == camera_id and ref.get("path") else None

    def geometry_unconfirmed(self, camera_id: Optional[str], synthetic: bool) -> bool:
        """The open camera's geometry was never confirmed (heights not to scale): the banner shows."""
        return bool(camera_id) and not synthetic and not self.camera(camera_id).get("geometry_confirmed")

    @property
    def use_gpu(self) -> bool:
        """The user asked for the live reconstruction on the GPU (View ▸ Live reconstruction on the GPU)."""
        return bool(self.data.get("gpu", False))

    @use_gpu.setter
    def use_gpu(self, value: bool) -> None:
        self.data["gpu"] = bool(value)
