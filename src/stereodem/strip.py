"""ASTER strips: ``stereodem dem G1.hdf G2.hdf ... -o OUT`` (or a folder of granules).

Consecutive L1A granules of one pass are joined into one stereo pair, 3N strip + 3B strip,
each with one model spanning the strip (:func:`stereodem.sensor.io.aster_strip.open_aster_strip`:
the checks that they are one pass, the line offsets from the orbit, the overlap); the pair
stage then runs unchanged (:func:`stereodem.pipeline.stages.stereo_stage`: sparse stage, one
relative pointing for the strip, tiles), so the strip has one DEM and no seam to blend.
``dem_report.json`` holds the pair route's report plus ``strip`` (granules, line offsets,
per-seam checks, the method).
"""

from __future__ import annotations

import logging
from pathlib import Path

from stereodem.core.errors import InputError
from stereodem.core.threads import job_threads
from stereodem.sensor.io.aster_l1a import is_aster_granule
from stereodem.sensor.io.aster_strip import open_aster_strip
from stereodem.stereo import sanity

from . import point_cloud
from .config import Config
from .outlock import output_folder
from .pipeline.inputs import Pair, input_paths, load_seed_dem
from .pipeline.stages import check_dem_result, stereo_stage, write_dem_report

log = logging.getLogger(__name__)

__all__ = ["load_strip_pair", "run_strip_dem", "strip_granules"]

#: the strip's pair as its report and point cloud name it (the granules are in ``strip``)
STRIP_PAIR = ("3N strip", "3B strip")


def _granules_in_folder(folder: Path) -> list:
    """The granules directly inside ``folder`` (V004 ``.hdf``, V003 zips or folders), sorted."""
    return sorted(
        str(p) for p in folder.iterdir() if not p.name.startswith(".") and is_aster_granule(p)
    )


def strip_granules(paths, band=1) -> list | None:
    """The granules of ``stereodem dem`` inputs when they make a strip, else ``None``.

    A strip is two or more ASTER granules given as files, or a folder holding two or more
    (a folder that is itself a V003 granule is one granule). With an ASTER band named
    (``--band 3N``) the inputs stay single images of a pair or an N-view set instead."""
    if isinstance(band, str):
        return None
    paths = [Path(p) for p in paths if p]
    if (
        len(paths) == 1
        and paths[0].is_dir()
        and not any(paths[0].glob("*.VNIR_Band3?.ImageData.tif"))
    ):
        found = _granules_in_folder(paths[0])
        if len(found) >= 2:
            return found
        if not found:
            raise InputError(f"{paths[0]}: a folder with no ASTER L1A granule in it")
        return None
    if len(paths) >= 2 and all(is_aster_granule(p) for p in paths):
        return [str(p) for p in paths]
    return None


def load_strip_pair(cfg: Config, paths):
    """``(Pair, AsterStrip)``: the joined 3N and 3B strips with their models, and the seed DEM."""
    strip = open_aster_strip(paths, radiometric=cfg.inputs.radiometric)
    n, b = strip.band("3N"), strip.band("3B")
    for band in (n, b):
        sanity.check_texture(band.image, f"strip of {len(paths)} granules band {band.band}")
    seed = load_seed_dem(cfg)
    if seed is not None:
        sanity.check_seed_dem(seed, n.model, b.model, name=f"seed DEM {cfg.inputs.seed_dem}:")
    tags = {
        **strip.granules[0].tags(),
        "ASTER_BAND": "3N",
        "ASTER_STRIP_GRANULES": ", ".join(g.granule_id for g in strip.granules),
    }
    pair = Pair(n.image, b.image, n.model, b.model, seed, tags=tags)
    return pair, strip


def run_strip_dem(cfg: Config, paths, *, started=None, progress=None):
    """Make the strip's DEM into ``cfg.output_dir`` (the pair route's layers and
    ``dem_report.json`` with a ``strip`` section), the folder locked for the job.
    Returns ``(products, folder, strip, cloud)``, ``cloud`` the summary of the point cloud
    written with ``[dem] point_cloud`` (else None); a suspect result fails afterwards
    (``--force``)."""
    inputs = [*paths, *input_paths(cfg)]
    with output_folder(cfg.output_dir, overwrite=cfg.run.overwrite, inputs=inputs) as out:
        pair, strip = load_strip_pair(cfg, paths)
        pts = point_cloud.prepare(out) if cfg.dem.point_cloud else None
        prod, failed = stereo_stage(cfg, pair, progress=progress, points_dir=pts)
        prod.write(  # waited for: its files side by side on the job's threads, as `dem` does
            out,
            overwrite=True,
            creation_options=cfg.run.creation_options,
            threads=job_threads(cfg.run.workers),
        )
        cloud = (
            point_cloud.point_cloud_stage(cfg, out, prod, pairs={0: STRIP_PAIR})
            if pts is not None
            else None
        )
        write_dem_report(
            out,
            prod,
            failed,
            pair,
            started,
            cloud,
            left=STRIP_PAIR[0],
            right=STRIP_PAIR[1],
            strip=strip.report,
        )
    check_dem_result(cfg, prod, failed, out / "dem_report.json")
    return prod, out, strip, cloud
