"""Linear-array (pushbroom) sensor model with ephemeris, attitude and detector look angles.

Frame chain (Topan 2009 Eq. 3.56 with look angles, Eq. 3.60-3.67; Bettemir 2006 §4.2;
ASTER notes §4.2-4.6):

* **instrument frame** — x along track (flight direction), y across track to the right of
  the flight direction, z along the boresight (down). Detector ``col`` looks along
  ``u = [tan psi_x(col), tan psi_y(col), 1] / |.|`` (``psi_x`` along-track, ``psi_y``
  cross-track look angle). This is the axis convention of ASTER's ``SightVector``.
* **body frame** — the instrument is mounted with a fixed tilt: ``u_B = T u``,
  ``T = body_to_orbital(roll=cross_track_tilt, pitch=along_track_tilt, yaw=0)``; a positive
  along-track tilt looks forward (ASTER 3B: -27.6 deg, backward), a positive cross-track tilt
  turns the view towards -y (left of the flight direction).
* **orbital frame** — body -> orbital by the interpolated attitude (roll, pitch, yaw,
  Bettemir Eq. 4.7) and the adjustable bias/drift angles.
* **ECEF** — orbital frame from position and velocity
  (:func:`stereodem.sensor.geo.rotations.orbital_frame`), built by default with the *inertial*
  velocity ``v + omega_E x r`` (ASTER notes §4.3).

Line ``row`` is acquired at ``t(row) = t0 + row * line_period`` (pixel centres at integers).
Ground -> image (:meth:`PushbroomModel.project`) is not in the seeds (Bettemir §3.3 of the
notes): here a vectorised secant iteration on the line finds the instant at which the ground
point lies on the detector array's scan surface, then the column is found by inverting the
monotonic cross-track look angle.
"""

from __future__ import annotations

import copy
import logging

import numpy as np
from numpy.polynomial import Polynomial
from scipy.interpolate import CubicSpline

from stereodem.core import geodesy
from stereodem.core.errors import ConvergenceError, SensorModelError
from stereodem.sensor.geo.rotations import body_to_orbital, orbital_frame
from stereodem.sensor.models.base import SensorModel, localize_on_rays
from stereodem.sensor.models.ephemeris import Attitude, CircularOrbit, Ephemeris
from stereodem.sensor.models.parameters import checked_parameters

log = logging.getLogger(__name__)

#: Tolerance of the line search of :meth:`PushbroomModel.project`, lines.
ROW_TOLERANCE = 1e-9


# ======================================================================= detector array


