"""Optional orthoimage layers: local incidence angle and terrain occlusion.

Both need the line of sight at each grid cell. It is computed exactly on the lattice of the
orthoimage's :class:`stereodem.ortho.drm.BackwardMap` (project the node at the mid height, localise
the same pixel 100 m higher) and interpolated bilinearly: lines of sight turn slowly across a
scene. Directions are expressed in the map frame (x east, y north, z up, metres), ignoring the
map scale factor (< 0.1 % in UTM) — angles, not lengths, matter here.

The orthoimage of the second image of a stereo pair on the same grid needs no layer code: pass
``grid=ortho_left.grid`` to :func:`stereodem.ortho.drm.orthorectify`.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import rasterio

from stereodem.core import geodesy

from .drm import Ortho, bilinear_nan

log = logging.getLogger(__name__)

#: ``stereodem ortho --layers``: each layer's band description, its file ``<stem>_<name>.tif``
#: beside the orthoimage (:func:`layer_path`)
LAYERS = {
    "incidence": "local incidence angle",
    "occlusion": "occlusion: 1 hidden from the sensor, 0 seen",
}


def layer_path(ortho_path, name: str) -> Path:
    """Where layer ``name`` (a key of :data:`LAYERS`) of the orthoimage ``ortho_path`` lives."""
    p = Path(ortho_path)
    return p.with_name(f"{p.stem}_{name}.tif")


def remove_stale_layers(ortho_path, keep=()) -> list[Path]:
    """Remove the layers of :data:`LAYERS` other than ``keep`` beside ``ortho_path``: an
    earlier orthoimage's, which no longer belong to the one written there now (as ``dem
    --overwrite`` removes the earlier job's companions). Only a layer this package wrote (its
    band description) is removed; a file of another origin by that name is left, with a
    warning. Returns the paths removed."""
    removed = []
    for name, description in LAYERS.items():
        p = layer_path(ortho_path, name)
        if name in keep or not p.is_file():
            continue
        try:
            with rasterio.open(p) as ds:
                ours = ds.count == 1 and ds.descriptions[0] == description
        except rasterio.errors.RasterioIOError:
            ours = False
        if not ours:
            log.warning("%s: not an orthoimage layer of stereodem; left as it is", p)
            continue
        p.unlink()
        Path(f"{p}.aux.xml").unlink(missing_ok=True)
        removed.append(p)
    return removed


def line_of_sight(
    ortho: Ortho, model, *, dh: float = 100.0, row0: int = 0, row1: int | None = None
):
    """Unit vectors from the ground toward the sensor, map frame (east, north, up).

    Returns an array (3, rows, cols) for grid rows ``row0:row1``.
    """
    bm = ortho.backward_map
    row1 = ortho.grid.height if row1 is None else row1
    lon, lat = bm.lattice_lonlat()
    h0 = np.full(lon.shape, bm.h_mid)
    col, row = model.project(lon, lat, h0)
    lon2, lat2 = model.localize(col, row, h0 + dh)
    x, y = geodesy.lonlat_to_crs(lon, lat, ortho.grid.crs)
    x2, y2 = geodesy.lonlat_to_crs(lon2, lat2, ortho.grid.crs)
    v = np.stack([np.asarray(x2) - x, np.asarray(y2) - y, np.full(lon.shape, dh)])
    v /= np.linalg.norm(v, axis=0, keepdims=True)
    los = bm.interpolate_planes(v, row0, row1)
    return los / np.linalg.norm(los, axis=0, keepdims=True)


def surface_normals(heights, res):
    """Unit upward normals (3, rows, cols) of a north-up height grid (map frame, metres)."""
    rx, ry = res if np.ndim(res) else (res, res)
    dz_drow, dz_dcol = np.gradient(np.asarray(heights, np.float64))
    gx, gy = dz_dcol / rx, -dz_drow / ry  # rows run south
    n = np.stack([-gx, -gy, np.ones_like(gx)])
    return n / np.linalg.norm(n, axis=0, keepdims=True)


def incidence_angle(ortho: Ortho, model) -> np.ndarray:
    """Local incidence angle (degrees) between the line of sight and the DEM surface normal.

    0 deg: the sensor looks straight down the normal; > 90 deg: the slope faces away from the
    sensor (hidden). NaN where the DEM has no height. Float32, on the orthoimage grid.
    """
    n = surface_normals(ortho.heights, ortho.grid.res)
    los = line_of_sight(ortho, model)
    cosi = np.clip(np.sum(n * los, axis=0), -1.0, 1.0)
    return np.degrees(np.arccos(cosi)).astype(np.float32)


def occlusion_mask(
    ortho: Ortho,
    model,
    *,
    tolerance: float | None = None,
    max_steps: int = 1024,
    block_rows: int = 256,
) -> np.ndarray:
    """Cells hidden from the sensor by terrain (True = occluded), by ray marching.

    From each cell the line of sight toward the sensor is followed across the height grid
    (one cell per step, vectorised over cells, loop over steps) until it rises above the
    highest terrain; the cell is occluded when the terrain along the way is higher than the
    ray by more than ``tolerance`` metres (default: a tenth of the posting). Earth curvature
    over the marching distance is neglected (0.08 m per km). Cells without height are False.
    """
    h = np.asarray(ortho.heights, np.float64)
    H, W = h.shape
    rx, ry = ortho.grid.res
    ds = min(rx, ry)
    tol = 0.1 * ds if tolerance is None else float(tolerance)
    hmax = np.nanmax(h)
    out = np.zeros((H, W), dtype=bool)
    for r0 in range(0, H, block_rows):
        r1 = min(H, r0 + block_rows)
        los = line_of_sight(ortho, model, row0=r0, row1=r1)
        hb = h[r0:r1]
        vv, uu = np.mgrid[r0:r1, 0:W]
        horiz = np.hypot(los[0], los[1])
        ok = np.isfinite(hb) & (horiz > 1e-9) & (los[2] > 0)
        idx = np.nonzero(ok.ravel())[0]
        if idx.size == 0:
            continue
        ex, ny_, slope = (
            (los[0] / np.maximum(horiz, 1e-12)).ravel()[idx],
            (los[1] / np.maximum(horiz, 1e-12)).ravel()[idx],
            (los[2] / np.maximum(horiz, 1e-12)).ravel()[idx],
        )
        u0, v0, z0 = uu.ravel()[idx].astype(float), vv.ravel()[idx].astype(float), hb.ravel()[idx]
        n_need = int(np.ceil(np.max((hmax - z0) / slope) / ds)) if idx.size else 0
        step = ds * max(1.0, n_need / max_steps)
        hidden = np.zeros(idx.size, dtype=bool)
        active = np.arange(idx.size)
        k = 1
        while active.size:
            d = k * step
            zr = z0[active] + d * slope[active]
            zt = bilinear_nan(
                h, u0[active] + d * ex[active] / rx, v0[active] - d * ny_[active] / ry
            )
            hit = zt > zr + tol
            hidden[active[hit]] = True
            keep = ~hit & (zr <= hmax) & ~np.isnan(zt)
            active = active[keep]
            k += 1
        out.ravel()[r0 * W + idx] = hidden
    return out
