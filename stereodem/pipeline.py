"""The job, top to bottom: sensor models -> stereo -> filters -> orthoimages -> assessment.

Every command builds a :class:`stereodem.config.Config` and calls these stage functions:
``stereodem dem`` runs :func:`load_pair` and :func:`stereo_stage`, ``stereodem filter``
:func:`post_stage`, ``stereodem ortho`` :func:`ortho_stage`, ``stereodem assess``
:func:`assess_stage`, and ``stereodem run`` (:func:`run`) all of them into one folder with
``run.json`` (configuration, versions, timings and peak memory per stage, failed tiles). The
hand route ``dem -> filter -> ortho -> assess`` and ``run`` therefore give the same rasters.

Output folder of :func:`run`::

    raw/dem.tif, raw/count.tif, raw/score.tif, raw/raygap.tif   stereo DEM before editing
    dem.tif                      filtered and hole-filled DEM
    dem_edit_mask.tif            uint8: filter Reason (1-8) or EditCode (99 border rim,
                                 100 filled by IDW, 101 filled from the seed DEM)
    ortho_left.tif, ortho_right.tif
    assess/report.json, report.md, *.png                        when a reference DEM is given
    tiles/tile_<n>.npz           finished stereo tiles (reused by --resume)
    run.json
"""
from __future__ import annotations

import dataclasses
import json
import logging
import os
import platform
import resource
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import rasterio
import rasterio.warp

from stereodem.post.filters import EditCode
from stereodem.sensor.errors import InputError
from stereodem.sensor.geo.dem import DEM
from stereodem.sensor.geo.grid import MapGrid
from stereodem.sensor.io.raster import (image_dtype, read_image, write_geotiff,
                                        write_text_atomic)
from stereodem.sensor.io.sidecar import load_image_model, load_model
from stereodem.stereo.grid import DEMGrid

from . import __version__, sanity
from .config import Config
from .outlock import output_folder
from .runner import (SharedArray, clean_cache, load_cached, pool_size, process_peak_rss_mb,
                     reset_peak_rss, run_tiles)

log = logging.getLogger(__name__)


def _peak_rss_mb():
    """Peak resident memory (MB) of this process (:func:`process_peak_rss_mb`) and of its
    largest finished child (``ru_maxrss``, which for a forked child includes the parent's
    pages at the fork: tile summaries carry each worker's own figure)."""
    kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
    return round(process_peak_rss_mb(), 1), round(kids, 1)


def _cpu_seconds():
    """CPU seconds (user + system) of this process (all its threads) and of its finished,
    waited-for child processes (the tile pool's workers once the pool is shut down)."""
    t = os.times()
    return t.user + t.system, t.children_user + t.children_system


@dataclass
class StageLog:
    """Per stage: wall seconds, CPU seconds (this process's threads: ``cpu_s``; worker
    processes: ``worker_cpu_s``) and peak resident memory (MB) of this process during the
    stage (``peak_rss_mb``; since the process started where the high-water mark cannot be
    reset, ``peak_rss_scope`` says which) and of its largest finished worker."""

    stages: dict = field(default_factory=dict)
    _cpu0: tuple = (0.0, 0.0)
    _scope: str = "process"

    def start(self) -> float:
        """Mark the start of a stage; returns its ``time.perf_counter()``."""
        self._scope = "stage" if reset_peak_rss() else "process"
        self._cpu0 = _cpu_seconds()
        return time.perf_counter()

    def record(self, name, t0, **extra):
        own, kids = _peak_rss_mb()
        cpu, workers = _cpu_seconds()
        self.stages[name] = dict(seconds=round(time.perf_counter() - t0, 3),
                                 cpu_s=round(cpu - self._cpu0[0], 2),
                                 worker_cpu_s=round(workers - self._cpu0[1], 2),
                                 peak_rss_mb=own, peak_rss_scope=self._scope,
                                 peak_worker_rss_mb=kids, **extra)
        log.info("stage %s: %.1f s", name, self.stages[name]["seconds"])


# ----------------------------------------------------------------------------- inputs

@dataclass
class Pair:
    """The loaded stereo pair: images (float32, NaN = no data), their models, the seed DEM."""

    left_image: np.ndarray
    right_image: np.ndarray
    left_model: object
    right_model: object
    seed_dem: DEM | None = None
    left_dtype: np.dtype = np.dtype("float32")
    right_dtype: np.dtype = np.dtype("float32")
    tags: dict = field(default_factory=dict)


