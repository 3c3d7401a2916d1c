"""Topan's (2009) line-of-sight model of a linear-array image with second-order exterior
orientation polynomials (Eq. 3.60-3.71), its 19 EOP parameter sets (Table 4.2) and his
pre-adjustment types 1 and 2 (§3.3.3.1).

Model (SPOT Geometry Handbook frames, as in the thesis)
-------------------------------------------------------
For line ``row`` (normalised ``tau`` in [-1, 1], :func:`._common.line_variable`; the thesis
uses the raw line ``x_i``, centring and scaling only conditions the normal equations) the nine
exterior-orientation series are quadratics (Eq. 3.71)::

    X_S = X_0 + X_1 tau + X_2 tau^2,  ... Y_S, Z_S (ECEF, m), V_X, V_Y, V_Z (ECEF, m/s),
    a_r, a_p, a_y (roll, pitch, yaw, rad)                       -> 27 coefficients

* orbital frame (Eq. 3.63, as *columns*): ``Z = P/|P|``, ``X = V x Z / |.|``, ``Y = Z x X``;
* attitude (payload -> orbital): ``R_PO = Rx(-a_p) Ry(-a_r) Rz(a_y)`` (active rotations; roll
  and pitch negated as SPOT Image prescribes, the OSSIM / NASA ASP reading; the thesis's own
  Eq. 3.61/3.62 disagree with each other, see the notes §3.5);
* look direction of detector ``col`` in the payload frame:
  ``u1 = [-tan psi_y, tan psi_x, s]`` with ``s = -1`` (SPOT Handbook, OSSIM, ASP, Jung et al.
  Eq. 3.41). Topan prints ``s = +1`` (Eq. 3.60, 3.67): the rays then point away from the
  Earth and a stereo intersection lands about 1.9e6 m above the terrain, his Table 4.3
  column L. ``los_sign=+1`` reproduces that (:meth:`TopanLOSModel.with_los_sign`).
* look angles ``psi_x`` (along track), ``psi_y`` (across track) per detector, linearly
  interpolated in the column, plus a correction quadratic in the normalised column
  ``nu = (col - c_c) / c_c``: ``dpsi = psi_*_0 + psi_*_1 nu + psi_*_2 nu^2`` — the
  look-angle pre-adjustment's unknowns (see below).

The condition equations (3.70) are the ratios ``f1/f3 = -tan psi_y``, ``f2/f3 = tan psi_x``
of ``R^T (P - P_S)``; :meth:`TopanLOSModel.project` solves them for (col, row) by a
secant iteration on the line.

Parameter sets
--------------
:data:`EOP_SETS` maps the 19 set names of Table 4.2 (also ``"1"`` ... ``"19"``) to coefficient
names; ``"L"`` is the six look-angle corrections. The velocity enters only through the
direction of ``V x Z``: of the three coefficients of one order only the one that turns
``V`` about ``Z`` changes the image, so sets 5, 6 (partly), 13, 14, 17-19 are singular or
near-singular whatever the GCPs — the instability Topan reports for them.

Pre-adjustment
--------------
Type 1: look-angle corrections only (set ``L``) with the EOPs held; type 2: type 1, then the
chosen EOP set with the look angles held, at most three times (Topan §3.3.3.1). Topan solves
type 1 per point (one pair of look angles per GCP, a diagonal system) and then fits a
quadratic to them to reach the ICPs; here the quadratic is the unknown directly, which is the
same model for the ICPs and gives the GCPs a real redundancy.
:func:`preadjust` takes the adjustment engine as an argument. One image is adjusted with
:func:`stereodem.sensor.estimation.adjust.adjust_model`, a pair (GCPs, tie points, independent
check points) with :func:`stereodem.sensor.estimation.adjust.bundle_adjust` (model sets
``eop-poly2``, ``eop-<set>`` or lists of coefficient names; ``tests/sensor/test_orbital_pair.py``).

Models left out of Topan's survey (package docstring, :mod:`stereodem.sensor.models.orbital`).
"""

from __future__ import annotations

import copy

import numpy as np
from scipy.spatial.transform import Rotation

from stereodem.core import geodesy
from stereodem.core.errors import InputError, SensorModelError
from stereodem.sensor.models.base import SensorModel, localize_on_rays
from stereodem.sensor.models.orbital._common import (
    CoefficientModel,
    line_variable,
    quadratic,
    secant_rows,
)

