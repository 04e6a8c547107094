"""The one small camera protocol every driver implements.

Lifecycle, after harvesters' acquirer: ``open -> start -> fetch(timeout_s) ->
stop -> close``. Both the camera and its acquisition are context managers;
``close`` is idempotent and releases in reverse order. Every blocking call
takes a finite timeout in seconds; a timeout of 0 never means "forever".

Timestamps that the camera does not provide are ``None`` and flagged, never 0.
"""

from __future__ import annotations

import dataclasses
import enum
from typing import Optional, Tuple

import numpy as np

__all__ = [
    "CameraError",
    "CameraLost",
    "CameraBusy",
    "FetchTimeout",
    "SettingError",
    "FrameFlags",
    "Frame",
    "CameraInfo",
    "CameraSettings",
    "Camera",
]


class CameraError(RuntimeError):
    """A camera could not be found, opened, configured or read; the message says what to do."""


class CameraLost(CameraError):
    """The camera stopped answering (unplugged, process killed, network gone)."""


class CameraBusy(CameraError):
    """Another program controls the camera (GigE Vision control channel privilege); nothing was changed on it."""


class FetchTimeout(CameraError, TimeoutError):
    """No frame arrived within the timeout; the camera may still be alive (e.g. waiting for a trigger)."""


class SettingError(CameraError):
    """A setting was refused by the camera (unknown feature, out of range, read-only)."""


class FrameFlags(enum.IntFlag):
    """Per-frame status bits, stored with every frame in the ring buffer and the file."""

    OK = 0
    INCOMPLETE = 1  # the driver delivered a buffer with missing packets/lines
    NO_DEVICE_TIMESTAMP = 2  # the camera gave no timestamp for this frame
    ID_GAP_BEFORE = 4  # camera frame ids jump before this frame: frames were lost upstream
    TIME_GAP_BEFORE = 8  # device/host timestamps jump by > 1.5 frame periods before this frame
    RING_OVERRUN_BEFORE = 16  # a consumer (recorder) lost frames to ring overwrites before this one
    TRIGGER = 32  # the trigger fell on this frame


@dataclasses.dataclass
class Frame:
    """One image as delivered by a driver.

    Attributes
    ----------
    image : ndarray, shape (rows, cols), uint8 or uint16
        Pixel data. Drivers may hand out a view on their own buffer: it is valid
        until :meth:`release` (or the end of a ``with`` block); copy what must
        outlive it.
    frame_id : int
        The camera's own frame/block id (monotonic; gaps mean lost frames); -1 when unknown
        (a GigE frame whose leader packet was lost before any id was seen).
    timestamp_ns : int or None
        Device timestamp in nanoseconds, None when the camera gives none.
    host_timestamp_ns : int
        ``time.monotonic_ns()`` when the driver received the frame.
    incomplete : bool
        True when pixels are missing (the transport lost packets that a resend did not bring).
    missing_bytes : int
        How many image bytes never arrived (their pixels are 0 in ``image``); 0 for a complete frame.
    bit_depth : int
        Significant bits per pixel (8, 10, 12, 16).
    """

    image: np.ndarray
    frame_id: int
    timestamp_ns: Optional[int]
    host_timestamp_ns: int
    incomplete: bool = False
    bit_depth: int = 8
    missing_bytes: int = 0
    _release: Optional[object] = dataclasses.field(default=None, repr=False)

    def release(self) -> None:
        """Give a borrowed buffer back to the driver (idempotent)."""
        release, self._release = self._release, None
        if release is not None:
            release()

    def __enter__(self) -> "Frame":
        return self

    def __exit__(self, *exc) -> None:
        self.release()


@dataclasses.dataclass(frozen=True)
class CameraInfo:
    """What discovery finds: ``camera_id`` opens it with :func:`drivers.open_camera`."""

    camera_id: str
    backend: str  # "synthetic" | "aravis" | "gentl"
    vendor: str = ""
    model: str = ""
    serial: str = ""
    address: str = ""


@dataclasses.dataclass(frozen=True)
class CameraSettings:
    """Settings as the camera *accepted* them (read back after writing).

    ``None`` means the camera has no such feature.
    """

    width: int
    height: int
    offset_x: int = 0
    offset_y: int = 0
    pixel_format: str = "Mono8"  # Mono8 | Mono10 | Mono12 | Mono16
    exposure_us: Optional[float] = None
    gain_db: Optional[float] = None
    frame_rate_hz: Optional[float] = None
    trigger_mode: str = "Off"  # "Off" (free running) | "On"
    trigger_source: Optional[str] = None  # "Software" | "Line0" | "Line1" ...
    trigger_activation: Optional[str] = None  # "RisingEdge" | "FallingEdge" ...
    bit_depth: int = 8

    @property
    def roi(self) -> Tuple[int, int, int, int]:
        """(offset_x, offset_y, width, height) in pixels."""
        return (self.offset_x, self.offset_y, self.width, self.height)

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


class Camera:
    """Base class of all drivers. Subclasses implement the ``_``-free methods below.

    Publishes: :attr:`camera_id`, :meth:`settings`, :meth:`statistics`.
    Takes: :meth:`configure`, :meth:`start`, :meth:`stop`, :meth:`fetch`,
    :meth:`trigger_software`, :meth:`close`.
    """

    camera_id: str = ""
    info: Optional[CameraInfo] = None  # vendor, model, serial once opened (None before)

    # -- lifecycle ---------------------------------------------------------
    def open(self) -> "Camera":  # pragma: no cover - interface
        raise NotImplementedError

    def close(self) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def __enter__(self) -> "Camera":
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    # -- settings ----------------------------------------------------------
    def configure(self, **values) -> CameraSettings:  # pragma: no cover - interface
        """Write settings (names as in :class:`CameraSettings`), return what the camera accepted.

        Raises :class:`SettingError` naming the setting and the allowed range.
        """
        raise NotImplementedError

    def settings(self) -> CameraSettings:  # pragma: no cover - interface
        raise NotImplementedError

    # -- acquisition -------------------------------------------------------
    def start(self) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def stop(self) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def fetch(self, timeout_s: float) -> Frame:  # pragma: no cover - interface
        """Wait at most ``timeout_s`` seconds for the next frame.

        Raises :class:`FetchTimeout` when none came, :class:`CameraLost` when
        the device is gone.
        """
        raise NotImplementedError

    def trigger_software(self) -> None:  # pragma: no cover - interface
        """Execute the GenICam ``TriggerSoftware`` command."""
        raise NotImplementedError

    def statistics(self) -> dict:
        """Transport statistics (completed, failed, underruns, lost packets ...), driver-specific keys."""
        return {}
