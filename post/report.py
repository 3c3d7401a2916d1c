"""Writing an assessment to a folder: report.json, report.md, report.html and PNG figures.

``report.html`` is one self-contained page (figures inline as base64 PNG, the tables of
``report.md``, the run's provenance) that opens in any browser without the folder.
"""

from __future__ import annotations

import base64
import html as _html
import logging
import math
from pathlib import Path

from stereodem.core import jsonutil
from stereodem.core.raster import prepare_output_dir, write_text_atomic

from . import figures, shift_units
from .coreg import parameter_notes, parameter_text

log = logging.getLogger(__name__)

FIGURES = {
    "hillshade": "hillshade.png",
    "difference": "difference_map.png",
    "histogram": "histogram.png",
    "error_vs_slope": "error_vs_slope.png",
}


def _fmt(v, nd=2):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    if isinstance(v, int):
        return str(v)
    return f"{v:.{nd}f}"


_COLS = ("n", "valid_pct", "mean", "median", "std", "rmse", "nmad", "le90", "le95", "min", "max")


def _table(entries, label="class"):
    head = f"| {label} | " + " | ".join(_COLS) + " |"
    sep = "|" + "---|" * (len(_COLS) + 1)
    rows = [
        f"| {e.get('class', '')} | " + " | ".join(_fmt(e.get(c)) for c in _COLS) + " |"
        for e in entries
    ]
    return "\n".join([head, sep, *rows])


def markdown(report: dict, figure_files: dict) -> str:
    """A short Markdown summary of a report dict."""
    s = report["stats"]
    lines = [
        "# DEM accuracy assessment",
        "",
        f"* DEM: `{report.get('dem')}`",
        f"* Reference: `{report.get('reference')}`",
        f"* Grid: DEM warped onto the reference grid ({report['grid']['resampling']}), "
        f"CRS {report['grid']['crs']}, pixel {report['grid']['pixel_size_m'][0]:.1f} × "
        f"{report['grid']['pixel_size_m'][1]:.1f} m",
        f"* Vertical: {report['vertical']['note']}",
        f"* Differences: {report['difference']}",
        "",
        "## Whole DEM",
        "",
        _table([dict(s, **{"class": "all"})]),
        "",
        VALID_NOTE,
        "",
        f"P16/P84: {_fmt(s['p16'])} / {_fmt(s['p84'])} m; Gaussian LE90/LE95 (from σ): "
        f"{_fmt(s['le90_gauss'])} / {_fmt(s['le95_gauss'])} m.",
        "",
    ]
    fit = report.get("slope_fit") or {}
    lines += [
        "## By slope (reference slope, degrees)",
        "",
        _table(report["by_slope"], "slope"),
        "",
        f"Linear fit of |dh − median| on slope: {_fmt(fit.get('slope_m_per_deg'), 3)} m/deg, "
        f"intercept {_fmt(fit.get('intercept_m'))} m, r = {_fmt(fit.get('r'), 3)}.",
        "",
        "## By elevation band (reference heights)",
        "",
        _table(report["by_elevation"], "band"),
        "",
    ]
    if report.get("by_landcover"):
        lines += ["## By land cover", "", _table(report["by_landcover"]), ""]
    cp = report.get("checkpoints")
    if cp:
        lines += [
            "## Check points",
            "",
            f"{cp['vertical']}; sampled {cp['sampling']}; "
            f"{cp['outside']} outside, {cp['on_void']} on voids.",
            "",
            _table([dict(cp["stats"], **{"class": "check points"})]),
            "",
        ]
    co = report.get("coregistration")
    if co:
        a = report["after_coregistration"]["stats"]
        lines += [f"## {coregistration_title(co)}", "", coregistration_intro(co), ""]
        lines += [
            "| " + " | ".join(STEP_COLUMNS) + " |",
            "|" + "---|" * len(STEP_COLUMNS),
            *("| " + " | ".join(r) + " |" for r in step_rows(co)),
            "",
        ]
        lines += [f"* {n}" for n in step_notes(co)] + ([""] if step_notes(co) else [])
        shift = shift_sentence(co)
        if shift:
            lines += [shift, ""]
        lines += [
            _table(
                [dict(s, **{"class": "before"}), dict(a, **{"class": AFTER_LABEL})],
                "stage",
            ),
            "",
        ]
    if report.get("error_analysis"):
        from .error_analysis import markdown_lines  # (its variogram modules: when used)

        lines += markdown_lines(report["error_analysis"]) + [""]
    lines += ["## Figures", ""] + [f"![{k}]({v})" for k, v in figure_files.items()] + [""]
    prov = report.get("provenance")
    if prov:
        lines += (
            ["## Provenance", ""] + [f"* {k}: `{v}`" for k, v in prov.items() if k != "argv"] + [""]
        )
    return "\n".join(lines)