@dataclass
class InputImage:
    """One input image as every stage sees it: float32 values (NaN = no data), its sensor
    model, the stored data type and metadata tags (an ASTER granule's acquisition time, ...)."""

    image: np.ndarray
    model: object
    dtype: np.dtype
    tags: dict = field(default_factory=dict)


ASTER_STEREO_BANDS = ("3N", "3B")


def open_image(path, *, band=1, prefer: str = "physical", model_file=None, rpc_direct: bool = False,
               radiometric: bool = True, granules: dict | None = None) -> InputImage:
    """The one input layer: a GeoTIFF (with RPCs or a model sidecar) or an ASTER L1A granule
    (V004 ``.hdf``, V003 ``.zip`` or folder; ``band`` ``"3N"``/``"3B"``, radiance by the
    granule's radiometric table unless ``radiometric`` is false), with its model (or the
    ``model_file``), checked against each other. ``granules`` caches opened granules by path."""
    from stereodem.sensor.io.aster_l1a import is_aster_granule, open_aster_granule
    if is_aster_granule(path):
        key = str(Path(path).resolve())
        g = (granules or {}).get(key) or open_aster_granule(path)
        if granules is not None:
            granules[key] = g
        name = band if isinstance(band, str) else ASTER_STEREO_BANDS[0]
        img = g.read_image(name, radiometric=radiometric)
        model = load_model(model_file) if model_file else g.model(name)
        dtype = np.dtype("float32") if radiometric else g.band(name).dn.dtype
        tags = {**g.tags(), "ASTER_BAND": str(name).upper(), "ASTER_RADIOMETRIC": str(bool(radiometric))}
    else:
        if isinstance(band, str):
            raise InputError(f"{path}: band {band!r} names an ASTER band, but this is not an ASTER "
                             "granule (give a band number)")
        model = (load_model(model_file, rpc_direct=rpc_direct) if model_file else
                 load_image_model(path, prefer=prefer, rpc_direct=rpc_direct))
        img, dtype, tags = read_image(path, band), image_dtype(path, band), {}
    if img.shape != (model.height, model.width):
        raise InputError(f"{path}: image is {img.shape[1]}x{img.shape[0]} but its model "
                         f"describes {model.width}x{model.height}")
    sanity.check_texture(img, f"{path}" + (f" band {band}" if isinstance(band, str) else ""))
    return InputImage(img, model, dtype, tags)


def image_model(path, *, band=1, prefer: str = "physical"):
    """The sensor model of an input (the image's sidecar or RPCs, or band ``band`` of an ASTER
    granule), without reading the pixels."""
    from stereodem.sensor.io.aster_l1a import is_aster_granule, open_aster_granule
    if is_aster_granule(path):
        return open_aster_granule(path).model(band if isinstance(band, str) else ASTER_STEREO_BANDS[0])
    return load_image_model(path, prefer=prefer)


def load_seed_dem(cfg: Config) -> DEM | None:
    """The seed DEM of the configuration (loaded once per job), or None."""
    if not cfg.inputs.seed_dem:
        return None
    return DEM.from_file(cfg.inputs.seed_dem, vertical=cfg.inputs.seed_dem_vertical)


def load_pair(cfg: Config) -> Pair:
    """Both images with their models, and the seed DEM. An ASTER granule given alone (or as
    both images) is its own pair: 3N left, 3B right."""
    i = cfg.inputs
    if not i.left:
        raise InputError("a stereo DEM needs two images ([inputs] left and right)")
    from stereodem.sensor.io.aster_l1a import is_aster_granule
    granule = is_aster_granule(i.left)
    right = i.right or (i.left if granule else None)
    if not right:
        raise InputError(f"{i.left}: a stereo DEM needs a second image (or an ASTER granule)")
    same = granule and Path(right).resolve() == Path(i.left).resolve()
    bands = ASTER_STEREO_BANDS if same else (i.band, i.band)
    cache: dict = {}
    kw = dict(prefer=i.model, rpc_direct=i.rpc_direct, radiometric=i.radiometric, granules=cache)
    left = open_image(i.left, band=bands[0], model_file=i.left_model, **kw)
    right = open_image(right, band=bands[1], model_file=i.right_model, **kw)
    seed = load_seed_dem(cfg)
    if seed is not None:
        sanity.check_seed_dem(seed, left.model, right.model, name=f"seed DEM {cfg.inputs.seed_dem}:")
    return Pair(left.image, right.image, left.model, right.model, seed,
                left.dtype, right.dtype, {**left.tags, **{f"RIGHT_{k}": v for k, v in right.tags.items()}})


