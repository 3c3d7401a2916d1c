"""The one DEM type: a raster of heights with its CRS, nodata, vertical reference and optional
companion layers (issue #23: stereo output, filters, orthoimages and assessment share it).

Heights are sampled bilinearly at longitude/latitude (degrees). Points outside the raster or
touching a void are reported (NaN plus a status code) and never filled with an invented value.

Companion layers live beside the heights file (:data:`LAYERS`): a stereo DEM's ``count.tif``,
``score.tif`` and ``raygap.tif`` in its folder, a clean DEM's ``<stem>_edit_mask.tif`` and
``<stem>_sigma_vertical.tif``. :meth:`DEM.write` writes the heights and every layer present,
:meth:`DEM.from_file` reads them back (``layers=True``).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np
import rasterio
import rasterio.transform
from affine import Affine
from pyproj import CRS
from pyproj.crs import VerticalCRS
from rasterio.enums import MaskFlags
from rasterio.warp import calculate_default_transform, transform_bounds

from stereodem.core import geodesy
from stereodem.core.errors import (
    CRSError,
    DEMCoverageError,
    DEMError,
    InputError,
    NoOverlapError,
    VerticalReferenceError,
)
from stereodem.core.grid import MapGrid, crs_unit, map_crs
from stereodem.core.memory import check_allocation
from stereodem.core.raster import (
    VERTICAL_TAG,
    crs_with_vertical,
    parse_creation_options,
    probe_blocks,
    read_image,
    reading_env,
    unreadable,
    write_geotiff,
)
from stereodem.core.vertical import ELLIPSOID, GEOID, VERTICALS
from stereodem.core.warp import RESAMPLING_METHODS, check_overlap, rio_crs, to_grid

#: status codes returned by :meth:`DEM.sample`
OK, OUTSIDE, VOID = 0, 1, 2

#: heights (m) that no place on Earth has, above the ellipsoid or the geoid: the deepest
#: ocean floor is about -11 000 m, the highest summit 8 849 m, the geoid within +-110 m. A DEM
#: file's cells outside are no-data (an undeclared nodata value such as -9999, -32768 or
#: 1e30), read as NaN with a warning (:meth:`DEM.from_file`)
PLAUSIBLE_HEIGHTS_M = (-12_000.0, 10_000.0)

#: the nodata value most DEM software writes (ArcGIS, ASCII grids), inside the plausible
#: range: a file that declares no nodata value has no-data there too
UNDECLARED_NODATA = -9999.0

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Layer:
    """How a companion layer is stored: ``name`` in the folder of the heights file, or
    ``suffix`` after the heights file's stem; stored dtype, nodata, band description, unit."""

    name: str | None
    suffix: str | None
    dtype: type
    nodata: float
    description: str | None
    unit: str | None

    def path(self, dem_path) -> Path:
        p = Path(dem_path)
        return p.with_name(self.name) if self.name else p.with_name(f"{p.stem}{self.suffix}")


#: companion layers of a DEM, by attribute, in writing order
LAYERS = {
    "count": Layer("count.tif", None, np.int32, 0, "space-intersected points per cell", "1"),
    "score": Layer(
        "score.tif",
        None,
        np.float32,
        np.nan,
        "mean correlation score (ZNCC) of the cell's points",
        "1",
    ),
    "ray_gap": Layer(
        "raygap.tif", None, np.float32, np.nan, "mean ray gap of the cell's points", "metre"
    ),
    "sigma": Layer(None, "_sigma_vertical.tif", np.float32, np.nan, None, None),
    "edit_mask": Layer(
        None,
        "_edit_mask.tif",
        np.uint8,
        255,
        "edit code: 0 kept, 1-9 filter reason (9 cloud), 99 border rim, 100/101 filled",
        "1",
    ),
}

#: band description of the heights by vertical reference
_HEIGHT_DESCRIPTION = {
    GEOID: "height above the EGM96 geoid",
    ELLIPSOID: "height above the WGS84 ellipsoid",
}


def layer_path(dem_path, layer: str) -> Path:
    """Where companion ``layer`` (a key of :data:`LAYERS`) of the DEM at ``dem_path`` lives."""
    return LAYERS[layer].path(dem_path)


def edit_mask_path(dem_path) -> Path:
    """Where the edit mask of a clean DEM is written (``<stem>_edit_mask.tif``)."""
    return layer_path(dem_path, "edit_mask")


def write_layer(
    dem_path,
    layer: str,
    data,
    transform,
    crs,
    *,
    overwrite=False,
    creation_options=None,
    description=None,
) -> Path:
    """Write companion ``layer`` of the DEM at ``dem_path`` (stored type, nodata, description
    and unit of :data:`LAYERS`; ``description`` replaces the band description, e.g. a fused
    DEM's ``count`` counts stereo pairs, not points); the one place a layer file is written."""
    spec = LAYERS[layer]
    kw = {}
    description = description or spec.description
    if description:
        kw = dict(descriptions=[description], units=[spec.unit])
    return write_geotiff(
        spec.path(dem_path),
        np.asarray(data).astype(spec.dtype, copy=False),
        transform,
        crs,
        spec.nodata,
        overwrite=overwrite,
        creation_options=creation_options,
        **kw,
    )


def _vertical_from_crs(crs: CRS | None) -> str | None:
    """Vertical reference said by a CRS: a compound CRS whose vertical part is a geoid height
    (EGM96/EGM2008, any gravity-related height) -> ``"geoid"``; a 3-D CRS with an ellipsoidal
    height axis (EPSG:4979, a projected CRS promoted to 3-D, or a compound CRS with an
    ellipsoidal vertical part) -> ``"ellipsoid"``; otherwise ``None``."""
    if crs is None:
        return None
    try:
        pcrs = CRS.from_user_input(crs)
    except Exception:
        return None
    axes = [a.name.lower() for a in pcrs.axis_info]
    if any("ellipsoidal height" in a for a in axes):
        return ELLIPSOID
    if pcrs.is_compound:
        names = " ".join(str(sub.name) for sub in pcrs.sub_crs_list).lower()
        if "ellipsoid" in names:
            return ELLIPSOID
        if (
            "egm96" in names
            or "egm2008" in names
            or "geoid" in names
            or any("gravity-related" in a for a in axes)
        ):
            return GEOID
    return None


def file_vertical(path, crs: CRS | None, tag: str | None, given: str | None) -> str | None:
    """The vertical reference of a DEM file's heights: what the file says (its CRS, else
    stereodem's ``STEREODEM_VERTICAL`` tag ``tag``), else ``given`` (``--dem-vertical``,
    ``--ref-vertical``, a configuration's ``*_vertical``: the reference of files that do not
    say), else ``None`` (unknown): :func:`said_vertical` with what a DEM file says."""
    own = _vertical_from_crs(crs) or (tag.lower() if tag else None)
    return said_vertical(path, own, given)


