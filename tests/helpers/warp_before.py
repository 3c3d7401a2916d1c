"""``core.warp.to_grid`` as it read its source before (up to 323fb35), for the tests and
``benchmarks/bench_warp_blocks.py`` to compare with: between two CRSs the whole source array
was written into an in-memory GeoTIFF at every call and read through a ``WarpedVRT``, so each
block of a blockwise warp copied the whole source."""

from unittest import mock

from rasterio.io import MemoryFile
from rasterio.vrt import WarpedVRT

from stereodem.core import warp

_REPROJECT = warp._reproject


def reproject_in_memory_geotiff(
    src, dst, src_transform, *, src_crs, dst_crs, src_nodata, dst_nodata, **kw
):
    """``core.warp._reproject`` before: the same arguments, the same-CRS branch unchanged."""
    if warp.same_horizontal_crs(src_crs, dst_crs):
        return _REPROJECT(
            src,
            dst,
            src_transform,
            src_crs=src_crs,
            dst_crs=dst_crs,
            src_nodata=src_nodata,
            dst_nodata=dst_nodata,
            **kw,
        )
    bands = src[None] if src.ndim == 2 else src
    with MemoryFile() as mem:
        with mem.open(
            driver="GTiff",
            width=bands.shape[2],
            height=bands.shape[1],
            count=bands.shape[0],
            dtype=bands.dtype,
            crs=src_crs,
            transform=src_transform,
            nodata=src_nodata,
        ) as ds:
            ds.write(bands)
        with (
            mem.open() as ds,
            WarpedVRT(
                ds,
                crs=dst_crs,
                transform=kw["dst_transform"],
                width=dst.shape[-1],
                height=dst.shape[-2],
                nodata=dst_nodata,
                dtype=dst.dtype.name,
                resampling=kw["resampling"],
                tolerance=warp.TRANSFORM_TOLERANCE_PX,
                warp_extras={"NUM_THREADS": kw["num_threads"]},
            ) as vrt,
        ):
            out = vrt.read()
    dst[...] = out[0] if dst.ndim == 2 else out


def reading_as_before():
    """A context in which every ``to_grid`` (and what calls it) reads its source as before."""
    return mock.patch.object(warp, "_reproject", reproject_in_memory_geotiff)


def to_grid_before(*args, **kw):
    """``to_grid`` as it was: the same function on the former reading of the source."""
    with reading_as_before():
        return warp.to_grid(*args, **kw)
