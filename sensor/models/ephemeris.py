"""Interpolation of satellite ephemeris (position, velocity) and attitude over time.

* :class:`Ephemeris`: ECEF positions (and optionally velocities) sampled at increasing times,
  interpolated by Lagrange polynomials over a sliding window of ``order`` samples (8 by
  default, as USGSCSM/ASP do for linear-array cameras; Topan 2009 Eq. 3.57). Without given
  velocities the velocity is the time derivative of the position interpolant.
* :class:`Attitude`: roll/pitch/yaw angles (natural cubic spline per angle, Bettemir 2006
  Eq. 4.56-4.61) or quaternions (scipy ``RotationSpline``) giving body -> orbital matrices.

Times are seconds on any one time base shared with the sensor model's line times.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, RotationSpline

from stereodem.core.errors import SensorModelError
from stereodem.core.geodesy import GM, OMEGA_EARTH
from stereodem.sensor.geo.rotations import body_to_orbital


def _as_times(times, what):
    t = np.asarray(times, dtype=np.float64)
    if t.ndim != 1 or t.size == 0:
        raise SensorModelError(f"{what}: times must be a non-empty 1-D array, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise SensorModelError(f"{what}: non-finite sample times")
    if t.size > 1 and not np.all(np.diff(t) > 0):
        raise SensorModelError(f"{what}: sample times must be strictly increasing")
    return t


def _as_samples(values, n, what, width=3):
    v = np.asarray(values, dtype=np.float64)
    if v.shape != (n, width):
        raise SensorModelError(f"{what}: expected shape ({n}, {width}), got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise SensorModelError(f"{what}: non-finite samples")
    return v


class _LagrangeTable:
    """Sliding-window Lagrange interpolation of vector samples, vectorised over query times.

    For every window of ``k`` consecutive samples the interpolating polynomial is stored in
    monomial form of the normalised time ``x = (t - centre) / half_span`` (values centred on
    the window mean, which keeps the Vandermonde solve well conditioned). A query time uses
    the window whose samples surround it (``k // 2`` on each side where possible; windows are
    clamped at the ends, i.e. extrapolation uses the end polynomial). Adjacent windows share
    the sample at which they switch, so the interpolant is continuous.
    """

    def __init__(self, times, values, order):
        n = times.size
        k = int(min(order, n))
        self.times, self.k = times, k
        starts = np.arange(n - k + 1)
        idx = starts[:, None] + np.arange(k)[None, :]  # (W, k)
        tw = times[idx]
        self.centre = 0.5 * (tw[:, 0] + tw[:, -1])
        self.half = np.where(k > 1, 0.5 * (tw[:, -1] - tw[:, 0]), 1.0)
        x = (tw - self.centre[:, None]) / self.half[:, None]  # (W, k) in [-1, 1]
        y = values[idx]  # (W, k, d)
        self.mean = y.mean(axis=1)  # (W, d)
        vander = x[:, :, None] ** np.arange(k)[None, None, :]  # (W, k, k)
        self.coef = np.linalg.solve(vander, y - self.mean[:, None, :])  # (W, k, d)

    def _window(self, t):
        n, k = self.times.size, self.k
        i = np.searchsorted(self.times, t, side="right")
        return np.clip(i - k // 2, 0, n - k)

    def evaluate(self, t, derivative=False):
        t = np.asarray(t, dtype=np.float64)
        shape = t.shape
        t = t.ravel()
        w = self._window(t)
        lo, hi = (int(w.min()), int(w.max())) if w.size else (0, -1)
        windows = np.arange(lo, hi + 1)
        if 0 < windows.size <= 16 and t.size > 64 * windows.size:
            return self._evaluate_by_window(t, w, windows, shape, derivative)
        x = (t - self.centre[w]) / self.half[w]
        c = self.coef[w]  # (M, k, d)
        val = c[:, -1, :].copy()
        for j in range(self.k - 2, -1, -1):
            val = val * x[:, None] + c[:, j, :]
        val = val + self.mean[w]
        d = val.shape[-1]
        if not derivative:
            return val.reshape(shape + (d,))
        der = np.zeros_like(val)
        for j in range(self.k - 1, 0, -1):
            der = der * x[:, None] + j * c[:, j, :]
        der = der / self.half[w][:, None]
        return val.reshape(shape + (d,)), der.reshape(shape + (d,))

    def _evaluate_by_window(self, t, w, windows, shape, derivative):
        """:meth:`evaluate` for many times in few windows (the lines of an image tile): the
        same arithmetic per time with each window's coefficients as scalars, on (d, n)
        arrays, instead of gathering a (times, order, d) coefficient array."""
        d = self.coef.shape[-1]
        val = np.empty((d, t.size))
        der = np.empty((d, t.size)) if derivative else None
        for wi in windows:
            sel = slice(None) if windows.size == 1 else np.flatnonzero(w == wi)
            tw = t[sel]
            if tw.size == 0:
                continue
            x = (tw - self.centre[wi]) / self.half[wi]
            c = self.coef[wi][:, :, None]  # (k, d, 1)
            v = np.repeat(c[-1], tw.size, axis=1)
            for j in range(self.k - 2, -1, -1):
                v *= x
                v += c[j]
            v += self.mean[wi][:, None]
            val[:, sel] = v
            if derivative:
                g = np.zeros((d, tw.size))
                for j in range(self.k - 1, 0, -1):
                    g *= x
                    g += j * c[j]
                g /= self.half[wi]
                der[:, sel] = g
        val = val.T.reshape(shape + (d,))
        if not derivative:
            return val
        return val, der.T.reshape(shape + (d,))


class Ephemeris:
    """Satellite positions (and velocities) in ECEF, interpolated in time.

    Parameters
    ----------
    times : array_like (n,)
        Sample times, seconds, strictly increasing.
    positions : array_like (n, 3)
        ECEF positions, metres.
    velocities : array_like (n, 3), optional
        Earth-fixed ECEF velocities, m/s. When given they are interpolated like the
        positions; otherwise the velocity is the derivative of the position interpolant.
    order : int
        Number of samples per Lagrange window (8 by default; fewer if fewer samples).
    """

    def __init__(self, times, positions, velocities=None, *, order: int = 8):
        self.times = _as_times(times, "ephemeris")
        n = self.times.size
        if n < 2:
            raise SensorModelError(f"ephemeris: at least 2 samples are needed, got {n}")
        if order < 2:
            raise SensorModelError(f"ephemeris: interpolation order must be >= 2, got {order}")
        self.positions = _as_samples(positions, n, "ephemeris positions")
        self.velocities = (
            None if velocities is None else _as_samples(velocities, n, "ephemeris velocities")
        )
        self.order = int(min(order, n))
        self._pos = _LagrangeTable(self.times, self.positions, self.order)
        self._vel = (
            None
            if self.velocities is None
            else _LagrangeTable(self.times, self.velocities, self.order)
        )

    @property
    def time_range(self):
        """``(first, last)`` sample time, seconds."""
        return float(self.times[0]), float(self.times[-1])

    def position(self, t):
        """ECEF position (m) at times ``t`` (s); shape ``t.shape + (3,)``."""
        return self._pos.evaluate(t)

    def velocity(self, t):
        """Earth-fixed ECEF velocity (m/s) at times ``t`` (s)."""
        if self._vel is not None:
            return self._vel.evaluate(t)
        return self._pos.evaluate(t, derivative=True)[1]

    def state(self, t):
        """``(position, velocity)`` at times ``t``: ECEF metres and m/s."""
        if self._vel is not None:
            return self._pos.evaluate(t), self._vel.evaluate(t)
        return self._pos.evaluate(t, derivative=True)


class Attitude:
    """Attitude of the body frame relative to the orbital frame, interpolated in time.

    Give exactly one of ``angles`` or ``quaternions``.

    Parameters
    ----------
    times : array_like (n,)
        Sample times, seconds, strictly increasing.
    angles : array_like (n, 3), optional
        Roll, pitch, yaw in radians (Bettemir Eq. 4.7 convention, see
        :func:`stereodem.sensor.geo.rotations.body_to_orbital`). Interpolated by a natural cubic
        spline per angle; a single sample is a constant attitude.
    quaternions : array_like (n, 4), optional
        Unit quaternions ``(q1, q2, q3, q4)``, scalar last (scipy convention), of the rotation
        taking body vectors to orbital ones (``d_O = M d_B``). Interpolated with scipy's
        ``RotationSpline`` (``Slerp``-like, C2-continuous).
    """

    def __init__(self, times, angles=None, *, quaternions=None):
        if (angles is None) == (quaternions is None):
            raise SensorModelError("attitude: give exactly one of angles or quaternions")
        self.times = _as_times(times, "attitude")
        n = self.times.size
        self.angles = self.quaternions = None
        if angles is not None:
            self.angles = _as_samples(angles, n, "attitude angles")
            self._spline = (
                CubicSpline(self.times, self.angles, axis=0, bc_type="natural") if n > 1 else None
            )
        else:
            q = _as_samples(quaternions, n, "attitude quaternions", width=4)
            norm = np.linalg.norm(q, axis=1)
            if np.any(np.abs(norm - 1.0) > 1e-3):
                raise SensorModelError("attitude quaternions must be unit quaternions")
            self.quaternions = q / norm[:, None]
            rot = Rotation.from_quat(self.quaternions)
            self._rot = rot
            self._rspline = RotationSpline(self.times, rot) if n > 1 else None

    @classmethod
    def fixed(cls, roll: float = 0.0, pitch: float = 0.0, yaw: float = 0.0) -> Attitude:
        """A constant attitude (radians)."""
        return cls([0.0], [[roll, pitch, yaw]])

    def angles_at(self, t):
        """Roll, pitch, yaw (rad) at times ``t``; only for angle-based attitude."""
        if self.angles is None:
            raise SensorModelError("attitude given as quaternions has no interpolated angles")
        t = np.asarray(t, dtype=np.float64)
        if self._spline is None:
            return np.broadcast_to(self.angles[0], t.shape + (3,)).copy()
        return self._spline(t)

    def matrix(self, t):
        """Body -> orbital rotation matrices at times ``t``: shape ``t.shape + (3, 3)``."""
        t = np.asarray(t, dtype=np.float64)
        if self.angles is not None:
            a = self.angles_at(t)
            return body_to_orbital(a[..., 0], a[..., 1], a[..., 2])
        if self._rspline is None:
            m = self._rot.as_matrix()[0]
            return np.broadcast_to(m, t.shape + (3, 3)).copy()
        return self._rspline(t.ravel()).as_matrix().reshape(t.shape + (3, 3))


class CircularOrbit:
    """A circular Keplerian orbit, for simulation (no perturbations, no precession).

    The inertial frame coincides with ECEF at ``t = 0``; the Earth turns about z at
    :data:`stereodem.core.geodesy.OMEGA_EARTH`, so ECEF = ``R3(omega_E t)`` ECI (passive rotation).

    Parameters
    ----------
    radius : float
        Orbit radius, metres from the Earth's centre.
    inclination : float
        Inclination, radians (about 98.2 deg for a sun-synchronous orbit at 705 km).
    raan : float
        Right ascension of the ascending node in the inertial frame (= ECEF longitude of the
        node at ``t = 0``), radians.
    u0 : float
        Argument of latitude at ``t = 0``, radians.
    """

    def __init__(self, radius: float, inclination: float, raan: float, u0: float):
        self.radius, self.inclination, self.raan, self.u0 = (
            float(radius),
            float(inclination),
            float(raan),
            float(u0),
        )
        self.mean_motion = float(np.sqrt(GM / self.radius**3))  #: rad/s

    def state(self, t):
        """ECEF position (m) and Earth-fixed ECEF velocity (m/s) at times ``t`` (s)."""
        t = np.asarray(t, dtype=np.float64)
        a, n, i, om = self.radius, self.mean_motion, self.inclination, self.raan
        u = self.u0 + n * t
        cu, su, ci, si, co, so = np.cos(u), np.sin(u), np.cos(i), np.sin(i), np.cos(om), np.sin(om)
        r = a * np.stack([co * cu - so * su * ci, so * cu + co * su * ci, su * si], -1)
        v = a * n * np.stack([-co * su - so * cu * ci, -so * su + co * cu * ci, cu * si], -1)
        th = OMEGA_EARTH * t
        c, s = np.cos(th), np.sin(th)
        re = np.stack(
            [c * r[..., 0] + s * r[..., 1], -s * r[..., 0] + c * r[..., 1], r[..., 2]], -1
        )
        vi = np.stack(
            [c * v[..., 0] + s * v[..., 1], -s * v[..., 0] + c * v[..., 1], v[..., 2]], -1
        )
        ve = vi - np.cross(np.array([0.0, 0.0, OMEGA_EARTH]), re)
        return re, ve

    def ephemeris(
        self, t_start: float, t_end: float, step: float = 1.0, *, order: int = 8
    ) -> Ephemeris:
        """Sample the orbit every ``step`` seconds on a grid of multiples of ``step`` covering
        ``[t_start, t_end]`` (positions and Earth-fixed velocities)."""
        k0, k1 = int(np.floor(t_start / step)), int(np.ceil(t_end / step))
        times = step * np.arange(k0, k1 + 1, dtype=np.float64)
        r, v = self.state(times)
        return Ephemeris(times, r, v, order=order)
