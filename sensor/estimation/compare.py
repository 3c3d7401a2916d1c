"""Side-by-side comparison of sensor models fitted to the same GCPs (Ok 2005 Table 6.15,
Topan 2009 Tables 4.3/A.5): every model gets the same check points (ICPs) and the same GCP
subsets, from small to large, and is scored by GCP and ICP RMSE (pixels), the a-posteriori
sigma0 (the a-posteriori standard deviation of unit weight: relative to the a-priori image
sigma when one is given, else in pixels), the condition number of its normal equations
(generic models: in their normalised coordinates, as :mod:`~stereodem.sensor.models.generic`
reports it; the others: column-equilibrated)
and its parameter count.

Model names: the generic models of :mod:`stereodem.sensor.models.generic` (fitted with
:func:`~stereodem.sensor.models.generic.fit_model`), and every set registered with the
adjustment engine (:mod:`stereodem.sensor.estimation.adjust.model_sets`: the physical model's
``attitude-*`` sets, ``rpc-*``, and the orbital ``eop-*``, ``orun``, ``toutin``, ``kratky``),
adjusted with :func:`~stereodem.sensor.estimation.adjust.adjust_model`. ``all`` = every
generic model, the sets that apply to the image's model and the orbital defaults.
"""

from __future__ import annotations

import logging

import numpy as np

from stereodem.core.errors import InputError, StereodemError
from stereodem.core.png import save_png
from stereodem.core.stats import check_sigma, generator
from stereodem.sensor.estimation.adjust import MODEL_SETS, adjust_model, model_set
from stereodem.sensor.io.gcps import ControlPoints
from stereodem.sensor.models.generic import MODEL_NAMES, fit_model, n_parameters
from stereodem.sensor.models.orbital import DEFAULT_SETS
from stereodem.sensor.models.orbital._common import require_gcps, require_inside
from stereodem.sensor.models.pushbroom import PushbroomModel

log = logging.getLogger(__name__)


def short_reason(text, width: int = 80) -> str:
    """A refusal's reason for a table cell: whole words up to ``width`` characters, then an
    ellipsis (a cut in the middle of a word turned "got 10" into "got 1"); ``|`` escaped."""
    text = " ".join(str(text or "").split())
    if len(text) > width:
        cut = text[: width - 1]
        text = (cut.rsplit(" ", 1)[0] if " " in cut else cut) + " …"
    return text.replace("|", "\\|")


def expand_models(names, base) -> list[str]:
    """The model list: ``all`` expanded for the image model ``base``; unknown names refused."""
    out = []
    for name in names:
        if name == "all":
            out += list(MODEL_NAMES)
            for k, ms in MODEL_SETS.items():
                if k.startswith(("rpc-shift", "rpc-affine")) or (
                    ms.applies_to and isinstance(base, ms.applies_to)
                ):
                    out.append(k)
            if isinstance(base, PushbroomModel) or hasattr(base, "ephemeris"):
                out += list(DEFAULT_SETS)
            else:
                out += [k for k in DEFAULT_SETS if k != "eop-poly2"]
        elif name in MODEL_NAMES or name in MODEL_SETS:
            out.append(name)
        else:
            known = sorted(set(MODEL_NAMES) | set(MODEL_SETS))
            raise InputError(f"unknown model {name!r} (known: all, {', '.join(known)})")
    return list(dict.fromkeys(out))


def _check_count(n_check, n_points: int | None = None):
    """:class:`InputError` unless ``n_check`` is a whole number >= 1 and, drawn from
    ``n_points`` points, leaves GCPs (``-1`` drew all points but one as check points)."""
    try:
        whole = float(n_check) == int(n_check)
    except (TypeError, ValueError, OverflowError):
        whole = False
    if not whole or n_check < 1:
        raise InputError(f"the number of check points must be a whole number >= 1, got {n_check}")
    if n_points is not None and n_check >= n_points:
        raise InputError(
            f"{n_points} point(s) cannot give {n_check} check points and GCPs (the number "
            f"of check points must be from 1 to {n_points - 1})"
        )


