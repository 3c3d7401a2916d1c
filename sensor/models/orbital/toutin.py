"""A Toutin-type rigorous orbital model, written from Toutin's published equations (CCRS 3D
model; Toutin 1995, 2003b; as transcribed in Topan 2009 Eq. 3.2-3.5), not from PCI's code.

Ground coordinates: ``(x, y)`` in a local frame on the ellipsoid tangent plane at the image
centre, ``y`` along the ground track and ``x`` along the scan (the map "rotation-translation"
of Toutin's last step: ``x0, y0, rot``, three of the eight unknowns), ``h`` the ellipsoidal
height (m). Then::

    X = (x - a y)(1 + h / N0) + b y^2 + c x y                               (3.4)
    H = h - X^2 / (2 N0)                                                    (3.5)
    P p + y (1 + dgamma X) - tau H - H0 dT* = 0          -> line   p = row - r_c     (3.2)
    X + theta H / cos(chi) + alpha q (Q + theta X - H / cos(chi)) - Q dR = 0
                                                         -> column q = col - c_c     (3.3)

``x, y`` are map coordinates: those of the point's foot on the ellipsoid (``h = 0``), as in
Toutin's cartographic frame; taking them at the point's own height instead puts a
``(1 + h/N0)`` scale on ``y`` that the equations do not model (0.3 px per 3 km of height at
the ends of an ASTER image).

Symbols: ``N0`` the ellipsoid normal at the image centre, ``H0`` the satellite height there,
``alpha`` the IFOV (signed with the column direction), ``chi`` the off-nadir angle of the
centre detector (Topan leaves it undefined; it is the view angle that scales the relief term),
``P, Q`` scale factors in ``y`` and ``x`` (m per line; m, about the slant range), ``tau,
theta`` the levelling angles in ``y`` and ``x``, ``a`` the Earth-rotation skew, ``b, c,
dgamma`` second-order terms, ``dT*`` (pitch + yaw) and ``dR`` (roll) the non-linear attitude
variations, here quadratic in ``y / 100 km`` (``dT_1, dT_2, dR_1, dR_2``).

Unknowns adjusted with GCPs (set ``toutin``, 8 = Toutin's 5 + 3, Zoej 1997): ``P, Q, tau,
theta, a, x0, y0, rot``. ``b, c, dgamma`` and the attitude variations are computed from the
orbit in Toutin's model; here they are taken from the metadata model of the image by fitting
the equations to its virtual points (:meth:`ToutinModel.from_model`) and then held fixed.
Set ``toutin-full`` frees them too (15).
"""
from __future__ import annotations

import numpy as np

from stereodem.sensor.errors import SensorModelError
from stereodem.sensor.geo import geodesy
from stereodem.sensor.models.base import SensorModel
from stereodem.sensor.models.orbital._common import (CoefficientModel, fit_to_points, invert_projection,
                                                     virtual_points)

ADJUSTED = ("P", "Q", "tau", "theta", "a", "x0", "y0", "rot")
SECOND_ORDER = ("b", "c", "dgamma", "dT_1", "dT_2", "dR_1", "dR_2")
_Y_SCALE = 1e5          # m, the unit of y in the attitude-variation polynomials


