"""A Toutin-type rigorous orbital model, written from Toutin's published equations (CCRS 3D
model; Toutin 1995, 2003b; as transcribed in Topan 2009 Eq. 3.2-3.5), not from PCI's code.

Ground coordinates: ``(x, y)`` in a local frame on the ellipsoid tangent plane at the image
centre, ``x`` along the scan and ``y`` across it (the map "rotation-translation" of Toutin's
last step: ``x0, y0, rot``, three of the eight unknowns), ``h`` the ellipsoidal height (m).
With ``L = 100 km`` the unit of the second-order terms::

    X = (x - a (y - tau h))(1 + h / N0) + L (b (y/L)^2 + c (x/L)(y/L))       (3.4*)
    H = h - X^2 / (2 N0)                                                    (3.5)
    P p + y (1 + dgamma X / L) - tau H - H0 dT* = 0       -> line   p = row - r_c     (3.2)
    X + theta H / cos(chi) + alpha q (Q + theta X - H / cos(chi)) - Q dR = 0
                                                          -> column q = col - c_c     (3.3)

``x, y`` are map coordinates: those of the point's foot on the ellipsoid (``h = 0``), as in
Toutin's cartographic frame; taking them at the point's own height instead puts a
``(1 + h/N0)`` scale on ``y`` that the equations do not model (0.3 px per 3 km of height at
the ends of an ASTER image).

Symbols: ``N0`` the ellipsoid normal at the image centre, ``H0`` the satellite height there,
``alpha`` the IFOV (signed with the column direction), ``P, Q`` scale factors in ``y`` and
``x`` (m per line; m, about the slant range), ``tau, theta`` the levelling angles in ``y`` and
``x``, ``a`` the Earth-rotation skew, ``b, c, dgamma`` second-order terms, ``dT*`` (pitch +
yaw) and ``dR`` (roll) the non-linear attitude variations, here the quadratic and cubic terms
of a polynomial in ``y / L`` (``dT_2, dT_3, dR_2, dR_3``). Their constant and linear parts are
not "non-linear variations" and are the same unknowns as ``y0, P`` (``dT*``) and ``x0, a``
(``dR``): with them free the normal matrix is singular, which is why an earlier version with
``dT_1, dR_1`` refused ``toutin-full``.

The oblique (along-track tilted) view
-------------------------------------
Topan leaves ``chi`` undefined. In the scan plane — the plane of the satellite and the detector
line, tilted by ``chi`` from the vertical about the scan direction — a point of height ``H``
lies ``H / cos(chi)`` closer to the satellite than its foot, and the in-plane geometry is
exactly Eq. 3.3 with ``Q = S (1 + theta^2)``, ``theta = tan(across-track tilt)``, ``S`` the
in-plane distance. So ``chi`` is the *along-track tilt of the scan plane at the image centre*
(:func:`scan_plane_tilt`: 0.2 degrees for ASTER 3N, 31.1 for 3B — its 27.6 at the satellite
plus the Earth's curvature over the 370 km to the image centre), not the total off-nadir angle
of the centre detector (9.6 and 32.3 degrees), which puts the across-track tilt into the relief
term a second time. The same plane makes a point of height ``h`` seen ``tau h`` metres of
ground track (``tau = tan chi`` after the fit) earlier or later than its foot; the Earth has
turned meanwhile, so the skew acts on the acquisition line ``y - tau h``, not on ``y`` (Eq.
3.4 as printed has ``x - a y``: right for a nadir view; on the 3B view the difference is
``a tau h`` ≈ 0.05 x 0.6 x 3000 m ≈ 90 m across the track at 3 km of relief, and the equations
as printed miss the metadata geometry by 0.43 px RMS; with both corrections 0.02 px).
:meth:`ToutinModel.from_model` starts ``chi`` at the scan plane's tilt and refines it with the
metadata fit (3B: 31.1 -> 31.1 degrees; 3N, pointed 9.6 degrees across the track: 0.2 -> 6.8,
taking up a small across-track relief term, 0.05 -> 0.04 px); it is then held.

Unknowns adjusted with GCPs (set ``toutin``, 8 = Toutin's 5 + 3, Zoej 1997): ``P, Q, tau,
theta, a, x0, y0, rot``. The levelling angles ``tau, theta`` are the tangents of the scan
plane's tilts, which the attitude of the metadata gives to about an arcminute: they are
weighted observations about the metadata's values (:data:`LEVELLING_SIGMA`). Unweighted, 10 GCPs
over a few km of relief fix them poorly (``tau`` trades the row against the height): median ICP
RMSE 1.06 / 1.14 x the rigorous model's on ASTER 3N / 3B, up to 1.6 x on single splits, and
condition numbers ~400; weighted, 0.98 / 1.01 x and condition numbers ~10, and from 6 GCPs on
better than the rigorous model's six unweighted attitude unknowns. ``b, c, dgamma`` and the attitude
variations are computed from the orbit in Toutin's model; here they are taken from the metadata
model of the image by fitting the equations to its virtual points (:meth:`ToutinModel.from_model`)
and then held fixed. Set ``toutin-full`` frees them too (15), as weighted observations about those
values (:data:`SECOND_ORDER_SIGMA`: each about 1-2 m at the ends of the scene).
"""

