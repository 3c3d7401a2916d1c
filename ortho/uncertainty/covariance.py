"""The input covariance of an uncertainty run: ``NAME=VALUE`` σ pairs and/or the covariance of
an adjustment report.

An adjustment report (``adjust_report.json``, written by the adjustment command) holds::

    {"model": <sidecar dict of the adjusted model>,
     "parameters": [{"name": ..., "value": ..., "std": ..., "unit": ...}, ...],
     "covariance": [[...], ...]}          # in the order of "parameters"

A bundle (pair) report has ``"model": {"left": {...}, "right": {...}}`` and parameter names
``left.<name>`` / ``right.<name>``; the side whose geometry is the image's is used, with its
block (the marginal covariance) of the joint covariance.

:func:`read_adjust_report` reads it; :func:`assemble` checks that the report belongs to the
image's model, and joins it with independent σ pairs (block-diagonal covariance).
"""

from __future__ import annotations

import inspect
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stereodem.core.errors import InputError
from stereodem.ortho.choices import check_input_sigma
from stereodem.ortho.uncertainty.propagation import adjustable_model, check_names, check_psd
from stereodem.sensor.io.sidecar import model_from_dict
from stereodem.sensor.models.corrected import ImageCorrectedModel


def parse_sigma_pairs(pairs) -> dict:
    """``["col_shift=0.5", "dem_height=3"]`` -> ``{name: σ}``; raises :class:`InputError` for a
    malformed pair, a repeated name, or a negative / non-finite σ."""
    out = {}
    for item in pairs or []:
        name, sep, val = str(item).partition("=")
        name = name.strip()
        if not sep or not name:
            raise InputError(f"--sigma expects NAME=VALUE, got {item!r}")
        try:
            v = float(val)
        except ValueError:
            raise InputError(f"--sigma {name}: {val!r} is not a number") from None
        check_input_sigma(v, f"--sigma {name}")
        if name in out:
            raise InputError(f"--sigma {name} given twice")
        out[name] = v
    return out


@dataclass
class AdjustReport:
    """An adjustment report: the adjusted model, parameter names and their covariance."""

    path: Path
    model: object
    names: list
    values: np.ndarray
    covariance: np.ndarray
    sides: dict | None = None  # bundle: side -> AdjustReport of that image

    def side_for(self, model):
        """The single-image report matching ``model`` (itself unless a bundle report)."""
        if not self.sides:
            return self
        diffs = {
            k: _same_geometry(adjustable_model(model, r.names), adjustable_model(r.model))
            for k, r in self.sides.items()
        }
        best = min(diffs, key=diffs.get)
        return self.sides[best] if diffs[best] <= 1e-3 else next(iter(self.sides.values()))


def read_adjust_report(path) -> AdjustReport:
    """Read and check an ``adjust_report.json`` (one-line :class:`InputError` on any defect)."""
    p = Path(path)
    try:
        doc = json.loads(p.read_text())
    except FileNotFoundError:
        raise InputError(f"{p}: no such covariance file") from None
    except (OSError, ValueError) as exc:
        raise InputError(f"{p}: not a JSON adjustment report ({exc})") from None
    if not isinstance(doc, dict) or not {"model", "parameters", "covariance"} <= set(doc):
        raise InputError(f"{p}: an adjustment report needs 'model', 'parameters' and 'covariance'")
    try:
        names = [str(q["name"]) for q in doc["parameters"]]
        values = np.array([float(q.get("value", 0.0)) for q in doc["parameters"]])
        C = np.array(doc["covariance"], dtype=float)
    except (TypeError, KeyError, ValueError) as exc:
        raise InputError(f"{p}: malformed parameters or covariance ({exc})") from None
    if C.shape != (len(names), len(names)):
        raise InputError(
            f"{p}: covariance is {C.shape}, expected {len(names)} x {len(names)} "
            f"(one row per parameter)"
        )
    try:
        check_psd(C, what=f"{p}: covariance")
    except InputError as exc:
        raise InputError(str(exc)) from None

    def load(d):
        try:
            return model_from_dict(d, source=p)
        except Exception as exc:  # any defect of the embedded sidecar
            raise InputError(f"{p}: cannot read the report's model ({exc})") from None

    md = doc["model"]
    if isinstance(md, dict) and "type" not in md and {"left", "right"} <= set(md):
        sides = {}
        for side in ("left", "right"):
            idx = [k for k, n in enumerate(names) if n.startswith(side + ".")]
            sides[side] = AdjustReport(
                p,
                load(md[side]),
                [names[k][len(side) + 1 :] for k in idx],
                values[idx],
                C[np.ix_(idx, idx)],
            )
        return AdjustReport(p, None, names, values, C, sides)
    return AdjustReport(p, load(md), names, values, C)