class DetectorArray:
    """Look directions of the detectors of a linear array in the instrument frame.

    Internally each detector is described by the two tangents ``tan psi_x`` (along track) and
    ``tan psi_y`` (across track) of its look direction as functions of the (fractional)
    column; ``tan psi_y`` must be strictly monotonic in the column. The tangents may also vary
    slowly with the image row (tables given per lattice row, blended linearly in row).

    Use the constructors :meth:`from_look_angles`, :meth:`from_sight_vectors` or
    :meth:`linear`.
    """

    def __init__(self, tan_x, tan_y, dtan_y, *, rows=None, col_range=None, spec=None):
        # tan_x, tan_y, dtan_y: callables (col, row) -> array, already vectorised
        self._tx, self._ty, self._dty = tan_x, tan_y, dtan_y
        self.rows = rows
        self.spec = spec or {}  #: constructor and arguments, for serialisation
        lo, hi = col_range if col_range is not None else (0.0, 1.0)
        c = np.linspace(lo, hi, 33)
        r = np.zeros_like(c)
        ty = np.asarray(self._ty(c, r), float)
        d = np.diff(ty)
        if not (np.all(d > 0) or np.all(d < 0)):
            raise SensorModelError(
                "detector array: the cross-track look angle must be strictly "
                "monotonic in the column"
            )
        # first guess of the inverse: a straight line through the table
        self._inv = np.polyfit(ty, c, 1)

    # ---------------------------------------------------------------- constructors
    @classmethod
    def from_look_angles(cls, psi_x, psi_y, *, cols=None, width: int | None = None):
        """Detectors from look angles (radians).

        Parameters
        ----------
        psi_x, psi_y : array_like or numpy.polynomial.Polynomial or float
            Along-track and cross-track look angles: a per-detector array (at ``cols``,
            default ``0..n-1``; interpolated with a cubic spline), a
            :class:`numpy.polynomial.Polynomial` in the column, or (``psi_x`` only) a constant.
        width : int, optional
            Number of detectors; required when ``psi_y`` is a polynomial (the cross-track
            angle is checked to be monotonic over ``0..width-1``).
        """

        def curve(psi, name):
            if isinstance(psi, Polynomial):
                d = psi.deriv()
                return (lambda c: np.tan(psi(c))), (lambda c: d(c) / np.cos(psi(c)) ** 2), None
            a = np.asarray(psi, dtype=np.float64)
            if a.ndim == 0:
                if name == "psi_y":
                    raise SensorModelError("detector array: psi_y must vary with the column")
                return (
                    (lambda c: np.full(np.shape(c), np.tan(float(a)))),
                    (lambda c: np.zeros(np.shape(c))),
                    None,
                )
            if a.ndim != 1 or a.size < 2 or not np.all(np.isfinite(a)):
                raise SensorModelError(
                    f"detector array: {name} must be a finite 1-D array of >= 2 values"
                )
            x = (
                np.arange(a.size, dtype=np.float64)
                if cols is None
                else np.asarray(cols, dtype=np.float64)
            )
            if x.shape != a.shape:
                raise SensorModelError(
                    f"detector array: {name} has {a.size} values for {x.size} columns"
                )

            s = CubicSpline(x, np.tan(a))
            ds = s.derivative()
            return s, ds, (float(x[0]), float(x[-1]))

        def describe(psi):
            if isinstance(psi, Polynomial):
                return {"polynomial": np.asarray(psi.convert().coef, float)}
            return np.asarray(psi, float)

        spec = {
            "kind": "look_angles",
            "psi_x": describe(psi_x),
            "psi_y": describe(psi_y),
            "cols": None if cols is None else np.asarray(cols, float),
            "width": width,
        }
        tx, _, rx = curve(psi_x, "psi_x")
        ty, dty, ry = curve(psi_y, "psi_y")
        if ry is None:
            if width is None or int(width) < 2:
                raise SensorModelError("detector array: give width= with a polynomial psi_y")
            ry = (0.0, float(int(width) - 1))
        return cls(
            lambda c, r: tx(c), lambda c, r: ty(c), lambda c, r: dty(c), col_range=ry, spec=spec
        )

    @classmethod
    def linear(cls, width: int, ifov: float, *, center: float | None = None, psi_x: float = 0.0):
        """Ideal line camera: ``tan psi_y = -(col - center) * ifov``, constant ``psi_x`` (rad).

        The column grows towards -y (to the left of the flight direction), which for a
        descending daytime pass makes the image north-up, east-right like ASTER.

        Parameters
        ----------
        width : int
            Number of detectors.
        ifov : float
            Angular step at the boresight, radians per pixel (pixel pitch / focal length).
        center : float, optional
            Column on the boresight (default the middle, ``(width - 1) / 2``).
        """
        cx = (width - 1) / 2.0 if center is None else float(center)
        tx, k = float(np.tan(psi_x)), float(ifov)
        if not (np.isfinite(k) and k > 0):
            raise SensorModelError(f"detector array: IFOV must be positive, got {ifov}")
        return cls(
            lambda c, r: np.full(np.shape(c), tx),
            lambda c, r: -(np.asarray(c, float) - cx) * k,
            lambda c, r: np.full(np.shape(c), -k),
            col_range=(0.0, float(max(width - 1, 1))),
            spec={
                "kind": "linear",
                "width": int(width),
                "ifov": k,
                "center": cx,
                "psi_x": float(psi_x),
            },
        )

    @classmethod
    def from_sight_vectors(cls, vectors, cols, *, rows=None):
        """Detectors from a table of sight vectors (instrument frame) at some columns.

        Parameters
        ----------
        vectors : array_like (K, 3) or (R, K, 3)
            Look directions (need not be unit) at the columns ``cols``; with three dimensions,
            one table per image row of ``rows`` (e.g. ASTER lattice rows).
        cols : array_like (K,)
            Increasing columns of the table (fractional pixel-centre coordinates).
        rows : array_like (R,), optional
            Rows of the tables when ``vectors`` is 3-D; tables are blended linearly in row
            (clamped at the ends).

        Notes
        -----
        The tangents ``x/z`` and ``y/z`` are interpolated with a cubic spline in the column,
        which reproduces the table exactly at its columns; directions are renormalised.
        """
        v = np.asarray(vectors, dtype=np.float64)
        x = np.asarray(cols, dtype=np.float64)
        if v.ndim == 2:
            v = v[None]
        if v.ndim != 3 or v.shape[-1] != 3 or v.shape[1] != x.size or x.size < 2:
            raise SensorModelError(
                f"detector array: sight vectors of shape {np.shape(vectors)} do not "
                f"match {x.size} columns"
            )
        if not np.all(np.isfinite(v)) or not np.all(np.isfinite(x)):
            raise SensorModelError("detector array: non-finite sight vectors or columns")
        if np.any(v[..., 2] <= 0):
            raise SensorModelError("detector array: sight vectors must point along +z (down)")
        if not np.all(np.diff(x) > 0):
            raise SensorModelError("detector array: sight-vector columns must increase")
        R = v.shape[0]
        spec = {
            "kind": "sight_vectors",
            "vectors": v.copy(),
            "cols": x.copy(),
            "rows": None if rows is None else np.asarray(rows, float),
        }
        if R > 1:
            r = np.asarray(rows, dtype=np.float64) if rows is not None else None
            if r is None or r.shape != (R,) or not np.all(np.diff(r) > 0):
                raise SensorModelError(
                    "detector array: row-dependent sight vectors need increasing rows"
                )
        else:
            r = None
        tx = CubicSpline(x, (v[..., 0] / v[..., 2]).T, axis=0)  # values (K, R)
        ty = CubicSpline(x, (v[..., 1] / v[..., 2]).T, axis=0)
        dty = ty.derivative()

        if R == 1:

            def ev(s):
                return lambda c, rr: s(c)[..., 0]

            return cls(ev(tx), ev(ty), ev(dty), col_range=(x[0], x[-1]), spec=spec)

        def blend(s):
            def f(c, rr):
                c = np.asarray(c, float)
                vals = s(c)  # c.shape + (R,)
                rr = np.broadcast_to(np.asarray(rr, float), c.shape)
                j = np.clip(np.searchsorted(r, rr, side="right") - 1, 0, R - 2)
                w = np.clip((rr - r[j]) / (r[j + 1] - r[j]), 0.0, 1.0)
                a = np.take_along_axis(vals, j[..., None], -1)[..., 0]
                b = np.take_along_axis(vals, (j + 1)[..., None], -1)[..., 0]
                return a + w * (b - a)

            return f

        return cls(blend(tx), blend(ty), blend(dty), rows=r, col_range=(x[0], x[-1]), spec=spec)

    @classmethod
    def from_spec(cls, spec: dict) -> DetectorArray:
        """Rebuild a detector array from its :attr:`spec` (e.g. read back from JSON)."""
        try:
            kind = spec["kind"]
            if kind == "linear":
                return cls.linear(
                    spec["width"], spec["ifov"], center=spec["center"], psi_x=spec["psi_x"]
                )
            if kind == "sight_vectors":
                return cls.from_sight_vectors(spec["vectors"], spec["cols"], rows=spec.get("rows"))
            if kind == "look_angles":

                def undescribe(p):
                    return (
                        Polynomial(p["polynomial"]) if isinstance(p, dict) else np.asarray(p, float)
                    )

                return cls.from_look_angles(
                    undescribe(spec["psi_x"]),
                    undescribe(spec["psi_y"]),
                    cols=spec.get("cols"),
                    width=spec.get("width"),
                )
        except (KeyError, TypeError, ValueError) as exc:
            raise SensorModelError(f"detector array: garbled description ({exc})") from None
        raise SensorModelError(f"detector array: unknown kind {spec.get('kind')!r}")

    # ---------------------------------------------------------------- evaluation
    def tangents(self, col, row=0.0):
        """``(tan psi_x, tan psi_y)`` of detectors at (fractional) ``col`` and image ``row``."""
        col = np.asarray(col, float)
        row = np.broadcast_to(np.asarray(row, float), col.shape)
        return np.asarray(self._tx(col, row), float), np.asarray(self._ty(col, row), float)

    def directions(self, col, row=0.0, *, cross_scale: float = 1.0):
        """Unit look directions in the instrument frame, shape ``col.shape + (3,)``."""
        tx, ty = self.tangents(col, row)
        u = np.stack([tx, cross_scale * ty, np.ones_like(tx)], -1)
        return u / np.linalg.norm(u, axis=-1, keepdims=True)

    def column(self, tan_y, row=0.0, *, iterations: int = 12):
        """Invert ``tan psi_y(col) = tan_y`` for the fractional column (Newton, vectorised)."""
        t = np.asarray(tan_y, float)
        row = np.broadcast_to(np.asarray(row, float), t.shape)
        c = np.polyval(self._inv, t)
        for _ in range(iterations):
            f = np.asarray(self._ty(c, row), float) - t
            d = np.asarray(self._dty(c, row), float)
            step = f / d
            c = c - step
            if np.all(~np.isfinite(step) | (np.abs(step) < 1e-11)):
                break
        return c