#: how a DEM file that says the wrong vertical reference is mended (:func:`said_vertical`)
MEND_DEM_FILE = "a mislabelled file is mended with gdal_edit.py -a_srs"


def said_vertical(
    path, own: str | None, given: str | None, *, said_by: str = "", mend: str = MEND_DEM_FILE
) -> str | None:
    """The vertical reference of a file's heights: ``own`` (what the file says: a DEM's CRS
    or tag, :func:`file_vertical`; a point file's height column, ``h_ellipsoid``/``h_geoid``,
    :func:`stereodem.post.altimetry.read_points`), else ``given`` (``--dem-vertical``,
    ``--ref-vertical``, a configuration's ``*_vertical``: the reference of files that do not
    say), else ``None`` (unknown). The one rule of every command and reader of heights, DEMs
    and points alike.

    A ``given`` that contradicts the file is not applied (a default or a template would
    otherwise relabel a correct file: ellipsoidal heights read as EGM96 heights are off by
    the geoid undulation, tens of metres); a warning names the file (``said_by``: where in
    it, e.g. `` (column 'h_ellipsoid')``) and how such a file is mended (``mend``). A
    ``given`` that is no vertical reference is a :class:`DEMError` naming the file, whatever
    the file says."""
    try:
        _check_vertical(given)
    except DEMError as exc:
        raise DEMError(f"{path}: {exc}") from None
    if own in VERTICALS and given in VERTICALS and given != own:
        log.warning(
            "%s: the file says %s heights%s: read as %s (the %s given applies to files that "
            "do not say; %s)",
            path,
            own,
            said_by,
            own,
            given,
            mend,
        )
    return own or given


#: metres per foot, by the names of a height unit: GDAL's unit type of a band (which a GeoTIFF
#: takes from its vertical CRS, e.g. ``US survey foot`` for NAVD88 height (ftUS), EPSG:6360) or
#: the unit of a CRS's vertical axis
_FEET_M = {
    "ft": 0.3048,
    "foot": 0.3048,
    "feet": 0.3048,
    "international foot": 0.3048,
    "us survey foot": 1200 / 3937,
    "us survey feet": 1200 / 3937,
    "us-ft": 1200 / 3937,
    "ftus": 1200 / 3937,
    "us_survey_foot": 1200 / 3937,
}


def other_geoid(crs: CRS | None) -> CRS | None:
    """The vertical part of a compound ``crs`` when it is a gravity-related height above
    another geoid than EGM96 (EGM2008 height, EPSG:3855; NAVD88 height, EPSG:5703; ...), else
    None (EGM96 height, EPSG:5773, is the geoid of every conversion here)."""
    try:
        pcrs = CRS.from_user_input(crs) if crs is not None else None
    except Exception:
        return None
    if pcrs is None or not pcrs.is_compound:
        return None
    for sub in pcrs.sub_crs_list:
        if sub.is_vertical and "ellipsoid" not in sub.name.lower():
            if "egm96" in sub.name.lower():
                return None
            unit = sub.axis_info[0].unit_name.lower() if sub.axis_info else "metre"
            if unit not in ("metre", "meter", "m"):  # heights are read in metres (feet: 0.3048)
                return VerticalCRS(name=f"{sub.datum.name} height", datum=sub.datum)
            return sub
    return None


def geoid_name(dem) -> str | None:
    """The name of the geoid ``dem``'s heights are above (``"EGM96 height"`` unless its file
    named another: :attr:`DEM.geoid_crs`); None when they are not geoid heights. ``dem``: a
    :class:`DEM` or anything with a ``vertical`` (altimetry points: EGM96 when geoid)."""
    if dem.vertical != GEOID:
        return None
    geoid = getattr(dem, "geoid_crs", None)
    return geoid.name if geoid is not None else "EGM96 height"


def to_vertical_of(heights, target, *, name: str = "DEM"):
    """``heights`` (a :class:`DEM` or altimetry points) in ``target``'s vertical reference, and
    a note saying what was done (``name``: what the note calls ``heights``). The one rule of
    every comparison of two sets of heights (``assess``, ``change``, ``stack``,
    ``coregister``, which brings its reference to the DEM's).

    Raises :class:`VerticalReferenceError` when one reference is known and the other is not.
    When both are unknown they are assumed identical (and the note says so). EGM96 is the
    geoid of the conversions: heights above another geoid (EGM2008, NAVD88:
    :attr:`DEM.geoid_crs`) on either side are off by its separation from EGM96, which is
    said, whichever side is converted (:meth:`DEM.to_reference` says it of the side it
    converts; here of geoid heights compared with another geoid's). ``post.assess.
    reconcile_vertical`` is this rule with the DEM converted to the reference's.
    """
    a, b = heights.vertical, target.vertical
    if a is not None and b is not None and a != b:
        converted = heights.to_reference(b)
        note = f"{name} converted from {a} to {b} (EGM96)"
    elif a == b:
        converted = heights
        note = f"both {a}" if a else "both unknown; assumed identical"
        if a is None:  # said, not only written in the report
            log.info(
                "%s and %s: neither says its vertical reference (geoid or ellipsoid): compared "
                "as if the same (--dem-vertical / --ref-vertical say it)",
                heights.path or name,
                target.path or "the reference",
            )
    else:
        unknown = heights if a is None else target
        raise VerticalReferenceError(
            f"{unknown.path or 'DEM'}: vertical reference unknown while the other is {a or b}; "
            "say which with --dem-vertical/--ref-vertical {geoid,ellipsoid}"
        )
    ga, gb = geoid_name(converted), geoid_name(target)
    if ga != gb:  # EGM2008 against EGM96 heights: no conversion here between the two
        log.warning(
            "%s: heights above %s%s compared with %s's above %s as if one geoid: off by "
            "their separation (EGM2008 - EGM96: within about 1 m over most land, a few "
            "metres in high mountains)",
            heights.path or name,
            ga,
            "" if a == b else f" (converted from the {a} with EGM96)",
            target.path or "the reference",
            gb,
        )
        if a == b:
            return converted, f"both geoid, but {ga} and {gb}: compared unconverted"
        note += f"; compared with {gb} as if one geoid"
    return converted, note