def check_pair(cfg: Config, pair: Pair) -> float:
    """Geometry of the pair before any stereo work (:func:`stereodem.sanity.check_base`);
    returns the base-to-height ratio."""
    hr = cfg.stereo.rectification.height_range
    if hr is None and pair.seed_dem is not None:
        hr = pair.seed_dem.height_range()
    if hr is None:
        lo = max(pair.left_model.height_bounds()[0], pair.right_model.height_bounds()[0])
        hi = min(pair.left_model.height_bounds()[1], pair.right_model.height_bounds()[1])
        hr = (lo, hi)
    return sanity.check_base(pair.left_model, pair.right_model, hr)


# ----------------------------------------------------------------------------- stereo

def tile_runner(run_settings, progress=None, cache_dir=None):
    """A tile runner for :func:`stereodem.stereo.pipeline.make_dem` backed by :func:`run_tiles`.

    Finished tiles are cached in ``cache_dir`` (``tile_<n>.npz``) so ``--resume`` skips them.
    """
    failures = []

    def runner(process_tile, tiles, inputs, settings):
        pool = pool_size(run_settings.workers, len(tiles), run_settings.dask) > 0
        key = None
        if cache_dir is not None:
            key = _cache_key(tiles, inputs, settings)
            _check_tile_cache(Path(cache_dir), key, run_settings.resume)
        with tempfile.TemporaryDirectory(prefix="shared-", dir=cache_dir) as tmp:
            if pool:       # workers map the images from disk instead of each receiving a copy
                inputs = dataclasses.replace(
                    inputs, left_image=SharedArray.create(inputs.left_image, tmp, "left"),
                    right_image=SharedArray.create(inputs.right_image, tmp, "right"))
            ctx = dict(inputs=inputs, settings=settings, fn=process_tile)
            results, fails, _ = run_tiles(_tile_job, tiles, ctx, workers=run_settings.workers,
                                          timeout=run_settings.tile_timeout, cache_dir=cache_dir,
                                          resume=run_settings.resume, dask_address=run_settings.dask,
                                          progress=progress, cache_key=key,
                                          hold_results=cache_dir is None)
        failures.extend(fails)
        by_index = {t.index: t for t in tiles}
        # in tile order, one at a time: a cached run holds one tile's cell sums, not all
        return (_tile_result(results[i] if results[i] is not None else load_cached(cache_dir, by_index[i]))
                for i in sorted(results))

    runner.failures = failures
    return runner


def _cache_key(tiles, inputs, settings) -> str:
    """Fingerprint of everything a stereo tile's result depends on (settings, tiles, lattice,
    models, the images' bytes), so ``--resume`` never reuses tiles of another job."""
    import hashlib
    h = hashlib.sha256()
    g = inputs.lattice
    h.update(json.dumps([settings.summary(), [t.bounds for t in tiles], list(inputs.height_range),
                         None if g is None else [tuple(g.transform), list(g.shape), g.crs.to_wkt(),
                                                 g.method, g.sigma, g.radius, g.geoid]],
                        default=_json_default, sort_keys=True).encode())
    for m in (inputs.left_model, inputs.right_model):
        h.update(_model_fingerprint(m))
    for img in (inputs.left_image, inputs.right_image):
        h.update(np.ascontiguousarray(img).data)
    return h.hexdigest()


def _model_fingerprint(model) -> bytes:
    """Bytes identifying a sensor model's parameters: a wrapper with a ``model`` attribute (an
    image-space correction) gives its own parameters plus its model's, other models their
    ``to_dict``, else their pickle."""
    import pickle
    if hasattr(model, "model") and hasattr(model, "parameters"):
        own = json.dumps(model.parameters(), sort_keys=True).encode()
        return own + _model_fingerprint(model.model)
    if hasattr(model, "to_dict"):
        return json.dumps(model.to_dict(), default=_json_default, sort_keys=True).encode()
    return pickle.dumps(model, protocol=4)