SERIES = ("X", "Y", "Z", "VX", "VY", "VZ", "roll", "pitch", "yaw")
EOP = tuple(f"{s}_{k}" for s in SERIES for k in range(3))
LOOK = tuple(f"psi_{a}_{k}" for a in ("x", "y") for k in range(3))


def _group(series, orders=(0, 1, 2)):
    return [f"{s}_{k}" for s in series for k in orders]


_P, _V, _A = ("X", "Y", "Z"), ("VX", "VY", "VZ"), ("roll", "pitch", "yaw")

#: Topan (2009) Table 4.2: the 19 EOP sets (names as printed; ``"1"``-``"19"`` as aliases),
#: plus ``"L"``: the look-angle corrections of the type-1 pre-adjustment.
EOP_SETS = {
    "P_S": _group(_P),
    "P_S0": _group(_P, (0,)),
    "P_S1": _group(_P, (1,)),
    "P_S2": _group(_P, (2,)),
    "V_S": _group(_V),
    "V_S0": _group(_V, (0,)),
    "V_S1": _group(_V, (1,)),
    "V_S2": _group(_V, (2,)),
    "A": _group(_A),
    "A_0": _group(_A, (0,)),
    "A_1": _group(_A, (1,)),
    "A_2": _group(_A, (2,)),
    "P_S V_S": _group(_P) + _group(_V),
    "(P_S V_S)_0": _group(_P, (0,)) + _group(_V, (0,)),
    "P_S A": _group(_P) + _group(_A),
    "(P_S A)_0": _group(_P, (0,)) + _group(_A, (0,)),
    "V_S A": _group(_V) + _group(_A),
    "(V_S A)_0": _group(_V, (0,)) + _group(_A, (0,)),
    "(P_S V_S A)_0": _group(_P, (0,)) + _group(_V, (0,)) + _group(_A, (0,)),
}
for _k, _name in enumerate(list(EOP_SETS), start=1):
    EOP_SETS[str(_k)] = EOP_SETS[_name]
EOP_SETS["L"] = list(LOOK)
#: Set names in Table 4.2 order.
SET_ORDER = tuple(list(EOP_SETS)[:19])


def eop_set(name) -> list[str]:
    """Coefficient names of a Topan parameter set (name of Table 4.2, its number, or ``L``)."""
    key = str(name).strip()
    if key not in EOP_SETS:
        raise InputError(
            f"unknown Topan EOP set {name!r}; choose one of {', '.join(SET_ORDER)}, 1-19 or L"
        )
    return list(EOP_SETS[key])


def payload_to_orbital(roll, pitch, yaw):
    """``R_PO = Rx(-pitch) Ry(-roll) Rz(yaw)`` (active rotations, radians), shape (..., 3, 3)."""
    roll, pitch, yaw = np.broadcast_arrays(*(np.asarray(a, float) for a in (roll, pitch, yaw)))
    e = np.stack([-pitch.ravel(), -roll.ravel(), yaw.ravel()], -1)
    return Rotation.from_euler("XYZ", e).as_matrix().reshape(roll.shape + (3, 3))


def orbital_to_ecef(p, v):
    """SPOT local orbital frame (Eq. 3.63) as columns: ``Z = P/|P|, X = V x Z, Y = Z x X``."""
    z = p / np.linalg.norm(p, axis=-1, keepdims=True)
    x = np.cross(v, z)
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    y = np.cross(z, x)
    return np.stack([x, y, z], -1)


