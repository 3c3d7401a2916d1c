"""Accuracy assessment of a DEM against a reference DEM and against check points.

The DEM is warped onto the **reference grid** (bilinear; this is stated in the report), its
heights first converted to the reference's vertical datum (EGM96 geoid ↔ WGS84 ellipsoid).
Differences are ``dh = DEM − reference``. Statistics (:mod:`stereodem.post.stats`) are given for the
whole overlap, per slope class (slope of the reference DEM, degrees, metric even on lon/lat
grids), per land-cover class, per elevation band (reference heights), with the linear fit of
error against slope; optionally before and after Nuth & Kääb co-registration.
"""
from __future__ import annotations

import csv
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import rasterio

from stereodem.sensor.geo import geodesy
from stereodem.sensor.geo.dem import DEM, as_dem
from stereodem.sensor.errors import (CRSError, DEMError, InputError, NoOverlapError,
                           VerticalReferenceError)

from . import stats as st
from . import terrain, warp
from .coregister import NuthKaab

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------- vertical

def reconcile_vertical(dem: DEM, reference: DEM) -> tuple[DEM, str]:
    """Return ``dem`` in the vertical reference of ``reference`` and a note saying what was done.

    Raises :class:`VerticalReferenceError` when one reference is known and the other is not.
    When both are unknown they are assumed identical (and the note says so).
    """
    a, b = dem.vertical, reference.vertical
    if a == b:
        return dem, (f"both {a}" if a else "both unknown; assumed identical")
    if a is None or b is None:
        unknown = dem if a is None else reference
        raise VerticalReferenceError(
            f"{unknown.path or 'DEM'}: vertical reference unknown while the other is {a or b}; "
            "say which with --dem-vertical/--ref-vertical {geoid,ellipsoid}")
    return dem.to_reference(b), f"DEM converted from {a} to {b} (EGM96)"


# ----------------------------------------------------------------------------- results

@dataclass
class Comparison:
    """DEM and reference on the reference grid, and their difference."""

    dem: np.ndarray            #: DEM heights warped onto the reference grid (m)
    ref: np.ndarray            #: reference heights (m)
    dh: np.ndarray             #: DEM − reference (m), NaN where either is void
    slope: np.ndarray          #: slope of the reference (degrees)
    transform: object
    crs: object
    landcover: np.ndarray | None = None


@dataclass
class Assessment:
    """Result of :func:`assess_dem`: ``report`` (a JSON-ready dict) and the arrays behind it."""

    report: dict
    before: Comparison
    after: Comparison | None = None
    extra: dict = field(default_factory=dict)


def compare_on_reference_grid(dem: DEM, reference: DEM, *, resampling: str = "bilinear") -> Comparison:
    """Warp ``dem`` onto ``reference``'s grid (same vertical reference assumed) and difference.

    Raises :class:`NoOverlapError` if the footprints or the valid cells do not overlap.
    """
    warp.check_overlap(dem.bounds_lonlat(), reference.bounds_lonlat(),
                       dem.path or "DEM", reference.path or "reference")
    z = warp.to_grid(dem.heights, dem.transform, dem.crs, reference.transform, reference.crs,
                     reference.shape, resampling=resampling)
    ref = reference.heights
    dh = z.astype(np.float64) - ref.astype(np.float64)
    if not np.isfinite(dh).any():
        raise NoOverlapError(f"{dem.path or 'DEM'}: no valid cell overlaps a valid cell of "
                             f"{reference.path or 'the reference'}")
    slope = terrain.slope_deg(ref, reference.transform, reference.crs)
    return Comparison(z, ref, dh, slope, reference.transform, reference.crs)


def _read_landcover(landcover, reference: DEM):
    """Land-cover raster (path or (array, transform, crs[, nodata])) on the reference grid
    (nearest neighbour). Returns (classes float64 with NaN for nodata)."""
    if isinstance(landcover, (str, Path)):
        try:
            with rasterio.open(landcover) as ds:
                if ds.crs is None:
                    raise CRSError(f"{landcover}: the land-cover raster has no CRS")
                arr = ds.read(1).astype(np.float64)
                nod = ds.nodata
                if nod is not None:
                    arr[arr == nod] = np.nan
                t, crs = ds.transform, ds.crs.to_wkt()
        except rasterio.errors.RasterioIOError as exc:
            raise InputError(f"{landcover}: cannot read the land-cover raster ({exc})") from None
    else:
        arr, t, crs = np.asarray(landcover[0], dtype=np.float64), landcover[1], landcover[2]
    return warp.to_grid(arr, t, crs, reference.transform, reference.crs, reference.shape,
                        resampling="nearest", dst_dtype=np.float64)


def dem_footprint(z) -> np.ndarray:
    """Cells inside the footprint of a DEM: the convex hull of its valid cells (bool, the
    shape of ``z``). A stereo DEM covers the overlap of two image footprints, a convex
    quadrilateral, so the hull is that area with its interior voids counted in."""
    import cv2
    fin = np.isfinite(z)
    out = np.zeros(fin.shape, dtype=np.uint8)
    if fin.any():
        rows, cols = np.nonzero(fin)
        pts = np.stack([cols, rows], axis=1).astype(np.int32)
        cv2.fillConvexPoly(out, cv2.convexHull(pts), 1)
    return out.astype(bool) | fin