class ToutinModel(CoefficientModel, SensorModel):
    """Toutin-type model (module docstring); build it with :meth:`from_model`."""

    ADJUST_SETS = {"toutin": list(ADJUSTED), "toutin-full": list(ADJUSTED + SECOND_ORDER)}
    PARAMETER_STEPS = {"P": 1e-6, "Q": 1.0, "tau": 1e-7, "theta": 1e-7, "a": 1e-7, "x0": 0.1,
                       "y0": 0.1, "rot": 1e-7, "b": 1e-13, "c": 1e-13, "dgamma": 1e-11,
                       "dT_1": 1e-8, "dT_2": 1e-8, "dR_1": 1e-8, "dR_2": 1e-8}
    MODEL_TYPE = "toutin"

    def __init__(self, *, width, height, lon0, lat0, N0, H0, alpha, chi, values: dict,
                 name=None, height_range=(-500.0, 9000.0)):
        self.width, self.height = int(width), int(height)
        self.lon0, self.lat0 = float(lon0), float(lat0)
        self.N0, self.H0, self.alpha, self.chi = float(N0), float(H0), float(alpha), float(chi)
        if not all(np.isfinite(v) for v in (self.N0, self.H0, self.alpha, self.chi)) or self.alpha == 0:
            raise SensorModelError("Toutin model: N0, H0, alpha, chi must be finite (alpha non-zero)")
        self.name = name or "toutin"
        self._c = dict.fromkeys(ADJUSTED + SECOND_ORDER, 0.0)
        self._set(values)
        self._hr = tuple(float(v) for v in height_range)
        self.r_c, self.c_c = 0.5 * (self.height - 1), 0.5 * (self.width - 1)

    # ------------------------------------------------------------------ parameters
    def parameters(self) -> dict:
        return dict(self._c)

    coefficients = parameters

    # ------------------------------------------------------------------ equations
    def _local(self, lon, lat, h):
        e, n, _ = geodesy.ecef_to_enu(*geodesy.geodetic_to_ecef(lon, lat, 0.0 * h), self.lon0, self.lat0, 0.0)
        v = self._c
        cr, sr = np.cos(v["rot"]), np.sin(v["rot"])
        de, dn = np.asarray(e) - v["x0"], np.asarray(n) - v["y0"]
        return cr * de - sr * dn, sr * de + cr * dn

    def project(self, lon, lat, h):
        """Ground (deg, deg, m above the ellipsoid) -> ``(col, row)`` by Eq. 3.2-3.5."""
        self.check_inputs(lon, lat, h, what="ground coordinates")
        lon, lat, h = np.broadcast_arrays(*(np.asarray(a, float) for a in (lon, lat, h)))
        v = self._c
        x, y = self._local(lon, lat, h)
        X = (x - v["a"] * y) * (1.0 + h / self.N0) + v["b"] * y ** 2 + v["c"] * x * y
        H = h - X ** 2 / (2.0 * self.N0)
        ys = y / _Y_SCALE
        dT = v["dT_1"] * ys + v["dT_2"] * ys ** 2
        dR = v["dR_1"] * ys + v["dR_2"] * ys ** 2
        with np.errstate(divide="ignore", invalid="ignore"):
            p = (v["tau"] * H + self.H0 * dT - y * (1.0 + v["dgamma"] * X)) / v["P"]
            k = 1.0 / np.cos(self.chi)
            q = (v["Q"] * dR - X - v["theta"] * H * k) / (self.alpha * (v["Q"] + v["theta"] * X - H * k))
        return self.c_c + q, self.r_c + p

    def localize(self, col, row, h):
        """Image -> ground at height ``h`` by Newton iteration on :meth:`project`."""
        self.check_inputs(col, row, h, what="image coordinates or heights")
        return invert_projection(self, col, row, h, lon0=self.lon0, lat0=self.lat0)

    # ------------------------------------------------------------------ initial values
    @classmethod
    def from_model(cls, reference, *, name=None):
        """Initial values from a metadata model of the image (pushbroom, ASTER, RPC): the
        scene geometry gives ``N0, H0, alpha, chi`` and first guesses; all 15 values are then
        fitted to the reference's virtual points (the fit's RMS, pixels, in
        :attr:`init_rms_px`)."""
        if isinstance(reference, cls):
            return reference                    # already this model (e.g. from a model set)
        w, hgt = reference.width, reference.height
        lon0, lat0 = reference.center_lonlat(0.0)
        c0, r0 = 0.5 * (w - 1), 0.5 * (hgt - 1)
        o, d = reference.rays(np.array([c0]), np.array([r0]))
        o, d = o[0], d[0]
        up = np.array(geodesy.enu_basis(lon0, lat0))[2]
        chi = float(np.arccos(np.clip(-d @ up, -1, 1)))
        if hasattr(reference, "ephemeris"):
            H0 = float(geodesy.ecef_to_geodetic(*o)[2])
        else:
            H0 = 705e3
        phi = np.radians(lat0)
        N0 = geodesy.A / np.sqrt(1.0 - geodesy.E2 * np.sin(phi) ** 2)

        def enu(c, r):
            lo, la = reference.localize(np.asarray(c, float), np.asarray(r, float), 0.0)
            e, n, _ = geodesy.ecef_to_enu(*geodesy.geodetic_to_ecef(lo, la, 0.0), lon0, lat0, 0.0)
            return np.array([float(e), float(n)])

        g0 = enu(c0, r0)
        g_row = (enu(c0, r0 + 100) - enu(c0, r0 - 100)) / 200.0
        g_col = (enu(c0 + 100, r0) - enu(c0 - 100, r0)) / 200.0
        rot = float(np.arctan2(g_row[0], g_row[1]))
        xdir = np.array([np.cos(rot), -np.sin(rot)])
        Q = H0 / np.cos(chi)
        alpha = -float(g_col @ xdir) / Q
        values = dict(P=-float(np.linalg.norm(g_row)), Q=Q, x0=float(g0[0]), y0=float(g0[1]), rot=rot)
        lo, hi = reference.height_bounds()
        model = cls(width=w, height=hgt, lon0=lon0, lat0=lat0, N0=N0, H0=H0, alpha=alpha, chi=chi,
                    values=values, name=name, height_range=(lo, hi))
        pts = virtual_points(reference)
        model, _ = fit_to_points(model, list(ADJUSTED), *pts, what=model.name)
        model, rms = fit_to_points(model, list(ADJUSTED + SECOND_ORDER), *pts, what=model.name)
        model.init_rms_px = rms
        return model

    def to_dict(self) -> dict:
        """Plain description, for :mod:`stereodem.sensor.io.sidecar`."""
        return {"width": self.width, "height": self.height, "lon0": self.lon0, "lat0": self.lat0,
                "N0": self.N0, "H0": self.H0, "alpha": self.alpha, "chi": self.chi,
                "values": dict(self._c), "name": self.name, "height_range": list(self._hr)}

    @classmethod
    def from_dict(cls, d: dict) -> "ToutinModel":
        """Inverse of :meth:`to_dict`."""
        return cls(width=d["width"], height=d["height"], lon0=d["lon0"], lat0=d["lat0"], N0=d["N0"],
                   H0=d["H0"], alpha=d["alpha"], chi=d["chi"], values=d["values"], name=d.get("name"),
                   height_range=tuple(d.get("height_range", (-500.0, 9000.0))))
