"""Optical geometry of a TIR (or FS-SS) deflectometry setup, and its pixel maps.

:class:`Geometry` holds what the numerics need to turn a displacement in
pixels into surface gradients and heights: the incidence angle, the depth of
the pattern, the scale of the image, which way the image rows run and how far
the camera is. It is read from a small TOML file (``docs/geometry.md`` lists
the keys) and validated there, so that a wrong setup fails with a message
that names the key and the fix instead of producing wrong heights.

Frames (see ``docs/architecture.md``)
-------------------------------------
*Canonical frame* (TIR): water surface ``z = 0`` at rest, ``z`` up, the pattern
on the plane ``z = -H``; ``+y`` points horizontally from the camera side
towards the pattern side, ``x`` completes it (the setup is symmetric in x).
The central camera ray travels along ``d0 = (0, sin theta, cos theta)``, hits
the surface at the origin and reflects down to the pattern at
``(0, H tan theta, -H)``.

*Image frame*: ``x`` along increasing column, ``y`` along increasing row, in
mm on the surface, origin where the central ray meets the surface. For TIR
``y_image = +y_canonical`` when ``rows_toward_camera`` is false and
``y_image = -y_canonical`` when it is true. FS-SS (camera above, looking
down) uses the image frame directly.

The camera model (rays, the flat surface's maps, the linear response of each
pixel, the check of a frame against the camera) is
:class:`processing.camera_model.CameraModel`, a base class of
:class:`Geometry`: its methods are the geometry's (``geometry.camera_rays``,
``geometry.linear_response``, ``geometry.check_frame``...). This module holds
the keys, their validation, the TOML file and the derived constants.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .camera_model import CameraModel
from .errors import GeometryError

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10 (Ubuntu 22.04): the same parser from PyPI
    import tomli as tomllib

__all__ = [
    "Geometry",
    "DEFAULT_REFERENCE_BAND",
    "default_reference_region_mask",
    "GRAZING_THETA_DEG",
    "grazing_view_note",
    "MAX_VIEW_DEPTH_GROWTH",
    "checked_geometry",
]


#: Width of the default reference band, as a fraction of the smaller frame side.
DEFAULT_REFERENCE_BAND = 0.04
#: TIR: largest ``T L / H`` (rows spanning L mm of surface, H = depth_mm) :meth:`Geometry.check_frame` accepts:
#: the heights' null mode ``exp(-T y / H)`` grows ``exp(T L / H)``-fold across the frame, beyond e^16 (1 / float32's
#: epsilon) past anything the height solve resolves.  By-hand trial of 7 Dec 2026: ``depth_mm = 0.3`` (T L / H = 70)
#: gave heights of 1e289 mm, "the surface is too steep" and numpy's overflow warnings.
MAX_VIEW_DEPTH_GROWTH = 16.0

#: Lengths beyond any set-up, mm: a slip of units (um typed as mm: 300 m of water), or a camera telecentric
#: to double precision (1e15 mm ended in a singular matrix; 1e13 already lost precision).  By-hand trial of 7 Dec 2026.
_MAX_MM = {"depth_mm": 2e4, "camera_distance_mm": 1e7, "fsss_camera_distance_mm": 1e7}

_SETUPS = ("tir", "fsss")
#: What the pattern is: a checkerboard (Fourier demodulation) or random dots (PIV).
_PATTERNS = ("checkerboard", "dots")

_EXAMPLES = {
    "setup": 'setup = "tir"',
    "theta_deg": "theta_deg = 60.0",
    "depth_mm": "depth_mm = 300.0",
    "pixel_mm": "pixel_mm = 0.1",
    "rows_toward_camera": "rows_toward_camera = false",
    "camera_distance_mm": "camera_distance_mm = 1500.0",
    "reference_region": "reference_region = [0, 40, 0, 1024]",
    "fsss_layers": "fsss_layers = [[57.0, 1.0003], [12.0, 1.48899], [43.0, 1.34]]",
    "n_water": "n_water = 1.333",
    "n_air": "n_air = 1.0003",
    "fsss_camera_distance_mm": "fsss_camera_distance_mm = 800.0",
    "pattern_stretch_y": "pattern_stretch_y = 1.7434",
    "pattern_period_mm": "pattern_period_mm = 2.0",
}

_MEANING = {
    "setup": '"tir" (total internal reflection, camera below the surface) or "fsss" (refraction, camera above)',
    "theta_deg": "incidence angle of the central camera ray on the water surface, degrees",
    "depth_mm": "vertical distance H from the water surface down to the pattern, mm",
    "pixel_mm": "surface mm per image column at the image centre",
    "rows_toward_camera": "true if the image row index increases towards the camera",
    "camera_distance_mm": "distance from the surface centre to the camera along the line of sight, mm (omit: telecentric)",
    "reference_region": "[row0, row1, col0, col1] half-open pixel box where the surface is at rest (omit: border band)",
    "fsss_layers": "[[thickness_mm, refractive_index], ...] from the pattern up to the surface, water last",
    "n_water": "refractive index of the water",
    "n_air": "refractive index of the air",
    "fsss_camera_distance_mm": "FS-SS: height of the camera above the water surface, mm (omit: telecentric)",
    "pattern_stretch_y": "cell height / width of the printed board along y (omit: square cells; "
                         "1/cos(theta) for a board printed to look square, `tirdeflect pattern --suggest`)",
    "pattern_period_mm": "full period of the printed checkerboard along x (one dark plus one bright square), mm "
                         "(omit: not checked; given, the reference's carriers must agree with it and pixel_mm)",
}

_REQUIRED = {
    "tir": ("theta_deg", "depth_mm", "pixel_mm", "rows_toward_camera"),
    "fsss": ("pixel_mm", "fsss_layers"),
}

_NUMBER_UNITS = {
    "theta_deg": "a number of degrees",
    "depth_mm": "a number of millimetres",
    "pixel_mm": "a number of millimetres",
    "camera_distance_mm": "a number of millimetres",
    "fsss_camera_distance_mm": "a number of millimetres",
    "n_water": "a number (refractive index)",
    "n_air": "a number (refractive index)",
    "pattern_stretch_y": "a number (cell height / width)",
    "pattern_period_mm": "a number of millimetres",
}


def _is_number(value: Any) -> bool:
    """A real number: Python's or numpy's scalars (``np.float32(55)``, ``np.int64(300)``), never a bool."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def _missing(key: str) -> GeometryError:
    return GeometryError(
        f"geometry is missing the key '{key}' ({_MEANING[key]}); "
        f"add a line such as: {_EXAMPLES[key]}"
    )


