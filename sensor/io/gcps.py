"""Ground control and check point files (CSV).

Format: a header ``id,lon,lat,h,col,row`` plus the optional columns

* ``sigma_px`` — a-priori standard deviation of the measured image coordinates (pixels, the
  same for col and row);
* ``sigma_ground_m`` — a-priori standard deviation of each ground coordinate (metres, the same
  for east, north and up); a point with it is a GCP whose ground coordinates are observations
  too (Gauss–Helmert model, :mod:`stereodem.sensor.estimation.adjust.gauss_helmert`);
* ``role`` — ``gcp`` (used in the estimation, default) or ``check`` (independent check point,
  never used by it).

``lon``/``lat`` are degrees (WGS84), ``h`` ellipsoidal metres (or EGM96 heights with
``vertical="geoid"``), ``col``/``row`` pixels with the centre of the top-left pixel at (0, 0),
as everywhere in the project. Empty optional cells mean "not given" (NaN).
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass, fields

import numpy as np

from stereodem.core import geodesy
from stereodem.core.errors import InputError, not_found, where
from stereodem.core.raster import write_text_atomic

__all__ = [
    "ControlPoints",
    "csv_rows",
    "read_gcps",
    "parse_roles",
    "write_gcps",
    "GCP_COLUMNS",
    "OPTIONAL_COLUMNS",
]

#: required columns, in order
GCP_COLUMNS = ("id", "lon", "lat", "h", "col", "row")
#: optional columns
OPTIONAL_COLUMNS = ("sigma_px", "sigma_ground_m", "role")
ROLES = ("gcp", "check")


def parse_roles(values, where: str = "") -> np.ndarray:
    """A ``role`` column's values as :data:`ROLES` (case and spaces ignored; empty is
    ``gcp``); an unknown role is an :class:`InputError` (``where``: its prefix, e.g.
    ``"pts.csv: "``). The one rule of every reader of point CSVs with roles."""
    role = np.array([(v or "").strip().lower() or "gcp" for v in values], dtype=str)
    unknown = sorted(set(role) - set(ROLES))
    if unknown:
        raise InputError(f"{where}unknown role(s) {', '.join(unknown)} (expected gcp or check)")
    return role


@dataclass
class ControlPoints:
    """Ground control / check points.

    Attributes
    ----------
    id, role : ndarray of str (n,)
        Point identifiers (unique) and roles (``gcp`` or ``check``).
    lon, lat : ndarray (n,)
        Degrees, WGS84.
    h : ndarray (n,)
        Metres above the WGS84 ellipsoid.
    col, row : ndarray (n,)
        Measured image coordinates, pixels (centre of the top-left pixel at (0, 0)).
    sigma_px, sigma_ground_m : ndarray (n,)
        A-priori standard deviations of the image (px) and ground (m) coordinates; NaN where
        not given.
    """

    id: np.ndarray
    lon: np.ndarray
    lat: np.ndarray
    h: np.ndarray
    col: np.ndarray
    row: np.ndarray
    role: np.ndarray = None
    sigma_px: np.ndarray = None
    sigma_ground_m: np.ndarray = None

    def __post_init__(self):
        self.id = np.asarray(self.id).astype(str).ravel()
        n = self.id.size
        for k in ("lon", "lat", "h", "col", "row"):
            setattr(self, k, np.asarray(getattr(self, k), dtype=np.float64).ravel())
        self.role = (
            np.full(n, "gcp", dtype="U16")
            if self.role is None
            else np.broadcast_to(np.asarray(self.role).astype("U16"), (n,)).copy()
        )
        for k in ("sigma_px", "sigma_ground_m"):
            v = getattr(self, k)
            v = np.full(n, np.nan) if v is None else np.asarray(v, dtype=np.float64)
            setattr(self, k, np.broadcast_to(v, (n,)).astype(np.float64).copy())
        sizes = {k: getattr(self, k).size for k in ("lon", "lat", "h", "col", "row")}
        if any(s != n for s in sizes.values()):
            raise InputError(
                f"control points: arrays of different lengths (id {n}, "
                + ", ".join(f"{k} {s}" for k, s in sizes.items())
                + ")"
            )

    def __len__(self):
        return int(self.lon.size)

    def subset(self, mask) -> ControlPoints:
        """The points where ``mask`` (boolean or index array) selects."""
        return ControlPoints(**{f.name: getattr(self, f.name)[mask] for f in fields(self)})

    def select(self, role: str) -> ControlPoints:
        """The points of one role (``"gcp"`` or ``"check"``)."""
        return self.subset(self.role == role)

    def arrays(self):
        """``(lon, lat, h, col, row)``, e.g. for
        :func:`stereodem.sensor.models.generic.fit_model`."""
        return self.lon, self.lat, self.h, self.col, self.row

    @classmethod
    def from_arrays(
        cls, lon, lat, h, col, row, *, ids=None, role=None, sigma_px=None, sigma_ground_m=None
    ) -> ControlPoints:
        """Build from arrays; ids default to ``P001, P002, ...``."""
        n = np.asarray(lon).size
        ids = [f"P{i + 1:03d}" for i in range(n)] if ids is None else ids
        return cls(ids, lon, lat, h, col, row, role, sigma_px, sigma_ground_m)


def _numbers(path, col_of, k, *, required):
    try:
        a = np.array([s.strip() or "nan" for s in col_of[k]], dtype=np.float64)
    except ValueError:
        raise InputError(f"{where(path)}non-numeric value in column '{k}'") from None
    if required:
        bad = np.flatnonzero(~np.isfinite(a))
        if bad.size:
            raise InputError(
                f"{where(path)}{bad.size} missing/NaN value(s) in column '{k}' "
                f"(first at line {bad[0] + 2})"
            )
    elif np.any(np.isinf(a)) or np.any(a[np.isfinite(a)] <= 0):
        raise InputError(f"{where(path)}column '{k}' must hold positive standard deviations")
    return a


def csv_rows(path, what: str) -> list:
    """The non-blank rows (lists of strings) of the CSV file ``path``, read as UTF-8 (a leading
    byte-order mark, as spreadsheets write, is dropped). An unreadable file, or one that is not
    UTF-8 text (binary, another encoding, NUL bytes), raises :class:`InputError` naming the
    file and ``what`` it should be."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            text = f.read()
        rows = list(csv.reader(io.StringIO(text)))
    except FileNotFoundError:
        raise InputError(not_found(path, what)) from None
    except OSError as exc:
        raise InputError(f"{where(path)}cannot read the {what} ({exc.strerror})") from None
    except (UnicodeDecodeError, csv.Error):
        raise InputError(
            f"{where(path)}not a UTF-8 text CSV (binary or another encoding); expected a {what}"
        ) from None
    return [r for r in rows if r and any(c.strip() for c in r)]


