"""Cost of the sparse stage (SIFT matches -> relative pointing -> terrain heights) on the real
Pleiades pair, against the dense DEM run it prepares.

Runs :func:`stereodem.stereo.sparse_stage.run_sparse_stage` on
``shared/data/s2p_pleiades/pair/img_0{1,2}.tif`` and then :func:`stereodem.stereo.pipeline.make_dem`
as ``bench_dem.py`` does (s2p's grid, SGM), and reports the stage's wall time as a share of the
whole run (issue #13: it should not add more than 10 %), with what the stage found: matches,
pointing correction, residual across the epipolar direction, height range against the span of
s2p's DSM. Writes ``benchmarks/results/bench_sparse.json``.

Usage: ``python benchmarks/bench_sparse.py``
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import rasterio

from stereodem.sensor.models.rpc import RPCModel
from stereodem.stereo.pipeline import DEMSettings, make_dem
from stereodem.stereo.sparse_stage import run_sparse_stage

HERE = Path(__file__).resolve().parent
PAIR = next((p / "shared" / "data" / "s2p_pleiades" / "pair" for p in HERE.parents
             if (p / "shared" / "data" / "s2p_pleiades" / "pair").is_dir()), None)


def main():
    if PAIR is None:
        raise SystemExit("shared/data/s2p_pleiades/pair: not found (the benchmark needs the shared data)")
    with rasterio.open(PAIR / "expected_dsm.tif") as ds:
        ref = ds.read(1).astype(np.float64)
        tr, crs, b = ds.transform, ds.crs, ds.bounds
    ref = ref[np.isfinite(ref)]
    images = [rasterio.open(PAIR / n).read(1).astype(np.float32) for n in ("img_01.tif", "img_02.tif")]
    left, right = (RPCModel.from_file(PAIR / n) for n in ("img_01.tif", "img_02.tif"))
    t0 = time.perf_counter()
    st = run_sparse_stage(images[0], images[1], left, right)
    t_sparse = time.perf_counter() - t0
    settings = DEMSettings(tile_size=512, height_range=st.height_range, matcher="sgm",
                           posting=abs(tr.a), crs=crs.to_wkt(), bounds=(b.left, b.bottom, b.right, b.top),
                           gridding="gaussian")
    t1 = time.perf_counter()
    prod = make_dem(images[0], images[1], left, st.right_model, settings)
    t_dense = time.perf_counter() - t1
    dem = prod.grid.height
    res = dict(
        pair=str(PAIR), sparse_seconds=round(t_sparse, 3), dense_seconds=round(t_dense, 3),
        sparse_share_of_run=round(t_sparse / (t_sparse + t_dense), 4),
        stage=st.summary(),
        s2p_dsm_range_m=[round(float(np.percentile(ref, 0.5)), 1), round(float(np.percentile(ref, 99.5)), 1)],
        height_range_found_m=[round(v, 1) for v in st.height_range],
        dem_valid_share=round(float(np.isfinite(dem).mean()), 4),
        note="2-core machine shared with other jobs: timings under contention")
    out = HERE / "results" / "bench_sparse.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=2, default=float) + "\n")
    print(f"sparse stage {t_sparse:.2f} s, dense DEM {t_dense:.2f} s: sparse share "
          f"{100 * res['sparse_share_of_run']:.1f} %; height range {res['height_range_found_m']} "
          f"vs s2p DSM {res['s2p_dsm_range_m']}")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
