"""GeoTIFF output shared by every stage: atomic writes, no silent overwrite.

A raster is written to a temporary file in the destination folder and moved into place with
``os.replace`` only when complete, so a crash never leaves a half-written product under the
final name. Rasters are Cloud-Optimised GeoTIFFs (GDAL's COG driver) with the vertical
reference of heights in the CRS (:func:`geotiff_crs`: a file is georeferenced on its own);
every file gets the permissions of the umask.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import shutil
import tempfile
import threading
import warnings
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import rasterio
import rasterio.crs
import rasterio.errors
import rasterio.shutil
from affine import Affine
from pyproj import CRS as PCRS
from pyproj.crs import CompoundCRS
from rasterio._err import CPLE_BaseError
from rasterio.io import MemoryFile

from stereodem.core.errors import (
    NOT_FOUND,
    CRSError,
    InputError,
    OutputExistsError,
    OutputWriteError,
    not_found,
)

from .memory import check_allocation


def check_writable(path, overwrite: bool = False) -> Path:
    """Raise :class:`OutputExistsError` if ``path`` exists and ``overwrite`` is false, is a
    folder, or cannot be created (:func:`check_creatable`)."""
    path = Path(path)
    if path.is_dir():  # before the advice to pass overwrite, which cannot replace a folder
        raise OutputExistsError(f"{path}: is a folder; give a file name")
    if path.exists() and not overwrite:
        raise OutputExistsError.needs_overwrite(f"{path}: exists")
    check_creatable(path)
    return path


def check_creatable(path) -> Path:
    """Check, leaving nothing behind, that ``path`` (a file or a folder) can be created: its
    nearest existing ancestor is a folder in which a file can be made; an existing folder
    ``path`` (an output folder given again) must take new files itself. A probe file is
    created and removed, because ``os.access`` answers yes to root even in read-only
    pseudo-file systems (``/proc``). Raises :class:`OutputExistsError` naming ``path`` (an
    existing output folder was probed as ``path/x``, and the message named that file, which
    the user never gave)."""
    path = Path(path)
    if path.is_dir():
        try:
            fd, probe = tempfile.mkstemp(prefix=".stereodem-probe-", dir=path)
        except OSError as exc:
            raise OutputExistsError(f"{path}: folder is not writable ({exc.strerror})") from None
        os.close(fd)
        os.unlink(probe)
        return path
    anc = next((p for p in path.absolute().parents if p.exists()), None)
    if anc is None or not anc.is_dir():
        raise OutputExistsError(f"{path}: cannot be created ({anc} is not a folder)")
    try:
        fd, probe = tempfile.mkstemp(prefix=".stereodem-probe-", dir=anc)
    except OSError as exc:
        raise OutputExistsError(
            f"{path}: cannot be created ({anc} is not a writable folder: {exc.strerror})"
        ) from None
    os.close(fd)
    os.unlink(probe)
    return path


def _umask() -> int:
    """The process umask: from ``/proc/self/status`` where there is one (Linux), else by
    setting and restoring it (there is no portable read-only call)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _sidecars(path) -> list[str]:
    """GDAL side-car files that belong to ``path`` (PAM ``.aux.xml``)."""
    return [f"{path}.aux.xml"]


@contextlib.contextmanager
def atomic_path(path: Path):
    """Yield a temporary path beside ``path``; move it into place only if the block succeeds.

    The file gets the permissions an ordinary ``open()`` would give it (``0o666`` less the
    umask), not the ``0o600`` of :func:`tempfile.mkstemp`. GDAL side-cars written next to the
    temporary file (``.aux.xml``, e.g. a CRS GeoTIFF keys cannot encode) are moved with it, and
    a stale side-car of a replaced file is removed.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    except OSError as exc:
        raise OutputExistsError(f"{path}: cannot be written ({exc.strerror})") from None
    os.close(fd)
    mode = 0o666 & ~_umask()
    try:
        yield tmp
        if os.path.exists(tmp):
            os.chmod(tmp, mode)
        for side_tmp, side in zip(_sidecars(tmp), _sidecars(path)):
            if os.path.exists(side_tmp):
                os.chmod(side_tmp, mode)
                os.replace(side_tmp, side)
            elif os.path.exists(side):
                os.unlink(side)  # belonged to the file being replaced
        os.replace(tmp, path)
    finally:
        for f in (tmp, *_sidecars(tmp)):
            if os.path.exists(f):
                os.unlink(f)


def check_output_dir(path, *, overwrite: bool = False) -> Path:
    """Check, without creating anything, that ``path`` can become an output folder: not a file,
    not a non-empty folder (unless ``overwrite``), under a folder that can be written."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputExistsError(f"{path}: exists and is not a folder")
    if path.is_dir() and any(path.iterdir()) and not overwrite:
        raise OutputExistsError.needs_overwrite(
            f"{path}: folder exists and is not empty", "to reuse it"
        )
    check_creatable(path)
    return path