# ======================================================================= pose tables

#: :meth:`PushbroomModel._pose` tabulates the pose per line when it is asked for at least
#: this many rows, and at least :data:`POSE_TABLE_ROWS_PER_LINE` rows per line of their span.
POSE_TABLE_MIN_ROWS = 4096
POSE_TABLE_ROWS_PER_LINE = 4


def _line_table(row):
    """``(lines, k, w)`` for tabulating a pose over the whole lines spanned by ``row``: the
    lines (float), the index of the line at or below each row and the weight of the line
    above (``row = lines[k] + w``); None when ``row`` is too small or too spread out for a
    table to pay (see :data:`POSE_TABLE_MIN_ROWS`) or holds non-finite values."""
    if row.size < POSE_TABLE_MIN_ROWS:
        return None
    lo, hi = float(row.min()), float(row.max())
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return None
    first, last = np.floor(lo), np.floor(hi) + 1.0
    n = int(last - first) + 1
    if n * POSE_TABLE_ROWS_PER_LINE > row.size:
        return None
    lines = first + np.arange(n, dtype=np.float64)
    k = np.minimum((row - first).astype(np.int64), n - 2)  # row >= first: floor
    w = row - lines[k]
    return lines, k, w


def _line_table_pose(centre, rot, k, w, shape):
    """Linear interpolation of a tabulated pose: ``centre`` (n, 3) and ``rot`` (n, 3, 3) at
    whole lines, ``k``/``w`` from :func:`_line_table`; returns arrays of ``shape + (3,)`` and
    ``shape + (3, 3)``. Interpolated rotation matrices are orthonormal to ~ (angle per
    line)^2 / 8 (the rays are renormalised)."""
    return _PoseTable(centre, rot).at(k, w, shape)


class _PoseTable:
    """A pose tabulated at whole lines (:func:`_line_table_pose`), with its line-to-line
    steps computed once, for looking up many rows in chunks."""

    def __init__(self, centre, rot):
        n = len(centre)
        self.tables = [centre.reshape(n, -1), rot.reshape(n, -1)]
        self.steps = [np.diff(t, axis=0) for t in self.tables]

    def at(self, k, w, shape):
        """Centre ``shape + (3,)`` and rotation ``shape + (3, 3)`` at ``row = lines[k] + w``."""
        k, w = k.ravel(), w.ravel()[:, None]
        out = []
        for table, steps in zip(self.tables, self.steps):
            v = np.take(table, k, axis=0)
            step = np.take(steps, k, axis=0)
            step *= w
            v += step
            out.append(v)
        return out[0].reshape(shape + (3,)), out[1].reshape(shape + (3, 3))


#: rays of many rows are computed this many points at a time (the poses gathered for them,
#: 24 float64 a point, stay in a core's cache; the values do not depend on it)
RAY_CHUNK = 8192


# ======================================================================= the model

#: Adjustable parameters (name -> meaning); all zero in a model as delivered.
PARAMETERS = {
    "time_offset": "added to every line time, s",
    "roll_bias": "extra roll of the body frame, rad",
    "pitch_bias": "extra pitch of the body frame, rad",
    "yaw_bias": "extra yaw of the body frame, rad",
    "roll_drift": "roll rate about the centre-line time, rad/s",
    "pitch_drift": "pitch rate about the centre-line time, rad/s",
    "yaw_drift": "yaw rate about the centre-line time, rad/s",
    "position_offset_x": "satellite position offset along orbital x (flight), m",
    "position_offset_y": "satellite position offset along orbital y (right), m",
    "position_offset_z": "satellite position offset along orbital z (nadir), m",
    "look_scale": "relative scale of the cross-track look tangents (focal length error), 1",
}


