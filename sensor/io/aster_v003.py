"""Legacy ASTER L1A V003 "GeoTIFF" granules: a zip (or its unzipped folder) of
``<granule>.<swath>.ImageData.tif`` images and ``<granule>.<swath>.<field>.txt`` tables.

Text tables (ASTER notes §3.3): whitespace-separated numbers without a header; 3-D fields
(``LatticePoint``, ``SightVector``) are blocks of 11 lines separated by an empty line (one block
per lattice row); ``SatellitePosition`` / ``SatelliteVelocity`` one line per lattice row;
``Latitude`` / ``Longitude`` one line of 11 values per lattice row (geocentric latitude);
``RadiometricCorrTable`` one ``D A G`` line per detector. The reader accepts any whitespace, CRLF,
extra blank lines and indentation, and takes block sizes from the data. An optional ECS
metadata sidecar (``<zip>.met`` or a ``.met`` in the folder) supplies the ODL metadata.

:func:`read_v003` returns the same :class:`stereodem.sensor.io.aster_l1a.L1ABandFields` as the
V004 reader; open granules with :func:`stereodem.sensor.io.aster_l1a.open_aster_granule`.
"""

from __future__ import annotations

import re
import warnings
import zipfile
from pathlib import Path

import numpy as np
import rasterio

from stereodem.core.errors import InputError
from stereodem.sensor.io.aster_l1a import VNIR_BANDS, L1ABandFields, swath_name
from stereodem.sensor.io.aster_metadata import not_l1a_message, product_level
from stereodem.sensor.io.odl import flatten_odl, parse_odl
from stereodem.sensor.io.tables import TableError, numeric_blocks

#: tables a band needs (besides ``ImageData.tif``); ASP's aster2asp requires the same set
REQUIRED_TABLES = (
    "LatticePoint",
    "SightVector",
    "SatellitePosition",
    "RadiometricCorrTable",
    "Latitude",
    "Longitude",
)
OPTIONAL_TABLES = ("SatelliteVelocity", "ObservationTime")


class _Source:
    """Member listing and reading of a zip or a folder (searched recursively)."""

    def __init__(self, path: Path):
        self.path = path
        if path.is_dir():
            self.zip = None
            self.members = {
                str(p.relative_to(path)).replace("\\", "/"): p
                for p in path.rglob("*")
                if p.is_file()
            }
        else:
            try:
                self.zip = zipfile.ZipFile(path)
                self.members = {n: n for n in self.zip.namelist() if not n.endswith("/")}
            except (zipfile.BadZipFile, OSError) as exc:
                raise InputError(
                    f"{path}: not a readable zip file - truncated or damaged ({exc})"
                ) from None

    def find(self, suffix: str):
        hits = sorted(
            m
            for m in self.members
            if Path(m).name.endswith(suffix) and "L1A" in Path(m).name.upper()
        )
        return hits[0] if hits else None

    def text(self, member: str) -> str:
        try:
            if self.zip is not None:
                return self.zip.read(member).decode("ascii", errors="replace")
            return self.members[member].read_text(encoding="ascii", errors="replace")
        except (zipfile.BadZipFile, OSError, EOFError) as exc:
            raise InputError(
                f"{self.path}: cannot read {member} - truncated or damaged ({exc})"
            ) from None

    def raster_path(self, member: str) -> str:
        if self.zip is not None:
            return f"/vsizip/{self.path.resolve()}/{member}"
        return str(self.members[member])


def _table(text: str, source: str, *, width: int | None = None):
    """Numbers of a text table as blocks: list of (lines, values) float arrays."""
    try:
        blocks = numeric_blocks(text)
    except TableError as exc:
        raise InputError(f"{source}: non-numeric line {exc.line[:40]!r}") from None
    if not blocks:
        raise InputError(f"{source}: empty table")
    try:
        arrs = [np.array(b, dtype=np.float64) for b in blocks]
        if any(a.ndim != 2 for a in arrs):
            raise ValueError
    except ValueError:
        raise InputError(f"{source}: lines of unequal length") from None
    if width is not None and any(a.shape[1] != width for a in arrs):
        raise InputError(f"{source}: expected {width} values per line")
    return arrs


def _blocks3d(text, source, width):
    arrs = _table(text, source, width=width)
    if len({a.shape[0] for a in arrs}) != 1:
        raise InputError(f"{source}: blocks of unequal length")
    return np.stack(arrs)  # (N, K, width)


def _rows(text, source, width=None):
    return np.concatenate(_table(text, source, width=width))  # blank lines ignored


