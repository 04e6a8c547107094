"""Experiment files: geometry + reference + settings of one set-up, in one TOML beside its reference.

::

    # tirdeflect experiment: geometry, reference and settings of one set-up
    format = 1
    camera = "aravis:Fake_1"
    reference = "tank-a-reference.tif"     # beside this file (float32 TIFF)

    [camera_settings]                      # what the camera accepted
    exposure_us = 1000.0
    ...
    [recording]                            # trigger and recording settings
    pre_frames = 50
    post_frames = 100
    ...
    [geometry]                             # docs/geometry.md
    setup = "tir"
    theta_deg = 55.0
    ...

Floats are written with ``repr`` (shortest text that reads back to the same
double), so nothing is rounded. ``tirdeflect --session FILE`` and the File
menu open it; the window saves it.
"""

from __future__ import annotations

import dataclasses
import json
import math
import tomllib
from pathlib import Path
from typing import Optional

import numpy as np

from .cache import atomic_write_bytes

__all__ = ["Experiment", "write_experiment", "read_experiment"]

FORMAT = 1


@dataclasses.dataclass
class Experiment:
    """What an experiment file holds.

    Attributes
    ----------
    path : Path
        The TOML file.
    geometry : processing.Geometry or None
    reference_path : Path or None
        Absolute path of the reference image (it lies beside the TOML).
    camera_id : str or None
    camera_settings : dict
        Accepted camera settings (names of :class:`drivers.base.CameraSettings`).
    recording : dict
        ``pre_frames``, ``post_frames``, ``folder``, ``auto_trigger``, ``threshold``...
    """

    path: Path
    geometry: object = None
    reference_path: Optional[Path] = None
    camera_id: Optional[str] = None
    camera_settings: dict = dataclasses.field(default_factory=dict)
    recording: dict = dataclasses.field(default_factory=dict)


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        f = float(v)
        if not math.isfinite(f):
            raise ValueError(f"cannot write {f} to TOML")
        text = repr(f)
        return text if any(ch in text for ch in ".eE") else text + ".0"
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} {v!r} to TOML")


def _table(name: str, values: dict) -> str:
    lines = [f"[{name}]"]
    for k, v in values.items():
        if v is not None:
            lines.append(f"{k} = {_value(v)}")
    return "\n".join(lines) + "\n"


def write_experiment(path, *, geometry=None, reference: Optional[np.ndarray] = None, reference_path=None,
                     camera_id: Optional[str] = None, camera_settings: Optional[dict] = None,
                     recording: Optional[dict] = None) -> Path:
    """Write the experiment TOML and its reference (``<stem>-reference.tif`` beside it).

    Parameters
    ----------
    path : path-like
        The TOML to write (``.toml`` added if missing).
    geometry : processing.Geometry, optional
    reference : ndarray, optional
        The reference image (float32 TIFF, exactly as in use); or
    reference_path : path-like, optional
        an existing reference file to point at instead (kept where it is).
    camera_id, camera_settings, recording :
        See :class:`Experiment`.

    Returns
    -------
    Path of the TOML.
    """
    path = Path(path)
    if path.suffix.lower() != ".toml":
        path = path.with_name(path.name + ".toml")
    parts = ["# tirdeflect experiment: geometry, reference and settings of one set-up",
             f"format = {FORMAT}"]
    if camera_id:
        parts.append(f"camera = {_value(camera_id)}")
    ref_file = None
    if reference is not None:
        import tifffile

        ref_file = path.with_name(path.stem + "-reference.tif")
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = ref_file.with_name("." + ref_file.name + ".tmp")
        tifffile.imwrite(tmp, np.asarray(reference, np.float32))
        tmp.replace(ref_file)
    elif reference_path is not None:
        ref_file = Path(reference_path).resolve()
    if ref_file is not None:
        try:
            rel = ref_file.resolve().relative_to(path.parent.resolve())
            parts.append(f"reference = {_value(str(rel))}")
        except ValueError:
            parts.append(f"reference = {_value(str(ref_file))}")
    text = "\n".join(parts) + "\n\n"
    if camera_settings:
        text += _table("camera_settings", camera_settings) + "\n"
    if recording:
        text += _table("recording", recording) + "\n"
    if geometry is not None:
        text += "[geometry]\n" + geometry.to_toml_text()
    atomic_write_bytes(path, text.encode("utf-8"))
    return path


def read_experiment(path) -> Experiment:
    """Read an experiment TOML.

    Raises
    ------
    OSError
        The file cannot be read.
    ValueError
        Not TOML, a newer format, or a geometry that :meth:`processing.Geometry.from_dict` refuses
        (the message names the file and the problem).
    """
    from processing import Geometry

    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"experiment file {path} is not valid TOML ({exc}): open the file a tirdeflect "
                         "window saved (File ▸ Save experiment)") from None
    fmt = data.get("format", FORMAT)
    if not isinstance(fmt, int) or fmt > FORMAT:
        raise ValueError(f"experiment file {path} has format {fmt!r}; this tirdeflect reads format {FORMAT}: "
                         "update tirdeflect")
    geometry = None
    if "geometry" in data:
        try:
            geometry = Geometry.from_dict(dict(data["geometry"]))
        except ValueError as exc:
            raise ValueError(f"experiment file {path}: [geometry] {exc}") from None
    ref = data.get("reference")
    reference_path = None
    if ref:
        reference_path = Path(ref) if Path(ref).is_absolute() else (path.parent / ref)
    return Experiment(path=path, geometry=geometry, reference_path=reference_path,
                      camera_id=data.get("camera"), camera_settings=dict(data.get("camera_settings", {})),
                      recording=dict(data.get("recording", {})))
