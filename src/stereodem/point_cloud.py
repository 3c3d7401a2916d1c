"""The point-cloud product of ``stereodem dem`` / ``stereodem run`` (``--point-cloud las|laz``,
``[dem] point_cloud``): where the tiles write their points, and the merge into ``dem.las`` /
``dem.laz`` (:mod:`stereodem.stereo.pointcloud`).

The tiles write ``OUT/tiles/points/points_<index>.npz``; the merge reads them one tile at a
time (memory: one tile's points) and removes them once the LAS/LAZ is in place. A run resumed
with ``--resume`` keeps the point files of its finished tiles.
"""

from __future__ import annotations

import contextlib
import logging
import shutil
from pathlib import Path

from stereodem.stereo.pointcloud import write_las

log = logging.getLogger(__name__)


def points_dir(out) -> Path:
    """Where the tiles of a job in ``out`` write their points."""
    return Path(out) / "tiles" / "points"


def prepare(out, *, resume: bool = False) -> Path:
    """The points folder, emptied of an earlier job's files unless ``resume``."""
    d = points_dir(out)
    if d.exists() and not resume:
        shutil.rmtree(d)
    d.mkdir(parents=True, exist_ok=True)
    return d


def point_cloud_stage(cfg, out, products, edit_codes=None, *, grid=None) -> dict:
    """Merge the tiles' points into ``OUT/dem.<las|laz>``; returns its summary (for the
    reports). ``edit_codes``: the DEM's edit mask on ``grid`` (default the raw DEM's grid)
    for the points' classification."""
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
    shutil.rmtree(d, ignore_errors=True)
    with contextlib.suppress(OSError):
        d.parent.rmdir()  # the tile cache folder, when nothing else is cached
    return summary
