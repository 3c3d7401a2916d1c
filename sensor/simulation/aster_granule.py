"""Synthetic ASTER L1A granules (V004 HDF-EOS2 and V003 zip/folder) from a simulated scene.

The simulator recipe of the ASTER notes (``aster-l1a-format.md`` §8, §2.7, §3):

* the 3N and 3B models of an ``aster`` scene
  (:func:`stereodem.sensor.simulation.simulate.simulate_scene`) are sampled on an 11-column lattice
  (columns ``0, w/10, ..., w``; rows every ``row_step`` lines from a negative first row, past the
  last line): per lattice row the ECEF satellite position, ``SatelliteVelocity`` (inertial in ECEF
  axes by default, or Earth-fixed), ``ObservationTime`` (days since 1958-01-01, ms of day split as
  MicMac reads it, us); per lattice point the sight vector in the orbital frame (z = -r, y = -(r x
  v_in), x = y x z) and the geocentric latitude / longitude of its ellipsoid intersection;
* the scene's image is taken as radiance ``L`` and turned into L1A DN with a per-detector
  ``RadiometricCorrTable`` (D, A, G) that has a smooth across-track trend and a few outlying
  detectors (visible stripes): ``DN = clip(round((L - D) G / A), 1, 255)``, 0 kept for fill;
* V004: one SDS per field with the bare field name, dimensions named ``<dim>:<swath>``, Vgroups
  ``VNIR`` -> ``VNIR_Band3N`` / ``VNIR_Band3B`` (class ``SWATH``) -> ``Data Fields`` /
  ``Geolocation Fields`` / ``Swath Attributes`` (class ``SWATH Vgroup``), global ODL attributes
  ``HDFEOSVersion``, ``StructMetadata.0`` (swaths, dimensions, dimension maps, fields),
  ``coremetadata.0``, ``productmetadata.0``, ``productmetadata.v``;
* V003: ``<id>.VNIR_Band<b>.ImageData.tif`` (uint8, no georeferencing) and
  ``<id>.VNIR_Band<b>.<field>.txt`` tables (``%.6f`` / ``%d``, no indentation, one empty line
  between blocks), plus the ODL ``.met`` sidecar, as a folder or a zip.

Only choices marked [UNVERIFIED] in the notes are ours (dimension names, dtypes of geometry
fields, ``ObservationTime`` words, attitude fields written as zeros); the reader depends on none
of them.
"""

from __future__ import annotations

import datetime as _dt
import os
import shutil
import tempfile
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stereodem.core import geodesy
from stereodem.core.errors import InputError, OutputExistsError
from stereodem.core.raster import write_geotiff
from stereodem.sensor.geo.rotations import inertial_velocity, orbital_frame
from stereodem.sensor.io.aster_l1a import swath_name
from stereodem.sensor.io.odl import format_odl
from stereodem.sensor.simulation.simulate import SUN_AZIMUTH, SUN_ELEVATION, write_scene

#: unit conversion coefficient of 3N/3B at normal gain (W m-2 sr-1 um-1 per DN)
UCC_NORMAL = 0.862
#: default acquisition start (UTC) of simulated granules (the bundled Rainier granule's day)
DEFAULT_START = _dt.datetime(2017, 7, 31, 19, 7, 28)
_EPOCH_1958 = _dt.datetime(1958, 1, 1)
#: production time of simulated granules before :func:`production_time` adds the seed's minutes
_PRODUCTION_BASE = _dt.datetime(2026, 11, 21, 12, 0, 0)
#: first lattice row as a fraction of the row step (fixture: -232/400 for 3N, -39/400 for 3B)
_FIRST_ROW_FRACTION = {"3N": -0.58, "3B": -0.0975}


@dataclass
class BandProduct:
    """The fields of one simulated band swath (product layout, see the module docstring)."""

    band: str
    dn: np.ndarray  #: uint8 (rows, cols)
    radiance: np.ndarray  #: float32 true radiance (NaN at fill)
    rc_table: np.ndarray  #: float32 (cols, 3) = (D, A, G)
    lattice: np.ndarray  #: int32 (N, 11, 2) = (col, row)
    sight_vectors: np.ndarray  #: (N, 11, 3)
    positions: np.ndarray  #: (N, 3)
    velocities: np.ndarray  #: (N, 3)
    observation_time: np.ndarray  #: int32 (N, 4)
    latitude: np.ndarray  #: geocentric (N, 11)
    longitude: np.ndarray  #: (N, 11)
    times: np.ndarray  #: model line time of every lattice row, s