def read_gcps(path, *, vertical: str = "ellipsoid") -> ControlPoints:
    """Read a GCP/check-point CSV (see the module docstring).

    Parameters
    ----------
    path : str or Path
    vertical : {"ellipsoid", "geoid"}
        Reference of the ``h`` column; ``"geoid"`` converts EGM96 heights to ellipsoidal ones
        (:func:`stereodem.core.geodesy.geoid_to_ellipsoid`).

    Raises
    ------
    InputError
        Missing file or column, non-numeric or NaN values, latitudes beyond +-90 degrees
        (saying when the columns look swapped), duplicate ids, unknown roles, non-positive
        sigmas.
    """
    if vertical not in ("ellipsoid", "geoid"):
        raise InputError(f"{where(path)}vertical must be 'ellipsoid' or 'geoid', got {vertical!r}")
    rows = csv_rows(path, "GCP file")
    if not rows:
        raise InputError(f"{where(path)}empty GCP file")
    header = [c.strip().lower() for c in rows[0]]
    missing = [c for c in GCP_COLUMNS if c not in header]
    if missing:
        raise InputError(
            f"{where(path)}missing GCP column(s) {', '.join(missing)} (expected "
            f"{','.join(GCP_COLUMNS)}[,{','.join(OPTIONAL_COLUMNS)}])"
        )
    body = rows[1:]
    if not body:
        raise InputError(f"{where(path)}no points in GCP file")
    width = len(header)
    short = [i + 2 for i, r in enumerate(body) if len(r) < width]
    if short:
        raise InputError(f"{where(path)}line {short[0]} has fewer than {width} fields")
    table = np.array([r[:width] for r in body], dtype=object).T
    col_of = {k: table[header.index(k)] for k in header}
    values = {
        k: _numbers(path, col_of, k, required=True) for k in ("lon", "lat", "h", "col", "row")
    }
    opt = {
        k: (_numbers(path, col_of, k, required=False) if k in col_of else None)
        for k in ("sigma_px", "sigma_ground_m")
    }
    lon, lat = values["lon"], values["lat"]
    bad_lat = np.flatnonzero(np.abs(lat) > 90)
    if bad_lat.size or np.any(np.abs(lon) > 360):
        swapped = np.all(np.abs(lon) <= 90) and np.all(np.abs(lat) <= 360)
        i = int(bad_lat[0]) if bad_lat.size else int(np.flatnonzero(np.abs(lon) > 360)[0])
        raise InputError(
            f"{where(path)}line {i + 2}: lat {lat[i]:g} / lon {lon[i]:g} out of range"
            + (" (likely swapped lon/lat columns)" if swapped else "")
        )
    ids = np.array([s.strip() for s in col_of["id"]], dtype=str)
    empty = np.flatnonzero(ids == "")
    if empty.size:
        raise InputError(f"{where(path)}empty id at line {empty[0] + 2}")
    uniq, counts = np.unique(ids, return_counts=True)
    if np.any(counts > 1):
        dup = uniq[counts > 1]
        raise InputError(
            f"{where(path)}duplicate point id(s) {', '.join(dup[:5])}"
            + (" ..." if dup.size > 5 else "")
        )
    if "role" in col_of:
        role = parse_roles(col_of["role"], where(path))
    else:
        role = np.full(ids.shape, "gcp")
    h = values["h"]
    if vertical == "geoid":
        h = geodesy.geoid_to_ellipsoid(lon, lat, h)
    return ControlPoints(
        ids, lon, lat, h, values["col"], values["row"], role, opt["sigma_px"], opt["sigma_ground_m"]
    )


