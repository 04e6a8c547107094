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

The camera model (both setups): pixel ``(row, col)`` of a frame of shape
``(n_rows, n_cols)`` is offset from the frame centre ``((n_rows-1)/2,
(n_cols-1)/2)``. A telecentric camera (distance None) sends parallel rays; a
pinhole camera at distance ``D`` from the surface centre sends its central
ray through the surface centre and one pixel subtends ``pixel_mm / D`` rad,
so that ``pixel_mm`` is the surface mm per column at the image centre in
both cases (and ``pixel_mm / cos(theta)`` the surface mm per row for TIR).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from .errors import GeometryError
from .fsss_flat import fsss_flat_trace, fsss_invert_radial, fsss_layers_from_surface

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10 (Ubuntu 22.04): the same parser from PyPI
    import tomli as tomllib

__all__ = [
    "Geometry",
    "LinearResponse",
    "DEFAULT_REFERENCE_BAND",
    "MAX_FIELD_HALF_ANGLE_DEG",
    "default_reference_region_mask",
]

#: Widest angle off the camera axis (deg) that the pinhole (rectilinear lens) model is
#: trusted for; see :meth:`Geometry.check_frame`.
MAX_FIELD_HALF_ANGLE_DEG = 60.0

#: Width of the default reference band, as a fraction of the smaller frame side.
DEFAULT_REFERENCE_BAND = 0.04

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
}


class LinearResponse(NamedTuple):
    """First-order optics of each sample: ``u = a * h + B @ grad_px(h)``.

    ``u`` is the displacement in pixels ``(u_row, u_col)`` (FD convention
    ``I(r) = I0(r - u)``), ``h`` the height in mm at the surface point seen by
    the sample and ``grad_px(h) = (dh/drow, dh/dcol)`` in mm per pixel.

    Attributes
    ----------
    a : ndarray, shape (..., 2), float64
        Pixels of displacement per mm of height.
    B : ndarray, shape (..., 2, 2), float64
        Pixels of displacement per unit of pixel gradient (mm/px).
    surface_xy : ndarray, shape (..., 2), float64
        Image-frame surface position ``(x_mm, y_mm)`` of each sample.
    jac_surface : ndarray, shape (..., 2, 2), float64
        ``d(y_mm, x_mm) / d(row, col)`` in the image frame (mm per pixel).
    """

    a: np.ndarray
    B: np.ndarray
    surface_xy: np.ndarray
    jac_surface: np.ndarray


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _missing(key: str) -> GeometryError:
    return GeometryError(
        f"geometry is missing the key '{key}' ({_MEANING[key]}); "
        f"add a line such as: {_EXAMPLES[key]}"
    )