def _check_tile_cache(cache_dir: Path, key: str, resume: bool):
    """Keep the tile cache consistent with this job: on ``resume`` the cache must hold tiles of
    the same job (else :class:`InputError`); otherwise old tiles are removed first."""
    cache_dir.mkdir(parents=True, exist_ok=True)
    clean_cache(cache_dir)
    manifest = cache_dir / "job.json"
    try:
        old = json.loads(manifest.read_text()).get("key") if manifest.exists() else None
    except (ValueError, AttributeError, UnicodeDecodeError):
        old = "unreadable"
    if resume and old is not None and old != key:
        raise InputError(f"{cache_dir}: the cached tiles belong to a run with other inputs or "
                         "settings; run again without --resume (and with --overwrite)")
    if not resume or old is None:
        for f in cache_dir.glob("tile_*.npz"):
            f.unlink()
    write_text_atomic(manifest, json.dumps({"key": key}), overwrite=True)


def _tile_job(tile, ctx):
    """One stereo tile as plain arrays (cacheable with ``np.savez``, no pickle): its cell
    sums on the output lattice, their window origin, point count and QA summary."""
    res = ctx["fn"](tile, ctx["inputs"], ctx["settings"])
    res.summary["process_peak_rss_mb"] = round(process_peak_rss_mb(), 1)
    c = res.cells
    return dict(sums=c.sums, origin=np.array([c.row0, c.col0, c.n_points], np.int64),
                summary=np.array(json.dumps(res.summary, default=_json_default)))


def _tile_result(arrays):
    from stereodem.stereo.grid import CellSums
    from stereodem.stereo.pipeline import TileResult
    r0, c0, n = (int(v) for v in arrays["origin"])
    return TileResult(CellSums(r0, c0, arrays["sums"], n), json.loads(str(arrays["summary"])))


def stereo_stage(cfg: Config, pair: Pair, *, progress=None, cache_dir=None):
    """Stereo DEM (raw): :func:`stereodem.stereo.pipeline.make_dem` with the configured tile
    runner (and, with ``[jitter] enabled``, the right camera's jitter estimated against the
    seed DEM, corrected and the DEM made again: :mod:`stereodem.stereo.jitter`); returns
    ``(products, failed_tiles)``."""
    from stereodem.stereo.pipeline import make_dem
    bh = check_pair(cfg, pair)
    left, right, findings = sanity.comparable_radiometry(pair.left_image, pair.right_image,
                                                         pair.left_dtype, pair.right_dtype)
    runner = tile_runner(cfg.run, progress, cache_dir=cache_dir)
    args = (left, right, pair.left_model, pair.right_model)
    if cfg.jitter.enabled:
        from stereodem.stereo.jitter import dem_with_jitter_correction
        j = cfg.jitter
        products, corrected, fit, first = dem_with_jitter_correction(
            *args, pair.seed_dem, cfg.stereo, seed_dem=pair.seed_dem, n_sines=j.n_sines,
            f_range=(j.min_frequency, j.max_frequency), runner=runner, axes=j.axis_names)
        pair.right_model = corrected
        log.info("jitter of the right camera: %s", products.info["jitter"])
    else:
        products = make_dem(*args, cfg.stereo, seed_dem=pair.seed_dem, runner=runner)
    products.info["base_to_height"] = round(bh, 4)
    products.info["warnings"] = findings + sanity.check_result(products.info)
    products.info["status"] = sanity.status(products.info["warnings"])
    return products, [f.to_dict() for f in runner.failures]


def suspect_error(cfg: Config, products, report_path) -> None:
    """Raise :class:`stereodem.sanity.SuspectResultError` for a suspect stereo result unless
    the job is forced (``--force``)."""
    bad = [w for w in products.info.get("warnings", []) if w["severity"] == "suspect"]
    if bad and not cfg.run.force:
        raise sanity.SuspectResultError(
            f"result suspect: {bad[0]['message']}; products kept for inspection, findings in "
            f"{report_path} (--force accepts them)")


