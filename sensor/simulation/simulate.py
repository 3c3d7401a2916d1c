"""Scene simulator: a stereo pair rendered from a real DEM and texture through sensor models.

A scene is built on a UTM grid around the DEM's centre:

* ``truth_dem``: the DEM resampled (cubic) to the grid, converted to ellipsoidal heights;
* a ground radiance field on a grid twice as fine: albedo (the texture stretched over the
  scene, times seeded multi-octave detail) times Lambertian shading of the DEM
  (sun azimuth 150 deg, elevation 55 deg), blurred by the system point-spread function: a
  Gaussian whose MTF at the image Nyquist frequency is ``mtf_nyquist`` (default 0.3, as ASTER
  VNIR's 0.25-0.35; 0.49 GSD), standing for optics, detector integration and motion. The
  image is the point sample of this band-limited field; an unblurred field would hold
  content above the image Nyquist frequency that no interpolation of the image can recover;
* the two images: every pixel is localised on the DEM through its sensor model (DRM relief
  iteration, :mod:`stereodem.sensor.simulation.render`) and reads the radiance there; then sensor
  noise (Gaussian, ``noise`` DN) and 8- or 16-bit quantisation;
* ``truth_ortho``: the same band-limited radiance field at the ``truth_dem`` cell centres, in
  the same DN scale without noise or quantisation (the left image's true orthoimage). An
  exact orthorectification differs from it by the interpolator's error on the band-limited
  image (smaller for smaller ``mtf_nyquist`` and better kernels: measured in
  ``tests/ortho/test_ortho.py``) plus the propagated noise;
* check points: random left-image pixels localised exactly on the DEM, with their right-image
  coordinates, half of them marked as GCPs.

Presets
-------
``aster``  the real geometry of the bundled ASTER granule (:func:`aster_geometry_parameters`):
           ~709 km orbit, ~15 m pixels, 2.1989 ms line period, band 3N near nadir and 3B
           27.7 deg backward (B/H ~0.6), both pointed ~8.6 deg across track, one orbit.
``frame``  BILSAT-like frame camera (0.0074 mm pixels, ~27 m GSD), two exposures on one
           orbit converging on the scene centre (B/H ~0.6).
``pushbroom``  a pushbroom pair at user-chosen along-track angles (``angles=(fwd, bwd)``).

Everything is reproducible from ``seed``.
"""

from __future__ import annotations

import csv
import io
import logging
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import cv2
import numpy as np
import rasterio
from affine import Affine
from rasterio.warp import Resampling, reproject

from stereodem.core import geodesy, jsonutil
from stereodem.core.dem import DEM, ELLIPSOID, as_dem
from stereodem.core.errors import InputError
from stereodem.core.grid import MapGrid
from stereodem.core.memory import check_allocation
from stereodem.core.raster import (
    prepare_output_dir,
    unreadable,
    write_geotiff,
    write_text_atomic,
)
from stereodem.core.stats import generator
from stereodem.sensor.estimation.jitter import (
    MAX_OSCILLATION_RAD,
    SineSeries,
    with_attitude_sines,
)
from stereodem.sensor.estimation.rpcfit import fit_rpc
from stereodem.sensor.io.aster_xml import bundled_xml, read_asp_aster_xml
from stereodem.sensor.io.sidecar import save_model
from stereodem.sensor.models.base import SensorModel
from stereodem.sensor.models.frame import FrameCamera
from stereodem.sensor.models.pushbroom import PushbroomModel
from stereodem.sensor.simulation.render import (
    MapRaster,
    nanmean_blocks,
    render,
    sampled_localization_error,
)

log = logging.getLogger(__name__)

SUN_AZIMUTH, SUN_ELEVATION = 150.0, 55.0
PRESETS = ("aster", "frame", "pushbroom")
#: System modulation transfer function (optics x detector integration x motion) at the image's
#: Nyquist frequency; ASTER VNIR's is about 0.25-0.35.
MTF_NYQUIST = 0.3
#: COG options of the (large, lossless) truth rasters, references for comparisons rather than
#: images to browse: DEFLATE level 1 and no overviews write a full ASTER scene's truth in a
#: quarter of the time of the defaults (level 6, overviews), for 3 % more bytes per level
TRUTH_CO = {"LEVEL": "1", "OVERVIEWS": "NONE"}


def psf_sigma(mtf_nyquist: float = MTF_NYQUIST) -> float:
    """Standard deviation (in ground sample distances) of the Gaussian system point-spread
    function whose MTF at the Nyquist frequency (0.5 cycle per pixel) is ``mtf_nyquist``.

    A Gaussian of standard deviation s has MTF(f) = exp(-2 pi^2 s^2 f^2), so
    s = sqrt(-ln(mtf) / (2 pi^2 * 0.25)); 0.3 gives 0.49 GSD.
    """
    if not 0.0 < mtf_nyquist < 1.0:
        raise InputError(f"mtf_nyquist must be in (0, 1), got {mtf_nyquist}")
    return float(np.sqrt(-np.log(mtf_nyquist) / (0.5 * np.pi**2)))


def check_noise(noise, bits: int = 16) -> float:
    """The sensor noise ``noise`` (DN) as a number from 0 to the full scale of ``bits``-bit
    images (``2**bits - 1`` DN), else :class:`InputError`: a negative or NaN noise rendered
    noiseless images (``noise > 0`` false) while ``scene.json`` recorded the value asked for,
    and a noise beyond the full scale (``1e308``: infinite in the float32 rendering) made
    images of nothing but clipped noise."""
    v = float(noise)
    full = 2**bits - 1
    if not (np.isfinite(v) and 0 <= v <= full):
        raise InputError(
            f"noise must be a standard deviation from 0 to the {bits}-bit full scale "
            f"({full} DN), got {noise}"
        )
    return v


#: the largest attitude oscillation :func:`simulate_scene` renders, radians
#: (:data:`stereodem.sensor.estimation.jitter.MAX_OSCILLATION_RAD`, the rule of every model
#: with attitude sines)
MAX_JITTER_RAD = MAX_OSCILLATION_RAD


def _check_image_memory(sizes, what: str):
    """:class:`InputError` before any model is built when the images of ``sizes`` ((w, h)
    pixels each) cannot be held while rendered (float64 plus the ray grids): a 1e11-pixel
    side reached the orbit's per-line ephemeris first and ended in the OOM killer."""
    check_allocation(16.0 * sum(float(w) * float(h) for w, h in sizes), what)


@dataclass
class Scene:
    """A simulated stereo scene (all arrays in memory)."""

    left: np.ndarray
    right: np.ndarray
    left_model: SensorModel
    right_model: SensorModel
    truth_dem: DEM
    truth_ortho: np.ndarray
    points: list
    preset: str
    settings: dict = field(default_factory=dict)
    diagnostics: dict = field(default_factory=dict)


