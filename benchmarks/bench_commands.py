"""The standalone commands at 1 and 2 workers (issue #28, "every stage parallel"): wall and
CPU seconds and the cores each uses, in one run.

The inputs come from ``bench_scaling.py``'s folder (the simulated full ASTER granule and the
job it ran: run ``python benchmarks/bench_scaling.py --workers 2`` first): 3000 x 3000 crops
of the truth DEM (15.2 m) for ``change``, ``coregister``, ``stack``, ``assess`` and
``mosaic`` (one shifted, offset and noisy, with a hole; two overlapping tiles), and the
stereo DEM of the 2-worker job for ``filter``, ``ortho`` and ``uncertainty``.

Every command runs with ``--workers 1`` and ``--workers 2`` (each takes it: the thread budget
of its process, :mod:`stereodem.core.threads`; ``mosaic``'s computes here, without
``--dask``). A command that lacked the option would run under ``taskset -c 0`` (one core:
its thread budget follows the affinity mask) and unrestricted. The counts alternate (w1, w2,
w1, ...) and each figure is the median of ``--repeat`` runs; CPU seconds are the child's
(``os.wait4``)::

    python benchmarks/bench_commands.py [--repeat 3] [--only change uncertainty]
        [--scaling /tmp/bench_scaling] [--out /tmp/bench_commands]

writes ``benchmarks/results/bench_commands.json`` and prints a Markdown table.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import rasterio
from rasterio.windows import Window

from stereodem.core.jsonutil import dumps as strict_json

ROOT = Path(__file__).resolve().parents[1]
DEST = ROOT / "benchmarks" / "results" / "bench_commands.json"
CROP = 3000


def crop(src, dst, r0, c0, n, *, shift=(0.0, 0.0), dz=0.0, noise=0.0, hole=False, seed=0):
    """A ``n`` x ``n`` crop of the DEM ``src`` at rows/cols ``r0, c0`` written to ``dst``:
    moved by ``shift`` (map units), offset by ``dz`` (m), Gaussian noise (m), a void."""
    rng = np.random.default_rng(seed)
    with rasterio.open(src) as s:
        w = Window(c0, r0, n, n)
        a = s.read(1, window=w).astype("float32")
        prof, t, tags = s.profile.copy(), s.window_transform(w), s.tags()
    a += np.float32(dz)
    if noise:
        a += rng.normal(0, noise, a.shape).astype("float32")
    if hole:
        a[n // 3 : n // 3 + 200, n // 3 : n // 3 + 300] = np.nan
    t = rasterio.Affine(t.a, t.b, t.c + shift[0], t.d, t.e, t.f + shift[1])
    prof.update(
        driver="GTiff",
        width=n,
        height=n,
        transform=t,
        nodata=np.nan,
        tiled=True,
        blockxsize=256,
        blockysize=256,
        compress="deflate",
    )
    with rasterio.open(dst, "w", **prof) as d:
        d.write(a, 1)
        d.update_tags(**tags)


def make_inputs(scaling: Path, inputs: Path):
    truth = scaling / "scene" / "truth_dem.tif"
    inputs.mkdir(parents=True, exist_ok=True)
    crop(truth, inputs / "a.tif", 1000, 1000, CROP)
    crop(truth, inputs / "b.tif", 1000, 1000, CROP, shift=(7, -4), dz=3, noise=1, hole=True)
    crop(truth, inputs / "c.tif", 1000, 1000, CROP, shift=(-5, 6), dz=-2, noise=1.5, seed=1)
    crop(truth, inputs / "m1.tif", 1000, 1000, CROP)
    crop(truth, inputs / "m2.tif", 2500, 2500, CROP, dz=1, noise=0.5, seed=2)


def commands(scaling: Path, i: Path) -> dict:
    """Each command's arguments (``{o}``: its output folder)."""
    scene, job = scaling / "scene", scaling / "w2"
    dates = ["--dates", "2004-08-01,2019-07-20"]
    return {
        "change": ["change", i / "a.tif", i / "b.tif", *dates, "-o", "{o}"],
        "uncertainty": (
            ["uncertainty", scene / "left.tif", "--dem", job / "dem.tif", "--res", "30"]
            + ["--sigma", "roll_bias=2e-5", "--sigma", "pitch_bias=2e-5"]
            + ["--sigma", "dem_height=5", "-o", "{o}"]
        ),
        "coregister": ["coregister", i / "b.tif", "--ref", i / "a.tif", "--no-figures"]
        + ["-o", "{o}"],
        "stack": (
            ["stack", i / "b.tif", i / "c.tif", "--ref", i / "a.tif", *dates]
            + ["--chain", "nuth_kaab", "-o", "{o}"]
        ),
        "mosaic": ["mosaic", i / "m1.tif", i / "m2.tif", "-o", "{o}/mosaic.tif"],
        "assess": ["assess", i / "b.tif", "--ref", i / "a.tif", "-o", "{o}"],
        "filter": ["filter", job / "raw" / "dem.tif", "-o", "{o}/clean.tif"],
        "ortho": ["ortho", scene / "left.tif", "--dem", job / "dem.tif", "--res", "15"]
        + ["-o", "{o}/ortho.tif"],
    }


