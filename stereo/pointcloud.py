"""The stereo points as a point cloud (ASP ``point2las``): per-tile point files, merged into one
LAS/LAZ in chunks.

Each stereo tile, when asked (``PairInputs.points_dir``), writes its intersected points to
``points_<tile index>.npz`` in the tile cache (:func:`save_tile_points`, atomic): x, y in the
DEM lattice's CRS, z in its vertical reference (ellipsoid, or EGM96 geoid with
``[gridding] geoid``), the matching score, the ray gap (m) and the source pair. At the end
:func:`write_las` reads them back one tile at a time, in tile order, and appends each to one
LAS 1.4 file through laspy's chunked writer (LAZ through lazrs), so the main process never
holds more than one tile's points.

LAS content: point format 6, x/y/z scaled at 1 mm (1e-8° on geographic grids), the CRS
(horizontal + vertical, as the DEM's GeoTIFF says it) in a WKT VLR, ``point_source_id`` = the
source pair, ``classification`` 1 (unclassified: kept) or 7 (noise: the cell was removed by a
blunder filter or the border rim), and extra dimensions ``ray_gap`` (m), ``score``
(correlation), ``source_pair`` and ``edit_code`` (the ``post.filters`` edit-mask code of the
point's DEM cell: 0 kept, 1–8 filter reason, 99 border rim).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from stereodem.core import geodesy
from stereodem.core.errors import InputError
from stereodem.core.raster import atomic_path, check_writable, crs_with_vertical

log = logging.getLogger(__name__)

__all__ = ["FORMATS", "points_file", "save_tile_points", "write_las"]

FORMATS = ("las", "laz")
#: LAS classes (ASPRS): kept points, and points in cells a filter removed
UNCLASSIFIED, NOISE = 1, 7
_EXTRA = (
    ("ray_gap", np.float32, "ray gap (m)"),
    ("score", np.float32, "matching score"),
    ("source_pair", np.uint16, "stereo pair index"),
    ("edit_code", np.uint8, "DEM edit code"),
)


def points_file(folder, index: int) -> Path:
    """The point file of tile ``index`` in ``folder``."""
    return Path(folder) / f"points_{int(index):05d}.npz"


def save_tile_points(
    folder, index: int, lon, lat, h, score, ray_gap, *, crs, geoid: bool = False, pair: int = 0
) -> Path:
    """Write one tile's points (lon/lat degrees, h metres above the ellipsoid) as x, y in
    ``crs`` and z in the DEM's vertical reference (``geoid``: EGM96), atomically."""
    lon, lat, h = (np.asarray(v, dtype=np.float64) for v in (lon, lat, h))
    x, y = geodesy.lonlat_to_crs(lon, lat, crs) if lon.size else (lon, lat)
    z = geodesy.ellipsoid_to_geoid(lon, lat, h) if (geoid and lon.size) else h
    path = points_file(folder, index)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(
            f,
            x=np.asarray(x, np.float64),
            y=np.asarray(y, np.float64),
            z=np.asarray(z, np.float64),
            score=np.asarray(score, np.float32),
            ray_gap=np.asarray(ray_gap, np.float32),
            pair=np.full(lon.shape, int(pair), np.uint16),
        )
    return path


def _laspy():
    try:
        import laspy
    except ImportError:  # pragma: no cover - optional extra
        raise InputError(
            "point clouds need laspy and lazrs (pip install 'stereodem[pointcloud]')"
        ) from None
    return laspy


def _header(grid, vertical):
    laspy = _laspy()
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.add_extra_dims(
        [laspy.ExtraBytesParams(name=n, type=t, description=d) for n, t, d in _EXTRA]
    )
    w, s, _, _ = grid.bounds
    xy_scale = 1e-8 if grid.crs.is_geographic else 1e-3
    header.scales = np.array([xy_scale, xy_scale, 1e-3])
    header.offsets = np.array([np.floor(w), np.floor(s), 0.0])
    header.add_crs(crs_with_vertical(grid.crs, vertical))
    header.generating_software = "stereodem"
    return header


def write_las(
    path,
    folder,
    tile_indices,
    grid,
    *,
    vertical=None,
    edit_codes=None,
    fmt: str | None = None,
    overwrite: bool = False,
) -> dict:
    """Merge the tiles' point files into one LAS/LAZ, one tile at a time.

    Parameters
    ----------
    path : path
        ``.las`` or ``.laz`` (``fmt`` overrides the extension).
    folder : path
        Where the tiles wrote ``points_<index>.npz``.
    tile_indices : iterable of int
        Tiles, in order; a tile without a point file is named in the log and counted.
    grid : MapGrid
        The DEM's grid: its CRS is the cloud's, and ``edit_codes`` lies on it.
    vertical : {"geoid", "ellipsoid"}
        Vertical reference of z (put in the CRS).
    edit_codes : ndarray (rows, cols) of int, optional
        The DEM's edit mask (``post.filters`` codes); points take their cell's code.

    Returns
    -------
    dict: path, format, n_points, missing_tiles, classes (counts per LAS class).
    """
    laspy = _laspy()
    path = check_writable(path, overwrite)
    fmt = (fmt or path.suffix.lstrip(".")).lower()
    if fmt not in FORMATS:
        raise InputError(f"{path}: point cloud format must be las or laz, got {fmt!r}")
    header = _header(grid, vertical)
    n_total, missing = 0, []
    classes = {UNCLASSIFIED: 0, NOISE: 0}
    with atomic_path(path) as tmp:
        with laspy.open(tmp, mode="w", header=header, do_compress=(fmt == "laz")) as writer:
            for index in tile_indices:
                f = points_file(folder, index)
                if not f.exists():
                    missing.append(int(index))
                    continue
                with np.load(f) as p:
                    n = int(p["x"].size)
                    if n == 0:
                        continue
                    rec = laspy.ScaleAwarePointRecord.zeros(n, header=header)
                    rec.x, rec.y, rec.z = p["x"], p["y"], p["z"]
                    rec.ray_gap, rec.score = p["ray_gap"], p["score"]
                    rec.source_pair = p["pair"]
                    rec.point_source_id = p["pair"]
                    code = np.zeros(n, np.uint8)
                    if edit_codes is not None:
                        col, row = grid.colrow(p["x"], p["y"])
                        c, r = np.rint(col).astype(np.int64), np.rint(row).astype(np.int64)
                        inside = (c >= 0) & (r >= 0) & (c < grid.width) & (r < grid.height)
                        code[inside] = np.asarray(edit_codes)[r[inside], c[inside]].astype(np.uint8)
                    rec.edit_code = code
                    # removed by a filter (reasons 1-8) or the border rim (99); filled cells
                    # (100, 101) have no points of their own
                    noise = (code >= 1) & (code <= 99)
                    rec.classification = np.where(noise, NOISE, UNCLASSIFIED).astype(np.uint8)
                    classes[NOISE] += int(noise.sum())
                    classes[UNCLASSIFIED] += int(n - noise.sum())
                writer.write_points(rec)
                n_total += n
    if missing:
        log.warning(
            "%d tile(s) have no point file (cached by a run without a point cloud?): "
            "their points are missing from %s",
            len(missing),
            path,
        )
    return dict(
        path=str(path),
        format=fmt,
        n_points=n_total,
        missing_tiles=missing,
        classes={"unclassified (kept)": classes[UNCLASSIFIED], "noise (filtered)": classes[NOISE]},
        crs=grid.crs.to_string(),
        vertical=vertical,
    )
