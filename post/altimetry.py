"""Altimetry points as a co-registration reference (ICESat-2 ATL06-like): lon, lat, h[, time].

Read from CSV (columns ``lon``/``longitude``, ``lat``/``latitude``, ``h``/``h_li``/``height``/
``elevation``, optional ``time``) or GeoParquet (the same columns, or a point geometry for
lon/lat; needs ``pyarrow``). Heights are metres above the ``vertical`` reference, which must
be said (``ellipsoid`` for ICESat-2) unless the file's column is named ``h_ellipsoid`` or
``h_geoid``: points in an unsaid datum are refused rather than guessed. What the column says
wins over a ``vertical`` given, with a warning naming the file, by the rule of DEM files
(:func:`stereodem.core.dem.said_vertical`).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import shapely

from stereodem.core import geodesy
from stereodem.core.dem import said_vertical
from stereodem.core.errors import InputError, VerticalReferenceError, not_found
from stereodem.core.vertical import ELLIPSOID, GEOID

_LON = ("lon", "longitude", "x_lon")
_LAT = ("lat", "latitude", "y_lat")
_H = ("h", "h_li", "height", "elevation", "h_ellipsoid", "h_geoid", "z")
_T = ("time", "t", "delta_time", "date")
#: how a point file whose height column says the wrong reference is mended
_MEND = "a mislabelled file is mended by renaming its height column (h, h_ellipsoid, h_geoid)"


@dataclass
class AltimetryPoints:
    """Point heights: ``lon``, ``lat`` (degrees WGS84), ``h`` (metres, ``vertical``
    reference), optional ``time`` (any numeric or datetime64 array)."""

    lon: np.ndarray
    lat: np.ndarray
    h: np.ndarray
    time: np.ndarray | None = None
    vertical: str | None = None
    path: str | None = None

    def __post_init__(self):
        self.lon = np.asarray(self.lon, np.float64).ravel()
        self.lat = np.asarray(self.lat, np.float64).ravel()
        self.h = np.asarray(self.h, np.float64).ravel()
        where = f"{self.path}: " if self.path else ""
        if not (self.lon.size == self.lat.size == self.h.size):
            raise InputError(f"{where}lon, lat and h differ in length")
        if self.lon.size == 0:
            raise InputError(f"{where}no point")
        bad = ~(np.isfinite(self.lon) & np.isfinite(self.lat) & np.isfinite(self.h))
        if bad.any():
            raise InputError(
                f"{where}{int(bad.sum())} of {bad.size} points have NaN/inf lon, "
                f"lat or h (first at row {int(np.flatnonzero(bad)[0])}); drop them first"
            )
        if np.any(np.abs(self.lat) > 90) or np.any(np.abs(self.lon) > 360):
            raise InputError(f"{where}lon/lat out of range: are the coordinates projected?")
        if self.vertical not in (None, GEOID, ELLIPSOID):
            raise InputError(
                f"{where}vertical reference must be 'geoid' or 'ellipsoid', got {self.vertical!r}"
            )

    def __len__(self):
        return self.h.size

    def to_reference(self, to: str) -> AltimetryPoints:
        """Heights converted to ``to`` (EGM96 geoid or WGS84 ellipsoid)."""
        if self.vertical == to:
            return self
        if self.vertical is None:
            raise VerticalReferenceError(
                f"{self.path or 'points'}: vertical reference unknown; "
                "say which (--ref-vertical geoid|ellipsoid)"
            )
        h = (
            geodesy.geoid_to_ellipsoid(self.lon, self.lat, self.h)
            if to == ELLIPSOID
            else geodesy.ellipsoid_to_geoid(self.lon, self.lat, self.h)
        )
        return AltimetryPoints(self.lon, self.lat, h, self.time, to, self.path)

    def subset(self, keep) -> AltimetryPoints:
        return AltimetryPoints(
            self.lon[keep],
            self.lat[keep],
            self.h[keep],
            None if self.time is None else np.asarray(self.time)[keep],
            self.vertical,
            self.path,
        )


def is_points_file(path) -> bool:
    """True for ``.csv``/``.txt``/``.parquet``/``.geoparquet`` files."""
    return Path(str(path)).suffix.lower() in (".csv", ".txt", ".parquet", ".geoparquet", ".pq")


def _pick(columns, names, path, what, required=True):
    low = {c.lower(): c for c in columns}
    for n in names:
        if n in low:
            return low[n]
    if required:
        raise InputError(
            f"{path}: no {what} column (expected one of {', '.join(names)}); "
            f"columns are {', '.join(map(str, columns))}"
        )
    return None


def _read_csv(path):
    """Columns of a CSV file with a header line (``#`` comment and blank lines skipped): name
    -> array of strings, and the file's line number (1-based) of each data row."""
    with open(path, newline="", encoding="utf-8") as f:
        numbered = [
            (k, line)
            for k, line in enumerate(f, 1)
            if line.strip() and not line.lstrip().startswith("#")
        ]
    rows = list(csv.reader(line for _, line in numbered))
    lines = [k for k, _ in numbered]
    if len(rows) < 2:
        raise InputError(f"{path}: no header and data rows in the CSV file")
    head = [h.strip() for h in rows[0]]
    body, lines = rows[1:], lines[1:]
    bad = next((i for i, r in enumerate(body) if len(r) != len(head)), None)
    if bad is not None:
        raise InputError(
            f"{path}: line {lines[bad]} has {len(body[bad])} fields, the header {len(head)}"
        )
    cols = list(zip(*body))
    return {h: np.asarray(c, dtype=object) for h, c in zip(head, cols)}, lines


def _read_parquet(path):
    """Columns of a (Geo)Parquet file: name -> numpy array; a WKB ``geometry`` column stays
    bytes objects."""
    try:
        import pyarrow.parquet as pq
    except ImportError:
        raise InputError(
            f"{path}: reading GeoParquet needs pyarrow (pip install 'stereodem[altimetry]')"
        ) from None
    table = pq.read_table(path)
    return {name: table.column(name).to_numpy(zero_copy_only=False) for name in table.column_names}


def _where(lines, i) -> str:
    """Where data row ``i`` (0-based) is: its CSV line, or its row in a Parquet table."""
    return f"line {lines[i]}" if lines is not None else f"row {i + 1}"


def _numbers(col, path, name, lines=None):
    try:
        return np.asarray(col, dtype=np.float64)
    except (TypeError, ValueError):
        out = np.full(len(col), np.nan)
        for i, v in enumerate(col):  # per value only to name the bad one
            try:
                out[i] = float(v)
            except (TypeError, ValueError):
                raise InputError(
                    f"{path}: column {name!r}, {_where(lines, i)}: {v!r} is not a number"
                ) from None
        return out


def read_points(path, *, vertical: str | None = None) -> AltimetryPoints:
    """Read altimetry points from CSV or GeoParquet (see the module docstring).

    ``vertical`` (``"geoid"``: EGM96, ``"ellipsoid"``: WGS84) is the reference of heights
    whose column does not say it; a column that says it (``h_ellipsoid``, ``h_geoid``) wins,
    a contradicting ``vertical`` being logged as a warning naming the file
    (:func:`stereodem.core.dem.said_vertical`, the rule of DEM files); neither is a
    :class:`VerticalReferenceError` (points are not compared in an unknown datum)."""
    path = str(path)
    suffix = Path(path).suffix.lower()
    if not Path(path).is_file():
        raise InputError(not_found(path, "points"))
    try:
        if suffix in (".parquet", ".geoparquet", ".pq"):
            cols, lines = _read_parquet(path), None
        else:
            cols, lines = _read_csv(path)
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - any garbled file: one line
        raise InputError(f"{path}: cannot read the points ({type(exc).__name__}: {exc})") from None
    names = list(cols)
    lon_c = _pick(names, _LON, path, "longitude", required=False)
    if lon_c is None and "geometry" in names:
        geom = shapely.from_wkb(cols["geometry"])
        lon, lat = shapely.get_x(geom), shapely.get_y(geom)
    else:
        lon = _numbers(cols[_pick(names, _LON, path, "longitude")], path, "lon", lines)
        lat = _numbers(cols[_pick(names, _LAT, path, "latitude")], path, "lat", lines)
    hc = _pick(names, _H, path, "height")
    h = _numbers(cols[hc], path, hc, lines)
    bad = ~(np.isfinite(lon) & np.isfinite(lat) & np.isfinite(h))
    if bad.any():  # here, where the file's lines are known
        raise InputError(
            f"{path}: {int(bad.sum())} of {bad.size} points have NaN/inf lon, lat or h "
            f"(first at {_where(lines, int(np.flatnonzero(bad)[0]))}); drop them first"
        )
    tc = _pick(names, _T, path, "time", required=False)
    said = {"h_ellipsoid": ELLIPSOID, "h_geoid": GEOID}.get(hc.lower())
    vert = said_vertical(path, said, vertical, said_by=f" (column {hc!r})", mend=_MEND)
    if vert is None:
        raise VerticalReferenceError(
            f"{path}: vertical reference of the point heights not said; "
            "give --ref-vertical geoid|ellipsoid (ICESat-2: ellipsoid)"
        )
    return AltimetryPoints(lon, lat, h, None if tc is None else cols[tc], vert, path)


def residuals_table(points: AltimetryPoints, dem_heights_at_points, used) -> dict:
    """Per-point residuals (DEM − point, metres) as JSON-ready columns."""
    r = np.asarray(dem_heights_at_points, float) - points.h
    return {
        "lon": points.lon.tolist(),
        "lat": points.lat.tolist(),
        "h": points.h.tolist(),
        "dh": [None if not np.isfinite(v) else float(v) for v in r],
        "used": np.asarray(used, bool).tolist(),
    }
