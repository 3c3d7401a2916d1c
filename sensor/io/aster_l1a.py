"""ASTER Level-1A VNIR granules (bands 3N and 3B): V004 HDF-EOS2 files and, through
:mod:`stereodem.sensor.io.aster_v003`, legacy V003 zips or folders.

One entry point, :func:`open_aster_granule`, returns an :class:`AsterGranule`: per band
(``"3N"``, ``"3B"``) an :class:`AsterBand` with the rigorous
:class:`stereodem.sensor.models.aster.AsterModel` built from the product's lattice geometry,
the image (float32 radiance ``L = A V / G + D`` from ``RadiometricCorrTable``, or DN), the mask
of fill pixels, and the granule's metadata (acquisition time, granule id, sun angles, cloud
cover, corners) from its ODL attributes.

Format (ASTER notes ``aster-l1a-format.md``): every VNIR band is an HDF-EOS swath
``VNIR_Band<b>`` (Vgroup of class ``SWATH``) with child Vgroups ``Data Fields``
(``ImageData`` uint8 (rows, cols), ``RadiometricCorrTable`` (cols, 3) as (D, A, G),
``LatticePoint`` (N, 11, 2) as (col, row), ``SightVector`` (N, 11, 3) in the orbital frame,
``SatellitePosition`` / ``SatelliteVelocity`` (N, 3) ECEF, ``ObservationTime``) and
``Geolocation Fields`` (``Latitude`` geocentric / ``Longitude`` (N, 11), degrees). The SDS
names repeat in every swath, so fields are found through the Vgroups (or, failing that, by the
``:<swath>`` suffix HDF-EOS gives dimension names), never by name alone (notes §2.6).

Using a granule::

    from stereodem.sensor.io.aster_l1a import open_aster_granule, is_aster_granule
    g = open_aster_granule("AST_L1A_00407312017190728_20250822173530.hdf")   # or V003 .zip / folder
    left, right = g.stereo_pair()                    # bands 3N and 3B
    image = left.image()                             # float32 radiance, NaN at fill
    model = left.model                               # AsterModel: project / localize / rays
    tags = g.tags()                                  # ASTER_ACQUISITION_TIME, ... for outputs

What the reader checks rather than assumes (notes §4.3, §7): the lattice is read from the data
(any N, any spacing, negative first row); sight vectors are renormalised; the convention of
``SatelliteVelocity`` (inertial or Earth-fixed) is decided against the positions; and the model
is validated against the product's own ``Latitude``/``Longitude`` when present.
"""

from __future__ import annotations

import logging
import re
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stereodem.core import geodesy
from stereodem.core.errors import InputError, SensorModelError, not_found
from stereodem.sensor.io.aster_metadata import (
    first_key,
    granule_metadata,
    not_l1a_message,
    product_level,
)
from stereodem.sensor.io.odl import flatten_odl, parse_odl
from stereodem.sensor.models.aster import (
    ASTER_LINE_PERIOD,
    AsterGeometry,
    AsterModel,
    lattice_velocities,
)

log = logging.getLogger(__name__)

#: the along-track stereo bands
VNIR_BANDS = ("3N", "3B")
#: data fields a band swath must have to build its model and image
REQUIRED_FIELDS = (
    "ImageData",
    "RadiometricCorrTable",
    "LatticePoint",
    "SightVector",
    "SatellitePosition",
)
#: mean lattice ray error (rad) above which the product's sight vectors and its own
#: Latitude/Longitude disagree (about 2 VNIR pixels at 700 km)
LATTICE_TOLERANCE_RAD = 50e-6
#: largest difference (m/s) between SatelliteVelocity and a candidate convention
VELOCITY_TOLERANCE = 30.0

_DFTAG_VG, _DFTAG_NDG = 1965, 720
_HDF4_MAGIC = b"\x0e\x03\x13\x01"


def swath_name(band: str) -> str:
    """HDF-EOS swath (and V003 file infix) of a VNIR band: ``VNIR_Band3N``."""
    return f"VNIR_Band{band}"


# ============================================================================ data classes