def height_unit_m(ds, band: int = 1, crs: CRS | None = None) -> float:
    """Metres per stored height unit of band ``band`` of the open raster ``ds``: a foot when
    its unit (GDAL's unit type) or else the vertical axis of its CRS (``crs``, the file's
    when not given) says so, else 1 (metres, the project's unit). Heights in feet read as
    metres put 3.28 times the height into every difference (2616 m of 3762 ft)."""
    unit = (ds.units[band - 1] or "").strip().lower()
    if unit in _FEET_M:
        return _FEET_M[unit]
    if crs is None and ds.crs is not None:
        try:
            crs = CRS.from_wkt(ds.crs.to_wkt())
        except Exception:  # an unparsable CRS is refused where it is used
            return 1.0
    axes = [a for a in (crs.axis_info if crs is not None else ()) if a.direction == "up"]
    if axes and axes[0].unit_name.strip().lower() in _FEET_M:
        return float(axes[0].unit_conversion_factor)
    return 1.0


def height_scaling(ds, band: int = 1, crs: CRS | None = None) -> tuple[float, float]:
    """``(scale, offset)`` taking the stored values of band ``band`` of the open raster ``ds``
    to metres, ``metres = value * scale + offset``: GDAL's scale and offset (a DEM stored as
    decimetres) in the height unit (:func:`height_unit_m`); ``(1.0, 0.0)`` for metres."""
    unit = height_unit_m(ds, band, crs)
    return ds.scales[band - 1] * unit, ds.offsets[band - 1] * unit


def horizontal_crs(crs: CRS) -> CRS:
    """The horizontal part of ``crs`` (the first member of a compound CRS, a 3-D CRS
    demoted to 2-D); a 2-D CRS is returned as it is."""
    crs = CRS.from_user_input(crs)
    if crs.is_compound:
        return crs.sub_crs_list[0]
    if len(crs.axis_info) == 3:
        return crs.to_2d()
    return crs


def _grid_bounds_lonlat(transform, shape, crs):
    """(west, south, east, north) in degrees of the grid ``transform, shape`` in ``crs``
    (its border densified: 21 points a side)."""
    rows, cols = shape
    t = np.linspace(0, 1, 21)
    xs = np.concatenate([t * cols, np.full_like(t, cols), t[::-1] * cols, np.zeros_like(t)])
    ys = np.concatenate([np.zeros_like(t), t * rows, np.full_like(t, rows), t[::-1] * rows])
    x, y = transform @ (xs, ys)
    lon, lat = geodesy.crs_to_lonlat(x, y, crs)
    return float(np.min(lon)), float(np.min(lat)), float(np.max(lon)), float(np.max(lat))


def _no_crs_message(path, ds) -> str:
    """Why the DEM file ``path`` (open as ``ds``) has no CRS, and what to do: a DEM written by
    an older stereodem on a projected grid with ellipsoidal heights kept its CRS in its
    ``.aux.xml`` side-car only (:func:`stereodem.core.raster.geotiff_crs`)."""
    msg = f"{path}: the DEM has no CRS"
    if ds.tags().get(VERTICAL_TAG) and not Path(f"{path}.aux.xml").exists():
        msg += (
            f" (a DEM of an older stereodem kept it in the side-car {Path(path).name}.aux.xml "
            "only: copy that file beside it, or set the CRS with gdal_edit.py -a_srs EPSG:code)"
        )
    return msg


@dataclass
class Voided:
    """What the DEM reading rules (:func:`void_nodata`) made no-data in a file's heights:
    ``n_sentinel`` cells at :data:`UNDECLARED_NODATA` in a file without a nodata value,
    ``n_wild`` finite cells outside :data:`PLAUSIBLE_HEIGHTS_M`, ``wild`` some of their values
    (sorted, at most four). Counts of reads of one file add up (:meth:`add`: a mosaic's
    blocks), and :meth:`warn` says it once."""

    n_sentinel: int = 0
    n_wild: int = 0
    wild: tuple = ()

    def __bool__(self) -> bool:
        return bool(self.n_sentinel or self.n_wild)

    def add(self, other: Voided) -> Voided:
        """Both reads' counts (in place); returns self."""
        self.n_sentinel += other.n_sentinel
        self.n_wild += other.n_wild
        self.wild = tuple(sorted(set(self.wild) | set(other.wild)))[:4]
        return self

    def warn(self, path) -> None:
        """The warning naming the file ``path``, how many cells and some of their values
        (nothing when no cell was voided)."""
        if not self:
            return
        lo, hi = PLAUSIBLE_HEIGHTS_M
        what = [f"heights no place on Earth has (outside {lo:g}..{hi:g} m)"] if self.n_wild else []
        what += [f"{UNDECLARED_NODATA:g} without a nodata value"] if self.n_sentinel else []
        seen = [f"{UNDECLARED_NODATA:g}"] if self.n_sentinel else []
        seen += [f"{v:g}" for v in self.wild]
        log.warning(
            "%s: %d cell(s) hold %s (%s): read as no-data; declare the file's nodata value "
            "(gdal_edit.py -a_nodata) if that is what they are",
            path,
            self.n_wild + self.n_sentinel,
            " or ".join(what),
            ", ".join(seen[:3]) + (", ..." if len(seen) > 3 else ""),
        )


def void_nodata(
    heights, nodata, scale: float = 1.0, offset: float = 0.0, *, sentinel=None, count=None
) -> Voided:
    """The DEM reading rules, in place on ``heights`` (float32 values as stored in a file whose
    nodata value is ``nodata``, NaN where the file's nodata or mask says): with no nodata value
    declared, cells at :data:`UNDECLARED_NODATA` are no-data; the values are taken to metres
    (``metres = value * scale + offset``, :func:`height_scaling`); cells not finite or outside
    :data:`PLAUSIBLE_HEIGHTS_M` are no-data. Read as heights, -9999 put a mean of -1455 m into
    an assessment, 1e30 a mean of 1.6e28 m.

    ``sentinel``: the cells at :data:`UNDECLARED_NODATA` when the caller found them otherwise
    (a warped read, where GDAL took the value for no-data); ``count``: an index of the cells
    counted in the returned :class:`Voided` (a block without its halo), default all. The
    caller warns (:meth:`Voided.warn`): once per file."""
    if sentinel is None:
        sentinel = heights == np.float32(UNDECLARED_NODATA) if nodata is None else False
    sentinel = np.asarray(sentinel, bool)
    if sentinel.any():
        heights[np.broadcast_to(sentinel, heights.shape)] = np.nan
    if (scale, offset) != (1.0, 0.0):  # stored as e.g. decimetres or feet
        heights *= np.float32(scale)
        heights += np.float32(offset)
    lo, hi = PLAUSIBLE_HEIGHTS_M
    with np.errstate(invalid="ignore"):
        void = ~((heights >= lo) & (heights <= hi))  # NaN and +-inf compare False
    sentinel = np.broadcast_to(sentinel, heights.shape)
    if count is None:
        count = ...
    if not void.any():  # (the sentinel cells are NaN already: void)
        return Voided(int(np.count_nonzero(sentinel[count])))
    wild = void & np.isfinite(heights)
    values = heights[count][wild[count]]
    heights[void] = np.nan
    return Voided(
        int(np.count_nonzero(sentinel[count])),
        values.size,
        tuple(float(v) for v in np.unique(values)[:4]),
    )


