"""Rasters written block by block, finished as one Cloud-Optimised GeoTIFF, atomically.

GDAL's COG driver only copies a whole dataset (``CreateCopy``), so a raster too large to hold
is first written window by window into a tiled GeoTIFF beside the destination, then copied to
a COG (GDAL streams the copy and builds the overviews from the file, not from memory), and
moved into place with ``os.replace``. Nothing appears under the final name unless the whole
raster was written; both temporary files are removed on failure.

Memory: the caller's blocks plus GDAL's block cache (``GDAL_CACHEMAX``, set here to
:data:`CACHE_MB`) and, while the COG is finished, the overview builder's chunk
(``GDAL_OVR_CHUNK_MAX_SIZE``, :data:`OVERVIEW_CHUNK_MB`), whatever the raster's size.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import numpy as np
import rasterio
import rasterio.crs
from rasterio.windows import Window

from .raster import (
    VERTICAL_TAG,
    atomic_path,
    check_creation_options,
    check_writable,
    cog_creation_options,
    copy_to_cog,
    crs_with_vertical,
    geotiff_crs,
    write_pam_crs,
)

__all__ = ["CACHE_MB", "BlockWriter"]

#: GDAL block cache while writing and converting (MB)
CACHE_MB = 32
#: largest chunk GDAL's overview builder holds at once while finishing the COG (MB)
OVERVIEW_CHUNK_MB = 8


class BlockWriter:
    """Write a float32 multi-band raster in windows, then publish it as a COG.

    Use as a context manager::

        with BlockWriter(path, grid, ["height", "count"], vertical="geoid") as w:
            w.write(row0, col0, arrays)        # (bands, rows, cols)

    Parameters
    ----------
    path : path
        Destination (a ``.tif``); refused if it exists and not ``overwrite``.
    grid : stereodem.core.grid.MapGrid
        Output grid (transform, size, horizontal CRS).
    descriptions : list of str
        One band description per band; ``units`` one unit each (or one for all).
    vertical : {"geoid", "ellipsoid"} or None
        Vertical reference of the heights, put in the CRS (as :func:`write_geotiff` does).
    geoid_crs : pyproj.CRS, optional
        With ``vertical="geoid"``: the geoid's vertical CRS when it is not EGM96
        (:attr:`stereodem.core.dem.DEM.geoid_crs`).
    creation_options : dict or list of "KEY=VALUE", optional
        COG creation options on top of the project's defaults.
    tags : dict, optional
        Dataset tags.
    """

    def __init__(
        self,
        path,
        grid,
        descriptions,
        *,
        units="metre",
        vertical=None,
        geoid_crs=None,
        overwrite=False,
        creation_options=None,
        tags=None,
    ):
        self.path = check_writable(path, overwrite)
        self.grid = grid
        self.descriptions = list(descriptions)
        self.units = (
            [units] * len(self.descriptions)
            if isinstance(units, str) or units is None
            else list(units)
        )
        self.vertical = vertical
        self.geoid_crs = geoid_crs
        check_creation_options(creation_options, source=f"{self.path}: creation options")
        self.co = cog_creation_options(np.float32, creation_options)
        self.tags = {k: str(v) for k, v in (tags or {}).items()}
        if vertical:
            self.tags[VERTICAL_TAG] = vertical
        self._atomic = None
        self.cog_seconds = 0.0  # the final copy to a COG (compression, overviews)
        self._ds = None
        self._tmp = None

    def __enter__(self):
        self._env = rasterio.Env(
            GDAL_CACHEMAX=CACHE_MB, GDAL_OVR_CHUNK_MAX_SIZE=str(OVERVIEW_CHUNK_MB * 2**20)
        )
        self._env.__enter__()
        self._atomic = atomic_path(self.path)
        self._final_tmp = self._atomic.__enter__()
        fd, self._tmp = tempfile.mkstemp(
            prefix=f".{self.path.name}.", suffix=".blocks.tif", dir=self.path.parent
        )
        os.close(fd)
        g = self.grid
        crs, self._side_crs = geotiff_crs(crs_with_vertical(g.crs, self.vertical, self.geoid_crs))
        profile = dict(
            driver="GTiff",
            width=g.width,
            height=g.height,
            count=len(self.descriptions),
            dtype="float32",
            nodata=np.nan,
            tiled=True,
            blockxsize=256,
            blockysize=256,
            compress="ZSTD",
            zstd_level=1,
            predictor=3,
            bigtiff="IF_SAFER",
            transform=g.transform,
            crs=rasterio.crs.CRS.from_wkt(crs.to_wkt()),
        )
        # georeferenced (a map grid): no warning to silence, and no warnings.catch_warnings,
        # which is not thread-safe (these writers run beside other threads)
        self._ds = rasterio.open(self._tmp, "w", **profile)
        return self

    def write(self, row0: int, col0: int, arrays):
        """Write ``arrays`` (bands, rows, cols) with its top-left cell at ``row0, col0``."""
        a = np.asarray(arrays, dtype=np.float32)
        if a.ndim == 2:
            a = a[None]
        self._ds.write(a, window=Window(int(col0), int(row0), a.shape[2], a.shape[1]))

    def __exit__(self, exc_type, exc, tb):
        try:
            if self._ds is not None and exc_type is None:
                for i, (desc, unit) in enumerate(
                    zip(self.descriptions, self.units, strict=True), start=1
                ):
                    self._ds.set_band_description(i, desc)
                    if unit:
                        self._ds.set_band_unit(i, unit)
                if self.tags:
                    self._ds.update_tags(**self.tags)
            if self._ds is not None:
                self._ds.close()
            if exc_type is None:
                t0 = time.perf_counter()
                # one thread: GDAL's overview chunks (GDAL_OVR_CHUNK_MAX_SIZE) are per thread
                g, nbytes = self.grid, 4 * len(self.descriptions)
                copy_to_cog(
                    self._tmp,
                    self._final_tmp,
                    self.co,
                    path=self.path,
                    nbytes=nbytes * g.width * g.height,  # float32 bands
                )
                self.cog_seconds = time.perf_counter() - t0
                if self._side_crs is not None:  # moved into place with the file
                    write_pam_crs(self._final_tmp, self._side_crs)
        except BaseException as err:
            self._atomic.__exit__(type(err), err, err.__traceback__)
            raise
        else:
            self._atomic.__exit__(exc_type, exc, tb)
        finally:
            for f in (self._tmp, f"{self._tmp}.aux.xml"):
                if f and os.path.exists(f):
                    os.unlink(f)
            self._env.__exit__(None, None, None)
        return False

    @property
    def final_path(self) -> Path:
        return self.path
