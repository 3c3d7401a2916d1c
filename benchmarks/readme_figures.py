"""Print the README's list of measured figures, regenerated from ``benchmarks/results/*.json``.

    python benchmarks/readme_figures.py            # Markdown block on stdout
    python benchmarks/readme_figures.py --results DIR

Each result file has its own summariser (the figures a reader needs, with the command that
measured them); a file without one is listed by name, and a summariser that no longer finds
its keys (the benchmark's output changed) says so on stderr and in the block, instead of
printing stale numbers. Paste the block into the README's "Measured" list.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def _x(v, nd=1):
    return f"{v:.{nd}f}×"


def demo(d):
    f = d["default_seed_figures"]
    c = d["cog_writing"]
    return (f"`stereodem demo` (600 × 600 simulated ASTER-like pair, `benchmarks/bench_demo.py`): "
            f"DEM − truth NMAD {f['nmad_m']:.2f} m, median {f['median_m']:+.2f} m, LE90 "
            f"{f['le90_m']:.2f} m, {f['valid_pct']:.1f} % of the DEM's footprint valid, "
            f"{c.get('fastest_demo_wall_seconds', f['wall_seconds']):.1f} s end to end; over seeds 1–{len(d['runs']) - 2} the NMAD "
            f"moves by up to {d['spread_over_seeds']['nmad_m']:.2f} m (LE90 "
            f"{d['spread_over_seeds']['le90_m']:.2f} m). Writing its rasters as Cloud-Optimised "
            f"GeoTIFFs (predictor, overviews) costs {c['extra_seconds']:+.2f} s "
            f"({100 * c['extra_fraction_of_demo_wall']:.1f} % of the run) against plain tiled "
            f"GeoTIFFs; files {c['old_bytes'] / 1e6:.2f} → {c['cog_bytes'] / 1e6:.2f} MB.")


def rpc(d):
    p, loc = d["project"], d["localize"]
    g6 = loc["gdal_1e-6px"]
    return (f"RPC model vs GDAL's RPC transformer, {d['n_points'] / 1e6:g} M points "
            f"(`benchmarks/bench_rpc.py`): `project` {_x(p['speedup'])} faster (agreement "
            f"{p['max_abs_diff_px']:.0e} px), exact `localize` {_x(g6['speedup'])} faster than "
            f"GDAL at 1e-6 px.")


def aster_scene(d):
    dr = {r["workers"]: r for r in d["dem_runs"]}
    rr = {r["workers"]: r for r in d["runs"]}
    same = all(all(v.values()) for v in d.get("bit_identical", {}).values())
    return (f"Full ASTER-sized simulated pair, 3N {d['size'][0]} × {d['size'][1]} and 3B "
            f"{d['right_size'][0]} × {d['right_size'][1]} pixels (`benchmarks/bench_aster_scene.py`): "
            f"`stereodem dem` in **{dr[1]['wall_s']:.1f} s with 1 worker, {dr[2]['wall_s']:.1f} s "
            f"with 2 ({d['speedup_dem']:.2f}×)**, peak {dr[1]['peak_rss_mb_all_processes'] / 1e3:.1f}–"
            f"{dr[2]['peak_rss_mb_all_processes'] / 1e3:.1f} GB over all processes; `stereodem run` "
            f"{rr[1]['wall_s']:.1f} s → {rr[2]['wall_s']:.1f} s (stereo stage "
            f"{d['speedup_stereo']:.2f}×), DEM NMAD {rr[1]['headline']['nmad']:.2f} m against the "
            f"truth." + (" Rasters are bit-identical between 1 and 2 workers." if same else ""))


def dem(d):
    r = {x["matcher"]: x for x in d["runs"]}
    s = r["sgm"]
    out = (f"Real Pleiades pair vs s2p's DSM (`benchmarks/bench_dem.py`): **NMAD "
           f"{s['nmad_m']:.3f} m**, median {s['median_offset_m']:+.2f} m, "
           f"**{100 * s['coverage_of_s2p_valid']:.1f} %** of s2p's valid cells covered, in "
           f"{s['seconds']:.1f} s (s2p: {s['s2p_seconds']:.0f} s).")
    if "ncc" in r:
        n = r["ncc"]
        out += (f" With `--matcher ncc`: {n['nmad_m']:.3f} m, {100 * n['coverage_of_s2p_valid']:.1f} %, "
                f"{n['seconds']:.1f} s.")
    return out


def match(d):
    parts = ", ".join(f"{r['matcher'].split(' (')[0]} {r['mpx_disp_per_s']:.0f}" for r in d["results"])
    return (f"Dense matching, {d['pair'].split(' ')[0]}, {d['disparities']} disparities "
            f"(`benchmarks/bench_match.py`), Mpx·disparities/s: {parts}.")


def ortho(d):
    s = d["speed_ratios"]
    return (f"Orthorectification vs GDAL (`benchmarks/bench_ortho.py`, {d['cells'] / 1e6:.1f} M "
            f"cells, same grid, DEM and kernel): "
            f"{d['max_position_difference_vs_gdal_rpc_transformer_px']:.4f} px apart; "
            f"**{_x(s['stereodem_1thread_vs_gdal_1thread'])} faster than GDAL on 1 thread, "
            f"{_x(s['stereodem_2threads_vs_gdal_2threads'])} on 2 threads**.")


def ortho_models(d):
    n = max(d["counts"])
    at_n = {r["model"]: r for r in d["records"] if r["n_gcp"] == n}

    def fig(name):
        r = at_n[name]
        return f"{name} refused" if "error" in r else f"{name} {r['icp_rmse_px']:.2f}"

    ok = [m for m in d["ok_twelve"] if m in at_n]
    orbital = [m for m, r in at_n.items() if r.get("family") == "orbital" and m not in ok]
    physical = [m for m, r in at_n.items() if r.get("family") == "physical"]
    return (f"Orthorectification models on a simulated ASTER scene "
            f"(`benchmarks/bench_ortho_models.py`): RMSE at {d['n_check']} check points with {n} "
            f"GCPs and {d['noise_px']} px image noise, in px: Ok's twelve: "
            + ", ".join(fig(m) for m in ok) + "; orbital: " + ", ".join(fig(m) for m in orbital)
            + "; rigorous: " + ", ".join(fig(m) for m in physical)
            + " (other GCP counts and all models: `benchmarks/results/bench_ortho_models.md`).")


def orbital_splits(d):
    parts = []
    for view, rows in d["views"].items():
        at = {(r["model"], r["n_gcp"]): r for r in rows}
        ten = ", ".join(f"{m} {at[(m, 10)]['median_ratio']:.2f}" for m in ("orun", "toutin")
                        if (m, 10) in at)
        five = ", ".join(f"{m} {at[(m, 5)]['median_icp_px']:.2f} px (condition "
                         f"{at[(m, 5)]['median_condition']:.2g})"
                         for m in (d["reference"], "orun", "toutin") if (m, 5) in at)
        parts.append(f"{view}: {ten} with 10 GCPs; with 5 GCPs median ICP RMSE {five}")
    return (f"Orun & Natarajan and Toutin-type models against the rigorous pushbroom model "
            f"(`benchmarks/bench_orbital_splits.py`, simulated ASTER 3N and 3B with ephemeris and "
            f"attitude biases and drifts, {d['n_splits']} random GCP/ICP splits, {d['n_check']} "
            f"check points, {d['noise_px']} px noise), median ICP RMSE ratio to "
            f"{d['reference']}: " + "; ".join(parts)
            + " (`benchmarks/results/bench_orbital_splits.md`).")


def adjust(d):
    full = {r["solver"]: r for r in d["full_size"]}
    s = full["schur"]
    out = (f"Bundle adjustment of the real Pleiades RPC pair (`benchmarks/bench_adjust.py`), "
           f"{s['ties']:,} ties + {s['gcps']} GCPs ({s['unknowns']:,} unknowns, "
           f"{s['observations']:,} observations): Schur-reduced normal equations **{s['seconds']:.2f} s** "
           f"({s['cpu_seconds']:.2f} s CPU, {s['iterations']} iterations, σ0 {s['sigma0']:.3f}, tie "
           f"RMSE {s['tie_rmse_px']:.3f} px), target {d['target']}")
    if "least_squares" in full:
        q = full["least_squares"]
        out += (f"; scipy `least_squares` on the same sparse problem {q['seconds']:.1f} s "
                f"({q['seconds'] / s['seconds']:.0f}× slower)")
    out += (f"; dense normal equations grow as n^{d['dense_scaling_exponent']:.2f}, extrapolated "
            f"{d['dense_extrapolated_seconds_at_full_size']:.0f} s and "
            f"{d['dense_memory_at_full_size_gb']:.1f} GB at full size "
            f"({d['speedup_schur_vs_dense_extrapolated']:.0f}× the Schur solver's time).")
    return out


def aster_granule(d):
    st = d["stages"]
    sz = d["sizes"]
    e = d["render_error_px"]
    q = d.get("baseline_before_block_rendering", {}).get("quarter_area_2050x2100_2500x2700_same_machine")
    out = (f"Full-size ASTER granule, 3N {sz['3N'][0]} × {sz['3N'][1]} and 3B {sz['3B'][0]} × "
           f"{sz['3B'][1]} pixels (`benchmarks/bench_aster_granule.py`): simulated in "
           f"{st['simulate_scene']['seconds']:.0f} s (render error {e['left_render_error_px']:.4f} / "
           f"{e['right_render_error_px']:.4f} px left / right), written as V004 HDF-EOS2 "
           f"({d['file_mb']['v004']:.1f} MB) in {st['write_v004']['seconds']:.2f} s and as a V003 zip "
           f"({d['file_mb']['v003_zip']:.1f} MB) in {st['write_v003_zip']['seconds']:.2f} s, read back "
           f"(models + images) in {st['open_v004_and_read_images']['seconds']:.2f} / "
           f"{st['open_v003_and_read_images']['seconds']:.2f} s; {d['total_seconds']:.0f} s in all, "
           f"peak {d['peak_rss_gb']:.1f} GB")
    c = d.get("cli_simulate_l1a_v004")
    if c:
        out += (f"; `stereodem simulate --preset aster --format l1a-v004` end to end "
                f"{c['wall_s']:g} s wall / {c['cpu_s']:g} s CPU, peak {c['peak_rss_gb']:.2f} GB "
                f"(load average {c['load_average_before_after'][0]:g}-{c['load_average_before_after'][1]:g}; "
                f"targets <= 40 s, <= 3 GB)")
    if q:
        out += (f" (quarter-area simulation before/after block rendering: {q['before'][0]:g} → "
                f"{q['after'][0]:g} {q['unit'][0]}, {q['before'][1]:g} → {q['after'][1]:g} {q['unit'][1]})")
    return out + "."


def topan_sets(d):
    rk = d["ranking"]
    layouts = list(dict.fromkeys(r["layout"] for r in d["rows"]))
    solid = [r for r in rk if r["status"] == "ok"]
    never = [r["set"] for r in rk if r["solved_H"] == 0 and r["solved_G"] == 0]
    return (f"Topan's 19 EOP parameter sets on a simulated ASTER 3N scene "
            f"(`benchmarks/bench_topan_sets.py`, {d['n_points']} points, {d['noise_px']} px noise, "
            f"layouts {', '.join(layouts)}), best sets solved on every layout, by median ICP RMSE over "
            "the H layouts (over the grouped G layouts): "
            + ", ".join(f"{r['set']} {r['median_icp_H']:.2f} px ({r['median_icp_G']:.2f} px)"
                        for r in solid[:4])
            + f"; {len(never)} sets ({', '.join(never)}) are refused as near-singular on every "
            "layout unless regularised (Tikhonov, GCV) (`benchmarks/results/bench_topan_sets.md`).")


def uncertainty(d):
    b = d["bettemir"]
    w = b["largest"][0]
    out = (f"Bettemir (2010) Tables 3–11 reproduced with the uncertainty propagation "
           f"(`benchmarks/bench_uncertainty.py`, {len(b['cells'])} table cells, some inputs inferred): "
           f"horizontal σ (N, E) within {b['median_abs_HU_diff_pct']:.2f} % of the paper (median), "
           f"{b['max_abs_HU_diff_pct']:.2f} % at worst (analysis {w['analysis']}, "
           f"{w['HU']:.2f} vs {w['HU_paper']:.2f} m)")
    t = d.get("thesis_footprints")
    if t:
        out += (f"; the thesis's footprint points (Tables 8.6/8.7) to {t['rms_misfit_m']:.0f} m RMS "
                f"with heading and terrain height fitted, {t['rms_misfit_m_h0']:.0f} m at h = 0 "
                f"(notes: {t['notes_expectation']})")
    sp = d.get("speed")
    if sp:
        a, mc = sp["aster_scene"], sp["monte_carlo_64x64_1000"]
        out += (f"; first-order maps of a full ASTER orthoimage in {a['first_order_maps_s']:.1f} s, "
                f"{a['ratio_maps_over_ortho']:.2f}× the orthorectification (target ≤ "
                f"{a['target_ratio']:g}×), {mc['samples']}-sample Monte Carlo on {mc['points']} points "
                f"in {mc['seconds']:.1f} s (target ≤ {mc['target_s']:g} s)")
    return out + "."


def sparse_scaling(d):
    runs = d["runs"]
    parts = ", ".join(f"{r['size']}² px {r['cpu_s']:.1f} s CPU ({r['matches']} matches, heights "
                      f"{r['height_range_m'][0]:.0f}–{r['height_range_m'][1]:.0f} m for a truth of "
                      f"{r['truth_dem_range_m'][0]:.0f}–{r['truth_dem_range_m'][1]:.0f} m)" for r in runs)
    return ("Sparse stage (SIFT matches checked through the models, relative pointing, terrain "
            f"heights) on simulated ASTER pairs (`benchmarks/bench_sparse_scaling.py`): {parts}.")


SUMMARISERS = {"bench_demo": demo, "bench_rpc": rpc, "bench_aster_scene": aster_scene,
               "bench_dem": dem, "bench_match": match, "bench_ortho": ortho,
               "bench_ortho_models": ortho_models, "bench_adjust": adjust,
               "bench_aster_granule": aster_granule, "bench_topan_sets": topan_sets,
               "bench_uncertainty": uncertainty, "bench_sparse_scaling": sparse_scaling,
               "bench_orbital_splits": orbital_splits}


def figures_markdown(results: Path = RESULTS) -> str:
    """The Markdown list, one bullet per result file (known summarisers first, in order)."""
    files = {p.stem: p for p in sorted(Path(results).glob("*.json"))}
    order = [k for k in SUMMARISERS if k in files] + [k for k in files if k not in SUMMARISERS]
    lines = [f"<!-- generated by benchmarks/readme_figures.py from {len(files)} file(s) in "
             "benchmarks/results/ -->"]
    for name in order:
        fn = SUMMARISERS.get(name)
        if fn is None:
            lines.append(f"* `{name}`: see `benchmarks/results/{files[name].name}`.")
            continue
        try:
            text = fn(json.loads(files[name].read_text()))
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            print(f"readme_figures: {files[name]}: cannot summarise ({type(exc).__name__}: {exc}); "
                  "update its summariser", file=sys.stderr)
            text = f"`{name}`: (summary unavailable: the result file changed shape; see the JSON)"
        lines.append(f"* {text}")
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--results", default=str(RESULTS), help="folder of result JSON files")
    a = ap.parse_args(argv)
    sys.stdout.write(figures_markdown(Path(a.results)))


if __name__ == "__main__":
    main()