def split_points(points: ControlPoints, n_check: int, seed: int = 0):
    """``(gcp pool in a fixed random order, check points)``: the points' own ``check`` roles
    when there are any, else ``n_check`` random points."""
    rng = generator(seed)
    _check_count(n_check)
    if np.any(points.role == "check"):
        pool, icp = points.select("gcp"), points.select("check")
    else:
        _check_count(n_check, len(points))
        order = rng.permutation(len(points))
        roles = np.array(["gcp"] * len(points), dtype=object)
        roles[order[:n_check]] = "check"
        pts = (
            points.with_roles(roles)
            if hasattr(points, "with_roles")
            else _with_roles(points, roles)
        )
        pool, icp = pts.select("gcp"), pts.select("check")
    perm = rng.permutation(len(pool))
    return pool.subset(perm), icp


def _with_roles(points, roles):
    return ControlPoints(
        points.id,
        points.lon,
        points.lat,
        points.h,
        points.col,
        points.row,
        role=np.asarray(roles, str),
        sigma_px=points.sigma_px,
        sigma_ground_m=points.sigma_ground_m,
    )


def _take(points, idx):
    return ControlPoints(
        points.id[idx],
        points.lon[idx],
        points.lat[idx],
        points.h[idx],
        points.col[idx],
        points.row[idx],
        role=points.role[idx],
        sigma_px=points.sigma_px[idx],
        sigma_ground_m=points.sigma_ground_m[idx],
    )


def _concat(a, b):
    cat = {
        k: np.concatenate([getattr(a, k), getattr(b, k)])
        for k in ("id", "lon", "lat", "h", "col", "row", "role", "sigma_px", "sigma_ground_m")
    }
    return ControlPoints(**cat)


def _generic_record(name, gcp, icp, sigma_px=None):
    model, rep = fit_model(
        name,
        *(getattr(gcp, k) for k in ("lon", "lat", "h", "col", "row")),
        check=tuple(getattr(icp, k) for k in ("lon", "lat", "h", "col", "row")),
    )
    u, n = n_parameters(name), len(gcp)
    dof = 2 * n - u
    # sigma0 as the engine reports it: relative to the a-priori sigma when one is given
    s0 = float(np.sqrt(n * rep.gcp_rmse**2 / dof)) / (sigma_px or 1.0) if dof > 0 else float("nan")
    return dict(
        n_params=u,
        gcp_rmse_px=float(rep.gcp_rmse),
        icp_rmse_px=float(rep.check_rmse),
        sigma0=s0,
        condition=float(rep.condition_number),
    )


def compare(
    base,
    points: ControlPoints,
    models,
    counts,
    *,
    n_check: int = 20,
    seed: int = 0,
    sigma_px=None,
    prepared: dict | None = None,
    names: tuple[str, str] = ("", ""),
    progress=None,
) -> list[dict]:
    """Fit every model with every GCP count on the same split; list of records (one per model
    and count) with ``model, family, n_gcp, n_icp, n_params, gcp_rmse_px, icp_rmse_px,
    sigma0, condition`` and ``error`` (the one-line reason when the fit was refused).
    ``prepared`` (a dict, filled here) keeps the models built from ``base`` for another call
    with the same ``base``. ``names``: the points' file and the image, for the messages.
    ``progress(done, total)`` is called after each fit."""
    if sigma_px is not None:
        sigma_px = check_sigma(sigma_px, "sigma_px")
    pool, icp = split_points(points, n_check, seed)
    require_inside(base, icp.col, icp.row, source=names[0], image=names[1])
    counts = sorted({int(c) for c in counts if 0 < int(c) <= len(pool)})
    if not counts:
        raise InputError(f"no GCP count fits the {len(pool)} GCP(s) available")
    prepared = {} if prepared is None else prepared
    records = []
    for name in models:
        family = (
            "generic"
            if name in MODEL_NAMES
            else ("orbital" if name.startswith(("eop", "orun", "toutin", "kratky")) else "physical")
        )
        for n in counts:
            gcp = pool.subset(np.arange(n))
            rec = dict(model=name, family=family, n_gcp=n, n_icp=len(icp))
            try:
                if name in MODEL_NAMES:
                    rec.update(_generic_record(name, gcp, icp, sigma_px))
                else:
                    if name not in prepared:
                        prepared[name] = model_set(name).prepare(base)
                    adjustable, params, priors = prepared[name]
                    require_gcps(n, params, name, n_prior=len(priors or {}))
                    res = adjust_model(
                        adjustable,
                        _concat(gcp, icp),
                        params,
                        sigma_px=sigma_px,
                        priors=priors or None,
                        snooping=False,
                        check_inputs=False,
                        what=name,
                    )
                    rec.update(
                        n_params=len(params),
                        gcp_rmse_px=res.gcp_rmse_px,
                        icp_rmse_px=res.check_rmse_px,
                        sigma0=res.sigma0,
                        condition=res.condition,
                    )
            except StereodemError as exc:
                rec.update(error=str(exc))
            except (np.linalg.LinAlgError, ValueError, FloatingPointError) as exc:
                rec.update(error=f"{type(exc).__name__}: {exc}")
            if "n_params" not in rec:
                rec["n_params"] = (
                    n_parameters(name) if name in MODEL_NAMES else len(MODEL_SETS[name].names)
                )
            if progress is not None:
                progress(len(records) + 1, len(models) * len(counts))
            records.append(
                {
                    k: (float(v) if isinstance(v, (np.floating, float)) else v)
                    for k, v in rec.items()
                }
            )
            log.info(
                "%s %d GCP: %s", name, n, rec.get("error") or f"ICP {rec['icp_rmse_px']:.3f} px"
            )
    return records