def check_georeferenced(path, ds) -> None:
    """A DEM file ``path`` (open as ``ds``) has a CRS and a geotransform: without one rasterio
    gives the identity (cell corners at whole CRS units from 0, rows going north), which
    would put the heights at a wrong place without an error (ground control points alone are
    not used). Its first and last blocks are read first (:func:`probe_blocks`): a DEM cut
    short lost its georeferencing with its pixels (it said "the DEM has no CRS"), and a
    partial one fails here, before any work, not when it is read whole."""
    probe_blocks(ds)
    if ds.crs is None:
        raise CRSError(_no_crs_message(path, ds))
    if ds.transform.is_identity:
        raise DEMError(
            f"{path}: the DEM has no geotransform (its cells are not placed on the map; set "
            "one with gdal_edit.py -a_ullr or -a_gt)"
        )


#: colour interpretations of a band of a colour image: its values are no heights
_COLOUR_CHANNELS = frozenset(
    {"red", "green", "blue", "alpha", "hue", "saturation", "lightness"}
    | {"cyan", "magenta", "yellow", "black", "Y", "Cb", "Cr"}
)
#: band units that are no length (lower case): stereodem's score, count and edit layers ("1"),
#: slope and aspect maps, shares
_NOT_LENGTH_UNITS = frozenset(
    {"1", "unitless", "dimensionless", "degree", "degrees", "deg", "radian", "radians", "rad"}
    | {"%", "percent"}
)


#: band descriptions (lower case, prefixes) of stereodem's rasters that hold no heights: its
#: orthoimages (``orthoimage (... resampling)``, :meth:`stereodem.ortho.drm.Ortho.write`) and a
#: DEM's companion layers (:data:`LAYERS`)
_NOT_HEIGHTS_DESCRIPTIONS = (
    "orthoimage",
    *(x.description.lower() for x in LAYERS.values() if x.description),
)


def check_heights_band(path, ds, band: int = 1) -> None:
    """Band ``band`` of the open raster ``ds`` (file ``path``) may hold heights: not a channel
    of a colour image (an RGB photograph or quick look: band 1 its red), not one of
    stereodem's own rasters that hold none (an orthoimage, a score, count or edit layer:
    their band descriptions), not in a unit that is no length (``1``, degrees, %). Such a
    file given as a DEM was read as heights without a word (an orthoimage's radiances as
    metres; a 3-band photograph with a warning only); now a one-line :class:`DEMError`
    naming it. A band that says nothing (GDAL's gray or undefined, no description, no unit or
    a length) passes: most DEMs say nothing."""
    i = band - 1
    channel = ds.colorinterp[i].name
    if channel in _COLOUR_CHANNELS:
        raise DEMError(
            f"{path}: band {band} is the {channel} channel of a colour image ({ds.count} "
            f"band(s) of {ds.dtypes[i]}), not heights; give a DEM"
        )
    desc = " ".join((ds.descriptions[i] or "").split())
    if desc.lower().startswith(_NOT_HEIGHTS_DESCRIPTIONS):
        raise DEMError(
            f"{path}: band {band} is stereodem's {desc!r}, not heights; give the DEM itself"
        )
    unit = (ds.units[i] or "").strip()
    if unit.lower() in _NOT_LENGTH_UNITS:
        raise DEMError(
            f"{path}: band {band} is in unit {unit!r}, not a length: not heights; give a DEM"
        )


def _check_vertical(vertical: str | None) -> None:
    """A DEM's vertical reference is None (unknown) or one of :data:`VERTICALS`."""
    if vertical is not None and vertical not in VERTICALS:
        raise DEMError(f"vertical reference must be 'geoid' or 'ellipsoid', got {vertical!r}")