def texture_path() -> Path:
    return Path(resources.files("stereodem.sensor") / "data" / "landsat_texture.tif")


# ----------------------------------------------------------------------------- sensor pairs


def _orbit_state(lon0, lat0, altitude, along_km, heading_deg):
    """ECEF position and velocity of a circular orbit passing over (lon0, lat0).

    The satellite is ``along_km`` along the ground track (heading ``heading_deg`` from north)
    from the point above the target.
    """
    r0 = np.array(geodesy.geodetic_to_ecef(lon0, lat0, altitude))
    enu = geodesy.enu_basis(lon0, lat0)
    hd = np.radians(heading_deg)
    t_dir = np.sin(hd) * enu[0] + np.cos(hd) * enu[1]
    R = np.linalg.norm(r0)
    v_circ = np.sqrt(geodesy.GM / R)
    ang = along_km * 1e3 / R
    u = r0 / R
    r = R * (np.cos(ang) * u + np.sin(ang) * t_dir)
    v_in = v_circ * (-np.sin(ang) * u + np.cos(ang) * t_dir)
    v_ecef = v_in - np.cross([0.0, 0.0, geodesy.OMEGA_EARTH], r)
    return r, v_ecef


def frame_pair(lon0, lat0, h0, size, gsd=27.6, altitude=686e3, base_to_height=0.6):
    """Two BILSAT-like frame cameras on one orbit converging on ``(lon0, lat0, h0)``."""
    w, h = size
    pitch = 0.0074
    focal = pitch * 1e-3 * altitude / gsd * 1e3
    along = 0.5 * base_to_height * altitude / 1e3
    cams = []
    for sign in (-1.0, 1.0):
        r, v = _orbit_state(lon0, lat0, altitude, sign * along, heading_deg=-12.0)
        cams.append(
            FrameCamera.looking_at(
                r, v, lon0, lat0, h0, width=w, height=h, focal_mm=focal, pitch_mm=pitch
            )
        )
    return cams[0], cams[1]