def read_stereo_layers(dem_path, *, vertical=None) -> DEMGrid:
    """A stereo DEM written by ``stereodem dem`` with its ``score.tif`` and ``raygap.tif``
    beside it (missing layers are NaN: the filters that need them then keep every cell)."""
    dem = DEM.from_file(dem_path, vertical=vertical)
    folder = Path(dem_path).parent
    grid = dem.grid
    layers = {}
    for name in ("score", "raygap"):
        path = folder / f"{name}.tif"
        layers[name] = read_image(path) if path.is_file() else np.full(grid.shape, np.nan, np.float32)
        if layers[name].shape != grid.shape:
            raise InputError(f"{path}: {layers[name].shape} cells, but the DEM has {grid.shape}")
    return DEMGrid(dem.heights.astype(np.float32), np.zeros(grid.shape, np.int32), layers["score"],
                   layers["raygap"], grid, dem.vertical or "ellipsoid")


# ----------------------------------------------------------------------------- post

def post_stage(cfg: Config, layers: DEMGrid, seed_dem: DEM | None = None):
    """Blunder filters and hole filling of a stereo DEM; returns (heights, edit mask, report).

    The edit mask holds the filter :class:`~stereodem.post.filters.Reason` of removed cells or
    an :class:`~stereodem.post.filters.EditCode`.
    """
    from stereodem.post.fill import fill_holes, gaussian_smooth
    from stereodem.post.filters import default_chain
    z = layers.heights
    mask = np.zeros(z.shape, np.uint8)
    report = {}
    if cfg.filters.enabled:
        res = default_chain(thesis=cfg.filters.thesis).apply(
            z, score=layers.score, ray_gap=layers.ray_gap, transform=layers.transform, crs=layers.crs)
        z, mask = res.heights, res.removed.copy()
        report["filters"] = res.report
    if cfg.filters.enabled and cfg.filters.erode > 0:
        # matches along the border of the overlap use partial windows: drop a rim of cells
        import cv2
        valid = np.isfinite(z).astype(np.uint8)
        k = 2 * cfg.filters.erode + 1
        rim = (valid == 1) & (cv2.erode(valid, np.ones((k, k), np.uint8), borderValue=0) == 0)
        z = np.where(rim, np.nan, z)
        mask[rim] = EditCode.BORDER_RIM
        report["erode"] = {"cells": int(cfg.filters.erode), "removed": int(rim.sum())}
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
    return z.astype(np.float32), mask, report


def write_clean_dem(path, heights, mask, layers: DEMGrid, *, overwrite=False, creation_options=None,
                    writer=None):
    """Write a clean DEM and its edit mask (``<stem>_edit_mask.tif``, uint8, 255 = nodata);
    returns the clean :class:`DEM`. With a ``writer`` (:class:`BackgroundWriter`) the files
    are written there, from copies of ``heights`` and ``mask``."""
    path = Path(path)
    clean = DEM(heights, layers.transform, layers.crs, layers.vertical, str(path))
    if writer is not None:
        stored = DEM(np.array(heights), layers.transform, layers.crs, layers.vertical, str(path))
        writer.submit(_write_dem_and_mask, path, stored, np.array(mask), overwrite, creation_options)
    else:
        _write_dem_and_mask(path, clean, mask, overwrite, creation_options)
    return clean


def _write_dem_and_mask(path, dem: DEM, mask, overwrite, creation_options):
    dem.write(path, overwrite=overwrite, creation_options=creation_options)
    write_geotiff(edit_mask_path(path), mask, dem.transform, dem.crs, 255, overwrite=overwrite,
                  descriptions=["edit code: 0 kept, 1-8 filter reason, 99 border rim, 100/101 filled"],
                  units=["1"], creation_options=creation_options)


def edit_mask_path(dem_path) -> Path:
    """Where the edit mask of a clean DEM is written."""
    p = Path(dem_path)
    return p.with_name(f"{p.stem}_edit_mask.tif")


def _fallback_on_grid(seed, layers: DEMGrid):
    """The seed DEM warped onto the stereo grid, in the grid's vertical reference."""
    seed = seed.to_reference(layers.vertical)
    out = np.full(layers.heights.shape, np.nan, np.float32)
    rasterio.warp.reproject(seed.heights, out, src_transform=seed.transform, src_crs=seed.crs.to_wkt(),
                            dst_transform=layers.transform, dst_crs=layers.crs.to_wkt(),
                            resampling=rasterio.warp.Resampling.bilinear, src_nodata=np.nan,
                            dst_nodata=np.nan)
    return out


# ----------------------------------------------------------------------------- ortho