def comparison_stats(cmp: Comparison, *, slope_bins=st.DEFAULT_SLOPE_BINS, elevation_bins=None,
                     landcover_names: dict | None = None) -> dict:
    """The statistics block of a :class:`Comparison`: ``stats``, ``by_slope``,
    ``by_elevation``, ``by_landcover`` (if any), ``slope_fit`` and ``slope_class_trend``."""
    footprint = dem_footprint(cmp.dem) & np.isfinite(cmp.ref)
    out = {"stats": st.error_stats(cmp.dh, n_total=int(footprint.sum()))}
    out["by_slope"] = st.binned_stats(cmp.dh, cmp.slope, slope_bins, unit="deg", name="slope")
    ebins = elevation_bins if elevation_bins is not None else st.default_elevation_bins(cmp.ref)
    out["by_elevation"] = st.binned_stats(cmp.dh, cmp.ref, ebins, unit="m", name="elevation")
    out["by_landcover"] = (st.class_stats(cmp.dh, cmp.landcover, names=landcover_names)
                           if cmp.landcover is not None else None)
    out["slope_fit"] = st.error_vs_slope(cmp.dh, cmp.slope)
    out["slope_class_trend"] = st.class_trend(out["by_slope"], x_key="slope_mean", y_key="nmad")
    return out


def assess_dem(dem, reference, *, coregister: bool = False, landcover=None,
               landcover_names: dict | None = None, slope_bins=st.DEFAULT_SLOPE_BINS,
               elevation_bins=None, checkpoints=None, checkpoint_crs=None,
               checkpoint_vertical: str | None = None, dem_vertical: str | None = None,
               ref_vertical: str | None = None, resampling: str = "bilinear",
               coregistration: NuthKaab | None = None) -> Assessment:
    """Assess ``dem`` against ``reference`` (DEM objects or paths).

    Parameters
    ----------
    coregister : bool
        Also co-register with :class:`~stereodem.post.coregister.NuthKaab` and assess again; the report
        then has ``coregistration`` (``dx``, ``dy``, ``dz`` metres east/north/up) and
        ``after_coregistration``.
    landcover : path or (array, transform, crs)
        Integer classes; warped onto the reference grid by nearest neighbour.
    slope_bins, elevation_bins : sequence of edges
        Degrees and metres; elevation bands default to 5 bands over the reference range.
    checkpoints : path or (x, y, z) arrays, optional
        See :func:`assess_checkpoints`.
    dem_vertical, ref_vertical : {"geoid", "ellipsoid"}, optional
        Override the vertical references read from the files.
    """
    if dem_vertical is not None or isinstance(dem, (str, Path)):
        dem = as_dem(dem, vertical=dem_vertical) if isinstance(dem, (str, Path)) else \
            DEM(dem.heights, dem.transform, dem.crs, dem_vertical, dem.path)
    if ref_vertical is not None or isinstance(reference, (str, Path)):
        reference = as_dem(reference, vertical=ref_vertical) if isinstance(reference, (str, Path)) \
            else DEM(reference.heights, reference.transform, reference.crs, ref_vertical, reference.path)
    dem_v, vnote = reconcile_vertical(dem, reference)
    cmp = compare_on_reference_grid(dem_v, reference, resampling=resampling)
    if landcover is not None:
        cmp.landcover = _read_landcover(landcover, reference)
    report = {
        "dem": str(dem.path) if dem.path else None,
        "reference": str(reference.path) if reference.path else None,
        "grid": {"on": "reference", "resampling": resampling, "crs": reference.crs.to_string(),
                 "shape": list(reference.shape), "transform": list(reference.transform)[:6],
                 "pixel_size_m": _pixel_size_report(reference)},
        "vertical": {"dem": dem.vertical, "reference": reference.vertical, "note": vnote},
        "difference": "dem - reference (m)",
        "slope_bins_deg": [float(b) for b in slope_bins],
    }
    report.update(comparison_stats(cmp, slope_bins=slope_bins, elevation_bins=elevation_bins,
                                   landcover_names=landcover_names))
    result = Assessment(report, cmp)
    if checkpoints is not None:
        report["checkpoints"] = assess_checkpoints(dem, checkpoints, crs=checkpoint_crs,
                                                   vertical=checkpoint_vertical)
    else:
        report["checkpoints"] = None
    report["coregistration"] = None
    if coregister:
        nk = coregistration or NuthKaab()
        nk.fit(reference, dem_v)
        report["coregistration"] = dict(nk.params)
        shifted = nk.apply(dem_v)
        cmp2 = compare_on_reference_grid(shifted, reference, resampling=resampling)
        cmp2.landcover = cmp.landcover
        report["after_coregistration"] = comparison_stats(
            cmp2, slope_bins=slope_bins, elevation_bins=elevation_bins, landcover_names=landcover_names)
        if checkpoints is not None:
            sh = nk.apply(dem)          # shift in the DEM's own vertical reference
            report["after_coregistration"]["checkpoints"] = assess_checkpoints(
                sh, checkpoints, crs=checkpoint_crs, vertical=checkpoint_vertical)
        result.after = cmp2
    log.info("assessment: n=%d rmse=%.3f nmad=%.3f", report["stats"]["n"], report["stats"]["rmse"],
             report["stats"]["nmad"])
    return result