class PushbroomModel(SensorModel):
    """Rigorous linear-array sensor model: ephemeris + attitude + detector look directions.

    Parameters
    ----------
    width, height : int
        Image size (detectors, lines).
    ephemeris : stereodem.sensor.models.ephemeris.Ephemeris
        ECEF positions and Earth-fixed velocities over the acquisition.
    detectors : DetectorArray
        Detector look directions in the instrument frame.
    line_period : float
        Seconds per line.
    t0 : float
        Time of line 0 (pixel centre), seconds on the ephemeris time base.
    attitude : stereodem.sensor.models.ephemeris.Attitude, optional
        Body -> orbital attitude; ``None`` means the body frame is the orbital frame.
    along_track_tilt_deg, cross_track_tilt_deg : float
        Fixed instrument tilt (pitch forward, roll towards -y), degrees.
    inertial_frame : bool
        Build the orbital frame with the inertial velocity ``v + omega_E x r`` (default, the
        standard orbital frame and ASTER's). ``False`` uses the ephemeris velocity as given
        (Earth-fixed), which is wrong by mrad for ASTER (notes §4.3) and is kept to show it.
    parameters : dict, optional
        Values of adjustable parameters (see :data:`PARAMETERS`), default all zero.
    """

    def __init__(
        self,
        *,
        width: int,
        height: int,
        ephemeris: Ephemeris,
        detectors: DetectorArray,
        line_period: float,
        t0: float = 0.0,
        attitude: Attitude | None = None,
        along_track_tilt_deg: float = 0.0,
        cross_track_tilt_deg: float = 0.0,
        inertial_frame: bool = True,
        parameters: dict | None = None,
        name: str | None = None,
    ):
        if int(width) < 1 or int(height) < 1:
            raise SensorModelError(
                f"pushbroom: image size must be positive, got {width} x {height}"
            )
        for key, v in (
            ("line_period", line_period),
            ("t0", t0),
            ("along_track_tilt_deg", along_track_tilt_deg),
            ("cross_track_tilt_deg", cross_track_tilt_deg),
        ):
            try:
                v = float(v)
            except (TypeError, ValueError):
                raise SensorModelError(f"pushbroom: {key} must be a number, got {v!r}") from None
            if not np.isfinite(v) and key != "line_period":
                raise SensorModelError(f"pushbroom: {key} must be finite, got {v}")
        if not (np.isfinite(line_period) and line_period > 0):
            raise SensorModelError(f"pushbroom: line period must be positive, got {line_period}")
        if not isinstance(ephemeris, Ephemeris):
            raise SensorModelError(
                "pushbroom: ephemeris must be a stereodem.sensor.models.ephemeris.Ephemeris"
            )
        if not isinstance(detectors, DetectorArray):
            raise SensorModelError("pushbroom: detectors must be a DetectorArray")
        self.width, self.height = int(width), int(height)
        self.ephemeris, self.detectors, self.attitude = ephemeris, detectors, attitude
        self.line_period, self.t0 = float(line_period), float(t0)
        self.along_track_tilt_deg = float(along_track_tilt_deg)
        self.cross_track_tilt_deg = float(cross_track_tilt_deg)
        self.inertial_frame = bool(inertial_frame)
        self.name = name or type(self).__name__
        self._tilt = body_to_orbital(
            np.radians(self.cross_track_tilt_deg), np.radians(self.along_track_tilt_deg), 0.0
        )
        self._params = dict.fromkeys(PARAMETERS, 0.0)
        if parameters:
            self._set_parameters(parameters)
        self._guess = None
        self.orbit: CircularOrbit | None = None  #: set by the synthetic constructors

    MODEL_TYPE = "pushbroom"

    def __reduce__(self):
        # pickle (process pools, Dask) through the exact JSON form: the detector table holds
        # closures that pickle cannot carry
        return (_rebuild_pushbroommodel, (self.to_dict(),))

    # ---------------------------------------------------------------- serialisation
    def to_dict(self) -> dict:
        """Plain description (numpy arrays inside; see :mod:`stereodem.sensor.io.sidecar`)."""
        e, a, o = self.ephemeris, self.attitude, self.orbit
        return {
            "width": self.width,
            "height": self.height,
            "line_period": self.line_period,
            "t0": self.t0,
            "along_track_tilt_deg": self.along_track_tilt_deg,
            "cross_track_tilt_deg": self.cross_track_tilt_deg,
            "inertial_frame": self.inertial_frame,
            "name": self.name,
            "parameters": dict(self._params),
            "ephemeris": {
                "times": e.times,
                "positions": e.positions,
                "velocities": e.velocities,
                "order": e.order,
            },
            "attitude": None
            if a is None
            else {"times": a.times, "angles": a.angles, "quaternions": a.quaternions},
            "detectors": self.detectors.spec,
            "orbit": None
            if o is None
            else {"radius": o.radius, "inclination": o.inclination, "raan": o.raan, "u0": o.u0},
        }

    @classmethod
    def from_dict(cls, d: dict) -> PushbroomModel:
        """Inverse of :meth:`to_dict`."""
        e = d["ephemeris"]
        eph = Ephemeris(e["times"], e["positions"], e.get("velocities"), order=e.get("order", 8))
        a = d.get("attitude")
        att = None
        if a is not None:
            att = Attitude(a["times"], a.get("angles"), quaternions=a.get("quaternions"))
        model = cls(
            width=d["width"],
            height=d["height"],
            ephemeris=eph,
            detectors=DetectorArray.from_spec(d["detectors"]),
            line_period=d["line_period"],
            t0=d.get("t0", 0.0),
            attitude=att,
            along_track_tilt_deg=d.get("along_track_tilt_deg", 0.0),
            cross_track_tilt_deg=d.get("cross_track_tilt_deg", 0.0),
            inertial_frame=d.get("inertial_frame", True),
            parameters=d.get("parameters"),
            name=d.get("name"),
        )
        o = d.get("orbit")
        if o is not None:
            model.orbit = CircularOrbit(o["radius"], o["inclination"], o["raan"], o["u0"])
        return model

    # ---------------------------------------------------------------- parameters
    def parameters(self) -> dict:
        """Adjustable parameters as an ordered ``{name: value}`` dict (units in
        :data:`PARAMETERS`)."""
        return dict(self._params)

    def with_parameters(self, **values) -> PushbroomModel:
        """A copy of the model with some adjustable parameters changed."""
        new = copy.copy(self)
        new._params = dict(self._params)
        new._set_parameters(values)
        return new

    def _set_parameters(self, values):
        self._params.update(checked_parameters(PARAMETERS, values, self.name))

    # ---------------------------------------------------------------- time and frames
    def line_time(self, row):
        """Acquisition time (s) of (fractional) image ``row``."""
        return self.t0 + np.asarray(row, float) * self.line_period + self._params["time_offset"]

    @property
    def reference_time(self) -> float:
        """Time of the centre line (s): origin of the drift parameters."""
        return self.t0 + 0.5 * (self.height - 1) * self.line_period

    def _pose(self, row):
        """Projection centre (ECEF, m) and instrument -> ECEF rotation at image rows.

        Many rows over few lines (the matched pixels of an image tile) take the pose from a
        table: :meth:`_exact_pose` at every whole line of their span, interpolated linearly
        in the fractional row (:func:`_line_table_pose`). The error is that of linear
        interpolation over one line period ``dt``, ``|f''| dt^2 / 8``: ~ 1e-5 m in position
        and ~ 1e-13 rad in rotation for a smooth orbit and attitude (the pose changes by
        ~ 15 m and ~ 2.5 urad per ASTER line); an attitude jitter of amplitude ``A`` (rad)
        and frequency ``f`` adds ``A (2 pi f)^2 dt^2 / 8`` (1e-8 rad, 5e-4 px, for 20 urad
        at 5 Hz). Few rows are evaluated directly.
        """
        row = np.asarray(row, dtype=np.float64)
        table = _line_table(row)
        if table is None:
            return self._exact_pose(row)
        lines, k, w = table
        c, rot = self._exact_pose(lines)
        return _line_table_pose(c, rot, k, w, row.shape)

    def _exact_pose(self, row):
        """:meth:`_pose` evaluated at every row (ephemeris, orbital frame and attitude)."""
        t = self.line_time(row)
        r, v = self.ephemeris.state(t)
        m = orbital_frame(r, v, inertial=self.inertial_frame)  # orbital -> ECEF
        p = self._params
        off = np.array([p["position_offset_x"], p["position_offset_y"], p["position_offset_z"]])
        if np.any(off):
            r = r + m @ off
        rot = m
        bias = np.array([p["roll_bias"], p["pitch_bias"], p["yaw_bias"]])
        drift = np.array([p["roll_drift"], p["pitch_drift"], p["yaw_drift"]])
        if np.any(bias) or np.any(drift):
            a = bias + (np.asarray(t) - self.reference_time)[..., None] * drift
            rot = rot @ body_to_orbital(a[..., 0], a[..., 1], a[..., 2])
        if self.attitude is not None:
            rot = rot @ self.attitude.matrix(t)
        return r, rot @ self._tilt

    # ---------------------------------------------------------------- image -> ground
    def rays(self, col, row):
        """Exact lines of sight in ECEF: ``(origin, direction)``, shape ``(..., 3)``.

        ``origin`` is the projection centre at the line time of ``row``; ``direction`` the
        unit look vector of detector ``col`` (fractional columns interpolate the detector
        table), pointing to the ground.
        """
        self.check_inputs(col, row, what="image coordinates")
        col, row = np.broadcast_arrays(np.asarray(col, float), np.asarray(row, float))
        scale = 1.0 + self._params["look_scale"]
        if type(self)._pose is not PushbroomModel._pose:
            c, rot = self._pose(row)
            u = self.detectors.directions(col, row, cross_scale=scale)
            d = (rot @ u[..., None])[..., 0]
            return c, d / np.sqrt(np.einsum("...i,...i->...", d, d))[..., None]
        table = _line_table(row)
        if table is None:
            c, rot = self._exact_pose(row)
            return c, self._look(rot, col, row, scale)
        # many rows over few lines: the pose table's look-ups and the directions by chunks
        # (:data:`RAY_CHUNK`), the same arithmetic point by point as in one piece
        lines, k, w = table
        poses = _PoseTable(*self._exact_pose(lines))
        shape = row.shape
        col, row, k, w = (np.ascontiguousarray(a).ravel() for a in (col, row, k, w))
        c, d = np.empty((row.size, 3)), np.empty((row.size, 3))
        for s in range(0, row.size, RAY_CHUNK):
            part = slice(s, s + RAY_CHUNK)
            c[part], rot = poses.at(k[part], w[part], k[part].shape)
            d[part] = self._look(rot, col[part], row[part], scale)
        return c.reshape(shape + (3,)), d.reshape(shape + (3,))

    def _look(self, rot, col, row, scale):
        """Unit look directions (ECEF) of detectors ``col`` at ``row`` for instrument ->
        ECEF rotations ``rot``: ``rot @ [tan_x, s tan_y, 1]`` column by column (the look
        vector's length cancels in the normalisation), without stacking per-point look
        vectors."""
        tx, ty = self.detectors.tangents(col, row)
        d = rot[..., 2].copy()
        d += rot[..., 0] * tx[..., None]
        d += rot[..., 1] * (scale * ty)[..., None]
        return d / np.sqrt(np.einsum("...i,...i->...", d, d))[..., None]

    def localize(self, col, row, h):
        """Image ``(col, row)`` at ellipsoidal height ``h`` (m) -> ``(lon, lat)`` degrees.

        NaN where the line of sight misses the surface.
        """
        return localize_on_rays(self, col, row, h)

    # ---------------------------------------------------------------- ground -> image
    def _scan_residual(self, p, row):
        """Along-track misfit (tangent units) of ground points ``p`` at ``row``, and the column."""
        c, rot = self._pose(row)
        d = np.einsum("...ji,...j->...i", rot, p - c)  # instrument frame
        with np.errstate(divide="ignore", invalid="ignore"):
            a, b = d[..., 0] / d[..., 2], d[..., 1] / d[..., 2]
        col = self.detectors.column(b / (1.0 + self._params["look_scale"]), row)
        tx, _ = self.detectors.tangents(col, row)
        return a - tx, col, d[..., 2]

    def _initial_rows(self, lon, lat, h):
        """First guess of (col, row) from a quadratic ground -> image fit built on demand."""
        if self._guess is None:
            self._guess = _GroundToImageFit.build(self)
        return self._guess(lon, lat, h)

    def project(self, lon, lat, h, *, max_iterations: int = 40):
        """Ground ``(lon, lat, h)`` (degrees, metres above the ellipsoid) -> image ``(col, row)``.

        The acquisition line is found exactly: a vectorised secant iteration on the line
        drives the along-track look tangent of ``P - C(t)`` in the instrument frame to the
        detector's along-track tangent at the column the point falls on, until the row moves
        by less than :data:`ROW_TOLERANCE` lines; the column comes from inverting the
        monotonic cross-track tangent of the detector table. Points that do not converge, or
        lie behind the sensor, get NaN (logged).
        """
        self.check_inputs(lon, lat, h, what="ground coordinates")
        lon, lat, h = np.broadcast_arrays(
            np.asarray(lon, float), np.asarray(lat, float), np.asarray(h, float)
        )
        shape = lon.shape
        lon, lat, h = lon.ravel(), lat.ravel(), h.ravel()
        p = np.stack(geodesy.geodetic_to_ecef(lon, lat, h), -1)
        row0 = self._initial_rows(lon, lat, h)
        f0, _, _ = self._scan_residual(p, row0)
        row1 = row0 + 0.5
        f1, col1, z1 = self._scan_residual(p, row1)
        rows, cols, front = row1.copy(), col1.copy(), z1 > 0
        done = np.zeros(lon.size, bool)
        active = np.arange(lon.size)
        r0, r1 = row0, row1
        for _ in range(max_iterations):
            if active.size == 0:
                break
            den = f1 - f0
            with np.errstate(divide="ignore", invalid="ignore"):
                step = np.where(den != 0, -f1 * (r1 - r0) / den, 0.0)
            step = np.clip(np.nan_to_num(step), -2.0 * self.height - 1000, 2.0 * self.height + 1000)
            r0, f0 = r1, f1
            r1 = r1 + step
            f1, c1, z1 = self._scan_residual(p[active], r1)
            rows[active], cols[active], front[active] = r1, c1, z1 > 0
            conv = np.abs(step) < ROW_TOLERANCE
            done[active[conv]] = True
            keep = ~conv
            active, r0, f0, r1, f1 = active[keep], r0[keep], f0[keep], r1[keep], f1[keep]
        bad = ~done | ~front | ~np.isfinite(cols)
        if np.any(bad):
            log.warning(
                "%s.project: %d of %d point(s) did not converge or lie behind the sensor",
                self.name,
                int(bad.sum()),
                lon.size,
            )
            rows[bad] = cols[bad] = np.nan
        return cols.reshape(shape), rows.reshape(shape)

    # ---------------------------------------------------------------- synthetic orbits
    @classmethod
    def synthetic(
        cls,
        center_lon: float,
        center_lat: float,
        *,
        width: int,
        height: int,
        altitude: float = 705e3,
        inclination_deg: float = 98.2,
        heading_deg: float | None = None,
        gsd: float = 15.0,
        line_period: float = 2.2e-3,
        along_track_tilt_deg: float = 0.0,
        cross_track_tilt_deg: float = 0.0,
        ephemeris_step: float = 1.0,
        inertial_frame: bool = True,
        name: str | None = None,
        center_height: float = 0.0,
    ) -> PushbroomModel:
        """A pushbroom camera on a circular Keplerian orbit, aimed at a ground centre.

        The orbit is circular with radius ``a + altitude`` (``a`` = WGS84 semi-major axis),
        inclined ``inclination_deg`` (sun-synchronous 98.2 deg by default), and passes
        descending over the scene. The pass is placed (node and along-track phase) so that the
        centre pixel ``((width-1)/2, (height-1)/2)`` sees ``(center_lon, center_lat)`` on the
        ellipsoid for the given tilt. The ideal line camera has its IFOV set so that the nadir
        ground sample across track is ``gsd`` (the along-track sample is the ground speed
        times ``line_period``). Ephemeris (positions and Earth-fixed velocities) is sampled
        every ``ephemeris_step`` seconds, 30 s beyond the image at both ends.

        Parameters
        ----------
        center_lon, center_lat : float
            Ground centre, degrees (geodetic).
        center_height : float
            Ellipsoidal height of the ground centre, m (0: on the ellipsoid).
        heading_deg : float, optional
            Inertial azimuth of the orbit track at the sub-satellite point (degrees clockwise
            from north); when given it replaces ``inclination_deg`` (and a northward heading
            gives an ascending pass).
        along_track_tilt_deg, cross_track_tilt_deg : float
            Instrument tilt, degrees (-27.6 for an ASTER-3B-like backward view).
        """
        orbit = _aimed_orbit(
            center_lon,
            center_lat,
            altitude=altitude,
            inclination_deg=inclination_deg,
            heading_deg=heading_deg,
            along_deg=along_track_tilt_deg,
            cross_deg=cross_track_tilt_deg,
            height=center_height,
        )
        ifov = gsd / _nadir_height(orbit, 0.0)
        return _model_on_orbit(
            cls,
            orbit,
            0.0,
            width=width,
            height=height,
            line_period=line_period,
            ifov=ifov,
            along_deg=along_track_tilt_deg,
            cross_deg=cross_track_tilt_deg,
            step=ephemeris_step,
            inertial=inertial_frame,
            name=name,
        )

    @classmethod
    def synthetic_pair(
        cls,
        center_lon: float,
        center_lat: float,
        *,
        width: int,
        height: int,
        backward_width: int | None = None,
        backward_height: int | None = None,
        backward_tilt_deg: float = -27.6,
        first_tilt_deg: float = 0.0,
        altitude: float = 705e3,
        inclination_deg: float = 98.2,
        heading_deg: float | None = None,
        gsd: float = 15.0,
        line_period: float = 2.2e-3,
        cross_track_tilt_deg: float = 0.0,
        ephemeris_step: float = 1.0,
        inertial_frame: bool = True,
        center_height: float = 0.0,
    ):
        """Along-track stereo pair on ONE orbit, both images centred on the same ground point
        ``(center_lon, center_lat, center_height)`` (ellipsoidal height, m: give the terrain's,
        or the tilted views are offset by ``h tan(tilt)`` on the ground; 1 km for ASTER 3B at
        2 km height).

        Returns ``(nadir_model, backward_model)``: the first is :meth:`synthetic` with
        along-track tilt ``first_tilt_deg`` (0: nadir, ASTER 3N); the second flies on the same
        orbit with along-track tilt ``backward_tilt_deg`` (ASTER 3B: -27.6 deg) and is
        acquired later when it looks further back (about 55 s at 705 km for 0 / -27.6 deg;
        any pair of tilts works, e.g. +20 / -20 deg). Because the Earth turns meanwhile, the
        backward camera's cross-track tilt is adjusted (by about 1.3 deg at mid-latitudes, as
        ASTER's wider 3B swath absorbs) so that its centre pixel sees the same ground centre; its
        ``cross_track_tilt_deg`` attribute holds the adjusted value. Both cameras have the
        same IFOV.
        """
        nadir = cls.synthetic(
            center_lon,
            center_lat,
            width=width,
            height=height,
            center_height=center_height,
            along_track_tilt_deg=first_tilt_deg,
            cross_track_tilt_deg=cross_track_tilt_deg,
            altitude=altitude,
            inclination_deg=inclination_deg,
            heading_deg=heading_deg,
            gsd=gsd,
            line_period=line_period,
            ephemeris_step=ephemeris_step,
            inertial_frame=inertial_frame,
            name="nadir" if first_tilt_deg == 0 else "first",
        )
        orbit = nadir.orbit  # the backward camera flies on the same orbit, with the same IFOV
        ifov = gsd / _nadir_height(orbit, 0.0)
        target = np.array(
            geodesy.geodetic_to_ecef(center_lon, center_lat, float(center_height)), float
        )
        v_ground = orbit.mean_motion * geodesy.A
        t_guess = (
            -_nadir_height(orbit, 0.0)
            * (np.tan(np.radians(backward_tilt_deg)) - np.tan(np.radians(first_tilt_deg)))
            / v_ground
        )

        def miss(x):
            return _centre_miss(
                orbit,
                x[0],
                backward_tilt_deg,
                cross_track_tilt_deg + np.degrees(x[1]),
                target,
                center_height,
            )

        t_c, droll = _newton2(
            miss,
            np.array([t_guess, 0.0]),
            np.array([1e-3, 1e-7]),
            what="backward view of the synthetic pair",
        )
        back = _model_on_orbit(
            cls,
            orbit,
            t_c,
            width=backward_width or width,
            height=backward_height or height,
            line_period=line_period,
            ifov=ifov,
            along_deg=backward_tilt_deg,
            cross_deg=cross_track_tilt_deg + float(np.degrees(droll)),
            step=ephemeris_step,
            inertial=inertial_frame,
            name="backward",
        )
        return nadir, back


