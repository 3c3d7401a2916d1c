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
blunder filter or the border rim, or the N-view fusion rejected the point's pair height in its
cell), and extra dimensions ``ray_gap`` (m), ``score`` (correlation), ``source_pair`` and
``edit_code`` (the ``post.filters`` edit-mask code of the point's DEM cell: 0 kept, 1–9 filter
reason, 99 border rim; :data:`FUSION_REJECTED` (98) where the N-view fusion rejected the
point's pair height in the cell). With ``pairs`` given, the source pairs' image names are in a
VLR (user id ``stereodem``, record :data:`PAIRS_RECORD_ID`, JSON ``{"<id>": [left, right]}``).

An N-view job (:mod:`stereodem.multiview`) writes its pairs' points into one sub-folder per
pair and merges them all into one cloud (:func:`write_las_files`), each point's ``source_pair``
the id of its pair; ``edit_codes`` is then one mask per pair id (the fusion's rejections differ
from pair to pair).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from stereodem.core import geodesy
from stereodem.core.errors import InputError
from stereodem.core.raster import atomic_path, check_writable, crs_with_vertical

log = logging.getLogger(__name__)

__all__ = [
    "FORMATS",
    "FUSION_REJECTED",
    "PAIRS_RECORD_ID",
    "points_file",
    "read_pairs",
    "save_tile_points",
    "write_las",
    "write_las_files",
]

FORMATS = ("las", "laz")
#: LAS classes (ASPRS): kept points, and points in cells a filter removed
UNCLASSIFIED, NOISE = 1, 7
#: ``edit_code`` of a point whose pair height the N-view fusion rejected in its cell
#: (further than k x max(σ, NMAD) from the cell's median: :func:`stereodem.stereo.fusion.fuse_dems`)
FUSION_REJECTED = 98
#: record id of the VLR (user id ``stereodem``) holding the source pairs' image names
PAIRS_RECORD_ID = 1
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


def _header(grid, vertical, pairs=None):
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
    if pairs:
        text = json.dumps({str(int(k)): [str(n) for n in v] for k, v in dict(pairs).items()})
        header.vlrs.append(
            laspy.VLR(
                user_id="stereodem",
                record_id=PAIRS_RECORD_ID,
                description="source_pair: images (JSON)",
                record_data=text.encode(),
            )
        )
    return header


def read_pairs(las) -> dict:
    """The source pairs of a cloud read by laspy (``laspy.read``/``laspy.open(...).header``):
    ``{id: [left image, right image]}``, empty when the file has no such VLR."""
    header = getattr(las, "header", las)
    for v in header.vlrs:
        if getattr(v, "user_id", "") == "stereodem" and v.record_id == PAIRS_RECORD_ID:
            return {int(k): v for k, v in json.loads(bytes(v.record_data).decode()).items()}
    return {}


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
    pairs=None,
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
        The DEM's edit mask (``post.filters`` codes); points take their cell's code. Or
        ``(pair ids, rows, cols)``: one mask per pair id, a point taking its pair's.
    pairs : mapping, optional
        ``{pair id: (left image, right image)}``, written in a VLR (:func:`read_pairs`).

    Returns
    -------
    dict: path, format, n_points, missing_tiles, classes (counts per LAS class).
    """
    indices = [int(i) for i in tile_indices]
    files = [points_file(folder, i) for i in indices]
    summary = write_las_files(
        path,
        files,
        grid,
        vertical=vertical,
        edit_codes=edit_codes,
        fmt=fmt,
        overwrite=overwrite,
        pairs=pairs,
    )
    missing = set(summary.pop("missing_files"))
    summary["missing_tiles"] = [i for i, f in zip(indices, files) if str(f) in missing]
    return summary


def write_las_files(
    path,
    files,
    grid,
    *,
    vertical=None,
    edit_codes=None,
    fmt: str | None = None,
    overwrite: bool = False,
    pairs=None,
) -> dict:
    """:func:`write_las` from a list of point files (in order; a missing one is logged and
    listed in ``missing_files``), e.g. the tiles of several pairs."""
    laspy = _laspy()
    path = check_writable(path, overwrite)
    fmt = (fmt or path.suffix.lstrip(".")).lower()
    if fmt not in FORMATS:
        raise InputError(f"{path}: point cloud format must be las or laz, got {fmt!r}")
    codes_of = None
    if edit_codes is not None:
        codes_of = np.asarray(edit_codes)
        if codes_of.shape[-2:] != (grid.height, grid.width) or codes_of.ndim not in (2, 3):
            raise InputError(
                f"{path}: edit codes of shape {codes_of.shape} do not match the grid "
                f"({grid.height}, {grid.width})"
            )
    header = _header(grid, vertical, pairs)
    n_total, missing, n_rejected = 0, [], 0
    classes = {UNCLASSIFIED: 0, NOISE: 0}
    with atomic_path(path) as tmp:
        with laspy.open(tmp, mode="w", header=header, do_compress=(fmt == "laz")) as writer:
            for f in files:
                f = Path(f)
                if not f.exists():
                    missing.append(str(f))
                    continue
                with np.load(f) as p:
                    n = int(p["x"].size)
                    if n == 0:
                        continue
                    rec = laspy.ScaleAwarePointRecord.zeros(n, header=header)
                    rec.x, rec.y, rec.z = p["x"], p["y"], p["z"]
                    rec.ray_gap, rec.score = p["ray_gap"], p["score"]
                    pair = p["pair"]
                    rec.source_pair = pair
                    rec.point_source_id = pair
                    code = np.zeros(n, np.uint8)
                    if codes_of is not None:
                        col, row = grid.colrow(p["x"], p["y"])
                        c, r = np.rint(col).astype(np.int64), np.rint(row).astype(np.int64)
                        inside = (c >= 0) & (r >= 0) & (c < grid.width) & (r < grid.height)
                        if codes_of.ndim == 3:
                            inside &= pair.astype(np.int64) < codes_of.shape[0]
                            at = (pair[inside].astype(np.int64), r[inside], c[inside])
                        else:
                            at = (r[inside], c[inside])
                        code[inside] = codes_of[at].astype(np.uint8)
                    rec.edit_code = code
                    n_rejected += int((code == FUSION_REJECTED).sum())
                    # removed by a filter (reasons 1-9), rejected by the fusion (98) or the
                    # border rim (99); filled cells (100, 101) have no points of their own
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
    out = dict(
        path=str(path),
        format=fmt,
        n_points=n_total,
        missing_files=missing,
        classes={"unclassified (kept)": classes[UNCLASSIFIED], "noise (filtered)": classes[NOISE]},
        crs=grid.crs.to_string(),
        vertical=vertical,
    )
    if n_rejected:
        out["classes"]["of which rejected by the N-view fusion"] = n_rejected
    if pairs:
        out["pairs"] = {str(int(k)): [str(n) for n in v] for k, v in dict(pairs).items()}
    return out