def prepare_output_dir(path, *, overwrite: bool = False) -> Path:
    """Create an output folder; refuse an existing non-empty one unless ``overwrite``."""
    path = check_output_dir(path, overwrite=overwrite)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputExistsError(f"{path}: cannot create the folder ({exc.strerror})") from None
    return path


#: default GDAL creation options of every GeoTIFF written (Cloud-Optimised GeoTIFF driver)
COG_DEFAULTS = {
    "COMPRESS": "DEFLATE",
    "BLOCKSIZE": "256",
    "OVERVIEWS": "AUTO",
    "BIGTIFF": "IF_SAFER",
}
#: DEFLATE level when none is given: the fastest. On stereodem's float products (noisy
#: heights, resampled grey levels) level 1 costs 1-3 % more bytes than GDAL's default 6 and
#: 30-40 % less CPU (full ASTER granule: orthoimage 70.3 -> 71.1 MB, 1.73 -> 1.19 CPU s)
DEFLATE_LEVEL = "1"

#: the file's own record of its heights' vertical reference, read by
#: :meth:`stereodem.core.dem.DEM.from_file` when the CRS does not say it: files of older
#: versions, and a projected grid with ellipsoidal heights whose ``.aux.xml`` side-car (the
#: 3-D CRS, :func:`geotiff_crs`) was not copied with it
VERTICAL_TAG = "STEREODEM_VERTICAL"


def parse_creation_options(options) -> dict:
    """GDAL creation options as an upper-case dict.

    ``options`` is a dict or a sequence of ``"KEY=VALUE"`` strings (as ``--co KEY=VALUE`` on
    the command line and in GDAL's tools); raises :class:`InputError` on a malformed item.
    """
    if not options:
        return {}
    if isinstance(options, dict):
        return {str(k).upper(): str(v) for k, v in options.items()}
    out = {}
    for item in options:
        key, sep, value = str(item).partition("=")
        if not sep or not key.strip():
            raise InputError(f"creation option {item!r}: expected KEY=VALUE (e.g. COMPRESS=ZSTD)")
        out[key.strip().upper()] = value.strip()
    return out


#: GDAL's complaints (logged by rasterio as warnings) about a creation option it does not
#: know or a value it does not accept: it then ignores the option and writes the file anyway
_OPTION_COMPLAINTS = ("CPLE_NotSupported in ", "CPLE_IllegalArg in ")


class _Complaints(logging.Handler):
    """Collects GDAL's complaints about creation options (:data:`_OPTION_COMPLAINTS`) that
    rasterio logs on ``rasterio._env``."""

    def __init__(self):
        super().__init__(logging.WARNING)
        self.found = []
        self.thread = threading.get_ident()

    def emit(self, record):
        if record.thread != self.thread:  # another thread's GDAL call, not the probe
            return
        text = record.getMessage()
        for prefix in _OPTION_COMPLAINTS:
            if text.startswith(prefix) and text[len(prefix) :] not in self.found:
                self.found.append(text[len(prefix) :])


def options_text(co: dict) -> str:
    """Creation options as GDAL's tools print them (``COMPRESS=ZSTD LEVEL=9``)."""
    return " ".join(f"{k}={v}" for k, v in co.items())


def check_creation_options(
    options, *, source: str = "creation options", float_products: bool = False
) -> dict:
    """:func:`parse_creation_options`, with each option and value checked against GDAL's COG
    driver (the driver of every product) before any work: GDAL ignores an option it does not
    know (``FOO=1``) or a value it does not accept (``COMPRESS=NOPE``, ``BLOCKSIZE=13``) with
    a warning and writes the file without it, so a typo would silently give other products
    than asked for. A 16 x 16 raster is written to memory with the options (on top of the
    defaults, :func:`cog_creation_options`) and GDAL's complaints become an
    :class:`InputError` naming ``source``. What depends on a product's data type
    (``COMPRESS=JPEG`` is fine for 8-bit orthoimages, not for float heights) is checked by
    each write (:func:`copy_to_cog`), unless ``float_products`` says that the caller's
    products include float32 rasters (a DEM: every command but ``ortho``): then GDAL's
    refusal to write float32 with the options is an :class:`InputError` here as well.

    The one check of creation options: where options enter (the command line, a job's
    configuration) and in every library write (:func:`write_geotiff`,
    :class:`~stereodem.core.blockwrite.BlockWriter`, ``source`` then names the file). One
    probe per set of options (cached)."""
    co = parse_creation_options(options)
    if not co:
        return co
    found, refused = _option_complaints(tuple(cog_creation_options("float32", co).items()))
    found = list(found)
    if refused and float_products:
        found.append(f"{refused} (the products include float32 rasters)")
    if found:
        raise InputError(f"{source} {options_text(co)}: GDAL's COG driver: {'; '.join(found)}")
    return co