@dataclass
class L1ABandFields:
    """The fields of one VNIR band swath as stored in the product (format-independent).

    Arrays are in the product's layout and units (notes §2.3); ``read_dn`` reads ``ImageData``
    (uint8, (rows, cols)) on demand. ``latitude`` is geocentric.
    """

    band: str
    source: str  #: "<file>:<swath>" for messages
    image_shape: tuple
    read_dn: Callable[[], np.ndarray]
    rc_table: np.ndarray  #: (cols, 3) = (D, A, G)
    lattice: np.ndarray  #: (N, K, 2) = (col, row)
    sight_vectors: np.ndarray  #: (N, K, 3) orbital frame
    satellite_positions: np.ndarray  #: (N, 3) ECEF m
    satellite_velocities: np.ndarray | None = None
    observation_times: np.ndarray | None = None
    latitude: np.ndarray | None = None  #: (N, K) geocentric deg
    longitude: np.ndarray | None = None


@dataclass
class AsterBand:
    """One VNIR band of a granule: its model, image access and the checks made on it."""

    band: str
    model: AsterModel
    fields: L1ABandFields
    velocity_convention: str
    lattice_error_rad: tuple | None = None  #: (mean, max) model vs product lat/lon; None if absent
    _dn: np.ndarray | None = field(default=None, repr=False)

    @property
    def shape(self) -> tuple:
        """Image (rows, cols)."""
        return tuple(self.fields.image_shape)

    def dn(self) -> np.ndarray:
        """The L1A digital numbers, uint8 (rows, cols); 0 is fill."""
        if self._dn is None:
            self._dn = self.fields.read_dn()
        return self._dn

    def fill_mask(self) -> np.ndarray:
        """True where the pixel is fill (DN 0; notes §5)."""
        return self.dn() == 0

    def image(self, radiometric: bool = True) -> np.ndarray:
        """The image as float32, NaN at fill pixels.

        ``radiometric=True`` applies the per-detector correction ``L = A V / G + D``
        (W m-2 sr-1 um-1; this is also the destriping), else returns the DN.
        """
        v = self.dn()
        out = v.astype(np.float32)
        if radiometric:  # in place (a granule's band is ~100 MB of float32): a * V / G + D
            d, a, g = (self.fields.rc_table[:, k].astype(np.float32) for k in range(3))
            np.multiply(out, a, out=out)
            np.divide(out, g, out=out)
            np.add(out, d, out=out)
        np.copyto(out, np.float32(np.nan), where=v == 0)
        return out


@dataclass
class AsterGranule:
    """An ASTER L1A granule opened by :func:`open_aster_granule`.

    Attributes
    ----------
    path : str
    product : str
        ``"AST_L1A V004"`` or ``"AST_L1A V003"``.
    granule_id : str
    metadata : dict
        ``acquisition_time`` (ISO 8601 UTC or None), ``granule_id``, ``sun_azimuth_deg``,
        ``sun_elevation_deg``, ``cloud_cover_pct``, ``pointing_angle_deg``, ``corners``
        (geodetic ``{"UPPERLEFT": (lat, lon), ...}``) - each None when the product lacks it.
    odl : dict
        Parsed ODL attributes by attribute name (nested dicts, :func:`parse_odl`).
    bands : dict
        ``"3N"`` / ``"3B"`` -> :class:`AsterBand`.
    """

    path: str
    product: str
    granule_id: str
    metadata: dict
    odl: dict
    bands: dict

    def __getitem__(self, band: str) -> AsterBand:
        return self.band(band)

    def band(self, band: str) -> AsterBand:
        """The band named ``"3N"`` / ``"3B"`` (also ``"3n"``, ``"Band3B"``, ``"VNIR_Band3B"``)."""
        m = re.search(r"(?:^|BAND)(3[NB])$", str(band).upper().strip())
        key = m.group(1) if m else str(band)
        if key not in self.bands:
            raise InputError(
                f"{self.path}: no band {band!r} in this granule (has {', '.join(self.bands)})"
            )
        return self.bands[key]

    def model(self, band: str) -> AsterModel:
        """The rigorous model of ``band`` (``"3N"`` or ``"3B"``)."""
        return self.band(band).model

    def read_image(self, band: str, radiometric: bool = True) -> np.ndarray:
        """The image of ``band`` as float32 with NaN at fill (see :meth:`AsterBand.image`)."""
        return self.band(band).image(radiometric)

    def stereo_pair(self):
        """``(3N, 3B)`` bands: the left and right images of the along-track pair."""
        return self.band("3N"), self.band("3B")

    def tags(self) -> dict:
        """Metadata as flat string tags (GeoTIFF tags, ``run.json``), prefixed ``ASTER_``."""
        out = {}
        for k, v in self.metadata.items():
            if v is None:
                continue
            if k == "corners":
                for name, (la, lo) in v.items():
                    out[f"ASTER_{name}"] = f"{la:.6f}, {lo:.6f}"
            else:
                out[f"ASTER_{k.upper()}"] = str(v)
        out["ASTER_PRODUCT"] = self.product
        return out


