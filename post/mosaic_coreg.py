"""Co-registration of every DEM of a mosaic to one reference, before mosaicking (the hook).

A *chain* string names how a DEM is fitted to the reference; it resolves, through
:data:`CHAINS`, to a function ``fit(reference: DEM, dem: DEM) -> DEMCorrection``. The mosaic
applies a :class:`DEMCorrection` block by block: the DEM's grid moved by ``dx, dy`` metres and
``dz`` metres subtracted from its heights. The chains are those of :func:`stereodem.post.coreg.
parse_chain` (registered with :func:`register_chain` by :func:`chain_fitter`) made of the steps
the mosaic can apply as a shift and an offset: ``nuth_kaab`` and ``vshift`` (e.g.
``nuth_kaab,vshift``); a chain with a surface step (``deramp``, ``along_track``, ...) is refused
with a one-line error (correct such DEMs with ``stereodem coregister`` first).

Memory: a fit holds one DEM and the reference cropped to that DEM's footprint (plus a
margin), never the mosaic.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import rasterio
from affine import Affine
from pyproj import CRS
from rasterio.warp import transform_bounds
from rasterio.windows import from_bounds

from stereodem.core.dem import (
    DEM,
    Voided,
    check_heights_band,
    file_vertical,
    height_scaling,
    horizontal_crs,
    void_nodata,
)
from stereodem.core.errors import ConvergenceError, DEMError, InputError, NoOverlapError
from stereodem.core.raster import VERTICAL_TAG, reading_env, unreadable

from . import warp
from .assess import coregistration_summary
from .coreg import parse_chain

log = logging.getLogger(__name__)

__all__ = ["CHAINS", "DEMCorrection", "chain_fitter", "crop_reference", "fitter", "register_chain"]


@dataclass(frozen=True)
class DEMCorrection:
    """What co-registration found for one DEM: ``dx, dy`` (m along x/y, grid east/north, the DEM's
    displacement relative to the reference, removed by moving its grid by −dx, −dy; the DEM
    grid's metres, the CRS's units on a projected grid: :func:`~stereodem.post.warp.translated`)
    and ``dz`` (m, subtracted from its heights); ``report`` is the fit's own record
    (JSON-able; with the projection's ``scale_factor`` and, where it matters, ``dx_ground``)."""

    dx: float
    dy: float
    dz: float
    report: dict = field(default_factory=dict)


#: the steps whose correction is a shift of the grid plus a height offset
SHIFT_STEPS = ("nuth_kaab", "vshift")


def chain_fitter(text: str) -> Callable | None:
    """The fit function of a :func:`~stereodem.post.coreg.parse_chain` string made of
    :data:`SHIFT_STEPS`: the chain fitted on the DEM's grid, its ``nuth_kaab`` shifts and
    ``nuth_kaab``/``vshift`` offsets summed into one :class:`DEMCorrection`. None for a
    string that is not a chain; :class:`InputError` for a chain with another step."""
    try:
        chain = parse_chain(text)
    except InputError:
        return None
    other = [s.name for s in chain.steps if s.name not in SHIFT_STEPS]
    if other:
        raise InputError(
            f"--coreg-chain {text!r}: the mosaic applies shifts and offsets only "
            f"({', '.join(SHIFT_STEPS)}); {', '.join(other)} changes the surface: "
            "correct such DEMs with 'stereodem coregister' first"
        )

    def fit(reference: DEM, dem: DEM) -> DEMCorrection:
        try:
            ch = parse_chain(text).fit(reference, dem)
        except (InputError, ConvergenceError) as exc:  # too little stable terrain: skipped
            raise DEMError(f"{dem.path or 'DEM'}: {exc}") from None
        rep = coregistration_summary(ch, reference)
        return DEMCorrection(rep["dx"], rep["dy"], rep["dz"], rep)

    return fit


def register_chain(parser: Callable[[str], Callable | None]):
    """Register a parser of chain strings: ``parser(text)`` returns a fit function
    ``fit(reference, dem) -> DEMCorrection`` for a string it understands, None otherwise
    (the issue-25 correction chain connects here)."""
    _PARSERS.append(parser)
    return parser


#: chain name -> fit function (checked before the parsers); resolved by :func:`fitter`
CHAINS: dict[str, Callable] = {}
_PARSERS: list[Callable] = []
register_chain(chain_fitter)


def fitter(chain: str = "nuth_kaab") -> Callable:
    """The fit function of a chain string; :class:`InputError` naming the known ones."""
    text = (chain or "nuth_kaab").strip()
    if text.lower() in CHAINS:
        return CHAINS[text.lower()]
    for parse in _PARSERS:
        fit = parse(text)
        if fit is not None:
            return fit
    raise InputError(
        f"--coreg-chain {chain!r}: unknown chain (steps, comma separated: {', '.join(SHIFT_STEPS)})"
    )


def check_reference(path) -> None:
    """:class:`DEMError` (one line naming ``path``) when the reference cannot be read as a
    raster, has no CRS or holds no heights (:func:`~stereodem.core.dem.check_heights_band`):
    a fault of the reference, not of each DEM, so refused at once."""
    path = str(path)
    try:
        with reading_env(), rasterio.open(path) as ds:
            if ds.crs is None:
                raise DEMError(f"{path}: the reference DEM has no CRS")
            check_heights_band(path, ds)
    except rasterio.errors.RasterioIOError as exc:
        raise DEMError(unreadable(path, "reference DEM", exc)) from None


def _read_columns(ds, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
    """Band 1 of ``ds`` over rows ``r0:r1``, columns ``c0:c1`` as float32 (NaN where masked);
    columns outside ``0..ds.width`` are those of a global grid's other edge (modulo its
    width)."""
    parts, c = [], c0
    while c < c1:
        k = c % ds.width
        n = min(c1 - c, ds.width - k)
        win = rasterio.windows.Window(k, r0, n, r1 - r0)
        parts.append(ds.read(1, window=win, masked=True).astype(np.float32).filled(np.nan))
        c += n
    return np.concatenate(parts, axis=1)


def crop_reference(
    path, bounds, crs, *, vertical=None, margin_cells: int = 8, voided: dict | None = None
) -> DEM:
    """The reference DEM over ``bounds`` (west, south, east, north in ``crs``) plus a margin,
    read through a window (the whole reference is never read); :class:`NoOverlapError` when it
    misses them. The heights follow :meth:`DEM.from_file`'s reading rules
    (:func:`~stereodem.core.dem.void_nodata`): what they voided is added to ``voided[path]``
    (for one warning per file over several crops), or warned at once without ``voided``."""
    path = str(path)
    try:
        with reading_env(), rasterio.open(path) as ds:
            if ds.crs is None:
                raise DEMError(f"{path}: the reference DEM has no CRS")
            w, s, e, n = transform_bounds(
                horizontal_crs(crs).to_wkt(), ds.crs, *bounds, densify_pts=21
            )
            if ds.crs.is_geographic:  # across the antimeridian: west > east, as GDAL gives it
                e += 360.0 if w > e else 0.0
                turn = warp._turn(ds.bounds.left, ds.bounds.right, w, e)
                w, e = w + turn, e + turn
            win = from_bounds(w, s, e, n, transform=ds.transform)
            # a global lon/lat reference goes on across 180: columns beyond its edge are
            # read from its other edge (the part of a DEM at 179.9..180.1 E beyond 180)
            wrap = warp.is_global(ds.transform, ds.crs, (ds.height, ds.width))
            c0 = int(np.floor(win.col_off)) - margin_cells
            c1 = int(np.ceil(win.col_off + win.width)) + margin_cells
            if wrap:
                c1 = min(c1, c0 + ds.width)
            else:
                c0, c1 = max(c0, 0), min(c1, ds.width)
            r0 = max(int(np.floor(win.row_off)) - margin_cells, 0)
            r1 = min(int(np.ceil(win.row_off + win.height)) + margin_cells, ds.height)
            if c1 <= c0 or r1 <= r0:
                raise NoOverlapError(f"{path}: the reference DEM does not overlap {bounds}")
            z = _read_columns(ds, r0, r1, c0, c1)
            t = ds.transform @ Affine.translation(c0, r0)
            pcrs = CRS.from_wkt(ds.crs.to_wkt())
            # -9999 without a nodata value, implausible heights: no-data; decimetres, feet:
            # metres
            found = void_nodata(z, ds.nodata, *height_scaling(ds, 1, pcrs))
            tag = ds.tags().get(VERTICAL_TAG)
            vert = file_vertical(path, pcrs, tag, vertical)
    except rasterio.errors.RasterioIOError as exc:
        raise DEMError(unreadable(path, "reference DEM", exc)) from None
    except rasterio.errors.WindowError:  # bounds beyond its grid's reach
        raise NoOverlapError(f"{path}: the reference DEM does not overlap {bounds}") from None
    if voided is None:
        found.warn(path)
    elif found:
        voided.setdefault(path, Voided()).add(found)
    if not np.isfinite(z).any():
        raise NoOverlapError(f"{path}: the reference DEM has no valid height over {bounds}")
    return DEM(z, t, horizontal_crs(pcrs), vert, path)
