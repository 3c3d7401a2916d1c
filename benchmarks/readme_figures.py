"""Print the README's list of measured figures, regenerated from ``benchmarks/results/*.json``.

    python benchmarks/readme_figures.py            # Markdown block on stdout
    python benchmarks/readme_figures.py --results DIR
    python benchmarks/readme_figures.py --write    # README's list, benchmarks/README's table

Each result file has its own summariser (the figures a reader needs, with the command that
measured them); a file without one is listed by name, and a summariser that no longer finds
its keys (the benchmark's output changed) says so on stderr and in the block, instead of
printing stale numbers. ``--write`` puts the list into README.md and the same summaries into
the table of benchmarks/README.md (between their markers); tests/app/test_products_docs.py checks
that both are what the result files give.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"

#: bench_scaling_full_forkserver's command, same code path, on the machines of other sessions:
#: the 2-core ratios are shown for every machine
OTHER_MACHINE = "bench_scaling_full_forkserver_fast_machine"
SESSION_33 = "bench_scaling_full_forkserver_session33"
SESSION_34 = "bench_scaling_full_forkserver_session34"
SESSION_35 = "bench_scaling_full_forkserver_session35"
OTHER_MACHINES = (OTHER_MACHINE, SESSION_33, SESSION_34, SESSION_35)


def _x(v, nd=1):
    return f"{v:.{nd}f}×"


def demo(d):
    f = d["default_seed_figures"]
    c = d["cog_writing"]
    return (
        f"`stereodem demo` (600 × 600 simulated ASTER-like pair, `benchmarks/bench_demo.py`): "
        f"DEM − truth NMAD {f['nmad_m']:.2f} m, median {f['median_m']:+.2f} m, LE90 "
        f"{f['le90_m']:.2f} m, {f['valid_pct']:.1f} % of the DEM's footprint valid, "
        f"{c.get('fastest_demo_wall_seconds', f['wall_seconds']):.1f} s end to end; over seeds "
        f"1–{len(d['runs']) - 2} the NMAD moves by up to {d['spread_over_seeds']['nmad_m']:.2f} m "
        f"(LE90 {d['spread_over_seeds']['le90_m']:.2f} m). Writing its rasters as Cloud-Optimised "
        f"GeoTIFFs (predictor, overviews) costs {c['extra_seconds']:+.2f} s "
        f"({100 * c['extra_fraction_of_demo_wall']:.1f} % of the run) against plain tiled "
        f"GeoTIFFs; files {c['old_bytes'] / 1e6:.2f} → {c['cog_bytes'] / 1e6:.2f} MB."
    )


def rpc(d):
    p, loc = d["project"], d["localize"]
    g6 = loc["gdal_1e-6px"]
    return (
        f"RPC model vs GDAL's RPC transformer, {d['n_points'] / 1e6:g} M points "
        f"(`benchmarks/bench_rpc.py`): `project` {_x(p['speedup'])} faster (agreement "
        f"{p['max_abs_diff_px']:.0e} px), exact `localize` {_x(g6['speedup'])} faster than "
        f"GDAL at 1e-6 px."
    )


def aster_scene(d):
    dr = {r["workers"]: r for r in d["dem_runs"]}
    rr = {r["workers"]: r for r in d["runs"]}
    same = all(all(v.values()) for v in d.get("bit_identical", {}).values())
    return (
        f"Full ASTER-sized simulated pair, 3N {d['size'][0]} × {d['size'][1]} and 3B "
        f"{d['right_size'][0]} × {d['right_size'][1]} pixels (`benchmarks/bench_aster_scene.py`): "
        f"`stereodem dem` in **{dr[1]['wall_s']:.1f} s with 1 worker, {dr[2]['wall_s']:.1f} s "
        f"with 2 ({d['speedup_dem']:.2f}×)**, peak {dr[1]['peak_rss_mb_all_processes'] / 1e3:.1f}–"
        f"{dr[2]['peak_rss_mb_all_processes'] / 1e3:.1f} GB over all processes; `stereodem run` "
        f"{rr[1]['wall_s']:.1f} s → {rr[2]['wall_s']:.1f} s (stereo stage "
        f"{d['speedup_stereo']:.2f}×), DEM NMAD {rr[1]['headline']['nmad']:.2f} m against the "
        f"truth."
        + (" Rasters are bit-identical between 1 and 2 workers." if same else "")
        + (_speed(d) if "machine" in d else "")
    )


def dem(d):
    r = {x["matcher"]: x for x in d["runs"]}
    s = r["sgm"]
    out = (
        f"Real Pleiades pair vs s2p's DSM (`benchmarks/bench_dem.py`): **NMAD "
        f"{s['nmad_m']:.3f} m**, median {s['median_offset_m']:+.2f} m, "
        f"**{100 * s['coverage_of_s2p_valid']:.1f} %** of s2p's valid cells covered, in "
        f"{s['seconds']:.1f} s (s2p's time {d['s2p_time']})"
        + (
            f"; OpenCV {d['opencv']}, load average {d['load_average_at_end'][0]:.1f} at the end "
            "(times are upper bounds)."
            if "load_average_at_end" in d
            else "."
        )
    )
    if "ncc" in r:
        n = r["ncc"]
        out += (
            f" With `--matcher ncc`: {n['nmad_m']:.3f} m, {100 * n['coverage_of_s2p_valid']:.1f} "
            f"%, {n['seconds']:.1f} s."
        )
    un = d.get("untuned_pairs") or []
    if un:
        out += (
            " The defaults were tuned on that pair; on the pairs of the Pleiades triplet over "
            "Marseille (automatic heights, against s2p's DSM of the triplet): "
            + "; ".join(
                f"{r['pair'].split('/')[-1]} "
                + (
                    f"failed ({r['error'][:80]})"
                    if "error" in r
                    else f"NMAD {r['nmad_m']:.2f} m, median {r['median_offset_m']:+.2f} m, "
                    f"{100 * r['coverage_of_s2p_valid']:.1f} % covered, {r['seconds']:.1f} s"
                )
                for r in un
            )
            + "."
        )
    return out


def match(d):
    parts = ", ".join(
        f"{r['matcher'].split(' (')[0]} {r['mpx_disp_per_s']:.0f}" for r in d["results"]
    )
    out = (
        f"Dense matching, {d['pair'].split(' ')[0]}, {d['disparities']} disparities "
        f"(`benchmarks/bench_match.py`), Mpx·disparities/s: {parts}."
    )
    o = d.get("sgm_overhead")
    if o:
        parts = "; ".join(
            f"{r['threads']} thread(s): {r['ratio_cpu']:.2f}× CPU, {r['ratio_wall']:.2f}× "
            f"wall ({r['stereodem_cpu_s']:.3f} vs {r['bare_cpu_s']:.3f} CPU s"
            + f"; call by call {r['ratio_cpu_paired']:.3f}× CPU, {r['ratio_wall_paired']:.3f}× wall"
            + (
                f"; {r['ratio_cpu_of_minima']:.2f}× CPU of the minima"
                if "ratio_cpu_of_minima" in r
                else ""
            )
            + ")"
            for r in o["by_threads"]
        )
        out += (
            f" The SGM wrapper (8-bit stretch, padding, no-data, ZNCC score layer) against the "
            f"bare `cv2.StereoSGBM` call, same tile and threads, medians of "
            f"{o['by_threads'][0]['repeats']}: {parts} (target ≤ 1.15×; load "
            f"{d.get('load_average', ['?'])[0]})."
        )
        pb = o.get("parts_1thread", {}).get("percent_of_bare")
        if pb:
            out += (
                f" Where it goes (1 thread, % of the bare call): padded SGBM "
                f"{pb['padded_sgbm']:.0f} %, 8-bit stretch {pb['stretch_8bit']:.1f} %, score layer "
                f"{pb['score']:.1f} %, whole wrapper {pb['wrapper']:.0f} %."
            )
        ba = o.get("before_after")
        if ba and "by_threads" in ba:  # each thread count, CPU and wall
            runs = "; ".join(
                f"{r['threads']} thread(s): {r['ratio_before']:.3f}× → {r['ratio_now']:.3f}× CPU "
                f"(call by call {r['ratio_before_paired']:.3f}× → {r['ratio_now_paired']:.3f}×), "
                f"{r['ratio_before_wall']:.3f}× → {r['ratio_now_wall']:.3f}× wall"
                for r in ba["by_threads"]
            )
            out += (
                f" Before/after in the same run (revision {ba['revision']}, against the bare "
                f"call, medians of {ba['repeats']}): {runs}; outputs " + _outputs_changed(ba)
            )
        elif ba:
            out += (
                f" Before/after in the same run (revision {ba['revision']}, 1 thread, CPU s): "
                f"{ba['ratio_before']:.2f}× → {ba['ratio_now']:.2f}× the bare call (call by call "
                f"{ba['ratio_before_paired']:.3f}× → {ba['ratio_now_paired']:.3f}×), outputs "
                + _outputs_changed(ba)
            )
    return out


def _outputs_changed(ba) -> str:
    """How the SGM wrapper's outputs compare before and after (bench_match's record)."""
    if ba["bit_identical"]:
        return "bit-identical."
    same = "bit-identical" if ba["disparity_identical"] else "changed"
    return f"disparities {same}, scores within {ba['score_max_abs_change']:.1e}."


def scaling(d):
    g, r = d["granule"], d["ratios"]
    rows = "; ".join(
        f"{x['workers']} w: {x['wall_s']:.1f} s wall / {x['cpu_s']:.1f} CPU s, peak "
        f"{x['peak_rss_mb_all_processes']} MB"
        + (f", cores idle {x['idle_core_s']:.1f} s" if "idle_core_s" in x else "")
        + f" (load {x['load_average_before'][0]:.1f})"
        for x in d["runs"]
    )
    same = all(
        all(v.values()) for x in d["runs"] for k, v in x.items() if k.startswith("bit_identical")
    )
    rep = d.get("repeat", 1)
    how = f", the median-wall run of {rep} alternating rounds" if rep > 1 else ""
    return (
        f"Scaling with `--workers` (`benchmarks/bench_scaling.py`, `stereodem run` on a simulated "
        f"V004 granule, 3N {g['left'][0]} × {g['left'][1]}, {d['machine']['cpus']} cores{how}): "
        f"{rows}; "
        + ", ".join(f"{k} {v}" for k, v in r.items())
        + f"; rasters {'bit-identical' if same else 'NOT identical'} across worker counts."
        + _speed(d)
    )


def _speed_tag(d) -> str:
    """`` (machine speed index N–M ms)`` of a result file whose machine's speed was measured
    (before and after its runs: a shared machine drifts), else nothing: figures of the
    targets' table come from different sessions' machines."""
    sp = d.get("machine", {}).get("speed_index_ms")
    if not sp:
        return ""
    lo, hi = min(sp), max(sp)
    said = f"{lo:.0f}" if round(lo) == round(hi) else f"{lo:.0f}–{hi:.0f}"
    return f" (machine speed index {said} ms)"


def _speed(d):
    """The machine's speed index of a scaling run (absent before session 15)."""
    sp = d["machine"].get("speed_index_ms")
    if not sp:
        return ""
    out = (
        f" Machine speed: one bare `cv2.StereoSGBM` call on a 1024² tile (1 thread, 64 "
        f"disparities) took {sp[0]:.0f} ms before the runs and {sp[1]:.0f} ms after."
    )
    ceiling = d["machine"].get("parallel_ceiling")
    if ceiling:  # absent before session 19
        out += (
            " The machine's own ceiling, bare SGBM calls in N processes at once (no stereodem "
            "code; throughput against 1 process, before / after the runs): "
            + _ceiling_parts(ceiling)
            + "."
        )
    stream = d["machine"].get("streaming_ceiling")
    if stream:  # absent before session 21
        out += (
            " Its ceiling for memory-bound work, element-wise NumPy passes over 80 MB arrays in "
            "N processes at once (as the full-size layers' passes of the filters, orthoimages "
            "and assessment): " + _ceiling_parts(stream) + "."
        )
    return out