# ============================================================================ entry point


def open_aster_granule(path, *, bands=VNIR_BANDS) -> AsterGranule:
    """Open an ASTER L1A granule: a V004 ``.hdf`` (HDF-EOS2), or a V003 ``.zip`` or folder.

    Parameters
    ----------
    path : str or Path
    bands : sequence of str
        Bands that must be present (default both stereo bands ``3N`` and ``3B``).

    Raises
    ------
    InputError
        Not an ASTER product, an L1B/L1T product, a missing band, a truncated file or a
        missing V003 table (one line naming the file and what is missing).
    SensorModelError
        Geometry fields with wrong shapes, or sight vectors that contradict the product's own
        latitude/longitude.
    """
    p = Path(path)
    if not p.exists():
        raise InputError(not_found(p, "ASTER granule"))
    if p.is_dir() or p.suffix.lower() == ".zip":
        from stereodem.sensor.io.aster_v003 import read_v003

        product, gid, odl, fields = "AST_L1A V003", *read_v003(p)
    else:
        product, (gid, odl, fields) = "AST_L1A V004", read_v004(p)
    for b in bands:
        if b not in fields:
            what = swath_name(b)
            why = (
                " (a night-time or VNIR-off scene has no along-track stereo)"
                if b == "3B" and "3N" in fields
                else ""
            )
            raise InputError(f"{p}: no band {b} ({what} swath){why}")
    built = {b: build_band(fields[b]) for b in fields if b in VNIR_BANDS}
    return AsterGranule(
        path=str(p),
        product=product,
        granule_id=gid,
        metadata=granule_metadata(odl, gid),
        odl=odl,
        bands=built,
    )


def read_granule_band(path, band: str, *, radiometric: bool = True):
    """``(image float32 with NaN fill, AsterModel, tags)`` of one band of a granule: the one
    call an image/model input layer needs (``band`` as :meth:`AsterGranule.band`)."""
    g = open_aster_granule(path, bands=())
    b = g.band(band)
    return (
        b.image(radiometric),
        b.model,
        {**g.tags(), "ASTER_BAND": b.band, "ASTER_RADIOMETRIC": str(bool(radiometric))},
    )


def is_aster_granule(path) -> bool:
    """Whether ``path`` should be opened with :func:`open_aster_granule` rather than as a
    GeoTIFF: any HDF4 file (the reader then says precisely what it is, e.g. L1B), a zip or
    folder holding ``*.VNIR_Band3N/3B.ImageData.tif``, or a zip named ``AST_L1*``."""
    p = Path(path)
    if p.is_dir():
        return any(p.rglob("*.VNIR_Band3?.ImageData.tif"))
    if not p.is_file():
        return False
    if p.suffix.lower() == ".zip":
        if p.name.upper().startswith("AST_L1"):
            return True

        try:
            with zipfile.ZipFile(p) as z:
                return any(
                    ".VNIR_Band3" in n and n.endswith(".ImageData.tif") for n in z.namelist()
                )
        except (zipfile.BadZipFile, OSError):
            return False
    with open(p, "rb") as fh:
        return fh.read(4) == _HDF4_MAGIC


# ============================================================================ geometry


def _geocentric_to_ecef(lat_gc_deg, lon_deg):
    """Point on the WGS84 ellipsoid at geocentric latitude / longitude (notes §4.1)."""
    psi, lam = np.radians(lat_gc_deg), np.radians(lon_deg)
    a, b = geodesy.A, geodesy.B
    rho = a * b / np.sqrt((a * np.sin(psi)) ** 2 + (b * np.cos(psi)) ** 2)
    return np.stack(
        [rho * np.cos(psi) * np.cos(lam), rho * np.cos(psi) * np.sin(lam), rho * np.sin(psi)], -1
    )


