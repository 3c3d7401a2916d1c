"""Tile execution for :func:`stereodem.stereo.pipeline.make_dem`: the process pool or Dask
(:func:`stereodem.stereo.runner.iter_tiles`), images shared through memory maps, and the tile cache
(``tiles/tile_<n>.npz``, keyed by a fingerprint of settings, models and images) that
``--resume`` reuses."""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import logging
import pickle
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor, wait
from pathlib import Path

import numpy as np

from stereodem.core.errors import InputError
from stereodem.core.jsonutil import json_default, stamped
from stereodem.core.raster import write_text_atomic
from stereodem.stereo.pipeline import TileResult
from stereodem.stereo.pointcloud import points_file
from stereodem.stereo.runner import (
    SharedArray,
    cache_file,
    clean_cache,
    iter_tiles,
    load_cached,
    pool_size,
    process_peak_rss_mb,
)
from stereodem.stereo.tiling import tile_order

log = logging.getLogger(__name__)


class ProgressPasses:
    """One ``progress(done, total)`` count over several passes of a tile loop that each count
    from 0 (the jitter correction's two DEMs, an N-view stage's pairs): a pass's tiles are
    counted after those of the passes before it, so the stage's one bar counts up once
    instead of starting again at every pass (its total grows as passes start).

    :func:`tile_runner` starts a pass (:meth:`next_pass`) at each call; a caller running
    several :func:`tile_runner` under one bar passes them the same instance."""

    def __init__(self, progress):
        self.progress, self.base, self.last = progress, 0, 0

    def next_pass(self):
        """Count the next calls after the units of the passes so far."""
        self.base, self.last = self.base + self.last, 0

    def __call__(self, done, total, *_):
        self.last = int(total)
        self.progress(self.base + int(done), self.base + int(total))


def tile_runner(run_settings, progress=None, cache_dir=None):
    """A tile runner for :func:`stereodem.stereo.pipeline.make_dem` backed by
    :func:`~stereodem.stereo.runner.iter_tiles`.

    ``run_settings`` has ``workers``, ``tile_timeout``, ``resume`` and ``dask`` (the address of
    a Dask scheduler or None): :class:`stereodem.config.RunSettings`. Finished tiles are cached in
    ``cache_dir`` (``tile_<n>.npz``) so ``--resume`` skips them. The runner yields the tiles in
    :func:`~stereodem.stereo.tiling.tile_order` as soon as each and those before it are done,
    so that the caller adds a tile's sums while the pool runs the later ones (not all of them
    after the pool: 0.5 s of one core on the full ASTER granule); ``runner.failures`` collects
    the failed tiles (by index, per call). ``progress(done, total)`` counts on over the calls
    (:class:`ProgressPasses`).
    """
    failures = []
    if progress is not None and not isinstance(progress, ProgressPasses):
        progress = ProgressPasses(progress)

    def runner(process_tile, tiles, inputs, settings):
        pool = pool_size(run_settings.workers, len(tiles), run_settings.dask) > 0
        if progress is not None:
            progress.next_pass()
        key = None
        if cache_dir is not None:  # what an interrupted run left, before this run's maps exist
            Path(cache_dir).mkdir(parents=True, exist_ok=True)
            clean_cache(cache_dir)
        by_index = {t.index: t for t in tiles}
        order = [t.index for t in tile_order(tiles)]
        failed = []
        with tempfile.TemporaryDirectory(prefix="shared-", dir=cache_dir) as tmp:
            # workers map the images from disk instead of each receiving a copy; the maps are
            # written while the cache key is hashed
            shared = _share_images(inputs, tmp) if pool else None
            try:
                if cache_dir is not None:
                    key = _cache_key(tiles, inputs, settings)
                    _check_tile_cache(Path(cache_dir), key, run_settings.resume)
            finally:
                if shared is not None:
                    inputs = shared()
            ctx = dict(inputs=inputs, settings=settings, fn=process_tile)
            reusable = _points_left(inputs, tiles, run_settings.resume, cache_dir)
            finished = iter_tiles(
                _tile_job,
                tiles,
                ctx,
                workers=run_settings.workers,
                timeout=run_settings.tile_timeout,
                cache_dir=cache_dir,
                resume=run_settings.resume,
                dask_address=run_settings.dask,
                progress=progress,
                cache_key=key,
                hold_results=cache_dir is None,
                reusable=reusable,
            )
            # tiles that end before their turn wait here: their arrays when held, else only
            # their index (a cached run's arrays are read back from the cache at their turn)
            waiting, turn = {}, 0
            with contextlib.closing(finished):
                for d in finished:
                    if d.failure is not None:
                        failed.append(d.failure)
                    waiting[d.index] = d
                    while turn < len(order) and order[turn] in waiting:
                        ready = waiting.pop(order[turn])
                        turn += 1
                        if ready.failure is None:
                            arrays = ready.result
                            if arrays is None:
                                arrays = load_cached(cache_dir, by_index[ready.index])
                            yield TileResult.from_arrays(arrays)
        failures.extend(sorted(failed, key=lambda f: f.tile.index))

    runner.failures = failures
    return runner


