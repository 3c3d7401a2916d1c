"""Benchmark: ``stereodem mosaic`` of 50 overlapping simulated DEMs — memory bound, seams,
time per DEM — against ``rasterio.merge`` and a naive full-array blend, in the same run.

Inputs: the bundled real SRTM 3" tile (``sensor/data/srtm_ref.tif``, eastern Turkey, EGM96)
warped to UTM 37N at ``--res`` m (cubic) is the truth. ``--n`` DEMs are cut from it on a
jittered 5-column layout with ~35 % / ~60 % overlaps (east-west / north-south), each with its
own bias (N(0, 1.5 m)), tilt (up to 1 cm/km... 2 cm/km), white noise (0.3 m) and two
elliptical voids; every fifth DEM is resampled a third of a cell off the lattice (those go
through GDAL's warper, the rest are copied), written as float32 COGs.

Runs, each in its own process (peak resident memory from ``VmHWM`` with the high-water mark
reset after the imports and a warm-up of the same job on a 64 x 64-cell window, so that the
libraries' first-use memory (GDAL drivers, PROJ database) is left out like the interpreter and
the figure is what the mosaic itself adds):

* ``stereodem mosaic --method blend`` (block 512 and 256), on all DEMs and on the first half
  (half the mosaic's area: the memory must not follow the area), ``--method first`` (for the
  seam figure) and ``--method median``;
* peer ``rasterio.merge.merge(method="first")`` (the whole mosaic in memory);
* a naive full-array blend (the same distance weights, full-size float64 sums).

The peers write a plain DEFLATE GeoTIFF; stereodem writes the project's COG (predictor,
overviews), whose final copy is timed apart (``seconds_cog_finish``).

Seams: the error (mosaic − truth) differences between neighbouring cells where the set of DEMs
covering them changes (``count`` differs: footprint edges) against all other neighbours; a
visible seam has a much larger median |step| than the interior. Figure: hillshades of ``first`` and
``blend`` around seams, axes in km with a scale bar.

Run: ``python benchmarks/bench_mosaic.py [--res 20] [--n 50]`` (writes
``benchmarks/results/bench_mosaic.json`` and ``bench_mosaic.png``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import rasterio
from affine import Affine
from rasterio.windows import Window

from stereodem.core.jsonutil import dumps as strict_json

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
UTM = "EPSG:32637"


# ----------------------------------------------------------------------------- inputs


def truth_grid(res: float):
    """SRTM warped to UTM 37N at ``res`` m: (heights float32, transform)."""
    from importlib import resources

    from rasterio.warp import Resampling, calculate_default_transform, reproject

    src = resources.files("stereodem.core") / "data" / "srtm_ref.tif"
    with rasterio.open(src) as ds:
        t, w, h = calculate_default_transform(
            ds.crs, UTM, ds.width, ds.height, *ds.bounds, resolution=res
        )
        t = Affine(res, 0, np.floor(t.c / res) * res, 0, -res, np.ceil(t.f / res) * res)
        z = np.full((h, w), np.nan, np.float32)
        reproject(
            rasterio.band(ds, 1),
            z,
            dst_transform=t,
            dst_crs=UTM,
            dst_nodata=np.nan,
            resampling=Resampling.cubic,
        )
    return z, t


def make_inputs(folder: Path, res: float, n: int, seed: int = 0):
    from scipy.ndimage import map_coordinates

    from stereodem.core.raster import write_geotiff

    rng = np.random.default_rng(seed)
    truth, t = truth_grid(res)
    write_geotiff(folder / "truth.tif", truth, t, UTM, np.nan, vertical="geoid")
    H, W = truth.shape
    filled = np.where(np.isfinite(truth), truth, np.nanmean(truth)).astype(np.float64)
    ncol = 5
    nrow = int(np.ceil(n / ncol))
    dw, dh = int(W / ncol * 1.35), int(H / nrow * 1.6)
    paths, layout = [], []
    for k in range(n):
        i, j = divmod(k, ncol)
        r0 = int(np.clip(i * H / nrow - 0.3 * dh / 1.6 + rng.integers(-40, 41), 0, H - dh))
        c0 = int(np.clip(j * W / ncol - 0.175 * dw / 1.35 + rng.integers(-40, 41), 0, W - dw))
        off = (1 / 3, 1 / 3) if k % 5 == 4 else (0.0, 0.0)
        rr, cc = np.mgrid[r0 : r0 + dh, c0 : c0 + dw].astype(np.float64)
        if off[0]:
            # the cubic spline's prefilter spreads NaN over the whole array: interpolate a
            # filled copy, then put the truth's voids (its border) back
            z = map_coordinates(filled, [rr + off[0], cc + off[1]], order=3, mode="nearest")
            z[
                ~np.isfinite(
                    map_coordinates(truth, [rr + off[0], cc + off[1]], order=0, cval=np.nan)
                )
            ] = np.nan
        else:
            z = truth[r0 : r0 + dh, c0 : c0 + dw].astype(np.float64)
        bias = rng.normal(0, 1.5)
        tilt = rng.uniform(-2e-5, 2e-5, 2)  # m per m (up to 2 cm/km)
        z = z + bias + tilt[0] * (cc - cc.mean()) * res + tilt[1] * (rr - rr.mean()) * res
        z += rng.normal(0, 0.3, z.shape)
        for _ in range(2):  # voids (clouds, shadows)
            cy, cx = rng.uniform(0.2, 0.8, 2) * (dh, dw)
            ay, ax = rng.uniform(10, 40, 2)
            z[((rr - r0 - cy) / ay) ** 2 + ((cc - c0 - cx) / ax) ** 2 < 1] = np.nan
        tk = t @ Affine.translation(c0 + off[1], r0 + off[0])
        p = folder / f"dem_{k:02d}.tif"
        write_geotiff(p, z.astype(np.float32), tk, UTM, np.nan, vertical="geoid")
        paths.append(str(p))
        layout.append(
            dict(
                path=p.name,
                row0=r0,
                col0=c0,
                rows=dh,
                cols=dw,
                bias_m=bias,
                off_lattice=bool(off[0]),
            )
        )
    return paths, layout, truth.shape


# ----------------------------------------------------------------------------- children


def _rss_mb(key="VmRSS"):
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith(key)) / 1024.0


def child(kind: str, paths, out: str, extra):
    """One measured run in this (fresh) process; prints a JSON line."""
    import cv2  # noqa: F401  (imported before the baseline, as the mosaic imports it)
    import rasterio.merge

    from stereodem.cli import main
    from stereodem.post import mosaic  # noqa: F401
    from stereodem.stereo.runner import process_peak_rss_mb, reset_peak_rss

    warm_up(kind, paths, out, main)
    base = _rss_mb()
    reset_peak_rss()
    t0 = time.perf_counter()
    c0 = time.process_time()
    if kind == "stereodem":
        rc = main(["-q", "mosaic", *paths, "-o", out, *extra])
        assert rc == 0, rc
    elif kind == "rasterio_merge":
        arr, t = rasterio.merge.merge(paths, method="first", nodata=np.nan)
        with rasterio.open(paths[0]) as ds:
            prof = dict(
                driver="GTiff",
                width=arr.shape[2],
                height=arr.shape[1],
                count=1,
                dtype="float32",
                crs=ds.crs,
                transform=t,
                nodata=np.nan,
                tiled=True,
                compress="deflate",
            )
        with rasterio.open(out, "w", **prof) as dst:
            dst.write(arr.astype(np.float32))
    elif kind == "naive_blend":
        naive_blend(paths, out, int(extra[0]))
    wall = time.perf_counter() - t0
    print(
        json.dumps(
            dict(
                kind=kind,
                extra=extra,
                wall_s=wall,
                cpu_s=time.process_time() - c0,
                baseline_rss_mb=base,
                peak_rss_mb=process_peak_rss_mb(),
                peak_above_baseline_mb=process_peak_rss_mb() - base,
            )
        )
    )


def warm_up(kind, paths, out, main):
    """The same kind of job on a 64 x 64-cell window of the first two DEMs, before the
    baseline: GDAL's drivers, PROJ's database, the CLI's modules and the thread pools are then
    loaded (libraries, which the memory bound leaves out, as it does the interpreter), while
    the window is too small to leave caches or heap of any size behind."""
    with rasterio.open(paths[0]) as ds:
        t = ds.transform
        x0, y0 = t.c + ds.width / 2 * t.a, t.f + ds.height / 2 * t.e
    w, s, e, n = x0, y0 + 64 * t.e, x0 + 64 * t.a, y0
    tiny = str(Path(out).with_name(Path(out).stem + "_warm_up.tif"))
    if kind == "stereodem":
        rc = main(["-q", "mosaic", *paths[:2], "-o", tiny, "--bounds", *map(str, (w, s, e, n))])
        assert rc == 0, rc
    elif kind == "rasterio_merge":
        rasterio.merge.merge(paths[:2], bounds=(w, s, e, n), method="first", nodata=np.nan)
    elif kind == "naive_blend":
        with rasterio.open(paths[0]) as ds:
            ds.read(1, window=Window(0, 0, 64, 64))


def naive_blend(paths, out, length):
    """Distance-to-edge blend with full-mosaic float64 sums (what a straightforward
    implementation holds): each DEM read whole, warped into its window of the full grid."""
    import cv2
    from rasterio.warp import Resampling, reproject
    from rasterio.windows import from_bounds

    bounds = []
    for p in paths:
        with rasterio.open(p) as ds:
            bounds.append(ds.bounds)
            if p == paths[0]:
                crs, t0 = ds.crs, ds.transform
    b = np.array(bounds)
    res = t0.a
    ox, oy = t0.c % res, t0.f % res  # the first DEM's lattice, as stereodem's
    w0 = ox + np.floor((b[:, 0].min() - ox) / res) * res
    n1 = oy + np.ceil((b[:, 3].max() - oy) / res) * res
    W = int(np.ceil((b[:, 2].max() - w0) / res))
    H = int(np.ceil((n1 - b[:, 1].min()) / res))
    t = Affine(res, 0, w0, 0, -res, n1)
    sw = np.zeros((H, W))
    swz = np.zeros((H, W))
    for p in paths:
        with rasterio.open(p) as ds:
            win = from_bounds(*ds.bounds, transform=t)
            r0, c0 = int(np.floor(win.row_off)), int(np.floor(win.col_off))
            r1, c1 = (
                min(int(np.ceil(win.row_off + win.height)), H),
                min(int(np.ceil(win.col_off + win.width)), W),
            )
            z = np.full((r1 - r0, c1 - c0), np.nan, np.float32)
            reproject(
                rasterio.band(ds, 1),
                z,
                dst_transform=t @ Affine.translation(c0, r0),
                dst_crs=crs,
                dst_nodata=np.nan,
                src_nodata=np.nan,
                resampling=Resampling.bilinear,
            )
        v = np.isfinite(z)
        # the DEM's own edge is an edge (cv2 ignores the array border: pad with void), except
        # where it lies on the mosaic's outer border (stereodem's convention)
        pad = (int(r0 > 0), int(r1 < H), int(c0 > 0), int(c1 < W))
        d = cv2.distanceTransform(
            np.pad(v, ((pad[0], pad[1]), (pad[2], pad[3]))).astype(np.uint8),
            cv2.DIST_L2,
            cv2.DIST_MASK_PRECISE,
        )
        d = d[pad[0] : d.shape[0] - pad[1], pad[2] : d.shape[1] - pad[3]]
        w = np.minimum(d, length).astype(np.float64) ** 2
        sw[r0:r1, c0:c1] += w
        swz[r0:r1, c0:c1] += np.where(v, w * np.nan_to_num(z), 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        m = np.where(sw > 0, swz / sw, np.nan).astype(np.float32)
    with rasterio.open(
        out,
        "w",
        driver="GTiff",
        width=W,
        height=H,
        count=1,
        dtype="float32",
        crs=crs,
        transform=t,
        nodata=np.nan,
        tiled=True,
        compress="deflate",
    ) as dst:
        dst.write(m, 1)


def run_child(kind, paths, out, extra=()):
    listing = Path(out).with_suffix(".paths")
    listing.write_text("\n".join(paths))
    cmd = [
        sys.executable,
        __file__,
        "--child",
        kind,
        "--paths",
        str(listing),
        "--out",
        str(out),
        "--extra",
        json.dumps(list(extra)),
    ]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)
    if p.returncode:
        raise RuntimeError(f"{kind} {extra}: {p.stderr[-2000:]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


# ----------------------------------------------------------------------------- evaluation


def on_truth(path, truth, t_truth, band=1):
    """A mosaic band on the truth's lattice (they share it: the first DEM's lattice)."""
    with rasterio.open(path) as ds:
        a = ds.read(band)
        t = ds.transform
    out = np.full(truth.shape, np.nan, np.float32)
    c0 = int(round((t.c - t_truth.c) / t_truth.a))
    r0 = int(round((t.f - t_truth.f) / t_truth.e))
    rs, cs = max(r0, 0), max(c0, 0)
    re_, ce = min(r0 + a.shape[0], truth.shape[0]), min(c0 + a.shape[1], truth.shape[1])
    out[rs:re_, cs:ce] = a[rs - r0 : re_ - r0, cs - c0 : ce - c0]
    return out


def seam_figures(err, count):
    """Error steps between neighbouring cells (m) across footprint edges (``count`` changes)
    and elsewhere: median |step| (robust: a seam is a consistent offset between two DEMs,
    while steep terrain makes rare large steps everywhere) and RMS, and the median ratio."""
    steps_seam, steps_in = [], []
    for ax in (0, 1):
        de = np.diff(err, axis=ax)
        seam = np.diff(count, axis=ax) != 0
        ok = np.isfinite(de)
        steps_seam.append(de[ok & seam])
        steps_in.append(de[ok & ~seam])
    s, i = np.abs(np.concatenate(steps_seam)), np.abs(np.concatenate(steps_in))
    ms, mi = float(np.median(s)), float(np.median(i))
    return dict(
        median_abs_step_at_seams_m=ms,
        median_abs_step_elsewhere_m=mi,
        ratio=ms / mi,
        rms_step_at_seams_m=float(np.sqrt(np.mean(s**2))),
        rms_step_elsewhere_m=float(np.sqrt(np.mean(i**2))),
        n_seam_pairs=int(s.size),
    )


def figure(first, blend, truth, t, layout, path):
    """Hillshades (top) and errors against the truth (bottom) of ``first`` and ``blend`` around
    a corner where several footprints meet; axes in km with a scale bar."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from stereodem.core.mapaxes import map_axes
    from stereodem.post import terrain

    L = layout[7]
    r0, c0 = max(L["row0"] - 150, 0), max(L["col0"] - 150, 0)
    win = (slice(r0, r0 + 500), slice(c0, c0 + 500))
    tw = t @ Affine.translation(c0, r0)
    fig, axes = plt.subplots(2, 2, figsize=(12, 11.5))
    for col, (z, name) in enumerate(
        ((first[win], "--method first"), (blend[win], "--method blend (default)"))
    ):
        ax = axes[0, col]
        hs = terrain.hillshade(z.astype(np.float64), tw, UTM, z_factor=3.0)
        extent = map_axes(ax, tw, UTM, z.shape)
        ax.imshow(hs, extent=extent, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        ax.set_title(f"stereodem mosaic {name}: hillshade (z × 3)", fontsize=10)
        ax = axes[1, col]
        extent = map_axes(ax, tw, UTM, z.shape)
        im = ax.imshow(
            z - truth[win], extent=extent, cmap="RdBu_r", vmin=-3, vmax=3, interpolation="nearest"
        )
        ax.set_title(f"{name}: mosaic − truth (m, clipped at ±3 m)", fontsize=10)
        fig.colorbar(im, ax=ax, shrink=0.8, label="mosaic − truth (m)")
    fig.suptitle(
        f"{len(layout)} simulated DEMs cut from SRTM (biases σ 1.5 m, tilts, 0.3 m noise, voids): "
        "footprint edges are steps with 'first', ramps with 'blend'",
        fontsize=10,
    )
    fig.savefig(path, dpi=80, bbox_inches="tight")
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--res", type=float, default=20.0)
    ap.add_argument("--n", type=int, default=50)
    ap.add_argument("--keep", help="folder for the inputs and mosaics (default: a temporary one)")
    ap.add_argument("--child")
    ap.add_argument("--paths")
    ap.add_argument("--out")
    ap.add_argument("--extra", default="[]")
    a = ap.parse_args(argv)
    if a.child:
        return child(a.child, Path(a.paths).read_text().split("\n"), a.out, json.loads(a.extra))
    load0 = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="bench_mosaic_", dir=a.keep) as tmp:
        d = Path(tmp)
        t0 = time.perf_counter()
        paths, layout, shape = make_inputs(d, a.res, a.n)
        t_inputs = time.perf_counter() - t0
        runs = {}
        specs = [
            ("blend", "stereodem", paths, ["--block", "512"]),
            ("blend_block256", "stereodem", paths, ["--block", "256"]),
            ("blend_half", "stereodem", paths[: len(paths) // 2], ["--block", "512"]),
            ("first", "stereodem", paths, ["--method", "first"]),
            ("median", "stereodem", paths, ["--method", "median"]),
            ("rasterio_merge", "rasterio_merge", paths, []),
            ("naive_blend", "naive_blend", paths, ["50"]),
        ]
        for name, kind, ps, extra in specs:
            out = d / f"{name}.tif"
            r = run_child(kind, ps, str(out), extra)
            if kind == "stereodem":
                rep = json.loads(out.with_suffix(".json").read_text())
                r.update(
                    memory_bound_mb=rep["memory_bound_mb"],
                    max_dems_per_block=rep["max_dems_per_block"],
                    n_dems=rep["n_used"],
                    cells=rep["grid"]["width"] * rep["grid"]["height"],
                    seconds_in_report=rep["seconds"],
                    seconds_cog_finish=rep["seconds_cog"],
                    reprojected=len(rep["reprojected"]),
                )
            else:
                r.update(n_dems=len(ps))
            r["seconds_per_dem"] = r["wall_s"] / len(ps)
            runs[name] = r
            print(name, json.dumps(r), flush=True)
        with rasterio.open(d / "truth.tif") as ds:
            truth, tt = ds.read(1), ds.transform
        acc, seams = {}, {}
        count = on_truth(d / "blend.tif", truth, tt, band=2)
        count[~np.isfinite(count)] = 0
        mosaics = {}
        for name in ("blend", "first", "median", "rasterio_merge", "naive_blend"):
            z = on_truth(d / f"{name}.tif", truth, tt)
            mosaics[name] = z
            e = z - truth
            fin = e[np.isfinite(e)]
            acc[name] = dict(
                nmad_m=float(1.4826 * np.median(np.abs(fin - np.median(fin)))),
                median_m=float(np.median(fin)),
                valid_cells=int(fin.size),
            )
            seams[name] = seam_figures(e, count)
        agree = {}
        for a_, b_ in (("blend", "naive_blend"), ("first", "rasterio_merge")):
            dd = mosaics[a_] - mosaics[b_]
            fin = np.isfinite(dd)
            agree[f"{a_}_vs_{b_}"] = dict(
                max_abs_m=float(np.abs(dd[fin]).max()),
                p99_abs_m=float(np.percentile(np.abs(dd[fin]), 99)),
                share_identical=float((np.abs(dd[fin]) < 1e-4).mean()),
            )
        figure(mosaics["first"], mosaics["blend"], truth, tt, layout, RESULTS / "bench_mosaic.png")
    b = runs["blend"]
    result = dict(
        benchmark="bench_mosaic",
        command="python benchmarks/bench_mosaic.py " + " ".join(argv or sys.argv[1:]),
        machine=dict(
            platform=platform.platform(),
            cpus=os.cpu_count(),
            load_before=load0,
            load_after=os.getloadavg(),
        ),
        inputs=dict(
            n_dems=len(paths),
            res_m=a.res,
            truth_shape=list(shape),
            seconds_to_make=t_inputs,
            off_lattice=sum(x["off_lattice"] for x in layout),
            source='bundled SRTM 3" tile warped to UTM 37N (cubic), per-DEM bias/tilt/noise/voids',
        ),
        runs=runs,
        accuracy_vs_truth=acc,
        seams=seams,
        agreement=agree,
        memory=dict(
            bound_mb=b["memory_bound_mb"],
            peak_above_baseline_mb=b["peak_above_baseline_mb"],
            under_bound=bool(b["peak_above_baseline_mb"] <= b["memory_bound_mb"]),
            half_area_peak_above_baseline_mb=runs["blend_half"]["peak_above_baseline_mb"],
            rasterio_merge_peak_above_baseline_mb=runs["rasterio_merge"]["peak_above_baseline_mb"],
            naive_blend_peak_above_baseline_mb=runs["naive_blend"]["peak_above_baseline_mb"],
        ),
        figure="benchmarks/results/bench_mosaic.png",
    )
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "bench_mosaic.json").write_text(strict_json(result, indent=2))
    print(json.dumps(dict(memory=result["memory"], seams=seams, accuracy=acc), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
