"""``stereodem batch`` of 8 simulated ASTER granules (7 good + 1 corrupt) on the process pool
and on a dask ``LocalCluster``, against the sum of single ``stereodem run`` jobs.

Each good scene is a simulated L1A V004 granule (3N 600 x 600, 3B in the real size ratio, the
``aster`` preset over the bundled SRTM, seeds 1..7) with a configuration (reference DEM =
its truth, both orthoimages, assessment); the eighth scene is a corrupt granule (an HDF4
signature then junk). Measured in one run, on the same machine:

* the sum of the single jobs: ``stereodem run CFG --workers 1`` for each good scene, one after
  the other (what a shell loop costs), and the corrupt granule's ``stereodem run``;
* ``stereodem batch`` of the 8 scenes with ``--workers 2`` (process pool) and ``--dask local``
  (LocalCluster of 2 single-threaded workers), from empty output folders;
* the failing scene's reported reason, the counts, and the load average.

    python benchmarks/bench_batch.py [--out /tmp/bench_batch] [--workers 2]

writes ``benchmarks/results/bench_batch.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

from stereodem.core.jsonutil import dumps as strict_json

ROOT = Path(__file__).resolve().parents[1]
DEST = ROOT / "benchmarks" / "results" / "bench_batch.json"
SIZE = (600, 600)
N_GOOD = 7

CONFIG = """[inputs]
left = "{granule}"
reference_dem = "truth_dem.tif"
reference_vertical = "ellipsoid"
checkpoints = "points.csv"
[output]
dir = "single"
[rectification]
tile_size = 512
height_range = [1000, 3500]
[ortho]
both = true
[assess]
coregister = false
"""


def make_scenes(root: Path) -> list[Path]:
    from stereodem.sensor.simulation.aster_granule import granule_right_size, write_granule_scene
    from stereodem.sensor.simulation.simulate import simulate_scene

    paths = []
    for seed in range(1, N_GOOD + 1):
        d = root / f"scene{seed}"
        cfg = d / f"scene{seed}.toml"
        if not cfg.exists():
            sc = simulate_scene(
                "aster", size=SIZE, right_size=granule_right_size(SIZE), seed=seed, n_points=30
            )
            g = write_granule_scene(sc, d, version=4, seed=seed, overwrite=True)
            cfg.write_text(CONFIG.format(granule=g.name))
        paths.append(cfg)
    bad = root / "AST_L1A_corrupt.hdf"
    bad.write_bytes(b"\x0e\x03\x13\x01" + os.urandom(4096))
    paths.append(bad)
    return paths


def timed(cmd):
    c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    return p, wall, (c1.ru_utime - c0.ru_utime) + (c1.ru_stime - c0.ru_stime)


def main(argv=None):
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", default="/tmp/bench_batch")
    ap.add_argument("--workers", type=int, default=2)
    a = ap.parse_args(argv)
    root = Path(a.out)
    root.mkdir(parents=True, exist_ok=True)
    scenes = make_scenes(root / "scenes")
    cli = [sys.executable, "-m", "stereodem.cli", "-q"]
    load0 = os.getloadavg()

    singles = []
    for cfg in scenes:
        if cfg.suffix == ".toml":
            shutil.rmtree(cfg.parent / "single", ignore_errors=True)
            p, wall, cpu = timed(cli + ["run", str(cfg), "--workers", "1", "--overwrite"])
        else:
            shutil.rmtree(root / "single_corrupt", ignore_errors=True)
            p, wall, cpu = timed(
                cli + ["dem", str(cfg), "-o", str(root / "single_corrupt"), "--workers", "1"]
            )
        singles.append(
            dict(
                scene=cfg.stem,
                exit=p.returncode,
                wall_s=round(wall, 2),
                cpu_s=round(cpu, 2),
                error=p.stderr.strip().splitlines()[-1:] if p.returncode else [],
            )
        )
        print(singles[-1], flush=True)
    runs = {}
    for name, extra in (("pool", []), ("dask_local", ["--dask", "local"])):
        out = root / f"batch_{name}"
        shutil.rmtree(out, ignore_errors=True)
        p, wall, cpu = timed(
            cli[:-1]
            + ["batch", *map(str, scenes), "-o", str(out), "--workers", str(a.workers), *extra]
        )
        table = json.loads((out / "batch.json").read_text())
        failed = [
            dict(name=r["name"], reason=r["reason"])
            for r in table["scenes"]
            if r["status"] == "failed"
        ]
        runs[name] = dict(
            exit=p.returncode,
            wall_s=round(wall, 2),
            cpu_s=round(cpu, 2),
            batch_seconds=table["seconds"],
            summary=table["summary"],
            failed=failed,
            sum_scene_seconds_inside=table["sum_scene_seconds"],
            load_average_after=[round(x, 2) for x in os.getloadavg()],
        )
        print(name, runs[name], flush=True)
    sum_single = sum(s["wall_s"] for s in singles)
    result = dict(
        scenes=f"{N_GOOD} simulated ASTER L1A V004 granules, 3N {SIZE[0]} x {SIZE[1]} (3B in the "
        "real ratio), run with both orthoimages and the assessment; 1 corrupt granule",
        workers=a.workers,
        cpus=os.cpu_count(),
        load_average_before=[round(x, 2) for x in load0],
        single_runs=singles,
        sum_of_single_runs_wall_s=round(sum_single, 2),
        sum_of_single_runs_cpu_s=round(sum(s["cpu_s"] for s in singles), 2),
        batch=runs,
        speedup_vs_single_runs={k: round(sum_single / v["wall_s"], 2) for k, v in runs.items()},
        note=(
            "wall seconds under the shared machine's load (load averages); every figure from this "
            "run"
        ),
    )
    DEST.write_text(strict_json(result, indent=1))
    print(
        json.dumps({k: result[k] for k in ("sum_of_single_runs_wall_s", "speedup_vs_single_runs")})
    )
    print(f"wrote {DEST}")


if __name__ == "__main__":
    main()
