"""Dense matcher throughput and accuracy: stereodem ZNCC vs OpenCV StereoSGBM, same run.

A 1024 x 1024 rectified pair is made from the bundled Landsat texture (the fully valid
320 x 320 centre, upsampled x3.2 with bicubic interpolation, plus independent Gaussian noise
of 1 DN in each image) and a smooth disparity field in about 8..56 px (slopes up to ~0.1 px/px); all
matchers search the same 64 disparities 0..63.  Throughput is megapixels x disparities per second
(1024 * 1024 * 64 / 1e6 / seconds); accuracy is the RMS disparity error over the valid
pixels and the share of valid pixels (and of pixels with error > 1 px, counting invalid as
errors).

    python benchmarks/bench_match.py [--before REV] [--repeats N]

``--before REV`` also times the SGM wrapper as it was at git revision REV (before/after, same
run, bit-identity checked). Writes ``benchmarks/results/bench_match.json`` and prints a table.
"""

from __future__ import annotations

import json
import platform
import time
from pathlib import Path

import cv2
import numpy as np
import rasterio

from stereodem.core.jsonutil import dumps as strict_json
from stereodem.stereo.match import match_rectified
from stereodem.stereo.score import _zncc_left, _zncc_warped
from stereodem.stereo.sgm import _sgbm, _to_uint8

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results" / "bench_match.json"
SIZE = 1024
DMIN, DMAX = 0, 63
ND = DMAX - DMIN + 1
REPEATS = 21