def _ceiling_parts(ceiling) -> str:
    """``N processes`` speed-up and CPU per call, before / after the runs, of one of
    bench_scaling.py's ceilings (``[before, after]``, each keyed by process count)."""
    before, after = ceiling
    return "; ".join(
        f"{n} processes {before[n]['speedup_vs_1']:.2f}× / {after[n]['speedup_vs_1']:.2f}× "
        f"(CPU per call {before[n]['cpu_per_call_over_1']:.2f} / "
        f"{after[n]['cpu_per_call_over_1']:.2f})"
        for n in before
        if n != "1"
    )


def scaling_16_on_2(d):
    by = {r["workers"]: r for r in d["runs"]}
    hi = max(by)
    parts = []
    for w in (2, hi):
        st = by[w]["stages"]["stereo"]
        parts.append(
            f"{w} w: tiles {st['tile_cpu_s_sum']:.1f} CPU s (median {st['tile_cpu_s_median']:.2f} "
            f"s per tile), workers {st['worker_cpu_s']:.1f} CPU s in all"
        )
    return (
        scaling(d)
        + f" The {hi} workers share {d['machine']['cpus']} cores ({hi // d['machine']['cpus']} "
        "processes per core): the tiles' own CPU seconds, measured in their workers: "
        + "; ".join(parts)
        + "."
    )


def worker_start(d):
    rows = "; ".join(
        f"{r['workers']} workers: {r['forkserver_cpu_s']:.2f} vs {r['spawn_cpu_s']:.2f} CPU s "
        f"({r['forkserver_wall_s']:.2f} vs {r['spawn_wall_s']:.2f} s wall)"
        for r in d["runs"]
    )
    same = all(r["identical"] for r in d["runs"])
    load = d["load_average_before_after"][0][0]
    return (
        "Tile pool start, fork server with the tile code preloaded vs spawned workers "
        f"(`benchmarks/bench_worker_start.py`, 2 × N equal tiles, medians of {d['repeat']}, "
        f"{d['machine']['cpus']} cores, load {load:.1f}): {rows}; results "
        f"{'identical' if same else 'NOT identical'}."
    )


def ortho_pair(d):
    m = d["median"]
    same = all(r["identical_to_first"] for r in d["runs"])
    loads = [r["load_before"] for r in d["runs"]]
    return (
        "Both orthoimages of a pair at once vs one after the other "
        f"(`benchmarks/bench_ortho_pair.py`, {d['grid'][0]} × {d['grid'][1]} cells each, "
        f"{d['threads']} threads, medians of {len(d['runs']) // 2} alternating runs): serial "
        f"{m['serial']['wall_s']:.2f} s wall / {m['serial']['cpu_s']:.2f} s CPU, concurrent "
        f"{m['concurrent']['wall_s']:.2f} s / {m['concurrent']['cpu_s']:.2f} s; outputs "
        f"{'bit-identical' if same else 'NOT identical'}; concurrent / serial wall "
        f"{m['concurrent']['wall_s'] / m['serial']['wall_s']:.2f} (load "
        f"{min(loads):.1f}–{max(loads):.1f} on 2 cores)."
    )


def batch(d):
    b = d["batch"]
    parts = "; ".join(
        f"{k}: {v['wall_s']:.1f} s ({d['speedup_vs_single_runs'][k]:.2f}× the single runs), "
        f"{v['summary']['done']} done, {v['summary']['failed']} failed"
        for k, v in b.items()
    )
    reason = next((v["failed"][0]["reason"] for v in b.values() if v["failed"]), "")
    return (
        f"`stereodem batch` (`benchmarks/bench_batch.py`, {d['scenes']}, {d['workers']} workers): "
        f"sum of single `stereodem run` jobs {d['sum_of_single_runs_wall_s']:.1f} s; {parts}; "
        f'the corrupt scene\'s reason: "{reason[:120]}" (load {d["load_average_before"][0]:.1f}).'
    )


def commands(d):
    parts = "; ".join(
        f"`{r['command']}` {r['w1']['wall_s']:.1f} → {r['w2']['wall_s']:.1f} s "
        f"({r['speedup_2_vs_1']:.2f}×, {r['w2']['cores']:.2f} cores)"
        for r in d["commands"]
    )
    return (
        f"The standalone commands at 1 → 2 workers (`benchmarks/bench_commands.py`, 3000² DEMs "
        f"and the full granule's scene, median of {d['repeat']}): {parts} "
        f"(load {d['load_average'][0]:.1f})."
    )