def ortho_stage(cfg: Config, images, dem: DEM, *, grid: MapGrid | None = None, progress=None):
    """Orthoimages of ``images`` (``[(name, image, model), ...]``) against ``dem``, all on one
    grid (the first image's unless ``grid`` is given); returns ``{name: Ortho}``.

    Cells the DEM does not cover get no data, with a warning giving their share, unless
    ``cfg.ortho.fill_dem`` names a second DEM to take their heights from. Row blocks run on
    ``cfg.run.workers`` threads (the result does not depend on the count).
    """
    from stereodem.ortho.drm import orthorectify
    orthos = {}
    threads = cfg.run.workers or os.cpu_count() or 1
    fill = (DEM.from_file(cfg.ortho.fill_dem, vertical=cfg.ortho.fill_dem_vertical)
            if cfg.ortho.fill_dem else None)
    for name, img, model in images:
        o = orthorectify(img, model, dem, grid=grid, res=cfg.ortho.res, crs=cfg.ortho.crs,
                         resampling=cfg.ortho.resampling, progress=progress, threads=threads,
                         fill_dem=fill)
        grid = grid or o.grid
        orthos[name] = o
    return orthos


# ----------------------------------------------------------------------------- uncertainty

def uncertainty_stage(cfg: Config, pair: Pair, dem: DEM, ortho_grid: MapGrid, raw: DEMGrid, out_dir):
    """Per-cell horizontal σ of the left orthoimage (on its grid) into ``out_dir`` and the
    vertical σ of the DEM; returns (summary dict, the DEM σ object)."""
    from stereodem.ortho.uncertainty.covariance import assemble, read_adjust_report
    from stereodem.ortho.uncertainty.maps import dem_vertical_sigma, ortho_uncertainty_maps
    u = cfg.uncertainty
    report = read_adjust_report(u.covariance) if u.covariance else None
    model, names, D = assemble(pair.left_model, sigmas=u.sigma, report=report, image=cfg.inputs.left)
    maps = ortho_uncertainty_maps(model, dem, ortho_grid, D, names, u.method, samples=u.samples,
                                  threads=cfg.run.workers or os.cpu_count() or 1)
    maps.write(out_dir, overwrite=True)
    model_names = [n for n in names if n != "dem_height"]
    keep = [names.index(n) for n in model_names]
    dsig = dem_vertical_sigma(pair.left_model, pair.right_model, dem, score=raw.score,
                              left_covariance=np.asarray(D)[np.ix_(keep, keep)], left_names=model_names)
    return maps.summary(), dsig


# ----------------------------------------------------------------------------- assessment

def assess_stage(cfg: Config, dem, out_dir, *, overwrite=True, provenance=None):
    """Accuracy report of ``dem`` (a :class:`DEM` or a path) against the reference DEM and
    check points of the configuration, written into ``out_dir``; returns (assessment, files)."""
    from stereodem.post.assess import assess_dem
    from stereodem.post.report import write_report
    i, a = cfg.inputs, cfg.assess
    if not i.reference_dem:
        raise InputError("the assessment needs a reference DEM ([inputs] reference_dem, --ref)")
    dem = dem if isinstance(dem, DEM) else DEM.from_file(dem, vertical=i.dem_vertical)
    ref = DEM.from_file(i.reference_dem, vertical=i.reference_vertical)
    kw = {} if a.slope_bins is None else dict(slope_bins=a.slope_bins)
    result = assess_dem(dem, ref, coregister=a.coregister, checkpoints=i.checkpoints,
                        checkpoint_crs=i.checkpoints_crs, checkpoint_vertical=i.checkpoints_vertical,
                        landcover=i.landcover,
                        landcover_names={int(k): v for k, v in (a.landcover_names or {}).items()},
                        elevation_bins=a.elevation_bins, threads=cfg.run.workers or os.cpu_count() or 1,
                        **kw)
    files = write_report(result, out_dir, dem_heights=dem.heights, dem_transform=dem.transform,
                         dem_crs=dem.crs, overwrite=overwrite, provenance=provenance)
    return result, files


# ----------------------------------------------------------------------------- the run

def check_inputs(cfg: Config):
    """Cheap checks of the assessment inputs, so that a bad reference DEM or check-point file
    fails the job before the stereo work rather than after it."""
    i = cfg.inputs
    if cfg.assess.enabled and i.reference_dem:
        DEM.from_file(i.reference_dem, vertical=i.reference_vertical)
        if i.checkpoints:
            from stereodem.post.assess import read_checkpoints
            read_checkpoints(i.checkpoints, crs=i.checkpoints_crs)