_PROBE_LOCK = threading.Lock()


@functools.lru_cache(maxsize=64)
def _option_complaints(items: tuple) -> tuple[tuple[str, ...], str | None]:
    """GDAL's complaints about the COG creation options ``items`` (``(KEY, VALUE)`` pairs),
    and its refusal to write float32 with them (None when it writes), from a probe write
    (:func:`_probe_cog_write`, not its cache: GDAL warns only while it writes). GDAL's
    warnings are collected from rasterio's logger (``rasterio._env``), on this thread only,
    one probe at a time."""
    complaints = _Complaints()
    log = logging.getLogger("rasterio._env")
    with _PROBE_LOCK:
        level, propagate = log.level, log.propagate
        log.addHandler(complaints)
        log.setLevel(logging.WARNING)
        log.propagate = False  # not shown to the user as well: the caller's error says it
        try:
            refused = _probe_cog_write.__wrapped__("float32", 1, items)
        finally:
            log.removeHandler(complaints)
            log.setLevel(level)
            log.propagate = propagate
    return tuple(complaints.found), refused


def _lower(co: dict) -> dict:
    """Creation options as rasterio's keyword arguments (lower-case keys)."""
    return {k.lower(): v for k, v in co.items()}


#: what a GDAL failure raises through rasterio (RasterioIOError is an OSError, not a
#: RasterioError, before rasterio 1.4)
_GDAL_ERRORS = (rasterio.errors.RasterioError, rasterio.errors.RasterioIOError, CPLE_BaseError)


@functools.lru_cache(maxsize=64)
def _probe_cog_write(dtype: str, count: int, items: tuple) -> str | None:
    """GDAL's refusal (its message) to write a COG of ``count`` bands of ``dtype`` with the
    creation options ``items`` (``(KEY, VALUE)`` pairs), found by writing 16 x 16 cells to
    memory; None when it writes. The compression runs on the calling thread (``NUM_THREADS``
    1: an error in one of GDAL's own threads is printed, not raised), which does not change
    what can be written. Cached: one probe per data type, band count and options."""
    probe = {**dict(items), "NUM_THREADS": "1"}
    profile = dict(driver="MEM", width=16, height=16, count=count, dtype=dtype)
    with rasterio.open("", "w", transform=Affine(10, 0, 0, 0, -10, 160), **profile) as src:
        src.write(np.zeros((count, 16, 16), dtype))
        with MemoryFile() as mem:
            try:
                rasterio.shutil.copy(src, mem.name, driver="COG", **_lower(probe))
            except _GDAL_ERRORS as exc:
                return " ".join(str(exc).split())
    return None


def _compression_threads(co: dict) -> str:
    """The threads GDAL compresses a COG on: ``NUM_THREADS`` of the options, else the
    ``GDAL_NUM_THREADS`` configuration (:func:`stereodem.core.threads.pin_threads`), else 1."""
    n = co.get("NUM_THREADS")
    if n is None:
        from rasterio.env import get_gdal_config

        n = get_gdal_config("GDAL_NUM_THREADS")
    return str(n or "1").strip().upper()


