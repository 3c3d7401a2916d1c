"""Error analysis of a DEM against a reference on stable terrain, for ``stereodem assess``
(Hugonnet et al. 2022): heteroscedasticity against slope and maximum curvature, the variogram
of the standardised ``dh`` fitted with two spherical models, the σ of the mean ``dh`` over each
polygon of ``outlines`` from that variogram, and — given the per-cell σ map the sensor models
propagate (``stereodem uncertainty``/the DEM's σ layer) — the share of the observed dispersion
it explains. Optionally a co-registration chain is applied first.

Everything on the DEM's grid (the reference warped onto it, :mod:`stereodem.post.coreg`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import rasterio

from stereodem.core.dem import DEM
from stereodem.core.errors import InputError
from stereodem.core.raster import check_map_raster, read_image
from stereodem.core.stats import nmad

from . import spatialstats as ss
from . import warp
from .biascorr import maximum_curvature
from .coreg import CoregChain, parse_chain, reference_on_grid
from .coreg_run import track_of
from .masks import StableMask, rasterize, read_outlines
from .terrain import slope_deg


@dataclass
class ErrorAnalysisJob:
    """Options of the error analysis (paths as on the command line)."""

    chain: str | None = None  #: co-registration chain applied first
    track_angle: float | None = None
    exclude: list = field(default_factory=list)
    outlines: list = field(default_factory=list)
    sigma_map: str | None = None  #: per-cell σ (m) from the sensor models
    n_pairs: int = 1_000_000


def fit_chain(dem: DEM, ref: DEM, chain: str, job: ErrorAnalysisJob, stable=None) -> CoregChain:
    """The co-registration ``chain`` (text) fitted on ``dem`` against ``ref`` (the same
    vertical reference) on the job's stable terrain (outside ``exclude``), with the job's
    track (``--track-angle``, else the DEM's tags), as the error analysis applies it: one
    fit for the report's co-registration section and for the analysis
    (:func:`stereodem.pipeline.assessment.assess_stage`)."""
    ch = parse_chain(chain)
    if stable is None:
        stable = StableMask(exclude=list(job.exclude)).array(dem)
    heading = frame = None
    if any(s.name in ("along_track", "cross_track") for s in ch.steps):
        heading, frame = track_of(dem.path, dem.crs, job.track_angle)
        if heading is None and frame is None:
            raise InputError(
                f"{dem.path or 'DEM'}: along_track/cross_track need the ground-track heading; "
                "the DEM carries none: give --track-angle DEG (clockwise from north)"
            )
    return ch.fit(ref, dem, stable=stable, track_angle_deg=heading, track_frame=frame)


def analyse(dem: DEM, ref: DEM, job: ErrorAnalysisJob, *, chain: CoregChain | None = None):
    """Run the analysis; returns ``(section, plots)``: a JSON-ready dict and what
    :func:`write_figures` draws. ``dem`` and ``ref`` in the same vertical reference.
    ``chain``: a chain already fitted on ``dem`` (:func:`fit_chain`), applied first instead
    of fitting ``job.chain``."""
    stable = StableMask(exclude=list(job.exclude)).array(dem)
    # outlines read and checked before any work: one outside the DEM is one line at once
    outlines = [(path, read_outlines(path, dem.crs)) for path in job.outlines]
    for path, polys in outlines:
        rasterize([o.geom for o in polys], dem, path=str(path))
    chain_rep = chain_plot = None
    if chain is None and job.chain:
        chain = fit_chain(dem, ref, job.chain, job, stable)
    if chain is not None:
        ch = chain
        corrected = ch.apply(dem)
        chain_plot = (ch, ref, dem, corrected, stable)  # the chain's figures (write_figures)
        dem = corrected
        chain_rep = ch.report()
    z = reference_on_grid(ref, dem)
    dh = dem.heights.astype(np.float64) - z
    slope = slope_deg(z, dem.transform, dem.crs)
    curv = maximum_curvature(z, dem.transform, dem.crs)
    d_st = np.where(stable, dh, np.nan)
    sig_model = _sigma_map(job.sigma_map, dem) if job.sigma_map else None
    hs = ss.heteroscedasticity(d_st, slope, curv, sigma_model=sig_model)
    per_cell = hs["sigma_sensor"] if sig_model is not None else hs["sigma"]
    zstd = ss.standardise(d_st, per_cell)
    if np.isfinite(zstd).sum() < 10:  # e.g. a DEM that differs from its reference by a constant
        raise InputError(
            f"{dem.path or 'DEM'} against {ref.path or 'the reference'}: the stable-terrain dh "
            f"has no dispersion to analyse (NMAD {nmad(d_st):.3g} m over "
            f"{int(np.isfinite(d_st).sum())} cells)"
        )
    zstd, n_out = ss.drop_outliers(zstd)  # blunders would set the variogram's sill and range
    emp = ss.variogram(zstd, transform=dem.transform, crs=dem.crs, n_pairs=job.n_pairs)
    model = ss.fit_variogram(emp, n_models=2)
    section = {
        "stable_cells": int(np.isfinite(d_st).sum()),
        "nmad_stable": nmad(d_st),
        "heteroscedasticity": {k: v for k, v in hs.items() if not k.startswith("sigma")},
        "variogram": {
            "empirical": emp.to_dict(),
            "model": model.to_dict(),
            "of": "dh standardised by the per-cell sigma: "
            + (
                "sensor-model sigma + unexplained binned dispersion"
                if sig_model is not None
                else "binned NMAD (slope, curvature)"
            ),
            "outliers_left_out": {"cells": n_out, "beyond_nmad": ss.OUTLIER_NMAD},
        },
    }
    if chain_rep is not None:  # the same fitted chain as the report's co-registration
        text = job.chain or ",".join(s.name for s in chain.steps)
        section["coregistration"] = {"chain": text, "steps": chain_rep}
        section["of"] = f"the DEM after the co-registration chain {text}"
    else:
        section["of"] = "the DEM as given (not co-registered)"
    areas = []
    for path, polys in outlines:
        for o in polys:
            m = rasterize([o.geom], dem, path=str(path)) & np.isfinite(dh)
            if not m.any():
                continue
            a = ss.area_mean_sigma(
                model, m, dem.transform, dem.crs, sigma=np.where(m, per_cell, np.nan)
            )
            areas.append(
                {"file": str(path), "polygon": o.label, "mean_dh": float(np.nanmean(dh[m])), **a}
            )
    if job.outlines and not areas:
        raise InputError(f"{job.outlines[0]}: no polygon covers a valid cell of the DEM")
    section["area_means"] = areas
    plots = {"hs": hs, "emp": emp, "model": model, "chain": chain_plot}
    plots["name"] = Path(dem.path).name if dem.path else None
    return section, plots


def _sigma_map(path, dem: DEM):
    a = read_image(path)
    with rasterio.open(path) as ds:
        check_map_raster(path, ds, "the σ map")
        t, crs = ds.transform, ds.crs.to_wkt()
    z = warp.to_grid(a, t, crs, dem.transform, dem.crs, dem.shape).astype(float)
    if not np.isfinite(z).any():
        raise InputError(f"{path}: the σ map does not overlap the DEM")
    return z


def _of(plots) -> str:
    """`` of <DEM file name>`` for a figure title, when the plots name the DEM."""
    return f" of {plots['name']}" if plots.get("name") else ""


def write_figures(plots, out_dir, *, overwrite=False) -> dict:
    """``error_vs_terrain.png`` (NMAD of dh against slope and curvature), ``variogram.png`` and,
    when a correction chain ran first, its figures as ``stereodem coregister`` draws them
    (``coreg_dh.png``: dh before/after; ``coreg_<i>_<step>.png``: each bias curve and its fit),
    named ``coreg_dh`` and ``coreg_<step>`` in the returned name -> path dict."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .figures import _save

    out_dir = Path(out_dir)
    hs, emp, model = plots["hs"], plots["emp"], plots["model"]
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
    for axis, key, label in (
        (ax[0], "slope", "slope (deg)"),
        (ax[1], "curvature", "|maximum curvature| (1/100 m)"),
    ):
        e = hs[key]
        axis.plot(e["centre"], e["nmad"], "o", label="NMAD of dh per bin")
        if e["quadratic_fit"]:
            x = np.linspace(np.nanmin(e["centre"]), np.nanmax(e["centre"]), 100)
            axis.plot(x, np.polyval(e["quadratic_fit"], x), "-", label="quadratic fit")
        if key == "slope" and "sensor_model" in hs:
            axis.plot(
                e["centre"],
                hs["sensor_model"]["rms_sigma_by_slope"],
                "s--",
                label="sensor-model σ (RMS)",
            )
        axis.set_xlabel(label)
        axis.set_ylabel("NMAD of dh (m)")
        # from 0: a y axis spanning the points alone blew a 3 % variation up to the whole height
        axis.set_ylim(0, axis.get_ylim()[1] * 1.1)
        axis.legend(fontsize=7, loc="lower right")
    fig.suptitle(f"Dispersion of dh on stable terrain{_of(plots)}", fontsize=10)
    files = {"error_vs_terrain": _save(fig, out_dir / "error_vs_terrain.png", overwrite)}
    fig, axis = plt.subplots(figsize=(6, 3.6))
    ok = emp.count > 0
    axis.semilogx(emp.lag[ok], emp.gamma[ok], ".", label="empirical")
    x = np.geomspace(emp.lag[ok].min(), emp.lag[ok].max(), 200)
    axis.semilogx(
        x,
        model.gamma(x),
        "-",
        label="sum of 2 spherical: ranges " + ", ".join(f"{r:.0f} m" for r in model.ranges),
    )
    axis.axhline(1.0, color="0.5", lw=0.8, ls=":", label="variance of standardised dh (1)")
    axis.set_xlabel("lag (m)")
    axis.set_ylabel("semivariance (standardised dh, unitless)")
    axis.set_ylim(0, max(axis.get_ylim()[1], 1.1))  # from 0: the nugget and sills to scale
    longest = float(emp.lag[ok].max())
    beyond = [r for r in model.ranges if r > longest]
    note = f"\nranges beyond the longest lag ({longest:.0f} m) are extrapolated" if beyond else ""
    axis.set_title(
        f"Variogram of dh / per-cell σ on stable terrain{_of(plots)}{note}",
        fontsize=9,
    )
    axis.legend(fontsize=7, loc="lower right")
    files["variogram"] = _save(fig, out_dir / "variogram.png", overwrite)
    if plots.get("chain") is not None:
        from .coreg_figures import chain_figures

        ch, ref, before, after, stable = plots["chain"]
        made = chain_figures(ch, ref, before, after, stable, out_dir, overwrite=overwrite)
        files.update({"coreg_" + k.removesuffix("_png"): v for k, v in made.items()})
    return files


def markdown_lines(section: dict) -> list[str]:
    """The report's Markdown lines of this section."""
    m = section["variogram"]["model"]
    lines = [
        "",
        "## Error analysis (stable terrain)",
        "",
        *([f"* analysed: {section['of']}"] if section.get("of") else []),
        f"* stable cells {section['stable_cells']}, NMAD {section['nmad_stable']:.2f} m",
        "* variogram of standardised dh: "
        + ", ".join(f"range {r:.0f} m sill {s:.2f}" for r, s in zip(m["ranges_m"], m["sills"])),
    ]
    sm = section["heteroscedasticity"].get("sensor_model")
    if sm:
        lines.append(
            f"* sensor-model σ explains {100 * sm['explained_variance_share']:.0f} % of the "
            f"variance of dh (binned r {sm['binned_r']:.2f})"
        )
    for a in section.get("area_means", []):
        lines.append(
            f"* {Path(a['file']).name} #{a['polygon']}: mean dh {a['mean_dh']:+.2f} ± "
            f"{a['sigma_mean']:.2f} m (1σ, {a['n_cells']} cells, "
            f"{a['n_effective']:.0f} effective samples; σ/√N would say {a['sigma_naive']:.3f} m)"
        )
    return lines