def input_paths(cfg: Config) -> list:
    """Every input file of a job (none may be among its outputs)."""
    i = cfg.inputs
    return [p for p in (i.left, i.right, i.left_model, i.right_model, i.seed_dem, i.reference_dem,
                        i.checkpoints, i.landcover, i.dem) if p]


def run(cfg: Config, *, progress_factory=None) -> dict:
    """Run the whole job; returns the ``run.json`` content.

    The output folder is locked for the job (:func:`stereodem.outlock.output_folder`); with
    ``overwrite`` the previous job's products are removed first, with ``resume`` its tile
    cache is kept. Inputs are checked before any stereo work; a suspect stereo result
    (:mod:`stereodem.sanity`) stops the job after ``raw/`` and ``run.json`` are written,
    unless ``cfg.run.force``.

    ``progress_factory(label)`` may return a ``progress(done, total)`` callable per stage.
    """
    with output_folder(cfg.output_dir, overwrite=cfg.run.overwrite, resume=cfg.run.resume,
                       inputs=input_paths(cfg)) as out:
        return _run_in(cfg, out, progress_factory)


def writer_options(cfg: Config) -> dict:
    """GeoTIFF creation options of a job's rasters: the configured ones, plus GDAL's
    multi-threaded compression on the job's workers (``NUM_THREADS``; the pixels written do
    not depend on it) unless the configuration sets it."""
    co = dict(cfg.run.creation_options or {})
    threads = cfg.run.workers or os.cpu_count() or 1
    if threads > 1 and not any(k.upper() == "NUM_THREADS" for k in co):
        co["NUM_THREADS"] = str(threads)
    return co


class BackgroundWriter:
    """One thread that writes output files while the run goes on (GDAL compresses with the
    GIL released, so a write overlaps the next stage's numpy work on the other core).

    ``submit(fn, *args)`` queues a write; ``wait_for(i)`` waits for the ``i``-th one,
    ``wait()`` for all, re-raising the first error. Used as a context manager it waits for
    every queued write on exit (also when the run fails), so no file is left half-written.
    """

    def __init__(self):
        from concurrent.futures import ThreadPoolExecutor
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="stereodem-writer")
        self._futures = []
        self.seconds = 0.0

    @property
    def count(self) -> int:
        return len(self._futures)

    def submit(self, fn, *args, **kwargs):
        def timed():
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.seconds += time.perf_counter() - t0
        self._futures.append(self._pool.submit(timed))

    def wait_for(self, index: int):
        if index < len(self._futures):
            self._futures[index].result()

    def wait(self):
        for f in self._futures:
            f.result()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self._pool.shutdown(wait=True)
        return False


def _run_in(cfg: Config, out: Path, progress_factory) -> dict:
    from .provenance import utc_now
    started = utc_now()
    co = writer_options(cfg)
    prog = progress_factory or (lambda label: None)
    stages = StageLog()
    t_all = time.perf_counter()
    written = []

    with BackgroundWriter() as writer:
        return _run_stages(cfg, out, prog, stages, t_all, started, co, written, writer)


