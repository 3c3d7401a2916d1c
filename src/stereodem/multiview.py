"""The N-view stereo stage: ``stereodem dem IMG1 IMG2 IMG3 ... -o OUT`` and ``[inputs] images``.

Every input image is opened through :func:`stereodem.pipeline.inputs.open_image`; the pairs to match
are chosen by :func:`stereodem.stereo.fusion.choose_pairs` (footprint overlap and
base-to-height ratio; an image in no usable pair is named and skipped); each pair runs the
pair stereo stage unchanged (:func:`stereodem.pipeline.stages.stereo_stage`: sanity checks, sparse
stage and relative pointing, tiles in the configured runner) with one CRS and posting fixed
for all, so the pair DEMs share one lattice; then :func:`stereodem.stereo.fusion.fuse_dems`
fuses them per cell. A pair that fails (no overlap after all, no sparse match) is reported
and left out; the job fails only when no pair succeeds.

With three or more images and ``[fusion] adjust`` (default ``auto``), the models are first
brought into agreement (:func:`stereodem.stereo.ties.agree_models`: tie points seen in
several images, bundle adjustment of image-space shifts, the best pair as datum) and the
pairs use the adjusted models; ``dem_report.json`` states the reprojection RMS and the
per-pair ray gaps before and after, and whether the adjusted models were kept.

The report (``dem_report.json``) holds every pair considered with its overlap, base-to-height
ratio and why it was chosen or not, the images skipped, each matched pair's run (time,
points, pointing correction, heights) and its agreement with the fused DEM.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stereodem.core import geodesy, jsonutil
from stereodem.core.errors import DEMCoverageError, InputError, StereodemError
from stereodem.core.raster import write_text_atomic
from stereodem.core.threads import job_threads
from stereodem.stereo.execution import ProgressPasses
from stereodem.stereo.fusion import FusedDEM, choose_pairs, fuse_dems, pair_sigma
from stereodem.stereo.grid import GridSpec
from stereodem.stereo.pipeline import DEMProducts, default_posting
from stereodem.stereo.plan import seed_height_range
from stereodem.stereo.sanity import SuspectResultError
from stereodem.stereo.ties import agree_models

from .config import Config
from .outlock import output_folder
from .pipeline.inputs import Pair, input_paths, load_seed_dem, open_image
from .pipeline.stages import stereo_stage
from .point_cloud import multiview_point_cloud_stage, pair_points_dir
from .point_cloud import prepare as prepare_points
from .provenance import provenance

log = logging.getLogger(__name__)

__all__ = [
    "MultiviewInfo",
    "MultiviewProducts",
    "multiview_stage",
    "reference_height",
    "run_dem",
    "run_stage",
    "source_pairs",
]


@dataclass
class MultiviewProducts:
    """The fused DEM and the job's account: pair plan, per-pair runs, failed tiles/pairs, and
    the pair DEMs themselves (``pair_dems``, in the order of ``report["pair_runs"]``) and the
    point cloud's summary (``point_cloud``, when :func:`run_dem` wrote one)."""

    fused: FusedDEM
    report: dict
    failed_tiles: list = field(default_factory=list)
    seconds: float = 0.0
    pair_dems: list = field(default_factory=list)
    point_cloud: dict | None = None


def reference_height(cfg: Config, models, seed_dem=None) -> float:
    """Height (m, ellipsoid) at which footprints, bases and the lattice are planned: the middle
    of the configured height range, else of the seed DEM's heights under the scene, else of
    the models' validity ranges
    (RPC height offsets: the terrain's middle for vendor RPCs)."""
    hr = cfg.stereo.rectification.height_range
    if hr is not None:
        return 0.5 * (float(hr[0]) + float(hr[1]))
    if seed_dem is not None:
        try:  # the seed's heights under the scene, not the whole file's (a 1 degree tile)
            lo, hi = seed_height_range(seed_dem, models[0], models[1 % len(models)])
            return 0.5 * (lo + hi)
        except DEMCoverageError:  # the seed's own check names it; plan on the models here
            pass
    mids = [0.5 * sum(m.height_bounds()) for m in models]
    return float(np.median(mids))