def ortho(d):
    s = d["speed_ratios"]
    return (
        f"Orthorectification vs GDAL (`benchmarks/bench_ortho.py`, {d['cells'] / 1e6:.1f} M "
        f"cells, same grid, DEM and kernel): "
        f"{d['max_position_difference_vs_gdal_rpc_transformer_px']:.4f} px apart; "
        f"**{_x(s['stereodem_1thread_vs_gdal_1thread'])} faster than GDAL on 1 thread, "
        f"{_x(s['stereodem_2threads_vs_gdal_2threads'])} on 2 threads**."
    )


def ortho_models(d):
    n = max(d["counts"])
    at_n = {r["model"]: r for r in d["records"] if r["n_gcp"] == n}

    def fig(name):
        r = at_n[name]
        return f"{name} refused" if "error" in r else f"{name} {r['icp_rmse_px']:.2f}"

    ok = [m for m in d["ok_twelve"] if m in at_n]
    orbital = [m for m, r in at_n.items() if r.get("family") == "orbital" and m not in ok]
    physical = [m for m, r in at_n.items() if r.get("family") == "physical"]
    return (
        f"Orthorectification models on a simulated ASTER scene "
        f"(`benchmarks/bench_ortho_models.py`): RMSE at {d['n_check']} check points with {n} "
        f"GCPs and {d['noise_px']} px image noise, in px: Ok's twelve: "
        + ", ".join(fig(m) for m in ok)
        + "; orbital: "
        + ", ".join(fig(m) for m in orbital)
        + "; rigorous: "
        + ", ".join(fig(m) for m in physical)
        + " (other GCP counts and all models: `benchmarks/results/bench_ortho_models.md`)."
    )


def orbital_splits(d):
    parts = []
    for view, rows in d["views"].items():
        at = {(r["model"], r["n_gcp"]): r for r in rows}
        ten = ", ".join(
            f"{m} {at[(m, 10)]['median_ratio']:.2f}" for m in ("orun", "toutin") if (m, 10) in at
        )
        five = ", ".join(
            f"{m} {at[(m, 5)]['median_icp_px']:.2f} px (condition "
            f"{at[(m, 5)]['median_condition']:.2g})"
            for m in (d["reference"], "orun", "toutin")
            if (m, 5) in at
        )
        parts.append(f"{view}: {ten} with 10 GCPs; with 5 GCPs median ICP RMSE {five}")
    return (
        f"Orun & Natarajan and Toutin-type models against the rigorous pushbroom model "
        f"(`benchmarks/bench_orbital_splits.py`, simulated ASTER 3N and 3B with ephemeris and "
        f"attitude biases and drifts, {d['n_splits']} random GCP/ICP splits, {d['n_check']} "
        f"check points, {d['noise_px']} px noise), median ICP RMSE ratio to "
        f"{d['reference']}: "
        + "; ".join(parts)
        + " (`benchmarks/results/bench_orbital_splits.md`)."
    )


def adjust(d):
    full = {r["solver"]: r for r in d["full_size"]}
    s = full["schur"]
    load = d["machine"]
    out = (
        f"Bundle adjustment of the real Pleiades RPC pair (`benchmarks/bench_adjust.py`), "
        f"{s['ties']:,} ties + {s['gcps']} GCPs ({s['unknowns']:,} unknowns, "
        f"{s['observations']:,} observations), every solver on 1 BLAS thread and stopped at the "
        f"same criterion (max |dz|/σ < 0.01): Schur-reduced normal equations **{s['seconds']:.2f} "
        f"s** wall, {s['cpu_seconds']:.2f} s CPU ({s['iterations']} iterations, σ0 "
        f"{s['sigma0']:.3f}, tie RMSE {s['tie_rmse_px']:.3f} px; target {d['target']})"
    )
    if "least_squares" in full:
        q = full["least_squares"]
        out += (
            f"; scipy `least_squares` (default tolerances, then Gauss–Newton to the criterion) "
            f"{q['seconds']:.1f} s wall, {q['cpu_seconds']:.2f} s CPU "
            f"({d['least_squares_over_schur_cpu']:.1f}× the CPU time, {q['iterations']} iterations)"
        )
    steps = d.get("per_iteration_dense_vs_schur", [])
    if steps:
        out += (
            "; one dense normal-equations iteration "
            + " / ".join(f"{r['dense_cpu_seconds_per_iteration']:.2f}" for r in steps)
            + " s CPU at "
            + " / ".join(f"{r['ties']}" for r in steps)
            + " ties vs "
            + " / ".join(f"{1e3 * r['schur_cpu_seconds_per_iteration']:.1f}" for r in steps)
            + " ms for the Schur step (full size would need a "
            f"{d['dense_memory_at_full_size_gb']:.0f} GB normal matrix: not run, not extrapolated)"
        )
    return out + (
        f"; load average {load['load_average_at_start'][0]:.1f} → "
        f"{load['load_average_at_end'][0]:.1f} on 2 cores (wall times are upper bounds)."
    )


def aster_granule(d):
    st = d["stages"]
    sz = d["sizes"]
    e = d["render_error_px"]
    q = (
        d.get("historical", {})
        .get("baseline_before_block_rendering", {})
        .get("quarter_area_2050x2100_2500x2700_same_machine")
    )
    out = (
        f"Full-size ASTER granule, 3N {sz['3N'][0]} × {sz['3N'][1]} and 3B {sz['3B'][0]} × "
        f"{sz['3B'][1]} pixels (`benchmarks/bench_aster_granule.py`): simulated in "
        f"{st['simulate_scene']['seconds']:.0f} s (render error {e['left_render_error_px']:.4f} / "
        f"{e['right_render_error_px']:.4f} px left / right), written as V004 HDF-EOS2 "
        f"({d['file_mb']['v004']:.1f} MB) in {st['write_v004']['seconds']:.2f} s and as a V003 zip "
        f"({d['file_mb']['v003_zip']:.1f} MB) in {st['write_v003_zip']['seconds']:.2f} s, read "
        f"back (models + images) in {st['open_v004_and_read_images']['seconds']:.2f} / "
        f"{st['open_v003_and_read_images']['seconds']:.2f} s; {d['total_seconds']:.0f} s in all, "
        f"peak {d['peak_rss_gb']:.1f} GB"
    )
    c = d.get("cli_simulate_l1a_v004")
    if c:
        out += (
            f"; `stereodem simulate --preset aster --format l1a-v004` end to end "
            f"{c['wall_s']:g} s wall / {c['cpu_s']:g} s CPU, peak {c['peak_rss_gb']:.2f} GB "
            "(load average "
            f"{c['load_average_before_after'][0]:g}-{c['load_average_before_after'][1]:g}; targets "
            "<= 40 s, <= 3 GB)"
        )
    if q:
        out += (
            f" (an earlier session's measurement, not re-run by this script: quarter-area "
            f"simulation before/after block rendering: {q['before'][0]:g} → "
            f"{q['after'][0]:g} {q['unit'][0]}, {q['before'][1]:g} → {q['after'][1]:g} "
            f"{q['unit'][1]})"
        )
    return out + "."


def topan_sets(d):
    rk = d["ranking"]
    layouts = list(dict.fromkeys(r["layout"] for r in d["rows"]))
    solid = [r for r in rk if r["status"] == "ok"]
    never = [r["set"] for r in rk if r["solved_H"] == 0 and r["solved_G"] == 0]
    return (
        f"Topan's 19 EOP parameter sets on a simulated ASTER 3N scene "
        f"(`benchmarks/bench_topan_sets.py`, {d['n_points']} points, {d['noise_px']} px noise, "
        f"layouts {', '.join(layouts)}), best sets solved on every layout, by median ICP RMSE over "
        "the H layouts (over the grouped G layouts): "
        + ", ".join(
            f"{r['set']} {r['median_icp_H']:.2f} px ({r['median_icp_G']:.2f} px)" for r in solid[:4]
        )
        + f"; {len(never)} sets ({', '.join(never)}) are refused as near-singular on every "
        "layout unless regularised (Tikhonov, GCV) (`benchmarks/results/bench_topan_sets.md`)."
    )


