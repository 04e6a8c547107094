"""Camera drivers: GenICam (Aravis, harvesters/GenTL) and a synthetic camera. No optics here.

Camera ids (see docs/cameras.md):

* ``synthetic`` -- :class:`drivers.synthetic.SyntheticCamera` (built-in moving
  checkerboard unless ``frames=`` is given);
* ``aravis:<device id or address>`` -- e.g. ``aravis:Fake_1``, ``aravis:127.0.0.1``,
  ``aravis:Basler-21234567``;
* ``gentl:<path to .cti>:<device>`` -- device = serial number, device id or index;
  ``gentl:<device>`` searches every producer on ``GENICAM_GENTL64_PATH``.
"""

from __future__ import annotations

from typing import List

from .base import (  # noqa: F401  (re-exported)
    Camera,
    CameraError,
    CameraInfo,
    CameraLost,
    CameraSettings,
    FetchTimeout,
    Frame,
    FrameFlags,
    SettingError,
)

__all__ = [
    "list_cameras",
    "open_camera",
    "Camera",
    "CameraError",
    "CameraInfo",
    "CameraLost",
    "CameraSettings",
    "FetchTimeout",
    "Frame",
    "FrameFlags",
    "SettingError",
]


def list_cameras(*, timeout_s: float = 3.0, include_fake: bool = False) -> List[CameraInfo]:
    """Find cameras on every available transport; never fails, never hangs.

    Parameters
    ----------
    timeout_s : float
        Upper bound in seconds for each backend's discovery (Aravis GigE
        discovery, GenTL producers); a backend that takes longer is skipped.
    include_fake : bool
        Also list Aravis' in-process fake camera (``aravis:Fake_1``).

    Returns
    -------
    list of CameraInfo
        Aravis devices (if the Aravis GObject bindings import), GenTL devices
        of every producer on ``GENICAM_GENTL64_PATH``, and always ``synthetic``
        last.
    """
    found: List[CameraInfo] = []
    try:
        from . import aravis

        found += aravis.list_devices(timeout_s=timeout_s, include_fake=include_fake)
    except Exception:  # Aravis missing or broken: other backends still work
        pass
    try:
        from . import gentl

        found += gentl.list_devices(timeout_s=timeout_s)
    except Exception:
        pass
    found.append(CameraInfo(camera_id="synthetic", backend="synthetic", vendor="tirdeflect", model="Synthetic"))
    return found


def open_camera(camera_id: str, **options) -> Camera:
    """Open a camera by id and return it (already opened; close it, or use ``with``).

    Parameters
    ----------
    camera_id : str
        ``synthetic``, ``aravis:<device>``, ``gentl:<path.cti>:<device>`` or
        ``gentl:<device>``.
    **options
        Passed to the driver's constructor (e.g. ``frames=``, ``frame_rate_hz=``
        for the synthetic camera, ``n_buffers=`` for Aravis and GenTL).

    Raises
    ------
    CameraError
        Unknown id prefix or the device cannot be opened (the message says which
        ids exist).
    """
    if not isinstance(camera_id, str) or not camera_id:
        raise CameraError(f"camera_id must be a non-empty string like 'synthetic'; got {camera_id!r}")
    backend, _, rest = camera_id.partition(":")
    if backend == "synthetic":
        from .synthetic import SyntheticCamera

        cam = SyntheticCamera(camera_id=camera_id, **options)
    elif backend == "aravis":
        from .aravis import AravisCamera

        cam = AravisCamera(rest, **options)
    elif backend == "gentl":
        from .gentl import GenTLCamera

        cam = GenTLCamera(rest, **options)
    else:
        raise CameraError(
            f"unknown camera id {camera_id!r}; use 'synthetic', 'aravis:<device>' or "
            "'gentl:<path.cti>:<device>' (run 'tirdeflect cameras' to list them)"
        )
    return cam.open()