@dataclass(frozen=True)
class Geometry:
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
        for key in ("depth_mm", "pixel_mm", "camera_distance_mm", "fsss_camera_distance_mm"):
            value = getattr(self, key)
            if value is not None and value <= 0:
                raise GeometryError(
                    f"{key} must be a positive length in mm, got {value!r}; "
                    f"{'omit it for a telecentric camera' if 'distance' in key else 'measure it on the setup'}"
                )
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
                raise GeometryError(
                    f"theta_deg must be below 90 deg (grazing incidence), got {theta!r}"
                )
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

    # ------------------------------------------------------------------ against the frame
    def check_frame(self, frame_shape) -> None:
        """Refuse a camera that cannot see the pattern over a frame of this shape.

        The keys alone do not say how wide the field is; with the frame they do
        (``pixel_mm`` per column, ``pixel_mm / cos(theta)`` per row for TIR).
        Two physical conditions, checked on the flat surface for every pixel
        of the frame's border, centre row and centre column (where the
        extremes of the incidence angle lie):

        * pinhole camera (finite distance): no pixel more than
          :data:`MAX_FIELD_HALF_ANGLE_DEG` off the optical axis. The camera
          model is a rectilinear lens (a pixel offset ``s`` is the direction
          ``atan(s / D)``); a wider field needs a fisheye, which the model
          does not describe, and a distance that short is almost always a
          typo (``camera_distance_mm = 1`` for 1 m). This is
          ``D >= half diagonal / tan(60 deg)``, about 0.3 field diagonals:
          measured with :mod:`processing.forward`, the ray-traced heights of
          the finite-distance model stay within 1.2 % of the truth down to
          half a field diagonal wherever the rays are totally reflected, so
          the bound the physics needs is the next one, not a multiple of the
          field.
        * TIR: every ray must meet the surface going up (incidence below
          90 deg) and be totally reflected (incidence above the critical
          angle ``arcsin(n_air / n_water)``), so that it reaches the pattern;
          elsewhere the camera sees through the surface, not the board.

        Raises
        ------
        GeometryError
            Naming the values, where in the frame it fails and what to change.
        """
        n_rows, n_cols = (int(v) for v in frame_shape)
        distance = self.camera_distance_mm if self.setup == "tir" else self.fsss_camera_distance_mm
        key = "camera_distance_mm" if self.setup == "tir" else "fsss_camera_distance_mm"
        row_mm = self.pixel_mm / math.cos(self.theta) if self.setup == "tir" else self.pixel_mm
        width_mm, height_mm = n_cols * self.pixel_mm, n_rows * row_mm
        field = (f"the {n_rows} x {n_cols} px frame spans {width_mm:.4g} x {height_mm:.4g} mm of surface "
                 f"(pixel_mm = {self.pixel_mm:g})")
        if distance is not None:
            half_diag_mm = 0.5 * math.hypot((n_cols - 1) * self.pixel_mm, (n_rows - 1) * self.pixel_mm)
            angle = math.degrees(math.atan2(half_diag_mm, distance))
            if angle > MAX_FIELD_HALF_ANGLE_DEG:
                need = half_diag_mm / math.tan(math.radians(MAX_FIELD_HALF_ANGLE_DEG))
                raise GeometryError(
                    f"{key} = {distance:g} mm is too short for the field: {field}, so its corners would be "
                    f"{angle:.1f} deg off the camera's axis, beyond the {MAX_FIELD_HALF_ANGLE_DEG:g} deg of a "
                    f"rectilinear lens; the camera must be at least {need:.4g} mm away. Measure the distance "
                    f"from the lens to the centre of the surface in mm (1 m is 1000), check pixel_mm, or omit "
                    f"{key} for a telecentric lens")
        if self.setup != "tir":
            return
        mid_r, mid_c = (n_rows - 1) / 2.0, (n_cols - 1) / 2.0
        all_r = np.arange(n_rows, dtype=np.float64)
        all_c = np.arange(n_cols, dtype=np.float64)
        rows = np.concatenate([all_r, all_r, all_r, np.full(3 * n_cols, 0.0)])
        rows[3 * n_rows + n_cols:3 * n_rows + 2 * n_cols] = mid_r
        rows[3 * n_rows + 2 * n_cols:] = n_rows - 1
        cols = np.concatenate([np.zeros(n_rows), np.full(n_rows, mid_c), np.full(n_rows, n_cols - 1.0),
                               all_c, all_c, all_c])
        _, d = self.camera_rays(rows, cols, (n_rows, n_cols))
        cos_inc = d[..., 2]
        crit = self.critical_angle_deg
        i_min = int(np.argmax(cos_inc))
        i_max = int(np.argmin(cos_inc))
        inc_min = math.degrees(math.acos(min(1.0, float(cos_inc[i_min]))))
        inc_max = 90.0 if cos_inc[i_max] <= 0 else math.degrees(math.acos(float(cos_inc[i_max])))
        where = lambda i: f"pixel (row {rows[i]:g}, col {cols[i]:g})"  # noqa: E731
        fix = (f"check theta_deg = {self.theta_deg:g}, pixel_mm = {self.pixel_mm:g} and "
               + (f"camera_distance_mm = {distance:g}" if distance is not None else "the frame size"))
        if cos_inc[i_max] <= 1e-9:
            raise GeometryError(
                f"the camera ray of {where(i_max)} does not reach the water surface (incidence "
                f"{inc_max:.1f} deg, 90 or more): {field}; {fix}")
        if not inc_min > crit:
            raise GeometryError(
                f"the camera ray of {where(i_min)} meets the surface at {inc_min:.1f} deg, below the critical "
                f"angle {crit:.1f} deg: it is not totally reflected and sees through the surface, not the "
                f"pattern ({field}; incidence ranges {inc_min:.1f}-{inc_max:.1f} deg over the frame); raise "
                f"theta_deg or move the camera farther away so that the whole field stays above {crit:.1f} deg; "
                f"{fix}")

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
                raise GeometryError(
                    f"unknown key {key!r} in geometry; allowed keys: {', '.join(allowed)}"
                )
        kw = dict(d)
        if "setup" not in kw:
            raise _missing("setup")
        if "reference_region" in kw and isinstance(kw["reference_region"], list):
            kw["reference_region"] = tuple(kw["reference_region"])
        if "fsss_layers" in kw and isinstance(kw["fsss_layers"], list):
            kw["fsss_layers"] = tuple(
                tuple(x) if isinstance(x, list) else x for x in kw["fsss_layers"]
            )
        return cls(**kw)

    @classmethod
    def from_toml_text(cls, text: str) -> "Geometry":
        """Parse TOML text (flat keys, or a ``[geometry]`` table)."""
        try:
            d = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise GeometryError(f"geometry file is not valid TOML: {exc}") from None
        if set(d) == {"geometry"} and isinstance(d["geometry"], dict):
            d = d["geometry"]
        return cls.from_dict(d)

    @classmethod
    def from_toml(cls, path: str | Path) -> "Geometry":
        """Read a geometry TOML file (see ``resources/geometry-example.toml``)."""
        path = Path(path)
        try:
            text = path.read_text(encoding="utf-8")
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
        lines = []
        for key, v in self.to_dict().items():
            lines.append(f"{key} = {_toml_value(v)}")
        return "\n".join(lines) + "\n"

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

    # ------------------------------------------------------------------ camera model
    def _basis(self):
        """Canonical-frame central direction and image-plane axes (TIR)."""
        th = self.theta
        d0 = np.array([0.0, math.sin(th), math.cos(th)])
        ex = np.array([1.0, 0.0, 0.0])
        ev = np.array([0.0, math.cos(th), -math.sin(th)])
        return d0, ex, ev

    @staticmethod
    def _offsets(rows_px, cols_px, frame_shape):
        rows_px = np.asarray(rows_px, dtype=np.float64)
        cols_px = np.asarray(cols_px, dtype=np.float64)
        n_rows, n_cols = frame_shape
        return rows_px - (n_rows - 1) / 2.0, cols_px - (n_cols - 1) / 2.0

    def camera_rays(self, rows_px, cols_px, frame_shape):
        """Rays of the camera for pixels ``(rows_px, cols_px)`` (broadcast).

        Parameters
        ----------
        rows_px, cols_px : array_like, float
            Pixel coordinates (broadcast together), any shape ``S``.
        frame_shape : (int, int)
            Frame shape; its centre is the optical axis.

        Returns
        -------
        origin, direction : ndarray, shape S + (3,), float64
            TIR: canonical frame, directions unit and going up (``d_z > 0``),
            origins below the surface. FS-SS: image frame (x along columns, y
            along rows), directions going down, origins above the surface.
        """
        dr, dc = self._offsets(rows_px, cols_px, frame_shape)
        dr, dc = np.broadcast_arrays(dr, dc)
        p = self.pixel_mm
        if self.setup == "tir":
            d0, ex, ev = self._basis()
            du = dc * p
            dv = dr * p * self.row_sign
            if self.camera_distance_mm is None:
                # parallel rays through the surface point (du, dv / cos theta, 0)
                s0 = np.stack([du, dv / math.cos(self.theta), np.zeros_like(du)], axis=-1)
                back = 2.0 * self.depth_mm
                origin = s0 - back * d0
                direction = np.broadcast_to(d0, origin.shape).copy()
            else:
                D = self.camera_distance_mm
                direction = d0 + (du / D)[..., None] * ex + (dv / D)[..., None] * ev
                direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
                origin = np.broadcast_to(-D * d0, direction.shape).copy()
            return origin, direction
        # FS-SS: camera above at height L looking straight down
        x = dc * p
        y = dr * p
        if self.fsss_camera_distance_mm is None:
            origin = np.stack([x, y, np.full_like(x, 10.0 * self.fsss_hp_mm + 1.0)], axis=-1)
            direction = np.broadcast_to(np.array([0.0, 0.0, -1.0]), origin.shape).copy()
        else:
            L = self.fsss_camera_distance_mm
            direction = np.stack([x / L, y / L, -np.ones_like(x)], axis=-1)
            direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
            origin = np.broadcast_to(np.array([0.0, 0.0, L]), direction.shape).copy()
        return origin, direction

    def to_canonical_xy(self, x_mm, y_mm):
        """Image-frame surface coordinates -> canonical (TIR); identity for FS-SS."""
        if self.setup == "tir":
            return x_mm, self.row_sign * np.asarray(y_mm)
        return x_mm, y_mm

    def flat_pattern_point(self, rows_px, cols_px, frame_shape):
        """Where each pixel's ray meets the pattern when the surface is flat.

        Returns
        -------
        px, py : ndarray, float64
            TIR: canonical-frame pattern-plane coordinates (mm). FS-SS: image
            frame pattern-plane coordinates (mm).
        """
        origin, d = self.camera_rays(rows_px, cols_px, frame_shape)
        if self.setup == "tir":
            s = -origin[..., 2] / d[..., 2]
            S = origin + s[..., None] * d
            t = self.depth_mm / d[..., 2]
            return S[..., 0] + t * d[..., 0], S[..., 1] + t * d[..., 1]
        return fsss_flat_trace(self, origin, d)

    def pixel_of_pattern_point(self, px, py, frame_shape):
        """Inverse of :meth:`flat_pattern_point`: pixel ``(row, col)`` (float).

        Exact for TIR (the flat mirror makes it a central projection of the
        mirror image of the pattern plane) and for FS-SS (radial Newton solve).
        """
        px = np.asarray(px, dtype=np.float64)
        py = np.asarray(py, dtype=np.float64)
        n_rows, n_cols = frame_shape
        rc, cc = (n_rows - 1) / 2.0, (n_cols - 1) / 2.0
        p = self.pixel_mm
        if self.setup == "tir":
            d0, ex, ev = self._basis()
            H = self.depth_mm
            if self.camera_distance_mm is None:
                y = py - H * math.tan(self.theta)
                du = px
                dv = y * math.cos(self.theta)
            else:
                D = self.camera_distance_mm
                # mirror image of the pattern point, seen from the camera at -D d0
                vx = px + D * d0[0]
                vy = py + D * d0[1]
                vz = H + D * d0[2]
                along = vx * d0[0] + vy * d0[1] + vz * d0[2]
                du = D * (vx * ex[0] + vy * ex[1] + vz * ex[2]) / along
                dv = D * (vx * ev[0] + vy * ev[1] + vz * ev[2]) / along
            return rc + self.row_sign * dv / p, cc + du / p
        # FS-SS
        if self.fsss_camera_distance_mm is None:
            return rc + py / p, cc + px / p
        L = self.fsss_camera_distance_mm
        rho_p = np.hypot(px, py)
        tan_b = fsss_invert_radial(self, rho_p)
        rho_s = L * tan_b
        with np.errstate(invalid="ignore", divide="ignore"):
            scale = np.where(rho_p > 0, rho_s / np.where(rho_p > 0, rho_p, 1.0), L / (L + self.fsss_apparent_depth_mm))
        return rc + py * scale / p, cc + px * scale / p

    def surface_point(self, rows_px, cols_px, frame_shape):
        """Image-frame surface position ``(x_mm, y_mm)`` where each pixel's ray meets the flat surface."""
        origin, d = self.camera_rays(rows_px, cols_px, frame_shape)
        s = -origin[..., 2] / d[..., 2]
        S = origin + s[..., None] * d
        if self.setup == "tir":
            return S[..., 0], self.row_sign * S[..., 1]
        return S[..., 0], S[..., 1]

    def linear_response(self, rows_px, cols_px, frame_shape) -> LinearResponse:
        """First-order displacement of each pixel per unit height and gradient.

        FS-SS: the exact refraction through the surface and the flat layers
        (:meth:`_fsss_linear_response`), differentiated numerically.

        Linearising the exact reflection (TIR) about the flat surface, the
        pattern point of a ray ``d`` (unit, going up) moves by
        ``dP = 2 h d_xy / d_z + 2 H (I + d_xy d_xy^T / d_z^2) grad h`` and the
        displacement is ``u = -J^-1 dP`` with ``J = dP0/d(row, col)`` the
        flat pixel-to-pattern Jacobian. The surface gradient is converted to
        pixel derivatives with ``K = dS/d(row, col)``. For the telecentric
        central ray this reproduces the paper's ``u_x = -2H h_x``,
        ``u_y = -(2H/cos^2 theta) h_y - 2 tan(theta) h``.

        Parameters
        ----------
        rows_px, cols_px : array_like
            Pixel coordinates (broadcast together).
        frame_shape : (int, int)

        Returns
        -------
        LinearResponse
        """
        rows_px, cols_px = np.broadcast_arrays(
            np.asarray(rows_px, dtype=np.float64), np.asarray(cols_px, dtype=np.float64)
        )
        if self.setup == "fsss":
            return self._fsss_linear_response(rows_px, cols_px, frame_shape)
        _, d = self.camera_rays(rows_px, cols_px, frame_shape)
        H = self.depth_mm
        dz = d[..., 2]
        dxy_c = d[..., :2]  # canonical (x, y)
        # work in image-frame (y, x) ordering: y_img = s * y_c
        s = self.row_sign
        dyx = np.stack([s * dxy_c[..., 1], dxy_c[..., 0]], axis=-1)
        # dP (image-frame (y, x)) = 2 h dyx/dz + 2H M grad_yx h, M = I + dyx dyx^T / dz^2
        a_P = 2.0 * dyx / dz[..., None]
        M = np.eye(2) + dyx[..., :, None] * dyx[..., None, :] / (dz**2)[..., None, None]
        # Jacobians by central differences of the exact flat maps (image frame)
        def pat(r, c):
            px, py = self.flat_pattern_point(r, c, frame_shape)
            return np.stack([s * py, px], axis=-1)

        def surf(r, c):
            x, y = self.surface_point(r, c, frame_shape)
            return np.stack([y, x], axis=-1)

        J = _pixel_jacobian(pat, rows_px, cols_px)  # J[..., i, j] = d P_i / d pix_j
        K = _pixel_jacobian(surf, rows_px, cols_px)
        Jinv = np.linalg.inv(J)
        Kinv_T = np.swapaxes(np.linalg.inv(K), -1, -2)
        a = -np.einsum("...ij,...j->...i", Jinv, a_P)
        B = -2.0 * H * Jinv @ M @ Kinv_T
        x, y = self.surface_point(rows_px, cols_px, frame_shape)
        return LinearResponse(a=a, B=B, surface_xy=np.stack([x, y], axis=-1), jac_surface=K)

    def _fsss_pattern_point(self, origin, d, h, hx, hy):
        """FS-SS pattern point of rays meeting a surface of height h, gradient (hx, hy).

        First order in ``h`` for the hit point (``S = S0 + h d / d_z``); exact
        vector refraction about the normal ``(-hx, -hy, 1)``, then through the
        flat layers (``n sin`` and the azimuth are conserved; the water column
        is ``h`` taller).
        """
        s0 = -origin[..., 2] / d[..., 2]
        S = origin[..., :2] + (s0 + h / d[..., 2])[..., None] * d[..., :2]
        nrm = np.stack([-hx * np.ones_like(s0), -hy * np.ones_like(s0), np.ones_like(s0)], axis=-1)
        nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
        cos_i = -np.sum(d * nrm, axis=-1)
        eta = self.n_air / self.n_water
        cos_t = np.sqrt(1.0 - eta**2 * (1.0 - cos_i**2))
        t = eta * d + (eta * cos_i - cos_t)[..., None] * nrm
        txy = t[..., :2]
        s2 = np.sum(txy * txy, axis=-1)
        P = S.copy()
        layers = fsss_layers_from_surface(self)
        for i, (thick, n) in enumerate(layers):
            r = self.n_water / n
            T = thick + (h if i == 0 else 0.0)
            P = P + (T * r / np.sqrt(1.0 - r * r * s2))[..., None] * txy
        return P

    def _fsss_linear_response(self, rows_px, cols_px, frame_shape) -> LinearResponse:
        """Per-pixel FS-SS response by central differences of :meth:`_fsss_pattern_point`."""
        origin, d = self.camera_rays(rows_px, cols_px, frame_shape)
        zero = np.zeros(rows_px.shape)
        eh, eg = 1e-3, 1e-4  # mm, slope: P is smooth, errors ~ eps^2

        def dP(h, hx, hy):
            return self._fsss_pattern_point(origin, d, h, hx, hy)

        # pattern shift per unit h and per unit gradient, image (y, x) ordering
        a_P = (dP(zero + eh, zero, zero) - dP(zero - eh, zero, zero)) / (2 * eh)
        gx = (dP(zero, zero + eg, zero) - dP(zero, zero - eg, zero)) / (2 * eg)
        gy = (dP(zero, zero, zero + eg) - dP(zero, zero, zero - eg)) / (2 * eg)
        a_P = a_P[..., ::-1]
        Mg = np.stack([gy[..., ::-1], gx[..., ::-1]], axis=-1)  # d P_(y,x) / d (h_y, h_x)
        def pat(r, c):
            px, py = self.flat_pattern_point(r, c, frame_shape)
            return np.stack([py, px], axis=-1)

        def surf(r, c):
            x, y = self.surface_point(r, c, frame_shape)
            return np.stack([y, x], axis=-1)

        J = _pixel_jacobian(pat, rows_px, cols_px)
        K = _pixel_jacobian(surf, rows_px, cols_px)
        Jinv = np.linalg.inv(J)
        Kinv_T = np.swapaxes(np.linalg.inv(K), -1, -2)
        a = -np.einsum("...ij,...j->...i", Jinv, a_P)
        B = -Jinv @ Mg @ Kinv_T
        x, y = self.surface_point(rows_px, cols_px, frame_shape)
        return LinearResponse(a=a, B=B, surface_xy=np.stack([x, y], axis=-1), jac_surface=K)

    def fsss_gradient_per_px(self) -> float:
        """FS-SS: surface slope per pixel of displacement, ``grad h = -s * u_px``.

        Returns ``s`` (dimensionless slope per pixel; image frame, both axes).

        Paraxial refraction through the layer stack (camera looking down):
        a surface slope ``grad h`` turns the ray entering the water towards
        the rising side by ``alpha grad h`` (``alpha = 1 - n_air/n_water``)
        and by ``alpha grad h * n_water/n_k`` in layer k (Snell at the flat
        interfaces), so the pattern point moves by ``dP = +alpha h_p grad h``
        with ``h_p = sum(t_k n_water / n_k)`` (thickness of water with the same
        lateral ray shift). The flat image maps one pixel to
        ``m = pixel_mm (1 + h_a / L)`` mm of pattern (``h_a = sum(t_k n_air /
        n_k)`` the apparent depth of the pattern, ``L`` the camera height;
        ``m = pixel_mm`` telecentric). With ``I(r) = I0(r - u)``, ``-m u = dP``
        hence ``grad h = -m u / (alpha h_p)``: Moisy et al. (2009)
        ``grad h = -dr / h*`` with ``h* = alpha h_p`` for the displacement
        ``dr = m u`` expressed at the pattern's scale; at the surface scale
        ``pixel_mm``, ``1/h* = (1 + h_a/L) / (alpha h_p)``. Checked against
        the exact refraction tracer of :mod:`processing.forward`.
        """
        if self.setup != "fsss":
            raise GeometryError("fsss_gradient_per_px is for the FS-SS setup")
        m = self.pixel_mm
        if self.fsss_camera_distance_mm is not None:
            m = m * (1.0 + self.fsss_apparent_depth_mm / self.fsss_camera_distance_mm)
        return m / (self.fsss_alpha * self.fsss_hp_mm)  # grad h = -this * u_px

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


