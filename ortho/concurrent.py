"""Several orthoimages on one map grid at once, under one thread budget.

The orthoimages of a stereo pair share the grid and the DEM but nothing else: each builds its
own backward map (exact sensor-model evaluations on a lattice, mostly numpy) and resamples its
own image (:func:`cv2.remap` on row blocks). :func:`orthorectify_all` runs them on concurrent
threads (numpy and OpenCV release the GIL), so the serial parts of one (DEM crop, backward
map, validity erosion) overlap the other's, and their row blocks go to one pool of
``threads`` threads: when the smaller orthoimage is done, the larger one's remaining blocks
take every thread (with ``threads // 2`` threads each, the last seconds of a pair ran on one
core). :func:`stereodem.ortho.drm.orthorectify` does not depend on its threads, so the
orthoimages are those of the serial calls.
"""

from __future__ import annotations

import functools
import threading
from concurrent.futures import ThreadPoolExecutor

from stereodem.core.dem import as_dem
from stereodem.core.grid import MapGrid

from .drm import Ortho, orthorectify
from .grid import grid_for_model


def orthorectify_all(
    images,
    dem,
    *,
    grid: MapGrid | None = None,
    res: float | None = None,
    crs=None,
    threads: int = 1,
    progress=None,
    **options,
) -> dict[str, Ortho]:
    """``{name: Ortho}`` of ``images`` (``[(name, image, model), ...]``) against ``dem``, all
    on ``grid`` (default :func:`~stereodem.ortho.grid.grid_for_model` of the first image with
    ``res`` metres and ``crs``, as :func:`~stereodem.ortho.drm.orthorectify` lays it).

    ``threads``: the thread budget; with 2 or more, up to ``threads`` orthoimages run at once
    and share a pool of ``threads`` row-block threads. ``progress(rows_done, rows_total)``
    counts the rows of all orthoimages (called under a lock, from the worker threads).
    ``options`` go to :func:`~stereodem.ortho.drm.orthorectify`. The first error raised (in
    image order) propagates.
    """
    images = list(images)
    dem = as_dem(dem)
    if grid is None and images:
        grid = grid_for_model(images[0][2], dem, res=res, crs=crs)
    threads = max(1, int(threads))
    running = max(1, min(len(images), threads))
    total = grid.shape[0] * len(images) if grid is not None else 0
    done, lock = {}, threading.Lock()

    def one(item, blocks):
        name, image, model = item

        def step(rows, _):
            if progress is not None:
                with lock:
                    done[name] = rows
                    progress(sum(done.values()), total)

        # the warnings name the image where there are several (the left and right images)
        label = str(name) if len(images) > 1 else None
        return name, orthorectify(
            image, model, dem, grid=grid, threads=blocks, progress=step, image_name=label, **options
        )

    if running == 1:
        return dict(one(item, threads) for item in images)
    with (
        ThreadPoolExecutor(threads, thread_name_prefix="stereodem-ortho-rows") as blocks,
        ThreadPoolExecutor(running, thread_name_prefix="stereodem-ortho") as ex,
    ):
        return dict(ex.map(functools.partial(one, blocks=blocks), images))
