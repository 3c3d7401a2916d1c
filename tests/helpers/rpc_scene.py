"""A stereo pair with real Pleiades crop geometry over steep terrain far from the RPCs'
height offset (test helper).

The two RPCs shipped in tests/data/pleiades (the s2p Pleiades pair, height offset 1 295 m,
validity -20..2 610 m) are moved by one longitude/latitude offset onto the bundled SRTM at
40.383 E, 39.542 N, where the ground lies at 2 250-2 600 m (ellipsoidal) with ~350 m of relief
within 450 m; a 512 x 512 crop of each image is rendered there through its RPC
(stereodem.sensor.simulation.render) from a seeded band-limited texture.
"""

from pathlib import Path

import cv2
import numpy as np
from affine import Affine
from rasterio.warp import Resampling, reproject

from stereodem.core import geodesy
from stereodem.core.dem import DEM, ELLIPSOID
from stereodem.core.grid import MapGrid
from stereodem.sensor.models.rpc import RPCModel
from stereodem.sensor.simulation.render import MapRaster, render

DATA = Path(__file__).resolve().parents[1] / "data"
TARGET = (40.3829, 39.5421)


def moved_rpc(path, dlon, dlat, size):
    d = RPCModel.from_file(path).to_dict()
    d["LONG_OFF"] = str(float(d["LONG_OFF"]) + dlon)
    d["LAT_OFF"] = str(float(d["LAT_OFF"]) + dlat)
    return RPCModel.from_dict(d, width=size, height=size, path=str(path))


def rpc_steep_pair(size=512, seed=0, posting=1.0, texture_res=0.25):
    """Returns ``(left_image, right_image, left_model, right_model, truth)``; ``truth`` is a
    :class:`MapRaster` of the ellipsoidal terrain heights (UTM)."""
    l0 = RPCModel.from_file(DATA / "pleiades" / "img_01_rpc.tif")
    clon, clat = l0.localize((size - 1) / 2, (size - 1) / 2, 2400.0)
    dlon, dlat = TARGET[0] - float(clon), TARGET[1] - float(clat)
    left = moved_rpc(DATA / "pleiades" / "img_01_rpc.tif", dlon, dlat, size)
    right = moved_rpc(DATA / "pleiades" / "img_02_rpc.tif", dlon, dlat, size)
    crs = geodesy.utm_crs(*TARGET)
    xs, ys = [], []
    for m in (left, right):
        for hh in (1800.0, 3000.0):
            lon, lat = m.footprint(hh)
            x, y = geodesy.lonlat_to_crs(lon, lat, crs)
            xs.append(np.asarray(x))
            ys.append(np.asarray(y))
    x0, x1 = np.min(np.concatenate(xs)) - 50, np.max(np.concatenate(xs)) + 50
    y0, y1 = np.min(np.concatenate(ys)) - 50, np.max(np.concatenate(ys)) + 50
    srtm = DEM.bundled()
    # terrain: SRTM (EGM96) -> ellipsoidal heights, cubic onto a 1 m UTM grid

    tr = Affine(posting, 0, x0, 0, -posting, y1)
    shape = (int(np.ceil((y1 - y0) / posting)), int(np.ceil((x1 - x0) / posting)))
    z = np.full(shape, np.nan, np.float32)
    reproject(
        srtm.heights,
        z,
        src_transform=srtm.transform,
        src_crs=srtm.crs.to_wkt(),
        dst_transform=tr,
        dst_crs=crs.to_wkt(),
        resampling=Resampling.cubic,
        src_nodata=np.nan,
        dst_nodata=np.nan,
    )
    cc, rr = np.meshgrid(np.arange(shape[1]) + 0.5, np.arange(shape[0]) + 0.5)
    lon, lat = geodesy.crs_to_lonlat(*(tr @ (cc, rr)), crs)
    z = srtm.convert_heights(lon, lat, z.astype(np.float64), ELLIPSOID).astype(np.float32)
    dem = MapRaster(z, MapGrid(tr, shape[1], shape[0], crs))
    # texture: seeded white noise blurred to the image resolution, plus larger patches
    rng = np.random.default_rng(seed)
    ttr = Affine(texture_res, 0, x0, 0, -texture_res, y1)
    tshape = (int(shape[0] * posting / texture_res), int(shape[1] * posting / texture_res))
    fine = cv2.GaussianBlur(rng.normal(0, 1, tshape).astype(np.float32), (0, 0), 2.0)
    coarse = cv2.GaussianBlur(rng.normal(0, 1, tshape).astype(np.float32), (0, 0), 24.0)
    tex = 1000 + 300 * fine / fine.std() + 200 * coarse / coarse.std()
    radiance = MapRaster(tex.astype(np.float32), MapGrid(ttr, tshape[1], tshape[0], crs))
    images = []
    for m in (left, right):
        img = render(m, dem, radiance, step=16)[0]
        img = img + rng.normal(0, 3.0, img.shape).astype(np.float32)
        images.append(np.clip(np.rint(np.nan_to_num(img, nan=0)), 0, 4095).astype(np.uint16))
    return images[0], images[1], left, right, dem
