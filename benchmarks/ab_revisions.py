"""Before/after in one run: ``stereodem run`` on the full simulated granule with two
installations of stereodem (an older revision and this one), alternating, at 1 and 2 workers.

The scene and its configurations are ``bench_scaling.py``'s (run it once first: it writes
``OUT/w1.toml`` and ``OUT/w2.toml``). The older revision runs from its own environment, e.g.::

    git worktree add /tmp/wt-before REV
    python -m venv --system-site-packages /tmp/venv-before
    /tmp/venv-before/bin/pip install --no-deps --no-build-isolation -e /tmp/wt-before
    python benchmarks/ab_revisions.py /tmp/venv-before/bin/python [--rounds 3]

Each round runs both installations at 1 worker and at 2 (which one goes first alternates by
round); prints wall and CPU seconds (the job and every process it waited for) of each run, and
per installation the speed-up of 2 workers over 1 by the medians and by round. Machine load
moves both the same way within a round, so the comparison holds where absolute times do not.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path


def timed_run(python: str, cfg: Path) -> tuple[float, float]:
    """Wall and CPU seconds of ``stereodem run CFG --overwrite`` with ``python``."""
    env = dict(os.environ)
    env.pop("PYTHONDONTWRITEBYTECODE", None)  # an installed package has its bytecode cached
    c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(
        [python, "-m", "stereodem.cli", "-q", "run", str(cfg), "--overwrite"],
        env=env,
        cwd="/",
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        check=True,
    )
    wall = time.perf_counter() - t0
    c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (c1.ru_utime + c1.ru_stime) - (c0.ru_utime + c0.ru_stime)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before_python", help="the Python of the older revision's environment")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", default="/tmp/bench_scaling", help="bench_scaling.py's --out")
    args = ap.parse_args(argv)
    cfgs = {w: Path(args.out) / f"w{w}.toml" for w in (1, 2)}
    missing = [str(p) for p in cfgs.values() if not p.exists()]
    if missing:
        sys.exit(f"{', '.join(missing)}: missing; run benchmarks/bench_scaling.py first")
    pythons = {"before": args.before_python, "now": sys.executable}
    walls = {(k, w): [] for k in pythons for w in cfgs}
    for r in range(args.rounds):
        order = ("before", "now") if r % 2 == 0 else ("now", "before")
        for w, cfg in cfgs.items():
            for k in order:
                wall, cpu = timed_run(pythons[k], cfg)
                walls[(k, w)].append(wall)
                load = os.getloadavg()[0]
                print(
                    f"round {r}: {k:6s} {w} worker(s): {wall:6.2f} s wall, {cpu:6.1f} CPU s, "
                    f"load {load:.2f}",
                    flush=True,
                )
    for k in pythons:
        one, two = walls[(k, 1)], walls[(k, 2)]
        print(
            f"{k}: 1 worker {[round(x, 2) for x in one]}, 2 workers {[round(x, 2) for x in two]}; "
            f"2 vs 1 by the medians {statistics.median(one) / statistics.median(two):.3f}, "
            f"by round {[round(a / b, 3) for a, b in zip(one, two)]}"
        )


if __name__ == "__main__":
    main()