def velocity_convention(times, positions, velocities) -> str:
    """``"inertial"``, ``"earth_fixed"`` or ``"unknown"``: what ``SatelliteVelocity`` holds.

    Compares the stored velocities with the time derivative of the ECEF positions (Earth-fixed)
    and with that plus ``omega_E x r`` (inertial in ECEF axes); the closer one wins if it is
    within :data:`VELOCITY_TOLERANCE` (notes §4.3, rule 3).
    """
    if velocities is None:
        return "unknown"
    v_ef = lattice_velocities(times, positions)
    v_in = v_ef + np.cross([0.0, 0.0, geodesy.OMEGA_EARTH], positions)
    d_ef = float(np.median(np.linalg.norm(velocities - v_ef, axis=-1)))
    d_in = float(np.median(np.linalg.norm(velocities - v_in, axis=-1)))
    best, dist = ("inertial", d_in) if d_in <= d_ef else ("earth_fixed", d_ef)
    return best if dist < VELOCITY_TOLERANCE else "unknown"


def _check_shapes(f: L1ABandFields):
    src = f.source
    lat = np.asarray(f.lattice)
    if lat.ndim != 3 or lat.shape[2] != 2 or lat.shape[0] < 2 or lat.shape[1] < 4:
        raise SensorModelError(f"{src}: LatticePoint has shape {lat.shape}, expected (N>=2, 11, 2)")
    n, k = lat.shape[:2]
    if np.shape(f.sight_vectors) != (n, k, 3):
        raise SensorModelError(
            f"{src}: SightVector has shape {np.shape(f.sight_vectors)}, expected ({n}, {k}, 3)"
        )
    if np.shape(f.satellite_positions) != (n, 3):
        raise SensorModelError(
            f"{src}: SatellitePosition has shape "
            f"{np.shape(f.satellite_positions)}, expected ({n}, 3)"
        )
    for name, arr in (("SatelliteVelocity", f.satellite_velocities),):
        if arr is not None and np.shape(arr) != (n, 3):
            raise SensorModelError(f"{src}: {name} has shape {np.shape(arr)}, expected ({n}, 3)")
    for name, arr in (("Latitude", f.latitude), ("Longitude", f.longitude)):
        if arr is not None and np.shape(arr) != (n, k):
            raise SensorModelError(f"{src}: {name} has shape {np.shape(arr)}, expected ({n}, {k})")
    rows, cols = f.image_shape
    if np.shape(f.rc_table) != (cols, 3):
        raise SensorModelError(
            f"{src}: RadiometricCorrTable has shape {np.shape(f.rc_table)}, "
            f"expected one (D, A, G) row per detector: ({cols}, 3)"
        )
    if np.any(f.rc_table[:, 2] == 0) or not np.all(np.isfinite(f.rc_table)):
        raise SensorModelError(f"{src}: RadiometricCorrTable holds zero gains or non-finite values")
    norm = np.linalg.norm(f.sight_vectors, axis=-1)
    if not np.all(np.isfinite(norm)) or np.any(norm < 0.5):
        raise SensorModelError(f"{src}: SightVector holds zero-length or non-finite vectors")
    if not np.all(np.isfinite(f.satellite_positions)):
        raise SensorModelError(f"{src}: SatellitePosition holds non-finite values")