def _pixel_size_report(d: DEM):
    pe, pn = terrain.pixel_size_m(d.transform, d.crs, d.shape)
    mid = pe.shape[0] // 2
    return [float(abs(pe[mid, 0])), float(abs(pn[mid, 0]))]


# ----------------------------------------------------------------------------- check points

_LON = ("lon", "longitude", "long")
_LAT = ("lat", "latitude")
_X = ("x", "easting", "e")
_Y = ("y", "northing", "n")
_Z = ("height", "h", "z", "elevation", "alt", "altitude")


def read_checkpoints(path, *, crs=None):
    """Read check points from a CSV with a header.

    Columns ``lon``/``lat`` (degrees WGS84) or ``x``/``y`` (then ``crs`` is required), and
    ``height``/``h``/``z``; an ``id`` column is kept if present.

    Returns
    -------
    lon, lat, z : ndarray float64 ; ids : list of str
    """
    path = str(path)
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except OSError as exc:
        raise InputError(f"{path}: cannot read the check points ({exc.strerror})") from None
    except (UnicodeDecodeError, csv.Error):
        raise InputError(f"{path}: not a text CSV of check points (binary or garbled)") from None
    if not rows:
        raise InputError(f"{path}: no check point")
    cols = {c.strip().lower(): c for c in rows[0].keys() if c is not None}

    def pick(names):
        for n in names:
            if n in cols:
                return cols[n]
        return None

    cx, cy = pick(_LON), pick(_LAT)
    geographic = cx is not None and cy is not None
    if not geographic:
        cx, cy = pick(_X), pick(_Y)
    cz = pick(_Z)
    if cx is None or cy is None or cz is None:
        raise InputError(f"{path}: need columns lon,lat,height or x,y,z; got {list(cols)}")
    try:
        x = np.array([float(r[cx]) for r in rows])
        y = np.array([float(r[cy]) for r in rows])
        z = np.array([float(r[cz]) for r in rows])
    except (TypeError, ValueError) as exc:
        raise InputError(f"{path}: non-numeric check point coordinate ({exc})") from None
    cid = pick(("id", "name", "point"))
    ids = [r[cid] for r in rows] if cid else [str(i) for i in range(len(rows))]
    if geographic and crs is None:
        lon, lat = x, y
    else:
        if crs is None:
            raise CRSError(f"{path}: x/y check points need a CRS (--checkpoints-crs)")
        lon, lat = geodesy.crs_to_lonlat(x, y, crs)
    return np.asarray(lon, float), np.asarray(lat, float), z, ids


def assess_checkpoints(dem, checkpoints, *, crs=None, vertical: str | None = None) -> dict:
    """DEM − check point heights, the DEM sampled bilinearly at each point.

    Parameters
    ----------
    checkpoints : path or (lon, lat, z) arrays (degrees, metres)
    vertical : {"geoid", "ellipsoid"}, optional
        Vertical reference of the check-point heights; the DEM is converted to it. ``None``
        assumes the DEM's own reference (stated in the result).
    """
    dem = as_dem(dem)
    if isinstance(checkpoints, (str, Path)):
        lon, lat, z, ids = read_checkpoints(checkpoints, crs=crs)
    else:
        lon, lat, z = (np.asarray(a, dtype=np.float64) for a in checkpoints)
        if crs is not None:
            lon, lat = geodesy.crs_to_lonlat(lon, lat, crs)
        ids = [str(i) for i in range(lon.size)]
    if vertical is not None and dem.vertical is None:
        raise VerticalReferenceError(f"{dem.path or 'DEM'}: vertical reference unknown; check "
                                     f"points are {vertical} (give --dem-vertical)")
    hz, status = dem.sample(lon, lat, reference=vertical, return_status=True)
    dh = hz - z
    res = st.error_stats(dh)
    if res["n"] == 0:
        raise DEMError(f"{dem.path or 'DEM'}: none of the {lon.size} check points falls on a "
                       "valid DEM cell")
    note = f"check points {vertical}" if vertical else f"check points assumed {dem.vertical or 'same as DEM'}"
    return {"stats": res, "vertical": note, "sampling": "bilinear",
            "outside": int((status == 1).sum()), "on_void": int((status == 2).sum()),
            "points": [{"id": i, "lon": float(a), "lat": float(b), "z": float(c),
                        "dem": float(d) if np.isfinite(d) else None,
                        "dh": float(e) if np.isfinite(e) else None}
                       for i, a, b, c, d, e in zip(ids, lon, lat, z, hz, dh)]}