def copy_to_cog(src, tmp, co: dict, *, path, nbytes: int | None = None) -> None:
    """GDAL's COG copy of ``src`` (an open dataset or a file) into ``tmp`` with the creation
    options ``co`` (:func:`rasterio.shutil.copy`, which releases the GIL while it
    compresses); a GDAL failure is an :class:`OutputWriteError` naming the product ``path``
    and the options (e.g. ``COMPRESS=JPEG`` on float32 heights, ``COMPRESS=WEBP`` on one
    band, ``PREDICTOR=3`` on integers), or the full disk where the disk holding ``tmp`` has
    less free space than the raster before compression (``nbytes``; None: ``src``'s).

    With more than one compression thread (``NUM_THREADS``, else ``GDAL_NUM_THREADS``) GDAL
    compresses on its own threads, which print a refusal on stderr and leave the copy to
    succeed with blank tiles (``COMPRESS=WEBP`` on a single-band orthoimage: all zeros, exit
    status 0), so whether GDAL can write the data type and band count with the options is
    probed first (:func:`_probe_cog_write`, once per data type, band count and options)."""
    refused = None
    try:
        if _compression_threads(co) != "1":
            dtype, count, _ = _raster_shape(src)
            refused = _probe_cog_write(str(dtype), int(count), tuple(co.items()))
        if refused is None:
            rasterio.shutil.copy(src, tmp, driver="COG", **_lower(co))
    except _GDAL_ERRORS as exc:
        refused = " ".join(str(exc).split())
        if nbytes is None:
            try:
                dtype, count, cells = _raster_shape(src)
                nbytes = cells * count * np.dtype(dtype).itemsize
            except _GDAL_ERRORS:  # a source the full disk left unreadable: size unknown
                nbytes = 0
        full = _short_of_space(tmp, nbytes)
        if full is not None:
            raise OutputWriteError(f"{path}: cannot be written: {full} ({refused})") from None
    if refused is not None:
        raise OutputWriteError(
            f"{path}: cannot be written with the creation options {options_text(co)} ({refused})"
        )


def _raster_shape(src) -> tuple[str, int, int]:
    """(data type, band count, cells) of ``src``, an open dataset or a file."""
    if isinstance(src, str | os.PathLike):
        with rasterio.open(src) as ds:
            return ds.dtypes[0], ds.count, ds.width * ds.height
    return src.dtypes[0], src.count, src.width * src.height


def _short_of_space(path, nbytes: int) -> str | None:
    """Why a write of ``nbytes`` (the raster before compression) into ``path`` failed when
    the disk holding it has less than that free (GDAL's own error is then a symptom, e.g. a
    block it cannot read back: 'TIFFReadEncodedTile() failed'), else None."""
    folder = Path(path).parent
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return None
    if free >= nbytes:
        return None
    return (
        f"the disk holding {folder} is full: {_size_text(free)} free for a raster of "
        f"{_size_text(nbytes)} before compression"
    )


def _size_text(nbytes: int) -> str:
    """``nbytes`` in MB with one decimal, or in kB below 0.1 MB."""
    return f"{nbytes / 2**20:.1f} MB" if nbytes >= 0.1 * 2**20 else f"{nbytes / 2**10:.0f} kB"


def predictor_for(dtype) -> str:
    """TIFF predictor for a data type: 2 (horizontal differencing) for integers, 3 for floats."""
    return "3" if np.issubdtype(np.dtype(dtype), np.floating) else "2"


def crs_with_vertical(crs, vertical: str | None, geoid_crs=None):
    """``crs`` (horizontal) with the vertical reference of the heights in it.

    ``"geoid"`` gives the compound CRS *horizontal + EGM96 height* (EPSG:5773), or
    *horizontal + geoid_crs* when the heights are above another geoid (EGM2008 height, ...:
    :attr:`stereodem.core.dem.DEM.geoid_crs`), written in the GeoTIFF keys; ``"ellipsoid"``
    gives the horizontal CRS promoted to 3-D with a *WGS 84 ellipsoidal height* axis
    (EPSG:4979 for geographic grids). GeoTIFF keys cannot encode a projected CRS with
    ellipsoidal heights: :func:`geotiff_crs` says how such a file is written. ``None``
    returns ``crs`` unchanged.
    """
    if crs is None or vertical is None:
        return crs
    h = PCRS.from_user_input(crs)
    if h.is_compound or len(h.axis_info) == 3:
        return h  # already carries a vertical axis
    if vertical == "geoid":
        v = PCRS("EPSG:5773") if geoid_crs is None else PCRS.from_user_input(geoid_crs)
        return PCRS.from_user_input(CompoundCRS(f"{h.name} + {v.name}", [h, v]))
    if vertical == "ellipsoid":
        return (
            PCRS("EPSG:4979") if h.equals(PCRS("EPSG:4326"), ignore_axis_order=True) else h.to_3d()
        )
    raise InputError(f"vertical reference must be 'geoid' or 'ellipsoid', got {vertical!r}")