def _points_left(inputs, tiles, resume, cache_dir):
    """With ``resume`` and tiles that write their points (a point cloud), the test that a
    cached tile's point file is still there: the merge into ``dem.las``/``dem.laz`` removes
    them, so a tile cached without its points is recomputed (reused, it left the cloud empty).
    None when nothing needs checking."""
    folder = getattr(inputs, "points_dir", None)
    if not resume or folder is None or cache_dir is None:
        return None
    missing = {
        t.index
        for t in tiles
        if cache_file(cache_dir, t).exists() and not points_file(folder, t.index).exists()
    }
    if missing:
        log.info(
            "resume: %d cached tile(s) recomputed for the point cloud (their point files "
            "are gone: a finished job's merge removes them)",
            len(missing),
        )
    return lambda t: t.index not in missing  # each file looked at once, here


def _share_images(inputs, directory):
    """Start writing both images as :class:`SharedArray` files in ``directory``, on two threads
    (file writes and SHA-256 release the GIL, so they overlap each other and the cache key:
    0.44 s one after the other on the full ASTER granule); returns a function that waits for
    them and gives ``inputs`` with the shared images (re-raising a write error)."""
    ex = ThreadPoolExecutor(2, thread_name_prefix="stereodem-share")
    left = ex.submit(SharedArray.create, inputs.left_image, directory, "left")
    right = ex.submit(SharedArray.create, inputs.right_image, directory, "right")
    ex.shutdown(wait=False)  # the threads end with their writes

    def shared():
        wait([left, right])  # both done before the folder may be removed
        return dataclasses.replace(inputs, left_image=left.result(), right_image=right.result())

    return shared


def _cache_key(tiles, inputs, settings) -> str:
    """Fingerprint of everything a stereo tile's result depends on (settings, tiles, lattice,
    models, the images' bytes), so ``--resume`` never reuses tiles of another job."""
    h = hashlib.sha256()
    g = inputs.lattice
    h.update(
        json.dumps(
            [
                settings.summary(),
                [t.bounds for t in tiles],
                list(inputs.height_range),
                None
                if g is None
                else [
                    tuple(g.transform),
                    list(g.shape),
                    g.crs.to_wkt(),
                    g.method,
                    g.sigma,
                    g.radius,
                    g.geoid,
                ],
            ],
            default=json_default,
            sort_keys=True,
        ).encode()
    )
    for m in (inputs.left_model, inputs.right_model):
        h.update(_model_fingerprint(m))
    for img in (inputs.left_image, inputs.right_image):
        h.update(np.ascontiguousarray(img).data)
    return h.hexdigest()


def _model_fingerprint(model) -> bytes:
    """Bytes identifying a sensor model's parameters: a wrapper with a ``model`` attribute (an
    image-space correction) gives its own parameters plus its model's, other models their
    ``to_dict``, else their pickle."""
    if hasattr(model, "model") and hasattr(model, "parameters"):
        own = json.dumps(model.parameters(), sort_keys=True).encode()
        return own + _model_fingerprint(model.model)
    if hasattr(model, "to_dict"):
        d = _without_paths(model.to_dict())
        return json.dumps(d, default=json_default, sort_keys=True).encode()
    return pickle.dumps(model, protocol=4)


def _without_paths(d):
    """A model's description without the file it was read from (an ASTER model's
    ``geometry.path``): the same granule named ``g.hdf`` or ``/data/g.hdf`` (a configuration
    given by a relative path, then an absolute one) is the same model, and its tiles the same
    tiles; the images' bytes are in the key."""
    if isinstance(d, dict):
        return {k: _without_paths(v) for k, v in d.items() if k != "path"}
    return d


class OtherJobTilesError(InputError):
    """A resumed job's tile cache ``cache_dir`` holds the tiles of a job with other inputs or
    settings (the message is ``stereodem run``'s: a caller without ``--resume``, such as
    ``batch``, words its own from ``cache_dir``)."""

    def __init__(self, cache_dir):
        self.cache_dir = cache_dir
        super().__init__(cache_dir)

    def __str__(self):
        return (
            f"{self.cache_dir}: the cached tiles belong to a run with other inputs or "
            "settings; run again without --resume (and with --overwrite)"
        )


def _check_tile_cache(cache_dir: Path, key: str, resume: bool):
    """Keep the tile cache consistent with this job: on ``resume`` the cache must hold tiles of
    the same job (else :class:`InputError`); otherwise old tiles are removed first. The
    folder exists (:func:`tile_runner` made it and cleared an interrupted run's leftovers)."""
    manifest = cache_dir / "job.json"
    try:
        old = json.loads(manifest.read_text()).get("key") if manifest.exists() else None
    except (ValueError, AttributeError, UnicodeDecodeError):
        old = "unreadable"
    if resume and old is not None and old != key:
        raise OtherJobTilesError(cache_dir)
    if not resume or old is None:
        for f in cache_dir.glob("tile_*.npz"):
            f.unlink()
    write_text_atomic(manifest, json.dumps(stamped({"key": key})), overwrite=True)


def _tile_job(tile, ctx):
    """One stereo tile as plain arrays (:meth:`~stereodem.stereo.pipeline.TileResult.to_arrays`,
    cacheable), its summary with the worker's peak memory and the tile's CPU seconds (the
    process's, all its threads)."""
    cpu0 = time.process_time()
    res = ctx["fn"](tile, ctx["inputs"], ctx["settings"])
    res.summary["cpu_s"] = round(time.process_time() - cpu0, 3)
    res.summary["process_peak_rss_mb"] = round(process_peak_rss_mb(), 1)
    return res.to_arrays()
