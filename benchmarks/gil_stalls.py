"""Where a job holds Python's GIL for long: ``stereodem run CONFIG`` in this process beside a
thread that wakes every 2 ms; each time it could not run for longer than ``--min-ms``, the
stall is listed with the other threads' innermost frames as the ticker found them on waking.

A stall is a C call that keeps the GIL while it works (every other thread of the run waits:
the background writer's overlap, the row-band threads). Closing a rasterio dataset opened with
``driver="COG"`` was one (GDAL's CreateCopy holding the GIL: 10-11 stalls, 2.58-2.64 s in a
full-granule run at 2 workers, before :func:`stereodem.core.raster.write_geotiff` copied a MEM
dataset with ``rasterio.shutil.copy`` instead: 0-2 stalls, at most 0.12 s, left).

    python benchmarks/gil_stalls.py /tmp/bench_scaling/w2.toml [--min-ms 50] [--top 25]

(the configuration ``bench_scaling.py`` writes for 2 workers). A diagnostic: it prints, it
writes no result file.
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time
import traceback


def _innermost(frame, depth=3) -> str:
    stack = traceback.extract_stack(frame)[-depth:]
    return " > ".join(f"{os.path.basename(f.filename)}:{f.name}:{f.lineno}" for f in stack)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("config", help="a stereodem run configuration (TOML)")
    ap.add_argument("--min-ms", type=float, default=50.0, help="shortest stall listed (ms)")
    ap.add_argument("--top", type=int, default=25, help="longest stalls printed")
    args = ap.parse_args(argv)
    from stereodem.cli import main as cli

    limit = args.min_ms / 1000.0
    stalls, done, t0 = [], threading.Event(), time.perf_counter()

    def ticker():
        last = time.perf_counter()
        while not done.is_set():
            time.sleep(0.002)
            now = time.perf_counter()
            if now - last > limit:
                me = threading.get_ident()
                frames = sys._current_frames()
                others = [_innermost(f) for tid, f in frames.items() if tid != me]
                stalls.append((last - t0, now - last, others))
            last = now

    th = threading.Thread(target=ticker, daemon=True, name="gil-ticker")
    th.start()
    try:
        cli(["-q", "run", args.config, "--overwrite"])
    except SystemExit as stop:
        if stop.code not in (0, None):
            raise
    finally:
        done.set()
        th.join()
    total = sum(s[1] for s in stalls)
    print(f"stalls over {args.min_ms:g} ms: {len(stalls)}, {total:.2f} s in all")
    for t, d, others in sorted(stalls, key=lambda s: -s[1])[: args.top]:
        print(f"at {t:7.2f} s  {d:5.2f} s | " + " || ".join(others))


if __name__ == "__main__":  # the tile pool's workers import this script: keep the job here
    main()
