"""Building a DEM stack from DEM files: each DEM co-registered to the reference with the
correction chain (:mod:`stereodem.post.coreg`), cloud-masked, put on the reference grid and
written into the Zarr store one date at a time (memory: one DEM and the reference).

Per DEM, in date order:

1. read it, reconcile its vertical reference with the reference's
   (:func:`stereodem.post.assess.reconcile_vertical`);
2. stable terrain on its grid: outside the ``exclude`` outlines and away from gross blunders
   (|DEM − reference − median| > the cloud deviation threshold, grown), so that a cloud does
   not pull the fit;
3. fit the chain on the stable terrain and apply it;
4. warp the corrected DEM onto the stack grid (bilinear);
5. the cloud mask (:func:`stereodem.post.clouds.cloud_mask`: deviation from the reference, and
   the matcher score / 3N radiance layers when the DEM's folder has them: ``score.tif`` or
   ``raw/score.tif``, ``ortho_left.tif``);
6. σ of the DEM: NMAD of DEM − reference over stable, cloud-free cells;
7. written as date ``k`` of the store (:func:`stereodem.post.stack.write_date`).
"""

from __future__ import annotations

import logging
import multiprocessing as mp
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import rasterio
from rasterio.warp import transform_bounds

from stereodem.core.dem import DEM, check_georeferenced, check_heights_band
from stereodem.core.errors import DEMError, InputError, NoOverlapError
from stereodem.core.pool import stop_pool
from stereodem.core.raster import read_image, unreadable
from stereodem.core.stats import nmad
from stereodem.core.threads import pool_initargs, pool_initializer, worker_threads

from . import warp
from .assess import reconcile_vertical
from .clouds import CloudSettings, cloud_mask, deviation_mask, grow_mask
from .coreg import parse_chain
from .coreg_run import track_heading_of
from .masks import StableMask
from .stack import CHUNK, MASK_CLOUD, MASK_VOID, create_stack, set_attrs, write_date

log = logging.getLogger(__name__)

DEFAULT_CHAIN = "nuth_kaab,deramp:1,along_track"
#: the default chain for a DEM whose ground-track heading is unknown
NO_TRACK_CHAIN = "nuth_kaab,deramp:1"
#: layers looked for beside a DEM made by stereodem (``stereodem dem``: beside it; ``stereodem
#: run``: the raw layers in ``raw/``): matcher score, 3N radiance orthoimage
SCORE_NAMES, RADIANCE_NAMES = ("score.tif", "raw/score.tif"), ("ortho_left.tif",)


@dataclass
class BuildSettings:
    """How the stack is built.

    Attributes
    ----------
    chain : str or None
        Co-registration chain (``--chain``, :func:`stereodem.post.coreg.parse_chain`); None:
        :data:`DEFAULT_CHAIN` where the DEM's ground-track heading is known (option or the
        DEM's ``STEREODEM_TRACK_HEADING`` tag), :data:`NO_TRACK_CHAIN` where it is not.
    exclude : list of paths
        Vector files of unstable terrain (glaciers, water; any CRS).
    track_angle_deg : float, optional
        Ground-track heading for ``along_track``/``cross_track`` where the DEMs carry none.
    cloud : CloudSettings
    chunk : int
        Chunk edge of the store (cells).
    """

    chain: str | None = None
    exclude: list = field(default_factory=list)
    track_angle_deg: float | None = None
    cloud: CloudSettings = field(default_factory=CloudSettings)
    chunk: int = CHUNK


def header_bounds_lonlat(path):
    """(west, south, east, north) of a raster from its header only (no pixels read)."""
    try:
        with rasterio.open(path) as ds:
            check_georeferenced(path, ds)
            check_heights_band(path, ds)
            # the corners through the transform: ``ds.bounds`` of a south-up grid has its
            # bottom above its top (and ignores rotation), which made it miss everything
            x, y = ds.transform @ (
                np.array([0, ds.width, ds.width, 0]),
                np.array([0, 0, ds.height, ds.height]),
            )
            box = (min(x), min(y), max(x), max(y))
            return transform_bounds(ds.crs, "EPSG:4326", *box, densify_pts=21)
    except rasterio.errors.RasterioIOError as exc:
        raise DEMError(unreadable(path, "DEM", exc)) from None