# ======================================================================= helpers


class _GroundToImageFit:
    """Quadratic-in-(lon, lat), linear-in-h least-squares map ground -> (col, row).

    Only a first guess for :meth:`PushbroomModel.project`; fitted on localised grid points.
    """

    def __init__(self, lon0, lat0, slon, slat, sh, coef_col, coef_row, height):
        self.lon0, self.lat0, self.slon, self.slat, self.sh = lon0, lat0, slon, slat, sh
        self.coef_col, self.coef_row, self.height = coef_col, coef_row, height

    @classmethod
    def build(cls, model: PushbroomModel, n: int = 9):
        w, hgt = model.width, model.height
        c, r, z = np.meshgrid(
            np.linspace(0, w - 1, n),
            np.linspace(0, hgt - 1, n),
            np.array([-500.0, 4000.0, 9000.0]),
            indexing="ij",
        )
        c, r, z = c.ravel(), r.ravel(), z.ravel()
        lon, lat = model.localize(c, r, z)
        ok = np.isfinite(lon) & np.isfinite(lat)
        if ok.sum() < 12:
            raise SensorModelError(f"{model.name}: the image does not see the Earth")
        c, r, z, lon, lat = c[ok], r[ok], z[ok], lon[ok], lat[ok]
        lon0, lat0 = float(np.mean(lon)), float(np.mean(lat))
        slon = float(np.ptp(lon)) or 1.0
        slat = float(np.ptp(lat)) or 1.0
        fit = cls(lon0, lat0, slon, slat, 4500.0, None, None, hgt)
        a = fit._design(lon, lat, z)
        fit.coef_col = np.linalg.lstsq(a, c, rcond=None)[0]
        fit.coef_row = np.linalg.lstsq(a, r, rcond=None)[0]
        return fit

    def _design(self, lon, lat, h):
        x = (((lon - self.lon0 + 180.0) % 360.0) - 180.0) / self.slon
        y = (lat - self.lat0) / self.slat
        z = h / self.sh
        one = np.ones_like(x)
        return np.stack([one, x, y, x * x, x * y, y * y, z, z * x, z * y], -1)

    def __call__(self, lon, lat, h):
        a = self._design(lon, lat, h)
        row = a @ self.coef_row
        return np.clip(row, -3.0 * self.height - 1000, 4.0 * self.height + 1000)


