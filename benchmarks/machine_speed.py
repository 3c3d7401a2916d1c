"""The machine's speed at the time of a measurement, for comparing figures taken on different
(shared, drifting) machines: :func:`speed_index`. Recorded by ``bench_scaling.py`` and
``bench_aster_scene.py`` with their runs, and quoted by ``readme_figures.py`` beside them."""

from __future__ import annotations

import time

import numpy as np

#: what :func:`speed_index` measures, stored beside its figures
WHAT = (
    "ms of one bare cv2.StereoSGBM call (MODE_SGBM, 1 thread, 64 disparities) on "
    "bench_match.py's 1024 x 1024 pair, median of 9, before and after the runs"
)


def speed_index(repeats=9):
    """Milliseconds of one bare ``cv2.StereoSGBM`` call (MODE_SGBM, 1 thread, 64 disparities)
    on ``bench_match.py``'s 1024 x 1024 pair, median of ``repeats``; measured before and after
    a benchmark's runs, so that figures from different sessions (shared machines that drift)
    can be compared."""
    import cv2
    from bench_match import _raw_sgbm, _to_uint8, make_pair

    left, right, _ = make_pair()
    l8, r8 = _to_uint8(left, right)
    saved = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        ts = []
        for _ in range(repeats):
            t = time.perf_counter()
            _raw_sgbm(l8, r8, "sgbm")
            ts.append(time.perf_counter() - t)
    finally:
        cv2.setNumThreads(saved)
    return round(1e3 * float(np.median(ts)), 1)