def build_band(f: L1ABandFields, *, line_period: float = ASTER_LINE_PERIOD) -> AsterBand:
    """The model of one band from its product fields, with the checks of notes §4.3."""
    _check_shapes(f)
    lattice = np.asarray(f.lattice, np.float64)
    sight = np.asarray(f.sight_vectors, np.float64)
    sight = sight / np.linalg.norm(sight, axis=-1, keepdims=True)
    pos = np.asarray(f.satellite_positions, np.float64)
    vel = None if f.satellite_velocities is None else np.asarray(f.satellite_velocities, np.float64)
    times = lattice[:, 0, 1] * line_period
    try:
        conv = velocity_convention(times, pos, vel)
    except ValueError:
        conv = "unknown"
    have_ll = f.latitude is not None and f.longitude is not None
    if have_ll:
        ground = _geocentric_to_ecef(np.asarray(f.latitude, float), np.asarray(f.longitude, float))
        world = ground - pos[:, None, :]
        world /= np.linalg.norm(world, axis=-1, keepdims=True)
    else:
        world = sight.copy()  # replaced below by the model's own rays
    rows, cols = f.image_shape
    name = f"{Path(f.source.rsplit(':', 1)[0]).stem}_{f.band}"

    def make(inertial):
        g = AsterGeometry(
            lattice=lattice,
            sight_vectors=sight,
            world_sight_vectors=world,
            satellite_positions=pos,
            image_cols=int(cols),
            image_rows=int(rows),
            path=f.source,
            satellite_velocities=vel,
            velocity_convention=conv,
            observation_times=None
            if f.observation_times is None
            else np.asarray(f.observation_times, np.float64),
        )
        return AsterModel(g, line_period=line_period, inertial_frame=inertial, name=name)

    try:
        model = make(True)
    except SensorModelError as exc:
        msg = str(exc)
        raise SensorModelError(msg if msg.startswith(f.source) else f"{f.source}: {msg}") from None
    if not have_ll:
        _, d = model.rays(lattice[..., 0], lattice[..., 1])
        model.geometry.world_sight_vectors = d
        return AsterBand(f.band, model, f, conv, None)
    err = model.lattice_sight_errors()
    if err.mean() > LATTICE_TOLERANCE_RAD:
        alt = make(False)
        err_alt = alt.lattice_sight_errors()
        if err_alt.mean() < LATTICE_TOLERANCE_RAD:
            log.warning(
                "%s: orbital frame built with the Earth-fixed velocity reproduces the "
                "product latitude/longitude (mean %.1f urad); using it",
                f.source,
                1e6 * err_alt.mean(),
            )
            model, err = alt, err_alt
        else:
            raise SensorModelError(
                f"{f.source}: SightVector/SatellitePosition do not reproduce the product's "
                f"Latitude/Longitude (mean ray error {1e6 * err.mean():.0f} urad inertial frame, "
                f"{1e6 * err_alt.mean():.0f} urad Earth-fixed frame)"
            )
    return AsterBand(f.band, model, f, conv, (float(err.mean()), float(err.max())))


# ============================================================================ V004 (HDF-EOS2)


def _hdf_error():
    from pyhdf.error import HDF4Error

    return HDF4Error


def _vgroup_swaths(path):
    """``{swath name: {"Data Fields": {field: ref}, "Geolocation Fields": {...}}}`` via Vgroups."""
    import pyhdf.V  # noqa: F401  (HDF.vgstart needs the V module imported; notes §2.6)
    from pyhdf.HDF import HDF

    HDF4Error = _hdf_error()
    h = HDF(str(path))
    v = h.vgstart()
    out: dict = {}
    try:
        ref = -1
        while True:
            try:
                ref = v.getid(ref)
            except HDF4Error:
                break
            vg = v.attach(ref)
            try:
                if vg._class != "SWATH":
                    continue
                groups = {}
                for tag, r in vg.tagrefs():
                    if tag != _DFTAG_VG:
                        continue
                    child = v.attach(r)
                    try:
                        groups[child._name] = [rr for t, rr in child.tagrefs() if t == _DFTAG_NDG]
                    finally:
                        child.detach()
                out[vg._name] = groups
            finally:
                vg.detach()
    finally:
        v.end()
        h.close()
    return out


def _sds_by_suffix(sd):
    """Fallback without Vgroups: ``{swath: {field: sds index}}`` from ``<dim>:<swath>`` names."""
    out: dict = {}
    for i in range(sd.info()[0]):
        s = sd.select(i)
        try:
            name = s.info()[0]
            dims = list(s.dimensions().keys())
        finally:
            s.endaccess()
        suffixes = {d.split(":", 1)[1] for d in dims if ":" in d}
        if len(suffixes) == 1:
            out.setdefault(suffixes.pop(), {})[name] = i
    return out


