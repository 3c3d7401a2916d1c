"""Scaling with the number of workers: ``stereodem run`` on one simulated ASTER granule with
``--workers`` 1, 2, 4, ... up to the machine's cores, in one run.

For each worker count: wall seconds, CPU seconds of the job and every process it waited for
(``RUSAGE_CHILDREN``; psutil's sum over the process tree, sampled every 0.2 s, beside it as a
check), peak memory summed over the process tree (psutil), the load average before and after,
and per stage (``run.json``'s stage records) wall seconds, CPU seconds of the main process and
of the tile workers and peak memory; the rasters of every count are compared with those of 1
worker (bit-identical or not). Ratios: speed-up and CPU-seconds against 2 workers and 1.

The scene is simulated as in ``bench_aster_scene.py`` (the ``aster`` preset over the mirrored
bundled SRTM, an L1A V004 granule); full size by default (3N 4100 x 4200, 3B 5000 x 5400),
``--half`` for 3N 2050 x 2100, 3B 2500 x 2700. Runs unchanged on a 16-core machine::

    python benchmarks/bench_scaling.py [--half] [--workers 1 2 4 8 16] [--repeat 3]
        [--out /tmp/bench_scaling]

writes ``benchmarks/results/bench_scaling.json`` and prints a Markdown table.
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
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from bench_aster_scene import CONFIG, RUN_LAYERS, granule, identical, simulate
from machine_speed import WHAT as SPEED_INDEX_WHAT
from machine_speed import speed_index

from stereodem.core.jsonutil import dumps as strict_json

DEST = ROOT / "benchmarks" / "results" / "bench_scaling.json"


def worker_counts(cores: int) -> list[int]:
    """1, 2, 4, ... below ``cores``, then ``cores``."""
    out, n = [], 1
    while n < cores:
        out.append(n)
        n *= 2
    return out + [cores]


def child_env() -> dict:
    """The job's environment: this one, but Python may cache bytecode (an installed package
    has it; with ``PYTHONDONTWRITEBYTECODE`` set, as on some CI machines, every process of
    every run would compile stereodem's modules again: ~0.7 CPU s in the main process)."""
    env = dict(os.environ)
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    return env


def _idle_core_s(psutil) -> float:
    """Seconds the machine's cores have been idle (all cores summed, iowait included)."""
    t = psutil.cpu_times()
    return t.idle + getattr(t, "iowait", 0.0)


def measured(cmd):
    """Run ``cmd``: wall s, CPU s (rusage of waited-for descendants), CPU s by psutil over the
    process tree (last sample of each process), peak RSS MB summed over the tree, and the
    machine's idle core-seconds meanwhile (all cores; on a machine doing nothing else, the
    cores the job left unused: its serial parts and waits)."""
    import psutil

    cpu0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    idle0 = _idle_core_s(psutil)
    t0 = time.perf_counter()
    p = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=child_env()
    )
    proc, peak, cpu_seen = psutil.Process(p.pid), 0, {}
    while p.poll() is None:
        try:
            tree = [proc] + proc.children(recursive=True)
            rss = 0
            for q in tree:
                try:
                    with q.oneshot():
                        rss += q.memory_info().rss
                        c = q.cpu_times()
                        cpu_seen[q.pid] = c.user + c.system
                except psutil.Error:
                    pass
            peak = max(peak, rss)
        except psutil.Error:
            pass
        time.sleep(0.2)
    _, err = p.communicate()
    wall = time.perf_counter() - t0
    idle = _idle_core_s(psutil) - idle0
    cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0:
        raise SystemExit(f"{' '.join(map(str, cmd))} failed:\n{err[-3000:]}")
    cpu = (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime)
    return wall, cpu, sum(cpu_seen.values()), peak / 2**20, idle


