"""A synthetic camera that streams images it is given, paced by a real-time clock.

It knows nothing about optics: the caller hands it the frames (an array or a
callable ``index -> image``); ``app/capture/scene.py`` builds ray-traced ones from
``processing.forward``. Without frames it shows a built-in moving checkerboard.

It behaves like a GenICam camera where that matters to the acquisition code:

* a device clock and a free-running frame clock (deadline based: frame ``k``
  is due at ``t0 + k / frame_rate_hz``, so the rate does not drift);
* a small pool of ``n_buffers`` output buffers: a consumer that falls more than
  ``n_buffers`` frames behind loses the oldest frames, which shows up as id
  gaps and in ``statistics()["n_underruns"]`` -- exactly like a real camera;
* injected drops (``drop_frames``) are never delivered, so consumers see an
  exact id gap;
* trigger settings: ``trigger_mode="On"`` with ``trigger_source="Software"``
  gives one frame per :meth:`SyntheticCamera.trigger_software`; with a
  ``LineN`` source no frame comes (there is no line), fetch times out;
* ``max_rate=True`` delivers a frame on every fetch without pacing (for ring
  buffer benchmarks); the device timestamp is then the host time of the fetch.

Frames are views on preallocated arrays (no per-frame copy); they are marked
read-only. The frames given are what the camera sees at its default exposure
(:data:`REFERENCE_EXPOSURE_US`) and 0 dB of gain; other settings scale their
light as a camera's do, ``exposure_us / 1000 * 10 ** (gain_db / 20)``, clipped at
the top of the bit depth (then each frame is a scaled copy): darker or saturated
frames, as at a tank. (Until 7 Dec 2026 exposure and gain were read back and
ignored: the window said "accepted: exposure 5000 us, gain 12 dB" over
unchanged frames.)
"""

from __future__ import annotations

import collections
import threading
import time
from typing import Callable, Iterable, Optional, Union

import numpy as np

from .base import (
    Camera,
    CameraError,
    CameraInfo,
    CameraSettings,
    FetchTimeout,
    Frame,
    SettingError,
)

__all__ = ["SyntheticCamera", "moving_checkerboard", "REFERENCE_EXPOSURE_US"]

_PIXEL_FORMATS_8 = ("Mono8",)
_PIXEL_FORMATS_16 = ("Mono10", "Mono12", "Mono16")
_BITS = {"Mono8": 8, "Mono10": 10, "Mono12": 12, "Mono16": 16}
_FRAME_RATE_RANGE_HZ = (0.01, 100000.0)
_EXPOSURE_RANGE_US = (1.0, 10_000_000.0)
_GAIN_RANGE_DB = (0.0, 48.0)
#: The exposure (us, at 0 dB) the frames given were taken at: the camera's default setting.
REFERENCE_EXPOSURE_US = 1000.0
_TRIGGER_SOURCES = ("Software", "Line0", "Line1", "Line2", "Line3")
_TRIGGER_ACTIVATIONS = ("RisingEdge", "FallingEdge")


def moving_checkerboard(
    shape=(1024, 1024), *, period_px: int = 32, n_phases: int = 32, bit_depth: int = 8
) -> np.ndarray:
    """A checkerboard drifting one step per frame, for the camera with no frames given.

    Parameters
    ----------
    shape : (rows, cols)
        Image size in pixels.
    period_px : int
        Full period of the pattern (two squares) in pixels.
    n_phases : int
        Number of frames in one cycle; the pattern moves ``period_px / n_phases``
        pixels along the columns per frame.
    bit_depth : int
        8 gives uint8, 10/12/16 give uint16 using that many bits.

    Returns
    -------
    ndarray, shape (n_phases, rows, cols), uint8 or uint16
        Soft-edged squares between 10 % and 90 % of full scale.
    """
    rows, cols = int(shape[0]), int(shape[1])
    if rows < 1 or cols < 1:
        raise ValueError(f"checkerboard shape must be positive; got {shape!r}")
    if bit_depth not in (8, 10, 12, 16):
        raise ValueError(f"bit_depth must be 8, 10, 12 or 16; got {bit_depth!r}")
    full = (1 << bit_depth) - 1
    dtype = np.uint8 if bit_depth == 8 else np.uint16
    k = 2 * np.pi / period_px
    r = np.arange(rows, dtype=np.float32)[:, None]
    c = np.arange(cols, dtype=np.float32)[None, :]
    out = np.empty((n_phases, rows, cols), dtype)
    sy = np.tanh(4 * np.sin(k * r))
    for p in range(n_phases):
        shift = p * period_px / n_phases
        v = sy * np.tanh(4 * np.sin(k * (c - shift)))
        out[p] = np.rint((0.5 + 0.4 * v) * full).astype(dtype)
    return out


