"""One function per stage of a job, shared by the commands and ``stereodem run``:
:func:`stereo_stage` (``stereodem dem``), :func:`post_stage` (``filter``), :func:`ortho_stage`
(``ortho``), :func:`uncertainty_stage`, :func:`assess_stage` (``assess``)."""

from __future__ import annotations

import logging

import numpy as np

from stereodem.core import jsonutil
from stereodem.core.dem import DEM
from stereodem.core.errors import InputError
from stereodem.core.grid import MapGrid
from stereodem.core.raster import write_text_atomic
from stereodem.core.threads import job_threads
from stereodem.ortho.concurrent import orthorectify_all
from stereodem.ortho.uncertainty.covariance import assemble, read_adjust_report
from stereodem.post.fill import fill_holes, gaussian_smooth
from stereodem.post.filters import EditCode, border_rim, default_chain
from stereodem.post.warp import to_grid
from stereodem.stereo import sanity
from stereodem.stereo.execution import tile_runner
from stereodem.stereo.fork_server import warm_fork_server
from stereodem.stereo.jitter import dem_with_jitter_correction
from stereodem.stereo.pipeline import make_dem

from ..config import Config
from ..provenance import provenance
from .assessment import assess_stage  # noqa: F401  (the stage's home: a lighter import)
from .inputs import Pair

log = logging.getLogger(__name__)


def stereo_stage(
    cfg: Config, pair: Pair, *, progress=None, cache_dir=None, points_dir=None, pair_id: int = 0
):
    """Stereo DEM (raw): :func:`stereodem.stereo.pipeline.make_dem` with the configured tile
    runner (and, with ``[jitter] enabled``, the right camera's jitter estimated against the
    seed DEM, corrected and the DEM made again: :mod:`stereodem.stereo.jitter`); returns
    ``(products, failed_tiles)``. ``points_dir``: the tiles (of the final DEM, with jitter
    correction) also write their points there (:mod:`stereodem.point_cloud`), ``source_pair``
    ``pair_id``."""
    runner = tile_runner(cfg.run, progress, cache_dir=cache_dir)
    # the pool's fork server imports while the sparse stage and the planning run here
    tiles_estimate = pair.left_image.size // cfg.stereo.rectification.tile_size**2
    warm_fork_server(cfg.run.workers, tiles_estimate, cfg.run.dask)
    args = (pair.left_image, pair.right_image, pair.left_model, pair.right_model)
    dtypes = dict(left_dtype=pair.left_dtype, right_dtype=pair.right_dtype)
    if cfg.jitter.enabled:
        j = cfg.jitter
        products, corrected, fit, first = dem_with_jitter_correction(
            *args,
            pair.seed_dem,
            cfg.stereo,
            seed_dem=pair.seed_dem,
            n_sines=j.n_sines,
            f_range=(j.min_frequency, j.max_frequency),
            runner=runner,
            axes=j.axis_names,
            points_dir=points_dir,
            pair_id=pair_id,
            **dtypes,
        )
        pair.right_model = corrected
        log.info("jitter of the right camera: %s", products.info.jitter)
    else:
        products = make_dem(
            *args,
            cfg.stereo,
            seed_dem=pair.seed_dem,
            runner=runner,
            points_dir=points_dir,
            pair_id=pair_id,
            **dtypes,
        )
    return products, [f.to_dict() for f in runner.failures]


def suspect_error(cfg: Config, products, report_path) -> None:
    """Raise :class:`stereodem.stereo.sanity.SuspectResultError` for a suspect stereo result unless
    the job is forced (``--force``)."""
    bad = [w for w in products.info.warnings if w["severity"] == "suspect"]
    if bad and not cfg.run.force:
        raise sanity.SuspectResultError(
            f"result suspect: {bad[0]['message']}; products kept for inspection, findings in "
            f"{report_path} (--force accepts them)"
        )


def write_dem_report(out, products, failed, pair: Pair, started, cloud, *, left, right, **extra):
    """Write the pair route's ``dem_report.json`` into the output folder ``out``: status and
    warnings of the stereo result, provenance (``started``: the job's UTC start), the pair's input
    metadata, the ``left``/``right`` inputs as named to the user, then ``extra`` sections (e.g.
    ``strip``), the settings, the stereo info, point count, seconds (wall clock), tiles, the
    ``failed`` tiles and the ``cloud`` (point cloud) section."""
    report = dict(
        status=products.info.status,
        warnings=products.info.warnings,
        provenance=provenance(started=started),
        input_metadata=pair.tags,
        left=left,
        right=right,
        **extra,
        settings=products.settings,
        info=products.info.to_dict(),
        n_points=products.n_points,
        seconds=products.seconds,
        tiles=products.tiles,
        failed_tiles=failed,
        point_cloud=cloud,
    )
    write_text_atomic(
        out / "dem_report.json",
        jsonutil.dumps(report, indent=2),
        overwrite=True,
    )


def check_dem_result(cfg: Config, products, failed, report_path) -> None:
    """After a pair DEM job (its folder released): log the ``failed`` tiles (holes in the DEM),
    then :func:`suspect_error` against the report at ``report_path``."""
    if failed:
        log.warning(
            "%d tile(s) failed (listed in dem_report.json); the DEM has holes there", len(failed)
        )
    suspect_error(cfg, products, report_path)