def geotiff_crs(crs):
    """``(keys, side_car)``: the CRS to write in a GeoTIFF's keys, and the one to write in its
    PAM side-car (``.aux.xml``), or None.

    A projected CRS with ellipsoidal heights (a projected CRS promoted to 3-D) has no GeoTIFF
    encoding: GDAL then writes it in the side-car only and no CRS keys in the file, which
    alone has no CRS at all (GDAL issue 9741), so a DEM copied, uploaded or read from object
    storage without its side-car would lose its georeferencing. Such a CRS goes to the keys as
    its horizontal part, so that the file alone is georeferenced (its heights' reference is
    then in the ``STEREODEM_VERTICAL`` tag and the band description), and whole to the
    side-car, which GDAL reads before the keys (``GDAL_GEOREF_SOURCES``: PAM first). Every
    other CRS (2-D, compound with a vertical CRS, geographic 3-D such as EPSG:4979) has a
    GeoTIFF encoding and goes to the keys alone."""
    if crs is None:
        return None, None
    c = PCRS.from_user_input(crs)
    if c.is_projected and not c.is_compound and len(c.axis_info) == 3:
        return c.to_2d(), c
    return c, None


def write_pam_crs(path, crs) -> Path:
    """Write GDAL's PAM side-car of the raster ``path`` (``path.aux.xml``) holding ``crs``
    (what GDAL itself writes for a CRS its GeoTIFF keys cannot encode: an ``SRS`` element
    with the WKT and GDAL's data-axis mapping, columns to the easting in the traditional GIS
    order). Returns the side-car's path."""
    c = PCRS.from_user_input(crs)
    first = c.axis_info[0].direction.lower() if c.axis_info else "east"
    mapping = [2, 1] if first in ("north", "south") else [1, 2]
    mapping += list(range(3, len(c.axis_info) + 1))
    root = ET.Element("PAMDataset")
    srs = ET.SubElement(root, "SRS", dataAxisToSRSAxisMapping=",".join(map(str, mapping)))
    srs.text = c.to_wkt()
    side = Path(f"{path}.aux.xml")
    side.write_bytes(ET.tostring(root, encoding="utf-8") + b"\n")
    return side


def cog_creation_options(
    dtype, creation_options=None, *, overview_resampling=None, compress=None
) -> dict:
    """GDAL COG creation options of a product of ``dtype``: :data:`COG_DEFAULTS`, the predictor
    of the data type, overview resampling (``average`` for floats, ``nearest`` for integers),
    then ``compress`` and the user's ``creation_options`` on top; DEFLATE at
    :data:`DEFLATE_LEVEL` unless a ``LEVEL`` is given."""
    is_float = np.issubdtype(np.dtype(dtype), np.floating)
    co = dict(
        COG_DEFAULTS,
        PREDICTOR=predictor_for(dtype),
        OVERVIEW_RESAMPLING=(overview_resampling or ("average" if is_float else "nearest")).upper(),
    )
    if compress:
        co["COMPRESS"] = str(compress).upper()
    co.update(parse_creation_options(creation_options))
    if co.get("COMPRESS", "").upper() == "DEFLATE":
        co.setdefault("LEVEL", DEFLATE_LEVEL)
    if co.get("COMPRESS", "").upper() in (
        "NONE",
        "JPEG",
        "WEBP",
        "LERC",
        "LERC_DEFLATE",
        "LERC_ZSTD",
    ):
        co.pop("PREDICTOR", None)  # predictor applies to LZW/DEFLATE/ZSTD only
    return co


def _as_list(value, count, what):
    if value is None:
        return [None] * count
    if isinstance(value, str):
        value = [value] * count
    value = list(value)
    if len(value) != count:
        raise InputError(f"{what}: {len(value)} given for {count} band(s)")
    return value


@contextlib.contextmanager
def _without_georeferencing_warning(transform, rpcs):
    """Where a raster is written without a geotransform or RPCs on purpose (an image in
    sensor geometry), rasterio's NotGeoreferencedWarning is silenced; otherwise nothing is
    done: ``warnings.catch_warnings`` saves and restores the process's filters, which a
    write on a background thread would do under the main thread's feet (Python < 3.14)."""
    if transform is not None or rpcs is not None:
        yield
        return
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        yield