def _run_stages(cfg, out, prog, stages, t_all, started, co, written, writer) -> dict:
    """The stages of :func:`_run_in` after loading; GeoTIFF writes go to ``writer`` (a
    :class:`BackgroundWriter`) and overlap the next stage."""
    from .provenance import provenance
    t0 = stages.start()
    check_inputs(cfg)
    pair = load_pair(cfg)
    stages.record("load", t0)

    t0 = stages.start()
    bar = prog("stereo")
    products, failed = stereo_stage(cfg, pair, progress=bar, cache_dir=out / "tiles")
    _close(bar)
    writer.submit(products.dem.prepare_write(out / "raw", overwrite=True, creation_options=co))
    written.append("raw")
    tile_rss = [t.get("process_peak_rss_mb", 0.0) for t in products.tiles]
    stages.record("stereo", t0, tiles=len(products.tiles), points=int(products.n_points),
                  failed_tiles=len(failed), tile_process_peak_rss_mb=max(tile_rss, default=0.0))
    warnings = products.info.get("warnings", [])
    suspect = sanity.status(warnings) == "suspect" and not cfg.run.force

    report = post_report = None
    if not suspect:
        t0 = stages.start()
        z, mask, post_report = post_stage(cfg, products.dem, pair.seed_dem)
        clean = write_clean_dem(out / "dem.tif", z, mask, products.dem, overwrite=True,
                                creation_options=co, writer=writer)
        written += ["dem.tif", edit_mask_path(out / "dem.tif").name]
        stages.record("post", t0, valid_pct=round(float(100 * np.isfinite(z).mean()), 3))

        if cfg.ortho.enabled:
            t0 = stages.start()
            bar = prog("ortho")
            images = [("left", pair.left_image, pair.left_model)]
            if cfg.ortho.both:
                images.append(("right", pair.right_image, pair.right_model))
            orthos = ortho_stage(cfg, images, clean, progress=bar)
            _close(bar)
            dtypes = {"left": pair.left_dtype, "right": pair.right_dtype}
            for name, o in orthos.items():           # in the image's own data type
                writer.submit(o.write, out / f"ortho_{name}.tif", overwrite=True, dtype=dtypes[name],
                              creation_options=co)
                written.append(f"ortho_{name}.tif")
            stages.record("ortho", t0, interpolation_error_px={k: o.interpolation_error_px
                                                               for k, o in orthos.items()})
            ortho_grid = orthos["left"].grid
            del orthos, images, o                     # written: their memory goes back

        if cfg.uncertainty.enabled:
            writer.wait()                              # its layers go beside dem.tif
            t0 = stages.start()
            summary, dsig = uncertainty_stage(cfg, pair, clean, ortho_grid, products.dem,
                                              out / "uncertainty")
            dsig.write(out / "dem.tif", clean, overwrite=True)
            written += ["uncertainty", "dem_sigma_vertical.tif"]
            stages.record("uncertainty", t0, shares=summary["shares"],
                          sigma_horizontal_median_m=summary["sigma_horizontal_m"]["median"])

        # the images and the raw layers are not needed any more (the assessment's memory)
        writer.wait_for(0)        # the raw layers are on disk (the orthoimages may still go)
        pair.left_image = pair.right_image = None
        products.dem = None
        if cfg.assess.enabled and cfg.inputs.reference_dem:
            t0 = stages.start()
            report = assess_stage(cfg, clean, out / "assess", overwrite=True,
                                  provenance=provenance(started=started))[0].report
            written.append("assess")
            stages.record("assess", t0)

    t0 = stages.start()
    writer.wait()
    stages.record("writes", t0, background_s=round(writer.seconds, 3), files=writer.count,
                  note="GeoTIFF writes in a background thread, overlapping the following "
                       "stages (their CPU counts in those stages); seconds: the wait for the "
                       "last ones")
    written += ["tiles", "run.json"]
    run_info = dict(status=sanity.status(warnings), warnings=warnings,
                    provenance=provenance(started=started), config=cfg.to_dict(),
                    input_metadata=pair.tags,
                    versions=versions(), stages=stages.stages,
                    seconds=round(time.perf_counter() - t_all, 3), failed_tiles=failed,
                    stereo=dict(tiles=products.tiles, info=products.info), post=post_report,
                    outputs=sorted(written), headline=_headline(report))
    write_text_atomic(out / "run.json", json.dumps(run_info, indent=1, default=_json_default),
                      overwrite=True)
    if suspect:
        suspect_error(cfg, products, out / "run.json")
    return run_info


def versions() -> dict:
    """Versions of stereodem and of the libraries that shape its results."""
    import cv2
    import pyproj
    import scipy
    return dict(stereodem=__version__, python=platform.python_version(), numpy=np.__version__,
                scipy=scipy.__version__, opencv=cv2.__version__, rasterio=rasterio.__version__,
                gdal=rasterio.__gdal_version__, pyproj=pyproj.__version__, platform=platform.platform())


def _close(bar):
    if hasattr(bar, "close"):
        bar.close()


def _headline(report):
    if not report:
        return None
    s = report["stats"]
    h = dict(n=s["n"], valid_pct=s["valid_pct"], median=s["median"], nmad=s["nmad"], rmse=s["rmse"],
             le90=s["le90"])
    if report.get("coregistration"):
        h["coregistration"] = {k: report["coregistration"].get(k) for k in ("dx", "dy", "dz")}
        h["nmad_after_coregistration"] = report["after_coregistration"]["stats"]["nmad"]
    return h


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)