def uncertainty(d):
    b = d["bettemir"]
    w = b["largest"][0]
    lv = b["independent_levers"]
    out = (
        f"Bettemir (2010) Tables 3–11 with the uncertainty propagation "
        f"(`benchmarks/bench_uncertainty.py`, {len(b['cells'])} table cells): with "
        f"{len(b['calibrated_inputs'])} inputs calibrated on the same tables (pitch/yaw σ as a "
        f"fraction of the roll σ, GPS σ per axis, the interior group's σ) the horizontal σ "
        f"(N, E) agree within {b['median_abs_HU_diff_pct']:.2f} % (median), "
        f"{b['max_abs_HU_diff_pct']:.2f} % at worst (analysis {w['analysis']}, "
        f"{w['HU']:.2f} vs {w['HU_paper']:.2f} m) — a calibration, not a prediction; predicted "
        f"from the orbit and camera geometry alone, the levers the tables imply: imaging time "
        f"{abs(lv['dN_dt_m_per_s']['model']):.0f} N / {abs(lv['dE_dt_m_per_s']['model']):.0f} E "
        f"m/s vs {lv['dN_dt_m_per_s']['paper_implied']:.0f} / "
        f"{lv['dE_dt_m_per_s']['paper_implied']:.0f} "
        f"({lv['dN_dt_m_per_s']['abs_rel_diff_pct']:.1f} % / "
        f"{lv['dE_dt_m_per_s']['abs_rel_diff_pct']:.1f} %), roll "
        f"{abs(lv['dE_droll_m_per_arcsec']['model']):.3f} vs "
        f"{lv['dE_droll_m_per_arcsec']['paper_implied']:.3f} m/″ "
        f"({lv['dE_droll_m_per_arcsec']['abs_rel_diff_pct']:.1f} %), while the DEM lever's "
        f"direction does not reproduce (∂E/∂h {abs(lv['dE_dh']['model']):.3f}, ∂N/∂h "
        f"{abs(lv['dN_dh']['model']):.3f} vs {lv['dE_dh']['paper_implied']:.3f}, "
        f"{lv['dN_dh']['paper_implied']:.3f})"
    )
    t = d.get("thesis_footprints")
    if t:
        out += (
            f"; the thesis's footprint points (Tables 8.6/8.7) to {t['rms_misfit_m']:.0f} m RMS "
            f"with heading and terrain height fitted, {t['rms_misfit_m_h0']:.0f} m at h = 0 "
            f"(notes: {t['notes_expectation']})"
        )
    sp = d.get("speed")
    if sp:
        a, mc = sp["aster_scene"], sp["monte_carlo_64x64_1000"]
        out += (
            f"; first-order maps of a full ASTER orthoimage in {a['first_order_maps_s']:.1f} s, "
            f"{a['ratio_maps_over_ortho']:.2f}× the orthorectification (target ≤ "
            f"{a['target_ratio']:g}×), {mc['samples']}-sample Monte Carlo on {mc['points']} points "
            f"in {mc['seconds']:.1f} s (target ≤ {mc['target_s']:g} s)"
        )
    return out + "."


def sparse_scaling(d):
    runs = d["runs"]
    parts = ", ".join(
        f"{r['size']}² px {r['cpu_s']:.1f} s CPU ({r['matches']} matches, heights "
        f"{r['height_range_m'][0]:.0f}–{r['height_range_m'][1]:.0f} m for a truth of "
        f"{r['truth_dem_range_m'][0]:.0f}–{r['truth_dem_range_m'][1]:.0f} m)"
        for r in runs
    )
    return (
        "Sparse stage (SIFT matches checked through the models, relative pointing, terrain "
        f"heights) on simulated ASTER pairs (`benchmarks/bench_sparse_scaling.py`): {parts}."
    )


def aster_strip(d):
    steps = ", ".join(
        f"{s['step_m']:+.2f} m ({s['half_width_lines']:g} lines)" for s in d["seam_steps"]
    )
    one = "; ".join(
        f"granule {k + 1}: {g['strip_nmad_same_cells_m']:.2f} vs {g['nmad_same_cells_m']:.2f} m"
        for k, g in enumerate(d["single_granules"])
    )
    n, m = d["size"]
    return (
        f"ASTER strip of {d['granules']} simulated granules of {n} × {m} 3N pixels, "
        f"{d['cut']['overlap_3N_lines']} lines of overlap (`benchmarks/bench_aster_strip.py`): "
        f"one DEM from the joined models, error step across the seam {steps} (target ≤ 0.5 m); "
        f"NMAD against the truth on each granule's cells, strip vs the granule alone: {one} "
        f"(target within 10 %); strip DEM {d['strip_dem_s']:.1f} s against "
        f"{sum(g['seconds'] for g in d['single_granules']):.1f} s for the granules one by one "
        f"(load {d['load_before'][0]:.1f})."
    )


def multiview(d):
    runs = {r["adjust"]: r for r in d["runs"]}
    parts = []
    for key, label in (
        ("never", 'without the adjustment (`[fusion] adjust = "never"`)'),
        ("auto", 'with it (`"auto"`, the default)'),
    ):
        r = runs.get(key)
        if r is None:
            continue
        pairs = " / ".join(f"{p['nmad_m']:.3f}" for p in r["pairs"])
        meds = " / ".join(f"{p['median_offset_m']:+.2f}" for p in r["pairs"])
        f = r["fused"][r["default_fusion"]]
        text = (
            f"{label}: pairs ({', '.join(p['pair'] for p in r['pairs'])}) NMAD {pairs} m, medians "
            f"{meds} m; fused ({r['default_fusion']}) **NMAD {f['nmad_m']:.3f} m**, coverage "
            f"**{100 * f['coverage_of_s2p_valid']:.1f} %** of s2p's valid cells (best pair "
            f"{r['best_pair']}: {min(p['nmad_m'] for p in r['pairs']):.3f} m, "
            f"{100 * max(p['coverage_of_s2p_valid'] for p in r['pairs']):.1f} %)"
        )
        adj = r.get("adjustment")
        if adj:
            text += (
                f"; reprojection RMS {adj['reprojection_rms_px_before']:.3f} → "
                f"{adj['reprojection_rms_px_after']:.3f} px over {adj['tie_points']} tie points"
            )
        text += (
            f"; N-view job {r['seconds_nview_job']:.1f} s against {r['seconds_pairs_sum']:.1f} s "
            f"for the three pair runs (load {r['load_average'][0]:.1f})"
        )
        parts.append(text)
    return (
        "N-view DEM of the real Pleiades triplet against s2p's fused DSM (its 0.5 m UTM grid; "
        "`benchmarks/bench_multiview.py`): " + "; ".join(parts) + "."
    )


def adjust_multi(d):
    r = d["run"]
    gaps = " / ".join(f"{v['ray_gap_rms_m']:.2f}" for v in r["ray_gaps_before"].values())
    after = max(v["ray_gap_rms_m"] for v in r["ray_gaps_after"].values())
    return (
        f"N-image bundle adjustment of the real Pleiades triplet RPCs with known image-space "
        f"shifts (`benchmarks/bench_adjust_multi.py`): {r['ties']} ties seen in all three images "
        f"({r['observations']} observations) + {r['gcps_per_image']} GCPs per image, "
        f"{r['unknowns']} unknowns: **{r['seconds']:.1f} s wall / {r['cpu_seconds']:.1f} s CPU** "
        f"({d['target']}), σ0 {r['sigma0']:.3f}, biases recovered within "
        f"**{r['max_abs_error_px']:.3f} px**; per-pair ray gaps {gaps} → ≤ {after:.2f} m RMS "
        f"(load {d['machine']['load_average_at_start'][0]:.1f} on {d['machine']['cpus']} cores)."
    )