def compare_splits(
    base,
    points: ControlPoints,
    models,
    counts,
    *,
    reference: str,
    n_check: int = 60,
    n_splits: int = 9,
    seed: int = 0,
    sigma_px=None,
    progress=None,
) -> list[dict]:
    """:func:`compare` repeated over ``n_splits`` random GCP/ICP splits of ``points`` (their
    roles are ignored), each model scored against ``reference`` (a model name, e.g. the
    rigorous ``attitude-bias-drift``) on the same split.

    Returns the records of :func:`compare` with ``split`` (0 ...) and ``ratio`` (the model's
    ICP RMSE over the reference's at the same split and GCP count; NaN when either was
    refused); the reference's own records are included (ratio 1). ``progress(done,
    total)`` is called after each split.
    """
    names = list(dict.fromkeys([reference, *models]))
    generator(seed)  # the seed's rule, before it is combined with the split's number
    _check_count(n_check, len(points))
    out, prepared = [], {}
    for split in range(int(n_splits)):
        rng = generator([seed, split])
        roles = np.array(["gcp"] * len(points), dtype=object)
        roles[rng.permutation(len(points))[:n_check]] = "check"
        recs = compare(
            base,
            _with_roles(points, roles),
            names,
            counts,
            n_check=n_check,
            seed=split,
            sigma_px=sigma_px,
            prepared=prepared,
        )
        ref = {
            r["n_gcp"]: r.get("icp_rmse_px", np.nan)
            for r in recs
            if r["model"] == reference and not r.get("error")
        }
        for r in recs:
            r["split"] = split
            r["ratio"] = (
                float(r.get("icp_rmse_px", np.nan) / ref.get(r["n_gcp"], np.nan))
                if not r.get("error")
                else float("nan")
            )
        out += recs
        if progress is not None:
            progress(split + 1, int(n_splits))
    return out


def split_summary(records) -> list[dict]:
    """Per model and GCP count over the splits of :func:`compare_splits`: ``median_ratio``,
    ``max_ratio``, ``median_icp_px``, ``median_condition``, ``refused`` (splits refused)."""
    out = []
    for name in dict.fromkeys(r["model"] for r in records):
        for n in sorted({r["n_gcp"] for r in records if r["model"] == name}):
            rs = [r for r in records if r["model"] == name and r["n_gcp"] == n]
            ok = [r for r in rs if not r.get("error")]
            ratio = np.array([r["ratio"] for r in ok], float)
            med = lambda k: float(np.median([r[k] for r in ok])) if ok else float("nan")  # noqa: E731, B023
            out.append(
                dict(
                    model=name,
                    n_gcp=n,
                    n_params=rs[0].get("n_params"),
                    splits=len(rs),
                    refused=len(rs) - len(ok),
                    median_ratio=float(np.median(ratio)) if ok else float("nan"),
                    max_ratio=float(np.max(ratio)) if ok else float("nan"),
                    median_icp_px=med("icp_rmse_px"),
                    median_condition=med("condition"),
                    error=None if ok else rs[0].get("error"),
                )
            )
    return out