def multiview_stage(
    cfg: Config, paths, *, progress=None, cache_dir=None, points_dir=None
) -> MultiviewProducts:
    """Pair DEMs of the chosen pairs of ``paths`` on one lattice, fused per cell.

    ``progress(done, total)`` counts the tiles of all pairs, pair after pair
    (:class:`~stereodem.stereo.execution.ProgressPasses`); ``cache_dir`` (a job's ``tiles/``)
    gets one sub-folder per pair (``pair_<i>_<j>``), so ``run --resume`` reuses pair tiles.
    Each chosen pair has an id, its rank in the plan (``pair_id`` in the report's
    ``pair_runs``); with ``points_dir`` its tiles write their points into
    ``points_dir/pair_<id>/`` with ``source_pair`` = the id
    (:func:`stereodem.point_cloud.multiview_point_cloud_stage` merges them).
    """
    t0 = time.perf_counter()
    paths = [str(p) for p in paths]
    if len(paths) < 2:
        raise InputError("an N-view DEM needs at least two images")
    dup = {p for p in paths if paths.count(p) > 1}
    if dup:
        raise InputError(f"{sorted(dup)[0]}: given more than once")
    i = cfg.inputs
    granules: dict = {}
    images = [
        open_image(
            p,
            band=i.band,
            prefer=i.model,
            rpc_direct=i.rpc_direct,
            radiometric=i.radiometric,
            granules=granules,
        )
        for p in paths
    ]
    models = [im.model for im in images]
    seed = load_seed_dem(cfg)
    h0 = reference_height(cfg, models, seed)
    fs = cfg.fusion
    plan = choose_pairs(
        models,
        h0,
        min_overlap=fs.min_overlap,
        min_base_to_height=fs.min_base_to_height,
        max_base_to_height=fs.max_base_to_height,
        max_pairs=fs.max_pairs,
        names=paths,
    )
    adjustment = None
    if fs.adjust != "never" and len(plan.pairs) >= 2:
        models, adjustment = agree_models(
            [im.image for im in images],
            models,
            [(c.i, c.j) for c in plan.ranked],
            height_range=cfg.stereo.rectification.height_range,
            min_gain=fs.adjust_min_gain,
            force=fs.adjust == "always",
        )
        log.info(
            "models %s: %s", "adjusted" if adjustment["applied"] else "kept", adjustment["reason"]
        )
    gs = cfg.stereo.gridding
    first = models[plan.pairs[0].i]
    crs = gs.crs
    if crs is None:
        crs = geodesy.utm_crs(*first.center_lonlat(h0)).to_wkt()
    res = gs.res or default_posting(first.gsd(h0), crs)
    pcfg = dataclasses.replace(
        cfg,
        stereo=dataclasses.replace(cfg.stereo, gridding=dataclasses.replace(gs, crs=crs, res=res)),
    )
    dems, sigmas, runs, failed_tiles, failed_pairs = [], [], [], [], []
    if progress is not None:  # one count over the pairs' tiles, not one per pair
        progress = ProgressPasses(progress)
    for pair_id, c in enumerate(plan.pairs):
        a, b = images[c.i], images[c.j]
        name = f"{Path(paths[c.i]).name} + {Path(paths[c.j]).name}"
        log.info(
            "pair %s: overlap %.0f %%, base-to-height %.3f", name, 100 * c.overlap, c.base_to_height
        )
        pair = Pair(a.image, b.image, models[c.i], models[c.j], seed, a.dtype, b.dtype, {})
        sub = None if cache_dir is None else Path(cache_dir) / f"pair_{c.i}_{c.j}"
        tp = time.perf_counter()
        try:
            prod, failed = stereo_stage(
                pcfg,
                pair,
                progress=progress,
                cache_dir=sub,
                points_dir=None if points_dir is None else pair_points_dir(points_dir, pair_id),
                pair_id=pair_id,
            )
        except StereodemError as exc:
            log.warning("pair %s failed: %s; left out of the fusion", name, exc)
            failed_pairs.append(dict(pair_id=pair_id, left=c.i, right=c.j, error=str(exc)))
            continue
        failed_tiles.extend(dict(pair=[c.i, c.j], **f) for f in failed)
        dems.append(prod.dem)
        info = prod.info
        sigmas.append(pair_sigma(info.gsd_m, info.base_to_height, fs.sigma_px))
        runs.append(
            dict(
                pair_id=pair_id,
                left=c.i,
                right=c.j,
                seconds=round(time.perf_counter() - tp, 2),
                n_points=prod.n_points,
                status=info.status,
                warnings=info.warnings,
                base_to_height=info.base_to_height,
                height_range=info.height_range,
                pointing=info.pointing,
                valid_cells=info.valid_cells,
                n_tiles=info.n_tiles,
            )
        )
    if not dems:
        raise InputError(
            "no pair could be matched: "
            + "; ".join(
                f"{Path(paths[f['left']]).name} + {Path(paths[f['right']]).name}: {f['error']}"
                for f in failed_pairs
            )
        )
    fused = fuse_dems(
        dems,
        sigmas,
        method=fs.method,
        k=fs.reject_k,
        grid=_bounds_grid(gs.bounds, res, crs) if gs.bounds is not None else None,
    )
    for run, agreement in zip(runs, fused.pairs):
        run.update(fusion=agreement)
    suspect = [w for r in runs for w in r["warnings"] if w.get("severity") == "suspect"]
    report = dict(
        images=paths,
        reference_height_m=round(h0, 1),
        posting=res,
        **plan.to_dict(paths),
        adjustment=adjustment,
        pair_runs=runs,
        failed_pairs=failed_pairs,
        fusion=dict(
            dataclasses.asdict(fs),
            valid_cells=float(np.isfinite(fused.heights).mean()),
            cells_by_count={int(k): int(v) for k, v in enumerate(np.bincount(fused.count.ravel()))},
        ),
        status="suspect" if suspect else ("warning" if any(r["warnings"] for r in runs) else "ok"),
        warnings=suspect or [w for r in runs for w in r["warnings"]],
    )
    return MultiviewProducts(fused, report, failed_tiles, time.perf_counter() - t0, dems)