@dataclass
class SimulatedGranule:
    """A simulated granule in memory: band products plus ODL metadata texts."""

    granule_id: str
    start: _dt.datetime
    bands: dict
    attributes: dict = field(default_factory=dict)  #: ODL global attributes (V004 names)
    settings: dict = field(default_factory=dict)
    production: _dt.datetime = _PRODUCTION_BASE  #: production time (the id's second stamp)


# ============================================================================ geometry


def lattice_product(model, band: str, *, row_step: int, velocity: str = "inertial"):
    """Lattice geometry of ``model`` as the product stores it.

    Returns ``(lattice int32 (N, 11, 2), sight (N, 11, 3), positions (N, 3), velocities (N, 3),
    geocentric latitude (N, 11), longitude (N, 11), lattice-row times (N,))``.
    """
    w, h = int(model.width), int(model.height)
    if w % 10:
        raise InputError(
            f"ASTER granule simulation: image width {w} must be a multiple of 10 "
            f"(11 lattice columns; real 3N 4100, 3B 5000)"
        )
    r0 = int(round(_FIRST_ROW_FRACTION.get(band, -0.5) * row_step))
    n = int(np.ceil((h - 1 - r0) / row_step)) + 1
    rows = r0 + row_step * np.arange(n)
    cols = (w // 10) * np.arange(11)
    cc, rr = np.meshgrid(cols.astype(float), rows.astype(float))
    origin, d = model.rays(cc, rr)
    t = model.line_time(rows.astype(float))
    pos, v_ef = model.ephemeris.state(t)
    frame = orbital_frame(pos, v_ef, inertial=True)  # (N, 3, 3)
    sight = np.einsum("nji,nkj->nki", frame, d)
    ground = geodesy.intersect_height(origin, d, np.zeros(cc.shape))
    lon = np.degrees(np.arctan2(ground[..., 1], ground[..., 0]))
    lat = np.degrees(np.arctan2(ground[..., 2], np.hypot(ground[..., 0], ground[..., 1])))
    vel = inertial_velocity(pos, v_ef) if velocity == "inertial" else v_ef
    lattice = np.stack(np.broadcast_arrays(cols[None, :], rows[:, None]), -1).astype(np.int32)
    return lattice, sight, pos, vel, lat, lon, t


def observation_time_words(when: _dt.datetime):
    """``(days since 1958-01-01, ms_of_day // 100000, ms_of_day % 100000, us)`` (notes §4.5)."""
    delta = when - _EPOCH_1958
    us_total = delta.seconds * 1_000_000 + delta.microseconds
    ms, us = divmod(us_total, 1000)
    return [delta.days, ms // 100000, ms % 100000, us]


# ============================================================================ radiometry


def radiometric_table(
    width: int,
    rng,
    *,
    ucc: float = UCC_NORMAL,
    trend: float = 0.04,
    stripes: float = 0.03,
    stripe_fraction: float = 0.05,
):
    """A per-detector (D, A, G) table: float32 (width, 3).

    ``A = ucc * s``, ``G = 1``, ``D`` in [-1, 0]; ``s`` has a smooth across-track trend of
    relative amplitude ``trend`` plus ``stripe_fraction`` of the detectors off by up to
    ``stripes`` (relative): without correction these show as stripes.
    """
    x = np.linspace(-1, 1, width)
    s = 1.0 + trend * (0.6 * x + 0.4 * np.sin(2.3 * np.pi * x + rng.uniform(0, 2 * np.pi)))
    bad = rng.random(width) < stripe_fraction
    s[bad] *= 1.0 + stripes * rng.uniform(-1, 1, int(bad.sum()))
    s *= 1.0 + 0.003 * rng.standard_normal(width)
    d = -rng.uniform(0.0, 1.0, width)
    return np.stack([d, ucc * s, np.ones(width)], -1).astype(np.float32)


def radiance_to_dn(radiance, table):
    """L1A DN from radiance: ``clip(round((L - D) G / A), 1, 255)``; NaN radiance -> 0 (fill)."""
    d, a, g = (table[:, k].astype(np.float32) for k in range(3))
    v = (radiance - d) * g / a
    dn = np.clip(np.rint(np.nan_to_num(v, nan=0.0)), 1, 255).astype(np.uint8)
    dn[~np.isfinite(radiance)] = 0
    return dn


# ============================================================================ from a scene


def granule_from_scene(
    scene,
    *,
    seed: int = 0,
    velocity: str = "inertial",
    row_step=None,
    start: _dt.datetime = DEFAULT_START,
    version: int = 4,
    radiance_scale: float = 0.9 * UCC_NORMAL,
    scene_index: int = 0,
) -> SimulatedGranule:
    """Turn an ``aster`` scene (3N = left, 3B = right) into a granule in memory.

    ``scene_index`` numbers the granules of one simulated pass
    (:mod:`stereodem.sensor.simulation.aster_strip`): it is added to the row of
    ``ASTERSCENEID`` and, in seconds, to the production time of the granule id; the seed sets
    the production time's minute (:func:`production_time`), so granules of different seeds
    have different ids (file names) though they share the acquisition start.

    The scene image (DN-like, 0 = void) times ``radiance_scale`` is the true radiance.
    ``row_step`` defaults to 400 lines for full-size images, else about a tenth of the 3N height.
    ``velocity`` is ``"inertial"`` (default, notes §4.3) or ``"earth_fixed"``.
    """
    if velocity not in ("inertial", "earth_fixed"):
        raise InputError(f"velocity must be 'inertial' or 'earth_fixed', got {velocity!r}")
    rng = np.random.default_rng(seed + 1)
    h3n = int(scene.left_model.height)
    if row_step is None:
        row_step = 400 if h3n >= 4000 else max(8, int(round(h3n / 10.5)))
    t_ref = float(scene.left_model.line_time(0.0))
    bands = {}
    for band, img, model in (
        ("3N", scene.left, scene.left_model),
        ("3B", scene.right, scene.right_model),
    ):
        lattice, sight, pos, vel, lat, lon, t = lattice_product(
            model, band, row_step=row_step, velocity=velocity
        )
        radiance = img.astype(np.float32) * np.float32(radiance_scale)
        radiance[img == 0] = np.nan
        table = radiometric_table(img.shape[1], rng)
        obs = np.array(
            [observation_time_words(start + _dt.timedelta(seconds=float(ti - t_ref))) for ti in t],
            np.int32,
        )
        bands[band] = BandProduct(
            band,
            radiance_to_dn(radiance, table),
            radiance,
            table,
            lattice,
            sight,
            pos,
            vel,
            obs,
            lat,
            lon,
            t,
        )
    now = production_time(seed, scene_index)
    gid = f"AST_L1A_00{version}{start:%m%d%Y%H%M%S}_{now:%Y%m%d%H%M%S}"
    g = SimulatedGranule(
        gid,
        start,
        bands,
        settings=dict(
            velocity=velocity,
            row_step=row_step,
            seed=seed,
            radiance_scale=radiance_scale,
            scene_index=int(scene_index),
        ),
        production=now,
    )
    g.attributes = _odl_attributes(g, scene)
    return g


def production_time(seed: int = 0, scene_index: int = 0) -> _dt.datetime:
    """The production time of a simulated granule, the second time stamp of its id
    (``AST_L1A_004<acquisition MMDDYYYYHHMMSS>_<production YYYYMMDDHHMMSS>``, as real ids):
    a fixed day plus ``seed`` minutes (modulo 10^6, about two years) plus ``scene_index``
    seconds, so two granules simulated with different seeds get different file names and
    can share a folder (``batch``)."""
    minutes = int(seed) % 1_000_000
    return _PRODUCTION_BASE + _dt.timedelta(minutes=minutes, seconds=int(scene_index))


def _corners(model):
    """Geodetic (lat, lon) of the image corners on the ellipsoid."""
    w, h = model.width - 1, model.height - 1
    lon, lat = model.localize(np.array([0.0, w, 0.0, w]), np.array([0.0, 0.0, h, h]), np.zeros(4))
    return {
        k: (round(float(la), 6), round(float(lo), 6))
        for k, la, lo in zip(("UPPERLEFT", "UPPERRIGHT", "LOWERLEFT", "LOWERRIGHT"), lat, lon)
    }


def _obj(value, cls=None):
    o = {"NUM_VAL": len(value) if isinstance(value, tuple) else 1}
    if cls is not None:
        o = {"CLASS": str(cls), **o}
    o["VALUE"] = value
    return o


def _odl_attributes(g: SimulatedGranule, scene) -> dict:
    m3n = scene.left_model
    corners = _corners(m3n)
    lats = [c[0] for c in corners.values()]
    lons = [c[1] for c in corners.values()]
    b3n = g.bands["3N"]
    mid = b3n.sight_vectors[0, 5]
    pointing = float(np.degrees(np.arctan2(mid[1], mid[2])))
    stop = g.start + _dt.timedelta(seconds=float(g.bands["3B"].times[-1] - b3n.times[0]))
    core = {
        "INVENTORYMETADATA": {
            "GROUPTYPE": "MASTERGROUP",
            "ECSDATAGRANULE": {
                "LOCALGRANULEID": _obj(g.granule_id + ".hdf"),
                "PRODUCTIONDATETIME": _obj(f"{g.production:%Y-%m-%dT%H:%M:%S}.000Z"),
            },
            "COLLECTIONDESCRIPTIONCLASS": {"SHORTNAME": _obj("ASTL1A"), "VERSIONID": _obj(4)},
            "RANGEDATETIME": {
                "RANGEBEGINNINGDATE": _obj(f"{g.start:%Y-%m-%d}"),
                "RANGEBEGINNINGTIME": _obj(f"{g.start:%H:%M:%S.%f}"),
                "RANGEENDINGDATE": _obj(f"{stop:%Y-%m-%d}"),
                "RANGEENDINGTIME": _obj(f"{stop:%H:%M:%S.%f}"),
            },
            "SPATIALDOMAINCONTAINER": {
                "HORIZONTALSPATIALDOMAINCONTAINER": {
                    "BOUNDINGRECTANGLE": {
                        "WESTBOUNDINGCOORDINATE": _obj(min(lons)),
                        "NORTHBOUNDINGCOORDINATE": _obj(max(lats)),
                        "EASTBOUNDINGCOORDINATE": _obj(max(lons)),
                        "SOUTHBOUNDINGCOORDINATE": _obj(min(lats)),
                    }
                }
            },
            "ASSOCIATEDPLATFORMINSTRUMENTSENSOR": {
                "ASSOCIATEDPLATFORMINSTRUMENTSENSORCONTAINER": {
                    "ASSOCIATEDPLATFORMSHORTNAME": _obj("Terra"),
                    "ASSOCIATEDINSTRUMENTSHORTNAME": _obj("ASTER"),
                }
            },
            "QASTATS": {"PROCESSINGLEVELID": _obj("1A")},
        }
    }
    product = {
        "ASTERGENERICMETADATA": {
            "SCENEINFORMATION": {
                "ASTERSCENEID": _obj((46, 27 + int(g.settings.get("scene_index", 0)), 0)),
                "CALENDARDATE": _obj(f"{g.start:%Y%m%d}"),
                "TIMEOFDAY": _obj(f"{g.start:%H%M%S}"),
                "SCENECLOUDCOVERAGE": _obj(0),
                "SOLARDIRECTION": _obj((float(SUN_AZIMUTH), float(SUN_ELEVATION))),
                "FIRSTPACKETTIME": _obj(f"{g.start:%Y-%m-%dT%H:%M:%S}Z"),
                "LASTPACKETTIME": _obj(f"{stop:%Y-%m-%dT%H:%M:%S}Z"),
                "INSTRUMENTSHORTNAME": _obj("ASTER"),
            },
            "POINTINGANGLES": {
                "POINTINGANGLE": _obj(round(pointing, 3), 1),
                "SENSORNAME": _obj("VNIR", 1),
            },
            "SCENEFOURCORNERS": {k: _obj(v) for k, v in corners.items()},
        }
    }
    vnir = {
        "PRODUCTSPECIFICMETADATAVNIR": {
            **{f"UNITCONVERSIONCOEFF{b}": {f"INCL{b}": _obj(UCC_NORMAL)} for b in ("3N", "3B")},
            "GAININFORMATION": {"GAIN": _obj(("03N", "NOR"), 1), "GAIN.2": _obj(("03B", "NOR"), 2)},
        }
    }
    return {
        "HDFEOSVersion": "HDFEOS_V2.19",
        "StructMetadata.0": struct_metadata(g),
        "coremetadata.0": format_odl(core),
        "productmetadata.0": format_odl(product),
        "productmetadata.v": format_odl(vnir),
    }


# ============================================================================ V004 writer

#: field -> (group, dimension names, HDF number type name); names of dims are our choice
_FIELDS = {
    "ImageData": ("Data Fields", ("ImageLine", "ImagePixel"), "UINT8"),
    "RadiometricCorrTable": ("Data Fields", ("ImagePixel", "CorrCoef"), "FLOAT32"),
    "LatticePoint": ("Data Fields", ("GeoTrack", "GeoXTrack", "Pair"), "INT32"),
    "SightVector": ("Data Fields", ("GeoTrack", "GeoXTrack", "Vector3"), "FLOAT64"),
    "SatellitePosition": ("Data Fields", ("GeoTrack", "Vector3"), "FLOAT64"),
    "SatelliteVelocity": ("Data Fields", ("GeoTrack", "Vector3"), "FLOAT64"),
    "ObservationTime": ("Data Fields", ("GeoTrack", "TimeWords"), "INT32"),
    "AttitudeAngle": ("Data Fields", ("GeoTrack", "Vector3"), "FLOAT64"),
    "AttitudeRate": ("Data Fields", ("GeoTrack", "Vector3"), "FLOAT64"),
    "Latitude": ("Geolocation Fields", ("GeoTrack", "GeoXTrack"), "FLOAT64"),
    "Longitude": ("Geolocation Fields", ("GeoTrack", "GeoXTrack"), "FLOAT64"),
    "SceneLineNumber": ("Geolocation Fields", ("GeoTrack",), "INT32"),
}


def _field_arrays(b: BandProduct) -> dict:
    n = b.lattice.shape[0]
    return {
        "ImageData": b.dn,
        "RadiometricCorrTable": b.rc_table,
        "LatticePoint": b.lattice,
        "SightVector": b.sight_vectors,
        "SatellitePosition": b.positions,
        "SatelliteVelocity": b.velocities,
        "ObservationTime": b.observation_time,
        "AttitudeAngle": np.zeros((n, 3)),
        "AttitudeRate": np.zeros((n, 3)),
        "Latitude": b.latitude,
        "Longitude": b.longitude,
        "SceneLineNumber": b.lattice[:, 0, 1].astype(np.int32),
    }


def struct_metadata(g: SimulatedGranule) -> str:
    """HDF-EOS ``StructMetadata.0`` describing the VNIR swaths (dimensions, maps, fields)."""
    out = ["GROUP=SwathStructure"]
    for k, (band, b) in enumerate(g.bands.items(), 1):
        arrays = _field_arrays(b)
        sizes = {}
        for name, (_, dims, _) in _FIELDS.items():
            for d, s in zip(dims, arrays[name].shape):
                sizes[d] = s
        out += [f"\tGROUP=SWATH_{k}", f'\t\tSwathName="{swath_name(band)}"', "\t\tGROUP=Dimension"]
        for i, (d, s) in enumerate(sizes.items(), 1):
            out += [
                f"\t\t\tOBJECT=Dimension_{i}",
                f'\t\t\t\tDimensionName="{d}"',
                f"\t\t\t\tSize={s}",
                f"\t\t\tEND_OBJECT=Dimension_{i}",
            ]
        out += ["\t\tEND_GROUP=Dimension", "\t\tGROUP=DimensionMap"]
        r0, dr = int(b.lattice[0, 0, 1]), int(b.lattice[1, 0, 1] - b.lattice[0, 0, 1])
        dc = int(b.lattice[0, 1, 0])
        for i, (geo, data, off, inc) in enumerate(
            (("GeoTrack", "ImageLine", r0, dr), ("GeoXTrack", "ImagePixel", 0, dc)), 1
        ):
            out += [
                f"\t\t\tOBJECT=DimensionMap_{i}",
                f'\t\t\t\tGeoDimension="{geo}"',
                f'\t\t\t\tDataDimension="{data}"',
                f"\t\t\t\tOffset={off}",
                f"\t\t\t\tIncrement={inc}",
                f"\t\t\tEND_OBJECT=DimensionMap_{i}",
            ]
        out += [
            "\t\tEND_GROUP=DimensionMap",
            "\t\tGROUP=IndexDimensionMap",
            "\t\tEND_GROUP=IndexDimensionMap",
        ]
        for group, kind in (("Geolocation Fields", "GeoField"), ("Data Fields", "DataField")):
            out.append(f"\t\tGROUP={kind}")
            names = [n for n, (grp, _, _) in _FIELDS.items() if grp == group]
            for i, name in enumerate(names, 1):
                _, dims, typ = _FIELDS[name]
                dl = ",".join(f'"{d}"' for d in dims)
                out += [
                    f"\t\t\tOBJECT={kind}_{i}",
                    f'\t\t\t\t{kind}Name="{name}"',
                    f"\t\t\t\tDataType=DFNT_{typ}",
                    f"\t\t\t\tDimList=({dl})",
                    f"\t\t\tEND_OBJECT={kind}_{i}",
                ]
            out.append(f"\t\tEND_GROUP={kind}")
        out += ["\t\tGROUP=MergedFields", "\t\tEND_GROUP=MergedFields", f"\tEND_GROUP=SWATH_{k}"]
    out += [
        "END_GROUP=SwathStructure",
        "GROUP=GridStructure",
        "END_GROUP=GridStructure",
        "GROUP=PointStructure",
        "END_GROUP=PointStructure",
        "END",
        "",
    ]
    return "\n".join(out)


def _check_target(path: Path, overwrite: bool):
    if path.exists() and not overwrite:
        raise OutputExistsError.needs_overwrite(f"{path}: exists")


def write_v004(g: SimulatedGranule, path, *, overwrite: bool = False) -> Path:
    """Write ``g`` as a V004 HDF-EOS2 file (atomically: temporary file, then rename)."""
    import pyhdf.V  # noqa: F401  (HDF.vgstart needs the module)
    from pyhdf.HDF import HC, HDF
    from pyhdf.SD import SD, SDC

    path = Path(path)
    _check_target(path, overwrite)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    os.close(fd)
    os.unlink(tmp)
    try:
        sd = SD(tmp, SDC.WRITE | SDC.CREATE | SDC.TRUNC)
        for name, text in g.attributes.items():
            sd.attr(name).set(SDC.CHAR8, text)
        refs = {}
        for band, b in g.bands.items():
            sw = swath_name(band)
            for name, arr in _field_arrays(b).items():
                group, dims, typ = _FIELDS[name]
                arr = np.ascontiguousarray(arr)
                s = sd.create(name, getattr(SDC, typ), arr.shape)
                for i, d in enumerate(dims):
                    s.dim(i).setname(f"{d}:{sw}")
                s[:] = arr
                refs.setdefault(band, {}).setdefault(group, []).append(s.ref())
                s.endaccess()
        sd.end()
        h = HDF(tmp, HC.WRITE)
        v = h.vgstart()
        top = v.create("VNIR")
        top._class = "VNIR"  # [UNVERIFIED] class of the lone Vgroup
        for band in g.bands:
            sw = v.create(swath_name(band))
            sw._class = "SWATH"
            for group in ("Geolocation Fields", "Data Fields", "Swath Attributes"):
                child = v.create(group)
                child._class = "SWATH Vgroup"
                for ref in refs[band].get(group, []):
                    child.add(720, ref)
                sw.insert(child)
                child.detach()
            top.insert(sw)
            sw.detach()
        top.detach()
        v.end()
        h.close()
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


# ============================================================================ V003 writer


def _fmt_rows(a, fmt):
    return "\n".join(" ".join(fmt % x for x in row) for row in np.atleast_2d(a)) + "\n"


def _fmt_blocks(a, fmt):
    return "\n".join(_fmt_rows(block, fmt) for block in a)


def v003_tables(b: BandProduct, decimals: int | None = 6) -> dict:
    """The V003 text tables of one band: ``{field: text}`` (notes §3.3 formats).

    ``decimals=6`` is the real products' fixed-point format (sight vectors then carry up to
    0.87 urad of rounding); ``None`` writes 17 significant digits, as ASP's V004 -> text
    extraction does.
    """
    f = "%.17g" if decimals is None else f"%.{int(decimals)}f"
    return {
        "LatticePoint": _fmt_blocks(b.lattice, "%d"),
        "SightVector": _fmt_blocks(b.sight_vectors, f),
        "SatellitePosition": _fmt_rows(b.positions, f),
        "SatelliteVelocity": _fmt_rows(b.velocities, f),
        "Latitude": _fmt_rows(b.latitude, f),
        "Longitude": _fmt_rows(b.longitude, f),
        "RadiometricCorrTable": _fmt_rows(b.rc_table, f),
        "ObservationTime": _fmt_rows(b.observation_time, "%d"),
        "AttitudeAngle": _fmt_blocks(np.zeros((b.lattice.shape[0], 1, 3)), "%.6f"),
        "AttitudeRate": _fmt_blocks(np.zeros((b.lattice.shape[0], 1, 3)), "%.6f"),
    }


def write_v003(
    g: SimulatedGranule, path, *, overwrite: bool = False, decimals: int | None = 6
) -> Path:
    """Write ``g`` as a V003 granule: a folder, or a zip if ``path`` ends in ``.zip``
    (then the ODL metadata goes to ``<zip>.met`` beside it). ``decimals`` as
    :func:`v003_tables`."""
    path = Path(path)
    _check_target(path, overwrite)
    as_zip = path.suffix.lower() == ".zip"
    work = Path(
        tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent if path.parent.exists() else None)
    )
    try:
        for band, b in g.bands.items():
            stem = f"{g.granule_id}.{swath_name(band)}"
            write_geotiff(work / f"{stem}.ImageData.tif", b.dn, None, None, None)
            for name, text in v003_tables(b, decimals).items():
                (work / f"{stem}.{name}.txt").write_text(text)
        met = g.attributes["coremetadata.0"].rsplit("END", 1)[0] + g.attributes["productmetadata.0"]
        if as_zip:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(f".{path.name}.part")
            with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as z:
                for f in sorted(work.iterdir()):
                    z.write(f, f.name)
            os.replace(tmp, path)
            Path(str(path) + ".met").write_text(met)
        else:
            (work / f"{g.granule_id}.met").write_text(met)
            if path.exists():
                shutil.rmtree(path)
            os.replace(work, path)
    finally:
        if work.exists():
            shutil.rmtree(work)
    return path


def granule_right_size(size) -> tuple[int, int]:
    """3B size (width, height) in the real 3N:3B ratio (4100 x 4200 : 5000 x 5400) for a 3N of
    ``size`` (width, height) pixels; the width a multiple of 10 (11 lattice columns)."""
    w, h = size
    return int(round(w * 5000 / 4100 / 10.0)) * 10, int(round(h * 5400 / 4200))


def write_granule_scene(
    scene,
    out,
    *,
    version: int = 4,
    seed: int = 0,
    velocity: str = "inertial",
    overwrite: bool = False,
) -> Path:
    """Write a simulated ASTER scene as an L1A granule (V004 ``.hdf`` or V003 ``.zip``) plus its
    truth (DEM, orthoimage, check points) in ``out``; returns the granule's path."""
    g = granule_from_scene(scene, seed=seed, velocity=velocity, version=version)
    out = write_scene(scene, out, overwrite=overwrite, write_images=False)
    if version == 4:
        return write_v004(g, out / f"{g.granule_id}.hdf", overwrite=overwrite)
    return write_v003(g, out / f"{g.granule_id}.zip", overwrite=overwrite)