def aster_geometry_parameters() -> dict:
    """Pointing, IFOV, orbit height and line period of the bundled real ASTER 3N/3B granule.

    Read from the real product geometry (:func:`stereodem.sensor.io.aster_xml.bundled_xml`): the
    centre detector's sight vector in the orbital frame gives the along-track angle of each band
    (3N about +0.03 deg, 3B about -27.7 deg) and their common cross-track pointing (about
    8.6 deg to the right of the track); the angle between the first and last detectors gives
    the IFOV; the satellite positions give the orbit height. The line period 2.1989 ms is the
    one that reproduces the product's own lattice (notes aster-l1a-format §4.4).
    """
    out = {}
    for band in ("3N", "3B"):
        g = read_asp_aster_xml(bundled_xml(band))
        sv = g.sight_vectors[len(g.sight_vectors) // 2]  # (11, 3), orbital frame
        mid = sv[sv.shape[0] // 2]
        cols = g.lattice[0, :, 0]
        first, last = sv[0] / np.linalg.norm(sv[0]), sv[-1] / np.linalg.norm(sv[-1])
        ifov = float(np.arccos(np.clip(first @ last, -1, 1)) / (cols[-1] - cols[0]))
        _, _, hsat = geodesy.ecef_to_geodetic(*np.asarray(g.satellite_positions, float).T)
        out[band] = dict(
            along_deg=float(np.degrees(np.arctan2(mid[0], mid[2]))),
            cross_deg=float(np.degrees(np.arctan2(mid[1], mid[2]))),
            ifov_rad=ifov,
            altitude_m=float(np.mean(hsat)),
        )
    return dict(
        bands=out,
        line_period_s=2.1989e-3,
        altitude_m=out["3N"]["altitude_m"],
        gsd_m=out["3N"]["ifov_rad"] * out["3N"]["altitude_m"],
        cross_track_right_deg=out["3N"]["cross_deg"],
    )


def pushbroom_pair(
    lon0,
    lat0,
    h0,
    size,
    angles,
    gsd=15.0,
    altitude=705e3,
    line_period=2.2e-3,
    cross_track_tilt_deg=0.0,
    right_size=None,
):
    """A pushbroom pair on one orbit with along-track tilts ``angles`` (degrees).

    ``cross_track_tilt_deg`` follows :class:`stereodem.sensor.models.pushbroom.PushbroomModel`
    (positive looks left of the flight direction). ``right_size`` (width, height) gives the second
    image its own size (ASTER 3B: about 5000 x 4600 against 3N's 4100 x 4200); default ``size``.
    """
    w, h = size
    rw, rh = right_size if right_size is not None else size
    # one orbit: the first image, then the second (e.g. ASTER 3N then 3B, ~55 s later), both
    # centred on the same ground point at the terrain height h0
    return PushbroomModel.synthetic_pair(
        lon0,
        lat0,
        width=w,
        height=h,
        backward_width=int(rw),
        backward_height=int(rh),
        gsd=gsd,
        altitude=altitude,
        line_period=line_period,
        first_tilt_deg=angles[0],
        backward_tilt_deg=angles[1],
        cross_track_tilt_deg=cross_track_tilt_deg,
        center_height=float(h0),
    )


# ----------------------------------------------------------------------------- ground fields


def _check_footprints_on_dem(models, dem: DEM, h_range, size, right_size):
    """:class:`InputError`, before anything is allocated, when the images of the requested
    sizes do not lie on the Earth (the view passes the horizon: localisation gives NaN) or
    lie mostly outside the DEM (the later coverage check allows 1 % of voids)."""
    lons, lats = [], []
    for m in models:
        for hh in h_range:
            lon, lat = m.footprint(hh)
            lons.append(lon)
            lats.append(lat)
    lon, lat = np.concatenate(lons), np.concatenate(lats)
    sizes = f"{size[0]}x{size[1]} / {right_size[0]}x{right_size[1]} px"
    if not (np.all(np.isfinite(lon)) and np.all(np.isfinite(lat))):
        raise InputError(
            f"image size {sizes}: the images would reach past the Earth's horizon "
            "from the simulated orbit; choose a smaller --size"
        )
    west, south, east, north = dem.bounds_lonlat()
    lon = geodesy.lon_beside(lon, 0.5 * (west + east))  # a footprint across 180 stays whole
    ow = max(0.0, min(east, lon.max()) - max(west, lon.min()))
    oh = max(0.0, min(north, lat.max()) - max(south, lat.min()))
    span = max(lon.max() - lon.min(), 1e-12) * max(lat.max() - lat.min(), 1e-12)
    if ow * oh < 0.5 * span:
        raise InputError(
            f"{dem.path or 'DEM'}: the DEM does not cover the simulated scene of "
            f"{sizes} (footprint lon {lon.min():.4f}..{lon.max():.4f}, lat "
            f"{lat.min():.4f}..{lat.max():.4f}; DEM lon {west:.4f}..{east:.4f}, lat "
            f"{south:.4f}..{north:.4f}); choose a smaller --size or a larger --dem"
        )


def _grid_for_models(models, crs, posting, h_range, margin_px=8):
    xs, ys = [], []
    for m in models:
        for hh in h_range:
            lon, lat = m.footprint(hh)
            x, y = geodesy.lonlat_to_crs(lon, lat, crs)
            xs.append(x)
            ys.append(y)
    x, y = np.concatenate(xs), np.concatenate(ys)
    x0 = np.floor(x.min() / posting - margin_px) * posting
    y1 = np.ceil(y.max() / posting + margin_px) * posting
    w = int(np.ceil((x.max() - x0) / posting + margin_px))
    h = int(np.ceil((y1 - y.min()) / posting + margin_px))
    return Affine(posting, 0, x0, 0, -posting, y1), (h, w)


def _reproject_dem(
    dem: DEM,
    transform,
    shape,
    crs,
    *,
    geoid_step: int = 16,
    map_step: int = 16,
    block_rows: int = 512,
    upsample: int = 8,
    diagnostics: dict | None = None,
):
    """``dem`` resampled (bicubic, GDAL's kernel) to the grid, in ellipsoidal heights (float32).

    Each grid cell centre's position in the source DEM (fractional pixel) is computed exactly
    (pyproj) every ``map_step`` cells and interpolated bilinearly in between. The DEM is then
    evaluated there with the cubic convolution kernel of GDAL's ``cubic`` resampling (Keys,
    a = -0.5, which reproduces linear ramps), row block by row block, in two exact steps and one
    approximate one: the block's source window is upsampled ``upsample`` times by the separable
    Keys kernel (a polyphase filter: exact values at every 1/``upsample`` source pixel), then
    sampled bilinearly (OpenCV ``remap``). The bilinear step departs from the exact Keys
    surface by at most ``|h''| d^2 / 8`` with ``d`` = the source posting / ``upsample`` (on a 3"
    DEM of alpine relief, centimetres), plus ``remap``'s 1/32-pixel position rounding (1/256
    source pixel). OpenCV's own bicubic (Keys a = -0.75) was not used: it displaces ramps by up
    to 0.05 source pixel, which puts ripples at the source posting into the terrain (NMAD 1.0 m
    against GDAL's on the bundled SRTM at 7.5 m) and made the full-granule DEM's error 7 %
    larger (``benchmarks/bench_aster_scene.py``). The interpolation error of the source
    positions is measured at the centres of the coarse cells and recorded in
    ``diagnostics["dem_map_error_px"]`` (source pixels; ~1e-6 for a 3" DEM at 16 cells of
    7.5 m). Grids or DEMs too large for OpenCV's remap (32767 pixels a side) go through
    ``rasterio.warp.reproject`` (cubic) instead.

    The geoid undulation is evaluated every ``geoid_step`` cells and interpolated bilinearly
    (EGM96 varies over tens of km: the interpolation error is at the millimetre level,
    :func:`geoid_on_grid`), in row blocks, so that no full-size float64 array is made.
    """
    out = np.full(shape, np.nan, np.float32)
    src = np.asarray(dem.heights, np.float32)
    if max(shape) >= 32767 or max(src.shape) * upsample >= 32767:
        reproject(
            dem.heights,
            out,
            src_transform=dem.transform,
            src_crs=dem.crs.to_wkt(),
            dst_transform=transform,
            dst_crs=crs.to_wkt(),
            resampling=Resampling.cubic,
            src_nodata=np.nan,
            dst_nodata=np.nan,
        )
    else:
        coarse, err = _source_pixel_grid(dem, transform, shape, crs, map_step)
        if diagnostics is not None:
            diagnostics["dem_map_error_px"] = max(err, diagnostics.get("dem_map_error_px", 0.0))
        rows, cols = shape
        sr, sc = src.shape
        mc_cols = (np.arange(cols, dtype=np.float32) / np.float32(map_step))[None]
        for r0 in range(0, rows, block_rows):
            r1 = min(rows, r0 + block_rows)
            mc = np.broadcast_to(mc_cols, (r1 - r0, cols))
            mr = np.broadcast_to(
                (np.arange(r0, r1, dtype=np.float32) / np.float32(map_step))[:, None],
                (r1 - r0, cols),
            )
            mc, mr = np.ascontiguousarray(mc), np.ascontiguousarray(mr)
            px = cv2.remap(coarse[0], mc, mr, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            py = cv2.remap(coarse[1], mc, mr, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            outside = (px < -0.5) | (px > sc - 0.5) | (py < -0.5) | (py > sr - 0.5)
            # the source window the block needs (whole pixels, clipped to the DEM)
            wc0 = int(np.clip(np.floor(np.nanmin(px)), 0, sc - 1))
            wc1 = int(np.clip(np.ceil(np.nanmax(px)) + 1, wc0 + 1, sc))
            wr0 = int(np.clip(np.floor(np.nanmin(py)), 0, sr - 1))
            wr1 = int(np.clip(np.ceil(np.nanmax(py)) + 1, wr0 + 1, sr))
            fine = keys_upsample(src, upsample, window=(wr0, wr1, wc0, wc1))
            px -= np.float32(wc0)
            px *= np.float32(upsample)
            py -= np.float32(wr0)
            py *= np.float32(upsample)
            block = cv2.remap(fine, px, py, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            block[outside] = np.nan
            out[r0:r1] = block
    if dem.vertical != ELLIPSOID:
        if dem.vertical is None:  # the DEM's own error about the unknown reference
            dem.convert_heights(np.zeros(1), np.zeros(1), np.zeros(1), ELLIPSOID)
        geoid_on_grid(transform, shape, crs, step=geoid_step, add_to=out)  # h = H + N
    return out


def _keys_weights(t, a: float = -0.5):
    """The four cubic-convolution weights (Keys 1981) of the samples at offsets -1, 0, 1, 2
    for a position ``t`` in [0, 1) after sample 0."""

    def k(x):
        x = abs(x)
        return (
            ((a + 2) * x**3 - (a + 3) * x**2 + 1)
            if x <= 1
            else (a * x**3 - 5 * a * x**2 + 8 * a * x - 4 * a)
            if x < 2
            else 0.0
        )

    return np.array([k(t + 1), k(t), k(1 - t), k(2 - t)], np.float32)


def keys_upsample(src, factor: int, *, window=None, a: float = -0.5):
    """``src`` (2-D float32) upsampled ``factor`` times by separable cubic convolution.

    Returns ``U`` with ``U[factor i + p, factor j + q]`` = the Keys (a = -0.5: GDAL's ``cubic``)
    interpolant at source pixel ``(i + p / factor, j + q / factor)`` (row, col; pixel centres at
    integers), edges replicated. ``window = (r0, r1, c0, c1)`` restricts the output to source
    rows ``r0..r1-1`` and columns ``c0..c1-1`` (the neighbours outside it are still used), so
    ``U[0, 0]`` is source pixel ``(r0, c0)``. A polyphase filter: ``factor`` vectorised 4-tap
    sums per axis, no per-pixel loop.
    """
    r0, r1, c0, c1 = window if window is not None else (0, src.shape[0], 0, src.shape[1])
    P = np.pad(np.asarray(src, np.float32), ((1, 2), (1, 2)), mode="edge")
    W = [_keys_weights(p / factor, a) for p in range(factor)]

    def along0(A, n):  # rows: A[1 + i] is sample i; n output samples
        out = np.empty((n * factor,) + A.shape[1:], np.float32)
        for p, w in enumerate(W):
            out[p::factor] = (
                w[0] * A[0:n] + w[1] * A[1 : n + 1] + w[2] * A[2 : n + 2] + w[3] * A[3 : n + 3]
            )
        return out

    rowsup = along0(P[r0 : r1 + 3, c0 : c1 + 3], r1 - r0)  # (rows * f, cols + 3)
    return np.ascontiguousarray(along0(rowsup.T, c1 - c0).T)


def _source_pixel_grid(dem: DEM, transform, shape, crs, step: int):
    """Fractional source-DEM (col, row) of the grid's cell centres every ``step`` cells
    (float32, (2, nr, nc), nodes ``0, step, ...`` past the last cell), and the maximum error
    (source pixels) of bilinear interpolation between nodes, measured at coarse-cell centres."""
    rows, cols = shape
    rc = np.arange(0, rows - 1 + step, step, dtype=np.float64)
    cc = np.arange(0, cols - 1 + step, step, dtype=np.float64)
    tr = geodesy.transformer(crs, dem.crs)
    inv = ~dem.transform

    def exact(c, r):
        x, y = transform @ (c + 0.5, r + 0.5)
        sx, sy = tr.transform(x, y)
        if dem.crs.is_geographic:  # a lon/lat DEM past 180 E: the grid's longitudes beside it
            sx = geodesy.lon_beside(sx, dem.transform.c + dem.transform.a * dem.shape[1] / 2.0)
        scol, srow = inv @ (np.asarray(sx), np.asarray(sy))
        return np.asarray(scol) - 0.5, np.asarray(srow) - 0.5

    gc, gr = np.meshgrid(cc, rc)
    nodes = np.stack(exact(gc, gr))
    # check: exact positions at the coarse-cell centres against the bilinear mean of the nodes
    mid = np.stack(exact(*np.meshgrid(cc[:-1] + step / 2, rc[:-1] + step / 2)))
    interp = 0.25 * (nodes[:, :-1, :-1] + nodes[:, 1:, :-1] + nodes[:, :-1, 1:] + nodes[:, 1:, 1:])
    err = float(np.max(np.hypot(*(mid - interp)))) if mid.size else 0.0
    return nodes.astype(np.float32), err


def geoid_on_grid(transform, shape, crs, *, step: int = 16, add_to=None, block_rows: int = 1024):
    """EGM96 undulation (m) at the cell centres of a map grid, bilinear (``cv2.remap``) from
    every ``step``-th cell (nodes ``0, step, ...`` up to past the last cell); added in place to
    ``add_to`` (float32, ``shape``) if given, else returned. EGM96 varies over tens of km: the
    interpolation error over ``step`` cells is at the millimetre level."""
    rows, cols = shape
    rc = np.arange(0, rows - 1 + step, step, dtype=np.float64)
    cc = np.arange(0, cols - 1 + step, step, dtype=np.float64)
    gc, gr = np.meshgrid(cc + 0.5, rc + 0.5)
    x, y = transform @ (gc, gr)
    lon, lat = geodesy.crs_to_lonlat(x, y, crs)
    coarse = geodesy.geoid_undulation(lon, lat).astype(np.float32)  # (len(rc), len(cc))
    out = add_to if add_to is not None else np.zeros(shape, np.float32)
    mc = (np.arange(cols, dtype=np.float32) / np.float32(step))[None]
    for r0 in range(0, rows, block_rows):
        r1 = min(rows, r0 + block_rows)
        mr = (np.arange(r0, r1, dtype=np.float32) / np.float32(step))[:, None]
        m1, m2 = np.broadcast_arrays(mc, mr)
        out[r0:r1] += cv2.remap(
            coarse,
            np.ascontiguousarray(m1),
            np.ascontiguousarray(m2),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )
    return out


def _valid_box(valid):
    """Largest centred-ish axis-aligned box (r0, r1, c0, c1) that is >= 99.9 % valid."""
    ii = cv2.integral(valid.astype(np.float64))
    H, W = valid.shape
    best = (0, 0, H, 0, W)
    if valid.mean() > 0.999:
        return best[1:]
    best = (0,)
    step = max(4, min(H, W) // 100)
    for r0 in range(0, H // 2, step):
        for c0 in range(0, W // 2, step):
            ww = W - 2 * c0
            for r1 in range(H - r0, r0 + H // 4, -step):
                s = ii[r1, W - c0] - ii[r0, W - c0] - ii[r1, c0] + ii[r0, c0]
                area = (r1 - r0) * (ww)
                if s >= 0.999 * area:
                    if area > best[0]:
                        best = (area, r0, r1, c0, W - c0)
                    break
    if best[0] == 0:
        raise InputError("texture has no usable (non-zero) area")
    return best[1:]


#: detail octaves of the albedo: (Gaussian sigma in fine cells, relative amplitude, decimation)
#: - white noise drawn on a grid ``decimation`` times coarser, blurred by sigma / decimation
#: there and resized (bicubic) to the fine grid: the same band-limited field for a fraction of
#: the cost (the blur removes what the coarser grid cannot hold)
DETAIL_OCTAVES = ((0.8, 1.0, 1), (2.0, 0.8, 2), (5.0, 0.6, 4), (12.0, 0.4, 8))


def _robust_std(a, stride: int = 4) -> float:
    """Standard deviation of a large 2-D float32 array from every ``stride``-th row and column
    (a deterministic subsample of ~1/stride^2 of the cells, in float64)."""
    return float(np.std(a[::stride, ::stride], dtype=np.float64))


def _albedo(texture, shape, rng, detail=0.35):
    """Texture stretched to ``shape`` times seeded multi-octave detail, range about 0.05-0.95.

    The texture's nodata border (zeros in every band, as in rotated Landsat scenes) is cut
    off first.
    """
    # the seeded detail first (it alone uses the generator), then the stretched texture: only
    # three full-size arrays live at a time
    d = np.zeros(shape, np.float32)
    for sigma, amp, k in DETAIL_OCTAVES:
        cshape = (-(-shape[0] // k), -(-shape[1] // k))
        n = _white_noise_float32(rng, cshape)
        cv2.GaussianBlur(n, (0, 0), sigma / k, dst=n)
        n *= amp / max(_robust_std(n, 4 if k == 1 else 1), 1e-6)
        if k == 1:
            d += n
        else:
            # coarse cell i covers fine cells [i k, (i + 1) k) (cv2.resize's convention)
            d += cv2.resize(n, (n.shape[1] * k, n.shape[0] * k), interpolation=cv2.INTER_CUBIC)[
                : shape[0], : shape[1]
            ]
        del n
    d *= 0.5 / _robust_std(d)
    np.tanh(d, out=d)
    d *= detail
    d += 1.0
    try:
        with rasterio.open(texture) as ds:
            t = ds.read().astype(np.float32)
    except rasterio.errors.RasterioIOError as exc:
        raise InputError(unreadable(texture, "texture image", exc)) from None
    r0, r1, c0, c1 = _valid_box(t.sum(axis=0) > 0)
    t = t[:, r0:r1, c0:c1]
    t = t.mean(axis=0) if t.shape[0] > 1 else t[0]
    # the stretch from the texture's own percentiles (a resize keeps them; this avoids sorting
    # the full-size array)
    lo, hi = (float(v) for v in np.percentile(t, [1, 99]))
    t = cv2.resize(t, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)
    t -= lo  # in place: full-size arrays
    t /= max(hi - lo, 1e-6)
    np.clip(t, 0, 1, out=t)
    t *= 0.7
    t += 0.15
    t *= d
    del d
    return np.clip(t, 0.02, 1.0, out=t)


def _white_noise_float32(rng, shape):
    """Zero-mean, unit-variance white noise (float32): uniform numbers, five times cheaper to
    draw than normal ones. The albedo detail is this noise blurred, which makes it Gaussian
    in all but the tails (central limit) and leaves its spectrum (flat before the blur)
    unchanged."""
    out = np.empty(shape, np.float32)
    rng.random(out.shape, dtype=np.float32, out=out)
    out -= np.float32(0.5)
    out *= np.float32(np.sqrt(12.0))
    return out


def _normal_float32(rng, shape, chunk_rows: int = 512):
    """Standard normal float32 numbers of ``shape``, drawn in row chunks directly in float32
    (``Generator.standard_normal(dtype=np.float32)``: no float64 array)."""
    out = np.empty(shape, np.float32)
    for r0 in range(0, shape[0], chunk_rows):
        r1 = min(shape[0], r0 + chunk_rows)
        rng.standard_normal((r1 - r0,) + tuple(shape[1:]), dtype=np.float32, out=out[r0:r1])
    return out


def _hillshade_blocks(z, res, azimuth, elevation, block_rows):
    """``(r0, r1, shade)`` row blocks of :func:`hillshade_factor` (one-row halo; central
    differences as ``np.gradient`` inside, float32)."""
    az, el = np.radians(azimuth), np.radians(elevation)
    s = np.array([np.sin(az) * np.cos(el), np.cos(az) * np.cos(el), np.sin(el)], np.float32)
    fill = nanmean_blocks(z)
    rows = z.shape[0]
    k = np.array([[-0.5, 0.0, 0.5]], np.float32) / np.float32(res)
    for r0 in range(0, rows, block_rows):
        r1 = min(rows, r0 + block_rows)
        a, b = max(r0 - 1, 0), min(r1 + 1, rows)
        blk = np.nan_to_num(z[a:b], nan=fill).astype(np.float32, copy=False)
        gx = cv2.filter2D(blk, cv2.CV_32F, k, borderType=cv2.BORDER_REPLICATE)
        gy = cv2.filter2D(blk, cv2.CV_32F, k.T, borderType=cv2.BORDER_REPLICATE)
        gy, gx = gy[r0 - a : r0 - a + (r1 - r0)], gx[r0 - a : r0 - a + (r1 - r0)]
        # rows go south: the north-ward slope is -gy; normal (-gx, gy, 1) / n
        n = gx * gx
        n += gy * gy
        n += 1.0
        np.sqrt(n, out=n)
        shade = gy * s[1]
        shade -= gx * s[0]
        shade += s[2]
        shade /= n
        yield r0, r1, np.clip(shade, 0.0, 1.0, out=shade)


def hillshade_factor(z, res, azimuth=SUN_AZIMUTH, elevation=SUN_ELEVATION, *, block_rows=256):
    """Lambertian cos(incidence) of the sun on a DEM array with square posting ``res`` (m).

    Computed in row blocks with a one-row halo (the same central differences as one
    ``np.gradient`` over the whole array), so temporaries stay block-sized.
    """
    out = np.empty(z.shape, np.float32)
    for r0, r1, shade in _hillshade_blocks(z, res, azimuth, elevation, block_rows):
        out[r0:r1] = shade
    return out


# ----------------------------------------------------------------------------- simulation


@dataclass
class _GroundFields:
    """The ground of a simulated scene: truth DEM grid, band-limited radiance field (on a grid
    twice as fine) and the fine rendering DEM with its height span."""

    truth: np.ndarray
    transform: Affine
    shape: tuple
    crs: object
    field: np.ndarray
    radiance: MapRaster
    dem_r: MapRaster
    h_mean: float
    fine_range: tuple


def _ground_fields(
    models, dem, lon0, lat0, h_range, gsd, texture, rng, sigma_psf, bits, diags
) -> _GroundFields:
    """Truth DEM and radiance field covering every model's footprint (see the module docstring)."""
    crs = geodesy.utm_crs(lon0, lat0)
    res_truth = float(np.round(gsd, 1))
    transform, shape = _grid_for_models(models, crs, res_truth, h_range)
    # the fine radiance field and DEM (4 x the truth cells, float32) and their temporaries,
    # plus the images (float64 while rendered)
    w, h = int(models[0].width), int(models[0].height)
    check_allocation(
        4 * shape[0] * shape[1] * 4 * 3 + 8 * 2 * sum(int(m.width) * int(m.height) for m in models),
        f"a simulated scene of {w}x{h} px ({shape[1]}x{shape[0]} truth cells)",
    )
    truth = _reproject_dem(dem, transform, shape, crs, diagnostics=diags)
    if np.isnan(truth).mean() > 0.01:
        raise InputError(
            f"{dem.path or 'DEM'}: the DEM does not cover the simulated scene "
            f"({100 * np.isnan(truth).mean():.1f}% of the scene outside or void)"
        )

    # fine grid (half the truth posting) for the radiance field and the rendering DEM
    ft = Affine(res_truth / 2, 0, transform.c, 0, -res_truth / 2, transform.f)
    fshape = (shape[0] * 2, shape[1] * 2)
    # radiance field = albedo * (0.25 + 0.75 * shade), built in place; the fine DEM is made
    # after the albedo so that the albedo's temporaries and it never coexist
    field = _albedo(texture or texture_path(), fshape, rng)
    fine_dem = _reproject_dem(dem, ft, fshape, crs, diagnostics=diags)
    for r0, r1, shade in _hillshade_blocks(
        fine_dem, res_truth / 2, SUN_AZIMUTH, SUN_ELEVATION, 256
    ):
        field[r0:r1] *= 0.25 + 0.75 * shade
    # the system PSF, in ground units, applied once to the radiance field: both the images
    # and truth_ortho sample this one band-limited field
    cv2.GaussianBlur(field, (0, 0), sigma_psf * gsd / (res_truth / 2), dst=field)
    dn_max = 255.0 if bits == 8 else 4095.0  # 12-bit signal in 16-bit words
    field *= 0.9 * dn_max / float(np.percentile(field[::4, ::4], 99.9))  # 1/16 of the cells
    fine_grid = MapGrid(ft, fine_dem.shape[1], fine_dem.shape[0], crs)
    return _GroundFields(
        truth,
        transform,
        shape,
        crs,
        field,
        MapRaster(field, fine_grid),
        MapRaster(fine_dem, fine_grid),
        nanmean_blocks(fine_dem),
        (float(np.nanmin(fine_dem)), float(np.nanmax(fine_dem))),
    )


def _render_view(model, name, g: _GroundFields, step, noise, bits, rng, seed, diags) -> np.ndarray:
    """One image of the scene through ``model``: rendered, noisy (``noise`` DN), quantised."""
    fine_lo, fine_hi = g.fine_range
    img, _, _, _, loc = render(
        model,
        g.dem_r,
        g.radiance,
        step=step,
        keep_ground=False,
        h0=g.h_mean,
        heights=(fine_lo - 50.0, fine_hi + 50.0),
    )
    diags[f"{name}_render_error_px"] = sampled_localization_error(
        model, loc, g.dem_r, seed=seed, h0=g.h_mean
    )
    diags[f"{name}_void_pct"] = float(100 * np.isnan(img).mean())
    if noise > 0:  # float32 noise, added in place
        img += np.float32(noise) * _normal_float32(rng, img.shape)
    dtype = np.uint8 if bits == 8 else np.uint16
    np.nan_to_num(img, copy=False, nan=0.0)
    return np.clip(np.rint(img, out=img), 0, np.iinfo(dtype).max, out=img).astype(dtype)


def _scene_centre(dem):
    """The scene DEM (the bundled one when ``dem`` is None), its centre (lon, lat in degrees,
    ellipsoidal height h0 in metres: the DEM there, else mid-range) and its ellipsoidal
    height range (m)."""
    dem = DEM.bundled() if dem is None else as_dem(dem)
    west, south, east, north = dem.bounds_lonlat()
    lon0, lat0 = (west + east) / 2, (south + north) / 2
    h_lo, h_hi = dem.height_range(ELLIPSOID)
    h0 = float(dem.sample(lon0, lat0)) if np.isfinite(dem.sample(lon0, lat0)) else (h_lo + h_hi) / 2
    return dem, (lon0, lat0, h0), (h_lo, h_hi)


def _check_jitter(axis: str, spec) -> tuple[float, float]:
    """``(amplitude_urad, frequency_hz)`` of a ``jitter`` / ``roll_jitter`` request, else
    :class:`InputError`: the amplitude finite and at most :data:`MAX_JITTER_RAD`, the
    frequency positive (its upper bound, half the line rate, is
    :func:`~stereodem.sensor.estimation.jitter.with_attitude_sines`' rule)."""
    try:
        amp_urad, freq = (float(x) for x in spec)
    except (TypeError, ValueError):
        raise InputError(
            f"{axis} jitter must be (amplitude_urad, frequency_hz), got {spec!r}"
        ) from None
    if not (np.isfinite(amp_urad) and abs(amp_urad) <= MAX_JITTER_RAD * 1e6):
        raise InputError(
            f"{axis} jitter amplitude must be a finite number of microradians up to "
            f"{MAX_JITTER_RAD * 1e6:g} (an attitude oscillation, not a new pointing), "
            f"got {spec[0]}"
        )
    if not (np.isfinite(freq) and freq > 0):
        raise InputError(f"{axis} jitter frequency must be a positive number of Hz, got {spec[1]}")
    return amp_urad, freq


def _size_pair(size, what: str) -> tuple[int, int]:
    """``(width, height)`` pixels from ``size``; :class:`InputError` naming ``what`` for
    anything but two whole numbers (``size=50`` was a TypeError from inside)."""
    try:
        w, h = size
        if float(w) != int(w) or float(h) != int(h):
            raise ValueError
        return int(w), int(h)
    except (TypeError, ValueError):
        raise InputError(f"{what} must be (width, height) in pixels, got {size!r}") from None


def simulate_scene(
    preset: str = "aster",
    *,
    size=(600, 600),
    dem=None,
    texture=None,
    noise: float = 1.0,
    seed: int = 0,
    bits: int = 8,
    angles=(0.0, -27.6),
    n_points: int = 60,
    step: int = 16,
    mtf_nyquist: float = MTF_NYQUIST,
    right_size=None,
    jitter=None,
    roll_jitter=None,
) -> Scene:
    """Simulate a stereo scene; see the module docstring.

    Parameters
    ----------
    preset : {"aster", "frame", "pushbroom"}
    size : (width, height) of each image in pixels.
    right_size : (width, height), optional
        A different size for the second image (pushbroom presets; ASTER 3B is about
        5000 x 4600 for 3N's 4100 x 4200).
    dem : DEM or path, optional; default the bundled SRTM (EGM96 heights).
    texture : path, optional; default the bundled Landsat image.
    noise : float, standard deviation of the sensor noise in DN.
    bits : 8 or 16, quantisation.
    angles : along-track tilts (deg) of the two images for the ``pushbroom`` preset.
    mtf_nyquist : float
        System MTF at the image Nyquist frequency (sets the Gaussian point-spread function
        applied to the ground radiance field, :func:`psf_sigma`).
    jitter : (amplitude_urad, frequency_hz), optional
        Along-track attitude oscillation (pitch) of the second (right, ASTER 3B) camera:
        the right image is rendered through the oscillating camera, while ``right_model``
        stays the nominal one (as an L1A product describes it) and
        ``diagnostics["right_jitter"]`` records the oscillation.
    roll_jitter : (amplitude_urad, frequency_hz), optional
        The same for the cross-track attitude (roll) of the second camera, recorded in
        ``diagnostics["right_roll_jitter"]``; it moves the right image across the epipolar
        direction (residual vertical parallax). Both may be given (pitch is drawn first).
    """
    if preset not in PRESETS:
        raise InputError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    if bits not in (8, 16):
        raise InputError(f"bits must be 8 or 16, got {bits}")
    sigma_psf = psf_sigma(mtf_nyquist)  # GSD; validates mtf_nyquist
    noise = check_noise(noise, bits)
    w, h = _size_pair(size, "size")
    rsize = (w, h) if right_size is None else _size_pair(right_size, "right_size")
    if min(w, h, *rsize) < 32:
        raise InputError(
            f"image size {w}x{h} / {rsize[0]}x{rsize[1]} is too small (at least 32x32)"
        )
    _check_image_memory([(w, h), rsize], f"a simulated pair of {w}x{h} / {rsize[0]}x{rsize[1]} px")
    for axis, spec in (("pitch", jitter), ("roll", roll_jitter)):
        if spec is not None:
            _check_jitter(axis, spec)
    if preset == "frame" and rsize != (w, h):
        raise InputError(
            "the frame preset takes one size for both images (right_size is for "
            "the pushbroom presets)"
        )
    rng = generator(seed)
    dem, (lon0, lat0, h0), (h_lo, h_hi) = _scene_centre(dem)

    if preset == "frame":
        left_model, right_model = frame_pair(lon0, lat0, h0, (w, h))
    elif preset == "aster":
        # the real granule's pointing, IFOV, orbit height and line timing, flown over the DEM
        p = aster_geometry_parameters()
        b = p["bands"]
        left_model, right_model = pushbroom_pair(
            lon0,
            lat0,
            h0,
            (w, h),
            (b["3N"]["along_deg"], b["3B"]["along_deg"]),
            gsd=p["gsd_m"],
            altitude=p["altitude_m"],
            line_period=p["line_period_s"],
            cross_track_tilt_deg=-p["cross_track_right_deg"],
            right_size=rsize,
        )
    else:
        left_model, right_model = pushbroom_pair(
            lon0, lat0, h0, (w, h), tuple(angles), right_size=rsize
        )

    _check_footprints_on_dem([left_model, right_model], dem, (h_lo, h_hi), (w, h), rsize)
    gsd = left_model.gsd(h0)
    diags = {}
    g = _ground_fields(
        [left_model, right_model],
        dem,
        lon0,
        lat0,
        (h_lo, h_hi),
        gsd,
        texture,
        rng,
        sigma_psf,
        bits,
        diags,
    )
    images = []
    right_true = right_model
    for axis, spec in (("pitch", jitter), ("roll", roll_jitter)):
        if spec is None:
            continue

        amp_urad, freq = _check_jitter(axis, spec)
        phase = float(rng.uniform(0, 2 * np.pi))
        right_true = with_attitude_sines(
            right_true,
            SineSeries(np.array([amp_urad * 1e-6]), np.array([freq]), np.array([phase])),
            axis=axis,
        )
        key = "right_jitter" if axis == "pitch" else "right_roll_jitter"
        diags[key] = dict(axis=axis, amplitude_urad=amp_urad, frequency_hz=freq, phase_rad=phase)
    for name, m in (("left", left_model), ("right", right_true)):
        # an oscillating attitude bends the rays between coarse-grid rows: a finer grid there
        jittered = name == "right" and right_true is not right_model
        images.append(
            _render_view(
                m, name, g, min(step, 8) if jittered else step, noise, bits, rng, seed, diags
            )
        )
    field, truth, transform, shape, crs = g.field, g.truth, g.transform, g.shape, g.crs
    # the field bilinear at the truth cell centres: each is the centre of 2 x 2 fine cells,
    # where bilinear interpolation is their mean, i.e. an exact 2:1 area reduction
    truth_ortho = cv2.resize(field, (shape[1], shape[0]), interpolation=cv2.INTER_AREA)
    truth_dem = DEM(truth, transform, crs, ELLIPSOID, None)
    points = _check_points(left_model, right_true, truth_dem, n_points, rng)
    settings = dict(
        preset=preset,
        size=[w, h],
        right_size=list(rsize),
        noise=noise,
        seed=seed,
        bits=bits,
        mtf_nyquist=mtf_nyquist,
        psf_sigma_gsd=sigma_psf,
        gsd=gsd,
        center_lon=lon0,
        center_lat=lat0,
        angles=list(angles) if preset == "pushbroom" else None,
        jitter=None if jitter is None else [float(x) for x in jitter],
        roll_jitter=None if roll_jitter is None else [float(x) for x in roll_jitter],
        dem=str(dem.path),
        texture=str(texture or texture_path()),
    )
    return Scene(
        images[0],
        images[1],
        left_model,
        right_model,
        truth_dem,
        truth_ortho.astype(np.float32),
        points,
        preset,
        settings,
        diags,
    )


@dataclass
class ViewsScene:
    """A simulated scene seen by N images (:func:`simulate_views`): images, their exact
    models, the truth DEM (ellipsoidal heights, UTM) and the true orthoimage."""

    images: list
    models: list
    truth_dem: DEM
    truth_ortho: np.ndarray
    preset: str
    settings: dict = field(default_factory=dict)
    diagnostics: dict = field(default_factory=dict)


def simulate_views(
    preset: str = "pushbroom",
    *,
    angles=(15.0, 0.0, -15.0),
    size=(300, 300),
    dem=None,
    texture=None,
    noise: float = 1.0,
    seed: int = 0,
    bits: int = 8,
    step: int = 16,
    mtf_nyquist: float = MTF_NYQUIST,
    gsd: float = 15.0,
) -> ViewsScene:
    """N images of one scene (a triplet by default), all on one orbit, one per along-track
    viewing angle in ``angles`` (degrees, positive forward), every image centred on the scene
    centre; ground, radiance and rendering as :func:`simulate_scene`.

    ``preset``: ``"pushbroom"`` (:meth:`PushbroomModel.synthetic_pair` from the first view to
    each other one: one orbit, later acquisitions for views looking further back) or
    ``"frame"`` (frame cameras along one orbit at ``altitude x tan(angle)`` from the point
    above the centre, aimed at it). ``gsd`` in metres.
    """
    if preset not in ("pushbroom", "frame"):
        raise InputError(f"simulate_views: unknown preset {preset!r} (pushbroom or frame)")
    angles = [float(a) for a in angles]
    if len(angles) < 2:
        raise InputError(f"simulate_views needs at least two view angles, got {angles}")
    sigma_psf = psf_sigma(mtf_nyquist)
    noise = check_noise(noise, bits)
    w, h = _size_pair(size, "size")
    if min(w, h) < 32:
        raise InputError(f"image size {w}x{h} is too small (at least 32x32)")
    _check_image_memory([(w, h)] * len(angles), f"{len(angles)} simulated views of {w}x{h} px")
    rng = generator(seed)
    dem, (lon0, lat0, h0), (h_lo, h_hi) = _scene_centre(dem)
    altitude = 705e3
    if preset == "pushbroom":
        # the first view's orbit depends on its angle only: one orbit for every pair
        pairs = [
            pushbroom_pair(lon0, lat0, h0, (w, h), (angles[0], a), gsd=gsd, altitude=altitude)
            for a in angles[1:]
        ]
        models = [pairs[0][0]] + [p[1] for p in pairs]
    else:
        pitch = 0.0074
        focal = pitch * altitude / gsd
        models = []
        for a in angles:
            r, v = _orbit_state(lon0, lat0, altitude, altitude * np.tan(np.radians(a)) / 1e3, -12.0)
            models.append(
                FrameCamera.looking_at(
                    r, v, lon0, lat0, h0, width=w, height=h, focal_mm=focal, pitch_mm=pitch
                )
            )
    diags = {}
    g = _ground_fields(
        models,
        dem,
        lon0,
        lat0,
        (h_lo, h_hi),
        models[0].gsd(h0),
        texture,
        rng,
        sigma_psf,
        bits,
        diags,
    )
    images = [
        _render_view(m, f"view{k}", g, step, noise, bits, rng, seed, diags)
        for k, m in enumerate(models)
    ]
    truth_ortho = cv2.resize(g.field, (g.shape[1], g.shape[0]), interpolation=cv2.INTER_AREA)
    settings = dict(
        preset=preset,
        angles=angles,
        size=[w, h],
        noise=noise,
        seed=seed,
        bits=bits,
        mtf_nyquist=mtf_nyquist,
        gsd=gsd,
        center_lon=lon0,
        center_lat=lat0,
        dem=str(dem.path),
        texture=str(texture or texture_path()),
    )
    return ViewsScene(
        images,
        models,
        DEM(g.truth, g.transform, g.crs, ELLIPSOID, None),
        truth_ortho.astype(np.float32),
        preset,
        settings,
        diags,
    )


def _check_points(left, right, dem, n, rng):
    """Random left pixels localised exactly on the DEM, with right-image coordinates."""
    m = 4 * n
    c = rng.uniform(5, left.width - 6, m)
    r = rng.uniform(5, left.height - 6, m)
    loc = left.localize_dem(c, r, dem, threshold=0.001)
    # pixels whose ray leaves the DEM (a --dem that just covers the scene) localise to NaN,
    # which project() refuses: project the others only
    fin = np.isfinite(loc.lon) & np.isfinite(loc.lat) & np.isfinite(loc.h)
    cr, rr = np.full(m, np.nan), np.full(m, np.nan)
    cr[fin], rr[fin] = right.project(loc.lon[fin], loc.lat[fin], loc.h[fin])
    ok = (
        loc.converged
        & np.isfinite(cr)
        & (cr > 5)
        & (cr < right.width - 6)
        & (rr > 5)
        & (rr < right.height - 6)
    )
    idx = np.flatnonzero(ok)[:n]
    pts = []
    for k, i in enumerate(idx):
        pts.append(
            dict(
                id=f"P{k + 1:03d}",
                lon=loc.lon[i],
                lat=loc.lat[i],
                h=loc.h[i],
                col=c[i],
                row=r[i],
                col_right=cr[i],
                row_right=rr[i],
                role="gcp" if k % 2 == 0 else "check",
            )
        )
    return pts


def points_csv(points) -> str:
    """The check points as CSV text: id, lon, lat, h (ellipsoidal), col, row, right, role."""
    buf = io.StringIO()
    fields = ["id", "lon", "lat", "h", "col", "row", "col_right", "row_right", "role"]
    wr = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    wr.writeheader()
    for p in points:
        wr.writerow(
            {
                k: (
                    f"{v:.9f}" if k in ("lon", "lat") else f"{v:.4f}" if isinstance(v, float) else v
                )
                for k, v in p.items()
            }
        )
    return buf.getvalue()


def write_scene(
    scene: Scene,
    out_dir,
    *,
    overwrite: bool = False,
    fit_rpcs: bool = True,
    write_images: bool = True,
):
    """Write a scene under fixed names in ``out_dir``.

    ``left.tif``/``right.tif`` (images with fitted RPC metadata and ``<name>.model.json``
    sidecars holding the exact physical model), ``truth_dem.tif`` (ellipsoidal heights, UTM),
    ``truth_ortho.tif`` (the left image's true orthoimage on the same grid), ``points.csv``
    and ``scene.json`` (settings, diagnostics, RPC fit residuals). ``write_images=False``
    leaves out the images and their models (a granule writer stores them instead).
    """
    out = prepare_output_dir(out_dir, overwrite=overwrite)
    meta = dict(settings=scene.settings, diagnostics=dict(scene.diagnostics), rpc_fit={})
    pairs = (("left", scene.left, scene.left_model), ("right", scene.right, scene.right_model))
    for name, img, model in pairs if write_images else ():
        rpcs = None
        if fit_rpcs:
            lo, hi = scene.truth_dem.height_range()
            rpc, report = fit_rpc(model, height_range=(lo - 500.0, hi + 500.0))
            rpcs = rpc.to_rasterio()
            meta["rpc_fit"][name] = report.to_dict()
        write_geotiff(
            out / f"{name}.tif",
            img,
            None,
            None,
            None,
            overwrite=overwrite,
            rpcs=rpcs,
            tags={"STEREODEM_MODEL": f"{name}.model.json"},
        )
        save_model(model, out / f"{name}.model.json", overwrite=overwrite)
    scene.truth_dem.write(out / "truth_dem.tif", overwrite=overwrite, creation_options=TRUTH_CO)
    write_geotiff(
        out / "truth_ortho.tif",
        scene.truth_ortho,
        scene.truth_dem.transform,
        scene.truth_dem.crs,
        np.nan,
        overwrite=overwrite,
        creation_options=TRUTH_CO,
    )
    write_text_atomic(out / "points.csv", points_csv(scene.points), overwrite=overwrite)
    write_text_atomic(
        out / "scene.json", jsonutil.dumps(jsonutil.stamped(meta), indent=2), overwrite=overwrite
    )
    return out