def write_geotiff(
    path,
    data,
    transform=None,
    crs=None,
    nodata=None,
    *,
    overwrite=False,
    tags=None,
    band_tags=None,
    rpcs=None,
    compress=None,
    dtype=None,
    vertical=None,
    descriptions=None,
    units=None,
    creation_options=None,
    overview_resampling=None,
    mask=None,
):
    """Write ``data`` (2-D, or 3-D band-first) atomically as a Cloud-Optimised GeoTIFF.

    GDAL's COG driver (through rasterio) lays the file out for range reads: 256² tiles,
    DEFLATE (level 1, :data:`DEFLATE_LEVEL`) with the predictor of the data type (2 for
    integers, 3 for floats), internal
    overviews when the raster is larger than a tile, the overviews before the full
    resolution. Pixel values are stored losslessly unless ``creation_options`` say otherwise.

    Parameters
    ----------
    transform : affine.Affine
        Pixel-corner georeferencing (GDAL convention).
    crs : CRS-like, optional
        Horizontal CRS of the grid (or a CRS already carrying the vertical).
    nodata : float, optional
        Nodata value; NaN for float rasters is allowed and is the default for float data.
    tags : dict, optional
        Dataset tags (strings); ``band_tags`` a list of per-band tag dicts. A
        ``STEREODEM_VERTICAL`` tag sets ``vertical`` when that is not given.
    rpcs : rasterio.rpc.RPC or dict, optional
        RPC metadata to embed (GDAL RFC 22 domain).
    compress : str, optional
        Compression (default DEFLATE); same as ``creation_options={"COMPRESS": ...}``.
    vertical : {"geoid", "ellipsoid"}, optional
        Vertical reference of height values, put in the CRS (:func:`crs_with_vertical`) and
        in the ``STEREODEM_VERTICAL`` tag.
    descriptions, units : str or list of str, optional
        Band descriptions and units (e.g. ``"metre"``), one per band or one for all.
    creation_options : dict or list of "KEY=VALUE", optional
        GDAL COG creation options overriding the defaults (:data:`COG_DEFAULTS`, the
        predictor, ``OVERVIEW_RESAMPLING``), as ``gdal_translate -co``. An option or value
        GDAL's COG driver does not accept is an :class:`InputError` naming the file and the
        option (:func:`check_creation_options`), not an option GDAL ignores with a warning.
    overview_resampling : str, optional
        Overview resampling; default ``average`` for floats, ``nearest`` for integers
        (classes, masks and counts keep their values).
    mask : ndarray bool (rows, cols), optional
        Valid cells, written as an internal per-dataset mask (for integer data where no
        value is free to serve as nodata).

    Returns
    -------
    pathlib.Path
    """
    path = check_writable(path, overwrite)
    if creation_options or compress:  # GDAL would ignore an option it does not know
        user = parse_creation_options(creation_options)
        if compress:
            user = {"COMPRESS": str(compress).upper(), **user}
        check_creation_options(user, source=f"{path}: creation options")
    arr = np.asarray(data)
    if arr.ndim not in (2, 3) or arr.size == 0 or arr.dtype.kind not in "biufc":
        raise InputError(
            f"{path}: data must be a non-empty 2-D (rows, cols) or 3-D (bands, rows, cols) "
            f"array of numbers, got shape {arr.shape} of {arr.dtype}"
        )
    if arr.ndim == 2:
        arr = arr[None]
    if crs is not None:
        try:
            crs = PCRS.from_user_input(crs)
        except Exception as exc:
            raise CRSError(
                f"{path}: unknown or unusable CRS {crs!r} ({' '.join(str(exc).split())})"
            ) from None
    if dtype is not None:
        arr = arr.astype(dtype)
    if arr.dtype == np.bool_:
        arr = arr.astype(np.uint8)
    if nodata is None and np.issubdtype(arr.dtype, np.floating):
        nodata = np.nan
    tags = {k: str(v) for k, v in (tags or {}).items()}
    vertical = vertical or (tags.get(VERTICAL_TAG) or "").lower() or None
    if vertical:
        tags[VERTICAL_TAG] = vertical
    crs = crs_with_vertical(crs, vertical)
    co = cog_creation_options(
        arr.dtype, creation_options, overview_resampling=overview_resampling, compress=compress
    )
    count = arr.shape[0]
    descriptions = _as_list(descriptions, count, "descriptions")
    units = _as_list(units, count, "units")
    # the raster is assembled in a MEM dataset, then copied to the COG by GDAL's CreateCopy
    # through rasterio.shutil.copy, which releases the GIL while it compresses; closing a
    # dataset opened with driver="COG" runs the same copy (the same bytes) holding the GIL
    # (rasterio 1.3.8 and 1.4.4), which stalls every Python thread (1.5 s for a 100 MB
    # raster): a write in the background would not overlap the next stage's work
    profile = dict(
        driver="MEM",
        width=arr.shape[2],
        height=arr.shape[1],
        count=count,
        dtype=arr.dtype,
        nodata=nodata,
    )
    crs, side_crs = geotiff_crs(crs)
    if crs is not None:
        profile["crs"] = rasterio.crs.CRS.from_wkt(crs.to_wkt())
    if transform is not None:
        profile["transform"] = transform
    if rpcs is not None:
        profile["rpcs"] = rpcs
    with atomic_path(path) as tmp, _without_georeferencing_warning(transform, rpcs):
        with rasterio.open("", "w", **profile) as dst:
            dst.write(arr)
            if tags:
                dst.update_tags(**tags)
            for i, bt in enumerate(band_tags or [], start=1):
                dst.update_tags(i, **{k: str(v) for k, v in bt.items()})
            if mask is not None:
                dst.write_mask(np.asarray(mask, dtype=bool))
            for i, (desc, unit) in enumerate(zip(descriptions, units), start=1):
                if desc:
                    dst.set_band_description(i, desc)
                if unit:
                    dst.set_band_unit(i, unit)
            copy_to_cog(dst, tmp, co, path=path)
        if side_crs is not None:  # moved into place with the file (atomic_path)
            write_pam_crs(tmp, side_crs)
    return path