from __future__ import annotations

import numpy as np

from stereodem.core import geodesy
from stereodem.core.errors import SensorModelError
from stereodem.sensor.models.base import SensorModel
from stereodem.sensor.models.orbital._common import (
    CoefficientModel,
    fit_to_reference,
    invert_projection,
)

ADJUSTED = ("P", "Q", "tau", "theta", "a", "x0", "y0", "rot")
SECOND_ORDER = ("b", "c", "dgamma", "dT_2", "dT_3", "dR_2", "dR_3")
_Y_SCALE = 1e5  # m, the unit L of x and y in the second-order terms
#: A-priori sigma of the levelling angles ``tau, theta`` (tangents of the scan plane's tilts)
#: about their metadata values: 3e-4 (about 1 arcmin of attitude knowledge; ``d tan`` of a
#: 31 degree tilt is 1.4 x the angle error), the order of the pointing accuracy of ASTER/SPOT.
LEVELLING_SIGMA = 3e-4
#: A-priori sigmas of the second-order terms about their metadata values (``toutin-full``):
#: each moves the image by about 2 m at the ends of the scene (|y| ~ 35 km, H0 ~ 7e5 m).
SECOND_ORDER_SIGMA = {
    "b": 2e-4,
    "c": 2e-4,
    "dgamma": 2e-4,
    "dT_2": 2e-5,
    "dT_3": 5e-5,
    "dR_2": 2e-5,
    "dR_3": 5e-5,
}


def scan_plane_tilt(boresight, line_direction, up) -> float:
    """Along-track tilt ``chi`` (rad, >= 0) of the scan plane: the angle between the plane
    spanned by the centre detector's ray ``boresight`` and the detector line's direction
    ``line_direction`` (ECEF vectors) and the vertical ``up`` (unit ECEF vector) at the image
    centre. Zero for a nadir or a purely across-track pointed view, about 31 degrees for the
    ASTER 3B view (its 27.6 degrees at the satellite plus the Earth's curvature over the
    ~370 km between the satellite's nadir and the image centre)."""
    n = np.cross(np.asarray(boresight, float), np.asarray(line_direction, float))
    n /= np.linalg.norm(n)
    return float(np.arcsin(min(1.0, abs(float(n @ np.asarray(up, float))))))


