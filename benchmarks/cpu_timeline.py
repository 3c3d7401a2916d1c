"""Where a job leaves cores idle: ``stereodem run CONFIG`` with its process tree's CPU sampled
every ``--every`` seconds, and, per stage, the seconds during which the job kept fewer than
``--busy`` cores busy (its serial parts on this machine) and its mean number of busy cores.

Sampling is of the job's own processes (psutil: the main process and every descendant, user +
system CPU seconds), not of the machine, so other tenants of a shared machine do not count as
the job's work; they still slow it, so run it on a quiet machine. The stage windows are
``run.json``'s stage seconds laid end to end from the job's start (its stages are sequential;
the background writer's work overlaps the later stages and counts in them).

    python benchmarks/cpu_timeline.py /tmp/bench_scaling/w2.toml [--every 0.1] [--busy 1.5]
        [--json benchmarks/results/cpu_timeline.json]

(the configuration ``bench_scaling.py`` writes for 2 workers). Prints a table and writes it
with the samples (``--json``; its line under the README's *Measured figures*).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path


def sample_tree(proc, seen: dict) -> float:
    """CPU seconds so far of ``proc`` and its descendants; ``seen`` keeps each process's last
    figure, so a process that ended still counts with what it had used when last seen."""
    import psutil

    try:
        tree = [proc] + proc.children(recursive=True)
    except psutil.Error:
        tree = []
    for q in tree:
        try:
            c = q.cpu_times()
            seen[q.pid] = c.user + c.system  # not children_*: the ended ones are in seen
        except psutil.Error:
            pass
    return sum(seen.values())


def stage_windows(run_json: dict, job_end: float) -> list[tuple[str, float, float]]:
    """(stage, start, end) in seconds since the command started, the stages laid end to end
    back from the job's end."""
    stages = [(k, float(v["seconds"])) for k, v in run_json["stages"].items()]
    t = job_end - float(run_json["seconds"])
    out = [("start", 0.0, t)]
    for name, s in stages:
        out.append((name, t, t + s))
        t += s
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("config", help="a stereodem run configuration (TOML)")
    ap.add_argument("--every", type=float, default=0.1, help="sampling period (s)")
    ap.add_argument("--busy", type=float, default=1.5, help="cores below which a sample is serial")
    ap.add_argument(
        "--json",
        default=str(Path(__file__).resolve().parent / "results" / "cpu_timeline.json"),
        help="write the samples and the table here (default results/cpu_timeline.json)",
    )
    args = ap.parse_args(argv)
    import psutil

    env = dict(os.environ)
    env.pop("PYTHONDONTWRITEBYTECODE", None)  # as an installed package: bytecode cached
    cmd = [sys.executable, "-m", "stereodem.cli", "-q", "run", args.config, "--overwrite"]
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, env=env, stderr=subprocess.PIPE, text=True)
    proc, seen, samples = psutil.Process(p.pid), {}, []
    while p.poll() is None:
        samples.append((time.perf_counter() - t0, sample_tree(proc, seen)))
        time.sleep(args.every)
    end = time.perf_counter() - t0
    err = p.stderr.read()
    if p.returncode:
        raise SystemExit(f"the run failed:\n{err[-2000:]}")
    import tomllib

    out_dir = Path(tomllib.loads(Path(args.config).read_text())["output"]["dir"])
    info = json.loads((out_dir / "run.json").read_text())
    windows = stage_windows(info, end)
    # busy cores in each sampling interval
    rows = []
    for (ta, ca), (tb, cb) in zip(samples, samples[1:]):
        rows.append((ta, tb, (cb - ca) / max(tb - ta, 1e-9)))
    table = []
    for name, a, b in windows:
        inside = [(max(ta, a), min(tb, b), busy) for ta, tb, busy in rows if tb > a and ta < b]
        dur = sum(t1 - t0_ for t0_, t1, _ in inside)
        serial = sum(t1 - t0_ for t0_, t1, busy in inside if busy < args.busy)
        cpu = sum((t1 - t0_) * busy for t0_, t1, busy in inside)
        table.append(
            dict(
                stage=name,
                wall_s=round(b - a, 2),
                serial_s=round(serial, 2),
                mean_busy_cores=round(cpu / dur, 2) if dur else None,
            )
        )
    serial_head = f"< {args.busy:.1f} cores s"
    print(f"{'stage':10s} {'wall s':>7s} {serial_head:>14s} {'busy cores':>10s}")
    for r in table:
        print(
            f"{r['stage']:10s} {r['wall_s']:7.2f} {r['serial_s']:14.2f} "
            f"{r['mean_busy_cores'] if r['mean_busy_cores'] is not None else '-':>10}"
        )
    total_serial = sum(r["serial_s"] for r in table)
    print(f"total wall {end:.2f} s, serial {total_serial:.2f} s, CPU {samples[-1][1]:.1f} s")
    if args.json:
        Path(args.json).write_text(
            json.dumps(
                dict(
                    config=args.config,
                    cpus=os.cpu_count(),
                    wall_s=end,
                    every_s=args.every,
                    busy_threshold=args.busy,
                    load_average=os.getloadavg(),
                    stages=table,
                    samples=samples,
                ),
                indent=1,
            )
        )


if __name__ == "__main__":
    main()