@dataclass(frozen=True)
class Geometry(CameraModel):
    """Optical geometry of the setup (lengths in mm, angles in degrees).

    Parameters
    ----------
    setup : {"tir", "fsss"}
        ``"tir"``: camera below the surface sees the pattern by total internal
        reflection. ``"fsss"``: free-surface synthetic schlieren, camera above
        sees the pattern through the water (Moisy et al. 2009).
    theta_deg : float
        TIR: incidence angle of the central camera ray on the surface, deg;
        must exceed the critical angle ``arcsin(n_air/n_water)`` (48.6 deg).
    depth_mm : float
        TIR: vertical distance H from the surface down to the pattern, mm.
    pixel_mm : float
        Surface mm per image column at the image centre (TIR: one row spans
        ``pixel_mm / cos(theta)`` mm of surface).
    rows_toward_camera : bool
        TIR: True if the image row index increases towards the camera (then
        image ``+y`` is canonical ``-y``). Required: the code never guesses.
        Ignored for FS-SS.
    camera_distance_mm : float or None
        TIR: distance from the surface centre to the camera along the central
        ray, mm. None: telecentric camera.
    reference_region : (row0, row1, col0, col1) or None
        Half-open pixel box of the frame where the surface is known to be at
        rest; it pins the null space of the integration (mean height 0 there).
        None: a border band ``ceil(0.04 * min(n_rows, n_cols))`` pixels wide
        along all four edges of the frame.
    fsss_layers : tuple of (thickness_mm, refractive_index)
        FS-SS: the layers from the pattern up to the water surface, water last
        (its index must equal ``n_water``).
    n_water, n_air : float
        Refractive indices (defaults 1.333 and 1.0003).
    fsss_camera_distance_mm : float or None
        FS-SS: height of the camera above the water surface, mm. None:
        telecentric.
    pattern_stretch_y : float or None
        Cell height / cell width of the printed checkerboard along y (surface
        y, along image rows). None: square cells. A board stretched by
        ``1/cos(theta)`` looks square to a TIR camera; the theta estimate from
        the carriers' aspect divides the stretch out. It does not enter the
        heights (they depend on the displacement only).
    pattern_period_mm : float or None
        Full period of the printed checkerboard along its x (one dark plus
        one bright square; along y it is ``pattern_stretch_y`` times that),
        mm: what ``tirdeflect pattern --period-mm`` printed. None: not
        checked. Given, a checkerboard reference's carriers measure it
        through ``pixel_mm``, ``theta_deg`` and the camera distance
        (:meth:`board_period_mm`), and a reconstructor refuses a reference
        that disagrees by more than :data:`BOARD_PERIOD_TOLERANCE`: a wrong
        ``pixel_mm`` scales every height by its square and nothing else
        shows it.

    Examples
    --------
    >>> g = Geometry(theta_deg=60, depth_mm=300, pixel_mm=0.1, rows_toward_camera=False)
    >>> round(g.critical_angle_deg, 1)
    48.6
    pattern : {"checkerboard", "dots"}
        What the camera sees through the surface: a checkerboard (default;
        Fourier demodulation) or a random-dot pattern (PIV with window
        deformation, :mod:`processing.piv`).
    """

    setup: str = "tir"
    theta_deg: float | None = None
    depth_mm: float | None = None
    pixel_mm: float | None = None
    rows_toward_camera: bool | None = None
    camera_distance_mm: float | None = None
    reference_region: tuple[int, int, int, int] | None = None
    fsss_layers: tuple[tuple[float, float], ...] = ()
    n_water: float = 1.333
    n_air: float = 1.0003
    fsss_camera_distance_mm: float | None = None
    pattern_stretch_y: float | None = None
    pattern: str = "checkerboard"
    pattern_period_mm: float | None = None

    # ------------------------------------------------------------------ validation
    def __post_init__(self) -> None:
        setup = self.setup
        if not isinstance(setup, str) or setup.lower() not in _SETUPS:
            raise GeometryError(
                f"setup must be \"tir\" or \"fsss\", got {setup!r}; add a line such as: setup = \"tir\""
            )
        object.__setattr__(self, "setup", setup.lower())
        for key in _REQUIRED[self.setup]:
            value = getattr(self, key)
            if value is None or (key == "fsss_layers" and len(value) == 0):
                raise _missing(key)
        for key, units in _NUMBER_UNITS.items():
            value = getattr(self, key)
            if value is None:
                continue
            if not _is_number(value) or not math.isfinite(value):
                raise GeometryError(
                    f"{key} must be {units}, got {value!r}; write for example: {_EXAMPLES[key]}"
                )
            object.__setattr__(self, key, float(value))
        if self.rows_toward_camera is None:
            object.__setattr__(self, "rows_toward_camera", False)
        if not isinstance(self.rows_toward_camera, (bool, np.bool_)):
            raise GeometryError(
                f"rows_toward_camera must be true or false ({_MEANING['rows_toward_camera']}), "
                f"got {self.rows_toward_camera!r}"
            )
        object.__setattr__(self, "rows_toward_camera", bool(self.rows_toward_camera))
        if self.pattern_stretch_y is not None and not self.pattern_stretch_y > 0:
            raise GeometryError(
                f"pattern_stretch_y must be a positive ratio (cell height / width), got "
                f"{self.pattern_stretch_y!r}; omit it for square cells")
        for key in ("depth_mm", "pixel_mm", "camera_distance_mm", "fsss_camera_distance_mm", "pattern_period_mm"):
            value, how = getattr(self, key), "omit it for a telecentric camera" if "distance" in key else \
                "measure it on the setup"
            if value is not None and value <= 0:
                raise GeometryError(f"{key} must be a positive length in mm, got {value!r}; {how}")
            if value is not None and value > _MAX_MM.get(key, math.inf):
                raise GeometryError(f"{key} = {value:g} mm ({value / 1e3:g} m) is beyond any set-up (at most "
                                    f"{_MAX_MM[key] / 1e3:g} m): lengths are in millimetres; {how}")
        if not self.n_air > 0 or not self.n_water > self.n_air:
            raise GeometryError(
                f"refractive indices must satisfy 0 < n_air < n_water, got n_air={self.n_air!r}, "
                f"n_water={self.n_water!r}; typical values are n_air = 1.0003, n_water = 1.333"
            )
        if not isinstance(self.pattern, str) or self.pattern.lower() not in _PATTERNS:
            raise GeometryError(
                f"pattern must be \"checkerboard\" or \"dots\" (a random-dot pattern, read by PIV), "
                f"got {self.pattern!r}; write for example: pattern = \"dots\""
            )
        object.__setattr__(self, "pattern", self.pattern.lower())
        self._validate_reference_region()
        self._validate_camera()
        if len(self.fsss_layers) or self.setup == "fsss":
            self._validate_layers()
        else:
            object.__setattr__(self, "fsss_layers", ())

    def _validate_camera(self) -> None:
        """TIR: theta between the critical angle and 90 deg; each setup's own camera distance key."""
        if self.setup == "tir":
            theta = self.theta_deg
            crit = self.critical_angle_deg
            if not theta < 90.0:
                raise GeometryError(f"theta_deg must be below 90 deg (grazing incidence), got {theta!r}")
            if not theta > crit:
                raise GeometryError(
                    f"no total internal reflection at theta={theta:g} deg: the critical angle "
                    f"arcsin(n_air/n_water) is {crit:.1f} deg; raise theta above {crit:.1f} deg "
                    f"(tilt the camera further from the vertical)"
                )
            if self.fsss_camera_distance_mm is not None and self.camera_distance_mm is None:
                raise GeometryError(
                    f"fsss_camera_distance_mm={self.fsss_camera_distance_mm:g} is the FS-SS camera height, but "
                    f"setup is \"tir\": give the TIR camera distance as camera_distance_mm (or remove the line "
                    f"for a telecentric lens)"
                )
        else:
            if self.camera_distance_mm is not None and self.fsss_camera_distance_mm is None:
                raise GeometryError(
                    f"camera_distance_mm={self.camera_distance_mm:g} is the TIR camera distance, but setup is "
                    f"\"fsss\": give the height of the camera above the water as fsss_camera_distance_mm "
                    f"(or remove the line for a telecentric lens)"
                )

    def _validate_reference_region(self) -> None:
        region = self.reference_region
        if region is None:
            return
        ok = (
            isinstance(region, (tuple, list))
            and len(region) == 4
            and all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in region)
        )
        if not ok:
            raise GeometryError(
                f"reference_region must be four integers [row0, row1, col0, col1] (half-open pixel box), "
                f"got {region!r}; write for example: {_EXAMPLES['reference_region']}"
            )
        r0, r1, c0, c1 = (int(v) for v in region)
        if r0 < 0 or c0 < 0 or r1 <= r0 or c1 <= c0:
            raise GeometryError(
                f"reference_region [row0, row1, col0, col1] needs 0 <= row0 < row1 and 0 <= col0 < col1, "
                f"got {list(region)}"
            )
        object.__setattr__(self, "reference_region", (r0, r1, c0, c1))

    def _validate_layers(self) -> None:
        layers = self.fsss_layers
        out = []
        if not isinstance(layers, (tuple, list)):
            raise GeometryError(
                f"fsss_layers must be a list of [thickness_mm, refractive_index] pairs, got {layers!r}; "
                f"write for example: {_EXAMPLES['fsss_layers']}"
            )
        for i, layer in enumerate(layers):
            if (
                not isinstance(layer, (tuple, list))
                or len(layer) != 2
                or not all(_is_number(v) for v in layer)
            ):
                raise GeometryError(
                    f"fsss_layers[{i}] must be a pair [thickness_mm, refractive_index], got {layer!r}; "
                    f"write for example: {_EXAMPLES['fsss_layers']}"
                )
            t, n = float(layer[0]), float(layer[1])
            if not t > 0 or not n >= 1.0:
                raise GeometryError(
                    f"fsss_layers[{i}] needs a positive thickness in mm and a refractive index >= 1, got {list(layer)}"
                )
            out.append((t, n))
        if abs(out[-1][1] - self.n_water) > 1e-6:
            raise GeometryError(
                f"the last of fsss_layers is the water under the surface and its index must equal "
                f"n_water={self.n_water}, got {out[-1][1]}; list the layers from the pattern up, water last"
            )
        object.__setattr__(self, "fsss_layers", tuple(out))

    def check_frame(self, frame_shape) -> None:
        """:meth:`CameraModel.check_frame`; TIR: refused where the frame's rows span more than
        :data:`MAX_VIEW_DEPTH_GROWTH` / T depths of surface (a wrong ``pixel_mm`` or ``depth_mm``)."""
        CameraModel.check_frame(self, frame_shape)
        if self.setup != "tir":
            return
        rows_mm = int(frame_shape[0]) * self.pixel_mm / math.cos(self.theta)
        if self.T * rows_mm <= MAX_VIEW_DEPTH_GROWTH * self.depth_mm:
            return
        raise GeometryError(
            f"the frame's {int(frame_shape[0])} rows span {rows_mm:.4g} mm of surface (pixel_mm = {self.pixel_mm:g}), "
            f"{rows_mm / self.depth_mm:.3g} times depth_mm = {self.depth_mm:g}, a view no TIR set-up has: the heights "
            f"would be lost in their null mode exp(-T y / H), which grows "
            f"{math.exp(min(self.T * rows_mm / self.depth_mm, 700.0)):.1e}-fold across it; check pixel_mm (mm of "
            f"surface per image column) and depth_mm (surface down to the board), both in mm (at this depth the "
            f"rows can span at most {MAX_VIEW_DEPTH_GROWTH * self.depth_mm / self.T:.4g} mm)")

    # ------------------------------------------------------------------ I/O
    @classmethod
    def from_dict(cls, d: dict) -> "Geometry":
        """Build from a mapping of TOML keys (see ``docs/geometry.md``).

        Raises
        ------
        GeometryError
            Unknown or missing key, wrong type, unphysical value.
        """
        if not isinstance(d, dict):
            raise GeometryError(f"geometry must be a table of keys, got {type(d).__name__}")
        allowed = [f.name for f in dataclasses.fields(cls)]
        for key in d:
            if key not in allowed:
                raise GeometryError(f"unknown key {key!r} in geometry; allowed keys: {', '.join(allowed)}")
        kw = dict(d)
        if "setup" not in kw:
            raise _missing("setup")
        if "reference_region" in kw and isinstance(kw["reference_region"], list):
            kw["reference_region"] = tuple(kw["reference_region"])
        if "fsss_layers" in kw and isinstance(kw["fsss_layers"], list):
            kw["fsss_layers"] = tuple(tuple(x) if isinstance(x, list) else x for x in kw["fsss_layers"])
        return cls(**kw)

    @classmethod
    def from_toml_text(cls, text: str) -> "Geometry":
        """Parse TOML text (flat keys, or a ``[geometry]`` table)."""
        try:
            d = tomllib.loads(text.removeprefix("\ufeff"))  # a byte-order mark read as text (Windows editors)
        except tomllib.TOMLDecodeError as exc:
            raise GeometryError(f"geometry file is not valid TOML: {exc}") from None
        if isinstance(d.get("geometry"), dict):
            others = sorted(k for k in d if k != "geometry")
            if others:
                raise GeometryError(
                    f"the file holds a [geometry] table and also {', '.join(others)}; a geometry file is its keys "
                    f"either at the top of the file or in one [geometry] table alone: keep notes as # comments "
                    f"and other tables in another file")
            d = d["geometry"]
        return cls.from_dict(d)

    @classmethod
    def from_toml(cls, path: str | Path) -> "Geometry":
        """Read a geometry TOML file (see ``resources/geometry-example.toml``)."""
        path = Path(path)
        try:
            text = path.read_text(encoding="utf-8-sig")
        except OSError as exc:
            raise GeometryError(f"cannot read geometry file {str(path)!r}: {exc.strerror}") from None
        except UnicodeDecodeError as exc:
            raise GeometryError(
                f"geometry file {str(path)!r} is not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at "
                f"offset {exc.start}); TOML files are UTF-8: save it as UTF-8 (e.g. iconv -f latin1 "
                f"-t utf-8)") from None
        try:
            return cls.from_toml_text(text)
        except GeometryError as exc:
            raise GeometryError(f"{path}: {exc}") from None

    def to_dict(self) -> dict:
        """Keys and values as in the TOML file; None entries are left out."""
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if v is None:
                continue
            if f.name == "fsss_layers":
                if self.setup != "fsss" and not v:
                    continue
                v = [list(x) for x in v]
            elif f.name == "reference_region":
                v = list(v)
            elif f.name == "pattern" and v == "checkerboard":
                continue  # the default: files written before the key existed read back equal
            out[f.name] = v
        return out

    def to_toml_text(self) -> str:
        """TOML text that :meth:`from_toml_text` reads back to an equal Geometry."""
        return "".join(f"{key} = {_toml_value(v)}\n" for key, v in self.to_dict().items())

    # ------------------------------------------------------------------ derived
    def _need_tir(self, what: str) -> None:
        if self.setup != "tir":
            raise GeometryError(f"{what} is defined for the TIR setup only; this geometry has setup={self.setup!r}")

    @property
    def theta(self) -> float:
        """Incidence angle in radians (TIR)."""
        self._need_tir("theta")
        return math.radians(self.theta_deg)

    @property
    def T(self) -> float:
        """``cos^2(theta) tan(theta) = sin(2 theta)/2`` (paper eq. utildeT; TIR)."""
        return math.cos(self.theta) ** 2 * math.tan(self.theta)

    @property
    def critical_angle_deg(self) -> float:
        """``arcsin(n_air / n_water)`` in degrees (48.6 for 1.0003/1.333)."""
        return math.degrees(math.asin(self.n_air / self.n_water))

    @property
    def row_sign(self) -> float:
        """+1 if image rows run along canonical +y, -1 if towards the camera."""
        return -1.0 if self.rows_toward_camera else 1.0

    @property
    def telecentric(self) -> bool:
        if self.setup == "tir":
            return self.camera_distance_mm is None
        return self.fsss_camera_distance_mm is None

    @property
    def fsss_hp_mm(self) -> float:
        """FS-SS: equivalent water depth ``h_p = sum(t_k * n_water / n_k)``, mm."""
        return float(sum(t * self.n_water / n for t, n in self.fsss_layers))

    @property
    def fsss_apparent_depth_mm(self) -> float:
        """FS-SS: apparent depth of the pattern seen from air, ``sum(t_k n_air / n_k)``."""
        return float(sum(t * self.n_air / n for t, n in self.fsss_layers))

    @property
    def fsss_alpha(self) -> float:
        """FS-SS: ``1 - n_air / n_water``."""
        return 1.0 - self.n_air / self.n_water

    def reference_mask(self, rows_px, cols_px, frame_shape) -> np.ndarray:
        """Bool (len(rows_px), len(cols_px)): samples inside the reference region."""
        rows_px = np.asarray(rows_px, dtype=np.float64)
        cols_px = np.asarray(cols_px, dtype=np.float64)
        if self.reference_region is None:
            return default_reference_region_mask(rows_px, cols_px, frame_shape)
        r0, r1, c0, c1 = self.reference_region
        n_rows, n_cols = frame_shape
        if r1 > n_rows or c1 > n_cols:
            raise GeometryError(
                f"reference_region {list(self.reference_region)} [row0, row1, col0, col1] reaches "
                f"outside the frame: the image has {n_rows} rows x {n_cols} columns; choose a box "
                f"inside it (row1 <= {n_rows}, col1 <= {n_cols})"
            )
        rin = (rows_px >= r0) & (rows_px < r1)
        cin = (cols_px >= c0) & (cols_px < c1)
        return rin[:, None] & cin[None, :]


