"""DEM stacks (issue 27): rates, clouds, volumes against a known truth; granules end to end;
time and memory of a 100-DEM stack.

Three parts (``--part``; default ``real``):

``real``      Five DEMs of the bundled real SRTM tile (a 400 x 400 crop on a 90 m UTM grid)
              over 16 years, each with its own horizontal shift, vertical offset, ramp,
              along-track oscillation (3 m at 5.5 km) and spatially correlated noise (two
              spherical ranges, 200 m and 2 km), a cloud (3600 m cloud top) in one, voids on
              the glacier tongue in four (hypsometric fill), and a known thinning inside a
              glacier-like outline (-2.0 m/yr at the tongue to -0.5 m/yr at the top).
              ``stereodem stack`` (default chain nuth_kaab,deramp:1,along_track, the outline
              excluded from stable terrain and used for volumes) against the truth:
              * the mean rate inside the outline (target: within 0.1 m/yr of the truth);
              * the rate's NMAD on stable terrain against the noise-only limit: the formal
                σ = √sill / √(Σ (t − t̄)²) and the NMAD of rates fitted to truth + noise alone
                (no biases, no cloud; target: within 30 %);
              * the cloud: the rate error inside its footprint (target: no trace, i.e. the same
                dispersion as elsewhere, no outlier);
              * the volume change rate against the truth (target: within 2σ);
              * the same stack with only a vertical shift per DEM (``--chain vshift``), to show
                what the chain removes; and an optional Gaussian-process rate (``--gp``).
``granules``  End to end: ASTER L1A granules simulated at 4 dates (300 x 300 3N, thinning
              inside an outline), ``stereodem dem`` on each, ``stereodem stack`` on the DEMs
              (dates read from the runs' metadata), the rate map against the truth.
``heavy``     100 simulated DEMs of 3000 x 3000 cells (20 m), ``stereodem stack`` on 2 worker
              threads: wall time and peak resident memory of the process (the job's own
              ``ru_maxrss``), with the load average.

    python benchmarks/bench_stack.py --part real [--gp]
    python benchmarks/bench_stack.py --part granules
    python benchmarks/bench_stack.py --part heavy --n 100 --size 3000

Writes (merges into) benchmarks/results/bench_stack.json. Timings are taken on a shared
2-core machine: the load average is recorded with each part.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from stereodem.core.jsonutil import dumps as strict_json

ROOT = Path(__file__).resolve().parents[1]
RESULT = ROOT / "benchmarks" / "results" / "bench_stack.json"
DATES = ["2003-07-10", "2007-08-02", "2011-07-21", "2015-08-14", "2019-07-25"]
HEADING = -12.0


def _stack(argv, env=None) -> dict:
    """Run ``stereodem stack`` in a child process; wall time, peak RSS (MiB) of the largest
    single process (``ru_maxrss`` of the children) and, with psutil, the peak of the sum over the
    job's processes (the build's worker processes included), sampled every 0.5 s; output."""
    import threading

    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-m", "stereodem.cli", "stack", *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    total = {"peak": 0}

    def sample():
        try:
            import psutil
        except ImportError:
            return
        while proc.poll() is None:
            try:
                top = psutil.Process(proc.pid)
                rss = sum(q.memory_info().rss for q in [top, *top.children(recursive=True)])
                total["peak"] = max(total["peak"], rss)
            except psutil.Error:
                pass
            time.sleep(0.5)

    th = threading.Thread(target=sample, daemon=True)
    th.start()
    out, err = proc.communicate()
    th.join()
    wall = time.perf_counter() - t0
    p = subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    if p.returncode:
        raise SystemExit(f"stereodem stack failed: {p.stderr.strip()[-2000:]}")
    return {
        "wall_s": round(wall, 2),
        "peak_rss_mib": round(peak / 1024, 1),
        "peak_total_rss_mib": round(total["peak"] / 2**20, 1) or None,
        "peak_is_this_job": peak > before,
        "stdout": p.stdout.strip(),
    }


def _read(path):
    import rasterio

    with rasterio.open(path) as ds:
        return ds.read(1)


def _georef(path):
    """(transform, crs) of a raster."""
    import rasterio

    with rasterio.open(path) as ds:
        return ds.transform, ds.crs


def _load():
    return [round(v, 2) for v in os.getloadavg()]


def part_real(work: Path, gp: bool) -> dict:
    from stereodem.core.dem import DEM
    from stereodem.core.stats import nmad
    from stereodem.post.rates import fit_rates, noise_limit
    from stereodem.post.spatialstats import VariogramModel
    from stereodem.post.synthetic import InjectedErrors
    from stereodem.post.synthetic_series import (
        dem_series,
        glacier_outline,
        utm_reference,
        write_polygons,
    )
    from stereodem.sensor.simulation.multidate import decimal_year, thinning_truth, write_dem_series

    n, res = 400, 90.0
    ref = utm_reference(DEM.bundled(), n, res, centre_lonlat=(40.42, 39.58))
    outline = glacier_outline(ref.grid, centre=(0.6, 0.45), radius=0.12)
    truth = thinning_truth(ref.grid, ref.heights, outline, t_ref=2000.13)
    noise = VariogramModel(np.array([200.0, 2000.0]), np.array([4.0, 1.0]))
    rng = np.random.default_rng(27)
    specs = []
    for k in range(5):
        specs.append(
            InjectedErrors(
                dx=float(rng.uniform(-40, 40)),
                dy=float(rng.uniform(-40, 40)),
                dz=float(rng.uniform(-6, 6)),
                ramp_e=float(rng.uniform(-2, 2)),
                ramp_n=float(rng.uniform(-2, 2)),
                heading_deg=HEADING,
                along_sines=[(3.0, 5500.0, float(rng.uniform(0, 2 * np.pi)))],
                noise=noise,
                seed=100 + k,
            )
        )
    clouds = [
        None,
        None,
        {"centre": (n * 0.3, n * 0.7), "radius": n * 0.07, "top": 3600.0},
        None,
        None,
    ]
    series = dem_series(truth, DATES, specs, clouds=clouds, vertical="geoid")
    # voids on the tongue (the outline's lowest quarter) in four DEMs: cells with one date
    inside = truth.rate != 0
    tongue = inside & (ref.heights <= np.percentile(ref.heights[inside], 25))
    tongue &= np.add.outer(np.arange(n), np.zeros(n)) % 7 < 4  # part of it
    for s in series[:4]:
        s.dem.heights[tongue] = np.nan
    dem_dir = work / "dems"
    paths = write_dem_series([s.dem for s in series], DATES, dem_dir, overwrite=True)
    ref.path = str(work / "ref.tif")
    ref.write(ref.path, overwrite=True)
    gl = write_polygons(work / "glacier.gpkg", [outline], ref.crs)
    times = np.array([decimal_year(d) for d in DATES])
    sill = float(noise.sill)
    limit_formal = noise_limit(times, np.full(5, np.sqrt(sill)))
    # noise alone: truth + noise of every date on the truth grid, no biases, no cloud
    noise_only = np.stack([s.noise_only for s in series])
    fit0 = fit_rates(noise_only, times, np.full(5, np.sqrt(sill)))
    stable = ~inside
    limit_empirical = nmad(fit0["rate"][stable])
    out = {
        "grid": f"{n} x {n} cells, {res:g} m (UTM crop of the bundled SRTM, lon 40.42 lat 39.58)",
        "dates": DATES,
        "injected": [
            dict(
                dx=s.dx,
                dy=s.dy,
                dz=s.dz,
                ramp_e_m_per_10km=s.ramp_e,
                ramp_n_m_per_10km=s.ramp_n,
                along=s.along_sines,
                heading_deg=s.heading_deg,
            )
            for s in specs
        ],
        "noise_variogram": noise.to_dict(),
        "cloud": {"date": DATES[2], "top_m": 3600.0, "cells": int(series[2].cloud.sum())},
        "tongue_void_cells_in_4_dems": int(tongue.sum()),
        "noise_limit_formal_m_per_yr": limit_formal,
        "noise_limit_empirical_nmad_m_per_yr": limit_empirical,
    }
    runs = {}
    for label, chain in (("chain", None), ("vshift_only", "vshift")):
        o = work / f"out_{label}"
        argv = [
            *map(str, paths),
            "--ref",
            ref.path,
            "--exclude",
            str(gl),
            "--outlines",
            str(gl),
            "--track-angle",
            str(HEADING),
            "--workers",
            "2",
            "-o",
            str(o),
            "--overwrite",
        ]
        if chain:
            argv += ["--chain", chain]
        run = _stack(argv)
        rate = _read(o / "rate.tif")
        n_obs = _read(o / "n_obs.tif")
        err = rate - truth.rate
        cloud = series[2].cloud
        vol = json.loads((o / "volumes.json").read_text())["polygons"][0]
        true_vol = float(np.mean(truth.rate[inside])) * vol["area_m2"]
        summ = json.loads((o / "stack.json").read_text())
        away = stable & ~cloud & np.isfinite(err)
        runs[label] = {
            "chain": summ["chain"],
            "wall_s": run["wall_s"],
            "peak_rss_mib": run["peak_rss_mib"],
            "peak_total_rss_mib": run["peak_total_rss_mib"],
            "per_dem_sigma_m": summ["sigma"],
            "per_dem_stable_nmad_after_chain_m": [
                d["coregistration"][-1]["after"]["nmad"] for d in summ["dems"]
            ],
            "inside_mean_rate_error_m_per_yr": float(np.nanmean(err[inside])),
            "inside_rate_error_nmad_m_per_yr": nmad(err[inside]),
            "stable_rate_nmad_m_per_yr": nmad(rate[stable]),
            "stable_rate_median_m_per_yr": float(np.nanmedian(rate[stable])),
            "stable_nmad_over_empirical_limit": nmad(rate[stable]) / limit_empirical,
            "stable_nmad_over_formal_limit": nmad(rate[stable]) / limit_formal,
            "cloud_rate_error_nmad_m_per_yr": nmad(err[cloud]),
            "cloud_rate_error_mean_m_per_yr": float(np.nanmean(err[cloud])),
            "cloud_rate_error_max_abs_m_per_yr": float(np.nanmax(np.abs(err[cloud]))),
            "stable_away_from_cloud_error_max_abs_m_per_yr": float(np.nanmax(np.abs(err[away]))),
            "cloud_cells_with_cloud_date_kept": int((n_obs[cloud] == 5).sum()),
            "cloud_cells": int(cloud.sum()),
            "volume_rate_m3_per_yr": vol["volume_rate_m3_per_yr"],
            "volume_rate_true_m3_per_yr": true_vol,
            "volume_rate_sigma_m3_per_yr": vol["volume_rate_sigma"],
            "volume_error_in_sigma": (vol["volume_rate_m3_per_yr"] - true_vol)
            / vol["volume_rate_sigma"],
            "mean_rate_sigma_m_per_yr": vol["mean_rate_sigma"],
            "n_effective": vol["n_effective"],
            "sigma_naive_m_per_yr": vol["sigma_naive"],
            "filled_pct": vol["filled_pct"],
            "rejected_observations": summ["rejected_observations"],
        }
    out["runs"] = runs
    r = runs["chain"]
    out["targets"] = {
        "inside_rate_within_0.1": abs(r["inside_mean_rate_error_m_per_yr"]) < 0.1,
        "stable_nmad_within_30pct_of_noise_limit": r["stable_nmad_over_empirical_limit"] < 1.3,
        "cloud_no_trace": (
            r["cloud_cells_with_cloud_date_kept"] == 0
            and r["cloud_rate_error_max_abs_m_per_yr"]
            <= r["stable_away_from_cloud_error_max_abs_m_per_yr"]
        ),
        "volume_within_2_sigma": abs(r["volume_error_in_sigma"]) < 2,
    }
    if gp:
        out["gp"] = gp_comparison(work / "out_chain", truth, stable, inside)
    return out


def gp_comparison(stack_dir: Path, truth, stable, inside) -> dict:
    """WLS against the Gaussian-process rate on the same stack: errors and seconds."""
    from stereodem.core.stats import nmad
    from stereodem.post.gp import GPSettings, gp_rates
    from stereodem.post.rates import fit_rates
    from stereodem.post.stack import open_stack

    ds = open_stack(stack_dir / "stack.zarr", chunk=None)
    h = ds["height"].values
    valid = ds["mask"].values == 0
    t = ds["decimal_year"].values
    sig = ds["sigma"].values
    t0 = time.perf_counter()
    w = fit_rates(h, t, sig, valid=valid)
    t_wls = time.perf_counter() - t0
    t0 = time.perf_counter()
    g = gp_rates(h, t, sig, valid=w["kept"], settings=GPSettings())
    t_gp = time.perf_counter() - t0
    res = {}
    for name, r in (("wls", w), ("gp", g)):
        e = r["rate"] - truth.rate
        res[name] = {
            "inside_mean_error": float(np.nanmean(e[inside])),
            "inside_error_nmad": nmad(e[inside]),
            "stable_nmad": nmad(r["rate"][stable]),
            "stable_sigma_median": float(np.nanmedian(r["rate_sigma"][stable])),
            "stable_z_nmad": nmad((r["rate"] / r["rate_sigma"])[stable]),
        }
    res["seconds"] = {"wls": round(t_wls, 3), "gp": round(t_gp, 3)}
    res["settings"] = GPSettings().__dict__
    return res


def part_granules(work: Path) -> dict:
    import shapely

    from stereodem.core.dem import DEM
    from stereodem.core.stats import nmad
    from stereodem.post.synthetic_series import write_polygons
    from stereodem.sensor.simulation.multidate import simulate_granule_series, thinning_truth

    dem = DEM.bundled()
    dates = ["2004-08-01", "2009-07-20", "2014-08-05", "2019-07-28"]
    lon0, lat0 = 40.415, 39.585
    outline = shapely.Point(lon0 + 0.01, lat0 - 0.005).buffer(0.02)
    t_ref = 2000.13
    t0 = time.perf_counter()
    recs = simulate_granule_series(
        dem,
        dates,
        outline_lonlat=outline,
        t_ref=t_ref,
        out_dir=work / "granules",
        size=(300, 300),
        seed=5,
        overwrite=True,
    )
    t_sim = time.perf_counter() - t0
    run_s = []
    dems = []
    for r in recs:
        o = work / "runs" / r["date"]
        t0 = time.perf_counter()
        p = subprocess.run(
            [
                sys.executable,
                "-m",
                "stereodem.cli",
                "dem",
                str(r["granule"]),
                "-o",
                str(o),
                "--overwrite",
                "--workers",
                "2",
            ],
            capture_output=True,
            text=True,
            check=False,
        )
        if p.returncode:
            raise SystemExit(f"stereodem dem failed: {p.stderr.strip()[-1500:]}")
        run_s.append(round(time.perf_counter() - t0, 1))
        dems.append(o / "dem.tif")
    # the reference: the unchanged truth (the SRTM surface) of the first scene, on its grid
    ref = work / "runs" / dates[0] / "truth_ref.tif"
    truth0 = DEM.from_file(recs[0]["folder"] / "truth_dem.tif")
    from stereodem.post import warp

    g = truth0.grid
    h_ref = warp.to_grid(
        dem.heights, dem.transform, dem.crs, g.transform, g.crs, g.shape, resampling="cubic"
    )
    ref_dem = DEM(h_ref, g.transform, g.crs, "geoid", None).to_reference("ellipsoid")
    ref_dem.write(ref)
    gl = write_polygons(work / "outline.gpkg", [outline], "EPSG:4326")
    o = work / "stack"
    run = _stack(
        [
            *map(str, dems),
            "--ref",
            str(ref),
            "--chain",
            "nuth_kaab,deramp:1",
            "--exclude",
            str(gl),
            "--workers",
            "2",
            "-o",
            str(o),
            "--overwrite",
        ]
    )
    rate = _read(o / "rate.tif")
    n_obs_seen = sum(
        np.isfinite(
            warp.to_grid(_read(p), *_georef(p), g.transform, g.crs, g.shape, resampling="nearest")
        ).astype(int)
        for p in dems
    )
    truth = thinning_truth(dem.grid, dem.heights, outline, t_ref=t_ref)
    true_rate = warp.to_grid(
        truth.rate, dem.transform, dem.crs, g.transform, g.crs, g.shape, resampling="nearest"
    )
    inside = true_rate < 0
    err = rate - true_rate
    stable = ~inside & np.isfinite(err)
    return {
        "dates": dates,
        "granule_size": "300 x 300 (3N), 3B in the 3N:3B ratio",
        "simulate_s": round(t_sim, 1),
        "run_s_per_granule": run_s,
        "stack": run,
        "cells_with_rate_pct": float(100 * np.isfinite(rate).mean()),
        # the reference grid is the simulator's truth grid, larger than the images' footprints:
        # the share that matters is that of the cells the DEMs observe
        "cells_observed_by_2_or_more_dates_pct": float(100 * (n_obs_seen >= 2).mean()),
        "cells_with_rate_of_those_observed_twice_pct": float(
            100 * np.isfinite(rate[n_obs_seen >= 2]).mean()
        ),
        "inside_cells": int(inside.sum()),
        "inside_mean_rate_error_m_per_yr": float(np.nanmean(err[inside])),
        "inside_true_mean_rate_m_per_yr": float(np.mean(true_rate[inside])),
        "stable_rate_nmad_m_per_yr": nmad(rate[stable]),
        "stable_rate_median_m_per_yr": float(np.nanmedian(rate[stable])),
    }


def part_heavy(
    work: Path, n_dems: int, size: int, chain: str, track_angle: float | None = None
) -> dict:
    from affine import Affine
    from scipy import ndimage

    from stereodem.core.dem import DEM
    from stereodem.core.raster import write_geotiff
    from stereodem.post.synthetic_series import utm_reference

    res = 20.0
    t0 = time.perf_counter()
    ref = utm_reference(DEM.bundled(), size, res, centre_lonlat=(40.42, 39.58))
    ref.path = str(work / "ref.tif")
    ref.write(ref.path, creation_options={"OVERVIEWS": "NONE", "LEVEL": "1"}, overwrite=True)
    dem_dir = work / "dems"
    dem_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    day0 = np.datetime64("2000-03-01")
    for k in range(n_dems):
        p = dem_dir / f"dem_{k:03d}.tif"
        paths.append(str(p))
        if p.exists():  # --work reused: the DEMs of an earlier run are there
            continue
        rng = np.random.default_rng(k)
        dx, dy = rng.uniform(-30, 30, 2)
        t = Affine.translation(dx, dy) @ ref.transform
        noise = ndimage.gaussian_filter(rng.standard_normal(ref.shape).astype(np.float32), 3)
        noise *= np.float32(2.0 / noise.std())
        h = ref.heights + noise + np.float32(rng.uniform(-5, 5))
        day = day0 + np.timedelta64(int(k * 9496 / max(n_dems - 1, 1)), "D")  # 26 years
        write_geotiff(
            p,
            h,
            t,
            ref.crs,
            np.nan,
            vertical="geoid",
            tags={"ACQUISITION_DATE": str(day)},
            creation_options={"OVERVIEWS": "NONE", "LEVEL": "1"},
        )
    t_gen = time.perf_counter() - t0
    load0 = _load()
    run = _stack(
        [
            *paths,
            "--ref",
            ref.path,
            "--chain",
            chain,
            *([] if track_angle is None else ["--track-angle", str(track_angle)]),
            "--workers",
            "2",
            "-o",
            str(work / "out"),
            "--overwrite",
        ]
    )
    load1 = _load()
    summ = json.loads((work / "out" / "stack.json").read_text())
    zsize = sum(f.stat().st_size for f in (work / "out" / "stack.zarr").rglob("*") if f.is_file())
    return {
        "dems": n_dems,
        "cells": f"{size} x {size}",
        "posting_m": res,
        "chain": chain,
        "track_angle_deg": track_angle,
        "workers": 2,
        "per_dem_build_s": round(summ["seconds"]["build"] / n_dems, 2),
        "generate_s": round(t_gen, 1),
        "wall_s": run["wall_s"],
        "peak_rss_mib": run["peak_rss_mib"],
        "peak_total_rss_mib": run["peak_total_rss_mib"],
        "build_s": summ["seconds"]["build"],
        "rates_and_outputs_s": round(summ["seconds"]["total"] - summ["seconds"]["build"], 1),
        "stack_zarr_mib": round(zsize / 2**20, 1),
        "input_float32_gib": round(n_dems * size * size * 4 / 2**30, 2),
        "load_before": load0,
        "load_after": load1,
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--part", choices=("real", "granules", "heavy"), default="real")
    ap.add_argument("--gp", action="store_true", help="also the Gaussian-process rate (real part)")
    ap.add_argument("--n", type=int, default=100, help="heavy part: number of DEMs")
    ap.add_argument("--size", type=int, default=3000, help="heavy part: cells per side")
    ap.add_argument(
        "--chain",
        default="vshift",
        help="heavy part: co-registration chain (default vshift: the container, masks "
        "and rates at scale); another chain's run is stored as heavy_chain",
    )
    ap.add_argument(
        "--track-angle",
        type=float,
        help="heavy part: ground-track heading for along_track/cross_track steps (degrees)",
    )
    ap.add_argument("--work", help="working folder (default: a temporary one, removed)")
    ap.add_argument("--keep", action="store_true", help="keep the working folder")
    args = ap.parse_args(argv)
    work = Path(args.work or tempfile.mkdtemp(prefix=f"bench_stack_{args.part}_"))
    work.mkdir(parents=True, exist_ok=True)
    load0 = _load()
    t0 = time.perf_counter()
    try:
        if args.part == "real":
            res = part_real(work, args.gp)
        elif args.part == "granules":
            res = part_granules(work)
        else:
            res = part_heavy(work, args.n, args.size, args.chain, args.track_angle)
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    res["seconds"] = round(time.perf_counter() - t0, 1)
    res["load_before"] = res.get("load_before", load0)
    res["load_after"] = res.get("load_after", _load())
    res["machine"] = f"{platform.platform()}, {os.cpu_count()} CPUs (shared by several jobs)"
    res["when"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    allres = json.loads(RESULT.read_text()) if RESULT.exists() else {}
    key = args.part
    if args.part == "heavy" and args.chain != "vshift":
        key = "heavy_chain"  # beside the vshift run: the container at scale vs the chain's cost
    allres[key] = res
    RESULT.parent.mkdir(parents=True, exist_ok=True)
    RESULT.write_text(strict_json(allres, indent=1))
    print(json.dumps(res, indent=1, default=float)[:6000])


if __name__ == "__main__":
    main()
