"""Settings <-> GenICam features, shared by the Aravis and GenTL drivers.

Each driver wraps its node map in a small :class:`Features` adapter; this
module maps :class:`~drivers.base.CameraSettings` names to standard feature
names (SFNC), checks values against the device's own bounds *before* writing,
writes in an order that works (offsets to 0, size, offsets; pixel format
first), and reads everything back.
"""

from __future__ import annotations

import math
from typing import Dict, Iterable, List, Optional, Tuple

import numpy as np

from .base import CameraSettings, SettingError

__all__ = [
    "Features",
    "read_settings",
    "apply_settings",
    "PIXEL_BITS",
    "SETTING_NAMES",
    "unwrap_block_id",
]

# unpacked monochrome formats the drivers can hand out as uint8/uint16 arrays
PIXEL_BITS = {"Mono8": 8, "Mono10": 10, "Mono12": 12, "Mono14": 14, "Mono16": 16}
# PFNC codes of the same formats
PFNC = {0x01080001: "Mono8", 0x01100003: "Mono10", 0x01100005: "Mono12", 0x01100025: "Mono14", 0x01100007: "Mono16"}

SETTING_NAMES = (
    "width",
    "height",
    "offset_x",
    "offset_y",
    "pixel_format",
    "exposure_us",
    "gain_db",
    "frame_rate_hz",
    "trigger_mode",
    "trigger_source",
    "trigger_activation",
)

# setting -> candidate feature names, first available wins
_FEATURES = {
    "width": ("Width",),
    "height": ("Height",),
    "offset_x": ("OffsetX",),
    "offset_y": ("OffsetY",),
    "pixel_format": ("PixelFormat",),
    "exposure_us": ("ExposureTime", "ExposureTimeAbs"),
    "gain_db": ("Gain",),  # GainRaw is in device units, not dB: not mapped
    "frame_rate_hz": ("AcquisitionFrameRate", "AcquisitionFrameRateAbs"),
    "trigger_mode": ("TriggerMode",),
    "trigger_source": ("TriggerSource",),
    "trigger_activation": ("TriggerActivation",),
}


class Features:
    """Minimal node-map access a driver provides. ``kind`` is None for an absent feature.

    Subclasses implement: ``kind(name) -> 'int'|'float'|'enum'|'bool'|'command'|None``,
    ``get(name)``, ``set(name, value)``, ``int_bounds(name) -> (min, max, inc)``,
    ``float_bounds(name) -> (min, max)``, ``enum_values(name) -> list[str]``,
    ``writable(name) -> bool``, ``execute(name)``. Errors from the device are
    raised as any Exception; this module turns them into SettingError.
    """

    def kind(self, name: str) -> Optional[str]:  # pragma: no cover - interface
        raise NotImplementedError

    #: Node kinds in the order they are tested (an enumeration is also an integer
    #: node in some bindings, so it comes first).
    KINDS = ("enum", "command", "bool", "float", "int", "string")

    @classmethod
    def kind_of(cls, node, classes) -> Optional[str]:
        """The kind of ``node`` given the binding's node classes, one per :attr:`KINDS` entry."""
        for kind, node_class in zip(cls.KINDS, classes):
            if isinstance(node, node_class):
                return kind
        return None

    def get(self, name: str):  # pragma: no cover - interface
        raise NotImplementedError

    def set(self, name: str, value) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def int_bounds(self, name: str) -> Tuple[int, int, int]:  # pragma: no cover - interface
        raise NotImplementedError

    def float_bounds(self, name: str) -> Tuple[float, float]:  # pragma: no cover - interface
        raise NotImplementedError

    def enum_values(self, name: str) -> List[str]:  # pragma: no cover - interface
        raise NotImplementedError

    def writable(self, name: str) -> bool:
        return True

    def execute(self, name: str) -> None:  # pragma: no cover - interface
        raise NotImplementedError


def feature_for(features: Features, setting: str) -> Optional[str]:
    """The device feature that implements ``setting``, or None."""
    for name in _FEATURES[setting]:
        try:
            k = features.kind(name)
        except Exception:
            k = None
        if k is not None and not (setting == "gain_db" and k != "float"):
            return name
    return None


def _select_frame_start(features: Features) -> None:
    """Point TriggerSelector at FrameStart (else AcquisitionStart) so trigger_* mean 'a frame per trigger'."""
    if features.kind("TriggerSelector") != "enum":
        return
    values = features.enum_values("TriggerSelector")
    for sel in ("FrameStart", "AcquisitionStart"):
        if sel in values:
            if features.get("TriggerSelector") != sel:
                features.set("TriggerSelector", sel)
            return