def make_pair(size=SIZE, seed=0):
    """Left, right (float32) and the true left disparity (left(x) ~ right(x - d))."""
    with rasterio.open(ROOT / "sensor" / "data" / "landsat_texture.tif") as f:
        rgb = f.read().astype(np.float32)
    base = rgb.mean(axis=0)[260:580, 100:420]  # fully valid 320 x 320 window
    tex = cv2.resize(base, (size, size), interpolation=cv2.INTER_CUBIC)
    y, x = np.mgrid[0:size, 0:size].astype(np.float32)
    # smooth disparity field, defined on right-image coordinates: right(xr) = left(xr + D(xr))
    D = (
        32
        + 20 * np.sin(2 * np.pi * x / 2000) * np.cos(2 * np.pi * y / 1500)
        + 4 * np.sin(2 * np.pi * (x + y) / 600)
    ).astype(np.float32)
    rng = np.random.default_rng(seed)
    left = tex + rng.normal(0, 1, tex.shape).astype(np.float32)
    right = cv2.remap(tex, x + D, y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    right += rng.normal(0, 1, tex.shape).astype(np.float32)
    # true left disparity: d(x) = D(x - d(x)), fixed-point iteration
    d = D.copy()
    for _ in range(20):
        d = cv2.remap(D, x - d, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    # left pixels whose match falls outside the right image have no truth
    d[(x - d) < 0] = np.nan
    return left, right, d


def accuracy(disp, truth):
    ok = np.isfinite(truth)
    err = disp[ok] - truth[ok]
    valid = np.isfinite(err)
    return {
        "valid_percent": round(100 * float(valid.mean()), 2),
        "rms_error_px": round(float(np.sqrt(np.mean(err[valid] ** 2))), 4),
        "bad1_percent_invalid_counted": round(
            100 * float(np.mean(~valid | (np.abs(np.nan_to_num(err, nan=99)) > 1))), 2
        ),
    }


def timed(fn, repeat=3):
    best, out = np.inf, None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def main(argv=None):
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--before",
        metavar="REV",
        help="also time the SGM wrapper of this git revision (before/after)",
    )
    ap.add_argument(
        "--repeats",
        type=int,
        default=REPEATS,
        help=f"alternating repeats of the SGM overhead timings (default {REPEATS})",
    )
    args = ap.parse_args(argv)
    left, right, truth = make_pair()
    mpd = SIZE * SIZE * ND / 1e6
    rows = []
    threads = cv2.getNumThreads()

    def run(name, fn, note, nthreads=None):
        if nthreads is not None:
            cv2.setNumThreads(nthreads)
        try:
            sec, disp = timed(fn)
        finally:
            cv2.setNumThreads(threads)
        row = {
            "matcher": name,
            "seconds": round(sec, 3),
            "mpx_disp_per_s": round(mpd / sec, 1),
            "note": note,
        }
        row.update(accuracy(disp, truth))
        rows.append(row)

    l8, r8 = _to_uint8(left, right)
    run(
        "stereodem ncc, single-scale full search (7x7)",
        lambda: match_rectified(left, right, (DMIN, DMAX), levels=0).disparity,
        "ZNCC 7x7, parabola sub-pixel, L-R check 1 px, score >= 0.5, both views",
    )
    run(
        "stereodem ncc, coarse-to-fine (7x7)",
        lambda: match_rectified(left, right, (DMIN, DMAX)).disparity,
        "auto levels (2), margin 2 px, both views at each level",
    )
    run(
        "stereodem sgm (OpenCV SGBM via match_rectified)",
        lambda: match_rectified(left, right, (DMIN, DMAX), matcher="sgm").disparity,
        "includes 8-bit stretch, border padding, ZNCC score layer",
    )
    for mode, label, nthr in (
        ("sgbm", "cv2.StereoSGBM MODE_SGBM, 1 thread", 1),
        ("3way", "cv2.StereoSGBM MODE_SGBM_3WAY, default threads", None),
    ):
        run(
            label,
            lambda mode=mode: _raw_sgbm(l8, r8, mode),
            "blockSize 5, P1 8*25, P2 32*25, uniqueness 10, speckle 100/2, disp12MaxDiff 1, "
            "no padding (first 64 columns invalid)",
            nthr,
        )
    overhead = sgm_overhead(left, right, l8, r8, repeats=args.repeats)
    if args.before:
        overhead["before_after"] = sgm_before_after(
            left, right, l8, r8, args.before, repeats=args.repeats
        )
        print("sgm before/after:", json.dumps(overhead["before_after"]))
    result = {
        "pair": f"{SIZE}x{SIZE} Landsat texture x3.2 + smooth disparity ~8..56 px, noise 1 DN",
        "disparities": ND,
        "machine": {
            "cpus": __import__("os").cpu_count(),
            "python": platform.python_version(),
            "opencv": cv2.__version__,
            "opencv_threads": threads,
        },
        "reference_2core": {
            "sgbm_1thread_mpx_d_s": 448,
            "sgbm_3way_mpx_d_s": 1156,
            "numpy_opencv_zncc7_mpx_d_s": "100-170",
        },
        "results": rows,
        "sgm_overhead": overhead,
        "load_average": [round(x, 2) for x in __import__("os").getloadavg()],
    }
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(strict_json(result, indent=2))
    print(f"{'matcher':58s} {'s':>7s} {'Mpx.d/s':>8s} {'valid%':>7s} {'RMS px':>7s} {'bad1%':>6s}")
    for r in rows:
        print(
            f"{r['matcher']:58s} {r['seconds']:7.3f} {r['mpx_disp_per_s']:8.1f} "
            f"{r['valid_percent']:7.2f} {r['rms_error_px']:7.4f} "
            f"{r['bad1_percent_invalid_counted']:6.2f}"
        )
    for o in overhead["by_threads"]:
        print(
            f"sgm overhead, {o['threads']} thread(s): stereodem {o['stereodem_cpu_s']:.3f} s CPU "
            f"/ {o['stereodem_wall_s']:.3f} s wall, bare SGBM {o['bare_cpu_s']:.3f} / "
            f"{o['bare_wall_s']:.3f} s: ratio {o['ratio_cpu']:.3f} CPU, "
            f"{o['ratio_wall']:.3f} wall, "
            f"{o['ratio_cpu_of_minima']:.3f} CPU of the minima; paired "
            f"{o['ratio_cpu_paired']:.3f} CPU, {o['ratio_wall_paired']:.3f} wall"
        )
    print("sgm parts, 1 thread, % of the bare call:", overhead["parts_1thread"]["percent_of_bare"])
    print(f"wrote {OUT}")


def sgm_overhead(left, right, l8, r8, repeats=REPEATS, threads=(1, 2)):
    """``match_rectified(matcher="sgm")`` against the bare ``cv2.StereoSGBM`` call it wraps,
    on the same tile at the same ``cv2.setNumThreads``, the two alternating ``repeats`` times;
    medians of wall and CPU seconds (this process, all threads) and their ratios.

    The bare call gets the wrapper's uint8 images and the same SGBM parameters (64
    disparities), and converts its result to float disparities with NaN where invalid (what
    any caller does); the wrapper adds the 8-bit stretch, the border padding (so the first 64
    columns get disparities: 6 % more columns at 1024 px), the no-data handling and the ZNCC
    score layer."""
    import os

    saved = cv2.getNumThreads()
    out = []
    load_before = [round(x, 2) for x in os.getloadavg()]
    try:
        for n in threads:
            cv2.setNumThreads(n)
            t = {"stereodem": [], "bare": []}
            for _ in range(repeats):
                for name, fn in (
                    (
                        "stereodem",
                        lambda: match_rectified(left, right, (DMIN, DMAX), matcher="sgm"),
                    ),
                    ("bare", lambda: _raw_sgbm(l8, r8, "sgbm")),
                ):
                    w0, c0 = time.perf_counter(), time.process_time()
                    fn()
                    t[name].append((time.perf_counter() - w0, time.process_time() - c0))
            med = {k: np.median(np.array(v), axis=0) for k, v in t.items()}
            low = {k: np.min(np.array(v), axis=0) for k, v in t.items()}
            # each stereodem call over the bare call just after it: robust to the machine's
            # speed drifting during the run (other tenants of a shared VM)
            pair = np.median(np.array(t["stereodem"]) / np.array(t["bare"]), axis=0)
            out.append(
                {
                    "threads": n,
                    "repeats": repeats,
                    "stereodem_wall_s": round(float(med["stereodem"][0]), 4),
                    "stereodem_cpu_s": round(float(med["stereodem"][1]), 4),
                    "bare_wall_s": round(float(med["bare"][0]), 4),
                    "bare_cpu_s": round(float(med["bare"][1]), 4),
                    "ratio_wall": round(float(med["stereodem"][0] / med["bare"][0]), 3),
                    "ratio_cpu": round(float(med["stereodem"][1] / med["bare"][1]), 3),
                    "ratio_cpu_of_minima": round(float(low["stereodem"][1] / low["bare"][1]), 3),
                    "ratio_wall_paired": round(float(pair[0]), 3),
                    "ratio_cpu_paired": round(float(pair[1]), 3),
                }
            )
        parts = sgm_parts(left, right, l8, r8, repeats)
    finally:
        cv2.setNumThreads(saved)
    return {
        "what": "match_rectified(matcher='sgm') / bare cv2.StereoSGBM.compute (+ float "
        "conversion), same 1024x1024 tile, same cv2.setNumThreads, interleaved "
        "(alternating) repeats, medians (and the ratio of the minima; *_paired: the median of "
        "each call's ratio to the bare call next to it); target <= 1.15 (issue 28)",
        "by_threads": out,
        "parts_1thread": parts,
        "load_average_before_after": [load_before, [round(x, 2) for x in os.getloadavg()]],
    }


def sgm_parts(left, right, l8, r8, repeats=REPEATS):
    """Where the wrapper's time goes at 1 thread: CPU seconds (medians, interleaved) of the
    bare call, the wrapper's padded SGBM call (the padding's cost is the difference), the
    8-bit stretch of both images, and the score layer (left and warped windows, band by
    band); in % of the bare call as well.  The parts are called as the wrapper calls them on
    this pair: told that the images have no NaN (the wrapper's one scan per image is in its
    glue)."""
    cv2.setNumThreads(1)
    disp = _sgbm(l8, r8, DMIN, DMAX)
    lw = _zncc_left(left, 7, finite=True)
    fns = {
        "bare_sgbm": lambda: _raw_sgbm(l8, r8, "sgbm"),
        "padded_sgbm": lambda: _sgbm(l8, r8, DMIN, DMAX),
        "stretch_8bit": lambda: _to_uint8(left, right, finite=(True, True)),
        "score": lambda: _zncc_warped(lw, right, disp, right_finite=True),
        "wrapper": lambda: match_rectified(left, right, (DMIN, DMAX), matcher="sgm"),
    }
    ts = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            c0 = time.process_time()
            fn()
            ts[k].append(time.process_time() - c0)
    med = {k: float(np.median(v)) for k, v in ts.items()}
    return {
        "cpu_s": {k: round(v, 4) for k, v in med.items()},
        "percent_of_bare": {k: round(100 * v / med["bare_sgbm"], 1) for k, v in med.items()},
    }


def load_matcher(rev):
    """The dense matcher of git revision ``rev``: its ``stereo/match.py`` and the modules
    that imports relatively (``.ncc``, ``.sgm``, ``.score``, ... where the matcher is split
    into them; only ``.pyramid`` where ``match.py`` held it all), all of them the
    revision's: its ``stereo/*.py`` are written to a temporary folder, the ``__path__`` of a
    package of their own (``stereodem.stereo._at_<commit>``), and ``match`` is imported
    from there. Absolute imports (``stereodem.core...``, ``stereodem.stereo.settings``)
    are today's, except the 8-bit stretch: a loaded module's ``linear_to_uint8`` is that of
    the revision's ``core/stretch.py`` (where it has one). Returns the ``match`` module."""
    import atexit
    import importlib
    import importlib.util
    import io
    import re
    import shutil
    import subprocess
    import sys
    import tarfile
    import tempfile
    import types

    def git(*args):
        return subprocess.run(
            ["git", "-C", str(ROOT), *args], capture_output=True, check=True
        ).stdout

    commit = git("rev-parse", "--verify", f"{rev}^{{commit}}").decode().strip()
    tmp = Path(tempfile.mkdtemp(prefix="bench_match_"))
    atexit.register(shutil.rmtree, tmp, ignore_errors=True)  # functions may import late
    # the revision's stereo/ and core/ (core/stretch.py where it has one)
    with tarfile.open(fileobj=io.BytesIO(git("archive", commit, "stereo", "core"))) as tar:
        for m in tar.getmembers():
            if m.isfile() and re.fullmatch(r"(stereo/\w+|core/stretch)\.py", m.name):
                dst = tmp / m.name
                dst.parent.mkdir(exist_ok=True)
                dst.write_bytes(tar.extractfile(m).read())
    package = f"stereodem.stereo._at_{commit[:12]}"
    if package not in sys.modules:
        pkg = types.ModuleType(package)
        pkg.__path__ = [str(tmp / "stereo")]
        sys.modules[package] = pkg
    match = importlib.import_module(f"{package}.match")
    stretch_py = tmp / "core" / "stretch.py"
    if stretch_py.exists():  # the stretch moved to core/stretch.py at some revision
        spec = importlib.util.spec_from_file_location(f"{package}_stretch", stretch_py)
        stretch = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(stretch)
        for name, module in list(sys.modules.items()):
            if name.startswith(f"{package}.") and hasattr(module, "linear_to_uint8"):
                module.linear_to_uint8 = stretch.linear_to_uint8
    return match


def sgm_before_after(left, right, l8, r8, rev, repeats=REPEATS, threads=(1, 2)):
    """The SGM wrapper of git revision ``rev`` (its matcher and 8-bit stretch, loaded by
    :func:`load_matcher`) against today's and the bare call,
    alternating (the order of the three rotates from one repeat to the next, so none always
    follows another), at each of ``threads`` (``cv2.setNumThreads``), wall and CPU seconds
    (medians, and the medians of each repeat's ratios to its bare call; the first thread
    count's CPU figures also at the top level); also whether the two wrappers' disparities
    and scores are bit-identical, and the largest score change."""
    before = load_matcher(rev)
    saved = cv2.getNumThreads()
    fns = {
        "before": lambda: before.match_rectified(left, right, (DMIN, DMAX), matcher="sgm"),
        "now": lambda: match_rectified(left, right, (DMIN, DMAX), matcher="sgm"),
        "bare": lambda: _raw_sgbm(l8, r8, "sgbm"),
    }
    rows = []
    try:
        for n in threads:
            cv2.setNumThreads(n)
            ts = {k: [] for k in fns}  # (wall, CPU) seconds of each call
            names = list(fns)
            for i in range(repeats):
                for k in names[i % 3 :] + names[: i % 3]:
                    w0, c0 = time.perf_counter(), time.process_time()
                    fns[k]()
                    ts[k].append((time.perf_counter() - w0, time.process_time() - c0))
            t = {k: np.array(v) for k, v in ts.items()}
            med = {k: np.median(v, axis=0) for k, v in t.items()}
            pair = {k: np.median(t[k] / t["bare"], axis=0) for k in ("before", "now")}
            rows.append(
                {
                    "threads": n,
                    "cpu_s": {k: round(float(v[1]), 4) for k, v in med.items()},
                    "wall_s": {k: round(float(v[0]), 4) for k, v in med.items()},
                    "ratio_before": round(float(med["before"][1] / med["bare"][1]), 3),
                    "ratio_now": round(float(med["now"][1] / med["bare"][1]), 3),
                    "ratio_before_paired": round(float(pair["before"][1]), 3),
                    "ratio_now_paired": round(float(pair["now"][1]), 3),
                    "ratio_before_wall": round(float(med["before"][0] / med["bare"][0]), 3),
                    "ratio_now_wall": round(float(med["now"][0] / med["bare"][0]), 3),
                    "ratio_before_wall_paired": round(float(pair["before"][0]), 3),
                    "ratio_now_wall_paired": round(float(pair["now"][0]), 3),
                }
            )
        a, b = fns["before"](), fns["now"]()  # MatchResult: disparity, score
    finally:
        cv2.setNumThreads(saved)
    same = all(
        np.array_equal(x, y, equal_nan=True)
        for x, y in ((a.disparity, b.disparity), (a.score, b.score))
    )
    both = np.isfinite(a.score) & np.isfinite(b.score)
    first = rows[0]  # the first thread count's figures at the top level, as before
    return {
        "revision": rev,
        "threads": first["threads"],
        "repeats": repeats,
        "cpu_s": first["cpu_s"],
        "ratio_before": first["ratio_before"],
        "ratio_now": first["ratio_now"],
        "ratio_before_paired": first["ratio_before_paired"],
        "ratio_now_paired": first["ratio_now_paired"],
        "by_threads": rows,
        "bit_identical": bool(same),
        "disparity_identical": bool(np.array_equal(a.disparity, b.disparity, equal_nan=True)),
        "score_same_cells": bool(np.array_equal(np.isfinite(a.score), np.isfinite(b.score))),
        "score_max_abs_change": float(np.max(np.abs(a.score[both] - b.score[both]), initial=0)),
    }


def _raw_sgbm(l8, r8, mode):
    """Plain OpenCV call (no padding, no score layer) for the peer rows."""
    b2 = 25
    sgbm = cv2.StereoSGBM_create(
        minDisparity=DMIN,
        numDisparities=ND,
        blockSize=5,
        P1=8 * b2,
        P2=32 * b2,
        disp12MaxDiff=1,
        preFilterCap=63,
        uniquenessRatio=10,
        speckleWindowSize=100,
        speckleRange=2,
        mode={"sgbm": cv2.STEREO_SGBM_MODE_SGBM, "3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY}[mode],
    )
    raw = sgbm.compute(l8, r8)
    disp = raw.astype(np.float32) / 16
    disp[raw < DMIN * 16] = np.nan
    return disp


if __name__ == "__main__":
    main()