def read_v003(path):
    """Read a V003 zip or folder: ``(granule_id, odl, {band: L1ABandFields})``.

    Raises
    ------
    InputError
        Not an ASTER L1A granule, an L1B product, a missing image or table (the message names
        the missing file), a damaged zip.
    """
    path = Path(path)
    src = _Source(path)
    images = {b: src.find(f".{swath_name(b)}.ImageData.tif") for b in VNIR_BANDS}
    any_l1 = [m for m in src.members if re.match(r"AST_?L1[BT]", Path(m).name.upper())]
    if not any(images.values()):
        if any_l1:
            level = "L1T" if any("L1T" in m.upper() for m in any_l1) else "L1B"
            raise InputError(not_l1a_message(path, level))
        raise InputError(
            f"{path}: not an ASTER L1A V003 granule (no "
            f"AST_L1A_*.VNIR_Band3N.ImageData.tif / VNIR_Band3B images)"
        )
    first = next(m for m in images.values() if m)
    gid = Path(first).name.split(".VNIR_Band")[0]
    odl = {}
    met = [m for m in src.members if m.lower().endswith(".met")]
    side = Path(str(path) + ".met")
    if side.is_file():
        odl["met"] = parse_odl(side.read_text(errors="replace"), source=str(side))
    elif met:
        odl["met"] = parse_odl(src.text(met[0]), source=f"{path}:{met[0]}")
    if odl:
        level = product_level(flatten_odl(odl["met"]), gid)
        if level in ("L1B", "L1T"):
            raise InputError(not_l1a_message(path, level))
    bands = {}
    for b, img in images.items():
        if img is None:
            continue
        sw = swath_name(b)
        prefix = img[: -len("ImageData.tif")]
        tables = {}
        for name in REQUIRED_TABLES + OPTIONAL_TABLES:
            member = prefix + name + ".txt"
            if member not in src.members:
                if name in REQUIRED_TABLES:
                    raise InputError(
                        f"{path}: V003 granule has no {Path(member).name} "
                        f"(the {name} table of {sw})"
                    )
                continue
            tables[name] = src.text(member)
        bands[b] = _band(src, b, sw, img, tables)
    return gid, odl, bands


def _band(src: _Source, band, sw, img_member, t):
    where = f"{src.path}:{sw}"
    rpath = src.raster_path(img_member)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with rasterio.open(rpath) as ds:
                shape = (ds.height, ds.width)
                if ds.count != 1 or ds.dtypes[0] != "uint8":
                    raise InputError(
                        f"{where}: ImageData.tif must be one uint8 band, got "
                        f"{ds.count} band(s) of {ds.dtypes[0]}"
                    )
    except rasterio.errors.RasterioIOError as exc:
        raise InputError(f"{where}: cannot open {Path(img_member).name} ({exc})") from None

    def read_dn():
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                with rasterio.open(rpath) as ds:
                    return ds.read(1)
        except rasterio.errors.RasterioError as exc:
            raise InputError(
                f"{where}: cannot read {Path(img_member).name} - truncated or damaged ({exc})"
            ) from None

    name = lambda f: f"{src.path}:{Path(img_member[: -len('ImageData.tif')] + f + '.txt').name}"  # noqa: E731
    lattice = _blocks3d(t["LatticePoint"], name("LatticePoint"), 2)
    n, k = lattice.shape[:2]
    latitude = _rows(t["Latitude"], name("Latitude"))
    longitude = _rows(t["Longitude"], name("Longitude"))
    for nm, arr in (("Latitude", latitude), ("Longitude", longitude)):
        if arr.size != n * k:
            raise InputError(f"{name(nm)}: {arr.size} values for a {n} x {k} lattice")
    vel = (
        _rows(t["SatelliteVelocity"], name("SatelliteVelocity"), 3)
        if "SatelliteVelocity" in t
        else None
    )
    obs = _rows(t["ObservationTime"], name("ObservationTime")) if "ObservationTime" in t else None
    return L1ABandFields(
        band=band,
        source=where,
        image_shape=shape,
        read_dn=read_dn,
        rc_table=_rows(t["RadiometricCorrTable"], name("RadiometricCorrTable"), 3),
        lattice=lattice,
        sight_vectors=_blocks3d(t["SightVector"], name("SightVector"), 3),
        satellite_positions=_rows(t["SatellitePosition"], name("SatellitePosition"), 3),
        satellite_velocities=vel,
        observation_times=obs,
        latitude=latitude.reshape(n, k),
        longitude=longitude.reshape(n, k),
    )