def read_settings(features: Features) -> CameraSettings:
    """Read every mapped setting back from the device (None where the feature is absent)."""
    values = {}
    try:
        _select_frame_start(features)
    except Exception:
        pass
    for setting in SETTING_NAMES:
        name = feature_for(features, setting)
        if name is None:
            values[setting] = None
            continue
        v = features.get(name)
        if setting in ("width", "height", "offset_x", "offset_y"):
            v = int(v)
        elif setting in ("exposure_us", "gain_db", "frame_rate_hz"):
            v = float(v)
        else:
            v = str(v)
        values[setting] = v
    for k in ("offset_x", "offset_y"):
        if values[k] is None:
            values[k] = 0
    if values["trigger_mode"] is None:
        values["trigger_mode"] = "Off"
    if values["pixel_format"] is None:
        values["pixel_format"] = "Mono8"
    values["bit_depth"] = PIXEL_BITS.get(values["pixel_format"], 8)
    return CameraSettings(**values)


def _check_int(features, setting, name, value):
    if isinstance(value, np.integer):
        value = int(value)
    if isinstance(value, bool) or not isinstance(value, int):
        raise SettingError(f"{setting} ({name}) must be an integer number of pixels; got {value!r}")
    lo, hi, inc = features.int_bounds(name)
    inc = max(int(inc or 1), 1)
    if not lo <= value <= hi or (value - lo) % inc:
        raise SettingError(
            f"{setting}={value} refused by the camera: {name} allows {lo} .. {hi} in steps of {inc}"
            + (" (given the current size/offset; set offsets to 0 first)" if setting.startswith(("offset", "width", "height")) else "")
        )
    return value


#: offset setting -> (size setting, features that give the sensor's extent along it, first preferred)
_SENSOR_EXTENT = {
    "offset_x": ("width", ("WidthMax", "SensorWidth")),
    "offset_y": ("height", ("HeightMax", "SensorHeight")),
}


def sensor_extent_px(features: Features, offset_setting: str) -> Tuple[Optional[int], str]:
    """(pixels, where from): how wide (``offset_x``) or high (``offset_y``) a region may reach from offset 0,
    the smallest of WidthMax/SensorWidth (HeightMax/SensorHeight) and the size feature's own maximum,
    read while the offsets are 0. (None, "") when the camera tells none of them."""
    size_setting, names = _SENSOR_EXTENT[offset_setting]
    found = []
    for name in names:
        try:
            if features.kind(name) == "int":
                found.append((int(features.get(name)), name))
        except Exception:
            pass
    size_name = feature_for(features, size_setting)
    if size_name is not None:
        try:
            found.append((int(features.int_bounds(size_name)[1]), f"the largest {size_name}"))
        except Exception:
            pass
    found = [(v, name) for v, name in found if v > 0]
    return min(found, key=lambda f: f[0]) if found else (None, "")


def _check_inside_sensor(features, setting, name, offset):
    """Refuse an offset that puts the region past the sensor's edge (offset + size > the sensor's extent).

    Cameras' offset bounds usually follow the size; some do not (Aravis' fake camera allows OffsetX 2000 with
    Width 100 on its 2048-pixel sensor, and reads 2000 back): then the stored offset would be a window the
    sensor does not have.
    """
    size_setting = _SENSOR_EXTENT[setting][0]
    size_name = feature_for(features, size_setting)
    if size_name is None:
        return
    size = int(features.get(size_name))
    extent, source = sensor_extent_px(features, setting)
    if extent is None or offset + size <= extent:
        return
    lo, _, inc = features.int_bounds(name)
    inc = max(int(inc or 1), 1)
    largest = lo + max(extent - size - lo, 0) // inc * inc
    raise SettingError(
        f"{setting}={offset} with {size_setting}={size} runs past the sensor's edge: it is {extent} pixels "
        f"{'wide' if setting == 'offset_x' else 'high'} ({source}), so {setting} may be at most {largest} for "
        f"{size_setting} {size} ({name} in steps of {inc}); give a smaller offset or {size_setting}"
    )


def _check_float(features, setting, name, value):
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise SettingError(f"{setting} ({name}) must be a number; got {value!r}") from None
    lo, hi = features.float_bounds(name)
    if not (lo <= value <= hi) or math.isnan(value):
        raise SettingError(f"{setting}={value:g} refused by the camera: {name} allows {lo:g} .. {hi:g}")
    return value


def _check_enum(features, setting, name, value, restrict: Optional[Iterable[str]] = None):
    allowed = list(features.enum_values(name))
    if restrict is not None:
        allowed = [v for v in allowed if v in restrict]
    if value not in allowed:
        raise SettingError(f"{setting}={value!r} refused by the camera: {name} allows {allowed}")
    return value


