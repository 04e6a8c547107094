"""The camera model and the first-order optics of a setup: :class:`CameraModel`,
a base class of :class:`processing.geometry.Geometry` (its methods read the
geometry's fields: ``setup``, ``theta``, ``depth_mm``, ``pixel_mm``,
``row_sign``, ``camera_distance_mm`` and the FS-SS keys), and
:class:`LinearResponse`, what :meth:`CameraModel.linear_response` returns.

Frames as in :mod:`processing.geometry`'s docstring. Pixel ``(row, col)`` of
a frame of shape ``(n_rows, n_cols)`` is offset from the frame centre
``((n_rows-1)/2, (n_cols-1)/2)``. A telecentric camera (distance None) sends
parallel rays; a pinhole camera at distance ``D`` from the surface centre
sends its central ray through the surface centre and one pixel subtends
``pixel_mm / D`` rad, so that ``pixel_mm`` is the surface mm per column at the
image centre in both cases (and ``pixel_mm / cos(theta)`` the surface mm per
row for TIR). :meth:`CameraModel.check_frame` refuses a camera and frame the
model does not describe.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .errors import GeometryError
from .fsss_flat import fsss_flat_trace, fsss_invert_radial, fsss_layers_from_surface

__all__ = ["CameraModel", "LinearResponse", "MAX_FIELD_HALF_ANGLE_DEG", "field_half_diagonal_mm",
           "nearest_camera_distance_mm", "pixel_jacobian"]

#: Widest angle off the camera axis (deg) that the pinhole (rectilinear lens) model is
#: trusted for; see :meth:`CameraModel.check_frame`.
MAX_FIELD_HALF_ANGLE_DEG = 60.0


def field_half_diagonal_mm(pixel_mm: float, frame_shape) -> float:
    """Half the diagonal of a frame of ``frame_shape`` pixels ``pixel_mm`` apart, from the first pixel's centre to
    the last's (mm): how far off the optical axis a finite-distance camera's corner pixels look."""
    n_rows, n_cols = (int(v) for v in frame_shape)
    return 0.5 * math.hypot((n_cols - 1) * pixel_mm, (n_rows - 1) * pixel_mm)


def nearest_camera_distance_mm(pixel_mm: float, frame_shape, half_angle_deg: float = MAX_FIELD_HALF_ANGLE_DEG) -> float:
    """The nearest camera distance (mm) at which no pixel of the frame is more than ``half_angle_deg`` off the
    optical axis (:meth:`CameraModel.check_frame`'s bound by default)."""
    return field_half_diagonal_mm(pixel_mm, frame_shape) / math.tan(math.radians(half_angle_deg))


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


class CameraModel:
    """Rays, flat-surface maps and the linear response of the setup's camera.

    A base of the frozen dataclass :class:`~processing.geometry.Geometry`,
    which holds the fields these methods read; not used on its own.
    """

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
            angle = math.degrees(math.atan2(field_half_diagonal_mm(self.pixel_mm, frame_shape), distance))
            if angle > MAX_FIELD_HALF_ANGLE_DEG:
                need = nearest_camera_distance_mm(self.pixel_mm, frame_shape)
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

    def board_period_mm(self, carrier_freq, frame_shape) -> float:
        """The printed checkerboard's period along its x (mm) that carriers
        ``carrier_freq`` (``(2, 2)``, ``(f_row, f_col)`` cycles per pixel, the
        two diagonal peaks of :func:`processing.carriers.find_carriers`) of a
        frame of ``frame_shape`` show through this setup, at the image centre.

        The flat-surface map pixel -> pattern plane (:meth:`flat_pattern_point`)
        has the Jacobian ``J`` (mm per pixel) there; a pattern frequency
        ``f`` (cycles per mm) shows in the image as ``J^T f``.  Both diagonal
        carriers of a board with periods ``p`` along x and ``p s`` along y
        (``s = pattern_stretch_y``) have ``|f| = sqrt(1 + 1 / s^2) / p``
        however the board is turned: ``p`` is that over the carriers'
        mean length.  It reads ``pixel_mm``, ``theta_deg``, ``depth_mm`` and
        the camera distance: the pattern's scale, not the surface's (the notes'
        two magnifications), which a pinhole camera sees smaller by ``D / (D +
        H / cos(theta))``.  NaN where the map is degenerate there (a camera
        that :meth:`check_frame` refuses)."""
        f_pattern = self._pattern_frequencies(carrier_freq, frame_shape)
        if f_pattern is None:
            return float("nan")
        stretch = float(self.pattern_stretch_y or 1.0)
        return float(math.sqrt(1.0 + 1.0 / stretch ** 2) / np.mean(np.hypot(f_pattern[:, 0], f_pattern[:, 1])))

    def board_cell_aspect(self, carrier_freq, frame_shape) -> float:
        """How many times longer along its y than along its x the printed board's cells are, as carriers
        ``carrier_freq`` show them through this setup at the image centre (what ``pattern_stretch_y`` should
        be; 1 for a square board). The two diagonal carriers of cells ``p`` by ``p s`` sum and differ to
        ``2 / p`` along the board's x and ``2 / (p s)`` along its y, however the board is turned (the one
        nearer the pattern's x is taken as x). A ``theta_deg`` a few degrees off moves it by about
        ``tan(theta) dtheta`` (5 % for 2 deg at 55 deg). NaN where the map is degenerate there."""
        f_pattern = self._pattern_frequencies(carrier_freq, frame_shape)
        if f_pattern is None:
            return float("nan")
        one, two = f_pattern[0] + f_pattern[1], f_pattern[0] - f_pattern[1]
        along_x, along_y = (one, two) if abs(one[0]) * np.hypot(*two) >= abs(two[0]) * np.hypot(*one) else (two, one)
        return float(np.hypot(*along_x) / max(float(np.hypot(*along_y)), 1e-300))

    def _pattern_frequencies(self, carrier_freq, frame_shape):
        """The carriers ``carrier_freq`` (``(2, 2)``, cycles per pixel) on the pattern plane (cycles per mm,
        ``(x, y)`` each) through the flat-surface map's Jacobian at the image centre; None where degenerate."""
        rows, cols = frame_shape
        centre_r, centre_c = np.array([(rows - 1) / 2.0]), np.array([(cols - 1) / 2.0])
        with np.errstate(all="ignore"):
            jac = pixel_jacobian(lambda r, c: np.stack(self.flat_pattern_point(r, c, frame_shape), axis=-1),
                                  centre_r, centre_c)[0]  # (pattern x, y) x (row, col), mm per pixel
        if not np.all(np.isfinite(jac)) or abs(np.linalg.det(jac)) < 1e-300:
            return None
        return np.linalg.solve(jac.T, np.asarray(carrier_freq, np.float64).T).T

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

    @property
    def surface_separable(self) -> bool:
        """Whether :meth:`surface_point`'s x depends on the column alone and its y on the row alone.

        True for a telecentric TIR camera and for FS-SS (either camera: it looks straight down). False
        for a TIR camera at a finite distance: the image is keystoned, the x of a column changes
        along the rows, and the ``(x_mm, y_mm)`` of the central row and column do not say where the
        other samples lie (:meth:`grid_surface_mm` does)."""
        return not (self.setup == "tir" and self.camera_distance_mm is not None)

    def grid_surface_mm(self, rows_px, cols_px, frame_shape):
        """``(x_mm, y_mm)``, each ``(len(rows_px), len(cols_px))`` float64: the image-frame surface position
        of every sample of the grid of ``rows_px`` x ``cols_px`` (pixel coordinates of a frame of
        ``frame_shape``), where its ray meets the flat surface (:meth:`surface_point`); in blocks of rows
        of about a million samples (the rays' temporaries of a 4096^2 grid would take 1 GB at once)."""
        rows = np.asarray(rows_px, dtype=np.float64).ravel()[:, None]
        cols = np.asarray(cols_px, dtype=np.float64).ravel()[None, :]
        x_mm = np.empty((rows.shape[0], cols.shape[1]))
        y_mm = np.empty_like(x_mm)
        block = max(1, (1 << 20) // max(cols.shape[1], 1))
        for start in range(0, rows.shape[0], block):
            x_mm[start:start + block], y_mm[start:start + block] = self.surface_point(
                rows[start:start + block], cols, frame_shape)
        return x_mm, y_mm

    def pixel_of_surface_point(self, x_mm, y_mm, frame_shape):
        """Inverse of :meth:`surface_point`: pixel ``(row, col)`` (float) whose ray meets the flat surface
        at image-frame ``(x_mm, y_mm)``. Exact: TIR at a finite distance is a central projection of the
        surface plane; telecentric TIR and FS-SS (either camera) scale each axis alone."""
        x_mm = np.asarray(x_mm, dtype=np.float64)
        y_mm = np.asarray(y_mm, dtype=np.float64)
        n_rows, n_cols = frame_shape
        rc, cc = (n_rows - 1) / 2.0, (n_cols - 1) / 2.0
        p = self.pixel_mm
        if self.setup != "tir":
            return rc + y_mm / p, cc + x_mm / p
        y_c = self.row_sign * y_mm  # canonical
        if self.camera_distance_mm is None:
            du, dv = x_mm, y_c * math.cos(self.theta)
        else:
            D = self.camera_distance_mm
            d0, ex, ev = self._basis()
            # the surface point seen from the camera at -D d0
            vx, vy, vz = x_mm + D * d0[0], y_c + D * d0[1], D * d0[2]
            along = vx * d0[0] + vy * d0[1] + vz * d0[2]
            du = D * (vx * ex[0] + vy * ex[1] + vz * ex[2]) / along
            dv = D * (vx * ev[0] + vy * ev[1] + vz * ev[2]) / along
        return rc + self.row_sign * dv / p, cc + du / p

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

        J = pixel_jacobian(pat, rows_px, cols_px)  # J[..., i, j] = d P_i / d pix_j
        K = pixel_jacobian(surf, rows_px, cols_px)
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

        J = pixel_jacobian(pat, rows_px, cols_px)
        K = pixel_jacobian(surf, rows_px, cols_px)
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



def pixel_jacobian(mapping, rows_px, cols_px, eps: float = 0.5) -> np.ndarray:
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