def post_stage(cfg: Config, layers: DEM, seed_dem: DEM | None = None, *, path=None):
    """Blunder filters and hole filling of a stereo DEM (with ``score`` and ``ray_gap``
    layers); returns (the clean :class:`DEM` with its ``edit_mask`` layer, to be written at
    ``path``; report).

    The edit mask holds the filter :class:`~stereodem.post.filters.Reason` of removed cells or
    an :class:`~stereodem.post.filters.EditCode`.
    """
    z = layers.heights
    mask = np.zeros(z.shape, np.uint8)
    report = {}
    if cfg.filters.enabled:
        res = default_chain(thesis=cfg.filters.thesis).apply(
            z,
            score=layers.score,
            ray_gap=layers.ray_gap,
            transform=layers.transform,
            crs=layers.crs,
        )
        z, mask = res.heights, res.removed.copy()
        report["filters"] = res.report
    if cfg.filters.enabled and cfg.filters.erode > 0:
        # the rim of the matched area (partial correlation windows): of the stereo DEM's own
        # voids and edges, not of the holes the blunder filters just made (eroding those too
        # took 20 % of the real Pleiades pair's cells, 96 -> 76.5 % valid)
        rim = border_rim(layers.heights, cfg.filters.erode) & np.isfinite(z)
        z = np.where(rim, np.nan, z)
        mask[rim] = EditCode.BORDER_RIM
        report["erode"] = {"cells": int(cfg.filters.erode), "removed": int(rim.sum())}
    # e.g. a DEM a few cells wide: the small-patch filter or the border rim takes every cell
    # (then the hole filling had nothing to fill from, or the clean DEM was all void)
    gone = cfg.filters.enabled and not np.isfinite(z).any()
    n = int(np.isfinite(layers.heights).sum()) if gone else 0
    if n:  # (an all-void DEM keeps its own error)
        rim = report.get("erode", {}).get("removed", 0)
        off = "--no-filters ([filters] enabled = false)"
        by, keep = "the blunder filters", off
        if rim:
            by = f"the blunder filters ({n - rim}) and the border rim ({rim})"
            keep = f"a smaller --erode ([filters] erode, now {int(cfg.filters.erode)}) or {off}"
        raise InputError(
            f"{layers.path or 'stereo DEM'}: {by} removed all {n} valid cells of the "
            f"{z.shape[0]} x {z.shape[1]} DEM; {keep} keeps them"
        )
    if cfg.fill.enabled:
        use = cfg.fill.fallback and seed_dem is not None
        fallback = _fallback_on_grid(seed_dem, layers) if use else None
        fr = fill_holes(z, max_hole_size=cfg.fill.max_hole_size, fallback=fallback)
        z = fr.heights
        mask[fr.filled == 1] = EditCode.FILLED_IDW
        mask[fr.filled == 2] = EditCode.FILLED_SEED
        report["fill"] = fr.report
        if cfg.fill.smooth_sigma > 0:
            z = gaussian_smooth(z, sigma=cfg.fill.smooth_sigma)
    clean = DEM(
        z.astype(np.float32),
        layers.transform,
        layers.crs,
        layers.vertical,
        None if path is None else str(path),
        edit_mask=mask,
    )
    return clean, report


def _fallback_on_grid(seed, layers: DEM):
    """The seed DEM warped onto the stereo grid, in the grid's vertical reference."""
    seed = seed.to_reference(layers.vertical)
    return to_grid(
        seed.heights,
        seed.transform,
        seed.crs,
        layers.transform,
        layers.crs,
        layers.heights.shape,
        resampling="bilinear",
    )


def ortho_stage(cfg: Config, images, dem: DEM, *, grid: MapGrid | None = None, progress=None):
    """Orthoimages of ``images`` (``[(name, image, model), ...]``) against ``dem``, all on one
    grid (the first image's unless ``grid`` is given); returns ``{name: Ortho}``.

    Cells the DEM does not cover get no data, with a warning giving their share, unless
    ``cfg.ortho.fill_dem`` names a second DEM to take their heights from. The orthoimages run
    concurrently, their row blocks on threads, ``cfg.run.workers`` threads in all
    (:func:`stereodem.ortho.concurrent.orthorectify_all`; the result does not depend on it).
    """
    fill = (
        DEM.from_file(cfg.ortho.fill_dem, vertical=cfg.ortho.fill_dem_vertical)
        if cfg.ortho.fill_dem
        else None
    )
    return orthorectify_all(
        images,
        dem,
        grid=grid,
        res=cfg.ortho.res,
        crs=cfg.ortho.crs,
        resampling=cfg.ortho.resampling,
        progress=progress,
        threads=job_threads(cfg.run.workers),
        fill_dem=fill,
    )


def uncertainty_stage(cfg: Config, pair: Pair, dem: DEM, ortho_grid: MapGrid, raw: DEM, out_dir):
    """Per-cell horizontal σ of the left orthoimage (on its grid) into ``out_dir`` and the
    vertical σ of the DEM; returns (summary dict, the DEM σ object)."""
    # imported here: the maps' sampling needs scipy.stats (0.2 s), which no other stage does
    from stereodem.ortho.uncertainty.maps import dem_vertical_sigma, ortho_uncertainty_maps

    u = cfg.uncertainty
    report = read_adjust_report(u.covariance) if u.covariance else None
    model, names, D = assemble(
        pair.left_model, sigmas=u.sigma, report=report, image=cfg.inputs.left
    )
    maps = ortho_uncertainty_maps(
        model,
        dem,
        ortho_grid,
        D,
        names,
        u.method,
        samples=u.samples,
        threads=job_threads(cfg.run.workers),
    )
    maps.write(out_dir, overwrite=True)
    model_names = [n for n in names if n != "dem_height"]
    keep = [names.index(n) for n in model_names]
    dsig = dem_vertical_sigma(
        pair.left_model,
        pair.right_model,
        dem,
        score=raw.score,
        left_covariance=np.asarray(D)[np.ix_(keep, keep)],
        left_names=model_names,
    )
    return maps.summary(), dsig