def run_once(scene: Path, out: Path, workers: int) -> dict:
    cfg = out.with_suffix(".toml")
    cfg.write_text(CONFIG.format(scene=scene, granule=granule(scene), out=out, workers=workers))
    load0 = os.getloadavg()
    wall, cpu, cpu_ps, peak, idle = measured(
        [sys.executable, "-m", "stereodem.cli", "-q", "run", str(cfg), "--overwrite"]
    )
    info = json.loads((out / "run.json").read_text())
    stages = {
        k: dict(
            wall_s=v["seconds"],
            cpu_s=v.get("cpu_s"),
            worker_cpu_s=v.get("worker_cpu_s"),
            main_peak_rss_mb=v.get("peak_rss_mb"),
            tile_process_peak_rss_mb=v.get("tile_process_peak_rss_mb"),
        )
        for k, v in info["stages"].items()
    }
    tile_cpu = [t["cpu_s"] for t in info["stereo"]["tiles"] if "cpu_s" in t]
    if tile_cpu:  # the tiles' own CPU seconds (in their workers): the same work at any N?
        stages["stereo"].update(
            tile_cpu_s_sum=round(float(np.sum(tile_cpu)), 2),
            tile_cpu_s_median=round(float(np.median(tile_cpu)), 3),
        )
    return dict(
        workers=workers,
        wall_s=round(wall, 2),
        cpu_s=round(cpu, 2),
        cpu_s_psutil=round(cpu_ps, 2),
        peak_rss_mb_all_processes=round(peak),
        idle_core_s=round(idle, 2),
        load_average_before=[round(x, 2) for x in load0],
        load_average_after=[round(x, 2) for x in os.getloadavg()],
        stages=stages,
        nmad_m=info["headline"]["nmad"],
        valid_pct=info["headline"]["valid_pct"],
    )


def scaling_ratios(runs, top: int) -> dict:
    """Speed-ups (walls of the median-wall runs) and CPU ratios (medians of the rounds' CPU
    seconds when there are rounds) of 2 workers against 1 and of ``top`` against 2; with
    rounds, also the speed-up of 2 workers in each round and its median."""
    by = {r["workers"]: r for r in runs}

    def cpu(w):
        return by[w].get("median_cpu_s", by[w]["cpu_s"])

    ratios = {}
    if 1 in by and 2 in by:
        ratios.update(
            speedup_2_vs_1=round(by[1]["wall_s"] / by[2]["wall_s"], 2),
            cpu_2_over_1=round(cpu(2) / cpu(1), 3),
        )
        if "rounds_wall_s" in by[1] and "rounds_wall_s" in by[2]:
            # each round runs 1 then 2 workers back to back: its ratio sees the machine in one
            # state (a shared machine's speed drifts between rounds by up to ~20 %)
            per = [a / b for a, b in zip(by[1]["rounds_wall_s"], by[2]["rounds_wall_s"])]
            ratios.update(
                speedup_2_vs_1_by_round=[round(x, 3) for x in per],
                speedup_2_vs_1_median_of_rounds=round(float(np.median(per)), 3),
            )
    if 2 in by and top > 2 and top in by:
        ratios[f"speedup_{top}_vs_2"] = round(by[2]["wall_s"] / by[top]["wall_s"], 2)
        ratios[f"cpu_{top}_over_2"] = round(cpu(top) / cpu(2), 3)
    return ratios


