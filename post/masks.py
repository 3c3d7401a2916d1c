"""Stable-terrain masks on a DEM grid: vector outlines (any CRS), a raster mask, slope and
outlier limits.

Vectors (GeoJSON, GeoPackage, Shapefile, ...) are read with pyogrio, reprojected to the DEM's
CRS with pyproj through shapely, and burnt with ``rasterio.features.rasterize`` (a cell is in a
polygon when its centre is). ``exclude`` outlines (glaciers, water, changed areas) are removed
from the stable terrain; ``include`` outlines, when given, are the only stable terrain.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np
import rasterio
import shapely
from pyproj import CRS, Transformer
from rasterio.features import rasterize as rio_rasterize

from stereodem.core.dem import DEM
from stereodem.core.errors import CRSError, InputError, NoOverlapError, not_found
from stereodem.core.raster import check_map_raster, reading_env, unreadable
from stereodem.core.stats import nmad

from . import warp

#: attributes that name a polygon, in order of preference (case-insensitive)
LABEL_FIELDS = ("id", "name")


@dataclass(frozen=True)
class Outline:
    """One polygon of a vector file: ``label`` is what reports and logs call it (see
    :func:`read_outlines`), ``geom`` the shapely geometry in the CRS asked for."""

    label: int | str
    geom: object


def read_polygons(path, crs):
    """Polygons of a vector file reprojected to ``crs``; a list of shapely geometries.

    Raises :class:`InputError` (one line naming the file) when it cannot be read, has no CRS,
    or holds no polygon."""
    return [o.geom for o in read_outlines(path, crs)]


def read_outlines(path, crs) -> list[Outline]:
    """The polygons of a vector file reprojected to ``crs``, each with its label: the one
    numbering of polygons in every report and log (``assess --outlines``, ``stack
    --outlines``). The label is the polygon's own ``id`` attribute, else its ``name``
    (:data:`LABEL_FIELDS`; as geopandas/xdem users name their features) when every polygon has
    one and no two share it; otherwise the feature's 1-based number in the file (features that
    are not polygons keep their numbers).

    Raises :class:`InputError` (one line naming the file) when it cannot be read, has no CRS,
    or holds no polygon."""
    import pyogrio  # here: importing it imports pandas (0.2 s), which a run does not need

    path = str(path)
    if not os.path.lexists(path) and "://" not in path and not path.startswith("/vsi"):
        raise InputError(not_found(path, "vector file"))
    try:
        meta, _, geom_wkb, fields = pyogrio.raw.read(path)
        geoms = shapely.from_wkb(geom_wkb)
    except Exception as exc:  # noqa: BLE001 - pyogrio/GDAL errors of many types: one line
        raise InputError(
            f"{path}: cannot read the vector file ({str(exc).splitlines()[0][:120]})"
        ) from None
    src = meta.get("crs")
    if src is None:
        raise CRSError(f"{path}: the vector file has no CRS")
    keep = [
        k
        for k, g in enumerate(geoms)
        if g is not None and not g.is_empty and g.geom_type in ("Polygon", "MultiPolygon")
    ]
    if not keep:
        raise InputError(f"{path}: no polygon in the vector file")
    labels = _labels(list(meta.get("fields", [])), fields, keep)
    geoms = [geoms[k] for k in keep]
    src, dst = CRS.from_user_input(src), CRS.from_user_input(crs)
    if src != dst:
        tr = Transformer.from_crs(src, dst, always_xy=True)
        geoms = [
            shapely.transform(g, lambda xy: np.column_stack(tr.transform(xy[:, 0], xy[:, 1])))
            for g in geoms
        ]
    return [Outline(lab, g) for lab, g in zip(labels, geoms)]


def _labels(names, columns, keep) -> list:
    """The labels of the kept features ``keep`` (indices in the file): see
    :func:`read_outlines`."""
    lower = [str(n).lower() for n in names]
    for want in LABEL_FIELDS:
        if want not in lower:
            continue
        labels = []
        for v in (columns[lower.index(want)][k] for k in keep):
            if isinstance(v, bytes):
                v = v.decode("utf-8", "replace")
            if isinstance(v, (np.integer, int)) or (
                isinstance(v, (np.floating, float)) and np.isfinite(v) and float(v).is_integer()
            ):
                v = int(v)
            elif isinstance(v, str) and v.strip():
                v = v.strip()
            else:  # missing (None, NaN, blank) or a type that makes no name: not this field
                break
            labels.append(v)
        else:
            if len(set(map(str, labels))) == len(labels):
                return labels
    return [k + 1 for k in keep]


def rasterize(geoms, dem: DEM, *, path: str = "outlines") -> np.ndarray:
    """Bool array on ``dem``'s grid, True in the polygons; :class:`NoOverlapError` when no
    polygon touches the DEM."""
    rows, cols = dem.shape
    t = dem.transform
    xs, ys = sorted([t.c, t.c + t.a * cols]), sorted([t.f, t.f + t.e * rows])
    box = shapely.box(xs[0], ys[0], xs[1], ys[1])
    if not any(g.intersects(box) for g in geoms):
        x0, y0, x1, y1 = shapely.total_bounds(np.asarray(geoms, dtype=object))
        raise NoOverlapError(
            f"{path}: no outline overlaps the DEM {dem.path or ''} "
            f"(outlines {x0:.4f},{y0:.4f},{x1:.4f},{y1:.4f}; DEM "
            f"{box.bounds[0]:.4f},{box.bounds[1]:.4f},{box.bounds[2]:.4f},"
            f"{box.bounds[3]:.4f} in its CRS)"
        )
    burnt = rio_rasterize(
        [(g, 1) for g in geoms], out_shape=dem.shape, transform=t, fill=0, dtype="uint8"
    )
    return burnt.astype(bool)


@dataclass
class StableMask:
    """What counts as stable terrain on a DEM grid.

    ``exclude``/``include``: vector files (any CRS); ``raster``: a mask raster (non-zero =
    stable) warped to the DEM grid with nearest neighbour; ``min_slope``/``max_slope``
    degrees on the reference (or DEM) slope; ``outlier_nmad``: cells with
    |dh − median| > this many NMADs are left out (needs ``dh``).
    """

    exclude: list = field(default_factory=list)
    include: list = field(default_factory=list)
    raster: str | None = None
    min_slope: float | None = None
    max_slope: float | None = None
    outlier_nmad: float | None = None

    def array(self, dem: DEM, *, slope=None, dh=None) -> np.ndarray:
        """The bool mask on ``dem``'s grid (True = stable)."""
        m = np.ones(dem.shape, bool)
        if self.include:
            m = np.zeros(dem.shape, bool)
            for path in self.include:
                m |= rasterize(read_polygons(path, dem.crs), dem, path=str(path))
        for path in self.exclude or []:
            m &= ~rasterize(read_polygons(path, dem.crs), dem, path=str(path))
        if self.raster:
            try:
                with reading_env(), rasterio.open(self.raster) as ds:
                    a = ds.read(1, masked=True).filled(0).astype(np.uint8)
                    check_map_raster(self.raster, ds, "the stable-mask raster")
                    z = warp.to_grid(
                        a,
                        ds.transform,
                        ds.crs.to_wkt(),
                        dem.transform,
                        dem.crs,
                        dem.shape,
                        resampling="nearest",
                        src_nodata=None,
                        dst_dtype=np.uint8,
                    )
            except rasterio.errors.RasterioIOError as exc:
                raise InputError(unreadable(self.raster, "mask", exc)) from None
            if not z.any():
                raise NoOverlapError(
                    f"{self.raster}: the stable mask has no stable cell on the DEM"
                )
            m &= z > 0
        if slope is not None and (self.min_slope is not None or self.max_slope is not None):
            s = np.asarray(slope, float)
            with np.errstate(invalid="ignore"):
                if self.min_slope is not None:
                    m &= s >= self.min_slope
                if self.max_slope is not None:
                    m &= s <= self.max_slope
        if dh is not None and self.outlier_nmad and np.isfinite(np.where(m, dh, np.nan)).any():
            d = np.where(m, dh, np.nan)
            med, s = np.nanmedian(d), nmad(d)
            with np.errstate(invalid="ignore"):
                m &= np.abs(dh - med) <= self.outlier_nmad * s
        return m


def stable_fraction(mask, valid) -> float:
    """Share of the ``valid`` cells that the mask keeps."""
    v = int(np.count_nonzero(valid))
    return float(np.count_nonzero(mask & valid) / v) if v else 0.0


def check_stable(mask, valid, *, min_fraction: float = 0.05, what: str = "stable mask"):
    """:class:`InputError` when under ``min_fraction`` of the valid cells are stable."""
    f = stable_fraction(mask, valid)
    if f < min_fraction:
        raise InputError(
            f"{what}: only {100 * f:.1f} % of the DEM's valid cells "
            f"({int(np.count_nonzero(mask & valid))} of {int(np.count_nonzero(valid))}) are "
            f"left as stable terrain (need at least {100 * min_fraction:.0f} %)"
        )
    return f