def read_v004(path):
    """Read a V004 HDF-EOS2 granule: ``(granule_id, odl, {band: L1ABandFields})``.

    See :func:`open_aster_granule` for the errors.
    """
    from pyhdf.SD import SD, SDC

    HDF4Error = _hdf_error()
    path = Path(path)
    with open(path, "rb") as fh:
        magic = fh.read(4)
    if magic != _HDF4_MAGIC:
        raise InputError(
            f"{path}: not an ASTER L1A granule (neither an HDF4 file, as V004 "
            f"granules are, nor a V003 zip or folder)"
        )
    try:
        sd = SD(str(path), SDC.READ)
    except HDF4Error as exc:
        raise InputError(
            f"{path}: HDF4 file cannot be opened - truncated or damaged ({exc})"
        ) from None
    try:
        attrs = sd.attributes()
    except HDF4Error as exc:
        sd.end()
        raise InputError(
            f"{path}: cannot read the global attributes - file truncated or damaged ({exc})"
        ) from None
    odl = {}
    for name, text in attrs.items():
        low = name.lower()
        if isinstance(text, str) and (
            low.startswith(("coremetadata", "productmetadata", "archivemetadata", "structmetadata"))
        ):
            try:
                odl[name] = parse_odl(text, source=f"{path}:{name}")
            except InputError:
                log.warning("%s: attribute %s is not valid ODL; ignored", path, name)
    flat: dict = {}
    for tree in odl.values():
        flat.update(flatten_odl(tree))
    level = product_level(flat, path.name)
    if level in ("L1B", "L1T"):
        sd.end()
        raise InputError(not_l1a_message(path, level))
    try:
        swaths = _vgroup_swaths(path)
        located = {}
        for sw, groups in swaths.items():
            refs = groups.get("Data Fields", []) + groups.get("Geolocation Fields", [])
            fields = {}
            for r in refs:
                idx = sd.reftoindex(r)
                s = sd.select(idx)
                fields[s.info()[0]] = idx
                s.endaccess()
            located[sw] = fields
        if not any(sw.startswith("VNIR_") for sw in located):
            located = _sds_by_suffix(sd)
    except HDF4Error as exc:
        sd.end()
        raise InputError(
            f"{path}: cannot walk the HDF-EOS swath structure - file truncated or damaged ({exc})"
        ) from None
    vnir = {sw: f for sw, f in located.items() if sw.startswith("VNIR_Band")}
    instrument = str(first_key(flat, "INSTRUMENTSHORTNAME") or "").upper()
    if not vnir:
        sd.end()
        if level is None and instrument != "ASTER":
            raise InputError(
                f"{path}: not an ASTER L1A granule (no ASTER metadata and no VNIR_Band3N/3B swaths)"
            )
        raise InputError(
            f"{path}: ASTER granule without VNIR swaths (VNIR_Band3N, VNIR_Band3B): "
            f"the VNIR telescope was off"
        )
    gid = str(first_key(flat, "LOCALGRANULEID") or path.stem)
    gid = re.sub(r"\.hdf$", "", gid, flags=re.I)
    bands = {}
    for b in VNIR_BANDS:
        sw = swath_name(b)
        if sw in vnir:
            bands[b] = _v004_band(sd, path, sw, b, vnir[sw])
    # keep the SD interface open for the lazy image reads; closed when garbage-collected
    return gid, odl, bands


def _v004_band(sd, path, sw, band, idx):
    HDF4Error = _hdf_error()
    src = f"{path}:{sw}"
    missing = [f for f in REQUIRED_FIELDS if f not in idx]
    if missing:
        raise InputError(
            f"{src}: swath has no {', '.join(missing)} field{'s' if len(missing) > 1 else ''}"
        )

    def get(name, dtype=np.float64):
        if name not in idx:
            return None
        try:
            s = sd.select(idx[name])
            try:
                return np.asarray(s.get(), dtype=dtype)
            finally:
                s.endaccess()
        except HDF4Error as exc:
            raise InputError(
                f"{src}: cannot read {name} - file truncated or damaged ({exc})"
            ) from None

    s = sd.select(idx["ImageData"])
    shape = tuple(s.info()[2])
    try:
        if len(shape) != 2:
            raise SensorModelError(f"{src}: ImageData has shape {shape}, expected (rows, cols)")
        s[shape[0] - 1 : shape[0], :]  # a truncated file fails here
    except HDF4Error as exc:
        raise InputError(
            f"{src}: cannot read ImageData - file truncated or damaged ({exc})"
        ) from None
    finally:
        s.endaccess()

    def read_dn():
        img = get("ImageData", np.uint8)
        return img

    return L1ABandFields(
        band=band,
        source=src,
        image_shape=shape,
        read_dn=read_dn,
        rc_table=get("RadiometricCorrTable"),
        lattice=get("LatticePoint"),
        sight_vectors=get("SightVector"),
        satellite_positions=get("SatellitePosition"),
        satellite_velocities=get("SatelliteVelocity"),
        observation_times=get("ObservationTime"),
        latitude=get("Latitude"),
        longitude=get("Longitude"),
    )