class TopanLOSModel(CoefficientModel, SensorModel):
    """Line-of-sight model with quadratic EOP polynomials (module docstring).

    Parameters
    ----------
    width, height : int
        Image size.
    coefficients : dict
        The 27 EOP coefficients (:data:`EOP`) and optionally the look-angle corrections.
    psi_x, psi_y : array_like (K,)
        Look angles (rad) of the detectors at columns ``cols`` (default ``0..K-1``).
    los_sign : {-1, +1}
        ``z`` of the payload look vector: -1 (correct) or +1 (Topan's print).
    """

    PARAMETER_STEPS = {
        **{n: (1.0 if n[0] in "XYZ" else 1e-3 if n[0] == "V" else 1e-7) for n in EOP},
        **{n: 1e-7 for n in LOOK},
    }
    MODEL_TYPE = "topan-los"

    def __init__(
        self,
        *,
        width: int,
        height: int,
        coefficients: dict,
        psi_x,
        psi_y,
        cols=None,
        los_sign: int = -1,
        name: str | None = None,
        height_range=(-500.0, 9000.0),
    ):
        self.width, self.height = int(width), int(height)
        if self.width < 2 or self.height < 2:
            raise SensorModelError(
                f"Topan LOS model: image must be at least 2 x 2, got {width} x {height}"
            )
        px, py = np.asarray(psi_x, float), np.asarray(psi_y, float)
        c = np.arange(py.size, dtype=float) if cols is None else np.asarray(cols, float)
        if (
            px.shape != py.shape
            or c.shape != py.shape
            or py.size < 2
            or not np.all(np.isfinite(py))
        ):
            raise SensorModelError(
                "Topan LOS model: look-angle tables must be finite 1-D arrays of one length"
            )
        d = np.diff(py)
        if not (np.all(d > 0) or np.all(d < 0)):
            raise SensorModelError(
                "Topan LOS model: psi_y must be strictly monotonic in the column"
            )
        if los_sign not in (-1, 1):
            raise SensorModelError(f"Topan LOS model: los_sign must be -1 or +1, got {los_sign}")
        self._cols, self._px, self._py = c, px, py
        self._order = np.argsort(py)
        self.los_sign = int(los_sign)
        self.name = name or "topan-los"
        self._c = dict.fromkeys(EOP + LOOK, 0.0)
        self._set(coefficients)
        self._hr = tuple(float(v) for v in height_range)

    # ------------------------------------------------------------------ parameters
    def parameters(self) -> dict:
        return dict(self._c)

    def with_los_sign(self, sign: int) -> TopanLOSModel:
        """The same model with the ``z`` of the look vector set to ``sign`` (+1: Topan's print)."""
        new = copy.copy(self)
        if sign not in (-1, 1):
            raise SensorModelError(f"Topan LOS model: los_sign must be -1 or +1, got {sign}")
        new.los_sign = int(sign)
        return new

    def _parameter_listing(self):
        return f"EOP coefficients {EOP[0]}..{EOP[-1]}, look-angle corrections {', '.join(LOOK)}"

    # ------------------------------------------------------------------ geometry
    def _series(self, row):
        tau = line_variable(row, self.height)
        c = self._c
        return {s: quadratic(c[f"{s}_0"], c[f"{s}_1"], c[f"{s}_2"], tau) for s in SERIES}

    def _pose(self, row):
        """Projection centre (ECEF, m) and payload -> ECEF rotation at image rows."""
        s = self._series(row)
        p = np.stack([s["X"], s["Y"], s["Z"]], -1)
        v = np.stack([s["VX"], s["VY"], s["VZ"]], -1)
        return p, orbital_to_ecef(p, v) @ payload_to_orbital(s["roll"], s["pitch"], s["yaw"])

    def _nu(self, col):
        half = 0.5 * (self.width - 1)
        return (np.asarray(col, float) - half) / half

    def look_angles(self, col):
        """``(psi_x, psi_y)`` (rad) of (fractional) columns, corrections included."""
        c, nu = self._c, self._nu(col)
        px = np.interp(col, self._cols, self._px) + quadratic(
            c["psi_x_0"], c["psi_x_1"], c["psi_x_2"], nu
        )
        py = np.interp(col, self._cols, self._py) + quadratic(
            c["psi_y_0"], c["psi_y_1"], c["psi_y_2"], nu
        )
        return px, py

    def _column(self, psi_y):
        """Invert ``psi_y(col)`` (table plus correction) by fixed-point iteration."""
        c = self._c
        col = self._extrap(psi_y)
        for _ in range(8):
            corr = quadratic(c["psi_y_0"], c["psi_y_1"], c["psi_y_2"], self._nu(col))
            col = self._extrap(psi_y - corr)
        return col

    def _extrap(self, psi):
        """Column of table look angle ``psi``, linear extrapolation beyond the table."""
        o = self._order
        py, cc = self._py[o], self._cols[o]
        col = np.interp(psi, py, cc)
        lo = psi < py[0]
        hi = psi > py[-1]
        col = np.where(lo, cc[0] + (psi - py[0]) * (cc[1] - cc[0]) / (py[1] - py[0]), col)
        return np.where(hi, cc[-1] + (psi - py[-1]) * (cc[-1] - cc[-2]) / (py[-1] - py[-2]), col)

    def rays(self, col, row):
        """ECEF lines of sight ``(projection centre, unit direction)`` of pixels."""
        self.check_inputs(col, row, what="image coordinates")
        col, row = np.broadcast_arrays(np.asarray(col, float), np.asarray(row, float))
        p, rot = self._pose(row)
        px, py = self.look_angles(col)
        u = np.stack([-np.tan(py), np.tan(px), np.full(px.shape, float(self.los_sign))], -1)
        d = np.einsum("...ij,...j->...i", rot, u)
        return p, d / np.linalg.norm(d, axis=-1, keepdims=True)

    def localize(self, col, row, h):
        """Image ``(col, row)`` at ellipsoidal height ``h`` -> ``(lon, lat)``; NaN where the ray
        misses (always with ``los_sign=+1``: the rays point away from the Earth)."""
        return localize_on_rays(self, col, row, h)

    def _payload(self, g, row):
        p, rot = self._pose(row)
        return np.einsum("...ji,...j->...i", rot, g - p)

    def project(self, lon, lat, h, *, max_iterations: int = 30):
        """Ground -> ``(col, row)`` solving Eq. 3.70 (secant iteration on the line)."""
        self.check_inputs(lon, lat, h, what="ground coordinates")
        lon, lat, h = np.broadcast_arrays(*(np.asarray(a, float) for a in (lon, lat, h)))
        shape = lon.shape
        g = np.stack(geodesy.geodetic_to_ecef(lon.ravel(), lat.ravel(), h.ravel()), -1)
        s = float(self.los_sign)

        def f(row):
            u = self._payload(g, row)
            k = u[:, 2] / s
            with np.errstate(divide="ignore", invalid="ignore"):
                tx, ty = u[:, 1] / k, -u[:, 0] / k
            col = self._column(np.arctan(ty))
            px, _ = self.look_angles(col)
            return np.arctan(tx) - px, col, k

        r1, (_, col, k) = secant_rows(f, g.shape[0], self.height, max_iterations=max_iterations)
        bad = ~(k > 0) | ~np.isfinite(col)
        return (np.where(bad, np.nan, col).reshape(shape), np.where(bad, np.nan, r1).reshape(shape))

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_series(
        cls,
        *,
        width,
        height,
        row_times,
        position,
        velocity,
        angles,
        psi_x,
        psi_y,
        cols=None,
        samples: int = 41,
        los_sign: int = -1,
        name=None,
        height_range=(-500.0, 9000.0),
    ):
        """Build from metadata series, as GeoSpot-1.0 does (Topan Fig. 4.4): the ephemeris and
        attitude interpolated at ``samples`` lines and fitted with quadratics in ``tau``.

        ``row_times(row) -> t``; ``position(t)``, ``velocity(t)`` -> (n, 3) ECEF m, m/s;
        ``angles(t)`` -> (n, 3) roll, pitch, yaw (rad, :func:`payload_to_orbital`).
        """
        rows = np.linspace(0.0, height - 1.0, samples)
        t = row_times(rows)
        tau = line_variable(rows, height)
        data = np.concatenate(
            [
                np.asarray(position(t), float),
                np.asarray(velocity(t), float),
                np.asarray(angles(t), float),
            ],
            -1,
        )
        coef = {}
        for j, sname in enumerate(SERIES):
            c2, c1, c0 = np.polyfit(tau, data[:, j], 2)
            coef.update({f"{sname}_0": c0, f"{sname}_1": c1, f"{sname}_2": c2})
        return cls(
            width=width,
            height=height,
            coefficients=coef,
            psi_x=psi_x,
            psi_y=psi_y,
            cols=cols,
            los_sign=los_sign,
            name=name,
            height_range=height_range,
        )

    @classmethod
    def from_model(cls, reference, *, samples: int = 41, name=None, attitude_from_reference=True):
        """Initial values from a physical model of the image with exact rays (a
        :class:`~stereodem.sensor.models.pushbroom.PushbroomModel`, ASTER or DIMAP model).

        The projection centres and velocities come from the reference's ephemeris; the look
        angles of every detector from its rays at the centre line expressed in the orbital
        frame there; the attitude series (the reference's pointing relative to that at the
        centre line, in the SPOT angles of :func:`payload_to_orbital`) from its rays at the
        other lines.
        """
        if isinstance(reference, cls):
            return reference  # already this model (e.g. from a model set)
        if not hasattr(reference, "ephemeris") or not hasattr(reference, "line_time"):
            raise SensorModelError(
                f"{type(reference).__name__}: the Topan LOS model needs a physical "
                "model with an ephemeris (pushbroom, ASTER or DIMAP)"
            )
        w, hgt = reference.width, reference.height
        rc = 0.5 * (hgt - 1)
        eph = reference.ephemeris

        def frame(row):
            """Reference instrument -> SPOT orbital frame rotations at rows."""
            t = reference.line_time(row)
            p, v = eph.state(t)
            return np.swapaxes(orbital_to_ecef(p, v), -1, -2) @ reference._pose(row)[1]

        cols = np.arange(w, dtype=float)
        _, d = reference.rays(cols, np.full(w, rc))
        t_c = reference.line_time(np.array(rc))
        p_c, v_c = eph.state(t_c)
        m_c = orbital_to_ecef(p_c, v_c)
        u = d @ m_c  # rows: d in orbital axes
        k = u[:, 2] / -1.0
        psi_x, psi_y = np.arctan(u[:, 1] / k), np.arctan(-u[:, 0] / k)
        f_c = frame(np.array(rc))

        def angles(t):
            rows = (t - reference.line_time(np.array(0.0))) / reference.line_period
            if not attitude_from_reference:
                return np.zeros(rows.shape + (3,))
            delta = frame(rows) @ f_c.T  # R_PO(t) with R_PO(t_c) = I
            e = Rotation.from_matrix(delta).as_euler("XYZ")  # (-pitch, -roll, yaw)
            return np.stack([-e[:, 1], -e[:, 0], e[:, 2]], -1)

        def pos(t):
            return eph.state(t)[0] + _position_offset(reference, t)

        lo, hi = reference.height_bounds()
        return cls.from_series(
            width=w,
            height=hgt,
            row_times=reference.line_time,
            position=pos,
            velocity=lambda t: eph.state(t)[1],
            angles=angles,
            psi_x=psi_x,
            psi_y=psi_y,
            samples=samples,
            name=name,
            height_range=(lo, hi),
        )

    def _dict_entries(self) -> dict:
        """The coefficients and look-angle tables (arrays)."""
        return {
            "coefficients": dict(self._c),
            "cols": self._cols,
            "psi_x": self._px,
            "psi_y": self._py,
            "los_sign": self.los_sign,
        }

    @classmethod
    def _entries_from_dict(cls, d: dict) -> dict:
        return dict(
            coefficients=d["coefficients"],
            psi_x=d["psi_x"],
            psi_y=d["psi_y"],
            cols=d.get("cols"),
            los_sign=int(d.get("los_sign", -1)),
        )