def mosaic(d):
    r, m, s = d["runs"], d["memory"], d["seams"]
    b, rm, nb = r["blend"], r["rasterio_merge"], r["naive_blend"]
    load = d["machine"]["load_before"][0]
    return (
        f"Mosaic of {d['inputs']['n_dems']} simulated overlapping DEMs cut from the bundled "
        f"SRTM tile ({d['inputs']['res_m']:g} m, {b['cells'] / 1e6:.1f} M cells, biases, tilts, "
        f"noise, voids; `benchmarks/bench_mosaic.py`): `stereodem mosaic` (blend) peaks at "
        f"**+{m['peak_above_baseline_mb']:.0f} MB** above the interpreter and libraries, "
        + ("under" if m["peak_above_baseline_mb"] <= m["bound_mb"] else "**over**")
        + " its stated bound "
        f"of {m['bound_mb']:.0f} MB (half the area: +{m['half_area_peak_above_baseline_mb']:.0f} "
        f"MB); `rasterio.merge` +{m['rasterio_merge_peak_above_baseline_mb']:.0f} MB and a naive "
        f"full-array blend +{m['naive_blend_peak_above_baseline_mb']:.0f} MB (both hold "
        "whole-mosaic arrays). Seams: median |error step| across footprint edges / elsewhere "
        f"**{s['blend']['ratio']:.2f}** (blend) vs {s['first']['ratio']:.2f} (first) and "
        f"{s['rasterio_merge']['ratio']:.2f} (`rasterio.merge`). {b['cpu_s'] / b['n_dems']:.2f} s "
        f"CPU ({b['seconds_per_dem']:.2f} s wall, of which the COG finish "
        f"{b['seconds_cog_finish']:.0f} s in all) per DEM; `rasterio.merge` "
        f"{rm['cpu_s'] / rm['n_dems']:.2f} s CPU, naive blend {nb['cpu_s'] / nb['n_dems']:.2f} s "
        f"CPU per DEM, both writing plain GeoTIFFs (load average {load:.1f} on "
        f"{d['machine']['cpus']} cores)."
    )


def stack(d):
    out = "DEM stacks (`benchmarks/bench_stack.py`)"
    r = d.get("real")
    if r:
        c = r["runs"]["chain"]
        out += (
            f": five DEMs of the real SRTM tile over {r['dates'][0][:4]}–{r['dates'][-1][:4]} "
            "with shift, ramp, along-track oscillation, correlated noise, a cloud and a thinning "
            f"inside an outline: rate inside off by {c['inside_mean_rate_error_m_per_yr']:+.3f} "
            f"m/yr (target 0.1), stable-terrain rate NMAD {c['stable_rate_nmad_m_per_yr']:.3f} "
            f"m/yr = {c['stable_nmad_over_empirical_limit']:.2f} × the noise-only "
            f"{r['noise_limit_empirical_nmad_m_per_yr']:.3f} (target ≤ 1.3), cloud date masked on "
            f"{c['cloud_cells'] - c['cloud_cells_with_cloud_date_kept']}/{c['cloud_cells']} "
            f"cells, volume rate within {abs(c['volume_error_in_sigma']):.1f}σ of the truth "
            f"(target 2σ), {c['filled_pct']:.1f} % filled hypsometrically"
        )
    g = d.get("granules")
    if g:
        out += (
            f"; granules → DEMs → stack ({len(g['dates'])} dates): rate inside off by "
            f"{g['inside_mean_rate_error_m_per_yr']:+.3f} m/yr"
        )
    for key in ("heavy", "heavy_chain"):
        h = d.get(key)
        if h:
            out += (
                f"; `stack` of {h['dems']} DEMs of {h['cells']} cells, chain `{h['chain']}`, on "
                f"{h['workers']} workers: {h['wall_s'] / 60:.1f} min, peak "
                f"{h['peak_rss_mib'] / 1024:.2f} GiB (load average "
                f"{h['load_before'][0]:.0f}–{h['load_after'][0]:.0f})"
            )
    return out + "."


def coreg(d):
    c = d["cases"]["integer_shift"]
    sub = d["cases"]["subpixel_shift"]
    sd, xd = c["stereodem"], c["xdem"]
    v, a = d["variogram_vs_skgstat"], d["area_sigma_vs_monte_carlo"]
    return (
        f"Co-registration of the bundled SRTM tile (UTM, {d['truth']['shape'][0]} × "
        f"{d['truth']['shape'][1]} at 90 m) with an injected 1 px shift, 3 m offset, ramp, 3 m / "
        f"5.5 km along-track sine, correlated noise (NMAD {c['noise_nmad']:.2f} m) and a −30 m "
        "change in an excluded outline (`benchmarks/bench_coreg.py`): stereodem "
        f"`{d['chains']['stereodem']}` leaves a stable NMAD of **{sd['nmad_after']:.2f} m** "
        f"(xdem {d.get('xdem_version', '')} NuthKaab + Deramp + DirectionalBias: "
        f"{xd['nmad_after']:.2f} m), shift error {sd['shift']['dx_error']:+.2f} / "
        f"{sd['shift']['dy_error']:+.2f} m, change {sd['change_recovered']:+.2f} m, in "
        f"{sd['seconds']:.1f} s (xdem {xd['seconds']:.1f} s, 1 thread, load "
        f"{d['load_avg_start'][0]:.1f}); with a sub-pixel shift "
        f"{sub['stereodem']['nmad_after']:.2f} m vs {sub['xdem']['nmad_after']:.2f} m, where the "
        "true parameters applied with the same cubic warp leave "
        f"{sub['oracle_nmad']:.2f} m (the resampling there and back; noise "
        f"{sub['noise_nmad']:.2f} m). Variogram range/sill vs scikit-gstat on the same dh: "
        f"{100 * v['range_rel_diff']:.3f} % / {100 * v['sill_rel_diff']:.4f} %; σ of a "
        f"{a['radius_m'] / 1e3:.0f} km-radius area mean {a['sigma_from_variogram']:.3f} m vs Monte "
        f"Carlo {a['sigma_monte_carlo']:.3f} m ({100 * a['rel_diff']:.1f} %; σ/√N would say "
        f"{a['sigma_naive']:.3f} m)."
    )


def nuth_kaab(d):
    rr = {r["threads"]: r for r in d["runs"]}
    parts = [
        f"{n} thread{'s' if n > 1 else ''}: {r['filter_wall_s']:.2f} s vs "
        f"{r['gdal_warp_wall_s']:.2f} s wall ({_x(r['speedup_wall'], 2)}), "
        f"CPU {_x(r['cpu_ratio'], 2)}"
        for n, r in sorted(rr.items())
    ]
    diff = max(max(r["param_difference_m"].values()) for r in rr.values())
    n = d["size"]
    return (
        f"Nuth & Kääb fit of a {n} × {n} DEM at 30 m with a 45 m / 30 m / 3 m injected shift "
        "(`benchmarks/bench_nuth_kaab.py`, same run, alternating): the iterations' translation "
        "as one separable cubic filter against GDAL's cubic warp of the whole DEM at each "
        f"iteration: {'; '.join(parts)}; the fitted shifts differ by at most {diff * 1000:.1f} mm."
    )


def warp_blocks(d):
    n, rows = d["size"], d["block_rows"]
    parts = []
    for r in d["summary"]:
        b, a = r["before"], r["now"]
        parts.append(
            f"{r['threads']} thread{'s' if r['threads'] > 1 else ''}: {a['wall_s']:.1f} s vs "
            f"{b['wall_s']:.1f} s wall, {a['cpu_s']:.1f} vs {b['cpu_s']:.1f} CPU s, peak "
            f"+{a['peak_above_baseline_mb']:.0f} vs +{b['peak_above_baseline_mb']:.0f} MB"
        )
    blocks = ", ".join(
        f"{round(c['source_cells'] ** 0.5)}² ({c['source_mb']:.0f} MB): "
        f"{c['now_s'] * 1000:.0f} vs {c['before_s'] * 1000:.0f} ms, peak "
        f"+{c['now_peak_mb']:.0f} vs +{c['before_peak_mb']:.0f} MB"
        for c in d["block_costs"]
    )
    same = d["statistics_identical"] and all(c["identical"] for c in d["block_costs"])
    return (
        f"Blockwise assessment of a {n} × {n} DEM (UTM 33N, 30 m, 78° N) against a {n} × {n} "
        f"reference on EPSG:3413 (turned by 58°) in blocks of {rows} rows "
        "(`benchmarks/bench_warp_blocks.py`, same run, alternating, medians of "
        f"{d['repeat']}): the source read in place vs written whole into an in-memory GeoTIFF "
        f"for every block (before): {'; '.join(parts)}; one block's warp ({rows} × {rows} cells "
        f"inside the DEM) against the DEM's size, now vs before: {blocks}; "
        f"{'results identical' if same else 'RESULTS DIFFER'} "
        f"(load {d['machine']['load_average'][0]:.1f} on {d['machine']['cpus']} cores)."
    )