def _same_geometry(a, b, tol_px: float = 1e-3) -> float:
    """Largest image-coordinate difference (px) of two models over the image footprint, with
    ``b``'s adjustable parameters set to ``a``'s."""
    try:
        b = b.with_parameters(**a.parameters())
    except Exception:
        return float("inf")
    lon, lat = a.footprint(0.0, n=5) if _has_footprint_n(a) else a.footprint(0.0)
    lon, lat = np.asarray(lon, float), np.asarray(lat, float)
    ca, ra = a.project(lon, lat, np.zeros_like(lon))
    cb, rb = b.project(lon, lat, np.zeros_like(lon))
    d = np.hypot(np.asarray(ca) - cb, np.asarray(ra) - rb)
    return float(np.nanmax(d)) if np.isfinite(d).any() else float("inf")


def _has_footprint_n(model) -> bool:
    try:
        return "n" in inspect.signature(model.footprint).parameters
    except (TypeError, ValueError):
        return False


def assemble(
    model,
    *,
    sigmas: dict | None = None,
    report: AdjustReport | None = None,
    image: str | None = None,
):
    """The model to propagate through, the input names and their covariance.

    With a report, the report's (adjusted) model is used after checking that it is the image's
    model (same type, same geometry within 10⁻³ px when its parameters are set to the image
    model's); σ pairs add independent inputs. The image-space correction's parameters
    (``col_shift`` ...) are inputs of every model (:func:`adjustable_model`): an
    ``adjust --model rpc-shift`` report of a physical model, or ``--sigma col_shift`` for one,
    wraps it. Returns ``(model, names, D)``.
    """
    sigmas = dict(sigmas or {})
    if report is not None:
        report = report.side_for(model)
    # the image-space correction (col_shift ...) wraps any model when named, as adjust's
    # rpc-* sets do: an rpc-shift report of a physical model is that model's
    model = adjustable_model(model, [*(report.names if report is not None else []), *sigmas])
    names, blocks = [], []
    if report is not None:
        rmodel = adjustable_model(report.model)
        inner = lambda m: type(getattr(m, "model", m)).__name__
        if type(rmodel) is not type(model) or inner(rmodel) != inner(model):
            what = lambda m: (
                f"{type(m).__name__}({inner(m)})"
                if isinstance(m, ImageCorrectedModel)
                else type(m).__name__
            )
            raise InputError(
                f"{report.path}: covariance file for another model "
                f"({what(rmodel)}; the image {image or ''} has {what(model)})"
            )
        diff = _same_geometry(model, rmodel)
        if not diff <= 1e-3:
            raise InputError(
                f"{report.path}: covariance file for another model (its geometry differs "
                f"from the image's by {diff:.3g} px)"
            )
        # the image defines the image size (an RPC sidecar dict may not carry it)
        for m in (rmodel, getattr(rmodel, "model", None)):
            if m is not None:
                m.width, m.height = model.width, model.height
        model = rmodel
        check_names(model, report.names)
        both = sorted(set(report.names) & set(sigmas))
        if both:
            raise InputError(
                f"--sigma {', '.join(both)} also in {report.path}; give each input once"
            )
        names += report.names
        blocks.append(report.covariance)
    if sigmas:
        extra = list(sigmas)
        check_names(model, extra)
        names += extra
        blocks.append(np.diag([sigmas[n] ** 2 for n in extra]))
    if not names:
        raise InputError(
            "no input uncertainty: give --sigma NAME=VALUE pairs or --covariance REPORT"
        )
    check_names(model, names)
    u = len(names)
    D = np.zeros((u, u))
    k = 0
    for B in blocks:
        m = B.shape[0]
        D[k : k + m, k : k + m] = B
        k += m
    return model, names, check_psd(D)
