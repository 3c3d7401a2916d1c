"""Writing an assessment to a folder: report.json, report.md and PNG figures."""
from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np

from stereodem.sensor.io.raster import prepare_output_dir, write_text_atomic

from . import figures

log = logging.getLogger(__name__)

FIGURES = {"hillshade": "hillshade.png", "difference": "difference_map.png",
           "histogram": "histogram.png", "error_vs_slope": "error_vs_slope.png"}


def _clean(obj):
    """JSON-ready copy: NaN/inf -> None, numpy scalars -> Python."""
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


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
    rows = [f"| {e.get('class', '')} | " + " | ".join(_fmt(e.get(c)) for c in _COLS) + " |"
            for e in entries]
    return "\n".join([head, sep, *rows])


def markdown(report: dict, figure_files: dict) -> str:
    """A short Markdown summary of a report dict."""
    s = report["stats"]
    lines = ["# DEM accuracy assessment", "",
             f"* DEM: `{report.get('dem')}`", f"* Reference: `{report.get('reference')}`",
             f"* Grid: DEM warped onto the reference grid ({report['grid']['resampling']}), "
             f"CRS {report['grid']['crs']}, pixel {report['grid']['pixel_size_m'][0]:.1f} × "
             f"{report['grid']['pixel_size_m'][1]:.1f} m",
             f"* Vertical: {report['vertical']['note']}",
             f"* Differences: {report['difference']}", "", "## Whole DEM", "",
             _table([dict(s, **{"class": "all"})]), "",
             f"P16/P84: {_fmt(s['p16'])} / {_fmt(s['p84'])} m; Gaussian LE90/LE95 (from σ): "
             f"{_fmt(s['le90_gauss'])} / {_fmt(s['le95_gauss'])} m.", ""]
    fit = report.get("slope_fit") or {}
    lines += ["## By slope (reference slope, degrees)", "", _table(report["by_slope"], "slope"), "",
              f"Linear fit of |dh − median| on slope: {_fmt(fit.get('slope_m_per_deg'), 3)} m/deg, "
              f"intercept {_fmt(fit.get('intercept_m'))} m, r = {_fmt(fit.get('r'), 3)}.", "",
              "## By elevation band (reference heights)", "", _table(report["by_elevation"], "band"), ""]
    if report.get("by_landcover"):
        lines += ["## By land cover", "", _table(report["by_landcover"]), ""]
    cp = report.get("checkpoints")
    if cp:
        lines += ["## Check points", "", f"{cp['vertical']}; sampled {cp['sampling']}; "
                  f"{cp['outside']} outside, {cp['on_void']} on voids.", "",
                  _table([dict(cp["stats"], **{"class": "check points"})]), ""]
    co = report.get("coregistration")
    if co:
        a = report["after_coregistration"]["stats"]
        lines += ["## Co-registration (Nuth & Kääb)", "",
                  f"Shift of the DEM relative to the reference: dx = {co['dx']:.2f} m east, "
                  f"dy = {co['dy']:.2f} m north, dz = {co['dz']:.2f} m up "
                  f"({co['dx_px']:.2f}, {co['dy_px']:.2f} px; {co['iterations']} iterations, "
                  f"{'converged' if co['converged'] else 'NOT converged'}).", "",
                  _table([dict(s, **{"class": "before"}), dict(a, **{"class": "after"})], "stage"), ""]
    lines += ["## Figures", ""] + [f"![{k}]({v})" for k, v in figure_files.items()] + [""]
    return "\n".join(lines)


def write_report(assessment, out_dir, *, dem_heights=None, dem_transform=None, dem_crs=None,
                 overwrite=False) -> dict:
    """Write ``report.json``, ``report.md`` and the PNG figures of an
    :class:`~stereodem.post.assess.Assessment` into ``out_dir``; returns the paths written.

    The hillshade is of the DEM on the reference grid unless ``dem_heights`` (with its
    transform and CRS) is given.
    """
    out = prepare_output_dir(out_dir, overwrite=overwrite)
    rep = assessment.report
    cmp = assessment.before
    files = {}
    if dem_heights is None:
        dem_heights, dem_transform, dem_crs = cmp.dem, cmp.transform, cmp.crs
    files["hillshade"] = figures.hillshade_png(dem_heights, dem_transform, dem_crs,
                                               out / FIGURES["hillshade"], overwrite=overwrite)
    files["difference"] = figures.difference_map_png(cmp.dh, out / FIGURES["difference"],
                                                     overwrite=overwrite)
    files["histogram"] = figures.histogram_png(cmp.dh, out / FIGURES["histogram"], overwrite=overwrite)
    files["error_vs_slope"] = figures.error_vs_slope_png(cmp.dh, cmp.slope, rep["by_slope"],
                                                         out / FIGURES["error_vs_slope"],
                                                         overwrite=overwrite)
    rel = {k: Path(v).name for k, v in files.items()}
    rep = dict(rep, figures=rel)
    files["json"] = write_text_atomic(out / "report.json", json.dumps(_clean(rep), indent=2),
                                      overwrite=overwrite)
    files["markdown"] = write_text_atomic(out / "report.md", markdown(_clean(rep), rel),
                                          overwrite=overwrite)
    log.info("report written to %s", out)
    return files
