"""The DEM stack container: co-registered DEMs of many dates on one grid, as a chunked
xarray dataset in Zarr (``OUT/stack.zarr``), and the rates fitted from it blockwise.

Layout (CF conventions, so that plain xarray and rioxarray read it):

=================  ===================  =======  =================================================
variable           dims                 dtype    meaning
=================  ===================  =======  =================================================
``height``         (time, y, x)         float32  co-registered heights (m, the reference's vertical
                                                 reference), NaN where the DEM has no data
``mask``           (time, y, x)         uint8    bit flags :data:`MASK_VOID` (no data),
                                                 :data:`MASK_CLOUD` (cloud mask: radiance, score
                                                 or deviation from the reference)
``sigma``          (time,)              float32  per-DEM σ (m): NMAD of DEM − reference on stable
                                                 terrain after co-registration, clouds left out
``reference``      (y, x)               float32  the reference heights (m)
``stable``         (y, x)               uint8    1 = stable terrain (outside ``--exclude``)
``decimal_year``   (time,)              float64  coordinate: the dates as decimal years
``spatial_ref``    ()                   int      grid mapping: ``crs_wkt``, ``spatial_ref``,
                                                 ``GeoTransform`` (GDAL order)
=================  ===================  =======  =================================================

``x``/``y`` are the cell centres in the CRS's units. On disk one chunk holds one date and
``chunk × chunk`` cells (each DEM is written as it is processed, without reading the others);
:func:`open_stack` rechunks to all dates per block for the per-cell fits. Dataset attributes
hold the per-DEM co-registration reports (JSON text, ``dem_reports``).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from affine import Affine
from pyproj import CRS

from stereodem.core import jsonutil
from stereodem.core.errors import InputError
from stereodem.core.grid import MapGrid
from stereodem.sensor.simulation.multidate import decimal_year

from .rates import RATE_LAYERS, RateSettings, fit_block

log = logging.getLogger(__name__)

MASK_VOID = 1
MASK_CLOUD = 2
#: default chunk edge (cells)
CHUNK = 256


def grid_coords(grid: MapGrid):
    """Cell-centre coordinates ``x`` (columns) and ``y`` (rows) of ``grid``, 1-D float64."""
    t = grid.transform
    if t.b or t.d:
        raise InputError("the stack grid must be north-up (no rotation terms)")
    x = t.c + t.a * (np.arange(grid.width) + 0.5)
    y = t.f + t.e * (np.arange(grid.height) + 0.5)
    return x, y


def grid_mapping_attrs(grid: MapGrid) -> dict:
    """Attributes of the ``spatial_ref`` coordinate (CF grid mapping as GDAL/rioxarray write)."""
    wkt = grid.crs.to_wkt()
    t = grid.transform
    return {
        "crs_wkt": wkt,
        "spatial_ref": wkt,
        "GeoTransform": " ".join(repr(float(v)) for v in (t.c, t.a, t.b, t.f, t.d, t.e)),
    }


def _dataset(grid: MapGrid, dates, *, chunk: int, reference, stable):
    import dask.array as da
    import xarray as xr

    x, y = grid_coords(grid)
    T, (ny, nx) = len(dates), grid.shape
    ch = (1, min(chunk, ny), min(chunk, nx))
    gm = {"grid_mapping": "spatial_ref"}
    geographic = grid.crs.is_geographic
    xattrs = (
        {"standard_name": "longitude", "units": "degrees_east"}
        if geographic
        else {"standard_name": "projection_x_coordinate", "units": "metre"}
    )
    yattrs = (
        {"standard_name": "latitude", "units": "degrees_north"}
        if geographic
        else {"standard_name": "projection_y_coordinate", "units": "metre"}
    )
    times = np.array([np.datetime64(d, "ns") for d in dates])
    ds = xr.Dataset(
        {
            "height": (
                ("time", "y", "x"),
                da.full((T, ny, nx), np.nan, dtype=np.float32, chunks=ch),
                {**gm, "units": "metre", "long_name": "co-registered height"},
            ),
            "mask": (
                ("time", "y", "x"),
                da.zeros((T, ny, nx), dtype=np.uint8, chunks=ch),
                {**gm, "flag_masks": [MASK_VOID, MASK_CLOUD], "flag_meanings": "void cloud"},
            ),
            "sigma": (
                ("time",),
                np.full(T, np.nan, np.float32),
                {
                    "units": "metre",
                    "long_name": "per-DEM sigma: stable-terrain NMAD after co-registration",
                },
            ),
            "reference": (
                ("y", "x"),
                np.asarray(reference, np.float32),
                {**gm, "units": "metre", "long_name": "reference height"},
            ),
            "stable": (
                ("y", "x"),
                np.asarray(stable, np.uint8),
                {**gm, "long_name": "stable terrain (1)"},
            ),
        },
        coords={
            "time": ("time", times),
            "x": ("x", x, xattrs),
            "y": ("y", y, yattrs),
            "decimal_year": ("time", np.array([decimal_year(d) for d in dates])),
            "spatial_ref": ((), 0, grid_mapping_attrs(grid)),
        },
        attrs={"title": "stereodem DEM stack", "Conventions": "CF-1.8"},
    )
    for name in ("reference", "stable"):
        ds[name].encoding["chunks"] = ch[1:]
    ds["sigma"].encoding["chunks"] = (T,)
    return ds


def create_stack(
    path, grid: MapGrid, dates, *, reference, stable, chunk: int = CHUNK, attrs: dict | None = None
):
    """Create ``path`` (a Zarr store) for ``dates`` on ``grid``: metadata, coordinates, the
    reference and stable layers; heights and masks are filled by :func:`write_date`."""
    ds = _dataset(grid, dates, chunk=chunk, reference=reference, stable=stable)
    ds.attrs.update(attrs or {})
    ds.to_zarr(str(path), mode="w-", compute=False, consolidated=True, zarr_format=2)


def write_date(path, index: int, heights, mask, sigma: float):
    """Write date ``index`` of the stack at ``path``: heights (m), mask flags, per-DEM σ."""
    import xarray as xr

    h = np.asarray(heights, np.float32)[None]
    m = np.asarray(mask, np.uint8)[None]
    part = xr.Dataset(
        {
            "height": (("time", "y", "x"), h),
            "mask": (("time", "y", "x"), m),
            "sigma": (("time",), np.array([sigma], np.float32)),
        }
    )
    part.to_zarr(
        str(path), region={"time": slice(index, index + 1), "y": slice(None), "x": slice(None)}
    )


def set_attrs(path, **attrs):
    """Add dataset attributes to the store: strings and numbers as they are (a non-finite
    number as null), anything else as a strict JSON string (:mod:`stereodem.core.jsonutil`)."""
    import zarr

    g = zarr.open_group(str(path), mode="r+")
    g.attrs.update(
        {
            k: jsonutil.json_ready(v)
            if isinstance(v, (str, int, float))
            else jsonutil.dumps(v, indent=None).rstrip("\n")
            for k, v in attrs.items()
        }
    )
    zarr.consolidate_metadata(str(path))


def open_stack(path, *, chunk: int | None = CHUNK):
    """The stack at ``path`` as an :class:`xarray.Dataset` (dask-backed, all dates per block of
    ``chunk × chunk`` cells). :class:`InputError` when it is not a stack."""
    import xarray as xr

    try:
        ds = xr.open_zarr(
            str(path), chunks=None if chunk is None else {"time": -1, "y": chunk, "x": chunk}
        )
    except (OSError, ValueError, KeyError) as exc:
        raise InputError(
            f"{path}: not a readable stack ({str(exc).splitlines()[0][:100]})"
        ) from None
    missing = {"height", "mask", "sigma"} - set(ds.data_vars)
    if missing:
        raise InputError(f"{path}: not a stereodem stack (no {', '.join(sorted(missing))})")
    return ds


def stack_grid(ds) -> MapGrid:
    """The :class:`MapGrid` of a stack dataset (from ``spatial_ref``)."""
    sr = ds["spatial_ref"].attrs
    c, a, b, f, d, e = (float(v) for v in sr["GeoTransform"].split())
    return MapGrid(
        Affine(a, b, c, d, e, f), ds.sizes["x"], ds.sizes["y"], CRS.from_wkt(sr["crs_wkt"])
    )


def stack_rates(ds, *, settings: RateSettings | None = None, workers: int = 1) -> dict:
    """Rates per cell of a stack (:func:`stereodem.post.rates.fit_rates` on every block of
    cells, in parallel on ``workers`` threads; masked observations left out).

    Returns a dict of 2-D arrays: the :data:`~stereodem.post.rates.RATE_LAYERS` (``n_obs`` and
    ``n_rejected`` as int16).
    """
    import dask
    import xarray as xr

    settings = settings or RateSettings()
    if ds.sizes["time"] < 2:
        raise InputError("a rate needs at least 2 dates in the stack")
    times = ds["decimal_year"].values.astype(np.float64)
    sigma = ds["sigma"].values.astype(np.float64)
    if not np.all(np.isfinite(sigma) & (sigma > 0)):
        raise InputError(f"stack: per-DEM sigma must be finite and positive, got {sigma.tolist()}")
    valid = ds["mask"] == 0
    out = xr.apply_ufunc(
        fit_block,
        ds["height"],
        valid,
        input_core_dims=[["time"], ["time"]],
        output_core_dims=[["layer"]],
        dask="parallelized",
        output_dtypes=[np.float32],
        dask_gufunc_kwargs={"output_sizes": {"layer": len(RATE_LAYERS)}},
        kwargs=dict(times=times, sigma=sigma, settings=settings),
    )
    with dask.config.set(scheduler="threads", num_workers=max(int(workers), 1)):
        arr = out.transpose("layer", "y", "x").values
    res = {k: arr[i] for i, k in enumerate(RATE_LAYERS)}
    for k in ("n_obs", "n_rejected"):
        res[k] = res[k].astype(np.int16)
    return res


def stack_path(out) -> Path:
    return Path(out) / "stack.zarr"
