"""The end-to-end job, top to bottom: sensor -> stereo -> post -> ortho -> assess.

Each stage is a function of the configuration's settings objects and the previous stage's
products, and is callable on its own from Python. :func:`run` chains them, writes everything
into one output folder and records ``run.json`` (configuration used, versions, timings and
peak memory per stage, failed tiles).

Output folder::

    raw/dem.tif, raw/count.tif, raw/score.tif, raw/raygap.tif   stereo DEM before editing
    dem.tif                      filtered and hole-filled DEM
    dem_edit_mask.tif            uint8: filter reason code, 99 = border rim, 100 = filled by IDW,
                                 101 = filled from the seed DEM
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

from stereodem.sensor.geo.dem import DEM
from stereodem.sensor.errors import InputError
from stereodem.sensor.io.raster import prepare_output_dir, write_geotiff, write_text_atomic
from stereodem.sensor.io.sidecar import load_image_model

from . import __version__
from .config import Config
from .tiles import SharedArray, Tile, pool_size, process_peak_rss_mb, run_tiles

log = logging.getLogger(__name__)


def _peak_rss_mb():
    """Peak resident memory (MB) of this process (:func:`process_peak_rss_mb`) and of its
    largest finished child (``ru_maxrss``, which for a forked child includes the parent's
    pages at the fork: tile summaries carry each worker's own figure)."""
    kids = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
    return round(process_peak_rss_mb(), 1), round(kids, 1)


@dataclass
class StageLog:
    """Timings (s) and peak resident memory (MB, this process / largest worker) per stage."""

    stages: dict = field(default_factory=dict)

    def record(self, name, t0, **extra):
        own, kids = _peak_rss_mb()
        self.stages[name] = dict(seconds=round(time.perf_counter() - t0, 3), peak_rss_mb=own,
                                 peak_worker_rss_mb=kids, **extra)
        log.info("stage %s: %.1f s", name, self.stages[name]["seconds"])


# ----------------------------------------------------------------------------- stages

def load_inputs(cfg: Config):
    """Read both images (band 1, float32) and their sensor models."""
    out = []
    for path in (cfg.inputs.left, cfg.inputs.right):
        model = load_image_model(path, prefer=cfg.inputs.model)
        try:
            with rasterio.open(path) as ds:
                img = ds.read(1).astype(np.float32)
                if ds.nodata is not None:
                    img[img == ds.nodata] = np.nan
        except rasterio.errors.RasterioIOError as exc:
            raise InputError(f"{path}: cannot read the image ({exc})") from None
        out.append((img, model))
    return out


def tile_runner(run_settings, progress=None, cache_dir=None):
    """A tile runner for :func:`stereodem.stereo.pipeline.make_dem` backed by :func:`run_tiles`.

    Finished tiles are cached in ``cache_dir`` (``tile_<n>.npz``) so ``--resume`` skips them.
    """
    failures = []

    def runner(process_tile, tiles, inputs, settings):
        wrapped = [Tile(i, 0, 0, 0, 0) for i in range(len(tiles))]
        pool = pool_size(run_settings.workers, len(tiles), run_settings.dask) > 0
        if cache_dir is not None:
            _check_tile_cache(Path(cache_dir), _cache_key(tiles, inputs, settings), run_settings.resume)
        with tempfile.TemporaryDirectory(prefix="shared-", dir=cache_dir) as tmp:
            if pool:       # workers map the images from disk instead of each receiving a copy
                inputs = dataclasses.replace(
                    inputs, left_image=SharedArray.create(inputs.left_image, tmp, "left"),
                    right_image=SharedArray.create(inputs.right_image, tmp, "right"))
            ctx = dict(tiles=tiles, inputs=inputs, settings=settings, fn=process_tile)
            results, fails, _ = run_tiles(_tile_job, wrapped, ctx, workers=run_settings.workers,
                                          timeout=run_settings.tile_timeout, cache_dir=cache_dir,
                                          resume=run_settings.resume, dask_address=run_settings.dask,
                                          progress=progress)
        failures.extend(fails)
        return [_tile_result(results[i]) for i in sorted(results)]

    runner.failures = failures
    return runner


def _cache_key(tiles, inputs, settings) -> str:
    """Fingerprint of everything a stereo tile's result depends on (settings, tiles, lattice,
    models, the images' bytes), so ``--resume`` never reuses tiles of another job."""
    import hashlib
    h = hashlib.sha256()
    g = inputs.grid
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
    manifest = cache_dir / "job.json"
    old = json.loads(manifest.read_text()).get("key") if manifest.exists() else None
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
    res = ctx["fn"](ctx["tiles"][tile.index], ctx["inputs"], ctx["settings"])
    res.summary["process_peak_rss_mb"] = round(process_peak_rss_mb(), 1)
    c = res.cells
    return dict(sums=c.sums, origin=np.array([c.row0, c.col0, c.n_points], np.int64),
                summary=np.array(json.dumps(res.summary, default=_json_default)))


def _tile_result(arrays):
    from stereodem.stereo.grid import CellSums
    from stereodem.stereo.pipeline import TileResult
    r0, c0, n = (int(v) for v in arrays["origin"])
    return TileResult(CellSums(r0, c0, arrays["sums"], n), json.loads(str(arrays["summary"])))


def stereo_stage(cfg: Config, left, right, *, progress=None, cache_dir=None):
    """Stereo DEM (raw): :func:`stereodem.stereo.pipeline.make_dem` with the configured tile runner."""
    from stereodem.stereo.pipeline import make_dem
    runner = tile_runner(cfg.run, progress, cache_dir=cache_dir)
    products = make_dem(left[0], right[0], left[1], right[1], cfg.stereo, runner=runner)
    return products, [f.to_dict() for f in runner.failures]


def post_stage(cfg: Config, grid, reference: DEM | None = None):
    """Blunder filters and hole filling on the raw grid; returns (heights, edit mask, report)."""
    from stereodem.post.fill import fill_holes, gaussian_smooth
    from stereodem.post.filters import default_chain
    z = grid.height
    mask = np.zeros(z.shape, np.uint8)
    report = {}
    if cfg.filters.enabled:
        res = default_chain(thesis=cfg.filters.thesis).apply(
            z, score=grid.score, ray_gap=grid.ray_gap, transform=grid.transform, crs=grid.crs)
        z, mask = res.heights, res.removed.copy()
        report["filters"] = res.report
    if cfg.filters.enabled and cfg.filters.erode > 0:
        # matches along the border of the overlap use partial windows: drop a rim of cells
        import cv2
        valid = np.isfinite(z).astype(np.uint8)
        k = 2 * cfg.filters.erode + 1
        rim = (valid == 1) & (cv2.erode(valid, np.ones((k, k), np.uint8), borderValue=0) == 0)
        z = np.where(rim, np.nan, z)
        mask[rim] = 99
        report["erode"] = {"cells": int(cfg.filters.erode), "removed": int(rim.sum())}
    if cfg.fill.enabled:
        use = cfg.fill.fallback and cfg.stereo.seed_dem is not None
        fallback = _fallback_on_grid(cfg.stereo.seed_dem, grid) if use else None
        fr = fill_holes(z, max_hole_size=cfg.fill.max_hole_size, fallback=fallback)
        z = fr.heights
        mask[fr.filled == 1] = 100
        mask[fr.filled == 2] = 101
        report["fill"] = fr.report
        if cfg.fill.smooth_sigma > 0:
            z = gaussian_smooth(z, sigma=cfg.fill.smooth_sigma)
    return z.astype(np.float32), mask, report


def _fallback_on_grid(seed, grid):
    """The seed DEM warped onto the stereo grid, in the grid's vertical reference."""
    from stereodem.sensor.geo.dem import as_dem
    seed = as_dem(seed).to_reference(grid.vertical)
    out = np.full(grid.height.shape, np.nan, np.float32)
    rasterio.warp.reproject(seed.heights, out, src_transform=seed.transform, src_crs=seed.crs.to_wkt(),
                            dst_transform=grid.transform, dst_crs=grid.crs.to_wkt(),
                            resampling=rasterio.warp.Resampling.bilinear, src_nodata=np.nan,
                            dst_nodata=np.nan)
    return out


def ortho_stage(cfg: Config, inputs, dem: DEM, *, progress=None):
    """Orthoimages of the left (and right) image on one grid against the clean DEM.

    Row blocks of the grid run on ``cfg.run.workers`` threads (the image is shared, not
    copied; numpy and OpenCV release the GIL); the result does not depend on the count.
    """
    from stereodem.ortho.drm import orthorectify
    orthos = {}
    grid = None
    names = ("left", "right") if cfg.ortho.both else ("left",)
    threads = cfg.run.workers or os.cpu_count() or 1
    for name, (img, model) in zip(names, inputs):
        o = orthorectify(img, model, dem, grid=grid, res=cfg.ortho.res,
                         resampling=cfg.ortho.resampling, progress=progress, threads=threads)
        grid = grid or o.grid
        orthos[name] = o
    return orthos


def assess_stage(cfg: Config, dem_path, out_dir):
    """Accuracy report of the clean DEM against the reference DEM and check points."""
    from stereodem.post.assess import assess_dem
    from stereodem.post.report import write_report
    a = assess_dem(dem_path, cfg.inputs.reference_dem, coregister=cfg.assess.coregister,
                   checkpoints=cfg.inputs.checkpoints, landcover=cfg.inputs.landcover,
                   ref_vertical=cfg.inputs.reference_vertical)
    write_report(a, out_dir, overwrite=True)
    return a.report


# ----------------------------------------------------------------------------- the run

def run(cfg: Config, *, progress_factory=None) -> dict:
    """Run the whole job; returns the ``run.json`` content.

    ``progress_factory(label)`` may return a ``progress(done, total)`` callable per stage.
    """
    out = prepare_output_dir(cfg.output_dir, overwrite=cfg.run.overwrite or cfg.run.resume)
    prog = progress_factory or (lambda label: None)
    stages = StageLog()
    t_all = time.perf_counter()

    t0 = time.perf_counter()
    inputs = load_inputs(cfg)
    stages.record("load", t0)

    t0 = time.perf_counter()
    bar = prog("stereo")
    products, failed = stereo_stage(cfg, *inputs, progress=bar, cache_dir=out / "tiles")
    _close(bar)
    grid = products.grid
    grid.write(out / "raw", overwrite=True)
    tile_rss = [t.get("process_peak_rss_mb", 0.0) for t in products.tiles]
    stages.record("stereo", t0, tiles=len(products.tiles), points=int(products.n_points),
                  failed_tiles=len(failed), tile_process_peak_rss_mb=max(tile_rss, default=0.0))

    t0 = time.perf_counter()
    z, mask, post_report = post_stage(cfg, grid)
    clean = DEM(z, grid.transform, grid.crs, grid.vertical, str(out / "dem.tif"))
    clean.write(out / "dem.tif", overwrite=True)
    write_geotiff(out / "dem_edit_mask.tif", mask, grid.transform, grid.crs, 255, overwrite=True)
    stages.record("post", t0, valid_pct=round(float(100 * np.isfinite(z).mean()), 3))

    orthos = {}
    if cfg.ortho.enabled:
        t0 = time.perf_counter()
        bar = prog("ortho")
        orthos = ortho_stage(cfg, inputs, clean, progress=bar)
        _close(bar)
        for name, o in orthos.items():
            o.write(out / f"ortho_{name}.tif", overwrite=True)
        stages.record("ortho", t0, interpolation_error_px={k: o.interpolation_error_px for k, o in orthos.items()})

    report = None
    if cfg.assess.enabled and cfg.inputs.reference_dem:
        t0 = time.perf_counter()
        report = assess_stage(cfg, out / "dem.tif", out / "assess")
        stages.record("assess", t0)

    import cv2
    import pyproj
    import scipy
    info = dict(
        stereodem=__version__, python=platform.python_version(), numpy=np.__version__,
        scipy=scipy.__version__, opencv=cv2.__version__, rasterio=rasterio.__version__,
        gdal=rasterio.__gdal_version__, pyproj=pyproj.__version__, platform=platform.platform())
    run_info = dict(config=cfg.to_dict(), versions=info, stages=stages.stages,
                    seconds=round(time.perf_counter() - t_all, 3), failed_tiles=failed,
                    stereo=dict(tiles=products.tiles, info=products.info), post=post_report,
                    outputs=sorted(p.name for p in out.iterdir()),
                    headline=_headline(report))
    write_text_atomic(out / "run.json", json.dumps(run_info, indent=1, default=_json_default),
                      overwrite=True)
    return run_info


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