def split_markdown(summary, reference: str) -> str:
    """Table of :func:`split_summary`: per model and GCP count the median and largest ICP
    RMSE ratio to ``reference``, the median ICP RMSE (px) and condition number."""
    lines = [
        f"| model | u | GCPs | median ICP / {reference} ICP | max | median ICP px | "
        "median condition | refused splits |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for s in summary:
        if s["refused"] == s["splits"]:
            lines.append(
                f"| {s['model']} | {s['n_params']} | {s['n_gcp']} | refused: "
                f"{short_reason(s['error'])} | | | | {s['refused']} |"
            )
            continue
        lines.append(
            f"| {s['model']} | {s['n_params']} | {s['n_gcp']} | {_num(s['median_ratio'], '.2f')} | "
            f"{_num(s['max_ratio'], '.2f')} | {_num(s['median_icp_px'], '.3f')} | "
            f"{_num(s['median_condition'], '.3g')} | {s['refused']} |"
        )
    return "\n".join(lines) + "\n"


def markdown(records) -> str:
    """Ok's Table 6.15 layout: one block per model, one row per GCP count."""
    lines = [
        "| model | u | GCP / ICP | GCP RMSE px | ICP RMSE px | sigma0 | condition |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in records:
        if r.get("error"):
            lines.append(
                f"| {r['model']} | {r.get('n_params', '')} | {r['n_gcp']} / {r['n_icp']} | "
                f"refused: {short_reason(r['error'])} | | | |"
            )
            continue
        lines.append(
            f"| {r['model']} | {r['n_params']} | {r['n_gcp']} / {r['n_icp']} | "
            f"{_num(r['gcp_rmse_px'], '.3f')} | {_num(r['icp_rmse_px'], '.3f')} | "
            f"{_num(r['sigma0'], '.3g')} | {_num(r['condition'], '.3g')} |"
        )
    return "\n".join(lines) + "\n"


def _num(v, fmt: str) -> str:
    """A table figure; ``None`` (a NaN as ``compare.json`` stores it: strict JSON) as NaN."""
    return format(float("nan") if v is None else v, fmt)


def figure(records, path, *, overwrite: bool = False, image: str | None = None):
    """ICP RMSE against GCP count, one line per model (log axes), written to ``path`` (PNG;
    ``overwrite``: replace an existing file); ``image``: the image's name, in the title.

    Each model has its own colour and marker pair (tab20's colours, a marker that changes when
    the colours come round again); the legend sits beside the axes, off the lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 6.5))
    styles = {"generic": ":", "physical": "--", "orbital": "-"}
    colours = plt.get_cmap("tab20").colors
    markers = "o^sDv<>p*h"
    for k, name in enumerate(dict.fromkeys(r["model"] for r in records)):
        rs = [
            r
            for r in records
            if r["model"] == name
            and not r.get("error")
            and np.isfinite(r.get("icp_rmse_px", np.nan))
        ]
        if not rs:
            continue
        ax.plot(
            [r["n_gcp"] for r in rs],
            [r["icp_rmse_px"] for r in rs],
            styles[rs[0]["family"]],
            color=colours[k % len(colours)],
            marker=markers[(k + k // len(colours)) % len(markers)],
            ms=4,
            label=f"{name} ({rs[0]['n_params']})",
        )
    counts = sorted({r["n_gcp"] for r in records})
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xticks(counts, [str(c) for c in counts])
    ax.minorticks_off()
    ax.set_xlabel("number of GCPs")
    ax.set_ylabel("ICP RMSE (pixels)")
    of = f" of {image}" if image else ""
    ax.set_title(f"Check-point error against GCP count{of} (same ICPs for every model)")
    ax.grid(True, which="major", alpha=0.3)
    n_lines = len(ax.get_lines())
    ax.legend(
        fontsize=7,
        ncol=1 if n_lines <= 30 else 2,
        title="model (parameters)\ndotted generic, dashed physical,\nsolid orbital",
        title_fontsize=7,
        loc="upper left",
        bbox_to_anchor=(1.01, 1.0),  # beside the axes: inside, it hid lines
        borderaxespad=0.0,
    )
    return save_png(fig, path, dpi=120, overwrite=overwrite, bbox_inches="tight")
