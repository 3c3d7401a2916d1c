"""GeoTIFF output shared by every stage: atomic writes, no silent overwrite.

A raster is written to a temporary file in the destination folder and moved into place with
``os.replace`` only when complete, so a crash never leaves a half-written product under the
final name.
"""
from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

import numpy as np
import rasterio

from stereodem.sensor.errors import OutputExistsError


def check_writable(path, overwrite: bool = False) -> Path:
    """Raise :class:`OutputExistsError` if ``path`` exists and ``overwrite`` is false."""
    path = Path(path)
    if path.exists() and not overwrite:
        raise OutputExistsError(f"{path}: exists; pass overwrite=True (--overwrite) to replace it")
    return path


@contextlib.contextmanager
def atomic_path(path: Path):
    """Yield a temporary path beside ``path``; move it into place only if the block succeeds."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    os.close(fd)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def check_output_dir(path, *, overwrite: bool = False) -> Path:
    """Check, without creating anything, that ``path`` can become an output folder: not a file,
    not a non-empty folder (unless ``overwrite``), under a folder that can be written."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputExistsError(f"{path}: exists and is not a folder")
    if path.is_dir() and any(path.iterdir()) and not overwrite:
        raise OutputExistsError(f"{path}: folder exists and is not empty; pass --overwrite to reuse it")
    parent = path if path.is_dir() else next((p for p in path.absolute().parents if p.exists()), None)
    if parent is None or not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        raise OutputExistsError(f"{path}: cannot be created ({parent} is not a writable folder)")
    return path


def prepare_output_dir(path, *, overwrite: bool = False) -> Path:
    """Create an output folder; refuse an existing non-empty one unless ``overwrite``."""
    path = check_output_dir(path, overwrite=overwrite)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputExistsError(f"{path}: cannot create the folder ({exc.strerror})") from None
    return path


def write_geotiff(path, data, transform=None, crs=None, nodata=None, *, overwrite=False,
                  tags=None, band_tags=None, rpcs=None, compress="deflate", dtype=None):
    """Write ``data`` (2-D, or 3-D band-first) to a GeoTIFF atomically.

    Parameters
    ----------
    transform : affine.Affine
        Pixel-corner georeferencing (GDAL convention).
    nodata : float, optional
        Nodata value; NaN for float rasters is allowed and is the default for float data.
    tags : dict, optional
        Dataset tags (strings); ``band_tags`` a list of per-band tag dicts.
    rpcs : rasterio.rpc.RPC or dict, optional
        RPC metadata to embed (GDAL RFC 22 domain).
    """
    path = check_writable(path, overwrite)
    arr = np.asarray(data)
    if arr.ndim == 2:
        arr = arr[None]
    if dtype is not None:
        arr = arr.astype(dtype)
    if nodata is None and np.issubdtype(arr.dtype, np.floating):
        nodata = np.nan
    profile = dict(driver="GTiff", width=arr.shape[2], height=arr.shape[1], count=arr.shape[0],
                   dtype=arr.dtype, crs=crs, transform=transform, nodata=nodata,
                   compress=compress, tiled=arr.shape[1] >= 256 and arr.shape[2] >= 256)
    if profile["tiled"]:
        profile.update(blockxsize=256, blockysize=256)
    if transform is None:
        profile.pop("transform")
    if rpcs is not None:
        profile["rpcs"] = rpcs
    import warnings
    with atomic_path(path) as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(tmp, "w", **profile) as dst:
            dst.write(arr)
            if tags:
                dst.update_tags(**{k: str(v) for k, v in tags.items()})
            for i, bt in enumerate(band_tags or [], start=1):
                dst.update_tags(i, **{k: str(v) for k, v in bt.items()})
    return path


def write_text_atomic(path, text: str, *, overwrite=False) -> Path:
    """Write a text file atomically (temporary file + rename)."""
    path = check_writable(path, overwrite)
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text)
    return path


def read_image(path, band: int = 1) -> np.ndarray:
    """One band of an image as float32, NaN where the file marks no data.

    The one no-data rule of the project: a pixel is missing where GDAL's mask for the band says
    so (the band's nodata value, an internal mask or an alpha band) or where the value is not
    finite. Raises :class:`InputError` naming the file when it cannot be read or has no such
    band.
    """
    from stereodem.sensor.errors import InputError
    try:
        with rasterio.open(path) as ds:
            if not 1 <= int(band) <= ds.count:
                raise InputError(f"{path}: no band {band} (the image has {ds.count})")
            from .memory import check_allocation      # before reading: the header may lie
            check_allocation(ds.width * ds.height * (4 + np.dtype(ds.dtypes[band - 1]).itemsize + 1),
                             f"{path}: reading its {ds.width} x {ds.height} pixels")
            data = ds.read(int(band), masked=True)
    except rasterio.errors.RasterioIOError as exc:
        raise InputError(f"{path}: cannot read the image ({str(exc).splitlines()[0][:120]})") from None
    img = np.ma.getdata(data).astype(np.float32)
    img[np.ma.getmaskarray(data)] = np.nan
    return img