#: A TIR view at this theta or steeper is named before a run (:func:`grazing_view_note`).
GRAZING_THETA_DEG = 75.0


def checked_geometry(geometry, frame_shape) -> Geometry:
    """``geometry`` (a :class:`Geometry`, a dict of its keys or a geometry TOML file's path) as a Geometry,
    checked against a frame of ``frame_shape`` (:meth:`Geometry.check_frame`); TypeError for anything else."""
    if isinstance(geometry, dict):
        geometry = Geometry.from_dict(geometry)
    elif isinstance(geometry, (str, Path)):
        geometry = Geometry.from_toml(geometry)
    elif not isinstance(geometry, Geometry):
        raise TypeError(
            f"geometry must be a processing.Geometry, a dict of its keys or the path of a geometry TOML file, got "
            f"{type(geometry).__name__}; e.g. Geometry.from_toml(\"geometry.toml\")")
    geometry.check_frame(frame_shape)
    return geometry


def grazing_view_note(geometry) -> str:
    """What a user must know of a TIR view near grazing ("" otherwise): the board's image is compressed
    ``1 / cos(theta)`` along the rows and a feature spans that many times fewer of them, and the heights
    lose accuracy fast. By-hand trial of 7 Dec 2026 (ray traced, 256^2, a bump of 1 um, 2 mm board at
    0.1 mm/px): 0.17 % at 55 deg, 0.9 % at 70, 3.2 % at 75, 10 % at 80 (19.5 % with a 4 mm board), with
    exit 0 and no word."""
    if getattr(geometry, "setup", "") != "tir" or not geometry.theta_deg >= GRAZING_THETA_DEG:
        return ""
    squeeze = 1.0 / math.cos(math.radians(geometry.theta_deg))
    return (f"theta_deg = {geometry.theta_deg:g} is near grazing: the board's image is compressed {squeeze:.1f}x "
            f"along the rows and heights lose accuracy fast (ray traced: 0.9 % at 70 deg, 3.2 % at 75, 10-20 % "
            f"at 80, against 0.2 % at 55); a view nearer 55-65 deg keeps them")


