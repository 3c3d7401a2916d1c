"""Writing an adjustment's report: ``adjust_report.json``, ``adjust_report.md`` and the figure
of the residual vectors over the image (``adjust_residuals.png``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stereodem.core import jsonutil
from stereodem.core.png import save_png
from stereodem.core.raster import check_writable, write_text_atomic

__all__ = ["write_report", "markdown", "residual_figure", "REPORT_NAME"]

REPORT_NAME = "adjust_report.json"


def _f(v, fmt=".4g"):
    return "–" if v is None or (isinstance(v, float) and not np.isfinite(v)) else format(v, fmt)


def markdown(report: dict, figure: str | None = None) -> str:
    """A Markdown summary of a report dict (:meth:`AdjustmentResult.to_report` or a bundle's)."""
    lines = [f"# Adjustment report — {report.get('model_set') or 'custom parameter set'}", ""]
    chi = report.get("chi2_test") or {}
    test = report.get("test") or {}
    lines += [
        f"* observations {report['n_observations']}, unknowns {report['n_unknowns']}, "
        f"redundancy {report['dof']}; {report['iterations']} iteration(s), "
        f"converged: {report['converged']} ({report['convergence_criterion']})"
        + (
            f"; STALLED: the line search could not lower the sum of squares, last correction "
            f"{_f(report.get('max_correction'), '.3g')} sigma"
            if report.get("status") == "stalled"
            else ""
        ),
        f"* sigma0 = {_f(report['sigma0'])} (a priori 1; sigma "
        f"{'known' if report['sigma_known'] else 'unknown: covariance scaled by sigma0²'})"
        + (
            f"; chi² test ({chi['dof']} dof, alpha {chi['alpha']}): statistic "
            f"{_f(chi['statistic'])} in [{_f(chi['lower'])}, {_f(chi['upper'])}] → "
            f"{'passed' if chi['passed'] else 'FAILED'}"
            if chi.get("passed") is not None
            else ""
        ),
        f"* condition number of the (equilibrated) normal matrix: {_f(report['condition'], '.3g')}",
        f"* GCP RMSE {_f(report['gcp_rmse_px'])} px ({report['n_gcp']} GCPs), check-point RMSE "
        f"{_f(report['check_rmse_px'])} px ({report['n_check']} check points)",
        f"* outlier test: {test.get('name')} (alpha {test.get('alpha')} per observation, "
        f"critical value {_f(test.get('threshold'), '.3f')}, delta0 "
        f"{_f(test.get('delta0'), '.3f')})",
        "",
        "## Parameters",
        "",
        "| name | value | std | unit | initial |",
        "|---|---|---|---|---|",
    ]
    for p in report["parameters"]:
        lines.append(
            f"| {p['name']} | {_f(p['value'], '.6g')} | {_f(p['std'], '.3g')} | "
            f"{p['unit']} | {_f(p['initial'], '.6g')} |"
        )
    names = [p["name"] for p in report["parameters"]]
    corr = np.array([[np.nan if v is None else v for v in row] for row in report["correlation"]])
    if corr.size > 1:
        iu = np.triu_indices_from(corr, 1)
        order = np.argsort(-np.abs(np.nan_to_num(corr[iu])))[:5]
        lines += [
            "",
            "Largest correlations: "
            + ", ".join(f"{names[iu[0][k]]}/{names[iu[1][k]]} {corr[iu][k]:+.3f}" for k in order),
        ]
    lines += ["", "## Outliers", ""]
    if report["outlier_details"]:
        lines += [f"* {o['id']}: {o['reason']}" for o in report["outlier_details"]]
    else:
        lines.append("none")
    lines += [
        "",
        "## Points",
        "",
        "| id | role | res col px | res row px | w col | w row | "
        "r col | r row | MDB px | outlier |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for p in report["points"]:
        res = p["residual_px"]
        w = p["w"] or [None, None]
        r = p["r"] or [None, None]
        mdb = p["mdb_px"] or [None, None]
        lines.append(
            f"| {p['id']} | {p['role']} | {_f(res[0], '.3f')} | {_f(res[1], '.3f')} | "
            f"{_f(w[0], '.2f')} | {_f(w[1], '.2f')} | {_f(r[0], '.2f')} | "
            f"{_f(r[1], '.2f')} | "
            f"{_f(max((m for m in mdb if m is not None), default=None), '.2f')} | "
            f"{'yes' if p['outlier'] else ''} |"
        )
    if figure:
        lines += ["", f"![residual vectors]({figure})"]
    return "\n".join(lines) + "\n"


def _rmse(mag) -> str:
    mag = np.asarray(mag, float)
    mag = mag[np.isfinite(mag)]
    return _f(float(np.sqrt(np.mean(mag**2))), ".3g") if mag.size else "–"


def residual_figure(
    report: dict,
    path,
    *,
    width: int,
    height: int,
    overwrite=False,
    title: str | None = None,
    image: str | None = None,
):
    """Residual vectors (model − measured) drawn over the image frame, scaled, with a scale
    arrow; axes in image pixels (row down). The title gives the arrows' scale and the RMSE:
    the report's, or, for ``image`` (one image of a bundle: ``left``, ``image2``), the RMSE
    of that image's GCP, check and drawn tie residuals (outliers left out)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = check_writable(path, overwrite)
    pts = report["points"]
    xy = np.array([[p["col"], p["row"]] for p in pts], float).reshape(-1, 2)
    uv = np.array(
        [[np.nan if v is None else v for v in p["residual_px"]] for p in pts], float
    ).reshape(-1, 2)
    kind = np.array(["outlier" if p["outlier"] else p["role"] for p in pts])
    mag = np.hypot(uv[:, 0], uv[:, 1])
    ref = (
        np.nanpercentile(mag[kind != "outlier"], 90)
        if np.any(np.isfinite(mag[kind != "outlier"]))
        else 1.0
    )
    ref = float(ref) if ref > 0 else 1.0
    nice = 10 ** np.floor(np.log10(ref))
    nice = min((m * nice for m in (1, 2, 5, 10) if m * nice >= ref), default=ref)
    scale = 0.08 * max(width, height) / nice  # figure px per residual px
    fig, ax = plt.subplots(figsize=(7.5, 7.5 * height / max(width, 1) + 0.6))
    styles = {
        "tie": ("0.55", "tie point"),
        "gcp": ("tab:blue", "GCP"),
        "check": ("tab:orange", "check point"),
        "outlier": ("tab:red", "rejected (outlier)"),
    }
    for k, (color, label) in styles.items():
        m = kind == k
        if not np.any(m):
            continue
        ax.plot(xy[m, 0], xy[m, 1], "o", ms=3, color=color, label=label)
        ax.quiver(
            xy[m, 0],
            xy[m, 1],
            uv[m, 0] * scale,
            uv[m, 1] * scale,
            angles="xy",
            scale_units="xy",
            scale=1,
            color=color,
            width=0.004,
        )
    # scale arrow, bottom-left inside the frame
    x0, y0 = 0.05 * width, 0.95 * height
    ax.quiver(
        [x0],
        [y0],
        [nice * scale],
        [0],
        angles="xy",
        scale_units="xy",
        scale=1,
        color="k",
        width=0.005,
    )
    ax.text(x0, y0 - 0.025 * height, f"{nice:g} px residual", fontsize=9)
    ax.set_xlim(-0.5, width - 0.5)
    ax.set_ylim(height - 0.5, -0.5)
    ax.set_aspect("equal")
    ax.set_xlabel("column (px)")
    ax.set_ylabel("row (px)")
    if image is None:  # one image: the report's RMSEs are this image's
        rmse = (
            f"GCP RMSE {_f(report['gcp_rmse_px'], '.3g')} px, check "
            f"{_f(report['check_rmse_px'], '.3g')} px"
        )
    else:  # one image of several: the report's RMSEs are the whole adjustment's
        rmse = "RMSE on this image: " + ", ".join(
            f"{label} {_rmse(mag[kind == k])} px (n={int(np.sum(kind == k))})"
            for k, label in (("gcp", "GCP"), ("check", "check"), ("tie", "tie"))
            if np.any(kind == k)
        )
    ax.set_title(
        title
        or f"{image + ': ' if image else ''}residuals (model − measured), arrows "
        f"×{scale:.3g} (scale arrow: {nice:g} px)\n{rmse}",
        fontsize=9,
    )
    ax.legend(loc="upper right", fontsize=8)
    ax.grid(alpha=0.3)
    return save_png(fig, path, dpi=110, overwrite=overwrite, bbox_inches="tight")


def write_report(result, out_dir, *, overwrite: bool = False, prefix: str = "adjust") -> dict:
    """Write ``<prefix>_report.json``, ``<prefix>_report.md`` and ``<prefix>_residuals.png``
    (the figure of :func:`residual_figure`) into ``out_dir``; returns ``{kind: path}``.

    ``result`` is an :class:`AdjustmentResult` or anything with ``to_report()``, ``model``
    (for the image size) and, for a pair, ``figures()`` (image name -> (report, w, h)).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rep = result.to_report()
    paths = {"json": out / f"{prefix}_report.json", "markdown": out / f"{prefix}_report.md"}
    for p in paths.values():
        check_writable(p, overwrite)
    figs = (
        result.figures()
        if hasattr(result, "figures")
        else {"": (rep, result.model.width, result.model.height)}
    )
    fig_names = []
    for tag, (r, w, h) in figs.items():
        name = f"{prefix}_residuals{'_' + tag if tag else ''}.png"
        paths[f"figure{'_' + tag if tag else ''}"] = residual_figure(
            r,
            out / name,
            width=w,
            height=h,
            overwrite=overwrite,
            image=tag or None,
        )
        fig_names.append(name)
    write_text_atomic(paths["json"], jsonutil.dumps(jsonutil.stamped(rep)), overwrite=overwrite)
    write_text_atomic(
        paths["markdown"],
        markdown(rep, fig_names[0] if len(fig_names) == 1 else None)
        + "".join(f"\n![{n}]({n})\n" for n in fig_names[1:] if len(fig_names) > 1),
        overwrite=overwrite,
    )
    return paths