def write_gcps(
    path,
    ids,
    lon=None,
    lat=None,
    h=None,
    col=None,
    row=None,
    *,
    role=None,
    sigma_px=None,
    sigma_ground_m=None,
    overwrite=False,
):
    """Write points in the CSV format read by :func:`read_gcps` (atomic write).

    ``ids`` may also be a :class:`ControlPoints` (then the other arrays are taken from it).
    Optional columns are written only when given (for a ``ControlPoints``: when any value is
    set); NaN sigmas are written as empty cells.
    """
    if isinstance(ids, ControlPoints):
        p = ids
        ids, lon, lat, h, col, row, role = p.id, p.lon, p.lat, p.h, p.col, p.row, p.role
        sigma_px = p.sigma_px if np.any(np.isfinite(p.sigma_px)) else None
        sigma_ground_m = p.sigma_ground_m if np.any(np.isfinite(p.sigma_ground_m)) else None
    lon, lat, h, col, row = (
        np.asarray(a, dtype=np.float64).ravel() for a in (lon, lat, h, col, row)
    )
    ids = np.asarray(ids).astype(str).ravel()
    cols = [
        ids,
        np.char.mod("%.10f", lon),
        np.char.mod("%.10f", lat),
        np.char.mod("%.4f", h),
        np.char.mod("%.6f", col),
        np.char.mod("%.6f", row),
    ]
    header = list(GCP_COLUMNS)
    for name, s in (("sigma_px", sigma_px), ("sigma_ground_m", sigma_ground_m)):
        if s is not None:
            s = np.broadcast_to(np.asarray(s, dtype=np.float64), ids.shape)
            cols.append(np.where(np.isfinite(s), np.char.mod("%.6g", s), ""))
            header.append(name)
    if role is not None:
        cols.append(np.broadcast_to(np.asarray(role).astype(str), ids.shape))
        header.append("role")
    lines = [",".join(header)] + [",".join(r) for r in zip(*cols)]
    return write_text_atomic(path, "\n".join(lines) + "\n", overwrite=overwrite)