def tile(d):
    rows = d["tiles"]
    cpu = ", ".join(f"{r['cpu_ms']:.0f}" for r in rows)
    parts = {k: statistics.median(r["parts_ms"][k] for r in rows) for k in rows[0]["parts_ms"]}
    c = d["conversions"]
    g, u = c["ecef_to_geodetic"], c["geodetic_to_dem_crs"]
    return (
        f"One stereo tile of the full simulated granule (`benchmarks/bench_tile.py`, "
        f"{len(rows)} of its {d['n_tiles']} tiles, 1 thread, medians of {d['repeat']}): "
        f"{cpu} ms CPU per tile; parts (median over the tiles, ms): "
        + ", ".join(f"{k} {v:.0f}" for k, v in parts.items())
        + f". On one tile's {c['n_points']} points, PROJ vs its checked polynomial stand-in "
        f"(`core/localfit.py`, tolerance {c['tolerance_m'] * 1000:g} mm): ECEF → geodetic "
        f"{g['proj_ms']:.1f} vs {g['localfit_ms']:.1f} ms ({g['ratio']:.1f}×), geodetic → UTM "
        f"{u['proj_ms']:.1f} vs {u['localfit_ms']:.1f} ms ({u['ratio']:.1f}×); largest "
        f"difference {max(g['max_difference_m'] + u['max_difference_m']) * 1e6:.1f} µm."
    )


def cpu_timeline(d):
    parts = "; ".join(
        f"{r['stage']} {r['wall_s']:.1f} s ({r['mean_busy_cores']} cores busy, "
        f"{r['serial_s']:.1f} s below {d['busy_threshold']})"
        for r in d["stages"]
        if r["mean_busy_cores"] is not None
    )
    serial = sum(r["serial_s"] for r in d["stages"])
    return (
        f"Where `stereodem run` leaves cores idle (`benchmarks/cpu_timeline.py`, the full "
        f"granule at 2 workers, {d['cpus']} cores, the job's own processes sampled every "
        f"{d['every_s']} s, load {d['load_average'][0]:.1f}): {d['wall_s']:.1f} s in all, "
        f"{serial:.1f} s of it with fewer than {d['busy_threshold']} cores busy; {parts}."
    )


SUMMARISERS = {
    "bench_demo": demo,
    "bench_rpc": rpc,
    "bench_aster_scene": aster_scene,
    "bench_dem": dem,
    "bench_match": match,
    "bench_ortho": ortho,
    "bench_ortho_models": ortho_models,
    "bench_adjust": adjust,
    "bench_aster_granule": aster_granule,
    "bench_topan_sets": topan_sets,
    "bench_uncertainty": uncertainty,
    "bench_sparse_scaling": sparse_scaling,
    "bench_orbital_splits": orbital_splits,
    "bench_mosaic": mosaic,
    "bench_scaling": scaling,
    "bench_scaling_full": scaling,
    "bench_scaling_full_forkserver": scaling,
    OTHER_MACHINE: lambda d: (
        "The line above's command, same code (fc088dc), on the faster machine of an earlier "
        "session: " + scaling(d)
    ),
    SESSION_33: lambda d: (
        "The same command on session 33's machine (the scaling path unchanged; its "
        "perfectly parallel ceiling fell from 1.87x to 1.51x during the run): " + scaling(d)
    ),
    SESSION_34: lambda d: (
        "The same command on session 34's machine (its ceilings, at the end of the line, "
        "held during the run: a quiet machine): " + scaling(d)
    ),
    SESSION_35: lambda d: (
        "The same command on session 35's machine (the same kind as session 34's; the code "
        "with the control-group-aware core count): " + scaling(d)
    ),
    "bench_scaling_16_on_2": scaling_16_on_2,
    "cpu_timeline": cpu_timeline,
    "bench_scaling_16_on_2_uncapped": lambda d: (
        "Before the main process's threads were "
        "capped at the cores (the code of c05bdea): " + scaling(d)
    ),
    "bench_worker_start": worker_start,
    "bench_batch": batch,
    "bench_commands": commands,
    "bench_coreg": coreg,
    "bench_nuth_kaab": nuth_kaab,
    "bench_multiview": multiview,
    "bench_adjust_multi": adjust_multi,
    "bench_aster_strip": aster_strip,
    "bench_stack": stack,
    "bench_ortho_pair": ortho_pair,
    "bench_tile": tile,
    "bench_warp_blocks": warp_blocks,
}