def _geocentric_latitude(lat_deg):
    return np.arctan((1.0 - geodesy.F) ** 2 * np.tan(np.radians(lat_deg)))


def _nadir_height(orbit: CircularOrbit, t: float) -> float:
    r, _ = orbit.state(t)
    return float(geodesy.ecef_to_geodetic(*r)[2])


def _centre_miss(orbit, t_c, along_deg, cross_deg, target, height=0.0):
    """East/north miss (m) of the boresight at time ``t_c`` from ECEF ``target``, which lies at
    ellipsoidal ``height`` (m)."""
    r, v = orbit.state(t_c)
    m = orbital_frame(r, v, inertial=True) @ body_to_orbital(
        np.radians(cross_deg), np.radians(along_deg), 0.0
    )
    d = m @ np.array([0.0, 0.0, 1.0])
    p = geodesy.intersect_height(r, d, float(height))
    lon, lat, _ = geodesy.ecef_to_geodetic(*target)
    enu = geodesy.enu_basis(lon, lat) @ (p - target)
    return enu[:2]


def _newton2(fun, x0, steps, *, what, tol=1e-4, max_iterations=30):
    """Solve ``fun(x) = 0`` for two unknowns by Newton with a forward-difference Jacobian."""
    x = np.array(x0, float)
    for _ in range(max_iterations):
        f = fun(x)
        if not np.all(np.isfinite(f)):
            raise ConvergenceError(f"{what}: the boresight misses the Earth")
        if np.max(np.abs(f)) < tol:
            return x
        jac = np.empty((2, 2))
        for k in range(2):
            dx = np.zeros(2)
            dx[k] = steps[k]
            jac[:, k] = (fun(x + dx) - f) / steps[k]
        x = x - np.linalg.solve(jac, f)
    raise ConvergenceError(f"{what}: aiming did not converge (miss {np.max(np.abs(f)):.3g} m)")


