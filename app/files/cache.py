"""The app's cache directory (FFTW wisdom) and settings directory (remembered settings).

Both follow the platform's conventions through :mod:`platformdirs`, unless an
environment variable names them (tests point both at temporary directories):

* cache: ``$TIRDEFLECT_CACHE_DIR``; else on Linux ``$XDG_CACHE_HOME/tirdeflect`` or
  ``~/.cache/tirdeflect``, on macOS ``~/Library/Caches/tirdeflect``, on Windows
  ``%LOCALAPPDATA%/tirdeflect/Cache``;
* settings: ``$TIRDEFLECT_CONFIG_DIR``; else on Linux ``$XDG_CONFIG_HOME/tirdeflect`` or
  ``~/.config/tirdeflect``, on macOS ``~/Library/Application Support/tirdeflect``, on
  Windows ``%LOCALAPPDATA%/tirdeflect``.

Files there are written atomically (temporary file in the same directory, then
``os.replace``), so a crash or a second instance never leaves a half-written
file. Anything unreadable or corrupt is ignored with a warning in the log and
rebuilt: the cache only ever saves time, it never stops the app.

FFTW wisdom is an opaque byte string from :func:`processing.fft.export_wisdom`;
this module frames it with a magic, a length and a CRC-32, so truncation or a
foreign file is detected before FFTW ever sees it.
"""

from __future__ import annotations

import json
import logging
import os
import struct
import tempfile
import zlib
from pathlib import Path

import platformdirs

__all__ = [
    "cache_dir",
    "config_dir",
    "wisdom_path",
    "settings_path",
    "load_wisdom",
    "save_wisdom",
    "restore_fftw_wisdom",
    "store_fftw_wisdom",
    "load_settings",
    "save_settings",
    "atomic_write_bytes",
]

log = logging.getLogger(__name__)

_WISDOM_NAME = "fftw-wisdom.bin"
_SETTINGS_NAME = "settings.json"
_MAGIC = b"TIRDFFTW"
_HEADER = struct.Struct("<8sII")  # magic, payload length, crc32


def cache_dir(*, create: bool = True) -> Path:
    """Return the cache directory (created unless ``create=False``).

    Returns
    -------
    pathlib.Path
    """
    return _app_dir("TIRDEFLECT_CACHE_DIR", platformdirs.user_cache_dir, create)


def config_dir(*, create: bool = True) -> Path:
    """Return the settings directory (created unless ``create=False``).

    Returns
    -------
    pathlib.Path
    """
    return _app_dir("TIRDEFLECT_CONFIG_DIR", platformdirs.user_config_dir, create)


def _app_dir(override: str, platform_dir, create: bool) -> Path:
    env = os.environ.get(override)
    path = Path(env).expanduser() if env else Path(platform_dir("tirdeflect", appauthor=False))
    if create:
        path.mkdir(parents=True, exist_ok=True)
    return path


def wisdom_path() -> Path:
    """Path of the FFTW wisdom file (may not exist yet)."""
    return cache_dir(create=False) / _WISDOM_NAME


def settings_path() -> Path:
    """Path of the JSON settings file (may not exist yet)."""
    return config_dir(create=False) / _SETTINGS_NAME


def atomic_write_bytes(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (temp file + fsync + rename).

    Parameters
    ----------
    path : path-like
        Destination; its directory is created if needed.
    data : bytes

    Returns
    -------
    pathlib.Path
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    return path


def save_wisdom(wisdom: bytes) -> Path | None:
    """Store FFTW wisdom bytes in the cache, atomically.

    Parameters
    ----------
    wisdom : bytes
        As returned by :func:`processing.fft.export_wisdom`.

    Returns
    -------
    pathlib.Path or None
        The file written, or None when the cache is not writable (logged).
    """
    if not isinstance(wisdom, (bytes, bytearray)):
        raise TypeError(f"wisdom must be bytes; got {type(wisdom).__name__}")
    payload = bytes(wisdom)
    blob = _HEADER.pack(_MAGIC, len(payload), zlib.crc32(payload)) + payload
    try:
        return atomic_write_bytes(cache_dir() / _WISDOM_NAME, blob)
    except OSError as exc:
        log.warning("could not save FFTW wisdom to the cache (%s); plans will be rebuilt next time", exc)
        return None


def load_wisdom() -> bytes | None:
    """Return the cached FFTW wisdom bytes, or None if absent or corrupt.

    A corrupt file (wrong magic, truncated, bad checksum) is logged as a
    warning and ignored, never raised.
    """
    path = wisdom_path()
    try:
        blob = path.read_bytes()
    except FileNotFoundError:
        return None
    except OSError as exc:
        log.warning("cannot read FFTW wisdom %s (%s); ignoring it", path, exc)
        return None
    if len(blob) < _HEADER.size:
        log.warning("FFTW wisdom %s is truncated (%d bytes); ignoring it", path, len(blob))
        return None
    magic, length, crc = _HEADER.unpack_from(blob)
    payload = blob[_HEADER.size :]
    if magic != _MAGIC or length != len(payload) or zlib.crc32(payload) != crc:
        log.warning("FFTW wisdom %s is corrupt (bad header or checksum); ignoring it", path)
        return None
    return payload


def restore_fftw_wisdom() -> bool:
    """Load cached wisdom into :mod:`processing.fft`; True if it was accepted.

    Never raises: a missing processing.fft, missing or corrupt wisdom is
    logged and ignored.
    """
    wisdom = load_wisdom()
    if wisdom is None:
        return False
    try:
        from processing import fft

        result = fft.import_wisdom(wisdom)
    except Exception as exc:  # corrupt content that passed the checksum, or API drift
        log.warning("cached FFTW wisdom was rejected (%s: %s); ignoring it", type(exc).__name__, exc)
        return False
    return result is not False


def store_fftw_wisdom() -> Path | None:
    """Save :func:`processing.fft.export_wisdom` to the cache; never raises."""
    try:
        from processing import fft

        wisdom = fft.export_wisdom()
    except Exception as exc:
        log.warning("could not export FFTW wisdom (%s: %s)", type(exc).__name__, exc)
        return None
    if not wisdom:
        return None
    return save_wisdom(wisdom)


def load_settings() -> dict:
    """Return the remembered settings (a JSON object), {} if none or corrupt."""
    path = settings_path()
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return {}
    except OSError as exc:
        log.warning("cannot read settings %s (%s); using defaults", path, exc)
        return {}
    try:
        data = json.loads(text)
    except ValueError as exc:
        log.warning("settings %s are corrupt (%s); using defaults", path, exc)
        return {}
    if not isinstance(data, dict):
        log.warning("settings %s hold a %s, not an object; using defaults", path, type(data).__name__)
        return {}
    return data


def save_settings(settings: dict) -> Path | None:
    """Store ``settings`` (JSON-serialisable dict) atomically; None if not writable."""
    if not isinstance(settings, dict):
        raise TypeError(f"settings must be a dict; got {type(settings).__name__}")
    data = json.dumps(settings, indent=2, sort_keys=True).encode("utf-8")
    try:
        return atomic_write_bytes(settings_path(), data)
    except OSError as exc:
        log.warning("could not save settings to %s (%s)", config_dir(create=False), exc)
        return None