#: the table of benchmarks/README.md: result name -> (benchmark, command, peer); its last
#: column is the summariser's text, so the table can never disagree with the result files
BENCHMARKS = {
    "bench_rpc": (
        "RPC model",
        "python benchmarks/bench_rpc.py",
        "GDAL's RPC transformer (rasterio `RPCTransformer`)",
    ),
    "bench_match": (
        "dense matching",
        "python benchmarks/bench_match.py [--before REV] [--repeats N]",
        (
            "`cv2.StereoSGBM` (1 thread, 3-way); the bare SGBM call at the same "
            "`cv2.setNumThreads` (the SGM wrapper's overhead)"
        ),
    ),
    "bench_dem": (
        "stereo DSM, real Pleiades pair",
        "python benchmarks/bench_dem.py",
        "s2p's DSM of the same pair",
    ),
    "bench_ortho": (
        "orthorectification",
        "python benchmarks/bench_ortho.py --repeat 5",
        "GDAL RPC warp (`rasterio.warp.reproject` with `rpcs=`, `RPC_DEM=`, 1 and 2 threads)",
    ),
    "bench_ortho_models": (
        "orthorectification models",
        "python benchmarks/bench_ortho_models.py",
        (
            "the structure of Ok (2005) Table 6.15 plus the orbital models and the "
            "rigorous pushbroom adjustment"
        ),
    ),
    "bench_orbital_splits": (
        "orbital models over random splits",
        "python benchmarks/bench_orbital_splits.py",
        "the rigorous pushbroom model (`attitude-bias-drift`) on the same splits",
    ),
    "bench_topan_sets": (
        "Topan's EOP sets",
        "python benchmarks/bench_topan_sets.py",
        "Topan (2009) Appendix A.5.1 and his reading of it",
    ),
    "bench_aster_scene": (
        "ASTER-sized scene",
        "python benchmarks/bench_aster_scene.py",
        "`--workers 1` vs `--workers 2`",
    ),
    "bench_demo": (
        "`stereodem demo`",
        "python benchmarks/bench_demo.py",
        "plain tiled GeoTIFFs for the same rasters; seeds 1–4 for the spread",
    ),
    "bench_adjust": (
        "bundle adjustment",
        "python benchmarks/bench_adjust.py",
        "scipy `least_squares` (sparse Jacobian, LSMR) and the dense normal equations",
    ),
    "bench_aster_granule": (
        "ASTER L1A granule",
        "python benchmarks/bench_aster_granule.py",
        "the simulator before this version's speed work (historical literals)",
    ),
    "bench_uncertainty": (
        "uncertainty",
        "python benchmarks/bench_uncertainty.py",
        "Bettemir (2010) Tables 3–11, thesis Tables 8.6/8.7; the orthorectification",
    ),
    "bench_sparse_scaling": (
        "sparse stage",
        "python benchmarks/bench_sparse_scaling.py",
        "the simulated truth's height range",
    ),
    "bench_mosaic": (
        "DEM mosaic",
        "python benchmarks/bench_mosaic.py --res 20 --n 50",
        "`rasterio.merge` and a naive whole-array blend",
    ),
    "bench_coreg": (
        "co-registration and error analysis",
        "python benchmarks/bench_coreg.py (with xdem installed: a peer only)",
        "xdem's NuthKaab + Deramp + DirectionalBias; scikit-gstat; Monte Carlo",
    ),
    "bench_nuth_kaab": (
        "Nuth & Kääb iterations on a 3000² DEM (issue 28)",
        "python benchmarks/bench_nuth_kaab.py",
        "the same fit with GDAL's warp at each iteration (before), same run",
    ),
    "bench_warp_blocks": (
        "blockwise warps between two CRSs",
        "python benchmarks/bench_warp_blocks.py",
        "the former reading (the whole source into an in-memory GeoTIFF per block), same run",
    ),
    "bench_scaling": (
        "scaling with `--workers`, half-size granule",
        "python benchmarks/bench_scaling.py --half",
        "itself at 1 worker (1, 2, 4, … up to the cores)",
    ),
    "bench_scaling_full": (
        "scaling with `--workers`, full granule",
        "python benchmarks/bench_scaling.py --results benchmarks/results/bench_scaling_full.json",
        "itself at 1 worker (1, 2, 4, … up to the cores)",
    ),
    "bench_scaling_full_forkserver": (
        "scaling, full granule, workers forked from a preloaded server (issue 28)",
        "python benchmarks/bench_scaling.py --workers 1 2 --repeat 3 --results "
        "benchmarks/results/bench_scaling_full_forkserver.json",
        "the same job with 1 worker, same run",
    ),
    OTHER_MACHINE: (
        "the same, on a faster 2-core machine (issue 28: the ratios on two machines)",
        "the bench_scaling_full_forkserver command on the code of fc088dc, another session's "
        "machine",
        "the same job with 1 worker, same run",
    ),
    SESSION_33: (
        "the same, on session 33's machine",
        "python benchmarks/bench_scaling.py --workers 1 2 --repeat 3 --results "
        "benchmarks/results/bench_scaling_full_forkserver_session33.json",
        "the same job with 1 worker, same run",
    ),
    SESSION_34: (
        "the same, on session 34's machine",
        "python benchmarks/bench_scaling.py --workers 1 2 --repeat 3 --results "
        "benchmarks/results/bench_scaling_full_forkserver_session34.json",
        "the same job with 1 worker, same run",
    ),
    SESSION_35: (
        "the same, on session 35's machine",
        "python benchmarks/bench_scaling.py --workers 1 2 --repeat 3 --results "
        "benchmarks/results/bench_scaling_full_forkserver_session35.json",
        "the same job with 1 worker, same run",
    ),
    "bench_tile": (
        "one stereo tile, its parts, PROJ vs core.localfit (issue 28)",
        "python benchmarks/bench_tile.py",
        "PROJ (pyproj) on the same points, same run",
    ),
    "bench_scaling_16_on_2": (
        "16 workers on this 2-core machine, full granule (issue 28, no 16-core machine lent)",
        "python benchmarks/bench_scaling.py --workers 2 16 --repeat 2 --results "
        "benchmarks/results/bench_scaling_16_on_2.json",
        "the same job with 2 workers, same run",
    ),
    "cpu_timeline": (
        "busy cores over a 2-worker run, per stage (issue 28: the serial parts)",
        "python benchmarks/cpu_timeline.py /tmp/bench_scaling/w2.toml",
        "— (a diagnostic)",
    ),
    "bench_scaling_16_on_2_uncapped": (
        "16 workers on 2 cores before the main-process thread cap (issue 28)",
        "the bench_scaling_16_on_2 command on the code of c05bdea",
        "the same job with 2 workers, same run",
    ),
    "bench_worker_start": (
        "tile pool start: fork server vs spawn (issue 28)",
        "python benchmarks/bench_worker_start.py",
        "the same pool with spawned workers, same run",
    ),
    "bench_commands": (
        "the standalone commands at 1 and 2 workers (issue 28)",
        "python benchmarks/bench_commands.py  # after bench_scaling.py --workers 2",
        "themselves at 1 worker (`--workers 1`, or one core by `taskset`)",
    ),
    "bench_batch": (
        "many scenes (`stereodem batch`)",
        "python benchmarks/bench_batch.py",
        "single `stereodem run` jobs one after the other",
    ),
    "bench_multiview": (
        "N-view DEM, real Pleiades triplet (issue 26)",
        "python benchmarks/bench_multiview.py",
        "s2p's fused DSM of the same triplet; the three pair DEMs of the same run",
    ),
    "bench_adjust_multi": (
        "N-image bundle adjustment (issue 26)",
        "python benchmarks/bench_adjust_multi.py",
        "the known biases it must recover",
    ),
    "bench_aster_strip": (
        "ASTER strip (issue 26)",
        "python benchmarks/bench_aster_strip.py",
        "each granule processed alone (same height range, posting); the truth DEM",
    ),
    "bench_ortho_pair": (
        "orthoimage pair on threads",
        "python benchmarks/bench_ortho_pair.py /tmp/bench_scaling/w1.toml --threads 2 --repeat 3",
        "the same two orthoimages one after the other at the same thread budget",
    ),
    "bench_stack": (
        "DEM stacks and rates (issue 27)",
        "python benchmarks/bench_stack.py",
        "the injected truth and the noise-only limit of the rate",
    ),
}
#: the README's table of issue 28's targets (:func:`scaling_targets`)
TARGETS_START = "<!-- targets generated by benchmarks/readme_figures.py --write: do not edit -->"
TARGETS_END = "<!-- end of generated targets -->"


def _load(results: Path, name: str):
    path = Path(results) / f"{name}.json"
    return json.loads(path.read_text()) if path.exists() else None


def _verdict(ok) -> str:
    """``met``, ``**not met**``, ``—`` (None: not measured), or a verdict given as text."""
    if isinstance(ok, str):
        return ok
    return "—" if ok is None else ("met" if ok else "**not met**")


def _by_machine(flags, files) -> bool | str:
    """One verdict for a target measured on several machines (``flags``: met or not on each,
    ``files``: their result files): met on all, not met on any, or which machine missed it
    (named by its speed index: a target met on one machine and missed on another is not
    met)."""
    if all(flags) or not any(flags):
        return all(flags)
    missed = [_speed_tag(d).strip(" ()") for d, ok in zip(files, flags) if not ok]
    count = "one machine" if len(missed) == 1 else f"{len(missed)} machines"
    return f"**not met** on {count} of {len(flags)} ({'; '.join(missed)})"


def sixteen_core_estimate(d, cores: int = 16) -> dict | None:
    """What ``stereodem run`` would take on ``cores`` cores, estimated from a scaling run's
    1- and 2-worker stage times (``bench_scaling.py``'s record): each stage split as Amdahl's
    law has it, ``T1 = s + p`` and ``T2 = s + p / 2`` (``p = 2 (T1 - T2)``, ``s = T1 - p``,
    neither below 0), then ``s + p / cores``; the 2-worker job's time outside its stages
    (start, imports) and its wait for the background writes count as serial. An estimate
    from 2 cores: parts that use 2 threads here but would not use 16 make it optimistic.
    Returns ``wall_s``, ``speedup_vs_2`` and each stage's ``serial_s``; None without both
    runs."""
    by = {r["workers"]: r for r in d.get("runs", [])}
    if 1 not in by or 2 not in by:
        return None
    one, two = by[1]["stages"], by[2]["stages"]
    wall, serial = 0.0, {}
    for name in two:
        t2 = two[name]["wall_s"]
        t1 = one.get(name, {}).get("wall_s", 0.0)
        if t1 <= 0:  # nothing at 1 worker (the background writes' wait): serial as measured
            serial[name], p = t2, 0.0
        else:
            p = max(2.0 * (t1 - t2), 0.0)
            serial[name] = max(t1 - p, 0.0)
        wall += serial[name] + p / cores
    outside = by[2]["wall_s"] - sum(v["wall_s"] for v in two.values())
    serial["start"] = max(outside, 0.0)
    wall += serial["start"]
    return dict(
        wall_s=wall,
        speedup_vs_2=by[2]["wall_s"] / wall,
        serial_s={k: round(v, 2) for k, v in serial.items()},
    )


