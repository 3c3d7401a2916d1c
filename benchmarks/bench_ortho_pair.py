"""Both orthoimages of a pair: one after the other (each on the budget's row-block threads,
as ``ortho_stage`` did before) vs concurrently (``ortho.concurrent.orthorectify_all``), at
the same thread budget, in one run, alternating; wall and CPU seconds of this process.

Input: a finished ``stereodem run`` folder of ``bench_scaling.py`` (its configuration TOML
and its ``dem.tif``)::

    python benchmarks/bench_ortho_pair.py /tmp/bench_scaling/w1.toml --threads 2 --repeat 3

writes ``benchmarks/results/bench_ortho_pair.json`` (with the load average: a shared machine).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from stereodem.config import load_config
from stereodem.core.jsonutil import dumps as strict_json
from stereodem.core.threads import thread_budget
from stereodem.ortho.concurrent import orthorectify_all
from stereodem.ortho.drm import orthorectify
from stereodem.pipeline.inputs import load_pair, read_stereo_dem

DEST = Path(__file__).resolve().parent / "results" / "bench_ortho_pair.json"


def serial(images, dem, threads):
    grid, out = None, {}
    for name, img, model in images:
        out[name] = o = orthorectify(img, model, dem, grid=grid, threads=threads)
        grid = grid or o.grid
    return out


def main():
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("config")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--results", default=str(DEST))
    a = ap.parse_args()
    cfg = load_config(a.config)
    pair = load_pair(cfg)
    dem = read_stereo_dem(Path(cfg.output_dir) / "dem.tif")
    images = [
        ("left", pair.left_image, pair.left_model),
        ("right", pair.right_image, pair.right_model),
    ]
    runs = []
    with thread_budget(a.threads):
        ref = None
        for _ in range(a.repeat):
            for how, fn in (
                ("serial", lambda: serial(images, dem, a.threads)),
                ("concurrent", lambda: orthorectify_all(images, dem, threads=a.threads)),
            ):
                load = os.getloadavg()[0]
                t, c = time.perf_counter(), time.process_time()
                res = fn()
                runs.append(
                    dict(
                        how=how,
                        wall_s=round(time.perf_counter() - t, 3),
                        cpu_s=round(time.process_time() - c, 3),
                        load_before=round(load, 2),
                    )
                )
                data = {k: o.data for k, o in res.items()}
                ref = ref or data
                runs[-1]["identical_to_first"] = all(
                    np.array_equal(ref[k], data[k], equal_nan=True) for k in data
                )
                print(runs[-1], flush=True)
    summary = {
        how: {
            k: float(np.median([r[k] for r in runs if r["how"] == how]))
            for k in ("wall_s", "cpu_s")
        }
        for how in ("serial", "concurrent")
    }
    out = dict(
        threads=a.threads,
        grid=list(res["left"].grid.shape),
        runs=runs,
        median=summary,
        note="wall seconds depend on the machine's load (2 shared cores); CPU seconds of "
        "this process are the robust figure",
    )
    Path(a.results).write_text(strict_json(out, indent=1))
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
