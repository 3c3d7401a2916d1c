"""``stereodem run``: every stage into one folder, with ``run.json``.

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

import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stereodem.core import jsonutil
from stereodem.core.dem import edit_mask_path
from stereodem.core.errors import InputError
from stereodem.core.raster import write_text_atomic
from stereodem.core.threads import job_threads, lower_thread_priority, thread_budget
from stereodem.post.coreg_run import track_tags
from stereodem.stereo import sanity

from .. import point_cloud
from ..config import Config
from ..multiview import run_stage, source_pairs
from ..outlock import output_folder, remove_tile_cache
from ..provenance import begin, provenance
from .inputs import check_inputs, input_paths, load_pair, pair_names
from .prefetch import AssessmentPrefetch
from .record import StageLog, headline, versions
from .stages import (
    assess_stage,
    ortho_stage,
    post_stage,
    stereo_stage,
    suspect_error,
    uncertainty_stage,
)

log = logging.getLogger(__name__)


def run(cfg: Config, *, progress_factory=None) -> dict:
    """Run the whole job; returns the ``run.json`` content.

    The output folder is locked for the job (:func:`stereodem.outlock.output_folder`); with
    ``overwrite`` the previous job's products are removed first, with ``resume`` its tile
    cache is kept. Inputs are checked before any stereo work; a suspect stereo result
    (:mod:`stereodem.stereo.sanity`) stops the job after ``raw/`` and ``run.json`` are written,
    unless ``cfg.run.force``.

    ``progress_factory(label)`` may return a ``progress(done, total)`` callable per stage.
    Raises :class:`~stereodem.core.errors.InputError` when ``cfg`` is not a :class:`Config`
    (a path: read it with :func:`stereodem.config.load_config`).
    """
    if not isinstance(cfg, Config):
        raise InputError(
            f"run: expected a Config, got {type(cfg).__name__} "
            f"{cfg!r:.80}; read a TOML file with stereodem.load_config(path)"
        )
    with (
        output_folder(
            cfg.output_dir,
            overwrite=cfg.run.overwrite,
            resume=cfg.run.resume,
            inputs=input_paths(cfg),
        ) as out,
        thread_budget(cfg.run.workers),
    ):
        return _run_in(cfg, out, progress_factory)


def writer_options(cfg: Config, *, overlapped: bool = False) -> dict:
    """GeoTIFF creation options of a job's rasters: the configured ones, plus the threads GDAL
    compresses on (``NUM_THREADS``; the bytes written do not depend on it) unless the
    configuration sets it.

    A write the job waits for compresses on the job's thread budget (:func:`job_threads`).
    An ``overlapped`` write (one the :class:`BackgroundWriter` does while a following stage
    keeps the budget's threads busy) compresses on the writer's one thread: more compression
    threads would only oversubscribe the cores (at 2 workers on 2 cores, ``stereodem run`` on
    the full granule was 0.7-1.7 s faster and used 0.8-2.5 CPU-s less, three alternating
    pairs).
    """
    co = dict(cfg.run.creation_options or {})
    threads = 1 if overlapped else job_threads(cfg.run.workers)
    if not any(k.upper() == "NUM_THREADS" for k in co):
        co["NUM_THREADS"] = str(threads)
    return co


#: files the background writer compresses at once (with a thread budget of 2 or more)
_MAX_WRITERS = 2


class BackgroundWriter:
    """Threads that write output files while the run goes on (GDAL compresses with the GIL
    released, :func:`stereodem.core.raster.write_geotiff`, so a write overlaps the next
    stage's work on another core).

    ``threads``: the job's thread budget (:func:`stereodem.core.threads.job_threads`); below
    2 there is no core to spare, so each write runs at once in the calling thread and a job
    of one worker keeps to one core. Otherwise two files are written at once
    (:data:`_MAX_WRITERS`): the two orthoimages, queued together, then compress side by side
    on the cores the assessment leaves idle and in the final wait (at 2 workers on 2 cores,
    ``stereodem run`` on the full granule: the final wait 0.34-0.42 s instead of 0.51-0.90 s,
    three alternating pairs), for a higher peak of memory while both are written (the
    assessment's peak 1.83-1.90 GB instead of 1.68-1.71 GB, two alternating pairs). More
    would add a file's buffers to the peak for each; the files' bytes do not depend on it.

    The writer threads run at a lower CPU priority
    (:func:`stereodem.core.threads.lower_thread_priority`, Linux): while a stage keeps every
    core busy it takes little of them, and it compresses at full speed on the cores that
    stage leaves idle or while the job waits for it. At 2 workers on 2 cores the orthoimages'
    writes then ran beside the single-threaded drawing of the report's figures instead of
    beside the assessment's blocks: the assessment and the final wait for the writes took
    5.21-5.68 s instead of 5.78-6.43 s, shorter in 4 of 4 alternating pairs of ``stereodem
    run`` on the full granule (0.57-0.79 s).

    ``submit(fn, *args)`` queues a write; ``wait_for(i)`` waits for the ``i``-th one,
    ``wait()`` for all, re-raising the first error. A write that failed stops the job at the
    next ``submit`` (at once without a pool: a full disk or creation options GDAL refuses for
    the raw DEM end the job there, not after the filters and orthoimages). Used as a context
    manager it waits for every queued write on exit (also when the run fails), so no file is
    left half-written.
    """

    def __init__(self, threads: int = 2):
        self._pool = (
            ThreadPoolExecutor(
                max_workers=min(threads, _MAX_WRITERS),
                thread_name_prefix="stereodem-writer",
                initializer=lower_thread_priority,
            )
            if threads >= 2
            else None
        )
        self._futures = []
        self.seconds = 0.0  # of every write, summed over the writer threads
        self._seconds_lock = threading.Lock()  # two writers may finish at once

    @property
    def count(self) -> int:
        return len(self._futures)

    def submit(self, fn, *args, **kwargs):
        def timed():
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                dt = time.perf_counter() - t0
                with self._seconds_lock:
                    self.seconds += dt

        for f in self._futures:  # an earlier write failed: the job stops here
            if f.done() and f.exception() is not None:
                raise f.exception()
        if self._pool is not None:
            self._futures.append(self._pool.submit(timed))
            return
        done = Future()  # written here and now
        self._futures.append(done)
        try:
            done.set_result(timed())
        except Exception as err:
            done.set_exception(err)
            raise

    def wait_for(self, index: int):
        if index < len(self._futures):
            self._futures[index].result()

    def wait(self):
        for f in self._futures:
            f.result()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if self._pool is not None:
            self._pool.shutdown(wait=True)
        return False


@dataclass
class Job:
    """One run in progress: its configuration and output folder, the per-stage progress
    factory, the background writer, the start (UTC text and ``perf_counter``), the stage log,
    the outputs written so far and the assessment's inputs read ahead (:mod:`.prefetch`)."""

    cfg: Config
    out: Path
    progress: Callable
    writer: BackgroundWriter
    started: str
    t_start: float = field(default_factory=time.perf_counter)
    stages: StageLog = field(default_factory=StageLog)
    written: list = field(default_factory=list)
    prefetch: AssessmentPrefetch | None = None


def _run_in(cfg: Config, out: Path, progress_factory) -> dict:
    started = begin()
    with BackgroundWriter(job_threads(cfg.run.workers)) as writer:
        job = Job(cfg, out, progress_factory or (lambda label: None), writer, started)
        try:
            return _run_stages(job)
        finally:
            if job.prefetch is not None:  # a failed job does not wait for the read ahead
                job.prefetch.close()


def _run_stages(job: Job) -> dict:
    """The stages of :func:`_run_in` after loading; GeoTIFF writes go to ``job.writer`` (a
    :class:`BackgroundWriter`) and overlap the next stage."""
    cfg, out, prog, stages, writer = job.cfg, job.out, job.progress, job.stages, job.writer
    t_all, started, written = job.t_start, job.started, job.written
    assessed = cfg.assess.enabled and bool(cfg.inputs.reference_dem)
    t0 = stages.start()
    check_inputs(cfg)
    if assessed:  # the reference DEM read ahead, in a background thread
        job.prefetch = AssessmentPrefetch(cfg, job_threads(cfg.run.workers))
    pair = None if cfg.inputs.images else load_pair(cfg)
    stages.record("load", t0)

    t0 = stages.start()
    bar = prog("stereo")
    pts = point_cloud.prepare(out, resume=cfg.run.resume) if cfg.dem.point_cloud else None
    cloud_args = None  # N-view: (source pairs, the fusion's rejections) for the point cloud
    if cfg.inputs.images:  # N-view DEM: pairs fused per cell (stereodem.multiview)
        pair, products, failed, raw = run_stage(
            cfg, progress=bar, cache_dir=out / "tiles", points_dir=pts
        )
        if pts is not None:
            cloud_args = (source_pairs(products.info.report), raw.rejected)
    else:
        products, failed = stereo_stage(
            cfg, pair, progress=bar, cache_dir=out / "tiles", points_dir=pts
        )
        raw = products.dem
    _close(bar)
    warnings = products.info.warnings
    suspect = sanity.status(warnings) == "suspect" and not cfg.run.force
    co = writer_options(cfg, overlapped=not suspect)  # the post stage follows
    writer.submit(raw.prepare_write(out / "raw" / "dem.tif", overwrite=True, creation_options=co))
    raw = None
    written.append("raw")
    tile_rss = [t.get("process_peak_rss_mb", 0.0) for t in products.tiles]
    stages.record(
        "stereo",
        t0,
        tiles=len(products.tiles),
        points=int(products.n_points),
        failed_tiles=len(failed),
        tile_process_peak_rss_mb=max(tile_rss, default=0.0),
    )

    report = post_report = None
    if not suspect:
        if job.prefetch is not None:  # the reference DEM could not be read: stop here
            job.prefetch.raise_if_failed()
        t0 = stages.start()
        clean, post_report = post_stage(cfg, products.dem, pair.seed_dem, path=out / "dem.tif")

        tags = track_tags(pair.left_model, pair.left_image.shape, clean.crs, clean.heights)
        co = writer_options(cfg, overlapped=pts is not None or cfg.ortho.enabled or assessed)
        writer.submit(
            clean.prepare_write(out / "dem.tif", overwrite=True, creation_options=co, tags=tags)
        )
        written += ["dem.tif", edit_mask_path(out / "dem.tif").name]
        stages.record(
            "post", t0, valid_pct=round(float(100 * np.isfinite(clean.heights).mean()), 3)
        )
        if pts is not None:  # the points, classified by the edit mask
            t0 = stages.start()
            if cloud_args is not None:
                pc = point_cloud.multiview_point_cloud_stage(
                    cfg,
                    out,
                    clean.grid,
                    clean.vertical,
                    *cloud_args,
                    edit_codes=clean.edit_mask,
                    keep=cfg.run.keep_tiles,
                )
                cloud_args = None
            else:
                pc = point_cloud.point_cloud_stage(
                    cfg,
                    out,
                    products,
                    clean.edit_mask,
                    grid=clean.grid,
                    pairs=_pair_names(cfg),
                    keep=cfg.run.keep_tiles,
                )
            written.append(Path(pc["path"]).name)
            stages.record("point_cloud", t0, **pc)

        if cfg.ortho.enabled:
            if job.prefetch is not None:
                job.prefetch.raise_if_failed()
            t0 = stages.start()
            bar = prog("ortho")
            images = [("left", pair.left_image, pair.left_model)]
            if cfg.ortho.both:
                images.append(("right", pair.right_image, pair.right_model))
            orthos = ortho_stage(cfg, images, clean, progress=bar)
            _close(bar)
            dtypes = {"left": pair.left_dtype, "right": pair.right_dtype}
            # the uncertainty stage waits for these writes; the assessment overlaps them
            co = writer_options(cfg, overlapped=assessed and not cfg.uncertainty.enabled)
            for name, o in orthos.items():  # in the image's own data type
                writer.submit(
                    o.write,
                    out / f"ortho_{name}.tif",
                    overwrite=True,
                    dtype=dtypes[name],
                    creation_options=co,
                )
                written.append(f"ortho_{name}.tif")
            stages.record(
                "ortho",
                t0,
                interpolation_error_px={k: o.interpolation_error_px for k, o in orthos.items()},
            )
            ortho_grid = orthos["left"].grid
            del orthos, images, o  # written: their memory goes back

        if cfg.uncertainty.enabled:
            writer.wait()  # its layers go beside dem.tif
            t0 = stages.start()
            summary, dsig = uncertainty_stage(
                cfg, pair, clean, ortho_grid, products.dem, out / "uncertainty"
            )
            dsig.write(out / "dem.tif", clean, overwrite=True)
            written += ["uncertainty", "dem_sigma_vertical.tif"]
            stages.record(
                "uncertainty",
                t0,
                shares=summary["shares"],
                sigma_horizontal_median_m=summary["sigma_horizontal_m"]["median"],
            )

        # the images and the raw layers are not needed any more (the assessment's memory)
        writer.wait_for(0)  # the raw layers are on disk (the orthoimages may still go)
        pair.left_image = pair.right_image = None
        products.dem = None
        if assessed:
            t0 = stages.start()
            report = assess_stage(
                cfg,
                clean,
                out / "assess",
                overwrite=True,
                provenance=provenance(started=started),
                reference=job.prefetch.reference(),
            )[0].report
            written.append("assess")
            stages.record("assess", t0, reference_wait_s=round(job.prefetch.waited_s, 3))

    t0 = stages.start()
    writer.wait()
    stages.record(
        "writes",
        t0,
        background_s=round(writer.seconds, 3),
        files=writer.count,
        note="GeoTIFF writes in a background thread, overlapping the following "
        "stages (their CPU counts in those stages); seconds: the wait for the "
        "last ones",
    )
    # the tile cache, for a later --resume: kept unless asked, and always after a suspect
    # result (the job stops below; --force --resume then reuses the tiles)
    if cfg.run.keep_tiles or suspect:
        written.append("tiles")
    else:
        remove_tile_cache(out)
    written.append("run.json")
    run_info = dict(
        status=sanity.status(warnings),
        warnings=warnings,
        provenance=provenance(started=started),
        config=cfg.to_dict(),
        input_metadata=pair.tags,
        versions=versions(),
        stages=stages.stages,
        seconds=round(time.perf_counter() - t_all, 3),
        failed_tiles=failed,
        stereo=dict(tiles=products.tiles, info=products.info.to_dict()),
        post=post_report,
        outputs=sorted(written),
        headline=headline(report),
    )
    write_text_atomic(out / "run.json", jsonutil.dumps(run_info), overwrite=True)
    if suspect:
        suspect_error(cfg, products, out / "run.json")
    return run_info


def _pair_names(cfg: Config) -> dict:
    """The pair cloud's source pair: ``{0: (left, right)}`` (:func:`.inputs.pair_names`)."""
    return {0: pair_names(cfg.inputs.left, cfg.inputs.right)}


def _close(bar):
    if hasattr(bar, "close"):
        bar.close()