def source_pairs(report: dict) -> dict:
    """``{pair id: (left image, right image)}`` of the matched pairs of an N-view report, in
    fusion order (the point cloud's ``source_pair`` values)."""
    images = report["images"]
    return {r["pair_id"]: (images[r["left"]], images[r["right"]]) for r in report["pair_runs"]}


def _bounds_grid(bounds, res, crs):
    return GridSpec.from_bounds(bounds, res, crs).grid


def run_dem(cfg: Config, *, started=None, progress=None) -> tuple:
    """``stereodem dem IMG1 IMG2 IMG3 ...``: the N-view DEM written into ``cfg.output_dir``
    (``dem.tif``, ``count.tif``, ``nmad.tif``, ``dem_sigma_vertical.tif``, ``score.tif``,
    ``raygap.tif``, ``dem_report.json``; with ``[dem] point_cloud`` ``dem.las|laz`` holding
    every matched pair's points), the folder locked for the job. Returns
    ``(products, folder)``; a suspect pair result fails afterwards unless ``--force`` (as a pair
    job)."""
    with output_folder(cfg.output_dir, overwrite=cfg.run.overwrite, inputs=input_paths(cfg)) as out:
        pts = prepare_points(out) if cfg.dem.point_cloud else None
        prod = multiview_stage(cfg, cfg.inputs.images, progress=progress, points_dir=pts)
        prod.fused.write(
            out / "dem.tif",
            overwrite=True,
            creation_options=cfg.run.creation_options,
            threads=job_threads(cfg.run.workers),
        )
        cloud = None
        if pts is not None:
            f = prod.fused
            cloud = multiview_point_cloud_stage(
                cfg, out, f.grid, f.vertical, source_pairs(prod.report), f.rejected
            )
            prod.point_cloud = cloud
        report = dict(
            status=prod.report["status"],
            warnings=prod.report["warnings"],
            provenance=provenance(started=started),
            settings=cfg.to_dict(),
            seconds=round(prod.seconds, 2),
            multiview=prod.report,
            failed_tiles=prod.failed_tiles,
            point_cloud=cloud,
        )
        write_text_atomic(
            out / "dem_report.json",
            jsonutil.dumps(report, indent=2),
            overwrite=True,
        )
    bad = [w for w in prod.report["warnings"] if w.get("severity") == "suspect"]
    if bad and not cfg.run.force:
        raise SuspectResultError(
            f"result suspect: {bad[0]['message']}; products kept for "
            f"inspection, findings in {out / 'dem_report.json'} (--force accepts them)"
        )
    return prod, out


@dataclass
class MultiviewInfo:
    """The N-view report as the pair route's :class:`~stereodem.stereo.pipeline.StereoInfo` is
    read by ``stereodem run`` (``warnings``, ``status``, ``valid_cells``, :meth:`to_dict`)."""

    report: dict

    warnings = property(lambda self: self.report["warnings"])
    status = property(lambda self: self.report["status"])
    valid_cells = property(lambda self: self.report["fusion"]["valid_cells"])

    def to_dict(self) -> dict:
        return dict(self.report, valid_cells=self.valid_cells)


def run_stage(cfg: Config, *, progress=None, cache_dir=None, points_dir=None):
    """The N-view stereo stage of ``stereodem run`` (``[inputs] images``): returns ``(pair,
    products, failed_tiles, fused)`` shaped like the pair route's, so the later stages run
    unchanged: ``pair`` holds the first matched pair's images (the orthoimages' sources),
    ``products.dem`` the fused DEM with its score and ray-gap layers (the filters' inputs),
    ``products.info`` the N-view report (:class:`MultiviewInfo`); ``fused`` the
    :class:`~stereodem.stereo.fusion.FusedDEM` (``fused.prepare_write(raw / "dem.tif")``
    writes its layers, ``nmad.tif`` included). ``points_dir``: as :func:`multiview_stage`'s."""
    prod = multiview_stage(
        cfg, cfg.inputs.images, progress=progress, cache_dir=cache_dir, points_dir=points_dir
    )
    first = prod.report["pair_runs"][0]
    i = cfg.inputs
    a, b = (
        open_image(
            cfg.inputs.images[k],
            band=i.band,
            prefer=i.model,
            rpc_direct=i.rpc_direct,
            radiometric=i.radiometric,
        )
        for k in (first["left"], first["right"])
    )
    pair = Pair(
        a.image,
        b.image,
        a.model,
        b.model,
        load_seed_dem(cfg),
        a.dtype,
        b.dtype,
        {**a.tags, **{f"RIGHT_{k}": v for k, v in b.tags.items()}},
    )
    products = DEMProducts(
        prod.fused.dem,
        [],
        sum(r["n_points"] for r in prod.report["pair_runs"]),
        prod.seconds,
        cfg.stereo.summary(),
        MultiviewInfo(prod.report),
    )
    return pair, products, prod.failed_tiles, prod.fused
