"""Collinearity line camera with polynomial exterior orientation in a local east/north/up
frame: the common body of Orun & Natarajan (1994) and Kratky (1989).

For image line ``row`` (normalised ``tau``, :func:`._common.line_variable`) the projection
centre is ``C(tau) = (X, Y, Z)`` with ``X = X_0 + X_1 tau + X_2 tau^2`` etc. (metres, local
ENU frame with its origin on the ellipsoid below the image centre) and the rotation from the
ground frame to the camera frame is ``R = R3(kappa) R2(phi) R1(omega)`` (passive rotations,
:mod:`stereodem.sensor.geo.rotations`; with ``phi = 0`` it is Topan Eq. 3.28), each angle a
quadratic in ``tau`` (radians). The camera frame has ``x`` normal to the scan plane (along the
flight), ``y`` along the detector line and ``z`` opposite to the boresight, and a ground point
``G`` is imaged when (Topan Eq. 3.17, x = 0 for a line camera)::

    c = R (G - C(tau)),   c_x = 0,   col = col0 + (-c_y / c_z) / (ifov (1 + scan_scale))

``ifov`` (rad per pixel, signed so that the column grows the way the image does) and ``col0``
come from the metadata model. Which coefficients a model exposes as adjustable parameters, and
which it freezes, is what distinguishes Orun & Natarajan from Kratky.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from stereodem.core import geodesy
from stereodem.core.errors import SensorModelError
from stereodem.sensor.geo.rotations import R1, R2, R3
from stereodem.sensor.models.base import SensorModel, localize_on_rays
from stereodem.sensor.models.orbital._common import (
    CoefficientModel,
    fit_to_reference,
    line_variable,
    quadratic,
    secant_rows,
)

#: Every coefficient of the line camera (units: m for X/Y/Z, rad for angles, 1 for the scale).
COEFFICIENTS = tuple(
    f"{p}_{k}" for p in ("X", "Y", "Z", "omega", "phi", "kappa") for k in range(3)
) + ("scan_scale",)


def _steps():
    return {n: (1.0 if n[0] in "XYZ" else 1e-6) for n in COEFFICIENTS}


class PolynomialLineCamera(CoefficientModel, SensorModel):
    """Line camera with quadratic exterior orientation (see the module docstring).

    Subclasses set :attr:`ADJUSTABLE` (the exposed parameters), :attr:`ADJUST_SETS` (named
    parameter sets; the first is the default) and may freeze coefficients in
    :meth:`_shape_initial`.
    """

    ADJUSTABLE: tuple = COEFFICIENTS
    ADJUST_SETS: dict = {}
    PARAMETER_STEPS = _steps()
    MODEL_TYPE = "linecam"
    DICT_FIELDS = ("lon0", "lat0", "col0", "ifov")

    def __init__(
        self,
        *,
        width: int,
        height: int,
        lon0: float,
        lat0: float,
        col0: float,
        ifov: float,
        coefficients: dict,
        name: str | None = None,
        height_range=(-500.0, 9000.0),
    ):
        if int(width) < 2 or int(height) < 2:
            raise SensorModelError(
                f"line camera: image must be at least 2 x 2, got {width} x {height}"
            )
        if not (np.isfinite(ifov) and ifov != 0):
            raise SensorModelError(f"line camera: IFOV must be finite and non-zero, got {ifov}")
        self.width, self.height = int(width), int(height)
        self.lon0, self.lat0 = float(lon0), float(lat0)
        self.col0, self.ifov = float(col0), float(ifov)
        self.name = name or type(self).__name__
        self._c = dict.fromkeys(COEFFICIENTS, 0.0)
        self._set(coefficients)
        self._hr = tuple(float(v) for v in height_range)
        self._enu = geodesy.enu_basis(self.lon0, self.lat0)  # rows: e, n, u in ECEF
        self._o = np.array(geodesy.geodetic_to_ecef(self.lon0, self.lat0, 0.0), float)

    # ------------------------------------------------------------------ parameters
    def parameters(self) -> dict:
        return {n: self._c[n] for n in self.ADJUSTABLE}

    def coefficients(self) -> dict:
        """All coefficients, frozen ones included."""
        return dict(self._c)

    def _parameter_listing(self):
        return ", ".join(self.ADJUSTABLE)

    # ------------------------------------------------------------------ geometry
    def _pose(self, row):
        tau = line_variable(row, self.height)
        c = self._c
        centre = np.stack(
            [quadratic(c[f"{a}_0"], c[f"{a}_1"], c[f"{a}_2"], tau) for a in "XYZ"], -1
        )
        om, ph, ka = (
            quadratic(c[f"{a}_0"], c[f"{a}_1"], c[f"{a}_2"], tau) for a in ("omega", "phi", "kappa")
        )
        return centre, R3(ka) @ R2(ph) @ R1(om)

    def _to_enu(self, lon, lat, h):
        p = np.stack(geodesy.geodetic_to_ecef(lon, lat, h), -1)
        return (p - self._o) @ self._enu.T

    def _camera(self, g, row):
        centre, rot = self._pose(row)
        return np.einsum("...ij,...j->...i", rot, g - centre)

    def project(self, lon, lat, h, *, max_iterations: int = 30):
        """Ground (deg, deg, m above the ellipsoid) -> ``(col, row)``: secant iteration on the
        line for ``c_x = 0``, then the column from the cross-track ratio."""
        self.check_inputs(lon, lat, h, what="ground coordinates")
        lon, lat, h = np.broadcast_arrays(*(np.asarray(a, float) for a in (lon, lat, h)))
        shape = lon.shape
        g = self._to_enu(lon.ravel(), lat.ravel(), h.ravel())

        def f(row):
            cam = self._camera(g, row)
            return cam[:, 0] / np.linalg.norm(cam, axis=-1), cam

        r1, (_, cam) = secant_rows(f, g.shape[0], self.height, max_iterations=max_iterations)
        with np.errstate(divide="ignore", invalid="ignore"):
            y = -cam[:, 1] / cam[:, 2]
        col = self.col0 + y / (self.ifov * (1.0 + self._c["scan_scale"]))
        bad = ~(cam[:, 2] < 0) | ~np.isfinite(col)
        col = np.where(bad, np.nan, col)
        row = np.where(bad, np.nan, r1)
        return col.reshape(shape), row.reshape(shape)

    def rays(self, col, row):
        """ECEF lines of sight ``(origin, unit direction)`` of pixels."""
        self.check_inputs(col, row, what="image coordinates")
        col, row = np.broadcast_arrays(np.asarray(col, float), np.asarray(row, float))
        centre, rot = self._pose(row)
        y = (col - self.col0) * self.ifov * (1.0 + self._c["scan_scale"])
        d_cam = np.stack([np.zeros_like(y), y, -np.ones_like(y)], -1)
        d_enu = np.einsum("...ji,...j->...i", rot, d_cam)
        o = self._o + centre @ self._enu
        d = d_enu @ self._enu
        return o, d / np.linalg.norm(d, axis=-1, keepdims=True)

    def localize(self, col, row, h):
        return localize_on_rays(self, col, row, h)

    # ------------------------------------------------------------------ initial values
    @classmethod
    def from_model(
        cls, reference, *, name: str | None = None, samples: int = 21, altitude: float = 705e3
    ):
        """Initial values from a metadata model (pushbroom, ASTER, RPC...).

        Projection centres: the origins of the reference's exact rays when it has an
        ephemeris, else the point of the centre detector's ray ``altitude`` metres up; the
        camera axes from the centre detector's ray, the detector line's direction and the
        flight direction; quadratics in ``tau`` fitted to both over ``samples`` lines. Then the
        coefficients the model keeps (:meth:`_shape_initial`) are refined on virtual points of
        the reference (:func:`._common.fit_to_points`); the refinement's RMS (pixels) is kept
        in :attr:`init_rms_px`.
        """
        if isinstance(reference, cls):
            return reference  # already this model (e.g. from a model set)
        w, hgt = reference.width, reference.height
        lon0, lat0 = reference.center_lonlat(0.0)
        col0 = 0.5 * (w - 1)
        rows = np.linspace(0, hgt - 1, samples)
        enu = geodesy.enu_basis(lon0, lat0)
        o0 = np.array(geodesy.geodetic_to_ecef(lon0, lat0, 0.0), float)
        origin, d0 = reference.rays(np.full(samples, col0), rows)
        if not hasattr(reference, "ephemeris"):
            up = origin / np.linalg.norm(origin, axis=-1, keepdims=True)
            _, _, h_o = geodesy.ecef_to_geodetic(*origin.T)
            s = (altitude - np.asarray(h_o)) / np.maximum(-np.sum(d0 * up, -1), 0.1)
            origin = origin - s[:, None] * d0
        centre = (origin - o0) @ enu.T
        b = d0 @ enu.T
        _, dl = reference.rays(np.full(samples, col0 + 1.0), rows)
        _, dr = reference.rays(np.full(samples, col0 - 1.0), rows)
        line = (dl - dr) @ enu.T
        flight = np.gradient(centre, axis=0)
        x = np.cross(b, line)
        x /= np.linalg.norm(x, axis=-1, keepdims=True)
        x *= np.sign(np.sum(x * flight, -1))[:, None]
        z = -b
        y = np.cross(z, x)
        rot = np.stack([x, y, z], -2)  # ground -> camera rows
        ang = Rotation.from_matrix(np.swapaxes(rot, -1, -2)).as_euler("XYZ")
        ang = np.unwrap(ang, axis=0)
        tau = line_variable(rows, hgt)
        coef = {}
        for k, a in enumerate("XYZ"):
            c2, c1, c0 = np.polyfit(tau, centre[:, k], 2)
            coef.update({f"{a}_0": c0, f"{a}_1": c1, f"{a}_2": c2})
        for k, a in enumerate(("omega", "phi", "kappa")):
            c2, c1, c0 = np.polyfit(tau, ang[:, k], 2)
            coef.update({f"{a}_0": c0, f"{a}_1": c1, f"{a}_2": c2})
        # signed IFOV from the neighbouring detector
        cam = rot[samples // 2] @ (dl[samples // 2] @ enu.T)
        ifov = float(-cam[1] / cam[2])
        model = cls(
            width=w,
            height=hgt,
            lon0=lon0,
            lat0=lat0,
            col0=col0,
            ifov=ifov,
            coefficients=cls._shape_initial(coef),
            name=name,
            height_range=reference.height_bounds(),
        )
        names = list(model.ADJUSTABLE) + [n for n in cls.REFINE_FROZEN if n not in model.ADJUSTABLE]
        return fit_to_reference(model, reference, names)

    #: Frozen coefficients still refined when the model is initialised from metadata.
    REFINE_FROZEN: tuple = ()

    @staticmethod
    def _shape_initial(coef: dict) -> dict:
        """Hook: set the frozen coefficients of the initial values (default: keep all)."""
        return coef

    def _dict_entries(self) -> dict:
        return {"coefficients": dict(self._c)}

    @classmethod
    def _entries_from_dict(cls, d: dict) -> dict:
        return {"coefficients": d["coefficients"]}