def check_inputs(dems, reference: DEM, *, reference_name: str | None = None):
    """Refuse, before anything is written: fewer than 2 DEMs, the same file twice, a DEM that
    does not overlap the reference. ``reference_name``: what the messages call the reference
    (default "the reference PATH"; ``stereodem change`` compares with DEM_A)."""
    if len(dems) < 2:
        raise InputError(
            f"a stack needs at least 2 DEMs, got {len(dems)}" + (f" ({dems[0]})" if dems else "")
        )
    seen = set()
    for p in dems:
        key = str(Path(p).resolve())
        if key in seen:
            raise InputError(f"{p}: given twice")
        seen.add(key)
    rb = reference.bounds_lonlat()
    for p in dems:
        warp.check_overlap(
            header_bounds_lonlat(p),
            rb,
            a_name=f"{p}",
            b_name=reference_name or f"the reference {reference.path or ''}".strip(),
        )


def exclude_mask(paths, dem: DEM) -> np.ndarray:
    """True outside the ``paths`` outlines on ``dem``'s grid (all True without outlines)."""
    m = np.ones(dem.shape, bool)
    if paths:
        m &= StableMask(exclude=list(paths)).array(dem)
    return m


def chain_for(settings: BuildSettings, heading) -> str:
    """The chain text used for a DEM whose heading is ``heading`` (None: unknown)."""
    if settings.chain:
        return settings.chain
    return DEFAULT_CHAIN if heading is not None else NO_TRACK_CHAIN


def fit_chain(reference: DEM, dem: DEM, stable, settings: BuildSettings, heading=None):
    """Fit the chain of ``settings`` on ``stable`` cells of ``dem`` (``heading``: its ground-track
    heading, degrees, or None); returns (corrected DEM, report list, chain text)."""
    text = chain_for(settings, heading)
    chain = parse_chain(text).fit(reference, dem, stable=stable, track_angle_deg=heading)
    return chain.apply(dem), chain.report(), text


def _layer_beside(dem_path, names, grid):
    """A layer stereodem wrote beside the DEM (score, radiance orthoimage) on ``grid``, or None."""
    folder = Path(dem_path).parent
    for name in names:
        p = folder / name
        if p.is_file():
            with rasterio.open(p) as ds:
                t, crs = ds.transform, ds.crs.to_wkt() if ds.crs else None
            if crs is None:
                continue
            return warp.to_grid(
                read_image(p), t, crs, grid.transform, grid.crs, grid.shape, resampling="nearest"
            )
    return None


def add_dem(reference: DEM, path, settings: BuildSettings, stable_grid):
    """One DEM co-registered and masked on the reference grid: (heights, mask flags, σ, report)."""
    dem = DEM.from_file(path)
    heading = (
        settings.track_angle_deg if settings.track_angle_deg is not None else track_heading_of(path)
    )
    dem, vnote = reconcile_vertical(dem, reference)
    ref_on_dem = warp.to_grid(
        reference.heights, reference.transform, reference.crs, dem.transform, dem.crs, dem.shape
    )
    stable = exclude_mask(settings.exclude, dem)
    if settings.cloud.max_deviation is not None:
        gross = deviation_mask(dem.heights, ref_on_dem, settings.cloud.max_deviation, stable=stable)
        stable &= ~grow_mask(gross, max(settings.cloud.grow, 1))
    corrected, report, chain = fit_chain(reference, dem, stable, settings, heading)
    g = reference.grid
    h = warp.to_grid(
        corrected.heights, corrected.transform, corrected.crs, g.transform, g.crs, g.shape
    )
    score = _layer_beside(path, SCORE_NAMES, g) if settings.cloud.min_score is not None else None
    radiance = (
        _layer_beside(path, RADIANCE_NAMES, g) if settings.cloud.max_radiance is not None else None
    )
    cloud, cinfo = cloud_mask(
        h,
        settings=settings.cloud,
        reference=reference.heights,
        score=score,
        radiance=radiance,
        stable=stable_grid,
    )
    void = ~np.isfinite(h)
    if void.all():
        raise NoOverlapError(
            f"{path}: no cell of the co-registered DEM falls on the reference grid"
        )
    flags = np.where(void, MASK_VOID, 0).astype(np.uint8)
    flags[cloud] |= MASK_CLOUD
    sel = stable_grid & ~void & ~cloud & np.isfinite(reference.heights)
    if sel.sum() < 50:
        raise InputError(
            f"{path}: only {int(sel.sum())} stable cloud-free cells overlap the "
            "reference; cannot estimate its sigma"
        )
    sigma = nmad(h[sel] - reference.heights[sel])
    if not sigma > 0:  # the rates weight each date by 1 / sigma**2
        raise InputError(
            f"{path}: its heights equal the reference's on the stable terrain (NMAD "
            f"{sigma:g} m): the reference itself, or a copy, has no error against it to weight "
            "it by; leave it out of the stack's dates"
        )
    rec = dict(
        path=str(path),
        vertical=vnote,
        chain=chain,
        track_heading_deg=heading,
        coregistration=report,
        clouds=cinfo,
        sigma=sigma,
        valid_pct=round(100.0 * (~void).mean(), 3),
        score_layer=score is not None,
        radiance_layer=radiance is not None,
    )
    return h, flags, sigma, rec


