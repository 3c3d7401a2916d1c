"""Benchmark: stereodem's DRM orthorectification vs GDAL's RPC orthorectification.

Both orthorectify the same image (a real Pleiades RPC from ``tests/data/pleiades``; the image is
a synthetic texture of ``--size`` pixels inside that RPC's domain, or the real 1024 x 1024
Pleiades crop with ``--real``) onto the same UTM grid (0.5 m) over the same ellipsoidal DEM
GeoTIFF, bilinear resampling, in one run:

* stereodem: :func:`stereodem.ortho.drm.orthorectify` (coarse lattice of exact projections, measured
  interpolation error <= 0.01 px, float32 maps, cv2.remap), with 1 and 2 threads;
* GDAL: ``rasterio.warp.reproject(..., rpcs=..., RPC_DEM=...)`` with its default approximate
  transformer (error threshold 0.125 px) at one and two threads (``num_threads``, GDAL's
  multithreaded warper, ``warp_mem_limit=512`` MB), and the exact transformer
  (``tolerance=0``), one thread.

The ratios reported are stereodem 1 thread vs GDAL 1 thread and stereodem 2 threads vs GDAL 2
threads (same kernel, grid, DEM and image).

Agreement is reported as the least-squares sub-pixel shift between the orthos and the largest
difference of projected positions at sampled cells. Figures go to
``benchmarks/results/bench_ortho.json``.

Run: ``python benchmarks/bench_ortho.py [--size 4096] [--repeat 3] [--real]``
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import rasterio
from affine import Affine
from rasterio.transform import RPCTransformer
from rasterio.warp import Resampling, reproject

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stereodem.core.dem import DEM  # noqa: E402
from stereodem.core.jsonutil import dumps as strict_json
from stereodem.ortho.drm import orthorectify  # noqa: E402
from stereodem.ortho.grid import grid_for_model  # noqa: E402
from stereodem.sensor.models.rpc import RPCModel  # noqa: E402

RPC_FILE = ROOT / "tests" / "data" / "pleiades" / "img_01_rpc.tif"
REAL_IMAGE = ROOT.parent / "shared" / "data" / "s2p_pleiades" / "pair" / "img_01.tif"


def ls_shift(a, ref):
    gy, gx = np.gradient(np.asarray(ref, np.float64))
    m = np.isfinite(a) & np.isfinite(gx) & np.isfinite(gy)
    A = np.stack([gx[m], gy[m]], 1)
    d, *_ = np.linalg.lstsq(A, (a - ref)[m], rcond=None)
    return d


def best_time(fn, repeat):
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return min(times), out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=4096, help="synthetic image size (pixels, square)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--real", action="store_true", help="use the real 1024x1024 Pleiades crop")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "bench_ortho.json"))
    args = ap.parse_args(argv)

    with rasterio.open(RPC_FILE) as ds:
        rpcs = ds.rpcs
    if args.real and REAL_IMAGE.exists():
        with rasterio.open(REAL_IMAGE) as ds:
            img, rpcs = ds.read(1).astype(np.float32), ds.rpcs
        model = RPCModel.from_rasterio(rpcs, width=img.shape[1], height=img.shape[0])
        source = str(REAL_IMAGE.name)
    else:
        n = args.size
        model = RPCModel.from_rasterio(rpcs, width=n, height=n)
        rng = np.random.default_rng(0)
        cc, rr = np.meshgrid(np.arange(n, dtype=np.float32), np.arange(n, dtype=np.float32))
        img = np.zeros((n, n), np.float32)
        for _ in range(8):
            lam, th = rng.uniform(8, 30), rng.uniform(0, 2 * np.pi)
            img += np.cos(
                2 * np.pi * (cc * np.cos(th) + rr * np.sin(th)) / lam + rng.uniform(0, 6.3)
            ).astype(np.float32)
        img = 1000 + 100 * img
        del cc, rr
        source = f"synthetic {n}x{n} texture"

    tmp = Path(tempfile.mkdtemp(prefix="bench_ortho_"))
    lon, lat = model.footprint(2300.0)
    w, s, e, nn = lon.min() - 0.003, lat.min() - 0.003, lon.max() + 0.003, lat.max() + 0.003
    st = 5e-5
    tr = Affine(st, 0, w, 0, -st, nn)
    nx, ny = int((e - w) / st), int((nn - s) / st)
    X, Y = tr @ np.meshgrid(np.arange(nx) + 0.5, np.arange(ny) + 0.5)
    Z = 2300 + 60 * np.sin((X - w) / 0.0015) * np.cos((Y - s) / 0.002) + 30 * (X - w) / (e - w)
    dem_path = tmp / "dem.tif"
    DEM(Z.astype(np.float32), tr, "EPSG:4326", "ellipsoid").write(dem_path)
    dem = DEM.from_file(dem_path)
    grid = grid_for_model(model, dem, res=0.5)
    cells = grid.width * grid.height
    print(
        f"{source}; grid {grid.width} x {grid.height} = {cells / 1e6:.1f} M cells at 0.5 m "
        f"({grid.crs.to_string()}); DEM {nx} x {ny} at {st} deg"
    )

    results = {}
    o = None
    for threads in (1, 2):
        t_me, o = best_time(
            lambda: orthorectify(
                img,
                model,
                dem,
                grid=grid,
                resampling="bilinear",
                threads=threads,  # noqa: B023
            ),
            args.repeat,
        )
        results[f"stereodem_{threads}thread{'s' if threads > 1 else ''}"] = dict(
            seconds=t_me,
            mcells_per_s=cells / t_me / 1e6,
            threads=threads,
            **{
                k: v
                for k, v in o.report().items()
                if k in ("interpolation_error_px", "lattice_step", "n_heights", "n_model_points")
            },
        )
    o = orthorectify(img, model, dem, grid=grid, resampling="bilinear", keep_maps=True)

    def gdal(tol, threads):
        dst = np.full(grid.shape, np.nan, np.float32)
        reproject(
            img,
            dst,
            rpcs=rpcs,
            src_crs="EPSG:4326",
            dst_crs=grid.crs,
            dst_transform=grid.transform,
            resampling=Resampling.bilinear,
            dst_nodata=np.nan,
            RPC_DEM=str(dem_path),
            tolerance=tol,
            num_threads=threads,
            warp_mem_limit=512,
        )
        return dst

    # GDAL's best options for this job: the approximate transformer (its default, error
    # threshold 0.125 px), bilinear kernel, the same DEM file, a 512 MB warp buffer, the
    # multithreaded warper at 1 and 2 threads; plus the exact transformer for reference
    refs = {}
    mine = {1: results["stereodem_1thread"]["seconds"], 2: results["stereodem_2threads"]["seconds"]}
    for name, tol, threads in (
        ("gdal_approx_0.125px_1thread", 0.125, 1),
        ("gdal_approx_0.125px_2threads", 0.125, 2),
        ("gdal_exact_1thread", 0.0, 1),
    ):
        t, ref = best_time(lambda: gdal(tol, threads), args.repeat)  # noqa: B023 (called at once)
        both = o.valid & np.isfinite(ref)
        d = ls_shift(np.where(both, o.data, np.nan), np.where(both, ref, np.nan))
        results[name] = dict(
            seconds=t,
            mcells_per_s=cells / t / 1e6,
            threads=threads,
            speedup_of_stereodem_same_threads=t / mine[threads],
            speedup_of_stereodem_1thread=t / mine[1],
            speedup_of_stereodem_2threads=t / mine[2],
            ortho_shift_px=[float(d[0]), float(d[1])],
            common_valid_fraction=float(both.mean()),
        )
        refs[name] = ref

    vv, uu = np.mgrid[0 : grid.height : 53, 0 : grid.width : 59]
    glon, glat = grid.lonlat(uu, vv)
    with RPCTransformer(rpcs, RPC_DEM=str(dem_path)) as t:
        r, c = t.rowcol(glon.ravel(), glat.ravel(), op=lambda v: v)
    dc = np.array(c) - 0.5 - o.col[vv, uu].ravel()
    dr = np.array(r) - 0.5 - o.row[vv, uu].ravel()
    inside = np.isfinite(dc) & np.isfinite(dr) & o.valid[vv, uu].ravel()
    pos = float(np.max(np.hypot(dc[inside], dr[inside])))

    g1 = results["gdal_approx_0.125px_1thread"]["seconds"]
    g2 = results["gdal_approx_0.125px_2threads"]["seconds"]
    ratios = {
        "stereodem_1thread_vs_gdal_1thread": g1 / mine[1],
        "stereodem_2threads_vs_gdal_2threads": g2 / mine[2],
        "stereodem_best_vs_gdal_best": min(g1, g2) / min(mine.values()),
    }
    summary = dict(
        source=source,
        grid=[grid.width, grid.height],
        cells=cells,
        res_m=0.5,
        crs=grid.crs.to_string(),
        dem=[nx, ny],
        repeat=args.repeat,
        gdal_options=dict(
            resampling="bilinear",
            RPC_DEM=True,
            approximate_transformer_error_px=0.125,
            warp_mem_limit_mb=512,
            num_threads=[1, 2],
            dst_nodata="nan",
        ),
        max_position_difference_vs_gdal_rpc_transformer_px=pos,
        speed_ratios=ratios,
        machine=dict(
            python=platform.python_version(),
            cpus=os.cpu_count(),
            gdal=rasterio.__gdal_version__,
            rasterio=rasterio.__version__,
            loadavg_at_end=list(os.getloadavg()),
        ),
        results=results,
    )
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(strict_json(summary, indent=2))
    print(f"{'method':<32}{'seconds':>9}{'Mcells/s':>10}{'stereodem x (same threads)':>28}")
    for k, v in results.items():
        print(
            f"{k:<32}{v['seconds']:9.3f}{v['mcells_per_s']:10.2f}"
            f"{v.get('speedup_of_stereodem_same_threads', 1.0):28.2f}"
        )
    print("ratios: " + ", ".join(f"{k} {v:.2f}x" for k, v in ratios.items()))
    print(
        "stereodem map interpolation error (measured): "
        f"{results['stereodem_1thread']['interpolation_error_px']:.2e} px; max position difference "
        f"vs GDAL RPC transformer: {pos:.2e} px; ortho shift vs exact GDAL: "
        f"{results['gdal_exact_1thread']['ortho_shift_px']}"
    )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