def _aimed_orbit(
    lon, lat, *, altitude, inclination_deg, heading_deg, along_deg, cross_deg, height=0.0
):
    """Circular orbit whose boresight (with tilt) sees ``(lon, lat, height)`` at ``t = 0``."""
    if not (np.isfinite(lon) and np.isfinite(lat) and abs(lat) < 90):
        raise SensorModelError(f"synthetic pushbroom: bad scene centre lon={lon}, lat={lat}")
    a = geodesy.A + float(altitude)
    psi = float(_geocentric_latitude(lat))
    if heading_deg is not None:
        az = np.radians(heading_deg)
        inc = float(np.arccos(np.clip(np.cos(psi) * np.sin(az), -1, 1)))
        descending = np.cos(az) < 0
    else:
        inc = float(np.radians(inclination_deg))
        descending = True
    s = np.sin(psi) / np.sin(inc)
    if abs(s) >= 1:
        raise SensorModelError(
            f"synthetic pushbroom: latitude {lat} is not reached by an orbit "
            f"inclined {np.degrees(inc):.2f} deg"
        )
    u0 = np.pi - np.arcsin(s) if descending else np.arcsin(s)
    raan = np.radians(lon) - np.arctan2(np.sin(u0) * np.cos(inc), np.cos(u0))
    target = np.array(geodesy.geodetic_to_ecef(lon, lat, float(height)), float)
    # start the along-track phase where the tilted view lands near the target
    u0 -= np.tan(np.radians(along_deg)) * altitude / geodesy.A

    def miss(x):
        return _centre_miss(
            CircularOrbit(a, inc, x[1], x[0]), 0.0, along_deg, cross_deg, target, height
        )

    u0, raan = _newton2(
        miss, np.array([u0, raan]), np.array([1e-7, 1e-7]), what="synthetic pushbroom"
    )
    return CircularOrbit(a, inc, raan, u0)


def _model_on_orbit(
    cls,
    orbit,
    t_centre,
    *,
    width,
    height,
    line_period,
    ifov,
    along_deg,
    cross_deg,
    step,
    inertial,
    name,
):
    if int(width) < 2 or int(height) < 2:
        raise SensorModelError(
            f"synthetic pushbroom: image must be at least 2 x 2, got {width} x {height}"
        )
    t0 = t_centre - 0.5 * (int(height) - 1) * line_period
    t_end = t0 + (int(height) - 1) * line_period
    pad = 30.0 + 8 * step
    eph = orbit.ephemeris(t0 - pad, t_end + pad, step)
    det = DetectorArray.linear(int(width), ifov)
    model = cls(
        width=width,
        height=height,
        ephemeris=eph,
        detectors=det,
        line_period=line_period,
        t0=t0,
        along_track_tilt_deg=along_deg,
        cross_track_tilt_deg=cross_deg,
        inertial_frame=inertial,
        name=name,
    )
    model.orbit = orbit
    return model


def _rebuild_pushbroommodel(d):
    return PushbroomModel.from_dict(d)