class SyntheticCamera(Camera):
    """Streams given frames like a free-running or triggered GenICam camera.

    Parameters
    ----------
    frames : ndarray (n, rows, cols) uint8/uint16, or callable, or None
        The images. A callable is called as ``frames(index)`` with the
        0-based frame index and must return a (rows, cols) uint8/uint16 array
        of constant shape. None: :func:`moving_checkerboard` of ``shape``.
    frame_rate_hz : float
        Free-running rate in frames per second.
    bit_depth : int
        Significant bits of the pixels (8 for uint8; 10, 12 or 16 for uint16).
    loop : bool
        With an array, start over after the last frame; if False, fetch
        raises :class:`FetchTimeout` once all frames were delivered.
    drop_frames : iterable of int
        Frame ids that are never delivered (simulated transport loss); the
        consumer sees an id gap. Frame id ``k`` shows image ``k`` (mod n).
    max_rate : bool
        Deliver a frame on every fetch, as fast as the consumer asks.
    n_buffers : int
        Output buffer pool size: frames older than the newest ``n_buffers``
        are lost (underruns) when the consumer falls behind.
    shape : (rows, cols)
        Size of the built-in checkerboard when ``frames`` is None.
    camera_id : str
        The id reported by :attr:`camera_id`.

    Publishes :meth:`settings`, :meth:`statistics`; takes :meth:`configure`,
    :meth:`start`, :meth:`stop`, :meth:`fetch`, :meth:`trigger_software`.
    """

    def __init__(
        self,
        frames: Union[np.ndarray, Callable[[int], np.ndarray], None] = None,
        *,
        frame_rate_hz: float = 30.0,
        bit_depth: Optional[int] = None,
        loop: bool = True,
        drop_frames: Iterable[int] = (),
        max_rate: bool = False,
        n_buffers: int = 16,
        shape=(1024, 1024),
        camera_id: str = "synthetic",
        device_timestamps: bool = True,
    ):
        # False: frames come without the camera's timestamp (a camera that has none, or a GigE frame whose
        # leader packet was lost): the app then times them by the host's clock
        self._device_timestamps = bool(device_timestamps)
        if frames is None:
            frames = moving_checkerboard(shape, bit_depth=bit_depth or 8)
        self._callable = None
        if callable(frames):
            self._callable = frames
            first = np.asarray(frames(0))
            self._frames = None
            proto = first
        else:
            arr = np.asarray(frames)
            if arr.ndim == 2:
                arr = arr[None]
            if arr.ndim != 3 or arr.shape[0] < 1:
                raise ValueError(
                    f"frames must be an array of shape (n, rows, cols) or a callable; got shape {arr.shape}"
                )
            self._frames = arr
            proto = arr[0]
        if proto.ndim != 2:
            raise ValueError(f"each frame must be 2-D (rows, cols); got shape {proto.shape}")
        if proto.dtype not in (np.uint8, np.uint16):
            raise ValueError(
                f"frames must be uint8 or uint16 like a camera's; got {proto.dtype}. "
                "Quantize first (processing.forward.quantize)."
            )
        if bit_depth is None:
            bit_depth = 8 if proto.dtype == np.uint8 else 16
        if proto.dtype == np.uint8 and bit_depth != 8:
            raise ValueError(f"uint8 frames need bit_depth=8; got {bit_depth}")
        if proto.dtype == np.uint16 and bit_depth not in (10, 12, 16):
            raise ValueError(f"uint16 frames need bit_depth 10, 12 or 16; got {bit_depth}")
        if n_buffers < 1:
            raise ValueError(f"n_buffers must be >= 1; got {n_buffers}")
        self._check_range("frame_rate_hz", frame_rate_hz, _FRAME_RATE_RANGE_HZ)
        self.camera_id = camera_id
        self.info = CameraInfo(camera_id=camera_id, backend="synthetic", vendor="tirdeflect", model="Synthetic")
        self._dtype = proto.dtype
        self._sensor_rows, self._sensor_cols = proto.shape
        self._loop = bool(loop)
        self._drops = frozenset(int(i) for i in drop_frames)
        self._max_rate = bool(max_rate)
        self._n_buffers = int(n_buffers)
        self._settings = CameraSettings(
            width=self._sensor_cols,
            height=self._sensor_rows,
            pixel_format="Mono8" if bit_depth == 8 else f"Mono{bit_depth}",
            exposure_us=REFERENCE_EXPOSURE_US,
            gain_db=0.0,
            frame_rate_hz=float(frame_rate_hz),
            trigger_mode="Off",
            trigger_source="Software",
            trigger_activation="RisingEdge",
            bit_depth=bit_depth,
        )
        self._cond = threading.Condition()
        self._opened = False
        self._closed = False
        self._acquiring = False
        self._reset_counters()

    # -- helpers -------------------------------------------------------------
    def _reset_counters(self):
        self._next_id = 0  # next frame id to hand out
        self._t0_ns = 0
        self._triggers = collections.deque()  # (frame_id, time_ns) of triggered frames
        self._n_triggers = 0
        self._stats = dict(
            n_completed_buffers=0,
            n_failed_buffers=0,
            n_underruns=0,
            n_dropped_injected=0,
            n_triggers=0,
            n_ignored_triggers=0,
        )

    @staticmethod
    def _check_range(name, value, bounds):
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise SettingError(f"{name} must be a number; got {value!r}") from None
        if not (bounds[0] <= v <= bounds[1]):
            raise SettingError(
                f"{name}={value!r} is out of range; the synthetic camera accepts "
                f"{bounds[0]:g} .. {bounds[1]:g}"
            )
        return v

    def _require_open(self, what):
        if self._closed:
            raise CameraError(f"{what}: the synthetic camera {self.camera_id!r} is closed; open a new one")
        if not self._opened:
            raise CameraError(f"{what}: call open() (or use 'with camera:') first")

    def _image(self, frame_id: int) -> np.ndarray:
        s = self._settings
        if self._callable is not None:
            img = np.asarray(self._callable(frame_id))
            if img.shape != (self._sensor_rows, self._sensor_cols) or img.dtype != self._dtype:
                raise CameraError(
                    f"frames({frame_id}) returned {img.dtype} {img.shape}; expected "
                    f"{self._dtype} {(self._sensor_rows, self._sensor_cols)} like frame 0"
                )
        else:
            img = self._frames[frame_id % self._frames.shape[0]]
        view = img[s.offset_y : s.offset_y + s.height, s.offset_x : s.offset_x + s.width]
        light = (s.exposure_us / REFERENCE_EXPOSURE_US) * 10.0 ** (s.gain_db / 20.0)
        if light != 1.0:  # the exposure and gain set: the light scaled, clipped at the top of the bit depth
            top = float((1 << s.bit_depth) - 1)
            view = np.minimum(view * np.float32(light), np.float32(top)).astype(self._dtype)
        view.flags.writeable = False  # a new view object: the source stays writable
        return view

    @property
    def exhausted(self) -> bool:
        """True when ``loop=False`` and every given frame was handed out."""
        return (
            self._frames is not None
            and not self._loop
            and self._next_id >= self._frames.shape[0]
        )

    # -- lifecycle -----------------------------------------------------------
    def open(self) -> "SyntheticCamera":
        if self._closed:
            raise CameraError(f"the synthetic camera {self.camera_id!r} was closed; create a new one")
        self._opened = True
        return self

    def close(self) -> None:
        if self._closed:
            return
        if self._acquiring:
            self.stop()
        with self._cond:
            self._closed = True
            self._opened = False
            self._cond.notify_all()

    # -- settings --------------------------------------------------------------
    def settings(self) -> CameraSettings:
        return self._settings

    def configure(self, **values) -> CameraSettings:
        """Write settings and return what was accepted (see :class:`CameraSettings`).

        Geometry (ROI, pixel format) can only change while not acquiring.
        Raises :class:`SettingError` naming the setting and what is allowed.
        """
        self._require_open("configure")
        s = self._settings.as_dict()
        known = set(s) - {"bit_depth"}
        for name in values:
            if name not in known:
                raise SettingError(
                    f"unknown setting {name!r}; the synthetic camera takes {sorted(known)}"
                )
        geometry = {"width", "height", "offset_x", "offset_y", "pixel_format"}
        if self._acquiring and geometry & set(values):
            raise SettingError(
                f"{sorted(geometry & set(values))} cannot change while acquiring; call stop() first"
            )
        for name in ("width", "height", "offset_x", "offset_y"):
            if name in values:
                v = values[name]
                if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                    raise SettingError(f"{name} must be an integer number of pixels; got {v!r}")
                s[name] = int(v)
        for name, size in (("width", self._sensor_cols), ("height", self._sensor_rows)):
            if not 1 <= s[name] <= size:
                raise SettingError(f"{name}={s[name]} is out of range; allowed 1 .. {size} pixels")
        for name, ext, size in (
            ("offset_x", "width", self._sensor_cols),
            ("offset_y", "height", self._sensor_rows),
        ):
            hi = size - s[ext]
            if not 0 <= s[name] <= hi:
                raise SettingError(
                    f"{name}={s[name]} is out of range; with {ext}={s[ext]} allowed 0 .. {hi} pixels"
                )
        if "pixel_format" in values:
            allowed = _PIXEL_FORMATS_8 if self._dtype == np.uint8 else _PIXEL_FORMATS_16
            if values["pixel_format"] not in allowed:
                raise SettingError(
                    f"pixel_format={values['pixel_format']!r} not available for {self._dtype} frames; "
                    f"allowed {list(allowed)}"
                )
            s["pixel_format"] = values["pixel_format"]
            s["bit_depth"] = _BITS[s["pixel_format"]]
        if "frame_rate_hz" in values:
            s["frame_rate_hz"] = self._check_range("frame_rate_hz", values["frame_rate_hz"], _FRAME_RATE_RANGE_HZ)
        if "exposure_us" in values:
            s["exposure_us"] = self._check_range("exposure_us", values["exposure_us"], _EXPOSURE_RANGE_US)
        if "gain_db" in values:
            s["gain_db"] = self._check_range("gain_db", values["gain_db"], _GAIN_RANGE_DB)
        if "trigger_mode" in values:
            if values["trigger_mode"] not in ("Off", "On"):
                raise SettingError(f"trigger_mode={values['trigger_mode']!r}; allowed ['Off', 'On']")
            s["trigger_mode"] = values["trigger_mode"]
        if "trigger_source" in values:
            if values["trigger_source"] not in _TRIGGER_SOURCES:
                raise SettingError(
                    f"trigger_source={values['trigger_source']!r}; allowed {list(_TRIGGER_SOURCES)}"
                )
            s["trigger_source"] = values["trigger_source"]
        if "trigger_activation" in values:
            if values["trigger_activation"] not in _TRIGGER_ACTIVATIONS:
                raise SettingError(
                    f"trigger_activation={values['trigger_activation']!r}; allowed {list(_TRIGGER_ACTIVATIONS)}"
                )
            s["trigger_activation"] = values["trigger_activation"]
        with self._cond:
            old = self._settings
            self._settings = CameraSettings(**s)
            resumes_free_run = old.trigger_mode == "On" and s["trigger_mode"] == "Off"
            if self._acquiring and (s["frame_rate_hz"] != old.frame_rate_hz or resumes_free_run):
                # keep the clock continuous: the next frame is due now, then one per period
                now = time.monotonic_ns()
                self._t0_ns = now - int(round(self._next_id * 1e9 / s["frame_rate_hz"]))
            if s["trigger_mode"] == "Off":
                self._triggers.clear()
            self._cond.notify_all()
        return self._settings

    # -- acquisition -----------------------------------------------------------
    def start(self) -> None:
        self._require_open("start")
        with self._cond:
            if self._acquiring:
                return
            self._reset_counters()
            self._t0_ns = time.monotonic_ns()
            self._acquiring = True

    def stop(self) -> None:
        with self._cond:
            self._acquiring = False
            self._triggers.clear()
            self._cond.notify_all()

    @property
    def _triggered(self) -> bool:
        return self._settings.trigger_mode == "On"

    def trigger_software(self) -> None:
        """Make one frame now when ``trigger_mode="On"`` and ``trigger_source="Software"``.

        Ignored (and counted in ``n_ignored_triggers``) otherwise, like a camera.
        """
        self._require_open("trigger_software")
        now = time.monotonic_ns()
        with self._cond:
            self._stats["n_triggers"] += 1
            s = self._settings
            if not (self._acquiring and s.trigger_mode == "On" and s.trigger_source == "Software"):
                self._stats["n_ignored_triggers"] += 1
                return
            self._triggers.append(now)
            if len(self._triggers) > self._n_buffers:
                # pool full: the oldest triggered frame is lost, as on a camera
                self._triggers.popleft()
                self._next_id += 1
                self._stats["n_underruns"] += 1
            self._cond.notify_all()

    def _skip_drops(self):
        while self._next_id in self._drops:
            self._next_id += 1
            self._stats["n_dropped_injected"] += 1

    def fetch(self, timeout_s: float) -> Frame:
        """Wait at most ``timeout_s`` seconds for the next frame (a read-only view).

        Raises :class:`FetchTimeout` when none came (also after the last frame
        with ``loop=False``, or with a hardware-line trigger), and
        :class:`CameraError` when not acquiring.
        """
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0 seconds; got {timeout_s!r}")
        deadline = time.monotonic_ns() + int(timeout_s * 1e9)
        with self._cond:
            while True:
                if self._closed:
                    raise CameraError(f"fetch: the synthetic camera {self.camera_id!r} is closed")
                if not self._acquiring:
                    raise CameraError("fetch: acquisition is not running; call start() first")
                if self._triggered:
                    # a dropped triggered frame was taken (the trigger is used up) but never arrives
                    while self._triggers and self._next_id in self._drops:
                        self._triggers.popleft()
                        self._next_id += 1
                        self._stats["n_dropped_injected"] += 1
                else:
                    self._skip_drops()
                if self.exhausted:
                    raise FetchTimeout(
                        f"the synthetic camera delivered all {self._frames.shape[0]} frames "
                        "(loop=False); no more will come"
                    )
                now = time.monotonic_ns()
                if self._max_rate and not self._triggered:
                    ts = now
                    break
                if self._triggered:
                    if self._triggers:
                        ts = self._triggers.popleft()
                        break
                    wait_ns = deadline - now
                else:
                    period_ns = 1e9 / self._settings.frame_rate_hz
                    due = self._t0_ns + int(round(self._next_id * period_ns))
                    if due <= now:
                        # frames that already left the buffer pool are lost
                        newest = int((now - self._t0_ns) // period_ns)
                        oldest_kept = newest - self._n_buffers + 1
                        if self._next_id < oldest_kept:
                            dropped = sum(1 for i in self._drops if self._next_id <= i < oldest_kept)
                            self._stats["n_underruns"] += oldest_kept - self._next_id - dropped
                            self._stats["n_dropped_injected"] += dropped
                            self._next_id = oldest_kept
                            self._skip_drops()
                            due = self._t0_ns + int(round(self._next_id * period_ns))
                        ts = due
                        break
                    wait_ns = min(due, deadline) - now
                if now >= deadline:
                    raise FetchTimeout(
                        f"no frame from {self.camera_id!r} within {timeout_s:g} s"
                        + (
                            f" (trigger_mode On, source {self._settings.trigger_source}: "
                            "waiting for a trigger)"
                            if self._triggered
                            else ""
                        )
                    )
                self._cond.wait(wait_ns / 1e9)
            frame_id = self._next_id
            self._next_id += 1
            self._stats["n_completed_buffers"] += 1
            bit_depth = self._settings.bit_depth
        image = self._image(frame_id)
        return Frame(
            image=image,
            frame_id=frame_id,
            timestamp_ns=int(ts) if self._device_timestamps else None,
            host_timestamp_ns=time.monotonic_ns(),
            incomplete=False,
            bit_depth=bit_depth,
        )

    def statistics(self) -> dict:
        """Counters since :meth:`start`.

        Keys common to all drivers: ``n_delivered``, ``n_incomplete_delivered`` (0),
        ``n_id_gap_frames`` (ids skipped: underruns + injected drops).
        Own keys: ``n_completed_buffers`` (delivered), ``n_failed_buffers`` (always 0),
        ``n_underruns`` (lost because the consumer fell more than ``n_buffers``
        behind), ``n_dropped_injected`` (ids in ``drop_frames`` skipped),
        ``n_triggers``, ``n_ignored_triggers``.
        """
        with self._cond:
            out = dict(self._stats)
        out["n_delivered"] = out["n_completed_buffers"]
        out["n_incomplete_delivered"] = 0
        out["n_id_gap_frames"] = out["n_underruns"] + out["n_dropped_injected"]
        return out
