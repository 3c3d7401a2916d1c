"""ASTER strip (issue 26, item 3): two adjacent simulated granules of one pass, one DEM.

Simulates ``--granules`` consecutive granules of one pass (``stereodem simulate --format
l1a-v004 --granules N`` code: one long along-track scene over the bundled SRTM, cut every 10
lattice steps with the real 5 % overlap), then:

* ``stereodem dem G1.hdf G2.hdf ...``: the strip's DEM (joined models, one pair);
* ``stereodem dem Gk.hdf`` for every granule alone;
* all with the same height range (the truth's +- 100 m) and posting (30 m), so that only the
  strip processing differs.

Measured against the truth DEM of the pass: the step of the strip DEM's error across every
seam line (median in a band of one lattice step on each side; target |step| <= 0.5 m); the
strip's NMAD on each granule's cells against that granule's own DEM on the same cells (target
within 10 %), and over all its cells; what processing the granules separately gives where
they overlap (median and NMAD of the difference of the two granule DEMs); times and the load.

    python benchmarks/bench_aster_strip.py [--size 820 840] [--granules 2] [--seed 5]

Writes benchmarks/results/bench_aster_strip.json. The machine is shared (2 cores, other jobs):
timings are upper bounds; the load average is recorded.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from stereodem.core.jsonutil import dumps as strict_json

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None):
    from stereodem.cli import main as cli
    from stereodem.core.dem import DEM
    from stereodem.core.stats import nmad
    from stereodem.post.assess import compare_on_reference_grid
    from stereodem.post.seams import seam_step
    from stereodem.post.warp import to_grid
    from stereodem.sensor.io.aster_strip import open_aster_strip
    from stereodem.sensor.simulation.aster_strip import simulate_strip, write_strip

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", nargs=2, type=int, default=[820, 840], help="one granule's 3N size")
    ap.add_argument("--granules", type=int, default=2)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument(
        "--out", default=str(ROOT / "benchmarks" / "results" / "bench_aster_strip.json")
    )
    a = ap.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="bench_aster_strip_"))
    res = dict(size=a.size, granules=a.granules, seed=a.seed, load_before=os.getloadavg())
    try:
        t = time.perf_counter()
        strip = simulate_strip(a.granules, size=tuple(a.size), seed=a.seed)
        paths = [str(p) for p in write_strip(strip, work / "sim")]
        res["simulate_s"] = round(time.perf_counter() - t, 2)
        res["cut"] = dict(
            advance_lines=strip.advance,
            overlap_3N_lines=strip.heights[0] - strip.advance,
            row_step=strip.row_step,
            lines=list(strip.heights),
        )
        truth = DEM.from_file(work / "sim" / "truth_dem.tif")
        lo, hi = truth.height_range()
        common = [
            "-q",
            "dem",
            "--res",
            "30",
            "--height-range",
            f"{lo - 100:.0f}",
            f"{hi + 100:.0f}",
        ]

        t = time.perf_counter()
        assert cli([*common, *paths, "-o", str(work / "strip")]) == 0
        res["strip_dem_s"] = round(time.perf_counter() - t, 2)
        report = json.loads((work / "strip" / "dem_report.json").read_text())
        dem = DEM.from_file(work / "strip" / "dem.tif")
        d_strip = compare_on_reference_grid(dem, truth).dh
        res["strip"] = dict(
            nmad_m=round(nmad(d_strip), 4),
            median_m=round(float(np.nanmedian(d_strip)), 4),
            valid_cells=report["info"]["valid_cells"],
            seams_3N=report["strip"]["seams"]["3N"],
            seams_3B=report["strip"]["seams"]["3B"],
        )
        model = open_aster_strip(paths).band("3N").model
        res["seam_steps"] = [
            seam_step(dem, truth, model, s["seam_line"], half_width=w)
            for s in report["strip"]["seams"]["3N"]
            for w in (strip.row_step, 2 * strip.row_step)
        ]

        singles, dems = [], []
        for k, p in enumerate(paths):
            t = time.perf_counter()
            assert cli([*common, p, "-o", str(work / f"g{k}"), "--force"]) == 0
            secs = time.perf_counter() - t
            one = DEM.from_file(work / f"g{k}" / "dem.tif")
            dems.append(one)
            d_one = compare_on_reference_grid(one, truth).dh
            same = np.isfinite(d_one) & np.isfinite(d_strip)
            singles.append(
                dict(
                    granule=Path(p).name,
                    seconds=round(secs, 2),
                    nmad_m=round(nmad(d_one), 4),
                    nmad_same_cells_m=round(nmad(d_one[same]), 4),
                    strip_nmad_same_cells_m=round(nmad(d_strip[same]), 4),
                    ratio=round(nmad(d_strip[same]) / nmad(d_one[same]), 4),
                    cells_compared=int(same.sum()),
                    strip_covers_pct=round(100 * same.sum() / np.isfinite(d_one).sum(), 2),
                )
            )
        res["single_granules"] = singles
        # separate processing: where consecutive granule DEMs overlap, how they differ
        sep = []
        for k in range(len(dems) - 1):
            b = to_grid(
                dems[k + 1].heights,
                dems[k + 1].transform,
                dems[k + 1].crs,
                dems[k].transform,
                dems[k].crs,
                dems[k].shape,
            )
            diff = b.astype(np.float64) - dems[k].heights
            sep.append(
                dict(
                    cells=int(np.isfinite(diff).sum()),
                    median_m=round(float(np.nanmedian(diff)), 4),
                    nmad_m=round(nmad(diff), 4),
                )
            )
        res["separate_granules_overlap_difference"] = sep
        worst_step = max(abs(s["step_m"]) for s in res["seam_steps"])
        worst_ratio = max(abs(s["ratio"] - 1) for s in singles)
        res["targets"] = dict(
            seam_step_le_0_5_m=bool(worst_step <= 0.5),
            worst_step_m=worst_step,
            nmad_within_10_pct=bool(worst_ratio <= 0.10),
            worst_nmad_ratio_dev=round(worst_ratio, 4),
        )
        res["load_after"] = os.getloadavg()
        res["cpu_count"] = os.cpu_count()
    finally:
        shutil.rmtree(work, ignore_errors=True)
    Path(a.out).write_text(strict_json(res, indent=2))
    print(
        json.dumps(
            {
                k: res[k]
                for k in (
                    "targets",
                    "seam_steps",
                    "single_granules",
                    "strip",
                    "separate_granules_overlap_difference",
                )
            },
            indent=1,
            default=float,
        )[:4000]
    )


if __name__ == "__main__":
    main()
