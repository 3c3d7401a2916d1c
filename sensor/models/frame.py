"""Frame (CCD matrix) camera: collinearity with interior and exterior orientation.

The chain follows Bettemir (2006) §4.1, with the errata of notes §9.2 fixed:

``image (col,row) -> photo (x', y', mm) -> distortion-corrected (x, y) -> camera
-> body -> orbital -> ECEF``

* Image -> photo (Eq. 4.1, pixel corners -> our pixel centres):
  ``x' = (col + 0.5 - width/2) c - dx``, ``y' = (height/2 - row - 0.5) c - dy`` (mm, y up).
* Brown distortion, applied as a direct correction (Eq. 4.2-4.3)::

    x = x'(1 - k1 r^2 - k2 r^4) - p1 (r^2 + 2x'^2) - 2 p2 x'y'
    y = y'(1 - k1 r^2 - k2 r^4) - p2 (r^2 + 2y'^2) - 2 p1 x'y'

  Ground -> image inverts it by Newton iteration (the thesis never goes that way).
* Camera -> body: ``R3(-90 deg) R1(180 deg)`` so ``D_B = (y, x, f)/n`` (Eq. 4.5: image up is the
  flight direction, the ray points down). The thesis's Appendix C drops R3(-90 deg); that is an
  erratum (notes §2.4).
* Body -> orbital: roll/pitch/yaw by Eq. 4.7
  (:func:`stereodem.sensor.geo.rotations.body_to_orbital`).
* Orbital -> ECEF: orbital frame from the position and the inertial velocity; the
  precession/nutation/sidereal chain of Eq. 4.22-4.31 cancels exactly (notes §2.6), so the
  model is independent of the epoch.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace

import numpy as np

from stereodem.core import geodesy
from stereodem.core.errors import SensorModelError
from stereodem.sensor.geo.rotations import body_to_orbital, orbital_frame
from stereodem.sensor.models.base import SensorModel, broadcast_coordinates, ray_to_lonlat


@dataclass
class FrameCamera(SensorModel):
    """A frame camera at one exposure.

    Parameters
    ----------
    width, height : int
        Image size, pixels.
    focal_mm : float
        Focal length f, millimetres.
    pitch_mm : float
        Pixel pitch c, millimetres per pixel (BILSAT: 0.0074).
    dx_mm, dy_mm : float
        Principal point offset (mm, photo frame).
    k1, k2 : float
        Radial distortion (1/mm^2, 1/mm^4); ``p1, p2`` decentering (1/mm).
    position : array (3,)
        Perspective centre in ECEF, metres.
    velocity : array (3,)
        Earth-fixed velocity in ECEF, m/s (defines the orbital frame with ``position``).
    roll, pitch, yaw : float
        Attitude of the body frame in the orbital frame, radians (Eq. 4.7).
    """

    width: int
    height: int
    focal_mm: float
    pitch_mm: float
    position: np.ndarray
    velocity: np.ndarray
    roll: float = 0.0
    pitch: float = 0.0
    yaw: float = 0.0
    dx_mm: float = 0.0
    dy_mm: float = 0.0
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    _R: np.ndarray = field(init=False, repr=False)

    #: names of the adjustable parameters, in the order of :meth:`parameters`
    PARAMETERS = (
        "focal_mm",
        "dx_mm",
        "dy_mm",
        "k1",
        "k2",
        "p1",
        "p2",
        "roll",
        "pitch",
        "yaw",
        "x",
        "y",
        "z",
    )
    #: unit of each parameter (focal length and principal point in mm, the radial and
    #: tangential distortion per mm^2, mm^4 and mm, attitude in rad, position in m)
    PARAMETER_UNITS = {
        "focal_mm": "mm",
        "dx_mm": "mm",
        "dy_mm": "mm",
        "k1": "1/mm^2",
        "k2": "1/mm^4",
        "p1": "1/mm",
        "p2": "1/mm",
        "roll": "rad",
        "pitch": "rad",
        "yaw": "rad",
        "x": "m",
        "y": "m",
        "z": "m",
    }

    def __post_init__(self):
        self.position = np.asarray(self.position, dtype=np.float64).reshape(3)
        self.velocity = np.asarray(self.velocity, dtype=np.float64).reshape(3)
        if not (np.all(np.isfinite(self.position)) and np.all(np.isfinite(self.velocity))):
            raise SensorModelError("FrameCamera: non-finite position or velocity")
        if self.focal_mm <= 0 or self.pitch_mm <= 0:
            raise SensorModelError("FrameCamera: focal length and pixel pitch must be positive")
        # camera -> ECEF rotation: ECEF <- orbital <- body <- camera
        c2b = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]) @ np.diag(
            [1.0, -1.0, -1.0]
        )
        self._R = (
            orbital_frame(self.position, self.velocity)
            @ body_to_orbital(self.roll, self.pitch, self.yaw)
            @ c2b
        )

    # ------------------------------------------------------------------ parameters
    def parameters(self) -> dict:
        """Adjustable parameters as an ordered name -> value dict (units as in the fields)."""
        vals = {n: getattr(self, n) for n in self.PARAMETERS[:10]}
        vals.update(x=self.position[0], y=self.position[1], z=self.position[2])
        return {k: float(v) for k, v in vals.items()}

    def with_parameters(self, **changes) -> FrameCamera:
        """A copy with some parameters changed (names of :attr:`PARAMETERS`)."""
        pos = self.position.copy()
        for i, k in enumerate("xyz"):
            if k in changes:
                pos[i] = changes.pop(k)
        unknown = set(changes) - {f.name for f in fields(self)}
        if unknown:
            raise SensorModelError(f"FrameCamera: unknown parameter(s) {sorted(unknown)}")
        return replace(self, position=pos, **changes)

    # ------------------------------------------------------------------ interior orientation
    def _pixel_to_photo(self, col, row):
        c = self.pitch_mm
        return (
            (np.asarray(col, float) + 0.5 - self.width / 2) * c - self.dx_mm,
            (self.height / 2 - np.asarray(row, float) - 0.5) * c - self.dy_mm,
        )

    def _photo_to_pixel(self, xp, yp):
        c = self.pitch_mm
        return (
            (xp + self.dx_mm) / c + self.width / 2 - 0.5,
            self.height / 2 - (yp + self.dy_mm) / c - 0.5,
        )

    def _distort(self, xp, yp):
        """Measured photo coordinates (x', y') -> corrected (x, y), Eq. 4.3 (mm)."""
        r2 = xp * xp + yp * yp
        radial = 1.0 - self.k1 * r2 - self.k2 * r2 * r2
        x = xp * radial - self.p1 * (r2 + 2 * xp * xp) - 2 * self.p2 * xp * yp
        y = yp * radial - self.p2 * (r2 + 2 * yp * yp) - 2 * self.p1 * xp * yp
        return x, y

    def _undistort(self, x, y, tol=1e-12, max_iter=50):
        """Invert :meth:`_distort` by Newton iteration with its analytic Jacobian."""
        xp, yp = np.array(x, float), np.array(y, float)
        k1, k2, p1, p2 = self.k1, self.k2, self.p1, self.p2
        for _ in range(max_iter):
            fx, fy = self._distort(xp, yp)
            ex, ey = fx - x, fy - y
            r2 = xp * xp + yp * yp
            radial = 1.0 - k1 * r2 - k2 * r2 * r2
            drad = -2 * k1 - 4 * k2 * r2  # d(radial)/d(r2) * 2 -> times x or y
            j11 = radial + xp * drad * xp - p1 * 6 * xp - 2 * p2 * yp
            j12 = xp * drad * yp - p1 * 2 * yp - 2 * p2 * xp
            j21 = yp * drad * xp - p2 * 2 * xp - 2 * p1 * yp
            j22 = radial + yp * drad * yp - p2 * 6 * yp - 2 * p1 * xp
            det = j11 * j22 - j12 * j21
            dx = (j22 * ex - j12 * ey) / det
            dy = (-j21 * ex + j11 * ey) / det
            xp -= dx
            yp -= dy
            if np.all(np.abs(dx) < tol) and np.all(np.abs(dy) < tol):
                break
        return xp, yp

    # ------------------------------------------------------------------ contract
    def rays(self, col, row):
        """Exact ECEF rays ``(origin, unit direction)`` of pixels."""
        col, row = broadcast_coordinates(self, col, row, what="image coordinates")
        x, y = self._distort(*self._pixel_to_photo(col, row))
        d_c = np.stack([x, y, np.full(x.shape, -self.focal_mm)], -1)
        d = d_c @ self._R.T
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        return np.broadcast_to(self.position, d.shape), d

    def localize(self, col, row, h):
        """Image to ground at ellipsoidal height ``h`` (m): ``(lon, lat)`` in degrees."""
        col, row, h = broadcast_coordinates(self, col, row, h, what="image coordinates or heights")
        o, d = self.rays(col, row)
        return ray_to_lonlat(o, d, h)

    def project(self, lon, lat, h):
        """Ground (deg, deg, m) to image ``(col, row)``; NaN for points behind the camera."""
        lon, lat, h = broadcast_coordinates(self, lon, lat, h, what="ground coordinates")
        x, y, z = geodesy.geodetic_to_ecef(lon, lat, h)
        d = np.stack([x, y, z], -1) - self.position
        d_c = d @ self._R  # = R^T d, camera frame
        behind = d_c[..., 2] >= 0  # camera looks along -z
        with np.errstate(divide="ignore", invalid="ignore"):
            xc = -self.focal_mm * d_c[..., 0] / d_c[..., 2]
            yc = -self.focal_mm * d_c[..., 1] / d_c[..., 2]
        xp, yp = self._undistort(xc, yc)
        col, row = self._photo_to_pixel(xp, yp)
        col = np.where(behind, np.nan, col)
        row = np.where(behind, np.nan, row)
        return col, row

    def height_bounds(self):
        return (-500.0, 9000.0)

    # ------------------------------------------------------------------ construction
    @classmethod
    def looking_at(
        cls, position, velocity, target_lon, target_lat, target_h=0.0, *, yaw=0.0, **interior
    ) -> FrameCamera:
        """A camera at ``position`` whose boresight passes through the ground target.

        Roll and pitch are solved so that the principal ray (no principal-point offset) hits
        ``(target_lon, target_lat, target_h)``; ``yaw`` is kept (radians).
        """
        cam = cls(position=position, velocity=velocity, **interior)
        t = (
            np.array(geodesy.geodetic_to_ecef(target_lon, target_lat, target_h), float)
            - cam.position
        )
        t_o = orbital_frame(cam.position, cam.velocity).T @ (t / np.linalg.norm(t))
        # boresight in body is +z; D_O = Rz(yaw) Rx(roll) Ry(pitch) e_z -> undo yaw first
        cy, sy = np.cos(yaw), np.sin(yaw)
        u = np.array([cy * t_o[0] + sy * t_o[1], -sy * t_o[0] + cy * t_o[1], t_o[2]])
        pitch = np.arcsin(np.clip(u[0], -1, 1))
        roll = np.arctan2(-u[1], u[2])
        return replace(cam, roll=float(roll), pitch=float(pitch), yaw=float(yaw))
