"""A GeoTIFF damaged in a block the input checks do not probe (test helper)."""

from __future__ import annotations

import shutil

import rasterio

from stereodem.core.dem import DEM
from stereodem.core.errors import DEMError


def damage_a_middle_block(src, dst) -> bool:
    """``dst``: ``src`` (a tiled GeoTIFF of 3 blocks or more) with the bytes of its second
    block (the first row's second) overwritten: its first and last blocks read, which is what
    the input checks probe (:func:`stereodem.core.raster.probe_blocks`). Returns whether
    :meth:`DEM.from_file` then refuses it (it does on every GDAL stereodem runs on: see
    :func:`stereodem.core.threads.gdal_threads`)."""
    shutil.copy(src, dst)
    with rasterio.open(dst) as ds:
        assert len(list(ds.block_windows(1))) >= 3
        offset = int(ds.get_tag_item("BLOCK_OFFSET_1_0", "TIFF", bidx=1))
        size = int(ds.get_tag_item("BLOCK_SIZE_1_0", "TIFF", bidx=1))
    with open(dst, "r+b") as f:
        f.seek(offset)
        f.write(bytes(range(256)) * (size // 256) + b"\xff" * (size % 256))
    DEM.check_file(dst)  # passes: the checks probe the first and last blocks
    try:
        DEM.from_file(dst)
    except DEMError:
        return True
    return False