def _write(features, setting, name, value):
    if not features.writable(name):
        raise SettingError(
            f"{setting} ({name}) is read-only right now (acquiring? stop() first, or a mode locks it)"
        )
    try:
        features.set(name, value)
    except SettingError:
        raise
    except Exception as exc:
        raise SettingError(f"{setting}={value!r}: the camera refused writing {name}: {exc}") from exc


def apply_settings(features: Features, values: Dict, *, acquiring: bool = False) -> None:
    """Validate and write ``values`` (names of :class:`CameraSettings`).

    Raises :class:`SettingError` for unknown names, features the camera lacks,
    values outside the device's range (naming it), and geometry changes while
    acquiring. Geometry is written in a working order; on failure the previous
    region is restored as far as the device allows.
    """
    unknown = sorted(set(values) - set(SETTING_NAMES))
    if unknown:
        raise SettingError(f"unknown setting(s) {unknown}; known: {list(SETTING_NAMES)}")
    names = {}
    for setting in values:
        name = feature_for(features, setting)
        if name is None:
            extra = ""
            if setting == "gain_db" and features.kind("GainRaw") is not None:
                extra = " (it has GainRaw in device units only, not dB)"
            raise SettingError(f"{setting}: this camera has no {'/'.join(_FEATURES[setting])} feature{extra}")
        names[setting] = name
    geometry = [s for s in ("pixel_format", "width", "height", "offset_x", "offset_y") if s in values]
    if acquiring and geometry:
        raise SettingError(f"{geometry} cannot change while acquiring; call stop() first")

    if "pixel_format" in values:
        v = _check_enum(features, "pixel_format", names["pixel_format"], values["pixel_format"], restrict=PIXEL_BITS)
        _write(features, "pixel_format", names["pixel_format"], v)

    roi_keys = [k for k in ("width", "height", "offset_x", "offset_y") if k in values]
    if roi_keys:
        old = {k: int(features.get(n)) for k in ("offset_x", "offset_y", "width", "height") if (n := feature_for(features, k))}
        try:
            for k in ("offset_x", "offset_y"):
                n = feature_for(features, k)
                if n and old.get(k):
                    _write(features, k, n, 0)
            for k in ("width", "height", "offset_x", "offset_y"):
                n = feature_for(features, k)
                if n is None:
                    continue
                target = values.get(k, old.get(k))
                if target is None:
                    continue
                target = _check_int(features, k, n, target)
                if k.startswith("offset"):
                    _check_inside_sensor(features, k, n, target)
                if int(features.get(n)) != target:
                    _write(features, k, n, target)
        except SettingError:
            # best effort: put the previous region back (offsets 0, size, offsets)
            for k, v in [("offset_x", 0), ("offset_y", 0)] + [(k, old[k]) for k in ("width", "height", "offset_x", "offset_y") if k in old]:
                n = feature_for(features, k)
                try:
                    if n is not None and int(features.get(n)) != v:
                        features.set(n, v)
                except Exception:
                    pass
            raise

    for setting in ("exposure_us", "gain_db"):
        if setting in values:
            n = names[setting]
            _write(features, setting, n, _check_float(features, setting, n, values[setting]))
    if "frame_rate_hz" in values:
        if features.kind("AcquisitionFrameRateEnable") == "bool":
            try:
                features.set("AcquisitionFrameRateEnable", True)
            except Exception:
                pass
        n = names["frame_rate_hz"]
        _write(features, "frame_rate_hz", n, _check_float(features, "frame_rate_hz", n, values["frame_rate_hz"]))
    trig = [s for s in ("trigger_source", "trigger_activation", "trigger_mode") if s in values]
    if trig:
        _select_frame_start(features)
        for setting in trig:  # source before mode, so the camera never waits on a wrong line
            n = names[setting]
            _write(features, setting, n, _check_enum(features, setting, n, values[setting]))


def unwrap_block_id(raw: int, last: Optional[int], *, modulus: int = 65535) -> int:
    """Unwrap a GigE Vision 16-bit block id (1 .. 65535; 0 is skipped) into a monotonic count.

    Parameters
    ----------
    raw : int
        The id the transport gave.
    last : int or None
        The previous *unwrapped* id (None for the first frame).

    Returns
    -------
    int
        ``raw + k * modulus`` with ``k`` chosen so the result is closest to
        ``last``; late (out-of-order) buffers therefore land just below ``last``.
        Ids above ``modulus`` (64-bit ids, GigE Vision 2 / USB3) pass through.
    """
    if last is None or raw > modulus:
        return raw
    k = round((last - raw) / modulus)
    return raw + k * modulus