@dataclass
class DEM:
    """A DEM raster in memory.

    Attributes
    ----------
    heights : ndarray (rows, cols) float32
        Heights in metres, NaN on voids.
    transform : affine.Affine
        GDAL pixel-corner transform to ``crs``.
    crs : pyproj.CRS
        Horizontal CRS of the grid (the vertical part of a file's compound or 3-D CRS goes
        to ``vertical``).
    vertical : {"geoid", "ellipsoid"} or None
        Vertical reference of ``heights``; ``None`` means unknown, and any operation that
        needs ellipsoidal heights raises :class:`VerticalReferenceError`.
    path : str, optional
        Source file, used in error messages.
    count, score, ray_gap, sigma, edit_mask : ndarray (rows, cols), optional
        Companion layers on the same grid (:data:`LAYERS`): points per cell (int), mean
        correlation score, mean ray gap (m), vertical σ (m), edit code (uint8).
    geoid_crs : pyproj.CRS, optional
        With ``vertical == "geoid"``: the vertical CRS of the heights when its file names a
        geoid other than EGM96 (EGM2008 height, NAVD88 height, ...; :func:`other_geoid`);
        None for EGM96, the geoid of every conversion here. Written back with the heights,
        and :meth:`to_reference` warns that its conversion uses EGM96.

    A DEM read or built as an input must hold a valid height; a stereo product (one with a
    ``count`` layer) may be all void (nothing matched: reported, not refused).
    """

    heights: np.ndarray
    transform: Affine
    crs: CRS
    vertical: str | None = None
    path: str | None = None
    count: np.ndarray | None = None
    score: np.ndarray | None = None
    ray_gap: np.ndarray | None = None
    sigma: np.ndarray | None = None
    edit_mask: np.ndarray | None = None
    geoid_crs: CRS | None = None
    _lonlat_is_native: bool = field(init=False, repr=False, default=False)

    def __post_init__(self):
        what = self.path or "DEM"
        if self.crs is None:
            raise CRSError(f"{what}: the DEM has no CRS")
        self.crs = map_crs(self.crs, f"{what}: crs")
        if not isinstance(self.transform, Affine):  # a GDAL geotransform tuple is another order
            raise DEMError(
                f"{what}: transform must be an affine.Affine (a rasterio dataset's "
                f"transform), got {type(self.transform).__name__}"
            )
        try:
            h = np.asarray(self.heights, dtype=np.float32)
        except (TypeError, ValueError) as exc:
            raise DEMError(f"{what}: heights are not numbers ({exc})") from None
        if h.ndim != 2:
            raise DEMError(
                f"{self.path or 'DEM'}: expected a 2-D height array, got shape {h.shape}"
            )
        self.heights = h
        _check_vertical(self.vertical)
        for name in LAYERS:
            layer = getattr(self, name)
            if layer is not None and np.shape(layer) != h.shape:
                raise DEMError(
                    f"{self.path or 'DEM'}: layer {name} has shape {np.shape(layer)}, "
                    f"the heights {h.shape}"
                )
        if self.count is None and not np.isfinite(h).any():
            raise DEMError(f"{self.path or 'DEM'}: the DEM has no valid height (all nodata)")
        geo = self.crs.is_geographic
        self._lonlat_is_native = bool(
            geo
            and self.crs.ellipsoid is not None
            and abs(self.crs.ellipsoid.semi_major_metre - geodesy.A) < 1e-3
            and abs(self.crs.ellipsoid.inverse_flattening - 1 / geodesy.F) < 1e-6
        )

    # ---------------------------------------------------------------- construction
    @classmethod
    def from_file(cls, path, vertical: str | None = None, band: int = 1, *, layers=()) -> DEM:
        """Read a DEM with rasterio.

        ``layers``: companion layers to read from beside the file (names of :data:`LAYERS`,
        or ``True`` for all); absent files leave them ``None``, a layer on another grid is an
        :class:`InputError`. Float layers read as float32 with NaN at nodata, integer layers
        in their stored type.

        The vertical reference is the file's: its CRS (compound *horizontal + EGM96 height*, or
        3-D with ellipsoidal heights, as :meth:`write` stores it, the latter in the
        ``.aux.xml`` side-car for projected grids) or else stereodem's own
        ``STEREODEM_VERTICAL`` tag (older files, or a file copied without its side-car);
        ``vertical`` applies when neither says (``None``: unknown), and one that contradicts
        the file is not applied, with a warning naming the file (:func:`file_vertical`).
        ``crs`` is the horizontal part. Heights are metres: GDAL's scale and offset are
        applied, and heights in feet (the band's unit or the vertical CRS's,
        :func:`height_scaling`) converted.
        """
        path = str(path)
        try:
            with reading_env(), rasterio.open(path) as ds:
                check_georeferenced(path, ds)
                if not 1 <= band <= ds.count:
                    raise DEMError(f"{path}: no band {band} (the file has {ds.count})")
                check_heights_band(path, ds, band)
                if ds.count > 1:  # an image given as a DEM, or a DEM with other layers
                    # a band described as heights (stereodem's mosaic: height, sigma, count)
                    # is what was asked for; any other multi-band file may be an image
                    said = (ds.descriptions[band - 1] or "").lower().startswith("height")
                    log.log(
                        logging.INFO if said else logging.WARNING,
                        "%s: %d bands; the heights are read from band %d",
                        path,
                        ds.count,
                        band,
                    )
                flags = ds.mask_flag_enums[band - 1]
                if all(f in (MaskFlags.nodata, MaskFlags.all_valid) for f in flags):
                    # nodata value or none: read straight into float32 (no mask array, no copy)
                    heights = ds.read(band, out_dtype=np.float32)
                    if ds.nodata is not None and np.isfinite(ds.nodata):
                        heights[heights == np.float32(ds.nodata)] = np.nan
                else:  # a mask band or alpha: GDAL's mask
                    heights = ds.read(band, masked=True).astype(np.float32).filled(np.nan)
                transform, crs = ds.transform, CRS.from_user_input(ds.crs.to_wkt())
                # -9999 without a nodata value, implausible heights: no-data; stored as e.g.
                # centimetres (GDAL's scaling) or feet (the vertical CRS's unit): metres
                voided = void_nodata(heights, ds.nodata, *height_scaling(ds, band, crs))
                tag = ds.tags().get(VERTICAL_TAG)
        except rasterio.errors.RasterioIOError as exc:
            raise DEMError(unreadable(path, "DEM", exc)) from None
        voided.warn(path)
        vert = file_vertical(path, crs, tag, vertical)
        geoid = other_geoid(crs) if vert == GEOID else None
        found = {}
        for name in tuple(LAYERS) if layers is True else layers or ():
            lp = LAYERS[name].path(path)
            if lp.is_file():
                found[name] = _read_layer(lp, LAYERS[name])
                if found[name].shape != heights.shape:
                    raise InputError(
                        f"{lp}: {found[name].shape} cells, but the DEM has {heights.shape}"
                    )
        return cls(heights, transform, horizontal_crs(crs), vert, path, geoid_crs=geoid, **found)

    @staticmethod
    def check_file(path, vertical: str | None = None, band: int = 1) -> None:
        """The checks of :meth:`from_file` that need no full read: the file opens as a raster
        with the band, has a CRS, the band may hold heights (:func:`check_heights_band`), its
        first and last blocks decode, and ``vertical`` (if given) is a
        vertical reference; raises what :meth:`from_file` raises. For input checks before
        long work, without holding the heights meanwhile (a void-only DEM passes here and
        fails when it is read)."""
        path = str(path)
        _check_vertical(vertical)
        try:
            with reading_env(), rasterio.open(path) as ds:
                check_georeferenced(path, ds)
                if not 1 <= band <= ds.count:
                    raise DEMError(f"{path}: no band {band} (the file has {ds.count})")
                check_heights_band(path, ds, band)
                probe_blocks(ds, band)
        except rasterio.errors.RasterioIOError as exc:
            raise DEMError(unreadable(path, "DEM", exc)) from None

    @classmethod
    def bundled(cls) -> DEM:
        """The bundled real SRTM 3" DEM (eastern Turkey, EGM96 geoid heights)."""
        return cls.from_file(
            resources.files("stereodem.core") / "data" / "srtm_ref.tif", vertical=GEOID
        )

    # ---------------------------------------------------------------- geometry
    @property
    def grid(self) -> MapGrid:
        """The DEM's :class:`~stereodem.core.grid.MapGrid` (:class:`DEMError` naming the file
        when its grid is not one, e.g. not north-up)."""
        try:
            return MapGrid(self.transform, self.heights.shape[1], self.heights.shape[0], self.crs)
        except InputError as exc:
            raise DEMError(f"{self.path or 'DEM'}: {exc}") from None

    def __repr__(self) -> str:
        """One line, as xdem's and rasterio's objects print: ``DEM('dem.tif', 600 x 600
        cells of 30 m, EPSG:32637, vertical ellipsoid, heights 1104..3272 m, 97.2 % valid,
        layers count, score)`` (the dataclass's own repr printed the arrays and the CRS's
        whole description, about 30 lines)."""
        rows, cols = self.shape
        z = self.heights
        valid = np.isfinite(z)
        n = int(np.count_nonzero(valid))
        heights = f"heights {np.nanmin(z):.6g}..{np.nanmax(z):.6g} m" if n else "no height"
        epsg = self.crs.to_epsg()
        crs = f"EPSG:{epsg}" if epsg else repr(self.crs.name)
        vertical = self.vertical or "unknown"
        if self.vertical == GEOID and self.geoid_crs is not None:
            vertical = f"geoid ({self.geoid_crs.name})"
        layers = [name for name in LAYERS if getattr(self, name, None) is not None]
        return (
            f"DEM({self.path!r}, {rows} x {cols} cells of {self.grid.posting_text}, {crs}, "
            f"vertical {vertical}, {heights}, {100 * n / max(z.size, 1):.1f} % valid"
            + (f", layers {', '.join(layers)}" if layers else "")
            + ")"
        )

    @property
    def shape(self):
        return self.heights.shape

    @property
    def posting(self) -> float:
        """Cell size in CRS units."""
        return self.grid.posting

    def bounds_lonlat(self):
        """(west, south, east, north) in degrees of the DEM's valid extent (corners densified)."""
        return _grid_bounds_lonlat(self.transform, self.shape, self.crs)

    def reproject(
        self,
        ref=None,
        crs=None,
        res=None,
        bounds=None,
        resampling: str = "bilinear",
        *,
        threads: int | None = None,
    ) -> DEM:
        """A new DEM: these heights warped onto another grid (xdem's ``DEM.reproject``).

        The grid is ``ref``'s exactly (a :class:`DEM` or a :class:`~stereodem.core.grid.
        MapGrid`: its transform, size and CRS), or one laid from ``crs`` (default this DEM's;
        a horizontal map CRS, anything pyproj takes), ``res`` (posting in ``crs``'s units,
        one number or ``(x, y)``; default this DEM's posting when ``crs`` has the same unit,
        e.g. metres to metres, else GDAL's choice for ``crs``, about as many cells) and
        ``bounds`` (west, south, east, north in ``crs``'s units; default this DEM's extent in
        ``crs``): top-left corner at (west, north), as many cells as cover east and south.

        Heights are resampled by GDAL's warper (``resampling``: ``"nearest"``,
        ``"bilinear"``, ``"cubic"``, ``"cubic_spline"``; :func:`stereodem.core.warp.to_grid`,
        on ``threads`` threads, default the process's budget), voids (NaN) kept as voids and
        cells off this DEM NaN. They stay metres above the same vertical reference
        (``vertical``, ``geoid_crs``): a warp moves heights across the map, it does not
        convert them (:meth:`to_reference` does), so a ``crs`` whose vertical part says the
        other reference is refused. Companion layers are warped too: float ones (``score``,
        ``ray_gap``, ``sigma``) with ``resampling``, integer ones (``count``, ``edit_mask``)
        by nearest neighbour.

        Raises :class:`InputError` for ``ref`` given with ``crs``/``res``/``bounds``, an
        unknown ``resampling``, a posting or bounds that are no grid, or a grid beyond the
        memory; :class:`NoOverlapError` when the grid holds none of this DEM's heights."""
        grid = self._target_grid(ref, crs, res, bounds)
        what = self.path or "DEM"
        if resampling not in RESAMPLING_METHODS:
            raise InputError(
                f"{what}: resampling must be one of {', '.join(RESAMPLING_METHODS)}, "
                f"got {resampling!r}"
            )
        present = [name for name in LAYERS if getattr(self, name) is not None]
        check_allocation(
            4.0 * grid.width * grid.height * (1 + len(present)),
            f"{what}: reprojecting onto {grid.width} x {grid.height} cells",
        )
        check_overlap(
            self.bounds_lonlat(),
            _grid_bounds_lonlat(grid.transform, grid.shape, grid.crs),
            what,
            "the target grid",
        )
        if threads is None:  # a conditional default: core.blocks loads OpenCV, which
            from stereodem.core.blocks import default_threads  # a DEM's import must not

            threads = default_threads()

        def warped(data, method, **kw):
            return to_grid(
                data,
                self.transform,
                self.crs,
                grid.transform,
                grid.crs,
                grid.shape,
                resampling=method,
                threads=threads,
                **kw,
            )

        heights = warped(self.heights, resampling)
        if np.isfinite(self.heights).any() and not np.isfinite(heights).any():
            raise NoOverlapError(f"{what}: none of its heights falls on the target grid")
        layers = {}
        for name in present:
            spec = LAYERS[name]
            if np.issubdtype(np.dtype(spec.dtype), np.floating):
                layers[name] = warped(getattr(self, name), resampling)
            else:
                layers[name] = warped(
                    getattr(self, name), "nearest", src_nodata=spec.nodata, dst_dtype=spec.dtype
                )
        return DEM(
            heights,
            grid.transform,
            grid.crs,
            self.vertical,
            self.path,
            geoid_crs=self.geoid_crs,
            **layers,
        )

    def _target_grid(self, ref, crs, res, bounds) -> MapGrid:
        """The grid :meth:`reproject` warps onto (see there)."""
        what = self.path or "DEM"
        if ref is not None:
            if crs is not None or res is not None or bounds is not None:
                raise InputError(
                    f"{what}: reproject onto ref's grid or onto crs/res/bounds, not both"
                )
            if isinstance(ref, DEM):
                return ref.grid
            if isinstance(ref, MapGrid):
                return ref
            raise InputError(f"{what}: ref must be a DEM or a MapGrid, got {type(ref).__name__}")
        dst = self.crs if crs is None else map_crs(crs, f"{what}: reproject crs")
        said = _vertical_from_crs(dst)
        if said is not None and self.vertical is not None and said != self.vertical:
            raise InputError(
                f"{what}: reproject crs {dst.name!r} says {said} heights, the DEM's are "
                f"{self.vertical}; a warp does not convert heights (DEM.to_reference does)"
            )
        dst = horizontal_crs(dst)
        same = dst == horizontal_crs(self.crs)
        rows, cols = self.shape
        own = rasterio.transform.array_bounds(rows, cols, self.transform)  # (w, s, e, n)
        if bounds is None:
            if same:
                bounds = own
            else:
                try:
                    bounds = transform_bounds(rio_crs(self.crs), rio_crs(dst), *own, densify_pts=21)
                except Exception as exc:  # noqa: BLE001 - PROJ's refusal: one line
                    raise InputError(
                        f"{what}: its extent cannot be expressed in {dst.name!r} ({exc})"
                    ) from None
        try:
            w, s, e, n = (float(v) for v in bounds)
        except (TypeError, ValueError):
            raise InputError(
                f"{what}: bounds must be (west, south, east, north), got {bounds!r}"
            ) from None
        if not all(np.isfinite([w, s, e, n])) or e <= w or n <= s:
            raise InputError(f"{what}: empty or invalid bounds {(w, s, e, n)} in {dst.name!r}")
        if res is None:
            if same or crs_unit(dst) == crs_unit(self.crs):
                res = (abs(self.transform.a), abs(self.transform.e))
            else:
                t, _, _ = calculate_default_transform(
                    rio_crs(self.crs), rio_crs(dst), cols, rows, *own
                )
                res = (abs(t.a), abs(t.e))
        xres, yres = (res, res) if np.ndim(res) == 0 else res
        try:
            xres, yres = float(xres), float(yres)
        except (TypeError, ValueError):
            raise InputError(f"{what}: res must be a posting or (x, y), got {res!r}") from None
        if not (np.isfinite(xres) and np.isfinite(yres) and xres > 0 and yres > 0):
            raise InputError(f"{what}: res must be positive, got {res!r}")
        width = max(1, int(np.ceil((e - w) / xres - 1e-6)))
        height = max(1, int(np.ceil((n - s) / yres - 1e-6)))
        return MapGrid(Affine(xres, 0.0, w, 0.0, -yres, n), width, height, dst)

    def _lonlat_to_pixel(self, lon, lat):
        lon = np.asarray(lon, dtype=np.float64)
        lat = np.asarray(lat, dtype=np.float64)
        if self._lonlat_is_native:
            x, y = lon, lat
        else:
            x, y = geodesy.lonlat_to_crs(lon, lat, self.crs)
        if self.crs.is_geographic:  # longitudes beside the grid's: -179.99 E is 180.01 E
            centre = self.transform.c + self.transform.a * self.shape[1] / 2.0
            x = geodesy.lon_beside(x, centre)
        col, row = ~self.transform @ (x, y)
        return np.asarray(col) - 0.5, np.asarray(row) - 0.5  # pixel-centre convention

    # ---------------------------------------------------------------- sampling
    def sample(
        self, lon, lat, *, reference: str | None = ELLIPSOID, return_status=False, strict=False
    ):
        """Bilinear heights at ``lon, lat`` (degrees).

        Parameters
        ----------
        reference : {"ellipsoid", "geoid", None}
            Vertical reference of the returned heights; ``None`` returns the raster's own values.
        return_status : bool
            Also return an int8 array: 0 ok, 1 outside the DEM, 2 on or next to a void.
        strict : bool
            Raise :class:`DEMCoverageError` if any point is outside or on a void.

        Returns
        -------
        heights : ndarray float64, metres, NaN where unavailable.
        """
        if lon is None or lat is None:  # asarray(None, float) is a NaN: "outside", not an error
            raise InputError("DEM.sample: lon and lat are required (degrees), got None")
        try:
            lon, lat = np.broadcast_arrays(
                np.asarray(lon, dtype=np.float64), np.asarray(lat, dtype=np.float64)
            )
        except (TypeError, ValueError) as exc:
            raise InputError(
                f"DEM.sample: lon {np.shape(lon)} and lat {np.shape(lat)} must be numbers of "
                f"one shape ({' '.join(str(exc).split())})"
            ) from None
        out_shape = lon.shape
        lon, lat = lon.ravel(), lat.ravel()
        c, r = self._lonlat_to_pixel(lon, lat)
        rows, cols = self.shape
        finite = np.isfinite(c) & np.isfinite(r)
        inside = (
            finite & (c >= -1e-9) & (r >= -1e-9) & (c <= cols - 1 + 1e-9) & (r <= rows - 1 + 1e-9)
        )
        c0 = np.clip(np.floor(np.where(inside, c, 0)), 0, max(cols - 2, 0)).astype(np.intp)
        r0 = np.clip(np.floor(np.where(inside, r, 0)), 0, max(rows - 2, 0)).astype(np.intp)
        fc = np.where(inside, c, 0) - c0
        fr = np.where(inside, r, 0) - r0
        c1 = np.minimum(c0 + 1, cols - 1)
        r1 = np.minimum(r0 + 1, rows - 1)
        H = self.heights
        z = (
            (1 - fr) * ((1 - fc) * H[r0, c0] + fc * H[r0, c1])
            + fr * ((1 - fc) * H[r1, c0] + fc * H[r1, c1])
        ).astype(np.float64)
        z[~inside] = np.nan
        status = np.zeros(lon.shape, dtype=np.int8)
        status[~inside] = OUTSIDE
        status[inside & ~np.isfinite(z)] = VOID
        if strict and status.any():
            n_out, n_void = int((status == OUTSIDE).sum()), int((status == VOID).sum())
            raise DEMCoverageError(
                f"{self.path or 'DEM'}: {n_out} point(s) outside the DEM and {n_void} on voids "
                f"(of {status.size}); DEM extent lon/lat {self.bounds_lonlat()}"
            )
        if reference is not None:
            z = self.convert_heights(lon, lat, z, to=reference)
        z, status = z.reshape(out_shape), status.reshape(out_shape)
        return (z, status) if return_status else z

    def convert_heights(self, lon, lat, z, to: str):
        """Convert heights ``z`` of this DEM's vertical reference to ``to``."""
        if to not in (GEOID, ELLIPSOID):
            raise DEMError(f"unknown vertical reference {to!r}")
        if self.vertical == to:
            return z
        if self.vertical is None:
            raise VerticalReferenceError(
                f"{self.path or 'DEM'}: vertical reference unknown (geoid or ellipsoid?); "
                "say which (vertical='geoid' / --dem-vertical geoid)"
            )
        if to == ELLIPSOID:
            return geodesy.geoid_to_ellipsoid(lon, lat, z)
        return geodesy.ellipsoid_to_geoid(lon, lat, z)

    def to_reference(self, to: str) -> DEM:
        """A copy of this DEM with heights converted to ``to`` (``geoid`` or ``ellipsoid``)."""
        if self.vertical == to:
            return self
        if self.geoid_crs is not None:
            log.warning(
                "%s: heights above %s converted to the %s with EGM96, stereodem's geoid: off "
                "by the separation of the two (EGM2008 - EGM96: within about 1 m over most "
                "land, a few metres in high mountains)",
                self.path or "DEM",
                self.geoid_crs.name,
                to,
            )
        rows, cols = self.shape
        cc, rr = np.meshgrid(np.arange(cols) + 0.5, np.arange(rows) + 0.5)
        x, y = self.transform @ (cc, rr)
        lon, lat = geodesy.crs_to_lonlat(x, y, self.crs)
        z = self.convert_heights(lon, lat, self.heights.astype(np.float64), to)
        return dataclasses.replace(self, heights=z.astype(np.float32), vertical=to, geoid_crs=None)

    def window_around(self, lon, lat, *, margin: int = 2) -> DEM | None:
        """The part of the DEM (heights only) that covers the points ``lon, lat`` (degrees):
        their bounding window of cells widened by ``margin`` cells; None when it holds no
        valid height (the points lie off the DEM or on its voids)."""
        c, r = self._lonlat_to_pixel(np.ravel(lon), np.ravel(lat))
        ok = np.isfinite(c) & np.isfinite(r)
        if not ok.any():
            return None
        rows, cols = self.shape
        c0 = max(int(np.floor(c[ok].min())) - margin, 0)
        r0 = max(int(np.floor(r[ok].min())) - margin, 0)
        c1 = min(int(np.ceil(c[ok].max())) + margin + 1, cols)
        r1 = min(int(np.ceil(r[ok].max())) + margin + 1, rows)
        if c1 <= c0 or r1 <= r0:
            return None
        h = self.heights[r0:r1, c0:c1]
        if not np.isfinite(h).any():
            return None
        return dataclasses.replace(
            self,
            heights=h,
            transform=self.transform @ Affine.translation(c0, r0),
            **{name: None for name in LAYERS},
        )

    def height_range(self, reference: str | None = ELLIPSOID, *, around=None):
        """(min, max) of the valid heights, in the requested reference (metres).

        ``around=(lon, lat)``: only the heights of the window covering those points
        (:meth:`window_around`; a scene's footprint in a DEM much larger than the scene);
        :class:`DEMCoverageError` when that window holds no valid height."""
        d = self
        if around is not None:
            d = self.window_around(*around)
            if d is None:
                west, south, east, north = self.bounds_lonlat()
                lon, lat = (np.asarray(a, float) for a in around)
                raise DEMCoverageError(
                    f"{self.path or 'DEM'}: does not cover the scene (no valid height under "
                    f"it; scene lon {np.nanmin(lon):.4f}..{np.nanmax(lon):.4f}, lat "
                    f"{np.nanmin(lat):.4f}.."
                    f"{np.nanmax(lat):.4f} deg; DEM lon {west:.4f}..{east:.4f}, lat "
                    f"{south:.4f}..{north:.4f} deg)"
                )
        d = d if reference is None else d.to_reference(reference)
        return float(np.nanmin(d.heights)), float(np.nanmax(d.heights))

    def write(
        self, path, *, overwrite=False, creation_options=None, layers=True, tags=None, threads=1
    ) -> Path:
        """Write the heights as a float32 Cloud-Optimised GeoTIFF with NaN nodata, the vertical
        reference in the CRS (and the ``STEREODEM_VERTICAL`` tag), band description and unit
        (metre), and every companion layer present beside it (:data:`LAYERS`; none with
        ``layers=False``); returns the heights file's path.

        ``creation_options``: GDAL COG creation options (see
        :func:`stereodem.core.raster.write_geotiff`); ``tags``: dataset tags of the heights file
        (e.g. the ground-track heading ``STEREODEM_TRACK_HEADING`` that ``coregister`` reads);
        ``threads``: see :meth:`prepare_write`.
        """
        return self.prepare_write(
            path,
            overwrite=overwrite,
            creation_options=creation_options,
            layers=layers,
            tags=tags,
            threads=threads,
        )()["dem"]

    def prepare_write(
        self,
        path,
        *,
        overwrite=False,
        creation_options=None,
        layers=True,
        tags=None,
        layer_descriptions=None,
        threads=1,
        more=None,
    ):
        """:meth:`write` in two steps: the heights and layers are copied to their stored types
        now, and the returned callable writes them (returning ``{"dem": path, layer: path}``);
        it can run in another thread while this DEM changes or goes away.
        ``layer_descriptions``: band descriptions replacing those of :data:`LAYERS`, by layer.
        ``more``: other files written with these, ``{name: write}``: each ``write`` takes the
        keyword ``creation_options`` (these files' own), writes its file and returns its path,
        e.g. a fused DEM's spread.

        ``threads`` > 1 writes the files that many at a time, each compressed on one GDAL
        thread (``NUM_THREADS=1`` unless ``creation_options`` sets it): the overviews and the
        COG's assembly are serial within a file, so files side by side use the cores better
        than one file's compression threads (``stereodem dem``'s four rasters of the full
        ASTER granule at 2 threads: 0.92-1.10 -> 0.71-0.83 s, 1.6-1.9 -> 1.3-1.5 CPU s). The
        files have the same bytes either way."""
        layer_descriptions = dict(layer_descriptions or {})
        threads = max(1, int(threads))
        if threads > 1:
            creation_options = parse_creation_options(creation_options)
            creation_options.setdefault("NUM_THREADS", "1")
        heights = self.heights.astype(np.float32)
        layers = {
            name: np.asarray(getattr(self, name)).astype(spec.dtype)
            for name, spec in LAYERS.items()
            if layers and getattr(self, name) is not None
        }
        transform, crs, vertical = self.transform, self.crs, self.vertical
        if vertical == GEOID and self.geoid_crs is not None:  # its own geoid, not EGM96's
            crs = crs_with_vertical(crs, vertical, self.geoid_crs)
        kw = dict(overwrite=overwrite, creation_options=creation_options)

        writes = {
            "dem": functools.partial(
                write_geotiff,
                path,
                heights,
                transform,
                crs,
                np.nan,
                vertical=vertical,
                descriptions=_HEIGHT_DESCRIPTION.get(vertical, "height"),
                units="metre",
                tags=tags,
                **kw,
            )
        }
        for name, data in layers.items():
            writes[name] = functools.partial(
                write_layer,
                path,
                name,
                data,
                transform,
                crs,
                description=layer_descriptions.get(name),
                **kw,
            )
        for name, write in (more or {}).items():
            writes[name] = functools.partial(write, creation_options=creation_options)

        def write_files():
            if threads == 1 or len(writes) == 1:
                return {name: write() for name, write in writes.items()}
            with ThreadPoolExecutor(min(threads, len(writes)), "stereodem-dem-write") as ex:
                futures = {name: ex.submit(write) for name, write in writes.items()}
                return {name: f.result() for name, f in futures.items()}

        return write_files


def _read_layer(path: Path, spec: Layer) -> np.ndarray:
    if np.issubdtype(spec.dtype, np.floating):
        return read_image(path)
    with reading_env(), rasterio.open(path) as ds:
        return ds.read(1, out_dtype=spec.dtype)


def as_dem(dem, vertical: str | None = None) -> DEM:
    """Accept a :class:`DEM` or a path and return a :class:`DEM`."""
    if isinstance(dem, DEM):
        return dem
    if isinstance(dem, (str, Path)):
        return DEM.from_file(dem, vertical=vertical)
    raise DEMError(f"expected a DEM or a path, got {type(dem).__name__}")