def _position_offset(reference, t):
    """The reference's own adjustable position offsets (pushbroom parameters), in ECEF."""
    c, _ = reference._pose(
        (np.asarray(t) - reference.line_time(np.array(0.0))) / reference.line_period
    )
    return c - reference.ephemeris.state(t)[0]


# ---------------------------------------------------------------------------- pre-adjustment


def preadjust(
    model: TopanLOSModel,
    points,
    *,
    eop_set_name=None,
    kind: int = 1,
    adjust=None,
    sigma_px: float = 1.0,
    iterations: int = 3,
):
    """Topan's pre-adjustment of one image with its GCPs.

    Parameters
    ----------
    model : TopanLOSModel
    points : stereodem.sensor.io.gcps.ControlPoints (or anything ``adjust`` accepts)
    eop_set_name : str, optional
        The EOP set of Table 4.2 adjusted in the type-2 step.
    kind : {1, 2}
        1: the look-angle corrections (set ``L``) only, EOPs held. 2: type 1, then the EOP set
        with the look angles held, repeated at most ``iterations`` times (Topan: 3) until the
        EOPs change by less than 1e-9 of their size.
    adjust : callable, optional
        ``adjust(model, points, names, sigma_px=...) -> result`` with ``result.model``; by
        default :func:`stereodem.sensor.estimation.adjust.adjust_model`.

    Returns
    -------
    list of the adjustment results (the last one's ``.model`` is the pre-adjusted model).
    """
    if kind not in (1, 2):
        raise InputError(f"Topan pre-adjustment type must be 1 or 2, got {kind}")
    if kind == 2 and eop_set_name is None:
        raise InputError("Topan type-2 pre-adjustment needs an EOP set")
    if adjust is None:
        from stereodem.sensor.estimation.adjust import adjust_model as adjust
    results = [adjust(model, points, list(LOOK), sigma_px=sigma_px)]
    if kind == 1:
        return results
    names = eop_set(eop_set_name)
    current = results[-1].model
    for _ in range(int(iterations)):
        res = adjust(current, points, names, sigma_px=sigma_px)
        results.append(res)
        before = np.array([current.parameters()[n] for n in names])
        after = np.array([res.model.parameters()[n] for n in names])
        current = res.model
        if np.all(np.abs(after - before) <= 1e-9 * np.maximum(1.0, np.abs(before))):
            break
    return results
