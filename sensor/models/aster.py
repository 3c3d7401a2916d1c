"""ASTER L1A VNIR (3N / 3B) geometry and its rigorous model (the files are read by
:mod:`stereodem.sensor.io.aster_xml`).

The product geometry is a lattice of 11 columns x N rows (ASTER notes §2.4): per lattice row
a satellite position (ECEF, m) and per lattice point a unit sight vector in the orbital frame
(z = -r/|r|, y = -(r x v)/|r x v|, x = y x z, built with the **inertial** velocity
``v + omega_E x r``; notes §4.2-4.3). Lattice integers are pixel centres, the project's
convention. The model (:class:`AsterModel`) is a
:class:`stereodem.sensor.models.pushbroom.PushbroomModel`:

* line times ``t(row) = row * line_period`` with ``line_period`` = 2.1989 ms (notes §4.4);
* positions interpolated by 8-point Lagrange polynomials over the lattice-row samples; the
  Earth-fixed velocity at the lattice rows is the time derivative of the positions (central
  differences by default, :func:`lattice_velocities`), interpolated likewise, and the orbital
  frame adds ``omega_E x r``;
* sight vectors interpolated across columns by a cubic spline (and linearly across lattice
  rows if they vary; they are constant along track in real products), renormalised.

ASP's XML (``<isd>``) holds ``LATTICE_POINT``, ``SIGHT_VECTOR`` (orbital frame, as in the
product), ``WORLD_SIGHT_VECTOR`` (ECEF, from the product's latitude/longitude),
``SAT_POS``, ``IMAGE_COLS``/``IMAGE_ROWS`` and ASP's fitted RPC in ``<RPB>``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stereodem.core import geodesy
from stereodem.core.errors import SensorModelError
from stereodem.sensor.models.ephemeris import Attitude, Ephemeris
from stereodem.sensor.models.pushbroom import DetectorArray, PushbroomModel

#: ASTER VNIR line period, seconds (0.87958 s per 400-line lattice step; notes §4.4).
ASTER_LINE_PERIOD = 2.1989e-3

#: coefficient keys of the product's RPC block (``AsterGeometry.rpc``), 20 values each
_RPB_COEFS = ("LINENUMCOEF", "LINEDENCOEF", "SAMPNUMCOEF", "SAMPDENCOEF")


@dataclass
class AsterGeometry:
    """Geometry of one ASTER band as written by ASP's ``aster2asp``.

    Attributes
    ----------
    lattice : ndarray (N, 11, 2) float64
        Lattice pixel coordinates ``(col, row)``, pixel centres at integers.
    sight_vectors : ndarray (N, 11, 3)
        Unit sight vectors in the orbital frame (renormalised after the product's rounding).
    world_sight_vectors : ndarray (N, 11, 3)
        Unit sight vectors in ECEF, from the product's own lattice latitude/longitude.
    satellite_positions : ndarray (N, 3)
        ECEF satellite position per lattice row, metres.
    image_cols, image_rows : int
        Image size.
    rpc : dict or None
        ASP's fitted RPC00B: the ``<RPB>`` keys (``LINEOFFSET``... as floats, the four
        ``*COEF`` keys as arrays of 20, ``SATID`` as a string); ``None`` if absent.
    path : str
        Source file.
    satellite_velocities : ndarray (N, 3) or None
        The product's ``SatelliteVelocity`` (m/s, ECEF axes), when read from an L1A granule.
    velocity_convention : {"inertial", "earth_fixed", "unknown"}
        What ``satellite_velocities`` holds: the inertial velocity ``v + omega_E x r`` or the
        Earth-fixed one (decided by the L1A reader against the positions; notes §4.3).
    observation_times : ndarray (N, k) or None
        The product's raw ``ObservationTime`` words (encoding unverified, notes §4.5; never
        used by the geometry).
    """

    lattice: np.ndarray
    sight_vectors: np.ndarray
    world_sight_vectors: np.ndarray
    satellite_positions: np.ndarray
    image_cols: int
    image_rows: int
    rpc: dict | None = None
    path: str = ""
    satellite_velocities: np.ndarray | None = None
    velocity_convention: str = "unknown"
    observation_times: np.ndarray | None = None
    lattice_rows: np.ndarray = field(init=False, repr=False)
    lattice_cols: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        where = f"{self.path}: " if self.path else ""
        lat = self.lattice
        n = lat.shape[0]
        if lat.ndim != 3 or lat.shape[2] != 2 or n < 2:
            raise SensorModelError(f"{where}lattice must have shape (N>=2, K, 2), got {lat.shape}")
        k = lat.shape[1]
        for name, arr in (
            ("SIGHT_VECTOR", self.sight_vectors),
            ("WORLD_SIGHT_VECTOR", self.world_sight_vectors),
        ):
            if arr.shape != (n, k, 3):
                raise SensorModelError(
                    f"{where}{name} has shape {arr.shape}, expected ({n}, {k}, 3)"
                )
        if self.satellite_positions.shape != (n, 3):
            raise SensorModelError(
                f"{where}SAT_POS has shape {self.satellite_positions.shape}, expected ({n}, 3)"
            )
        rows = lat[:, :, 1]
        if not np.all(rows == rows[:, :1]):
            raise SensorModelError(f"{where}lattice rows are not constant along each lattice row")
        cols = lat[:, :, 0]
        if not np.all(cols == cols[:1, :]):
            raise SensorModelError(f"{where}lattice columns differ between lattice rows")
        self.lattice_rows = rows[:, 0].astype(float)
        self.lattice_cols = cols[0].astype(float)
        if not (np.all(np.diff(self.lattice_rows) > 0) and np.all(np.diff(self.lattice_cols) > 0)):
            raise SensorModelError(f"{where}lattice rows/columns must increase")
        if self.satellite_velocities is not None and np.shape(self.satellite_velocities) != (n, 3):
            raise SensorModelError(
                f"{where}satellite velocities have shape "
                f"{np.shape(self.satellite_velocities)}, expected ({n}, 3)"
            )
        if self.velocity_convention not in ("inertial", "earth_fixed", "unknown"):
            raise SensorModelError(
                f"{where}unknown velocity convention {self.velocity_convention!r}"
            )
        if self.image_cols < 1 or self.image_rows < 1:
            raise SensorModelError(f"{where}bad image size {self.image_cols} x {self.image_rows}")


def lattice_velocities(times, positions, *, method: str = "central"):
    """Earth-fixed ECEF velocity (m/s) at the lattice-row times from the positions.

    The positions of a real product carry centimetre-level noise (third differences of
    0.1-0.9 m in the Rainier fixture against ~0.01 m for a smooth orbit), which the
    derivative of a high-order interpolant amplifies at the ends of the lattice.

    Parameters
    ----------
    method : {"central", "polynomial", "lagrange"}
        ``"central"``: central differences, second-order one-sided at the ends (default; it
        reproduces the product's own lattice latitude/longitude best: mean 0.56 / 2.1 urad
        for 3N / 3B of the fixture). ``"polynomial"``: derivative of a least-squares
        polynomial of degree 5 in time over the whole scene. ``"lagrange"``: derivative of the
        8-point Lagrange interpolant (noisiest at the lattice ends).
    """
    t = np.asarray(times, dtype=np.float64)
    p = np.asarray(positions, dtype=np.float64)
    if method == "central":
        return np.gradient(p, t, axis=0, edge_order=2 if t.size > 2 else 1)
    if method == "polynomial":
        half = 0.5 * (t[-1] - t[0])
        x = (t - 0.5 * (t[0] + t[-1])) / half
        c = np.polynomial.polynomial.polyfit(x, p, min(5, t.size - 1))
        return np.polynomial.polynomial.polyval(x, np.polynomial.polynomial.polyder(c)).T / half
    if method == "lagrange":
        return Ephemeris(t, p).velocity(t)
    raise SensorModelError(f"unknown velocity method {method!r} (central, polynomial, lagrange)")


class AsterModel(PushbroomModel):
    """Rigorous ASTER VNIR band model from its lattice geometry (see the module docstring).

    Parameters
    ----------
    geometry : AsterGeometry
        From :func:`read_asp_aster_xml` (or an L1A reader producing the same fields).
    line_period : float
        Seconds per line (ASTER VNIR: 2.1989e-3).
    inertial_frame : bool
        Build the orbital frame with the inertial velocity (default, correct; ``False``
        reproduces the Earth-fixed-velocity mistake, mrad off; notes §4.3).
    velocity_method : {"central", "polynomial", "lagrange", "file"}
        How the Earth-fixed velocity at the lattice rows is derived from the positions (see
        :func:`lattice_velocities`), or ``"file"``: the product's own ``SatelliteVelocity``
        (``geometry.satellite_velocities``, made Earth-fixed according to
        ``geometry.velocity_convention``, which must then be known); the velocities are then
        interpolated between lattice rows by 8-point Lagrange polynomials like the positions.
    """

    def __init__(
        self,
        geometry: AsterGeometry,
        *,
        line_period: float = ASTER_LINE_PERIOD,
        inertial_frame: bool = True,
        velocity_method: str = "central",
        name: str | None = None,
    ):
        g = geometry
        times = g.lattice_rows * float(line_period)
        eph = Ephemeris(times, g.satellite_positions, _band_velocities(g, times, velocity_method))
        self.velocity_method = velocity_method
        sv = g.sight_vectors
        if np.allclose(sv, sv[:1], rtol=0.0, atol=1e-12):
            det = DetectorArray.from_sight_vectors(sv[0], g.lattice_cols)
        else:
            det = DetectorArray.from_sight_vectors(sv, g.lattice_cols, rows=g.lattice_rows)
        super().__init__(
            width=g.image_cols,
            height=g.image_rows,
            ephemeris=eph,
            detectors=det,
            line_period=line_period,
            t0=0.0,
            inertial_frame=inertial_frame,
            name=name or (Path(g.path).stem if g.path else "AsterModel"),
        )
        self.geometry = g

    MODEL_TYPE = "aster"

    def __reduce__(self):
        # pickle (process pools, Dask) through the exact JSON form: the detector table holds
        # closures that pickle cannot carry
        return (_rebuild_astermodel, (self.to_dict(),))

    def to_dict(self) -> dict:
        """Plain description: the lattice geometry and the model options."""
        g = self.geometry
        return {
            "geometry": {
                "lattice": g.lattice,
                "sight_vectors": g.sight_vectors,
                "world_sight_vectors": g.world_sight_vectors,
                "satellite_positions": g.satellite_positions,
                "image_cols": g.image_cols,
                "image_rows": g.image_rows,
                "rpc": g.rpc,
                "path": g.path,
                "satellite_velocities": g.satellite_velocities,
                "velocity_convention": g.velocity_convention,
                "observation_times": g.observation_times,
            },
            "line_period": self.line_period,
            "inertial_frame": self.inertial_frame,
            "velocity_method": self.velocity_method,
            "name": self.name,
            "parameters": self.parameters(),
            # a time-varying attitude correction (e.g. jitter, stereodem.sensor.estimation.jitter)
            "attitude": None
            if self.attitude is None
            else {
                "times": self.attitude.times,
                "angles": self.attitude.angles,
                "quaternions": self.attitude.quaternions,
            },
        }

    @classmethod
    def from_dict(cls, d: dict) -> AsterModel:
        """Inverse of :meth:`to_dict`."""
        g = dict(d["geometry"])
        for k in (
            "lattice",
            "sight_vectors",
            "world_sight_vectors",
            "satellite_positions",
            "satellite_velocities",
            "observation_times",
        ):
            if g.get(k) is not None:
                g[k] = np.asarray(g[k], dtype=np.float64)
        if g.get("rpc"):
            g["rpc"] = {
                k: (np.asarray(v, float) if k in _RPB_COEFS else v) for k, v in g["rpc"].items()
            }
        model = cls(
            AsterGeometry(**g),
            line_period=d.get("line_period", ASTER_LINE_PERIOD),
            inertial_frame=d.get("inertial_frame", True),
            velocity_method=d.get("velocity_method", "central"),
            name=d.get("name"),
        )
        if d.get("parameters"):
            model._set_parameters(d["parameters"])
        a = d.get("attitude")
        if a is not None:
            model.attitude = Attitude(a["times"], a.get("angles"), quaternions=a.get("quaternions"))
        return model

    @classmethod
    def from_xml(cls, path, **kwargs) -> AsterModel:
        """Model from an ASP ``aster2asp`` XML file; keyword options as :class:`AsterModel`."""
        from stereodem.sensor.io.aster_xml import read_asp_aster_xml

        return cls(read_asp_aster_xml(path), **kwargs)

    def lattice_sight_errors(self):
        """Angle (rad) between the model's ECEF rays and the product's world sight vectors
        at every lattice point, shape (N, 11): the consistency check of notes §4.3."""
        g = self.geometry
        _, d = self.rays(g.lattice[..., 0], g.lattice[..., 1])
        w = g.world_sight_vectors
        cosang = np.clip(np.sum(d * w, axis=-1), -1.0, 1.0)
        sinang = np.linalg.norm(np.cross(d, w), axis=-1)
        return np.arctan2(sinang, cosang)


def _band_velocities(g: AsterGeometry, times, method):
    """Earth-fixed ECEF velocities at the lattice rows (see :class:`AsterModel`)."""
    if method != "file":
        return lattice_velocities(times, g.satellite_positions, method=method)
    if g.satellite_velocities is None or g.velocity_convention == "unknown":
        raise SensorModelError(
            f"{g.path or 'ASTER geometry'}: velocity_method='file' needs the "
            "product's SatelliteVelocity with a known convention"
        )
    v = np.asarray(g.satellite_velocities, dtype=np.float64)
    if g.velocity_convention == "inertial":
        v = v - np.cross([0.0, 0.0, geodesy.OMEGA_EARTH], g.satellite_positions)
    return v


def _rebuild_astermodel(d):
    return AsterModel.from_dict(d)
