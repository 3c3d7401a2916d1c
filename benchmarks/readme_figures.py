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
    row = {k: v.get(str(n)) for k, v in d["table"].items()}
    best = sorted(((v["check"], k) for k, v in row.items() if v), key=lambda t: t[0])[:6]
    return (f"Orthorectification models on a simulated ASTER scene "
            f"(`benchmarks/bench_ortho_models.py`): check-point RMSE with {n} GCPs and "
            f"{d['noise_px']} px noise: " + ", ".join(f"{k} {v:.2f} px" for v, k in best) +
            " (all models: `benchmarks/results/bench_ortho_models.md`).")


SUMMARISERS = {"bench_demo": demo, "bench_rpc": rpc, "bench_aster_scene": aster_scene,
               "bench_dem": dem, "bench_match": match, "bench_ortho": ortho,
               "bench_ortho_models": ortho_models}


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