def has_workers(command: str) -> bool:
    """Whether ``stereodem COMMAND`` takes ``--workers`` (every command that computes does:
    its process's thread budget; mosaic's also sizes its ``--dask local`` cluster)."""
    out = subprocess.run(
        [sys.executable, "-m", "stereodem.cli", command, "--help"], capture_output=True, text=True
    ).stdout
    return "--workers" in out


def run_once(argv, out: Path, workers: int, own_option: bool):
    """(wall s, CPU s, peak RSS MiB) of one run."""
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    cmd = [sys.executable, "-m", "stereodem.cli", "-q"]
    cmd += [str(a).replace("{o}", str(out)) for a in argv]
    if own_option:
        cmd += ["--workers", str(workers)]
    elif workers == 1:
        cmd = ["taskset", "-c", "0", *cmd]
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, ru = os.wait4(p.pid, 0)
    wall = time.perf_counter() - t0
    if os.waitstatus_to_exitcode(status):
        raise SystemExit(f"{' '.join(cmd)} failed: {p.stderr.read().decode()[-2000:]}")
    p.stderr.close()
    return wall, ru.ru_utime + ru.ru_stime, ru.ru_maxrss / 1024


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--only", nargs="+", help="these commands only")
    ap.add_argument("--scaling", default="/tmp/bench_scaling", help="bench_scaling.py's --out")
    ap.add_argument("--out", default="/tmp/bench_commands")
    ap.add_argument("--results", default=str(DEST))
    args = ap.parse_args(argv)
    scaling, out = Path(args.scaling), Path(args.out)
    need = [scaling / "scene" / "truth_dem.tif", scaling / "w2" / "dem.tif"]
    if not all(p.exists() for p in need):
        raise SystemExit(f"{scaling}: run python benchmarks/bench_scaling.py --workers 2 first")
    make_inputs(scaling, out / "in")
    cmds = commands(scaling, out / "in")
    names = args.only or list(cmds)
    own_option = {name: has_workers(name) for name in names}
    if not all(own_option.values()) and shutil.which("taskset") is None:
        raise SystemExit("taskset (util-linux) is needed for the commands without --workers")
    rows = []
    for name in names:
        own = own_option[name]
        runs = {1: [], 2: []}
        for _ in range(args.repeat):
            for w in (1, 2):
                runs[w].append(run_once(cmds[name], out / f"{name}_{w}", w, own))
        row = dict(command=name, workers_option=own)
        for w, rs in runs.items():
            wall = statistics.median(r[0] for r in rs)
            cpu = statistics.median(r[1] for r in rs)
            row[f"w{w}"] = dict(
                wall_s=round(wall, 2),
                cpu_s=round(cpu, 2),
                cores=round(cpu / wall, 2),
                peak_rss_mb=round(max(r[2] for r in rs)),
                walls=[round(r[0], 2) for r in rs],
            )
        row["speedup_2_vs_1"] = round(row["w1"]["wall_s"] / row["w2"]["wall_s"], 2)
        rows.append(row)
        print(
            f"{name}: w1 {row['w1']['wall_s']} s, w2 {row['w2']['wall_s']} s "
            f"({row['w2']['cores']} cores), {row['speedup_2_vs_1']}x",
            flush=True,
        )
    table = [
        "| command | option | w1 wall s | w2 wall s | w2 cores | speed-up |",
        "|---|---|---|---|---|---|",
    ] + [
        f"| {r['command']} | {'--workers' if r['workers_option'] else 'taskset'} | "
        f"{r['w1']['wall_s']} | {r['w2']['wall_s']} | {r['w2']['cores']} | "
        f"{r['speedup_2_vs_1']} |"
        for r in rows
    ]
    print("\n".join(table))
    doc = dict(
        machine=dict(
            platform=platform.platform(), cpus=os.cpu_count(), python=sys.version.split()[0]
        ),
        measured=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        repeat=args.repeat,
        load_average=list(os.getloadavg()),
        commands=rows,
        table_markdown="\n".join(table),
    )
    Path(args.results).write_text(strict_json(doc, indent=2) + "\n")
    print(f"wrote {args.results}")


if __name__ == "__main__":
    main()