_WORKER: dict = {}


def _init_worker(reference, settings, stable_grid, store):
    """Process-pool initialiser: what every DEM of the stack needs, sent once per process."""
    _WORKER.update(reference=reference, settings=settings, stable=stable_grid, store=store)


def _add_and_write(k: int, path: str):
    """One DEM into date ``k`` of the store (in a worker process); returns its report. Dates
    are separate chunks, so processes never write the same chunk."""
    w = _WORKER
    h, flags, sigma, rec = add_dem(w["reference"], path, w["settings"], w["stable"])
    write_date(w["store"], k, h, flags, sigma)
    return rec


def build_stack(
    dems,
    dates,
    reference: DEM,
    store,
    settings: BuildSettings | None = None,
    progress=None,
    workers: int = 1,
) -> list[dict]:
    """Build the stack at ``store`` (a Zarr path) from ``dems`` (paths) with ``dates``
    (datetime64) on ``reference``'s grid; returns one report per DEM (date order).

    ``workers`` > 1 processes that many DEMs at a time in separate processes (memory: one DEM's
    working set per process, plus the reference in each). ``progress``: optional callable
    ``progress(done, total)``."""
    settings = settings or BuildSettings()
    order = np.argsort(np.array(dates, dtype="datetime64[s]"), kind="stable")
    dems = [dems[i] for i in order]
    dates = [dates[i] for i in order]
    g = reference.grid
    stable_grid = exclude_mask(settings.exclude, reference)
    create_stack(
        store,
        g,
        dates,
        reference=reference.heights,
        stable=stable_grid,
        chunk=settings.chunk,
        attrs={
            "reference_path": str(reference.path),
            "chain": settings.chain
            or f"default: {DEFAULT_CHAIN} ({NO_TRACK_CHAIN} without a track heading)",
            "vertical_reference": str(reference.vertical),
        },
    )
    records = [None] * len(dems)

    def done(k, rec):
        rec["date"] = str(np.datetime64(dates[k], "s"))
        records[k] = rec
        log.info(
            "%s (%s): sigma %.2f m, clouds %.2f %%",
            rec["path"],
            rec["date"],
            rec["sigma"],
            rec["clouds"]["cloud_pct"],
        )
        if progress:
            progress(sum(r is not None for r in records), len(dems))

    if workers <= 1 or len(dems) < 2:
        for k, p in enumerate(dems):
            h, flags, sigma, rec = add_dem(reference, p, settings, stable_grid)
            write_date(store, k, h, flags, sigma)
            done(k, rec)
    else:
        pool = ProcessPoolExecutor(
            max_workers=min(workers, len(dems)),
            mp_context=mp.get_context("spawn"),
            # each process pinned to its share of the cores (BLAS, OpenCV, GDAL), as the tile
            # pool's are (spawned, each inherited the whole budget of the parent)
            initializer=pool_initializer,
            initargs=pool_initargs(
                worker_threads(min(workers, len(dems))),
                _init_worker,
                reference,
                settings,
                stable_grid,
                str(store),
            ),
        )
        try:
            futures = {pool.submit(_add_and_write, k, str(p)): k for k, p in enumerate(dems)}
            for f in as_completed(futures):
                done(futures[f], f.result())
        except BaseException:  # Ctrl-C, SIGTERM, a failed DEM: stop the workers now
            stop_pool(pool)
            raise
        pool.shutdown(wait=True)
    set_attrs(store, dem_reports=records, sources=[str(p) for p in dems])
    return records