def default_reference_region_mask(rows_px, cols_px, frame_shape) -> np.ndarray:
    """Default reference region: a border band of the frame.

    The band is ``ceil(0.04 * min(n_rows, n_cols))`` pixels wide (at least 1)
    along all four edges of the frame, and holds the grid's outermost samples
    where they lie further in (:func:`_band`); returns a bool mask of shape
    ``(len(rows_px), len(cols_px))`` that is True on samples inside it.
    """
    n_rows, n_cols = frame_shape
    w = max(1, math.ceil(DEFAULT_REFERENCE_BAND * min(n_rows, n_cols)))
    rows_px = np.asarray(rows_px, dtype=np.float64)
    cols_px = np.asarray(cols_px, dtype=np.float64)
    return _band(rows_px, n_rows, w)[:, None] | _band(cols_px, n_cols, w)[None, :]


def _band(px, n: int, w: int) -> np.ndarray:
    """Which of the samples at ``px`` (one axis of ``n`` pixels) lie in the border band ``w`` px wide, the
    outermost samples always: random dots' PIV grid starts half a window in (8 px), beyond the band of a
    frame under 200 px, and every frame of 160^2 was refused ("reference region None contains no sample of
    the grid"; by-hand sweep, 7 Dec 2026)."""
    if not px.size:
        return np.zeros(0, bool)
    return (px < max(w, px.min() + 0.5)) | (px > min(n - 1 - w, px.max() - 0.5))


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, float):
        return repr(v)
    if isinstance(v, int):
        return str(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {v!r} to TOML")  # pragma: no cover