class ToutinModel(CoefficientModel, SensorModel):
    """Toutin-type model (module docstring); build it with :meth:`from_model`."""

    ADJUST_SETS = {"toutin": list(ADJUSTED), "toutin-full": list(ADJUSTED + SECOND_ORDER)}
    #: Weighted parameters of each set: name -> a-priori sigma about the initial value.
    PRIORS = {
        "toutin": {"tau": LEVELLING_SIGMA, "theta": LEVELLING_SIGMA},
        "toutin-full": {"tau": LEVELLING_SIGMA, "theta": LEVELLING_SIGMA, **SECOND_ORDER_SIGMA},
    }
    PARAMETER_STEPS = {
        "P": 1e-6,
        "Q": 1.0,
        "tau": 1e-7,
        "theta": 1e-7,
        "a": 1e-7,
        "x0": 0.1,
        "y0": 0.1,
        "rot": 1e-7,
        "b": 1e-6,
        "c": 1e-6,
        "dgamma": 1e-6,
        "dT_2": 1e-8,
        "dT_3": 1e-8,
        "dR_2": 1e-8,
        "dR_3": 1e-8,
        "chi": 1e-4,
    }
    MODEL_TYPE = "toutin"
    DICT_FIELDS = ("lon0", "lat0", "N0", "H0", "alpha", "chi")

    def __init__(
        self,
        *,
        width,
        height,
        lon0,
        lat0,
        N0,
        H0,
        alpha,
        chi,
        values: dict,
        name=None,
        height_range=(-500.0, 9000.0),
    ):
        self.width, self.height = int(width), int(height)
        self.lon0, self.lat0 = float(lon0), float(lat0)
        self.N0, self.H0, self.alpha = float(N0), float(H0), float(alpha)
        if not all(np.isfinite(v) for v in (self.N0, self.H0, self.alpha, chi)) or self.alpha == 0:
            raise SensorModelError(
                "Toutin model: N0, H0, alpha, chi must be finite (alpha non-zero)"
            )
        self.name = name or "toutin"
        self._c = dict.fromkeys(ADJUSTED + SECOND_ORDER, 0.0)
        self._c["chi"] = float(chi)
        self._set({k: v for k, v in values.items() if k != "chi"})
        self._hr = tuple(float(v) for v in height_range)
        self.r_c, self.c_c = 0.5 * (self.height - 1), 0.5 * (self.width - 1)

    # ------------------------------------------------------------------ parameters
    def parameters(self) -> dict:
        """The adjustable parameters (``chi`` is a constant of the geometry, see
        :meth:`from_model`)."""
        return {k: v for k, v in self._c.items() if k != "chi"}

    def coefficients(self) -> dict:
        """Every value of the equations, ``chi`` included."""
        return dict(self._c)

    @property
    def chi(self) -> float:
        """Along-track tilt of the scan plane (rad) in the relief terms of Eq. 3.3."""
        return self._c["chi"]

    # ------------------------------------------------------------------ equations
    def _local(self, lon, lat, h):
        e, n, _ = geodesy.ecef_to_enu(
            *geodesy.geodetic_to_ecef(lon, lat, 0.0 * h), self.lon0, self.lat0, 0.0
        )
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
        xs, ys = x / _Y_SCALE, y / _Y_SCALE
        # Earth-rotation skew at the acquisition time of the point: the line that sees it is
        # ``y - tau h`` (ground metres) from the centre line, not ``y`` (oblique views)
        X = (x - v["a"] * (y - v["tau"] * h)) * (1.0 + h / self.N0) + _Y_SCALE * (
            v["b"] * ys**2 + v["c"] * xs * ys
        )
        H = h - X**2 / (2.0 * self.N0)
        dT = ys**2 * (v["dT_2"] + v["dT_3"] * ys)
        dR = ys**2 * (v["dR_2"] + v["dR_3"] * ys)
        with np.errstate(divide="ignore", invalid="ignore"):
            p = (v["tau"] * H + self.H0 * dT - y * (1.0 + v["dgamma"] * X / _Y_SCALE)) / v["P"]
            k = 1.0 / np.cos(v["chi"])
            q = (v["Q"] * dR - X - v["theta"] * H * k) / (
                self.alpha * (v["Q"] + v["theta"] * X - H * k)
            )
        return self.c_c + q, self.r_c + p

    def localize(self, col, row, h):
        """Image -> ground at height ``h`` by Newton iteration on :meth:`project`."""
        self.check_inputs(col, row, h, what="image coordinates or heights")
        return invert_projection(self, col, row, h, lon0=self.lon0, lat0=self.lat0)

    # ------------------------------------------------------------------ initial values
    @classmethod
    def from_model(cls, reference, *, name=None):
        """Initial values from a metadata model of the image (pushbroom, ASTER, RPC): the
        scene geometry gives ``N0, H0, alpha``, ``chi`` (:func:`scan_plane_tilt`) and first
        guesses; the 15 values and ``chi`` are then fitted to the reference's virtual points
        at several heights (the fit's RMS, pixels, in :attr:`init_rms_px`). ``chi`` stays a
        constant of the geometry afterwards (not a GCP unknown)."""
        if isinstance(reference, cls):
            return reference  # already this model (e.g. from a model set)
        w, hgt = reference.width, reference.height
        lon0, lat0 = reference.center_lonlat(0.0)
        c0, r0 = 0.5 * (w - 1), 0.5 * (hgt - 1)
        o, d = reference.rays(np.array([c0, c0 + 100.0, c0 - 100.0]), np.full(3, r0))
        up = np.array(geodesy.enu_basis(lon0, lat0))[2]
        chi = scan_plane_tilt(d[0], d[1] - d[2], up)
        off_nadir = float(np.arccos(np.clip(-d[0] @ up, -1.0, 1.0)))
        o = o[0]
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
        Q = H0 / np.cos(off_nadir)  # about the slant range of the centre detector
        alpha = -float(g_col @ xdir) / Q
        values = dict(
            P=-float(np.linalg.norm(g_row)), Q=Q, x0=float(g0[0]), y0=float(g0[1]), rot=rot
        )
        model = cls(
            width=w,
            height=hgt,
            lon0=lon0,
            lat0=lat0,
            N0=N0,
            H0=H0,
            alpha=alpha,
            chi=chi,
            values=values,
            name=name,
            height_range=reference.height_bounds(),
        )
        return fit_to_reference(model, reference, list(ADJUSTED), [*ADJUSTED, *SECOND_ORDER, "chi"])

    def _dict_entries(self) -> dict:
        return {"values": self.parameters()}

    @classmethod
    def _entries_from_dict(cls, d: dict) -> dict:
        return {"values": d["values"]}