#: the row of the before/after table of the DEM after the whole co-registration chain
AFTER_LABEL = "after (whole chain)"

STEP_COLUMNS = ("step", "parameters", "stable NMAD before (m)", "stable NMAD after (m)", "n")


def coregistration_title(co: dict) -> str:
    """The co-registration section's title: the chain that was applied, step by step."""
    steps = [r["step"] for r in co.get("steps") or []] or [co.get("method", "nuth_kaab")]
    if steps == ["nuth_kaab"]:
        return "Co-registration (Nuth & Kääb)"
    return f"Co-registration chain ({' → '.join(steps)})"


def coregistration_intro(co: dict) -> str:
    """What the section's tables are: each step fitted on stable terrain after the ones
    before it; the before/after table of the DEM after the whole chain."""
    n = len(co.get("steps") or [])
    fit = "fitted on the DEM's grid (the reference warped onto it) on stable terrain"
    steps = (
        f"One step, {fit}"
        if n == 1
        else f"{n} steps applied in order, each {fit} after the steps before it"
    )
    return (
        f"{steps} (stable NMAD: of the fit's samples). The table below compares the DEM "
        "before and after the whole chain with the reference, on the reference grid as above."
    )


def step_rows(co: dict) -> list[tuple[str, ...]]:
    """One row per step of the chain: name, parameters with σ and units
    (:func:`~stereodem.post.coreg.parameter_text`), stable NMAD before and after, samples."""
    return [
        (
            r["step"],
            parameter_text(r.get("parameters") or {}),
            _fmt(r["before"]["nmad"]),
            _fmt(r["after"]["nmad"]),
            str(r["after"]["n"]),
        )
        for r in co.get("steps") or []
    ]


def step_notes(co: dict) -> list[str]:
    """The steps' notes (their coordinates, their track), ``step: note``."""
    return [
        f"{r['step']}: {n}"
        for r in co.get("steps") or []
        for n in parameter_notes(r.get("parameters") or {})
    ]


def shift_sentence(co: dict) -> str | None:
    """The Nuth & Kääb shift of the chain in words (None without a ``nuth_kaab`` step)."""
    if not any(r["step"] == "nuth_kaab" for r in co.get("steps") or []):
        return None
    return (
        "Shift of the DEM relative to the reference (the chain's shift steps): "
        f"{shift_units.shift_phrase(co['dx'], co['dy'])}, dz = {co['dz']:.2f} m up "
        f"({co['dx_px']:.2f}, {co['dy_px']:.2f} px; {co['iterations']} iterations, "
        f"{'converged' if co['converged'] else 'NOT converged'}).{shift_units.shift_units(co)}"
    )


VALID_NOTE = (
    "valid_pct: share of the reference cells inside the DEM's footprint (the convex "
    "hull of its data on the reference grid) where the DEM has a height; per class, "
    "the same share among the class's cells inside the footprint (n_total)."
)

FIGURE_CAPTIONS = {
    "hillshade": "Shaded relief of the DEM (colour: height; hatched: no data).",
    "difference": "DEM − reference; red: DEM above the reference, blue: below.",
    "histogram": "Distribution of DEM − reference with the mean, median and median ± NMAD.",
    "error_vs_slope": "Error statistics per slope class of the reference (n: valid cells).",
    "error_vs_terrain": "NMAD of dh on stable terrain against slope and maximum curvature, fitted.",
    "variogram": (
        "Variogram of the standardised dh on stable terrain and its fit (two spherical models)."
    ),
}


def figure_caption(name: str) -> str:
    """The caption of report figure ``name`` (the correction chain's: ``coreg_dh``,
    ``coreg_<step>``)."""
    if name == "coreg_dh":
        return "DEM − reference before and after the correction chain (stable NMAD in the titles)."
    if name.startswith("coreg_"):
        step = name.removeprefix("coreg_")
        return (
            f"Correction step {step}: binned dh on stable terrain against its variable, "
            "and the fit."
        )
    return FIGURE_CAPTIONS.get(name, name)


_CSS = """body{font-family:system-ui,sans-serif;max-width:980px;margin:1.5em auto;padding:0 1em;
color:#222;line-height:1.4}h1{font-size:1.6em}h2{font-size:1.25em;border-bottom:1px solid #ccc;
padding-bottom:.2em;margin-top:1.6em}table{border-collapse:collapse;font-size:.85em;margin:.6em 0}
th,td{border:1px solid #ccc;padding:.25em .5em;text-align:right}th{background:#f3f3f3}
td:first-child,th:first-child{text-align:left}figure{display:inline-block;margin:.5em;
vertical-align:top;max-width:460px}figure img{max-width:100%;border:1px solid #ddd}
figcaption{font-size:.85em;color:#555}code{background:#f5f5f5;padding:0 .2em}
.note{font-size:.85em;color:#555}\
dl{display:grid;grid-template-columns:max-content auto;gap:.2em 1em}
dt{font-weight:600}dd{margin:0;font-family:monospace;word-break:break-all}"""


