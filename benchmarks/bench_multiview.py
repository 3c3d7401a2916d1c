"""N-view DEM on the real Pleiades triplet (s2p test data) against s2p's fused DSM.

Runs :func:`stereodem.multiview.multiview_stage` (what ``stereodem dem img_01.tif img_02.tif
img_03.tif`` runs) on ``../shared/data/s2p_pleiades/triplet/img_0{1,2,3}.tif`` (RPCs from the
GeoTIFF metadata, heights from the sparse matches as by default) onto s2p's output grid
(EPSG:32631, 0.5 m, ``expected_dsm.tif``, ellipsoidal heights) and compares each pair's DEM
and the fused DEM (both fusion rules) with s2p's DSM: median offset, NMAD of the difference,
coverage of s2p's valid cells; times: each pair's stereo run and the whole N-view job (pairs
+ fusion). Writes ``benchmarks/results/bench_multiview.json``.

Runs the job twice: without the bundle adjustment of the three models (``[fusion] adjust =
"never"``) and with it (``"auto"``, the default: :func:`stereodem.stereo.ties.agree_models`).

Usage: ``python benchmarks/bench_multiview.py [--workers N]``
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
import rasterio

from stereodem.config import Config, InputSettings, RunSettings
from stereodem.core.jsonutil import dumps as strict_json
from stereodem.core.stats import nmad
from stereodem.multiview import multiview_stage
from stereodem.stereo.fusion import FusionSettings, fuse_dems
from stereodem.stereo.settings import GriddingSettings, StereoSettings

HERE = Path(__file__).resolve().parent
TRIPLET = next(
    (
        p / "shared" / "data" / "s2p_pleiades" / "triplet"
        for p in HERE.parents
        if (p / "shared" / "data" / "s2p_pleiades" / "triplet").is_dir()
    ),
    HERE.parents[1] / "shared" / "data" / "s2p_pleiades" / "triplet",
)


def compare(heights, ref):
    """Median offset, NMAD (m) and coverage of ``heights`` against s2p's valid cells."""
    ref_valid = np.isfinite(ref)
    both = ref_valid & np.isfinite(heights)
    d = heights[both].astype(np.float64) - ref[both]
    return dict(
        median_offset_m=round(float(np.median(d)), 4),
        nmad_m=round(nmad(d), 4),
        coverage_of_s2p_valid=round(float(both.sum() / ref_valid.sum()), 4),
    )


def run(workers=1, method="weighted", adjust="auto"):
    with rasterio.open(TRIPLET / "expected_dsm.tif") as ds:
        ref = ds.read(1).astype(np.float64)
        if ds.nodata is not None and np.isfinite(ds.nodata):
            ref[ref == ds.nodata] = np.nan
        tr, crs, b = ds.transform, ds.crs, ds.bounds
    paths = [str(TRIPLET / f"img_0{k}.tif") for k in (1, 2, 3)]
    cfg = Config(
        inputs=InputSettings(images=paths, model="rpc"),
        output_dir="unused",
        stereo=StereoSettings(
            gridding=GriddingSettings(
                res=abs(tr.a), crs=crs.to_wkt(), bounds=(b.left, b.bottom, b.right, b.top)
            )
        ),
        run=RunSettings(workers=workers),
        fusion=FusionSettings(method=method, adjust=adjust),
    )
    t0 = time.perf_counter()
    prod = multiview_stage(cfg, paths)
    seconds = time.perf_counter() - t0
    mv = prod.report
    pairs = []
    for r, dem in zip(mv["pair_runs"], prod.pair_dems):
        assert dem.heights.shape == ref.shape
        pairs.append(
            dict(
                pair=f"img_0{r['left'] + 1} + img_0{r['right'] + 1}",
                base_to_height=r["base_to_height"],
                seconds=r["seconds"],
                height_range=[round(v, 1) for v in r["height_range"]],
                **compare(dem.heights, ref),
            )
        )
    fusions = {}
    for m in ("weighted", "median"):
        t = time.perf_counter()
        f = (
            prod.fused
            if m == method
            else fuse_dems(
                prod.pair_dems,
                [p["sigma_m"] for p in prod.fused.pairs],
                method=m,
                k=cfg.fusion.reject_k,
                grid=prod.fused.grid,
            )
        )
        fusions[m] = dict(
            **compare(f.heights, ref),
            fusion_seconds=round(time.perf_counter() - t, 3) if m != method else None,
            cells_by_count={int(k): int(v) for k, v in enumerate(np.bincount(f.count.ravel()))},
            median_sigma_m=round(float(np.nanmedian(f.sigma)), 4),
            median_nmad_layer_m=round(float(np.nanmedian(f.nmad)), 4),
        )
    best = min(pairs, key=lambda p: p["nmad_m"])
    return dict(
        triplet=str(TRIPLET),
        s2p_reference="expected_dsm.tif",
        workers=workers,
        adjust=adjust,
        adjustment=mv["adjustment"],
        load_average=[round(v, 2) for v in os.getloadavg()],
        pairs_considered=mv["pairs"],
        skipped_images=mv["skipped_images"],
        pairs=pairs,
        fused=fusions,
        default_fusion=method,
        seconds_nview_job=round(seconds, 2),
        seconds_pairs_sum=round(sum(p["seconds"] for p in pairs), 2),
        best_pair=best["pair"],
        fused_nmad_le_best_pair=bool(fusions[method]["nmad_m"] <= best["nmad_m"]),
        fused_coverage_ge_best_pair=bool(
            fusions[method]["coverage_of_s2p_valid"] >= best["coverage_of_s2p_valid"]
        ),
        pair_agreement_with_fused=[r["fusion"] for r in mv["pair_runs"]],
    )


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", type=int, default=1)
    a = ap.parse_args()
    if not TRIPLET.is_dir():
        raise SystemExit(f"{TRIPLET}: not found (the benchmark needs ../shared/data)")
    runs = [run(a.workers, adjust=adj) for adj in ("never", "auto")]
    for res in runs:
        adj = res["adjustment"]
        print(
            f"[fusion] adjust = {res['adjust']}"
            + (
                f": {adj['reason']}, reprojection RMS "
                f"{adj['reprojection_rms_px_before']} -> {adj['reprojection_rms_px_after']} px"
                if adj
                else ""
            )
        )
        print(f"{'DEM':22} {'B/H':>6} {'time s':>7} {'median m':>9} {'NMAD m':>7} {'cover':>6}")
        for p in res["pairs"]:
            print(
                f"{p['pair']:22} {p['base_to_height']:6.3f} {p['seconds']:7.1f} "
                f"{p['median_offset_m']:9.3f} {p['nmad_m']:7.3f} {p['coverage_of_s2p_valid']:6.4f}"
            )
        for m, f in res["fused"].items():
            print(
                f"{'fused (' + m + ')':22} {'':6} {'':7} {f['median_offset_m']:9.3f} "
                f"{f['nmad_m']:7.3f} {f['coverage_of_s2p_valid']:6.4f}"
            )
        print(
            f"N-view job {res['seconds_nview_job']:.1f} s (pairs {res['seconds_pairs_sum']:.1f} "
            f"s), load {res['load_average']}"
        )
    res = dict(runs=runs)
    out = HERE / "results" / "bench_multiview.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(strict_json(res, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