def _pixel_jacobian(mapping, rows_px, cols_px, eps: float = 0.5) -> np.ndarray:
    """Jacobian of ``mapping(rows_px, cols_px) -> (..., 2)`` with respect to (row, col), by central differences.

    Returns ``J[..., i, j] = d mapping_i / d pixel_j`` (j = 0: row, 1: column), in
    the mapping's units per pixel; ``eps`` is the half step in pixels.
    """
    return np.stack(
        [
            (mapping(rows_px + eps, cols_px) - mapping(rows_px - eps, cols_px)) / (2 * eps),
            (mapping(rows_px, cols_px + eps) - mapping(rows_px, cols_px - eps)) / (2 * eps),
        ],
        axis=-1,
    )


def default_reference_region_mask(rows_px, cols_px, frame_shape) -> np.ndarray:
    """Default reference region: a border band of the frame.

    The band is ``ceil(0.04 * min(n_rows, n_cols))`` pixels wide (at least 1)
    along all four edges of the frame; returns a bool mask of shape
    ``(len(rows_px), len(cols_px))`` that is True on samples inside it.
    """
    n_rows, n_cols = frame_shape
    w = max(1, math.ceil(DEFAULT_REFERENCE_BAND * min(n_rows, n_cols)))
    rows_px = np.asarray(rows_px, dtype=np.float64)
    cols_px = np.asarray(cols_px, dtype=np.float64)
    rb = (rows_px < w) | (rows_px > n_rows - 1 - w)
    cb = (cols_px < w) | (cols_px > n_cols - 1 - w)
    return rb[:, None] | cb[None, :]


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