def _html_table(entries, label="class"):
    esc = _html.escape
    head = "".join(f"<th>{esc(c)}</th>" for c in (label, *_COLS))
    rows = "".join(
        "<tr>"
        + f"<td>{esc(str(e.get('class', '')))}</td>"
        + "".join(f"<td>{esc(_fmt(e.get(c)))}</td>" for c in _COLS)
        + "</tr>"
        for e in entries
    )
    return f"<table><thead><tr>{head}</tr></thead><tbody>{rows}</tbody></table>"


def html_report(report: dict, figure_paths: dict) -> str:
    """A self-contained HTML page of a report dict: summary, tables, figures embedded as
    base64 PNG (``figure_paths``: name -> PNG path), provenance."""
    esc = _html.escape
    s = report["stats"]
    g = report["grid"]
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        "<title>DEM accuracy assessment</title>",
        f"<style>{_CSS}</style></head><body>",
        "<h1>DEM accuracy assessment</h1>",
        f"<p><b>NMAD {esc(_fmt(s['nmad']))} m</b> · median {esc(_fmt(s['median']))} m · "
        f"RMSE {esc(_fmt(s['rmse']))} m · LE90 {esc(_fmt(s['le90']))} m · "
        f"{esc(_fmt(s['valid_pct'], 1))} % valid · {s['n']:,} cells</p>",
        "<ul>",
        f"<li>DEM: <code>{esc(str(report.get('dem')))}</code></li>",
        f"<li>Reference: <code>{esc(str(report.get('reference')))}</code></li>",
        f"<li>Grid: DEM warped onto the reference grid ({esc(g['resampling'])}), CRS "
        f"{esc(g['crs'])}, pixel {g['pixel_size_m'][0]:.1f} × {g['pixel_size_m'][1]:.1f} m</li>",
        f"<li>Vertical: {esc(report['vertical']['note'])}</li>",
        f"<li>Differences: {esc(report['difference'])}</li></ul>",
        "<h2>Whole DEM</h2>",
        _html_table([dict(s, **{"class": "all"})]),
        f'<p class="note">{esc(VALID_NOTE)} P16/P84: {esc(_fmt(s["p16"]))} / '
        f"{esc(_fmt(s['p84']))} m; Gaussian LE90/LE95 (from σ): {esc(_fmt(s['le90_gauss']))} / "
        f"{esc(_fmt(s['le95_gauss']))} m.</p>",
        "<h2>Figures</h2>",
    ]
    for name, fp in figure_paths.items():
        data = base64.b64encode(Path(fp).read_bytes()).decode("ascii")
        cap = figure_caption(name)
        parts.append(
            f'<figure><img alt="{esc(name)}" src="data:image/png;base64,{data}">'
            f"<figcaption>{esc(cap)}</figcaption></figure>"
        )
    fit = report.get("slope_fit") or {}
    parts += [
        "<h2>By slope (reference slope, degrees)</h2>",
        _html_table(report["by_slope"], "slope"),
        f'<p class="note">Linear fit of |dh − median| on slope: '
        f"{esc(_fmt(fit.get('slope_m_per_deg'), 3))} m/deg, intercept "
        f"{esc(_fmt(fit.get('intercept_m')))} m, r = {esc(_fmt(fit.get('r'), 3))}.</p>",
        "<h2>By elevation band (reference heights)</h2>",
        _html_table(report["by_elevation"], "band"),
    ]
    if report.get("by_landcover"):
        parts += ["<h2>By land cover</h2>", _html_table(report["by_landcover"])]
    cp = report.get("checkpoints")
    if cp:
        parts += [
            "<h2>Check points</h2>",
            f"<p>{esc(cp['vertical'])}; sampled {esc(cp['sampling'])}; {cp['outside']} outside, "
            f"{cp['on_void']} on voids.</p>",
            _html_table([dict(cp["stats"], **{"class": "check points"})]),
        ]
    co = report.get("coregistration")
    if co:
        a = report["after_coregistration"]["stats"]
        head = "".join(f"<th>{esc(c)}</th>" for c in STEP_COLUMNS)
        rows = "".join(
            "<tr>" + "".join(f"<td>{esc(c)}</td>" for c in r) + "</tr>" for r in step_rows(co)
        )
        shift = shift_sentence(co)
        parts += [
            f"<h2>{esc(coregistration_title(co))}</h2>",
            f"<p>{esc(coregistration_intro(co))}</p>",
            f"<table><thead><tr>{head}</tr></thead><tbody>{rows}</tbody></table>",
            *(
                ["<ul>" + "".join(f"<li>{esc(n)}</li>" for n in step_notes(co)) + "</ul>"]
                if step_notes(co)
                else []
            ),
            *([f"<p>{esc(shift)}</p>"] if shift else []),
            _html_table(
                [dict(s, **{"class": "before"}), dict(a, **{"class": AFTER_LABEL})], "stage"
            ),
        ]
    if report.get("error_analysis"):
        from .error_analysis import markdown_lines

        ea = markdown_lines(report["error_analysis"])
        parts += (
            ["<h2>Error analysis (stable terrain)</h2>", "<ul>"]
            + [f"<li>{esc(x[2:])}</li>" for x in ea if x.startswith("* ")]
            + ["</ul>"]
        )
    prov = report.get("provenance")
    if prov:
        parts += (
            ["<h2>Provenance</h2>", "<dl>"]
            + [f"<dt>{esc(k)}</dt><dd>{esc(str(v))}</dd>" for k, v in prov.items() if k != "argv"]
            + ["</dl>"]
        )
    parts.append("</body></html>")
    return "\n".join(parts)


