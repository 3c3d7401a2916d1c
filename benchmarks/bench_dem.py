"""Stereo DEM on the real Pleiades pair (s2p test data) against s2p's own DSM.

Runs :func:`stereodem.stereo.pipeline.make_dem` on
``../shared/data/s2p_pleiades/pair/img_0{1,2}.tif`` (RPCs from the GeoTIFF metadata) onto s2p's
output grid (EPSG:32740, 0.5 m), and compares the result with ``expected_dsm.tif`` (ellipsoidal
heights): median offset, NMAD of the difference, fraction of s2p's valid cells covered, wall time,
and the sparse stage's share of it (SIFT matches, relative pointing and — in the run without a
height range — the automatic terrain heights; issue #13 asks for at most 10 %). Writes
``benchmarks/results/bench_dem.json``.

The defaults (matcher, tile size, filters) were tuned on that pair, so the same defaults are
also run, with automatic heights, on the three pairs of the Pleiades triplet over Marseille
(``../shared/data/s2p_pleiades/triplet``), against s2p's DSM of the triplet: pairs nothing was
tuned on. s2p's own run time is not measured here (``pip install s2p`` fails on this machine,
see ``S2P_TIME``); earlier versions printed a constant 75 s that had no recorded source.

Usage: ``python benchmarks/bench_dem.py [--matcher sgm|ncc] [--out DIR]``
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import rasterio

from stereodem.sensor.models.rpc import RPCModel
from stereodem.stereo.pipeline import make_dem
from stereodem.stereo.settings import (
    GriddingSettings,
    MatchingSettings,
    RectificationSettings,
    StereoSettings,
)

HERE = Path(__file__).resolve().parent
PAIR = next(
    (
        p / "shared" / "data" / "s2p_pleiades" / "pair"
        for p in HERE.parents
        if (p / "shared" / "data" / "s2p_pleiades" / "pair").is_dir()
    ),
    HERE.parents[1] / "shared" / "data" / "s2p_pleiades" / "pair",
)
TRIPLET = PAIR.parent / "triplet"
#: why there is no s2p time: its last PyPI release (1.0b25, 2021) pins pyproj < 3 and builds C
#: code; ``pip install s2p`` in a fresh Python 3.11 venv stops before that (see the JSON)
S2P_TIME = (
    "not measured: `pip install s2p` (1.0b25, its last release) fails in a fresh Python 3.11 "
    "venv here (its setup.py needs pkg_resources; with an older setuptools it stops building "
    "pyproj 2.6 from source: s2p pins pyproj<3, which has no wheel for Python 3.11)"
)
#: a deliberately loose height range for La Reunion's Piton de la Fournaise area (m, ellipsoid);
#: s2p derives its own from SRTM. The DSM's true span is 2270-2376 m.
HEIGHT_RANGE = (2100.0, 2600.0)


from stereodem.core.jsonutil import dumps as strict_json  # noqa: E402
from stereodem.core.stats import nmad  # noqa: E402


def run(
    matcher="sgm",
    gridding="gaussian",
    tile_size=512,
    out=None,
    height_range=HEIGHT_RANGE,
    folder=PAIR,
    names=("img_01.tif", "img_02.tif"),
):
    with rasterio.open(folder / "expected_dsm.tif") as ds:
        ref = ds.read(1).astype(np.float64)
        if ds.nodata is not None and np.isfinite(ds.nodata):
            ref[ref == ds.nodata] = np.nan
        tr, crs = ds.transform, ds.crs
        bounds = ds.bounds
    t0 = time.perf_counter()
    images, models = [], []
    for name in names:
        with rasterio.open(folder / name) as ds:
            images.append(ds.read(1).astype(np.float32))
        models.append(RPCModel.from_file(folder / name))
    settings = StereoSettings(
        RectificationSettings(tile_size=tile_size, height_range=height_range),
        MatchingSettings(matcher=matcher),
        gridding=GriddingSettings(
            res=abs(tr.a),
            crs=crs.to_wkt(),
            method=gridding,
            bounds=(bounds.left, bounds.bottom, bounds.right, bounds.top),
        ),
    )
    prod = make_dem(images[0], images[1], models[0], models[1], settings)
    seconds = time.perf_counter() - t0
    if out:
        prod.write(out, overwrite=True)
    dem = prod.dem.heights.astype(np.float64)
    assert dem.shape == ref.shape, (dem.shape, ref.shape)
    ref_valid = np.isfinite(ref)
    both = ref_valid & np.isfinite(dem)
    d = dem[both] - ref[both]
    sparse_s = (prod.info.sparse or {}).get("seconds", {}).get("total", 0.0)
    res = dict(
        matcher=matcher,
        gridding=gridding,
        tile_size=tile_size,
        height_range=height_range or "automatic (sparse matches)",
        height_range_used=[round(v, 1) for v in prod.info.height_range],
        pair=f"{folder.name}/{names[0]}+{names[1]}",
        seconds=round(seconds, 2),
        sparse_seconds=round(sparse_s, 2),
        sparse_share=round(sparse_s / seconds, 4),
        pointing=prod.info.pointing.get("parameters"),
        suspect=prod.info.suspect,
        median_offset_m=round(float(np.median(d)), 4),
        nmad_m=round(nmad(d), 4),
        nmad_after_offset_m=round(nmad(d - np.median(d)), 4),
        abs_gt_1m_fraction=round(float(np.mean(np.abs(d - np.median(d)) > 1.0)), 4),
        coverage_of_s2p_valid=round(float(both.sum() / ref_valid.sum()), 4),
        n_tiles=prod.info.n_tiles,
        max_tile_residual_y_parallax_px=round(prod.info.max_residual_rms_px, 5),
        n_points=prod.n_points,
    )
    return res


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--matcher", default="sgm", choices=("sgm", "ncc"))
    ap.add_argument("--gridding", default="gaussian", choices=("mean", "gaussian"))
    ap.add_argument("--tile-size", type=int, default=512)
    ap.add_argument("--out", help="also write the DEM products to this folder")
    a = ap.parse_args()
    if not PAIR.is_dir():
        raise SystemExit(f"{PAIR}: not found (the benchmark needs ../shared/data)")
    rows = [
        run(m, a.gridding, a.tile_size, a.out if m == a.matcher else None)
        for m in dict.fromkeys([a.matcher, "ncc" if a.matcher == "sgm" else "sgm"])
    ]
    rows.append(run(a.matcher, a.gridding, a.tile_size, None, height_range=None))
    print(
        f"{'matcher':8} {'heights':>9} {'time s':>7} {'sparse':>7} {'median m':>9} {'NMAD m':>7} "
        f"{'cover':>6} {'|dz|>1m':>8}"
    )
    for r in rows:
        hr = "given" if isinstance(r["height_range"], tuple) else "automatic"
        print(
            f"{r['matcher']:8} {hr:>9} {r['seconds']:7.1f} {100 * r['sparse_share']:6.1f}% "
            f"{r['median_offset_m']:9.3f} {r['nmad_m']:7.3f} "
            f"{r['coverage_of_s2p_valid']:6.3f} {r['abs_gt_1m_fraction']:8.4f}"
        )
    others = []
    if TRIPLET.is_dir():
        for pair in (
            ("img_01.tif", "img_02.tif"),
            ("img_01.tif", "img_03.tif"),
            ("img_02.tif", "img_03.tif"),
        ):
            try:
                r = run(
                    a.matcher,
                    a.gridding,
                    a.tile_size,
                    None,
                    height_range=None,
                    folder=TRIPLET,
                    names=pair,
                )
            except Exception as exc:  # a failure is a result too
                r = {
                    "pair": f"triplet/{pair[0]}+{pair[1]}",
                    "error": f"{type(exc).__name__}: {exc}",
                }
            print(r)
            others.append(r)
    import os

    out = HERE / "results" / "bench_dem.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(
        strict_json(
            dict(
                pair=str(PAIR),
                s2p_reference="expected_dsm.tif",
                runs=rows,
                s2p_time=S2P_TIME,
                untuned_pairs=others,
                untuned_reference="triplet/expected_dsm.tif (s2p's DSM of the "
                "three images, EPSG:32631, 0.5 m)",
                load_average_at_end=[round(v, 2) for v in os.getloadavg()],
                opencv=__import__("cv2").__version__,
                numpy=np.__version__,
            ),
            indent=2,
        )
        + "\n"
    )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