def write_text_atomic(path, text: str, *, overwrite=False) -> Path:
    """Write a text file atomically (temporary file + rename)."""
    path = check_writable(path, overwrite)
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text, encoding="utf-8")
    return path


def reading_env():
    """A rasterio environment that decodes compressed blocks on several threads
    (``GDAL_NUM_THREADS``: the process's thread budget when one is set in the environment,
    e.g. by ``stereodem.core.threads.pin_threads``, else all CPUs): reading a DEFLATE-compressed
    scene-sized GeoTIFF takes about half the time on two cores. The values read are the same.
    One thread with a GDAL older than 3.8, whose threaded decoding turns a damaged block into
    zeros without an error (:func:`stereodem.core.threads.gdal_threads`)."""
    from stereodem.core.threads import gdal_threads

    return rasterio.Env(
        GDAL_NUM_THREADS=gdal_threads(os.environ.get("GDAL_NUM_THREADS") or "ALL_CPUS")
    )


def probe_blocks(ds, band: int = 1) -> None:
    """The first and the last block of ``band`` of the open raster ``ds`` decode; GDAL's
    ``RasterioIOError`` otherwise, which the callers word with :func:`unreadable`. A GeoTIFF
    cut short (a partial download or copy) still opens: its header is at the front, so its
    size and type are known, while its pixels, and often its georeferencing (the GeoTIFF keys
    stored after the first bytes: the file then seemed to have "no CRS"), are lost. Its last
    block lies beyond the end, and one read of it tells before any work, not when the whole
    raster is read after the stereo stage. Two blocks, whatever the raster's size."""
    if not 1 <= band <= ds.count:
        return  # the callers say that the band is missing
    bh, bw = ds.block_shapes[band - 1]
    rows, cols = -(-ds.height // bh), -(-ds.width // bw)
    for r, c in dict.fromkeys([(0, 0), (rows - 1, cols - 1)]):  # first, then last
        r0, c0 = r * bh, c * bw
        ds.read(band, window=((r0, min(r0 + bh, ds.height)), (c0, min(c0 + bw, ds.width))))


def check_map_raster(path, ds, what: str) -> None:
    """A raster ``path`` (open as ``ds``) that is read onto a map grid (a land-cover, mask or
    σ raster) has a CRS and a geotransform: without a geotransform rasterio gives the identity
    (cells at whole CRS units from 0) with a warning only, which placed it where it covers
    nothing (empty per-class statistics, no error). :class:`CRSError` / :class:`InputError`
    naming ``what``. Its first and last blocks are read first (:func:`probe_blocks`): a file
    cut short lost its georeferencing with its pixels, and says so."""
    probe_blocks(ds)
    if ds.crs is None:
        raise CRSError(f"{path}: {what} has no CRS")
    if ds.transform.is_identity and not ds.gcps[0]:
        raise InputError(
            f"{path}: {what} has no geotransform (its cells are not placed on the map; set "
            "one with gdal_edit.py -a_ullr or -a_gt)"
        )


def as_path(path, what: str = "path") -> Path:
    """``path`` (a ``str`` or ``os.PathLike``) as a :class:`~pathlib.Path`;
    :class:`InputError` naming ``what`` for anything else (``None`` was pathlib's or
    rasterio's ``TypeError``)."""
    if not isinstance(path, str | os.PathLike):
        raise InputError(f"{what}: expected a file path, got {type(path).__name__}")
    return Path(path)


def unreadable(path, what: str, exc) -> str:
    """The one-line message for a raster ``path`` that GDAL could not open or read as ``what``
    ("DEM", "image", "reference DEM"): a folder given for the file says so ("PATH: is a
    directory, not a DEM file"; GDAL's "not recognized as being in a supported file format"
    said nothing of it), a missing file :func:`~stereodem.core.errors.not_found` (GDAL's
    "PATH: No such file or directory" named the file twice), anything else "PATH: cannot read
    the WHAT (GDAL's first line)". Every reader of DEM files and images words its failure
    with it."""
    if isinstance(path, str | os.PathLike) and Path(path).is_dir():
        article = "an" if what[:1].lower() in "aeiou" else "a"
        return f"{path}: is a directory, not {article} {what} file"
    cause = exc.__cause__ or exc.__context__
    first = str(exc).splitlines()[0] if str(exc) else ""
    if first.endswith(NOT_FOUND) and isinstance(path, str | os.PathLike):
        if not os.path.lexists(path):  # not a GDAL virtual path ("/vsizip/...") GDAL misses
            return not_found(path, what)
    said = None
    if isinstance(cause, CPLE_BaseError) and "previous exception" in first:
        # the header opened, a block did not decode: rasterio's own message ("Read failed.
        # See previous exception for details.") said nothing; GDAL's is the cause
        said = str(cause).splitlines()[0].split(": ", 1)[-1]  # without "NAME, band N: "
    elif first.startswith("Read or write failed"):
        # the same with rasterio 1.3 (GDAL 3.6): GDAL's reason in its own message
        said = first.split(": ", 1)[-1]
    if said is not None:
        return (
            f"{path}: cannot read the {what}: its pixels do not decode (the file is cut "
            f"short or damaged; GDAL: {said[:120]})"
        )
    return f"{path}: cannot read the {what} ({str(exc).splitlines()[0][:120]})"


def read_image(path, band: int = 1) -> np.ndarray:
    """One band of an image as float32, NaN where the file marks no data.

    The one no-data rule of the project: a pixel is missing where GDAL's mask for the band says
    so (the band's nodata value, an internal mask or an alpha band) or where the value is not
    finite. Raises :class:`InputError` naming the file when it cannot be read or has no such
    band.
    """
    if not hasattr(path, "read"):  # rasterio also opens file objects
        as_path(path, "image")
    try:
        with reading_env(), rasterio.open(path) as ds:
            if not 1 <= int(band) <= ds.count:
                raise InputError(f"{path}: no band {band} (the image has {ds.count})")

            check_allocation(
                ds.width * ds.height * (4 + np.dtype(ds.dtypes[band - 1]).itemsize + 1),
                f"{path}: reading its {ds.width} x {ds.height} pixels",
            )
            data = ds.read(int(band), masked=True)
    except rasterio.errors.RasterioIOError as exc:
        raise InputError(unreadable(path, "image", exc)) from None
    img = np.ma.getdata(data).astype(np.float32)
    img[np.ma.getmaskarray(data) | ~np.isfinite(img)] = np.nan  # +-inf too (defective L1 columns)
    return img


def image_shape(path, band: int = 1) -> tuple[int, int]:
    """``(width, height)`` of one band of an image, from its header (pixels not read)."""
    try:
        with rasterio.open(path) as ds:
            if not 1 <= int(band) <= ds.count:
                raise InputError(f"{path}: no band {band}")
            return int(ds.width), int(ds.height)
    except rasterio.errors.RasterioIOError as exc:
        raise InputError(unreadable(path, "image", exc)) from None


def check_image(path, band: int = 1) -> tuple[int, int]:
    """The checks of :func:`read_image` that need no full read, for the commands that use an
    image's sensor model without its pixels: the file opens as a raster with the band and its
    first and last blocks decode (:func:`probe_blocks`). A zero-byte file, a text file named
    ``.tif`` or a GeoTIFF cut short is the :class:`InputError` :func:`read_image` gives
    (worded by :func:`unreadable`). Returns ``(width, height)``."""
    as_path(path, "image")
    try:
        with reading_env(), rasterio.open(path) as ds:
            if not 1 <= int(band) <= ds.count:
                raise InputError(f"{path}: no band {band} (the image has {ds.count})")
            probe_blocks(ds, int(band))
            return int(ds.width), int(ds.height)
    except rasterio.errors.RasterioIOError as exc:
        raise InputError(unreadable(path, "image", exc)) from None


def image_dtype(path, band: int = 1) -> np.dtype:
    """The stored data type of one band of an image (products keep it, e.g. orthoimages)."""
    try:
        with rasterio.open(path) as ds:
            return np.dtype(ds.dtypes[int(band) - 1])
    except rasterio.errors.RasterioIOError as exc:
        raise InputError(unreadable(path, "image", exc)) from None
    except IndexError:
        raise InputError(f"{path}: no band {band}") from None
