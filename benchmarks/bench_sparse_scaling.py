"""Cost of the sparse stage (SIFT matches -> relative pointing -> terrain heights) against the
scene size: simulated ``aster`` pairs of 800², 1600² and 3200² pixels.

Keypoints are detected on images reduced to at most 512 px a side and refined at full
resolution, so the cost should grow far slower than the pixel count. Writes
``benchmarks/results/bench_sparse_scaling.json`` (wall and CPU seconds, matches, height range).

Usage: ``python benchmarks/bench_sparse_scaling.py``
"""

from __future__ import annotations

import time
from pathlib import Path

from stereodem.core.jsonutil import dumps as strict_json
from stereodem.sensor.simulation.simulate import simulate_scene
from stereodem.stereo.sparse_stage import run_sparse_stage

HERE = Path(__file__).resolve().parent


def main(sizes=(800, 1600, 3200)):
    rows = []
    for n in sizes:
        s = simulate_scene("aster", size=(n, n), seed=1)
        lo, hi = s.truth_dem.height_range()
        c, w = time.process_time(), time.perf_counter()
        st = run_sparse_stage(s.left, s.right, s.left_model, s.right_model)
        rows.append(
            dict(
                size=n,
                wall_s=round(time.perf_counter() - w, 2),
                cpu_s=round(time.process_time() - c, 2),
                stages_s={k: round(v, 3) for k, v in st.seconds.items()},
                matches=len(st.matches),
                height_range_m=[round(v) for v in st.height_range],
                truth_dem_range_m=[round(float(lo)), round(float(hi))],
            )
        )
        print(rows[-1], flush=True)
    out = HERE / "results" / "bench_sparse_scaling.json"
    out.write_text(
        strict_json(
            dict(
                runs=rows,
                note="2-core machine shared with other jobs: wall "
                "times under contention; CPU seconds are the steadier figure",
            ),
            indent=2,
        )
        + "\n"
    )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
