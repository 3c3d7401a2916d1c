"""The point-cloud product of ``stereodem dem`` / ``stereodem run`` (``--point-cloud las|laz``,
``[dem] point_cloud``): where the tiles write their points, and the merge into ``dem.las`` /
``dem.laz`` (:mod:`stereodem.stereo.pointcloud`).

The tiles write ``OUT/tiles/points/points_<index>.npz``; the merge reads them one tile at a
time (memory: one tile's points) and removes them once the LAS/LAZ is in place, unless the
job keeps its tile cache for a later ``--resume`` (``stereodem run``, ``[run] keep_tiles``):
the points then stay beside the cached tiles, and a resumed run merges them again. A cached
tile whose point file is gone is recomputed (:func:`stereodem.stereo.execution.tile_runner`).

An N-view job (:mod:`stereodem.multiview`) gives each chosen pair an id (its rank in the pair
plan, ``pair_id`` in ``dem_report.json``) and a folder ``OUT/tiles/points/pair_<id>/``;
:func:`multiview_point_cloud_stage` merges the matched pairs' points into ONE cloud, each point's
``source_pair`` (and LAS ``point_source_id``) its pair's id, the pair list (id -> images) in a
VLR and in the report, and the points whose pair height the fusion rejected in their cell
classified as noise (edit code :data:`~stereodem.stereo.pointcloud.FUSION_REJECTED`).
"""

from __future__ import annotations

import contextlib
import logging
import shutil
from pathlib import Path

import numpy as np

from stereodem.stereo.pointcloud import FUSION_REJECTED, write_las, write_las_files

log = logging.getLogger(__name__)


def points_dir(out) -> Path:
    """Where the tiles of a job in ``out`` write their points."""
    return Path(out) / "tiles" / "points"


def pair_points_dir(points: Path, pair_id: int) -> Path:
    """The folder of N-view pair ``pair_id``'s points inside a job's points folder."""
    return Path(points) / f"pair_{int(pair_id)}"


def prepare(out, *, resume: bool = False) -> Path:
    """The points folder, emptied of an earlier job's files unless ``resume``."""
    d = points_dir(out)
    if d.exists() and not resume:
        shutil.rmtree(d)
    d.mkdir(parents=True, exist_ok=True)
    return d


def point_cloud_stage(
    cfg, out, products, edit_codes=None, *, grid=None, pairs=None, keep=False
) -> dict:
    """Merge the tiles' points into ``OUT/dem.<las|laz>``; returns its summary (for the
    reports). ``edit_codes``: the DEM's edit mask on ``grid`` (default the raw DEM's grid)
    for the points' classification; ``pairs``: ``{0: (left, right)}`` for the cloud's pair VLR;
    ``keep``: leave the tiles' point files for a later ``--resume``."""
    fmt = cfg.dem.point_cloud
    d = points_dir(out)
    indices = sorted(int(p.stem.split("_")[1]) for p in d.glob("points_*.npz"))
    g = grid if grid is not None else products.dem.grid
    summary = write_las(
        Path(out) / f"dem.{fmt}",
        d,
        indices,
        g,
        vertical=products.dem.vertical,
        edit_codes=edit_codes,
        fmt=fmt,
        overwrite=True,
        pairs=pairs,
    )
    expected = len(products.tiles)
    summary["tiles_with_points"] = len(indices)
    if len(indices) < expected:
        log.warning(
            "%d of %d tiles left no point file: their points are not in %s",
            expected - len(indices),
            expected,
            summary["path"],
        )
    if not keep:
        _clean(d)
    return summary


def _clean(d: Path) -> None:
    shutil.rmtree(d, ignore_errors=True)
    with contextlib.suppress(OSError):
        d.parent.rmdir()  # the tile cache folder, when nothing else is cached


def multiview_point_cloud_stage(
    cfg, out, grid, vertical, pairs, rejected=None, edit_codes=None, *, keep=False
) -> dict:
    """Merge the N-view pairs' points into ``OUT/dem.<las|laz>``; returns its summary.

    Parameters
    ----------
    grid : MapGrid
        The fused DEM's grid (its CRS is the cloud's; ``rejected`` and ``edit_codes`` lie on it).
    vertical : {"geoid", "ellipsoid"}
        Vertical reference of the heights.
    pairs : dict
        ``{pair id: (left image, right image)}`` of the matched pairs, in fusion order (the
        order of ``rejected``'s first axis).
    rejected : ndarray (len(pairs), rows, cols) of bool, optional
        Where the fusion rejected each pair's height
        (:attr:`stereodem.stereo.fusion.FusedDEM.rejected`): those points get edit code
        ``FUSION_REJECTED`` and LAS class 7 (noise).
    edit_codes : ndarray (rows, cols), optional
        The filtered DEM's edit mask (``stereodem run``): the other points take their cell's code.
    keep : bool
        Leave the pairs' point files for a later ``--resume``.
    """
    fmt = cfg.dem.point_cloud
    d = points_dir(out)
    ids = [int(k) for k in pairs]
    base = (
        np.zeros(grid.shape, np.uint8)
        if edit_codes is None
        else np.asarray(edit_codes).astype(np.uint8)
    )
    codes = np.empty((max(ids) + 1,) + tuple(base.shape), np.uint8)
    codes[:] = base
    if rejected is not None:
        for k, pid in enumerate(ids):
            codes[pid][rejected[k]] = FUSION_REJECTED
    files, per_pair = [], {}
    for pid in ids:
        found = sorted(pair_points_dir(d, pid).glob("points_*.npz"))
        per_pair[str(pid)] = len(found)
        files += found
    summary = write_las_files(
        Path(out) / f"dem.{fmt}",
        files,
        grid,
        vertical=vertical,
        edit_codes=codes,
        fmt=fmt,
        overwrite=True,
        pairs=pairs,
    )
    summary.pop("missing_files")
    summary["tiles_with_points"] = per_pair
    if not keep:
        _clean(d)
    return summary