def scaling_targets(results: Path = RESULTS) -> str:
    """The Markdown table of issue 28's targets against the committed result files: each row
    the target, the figure measured, whether it is met and the result file it comes from (a
    target without a measurement says so)."""
    rows = ["| target (issue 28) | measured | verdict | from |", "|---|---|---|---|"]

    def row(target, measured, ok, source):
        rows.append(f"| {target} | {measured} | {_verdict(ok)} | {source} |")

    sc = _load(results, "bench_aster_scene")
    if sc:
        cpus = "2 cores"
        run2 = next(r for r in sc["runs"] if r["workers"] == 2)["wall_s"]
        dem2 = next(r for r in sc["dem_runs"] if r["workers"] == 2)["wall_s"]
        src = "`results/bench_aster_scene.json`"
        tag = _speed_tag(sc) or " (machine speed not recorded)"
        row(f"full granule `run` ≤ 30 s, 2 workers ({cpus})", f"{run2:.1f} s{tag}", run2 <= 30, src)
        row(f"full granule `dem` ≤ 20 s, 2 workers ({cpus})", f"{dem2:.1f} s{tag}", dem2 <= 20, src)
    fs = _load(results, "bench_scaling_full_forkserver")
    if fs:
        # the same job on the machine of another session, when kept: a ratio met on one
        # machine and missed on the other is not met
        runs = [("", fs, "`results/bench_scaling_full_forkserver.json`")]
        for name in OTHER_MACHINES:
            other = _load(results, name)
            if other:
                runs.append(("; ", other, f"`results/{name}.json`"))
        src = ", ".join(f for _, _, f in runs)
        files = [d for _, d, _ in runs]

        def said(fmt):  # each machine's figure with its speed index
            return "".join(f"{sep}{fmt(d['ratios'])}{_speed_tag(d)}" for sep, d, _ in runs)

        def rounds(r):
            by = ", ".join(f"{x:.2f}" for x in r.get("speedup_2_vs_1_by_round", []))
            return f"{r['speedup_2_vs_1']:.2f}× (median-wall runs; rounds {by})"

        row(
            "2 workers ≥ 1.8× faster than 1",
            said(rounds),
            _by_machine([d["ratios"]["speedup_2_vs_1"] >= 1.8 for _, d, _ in runs], files),
            src,
        )
        row(
            "CPU s at 2 workers ≤ 1.1 × at 1",
            said(lambda r: f"{r['cpu_2_over_1']:.2f}"),
            _by_machine([d["ratios"]["cpu_2_over_1"] <= 1.1 for _, d, _ in runs], files),
            src,
        )
        checks = [
            v
            for _, d, _ in runs
            for x in d["runs"]
            for k, v in x.items()
            if k.startswith("bit_identical")
        ]
        same = bool(checks) and all(all(v.values()) for v in checks)
        row("rasters bit-identical for 1, 2, N workers", "yes" if same else "no", same, src)
    s16 = _load(results, "bench_scaling_16_on_2")
    if s16:
        c = s16["ratios"]["cpu_16_over_2"]
        row(
            "CPU s at 16 workers ≤ 1.25 × at 2",
            f"{c:.2f} (16 workers on {s16['machine']['cpus']} cores: no 16-core machine lent)",
            c <= 1.25,
            "`results/bench_scaling_16_on_2.json`",
        )
    ests = [
        (d, sixteen_core_estimate(d))
        for d in (fs, *(_load(results, name) for name in OTHER_MACHINES))
        if d and sixteen_core_estimate(d)
    ]

    def estimate(d, est):
        serial = ", ".join(
            f"{k} {v:.1f} s"
            for k, v in sorted(est["serial_s"].items(), key=lambda kv: -kv[1])
            if v >= 0.05
        )
        return (
            f"{est['wall_s']:.1f} s, {est['speedup_vs_2']:.1f}×, of which serial {serial}"
            f"{_speed_tag(d)}"
        )

    row(
        "16 cores: `run` ≥ 6× faster than 2 workers (≤ 8 s)",
        "not measured (no 16-core machine lent)"
        + (
            "; estimate from the 1- and 2-worker stages: "
            + "; ".join(estimate(d, e) for d, e in ests)
            + " (*16 cores* below)"
            if ests
            else ""
        ),
        None,
        src if ests else "—",
    )
    m = _load(results, "bench_match")
    o = (m or {}).get("sgm_overhead")
    if o:
        worst = max(max(r["ratio_wall"], r["ratio_wall_paired"]) for r in o["by_threads"])
        parts = "; ".join(
            f"{r['threads']} thread(s) {r['ratio_wall']:.3f}× wall (call by call "
            f"{r['ratio_wall_paired']:.3f}×)"
            for r in o["by_threads"]
        )
        row(
            "SGM wrapper ≤ 1.15 × the bare `cv2.StereoSGBM`",
            parts,
            worst <= 1.15,
            "`results/bench_match.json`",
        )
    b = _load(results, "bench_batch")
    if b:
        sums = {k: v["summary"] for k, v in b["batch"].items()}
        n = sum(next(iter(sums.values())).values())
        row(
            f"`batch` of {n} scenes, one corrupt, process pool and Dask `LocalCluster`",
            ", ".join(
                f"{k}: {b['speedup_vs_single_runs'][k]:.2f}× faster than the single runs, "
                f"{v['done']} done, {v['failed']} failed (the corrupt one, with its reason)"
                for k, v in sums.items()
            ),
            all(v["failed"] == 1 and v["done"] == n - 1 for v in sums.values()),
            "`results/bench_batch.json`",
        )
    return "\n".join(rows) + "\n"


TABLE_START = "<!-- table generated by benchmarks/readme_figures.py --write: do not edit -->"
TABLE_END = "<!-- end of generated table -->"
LIST_END = "<!-- end of generated figures -->"


def benchmarks_table(results: Path = RESULTS) -> str:
    """The Markdown table of benchmarks/README.md (one row per result file)."""
    files = {p.stem: p for p in sorted(Path(results).glob("*.json"))}
    rows = ["| benchmark | command | peer | latest figures |", "|---|---|---|---|"]
    for name in [k for k in BENCHMARKS if k in files] + [k for k in files if k not in BENCHMARKS]:
        title, command, peer = BENCHMARKS.get(name, (name, f"python benchmarks/{name}.py", "—"))
        fn = SUMMARISERS.get(name)
        text = fn(json.loads(files[name].read_text())) if fn else f"see `results/{name}.json`"
        rows.append(f"| {title} | `{command}` | {peer} | {text.replace('|', '/')} |")
    return "\n".join(rows) + "\n"


def _replace_block(text: str, start: str, end: str, block: str, where: str) -> str:
    i = text.find(start)
    j = text.find(end, i)
    if i < 0 or j < 0:
        raise SystemExit(f"readme_figures: {where}: markers {start!r} / {end!r} not found")
    return text[:i] + block + text[j:]


def write_readmes(root: Path = RESULTS.parents[1], results: Path = RESULTS):
    """Regenerate the figures list of README.md and the table of benchmarks/README.md in place."""
    readme = root / "README.md"
    text = readme.read_text()
    figures = figures_markdown(results)
    readme.write_text(
        _replace_block(
            text, "<!-- generated by benchmarks/readme_figures.py", LIST_END, figures, str(readme)
        )
    )
    text = readme.read_text()
    readme.write_text(
        _replace_block(
            text,
            TARGETS_START,
            TARGETS_END,
            TARGETS_START + "\n" + scaling_targets(results),
            str(readme),
        )
    )
    bench = root / "benchmarks" / "README.md"
    bench.write_text(
        _replace_block(
            bench.read_text(),
            TABLE_START,
            TABLE_END,
            TABLE_START + "\n" + benchmarks_table(results),
            str(bench),
        )
    )


def figures_markdown(results: Path = RESULTS) -> str:
    """The Markdown list, one bullet per result file (known summarisers first, in order)."""
    files = {p.stem: p for p in sorted(Path(results).glob("*.json"))}
    order = [k for k in SUMMARISERS if k in files] + [k for k in files if k not in SUMMARISERS]
    lines = [
        f"<!-- generated by benchmarks/readme_figures.py from {len(files)} file(s) in "
        "benchmarks/results/ -->"
    ]
    for name in order:
        fn = SUMMARISERS.get(name)
        if fn is None:
            lines.append(f"* `{name}`: see `benchmarks/results/{files[name].name}`.")
            continue
        try:
            text = fn(json.loads(files[name].read_text()))
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            print(
                f"readme_figures: {files[name]}: cannot summarise ({type(exc).__name__}: {exc}); "
                "update its summariser",
                file=sys.stderr,
            )
            text = f"`{name}`: (summary unavailable: the result file changed shape; see the JSON)"
        lines.append(f"* {text}")
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--results", default=str(RESULTS), help="folder of result JSON files")
    ap.add_argument(
        "--write",
        action="store_true",
        help="rewrite the generated blocks of README.md and benchmarks/README.md in place",
    )
    a = ap.parse_args(argv)
    if a.write:
        write_readmes(results=Path(a.results))
    else:
        sys.stdout.write(figures_markdown(Path(a.results)))


if __name__ == "__main__":
    main()