def write_report(
    assessment,
    out_dir,
    *,
    dem_heights=None,
    dem_transform=None,
    dem_crs=None,
    overwrite=False,
    provenance: dict | None = None,
    extra=None,
) -> dict:
    """Write ``report.json``, ``report.md``, ``report.html`` and the PNG figures of an
    :class:`~stereodem.post.assess.Assessment` into ``out_dir``; returns the paths written.

    The hillshade is of the DEM on the reference grid unless ``dem_heights`` (with its
    transform and CRS) is given. ``provenance`` (:func:`stereodem.provenance.provenance`) is
    stored in ``report.json`` and shown in both reports. ``extra(out, overwrite)`` returns
    ``(key, section, figure_files)``: one more section (e.g. the error analysis of
    :mod:`stereodem.post.error_analysis`) and its figures, written into the same folder.
    """
    out = prepare_output_dir(out_dir, overwrite=overwrite)
    rep = assessment.report
    cmp = assessment.before
    files = {}
    vertical = rep.get("vertical") or {}
    if dem_heights is None:
        dem_heights, dem_transform, dem_crs = cmp.dem, cmp.transform, cmp.crs
        vref = vertical.get("reference")
    else:
        vref = vertical.get("dem")
    label = {
        "geoid": "height above the EGM96 geoid (m)",
        "ellipsoid": "height above the WGS84 ellipsoid (m)",
    }.get(vref, "height (m)")
    dem_name = Path(rep["dem"]).name if rep.get("dem") else "DEM"
    ref_name = Path(rep["reference"]).name if rep.get("reference") else "reference"
    # the figures show the DEM as given: with --coregister, say that they are before it
    stage = " (before co-registration)" if rep.get("coregistration") else ""
    files["hillshade"] = figures.hillshade_png(
        dem_heights,
        dem_transform,
        dem_crs,
        out / FIGURES["hillshade"],
        overwrite=overwrite,
        height_label=label,
        title=f"Shaded relief of {dem_name}",
    )
    files["difference"] = figures.difference_map_png(
        cmp.dh,
        out / FIGURES["difference"],
        overwrite=overwrite,
        transform=cmp.transform,
        crs=cmp.crs,
        title=f"{dem_name} − {ref_name}{stage}",
    )
    hist = getattr(assessment, "histogram", None)
    files["histogram"] = figures.histogram_png(
        cmp.dh if hist is None else hist,
        out / FIGURES["histogram"],
        overwrite=overwrite,
        title=f"Histogram of {dem_name} − {ref_name}{stage}",
    )
    files["error_vs_slope"] = figures.error_vs_slope_png(
        cmp.dh,
        cmp.slope,
        rep["by_slope"],
        out / FIGURES["error_vs_slope"],
        overwrite=overwrite,
        centre=rep["stats"]["median"],
    )
    if extra is not None:
        key, section, figs = extra(out, overwrite)
        rep = dict(rep, **{key: section})
        files.update(figs)
    figure_paths = dict(files)
    rel = {k: Path(v).name for k, v in files.items()}
    rep = dict(rep, figures=rel)
    if provenance:
        rep["provenance"] = provenance
    files["json"] = write_text_atomic(
        out / "report.json", jsonutil.dumps(jsonutil.stamped(rep), indent=2), overwrite=overwrite
    )
    files["markdown"] = write_text_atomic(
        out / "report.md", markdown(jsonutil.json_ready(rep), rel), overwrite=overwrite
    )
    files["html"] = write_text_atomic(
        out / "report.html",
        html_report(jsonutil.json_ready(rep), figure_paths),
        overwrite=overwrite,
    )
    log.info("report written to %s", out)
    return files
