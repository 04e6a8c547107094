"""What the window says when a camera cannot be opened or started.

The drivers raise with the camera's own words (Aravis: "Controller privilege
required for streaming control"); a physicist needs to know *why* and what to
do. :func:`explain_open_error` maps the known causes to one message; anything
else keeps the driver's message.

GigE Vision gives one application at a time control of a camera (the CCP
register). A camera controlled by another program refuses streaming and
settings; where the driver found out which host holds it (an exception
attribute ``controller_host``/``holder``, or "held by HOST" / "controlled by
HOST" in its message), the message names it.
"""

from __future__ import annotations

import re

__all__ = ["explain_open_error", "is_controlled_elsewhere"]

_CONTROL_WORDS = (
    "privilege",  # Aravis: "Controller privilege required for streaming control", "Write privilege ..."
    "access denied",  # GenTL: GC_ERR_ACCESS_DENIED
    "gc_err_access_denied",
    "exclusive access",
    "already open",
    "in use by",
    "controlled by another",
    "busy",
)
_HOST_RE = re.compile(r"(?:held|controlled|owned|opened)\s+by\s+(?:host\s+)?([0-9A-Za-z_.:\-]+)", re.IGNORECASE)


def is_controlled_elsewhere(exc) -> bool:
    """True when ``exc`` (exception or message) says another application controls the camera."""
    for name in ("controller_host", "holder"):
        if getattr(exc, name, None):
            return True
    if type(exc).__name__ in ("CameraInUse", "CameraBusy", "CameraInUseError", "CameraBusyError"):
        return True
    text = str(exc).lower()
    return any(word in text for word in _CONTROL_WORDS)


def _holder(exc):
    for name in ("controller_host", "holder"):
        host = getattr(exc, name, None)
        if host:
            return str(host)
    for m in _HOST_RE.finditer(str(exc)):  # "controlled by another program (held by 10.0.0.42:50123)"
        if m.group(1).lower() not in ("another", "other", "a", "the"):
            return m.group(1).rstrip(".,;:")
    return None


def explain_open_error(camera_id: str, exc) -> str:
    """One message for a camera that could not be opened or started.

    Parameters
    ----------
    camera_id : str
        The id the user chose (``aravis:...``, ``gentl:...``).
    exc : Exception or str
        What the driver raised.

    Returns
    -------
    str
        For a camera controlled by another program: who holds it (when known) and what to do,
        with the driver's own words in brackets; otherwise the driver's message.
    """
    raw = str(exc) or type(exc).__name__
    if not is_controlled_elsewhere(exc):
        return raw
    host = _holder(exc)
    where = f" on host {host}" if host else ""
    return (f"camera {camera_id} is controlled by another program{where}: close that program "
            f"(another tirdeflect, arv-viewer, the vendor's viewer{', on ' + host if host else ''}) or wait "
            f"until it lets go (a GigE camera frees itself a few seconds after its controller stops), "
            f"then press Open again [camera said: {raw}]")