def table(runs) -> str:
    base = {r["workers"]: r for r in runs}
    ref2 = base.get(2) or runs[0]
    lines = [
        "| workers | `run` wall s | `run` CPU s | CPU / CPU(2 w) | stereo s | post / ortho / "
        "assess s | peak MB | load before |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in runs:

        def g(k, st=r["stages"]):
            return st.get(k, {}).get("wall_s", 0.0)

        lines.append(
            f"| {r['workers']} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | "
            f"{r['cpu_s'] / ref2['cpu_s']:.2f} | {g('stereo'):.1f} | "
            f"{g('post'):.1f} / {g('ortho'):.1f} / {g('assess'):.1f} | "
            f"{r['peak_rss_mb_all_processes']} | {r['load_average_before'][0]:.2f} |"
        )
    return "\n".join(lines)


#: rows x columns of the float32 arrays of the streaming ceiling: 80 MB each, far beyond any
#: cache, as a DEM's or an orthoimage's full-size layers are
_STREAM_SHAPE = (4000, 5000)


def _stream_call(a, b, c):
    """One call of the streaming ceiling: two element-wise passes over 80 MB float32 arrays
    (``c = a + b``, ``a = c * b``), memory-bound, as a full-size layer's NumPy passes are."""
    np.add(a, b, out=c)
    np.multiply(c, b, out=a)


def _ceiling_worker(calls, barrier, results, kind="sgbm"):
    """One process of :func:`parallel_ceiling`: ``calls`` calls of ``kind`` (1 thread) after
    every process is ready; puts (wall s, CPU s) of the calls. ``kind``: ``"sgbm"``, a bare
    SGBM call on bench_match.py's pair (compute-bound, its data in cache), or ``"stream"``,
    :func:`_stream_call` (bound by the memory's bandwidth)."""
    if kind == "stream":
        a = np.ones(_STREAM_SHAPE, np.float32)
        b, c = np.ones_like(a), np.empty_like(a)

        def call():
            _stream_call(a, b, c)

    else:
        import cv2
        from bench_match import _raw_sgbm, _to_uint8, make_pair

        cv2.setNumThreads(1)
        l8, r8 = _to_uint8(*make_pair()[:2])

        def call():
            _raw_sgbm(l8, r8, "sgbm")

    call()  # warm: first-call allocations and page faults out of the timing
    barrier.wait()
    w0, c0 = time.perf_counter(), time.process_time()
    for _ in range(calls):
        call()
    results.put((time.perf_counter() - w0, time.process_time() - c0))


def _ceiling_once(n, calls, kind="sgbm") -> tuple[float, float]:
    """Wall s of the slowest of ``n`` processes of :func:`_ceiling_worker`, and CPU s per call."""
    import multiprocessing

    ctx = multiprocessing.get_context("spawn")
    barrier, results = ctx.Barrier(n), ctx.Queue()
    procs = [
        ctx.Process(target=_ceiling_worker, args=(calls, barrier, results, kind)) for _ in range(n)
    ]
    for p in procs:
        p.start()
    got = [results.get(timeout=600) for _ in procs]
    for p in procs:
        p.join()
    return max(w for w, _ in got), sum(c for _, c in got) / (n * calls)


def parallel_ceiling(counts, calls=6, rounds=3, kind="sgbm") -> dict:
    """What this machine gives perfectly parallel work at each process count: N processes
    (spawned, 1 thread each, no shared data) each run ``calls`` bare ``cv2.StereoSGBM`` calls
    on bench_match.py's pair at once, as N tile workers would (``kind="stream"``: element-wise
    NumPy passes over 80 MB arrays instead, :func:`_stream_call`, bound by the memory's
    bandwidth, as the full-size layers' passes of the filters, orthoimages and assessment
    are). For each N: the speed-up in throughput against 1 process (``N x wall(1) /
    wall(N)``, wall of the slowest) and the CPU seconds per call against 1 process, each the
    median of ``rounds`` rounds (1 process and every N in each, back to back). No stereodem
    code runs: a job's speed-up and CPU ratio are read against these (shared or virtual cores
    lose some of both to each other; cores that share one memory bus lose the streaming
    work's)."""
    ns = sorted(set(counts) | {1})
    per = {n: [] for n in ns}
    if kind == "stream":
        calls *= 5  # 6 SGBM calls take ~1 s, 30 streaming calls ~0.5-1 s
    for _ in range(rounds):
        w1, c1 = _ceiling_once(1, calls, kind)
        for n in ns:
            w, c = (w1, c1) if n == 1 else _ceiling_once(n, calls, kind)
            per[n].append((n * w1 / w, c / c1, w))
    return {
        str(n): dict(
            speedup_vs_1=round(float(np.median([x[0] for x in v])), 3),
            cpu_per_call_over_1=round(float(np.median([x[1] for x in v])), 3),
            rounds_speedup=[round(x[0], 3) for x in v],
            rounds_wall_s=[round(x[2], 3) for x in v],
        )
        for n, v in per.items()
    }


def main(argv=None):
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--half", action="store_true", help="half-size granule (3N 2050 x 2100)")
    ap.add_argument(
        "--size",
        nargs=4,
        type=int,
        metavar=("W3N", "H3N", "W3B", "H3B"),
        help="other granule sizes (3N then 3B)",
    )
    ap.add_argument("--workers", nargs="+", type=int, help="default: 1, 2, 4, ... up to the cores")
    ap.add_argument("--out", default="/tmp/bench_scaling")
    ap.add_argument("--results", default=str(DEST), help=f"results file (default {DEST.name})")
    ap.add_argument(
        "--repeat",
        type=int,
        default=1,
        help="rounds over the worker counts (alternating); each count's run of median wall "
        "is reported, with every round's wall and CPU seconds (shared machines drift)",
    )
    args = ap.parse_args(argv)
    size, right = ((2050, 2100), (2500, 2700)) if args.half else ((4100, 4200), (5000, 5400))
    if args.size:
        size, right = tuple(args.size[:2]), tuple(args.size[2:])
    cores = os.cpu_count() or 1
    counts = args.workers or worker_counts(cores)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    simulate(out / "scene", size, right)
    subprocess.run(  # the modules' bytecode cached before the first measured run
        [sys.executable, "-c", "import stereodem.pipeline.job, stereodem.post.report"],
        env=child_env(),
        check=True,
    )
    speed_before = speed_index()
    ceiling_before = parallel_ceiling(counts)
    print("parallel ceiling (bare SGBM, N processes):", json.dumps(ceiling_before), flush=True)
    stream_before = parallel_ceiling(counts, kind="stream")
    print("streaming ceiling (80 MB passes, N processes):", json.dumps(stream_before), flush=True)
    rounds = {w: [] for w in counts}
    for _ in range(max(1, args.repeat)):
        for w in counts:
            shutil.rmtree(out / f"w{w}", ignore_errors=True)
            r = run_once(out / "scene", out / f"w{w}", w)
            if w != counts[0]:
                r[f"bit_identical_to_workers_{counts[0]}"] = identical(
                    out / f"w{counts[0]}", out / f"w{w}", RUN_LAYERS
                )
            rounds[w].append(r)
            print(
                f"workers {w}: {r['wall_s']} s wall, {r['cpu_s']} CPU s ({r['cpu_s_psutil']} by "
                f"psutil), peak {r['peak_rss_mb_all_processes']} MB, idle "
                f"{r['idle_core_s']} core-s, load {r['load_average_before'][0]}",
                flush=True,
            )
    runs = []
    for w in counts:  # the round of median wall, with every round's figures
        rs = sorted(rounds[w], key=lambda r: r["wall_s"])
        r = dict(rs[(len(rs) - 1) // 2])
        if len(rs) > 1:
            r["rounds_wall_s"] = [x["wall_s"] for x in rounds[w]]
            r["rounds_cpu_s"] = [x["cpu_s"] for x in rounds[w]]
            r["median_cpu_s"] = float(np.median(r["rounds_cpu_s"]))
            same = f"bit_identical_to_workers_{counts[0]}"
            if same in r:  # identical in every round, layer by layer
                r[same] = {k: all(x[same][k] for x in rs) for k in r[same]}
        runs.append(r)
    ratios = scaling_ratios(runs, counts[-1])
    result = dict(
        granule=dict(left=list(size), right=list(right), input="ASTER L1A V004, simulated"),
        machine=dict(
            cpus=cores,
            python=platform.python_version(),
            node=platform.node(),
            speed_index_ms=[speed_before, speed_index()],
            speed_index=SPEED_INDEX_WHAT,
            parallel_ceiling=[ceiling_before, parallel_ceiling(counts)],
            parallel_ceiling_what=parallel_ceiling.__doc__.split("\n\n")[0]
            + " Measured before and after the runs.",
            streaming_ceiling=[stream_before, parallel_ceiling(counts, kind="stream")],
        ),
        measured=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        repeat=max(1, args.repeat),
        runs=runs,
        ratios=ratios,
        table_markdown=table(runs),
        note=(
            "wall seconds depend on the machine's load (load_average_*: a shared "
            "machine); CPU seconds are the robust figure; Python's bytecode cached, as in "
            "an installed package"
        ),
    )
    dest = Path(args.results)
    dest.parent.mkdir(parents=True, exist_ok=True)
    dest.write_text(strict_json(result, indent=1))
    print(result["table_markdown"])
    print(json.dumps(ratios))
    print(f"wrote {dest}")


if __name__ == "__main__":
    np.seterr(all="ignore")
    main()
