"""Adjustment: estimating and correcting sensor models from ground control and tie points.

* :func:`adjust_model` — one image's model from GCPs (Gauss–Markov, or Gauss–Helmert when the
  GCP ground coordinates are observations too), with a-posteriori sigma0 and its chi-square
  test, covariance and correlation, redundancy numbers, standardised residuals, Baarda data
  snooping / Pope's tau test, minimal detectable biases and iterative outlier rejection;
  returns an :class:`AdjustmentResult` (``to_report()`` is ``adjust_report.json``).
* :mod:`.model_sets` — named parameter sets (``rpc-shift``, ``rpc-affine``, ``frame-eo``,
  ``attitude-bias`` ...), extensible with :func:`register_model_set`.
* :func:`bundle_adjust` — a stereo pair from tie points and optional GCPs, tie-point ground
  coordinates as unknowns, sparse normal equations.
* :func:`adjust_generic` — the 15 GCP-fitted generic models through the same statistics.
* :func:`write_report` — ``adjust_report.json``, a Markdown summary and the residual figure.

Sources: Bettemir (2006) §5–7 and Tables B.32/B.33 (mixed model, constraints, reliability),
Topan (2009) §3.3, §3.6 (Gauss–Helmert adjustment of orbital models), Baarda (1968), Pope
(1976), Förstner (1987), Grodecki & Dial (2003), Fraser & Hanley (2005).
"""

from stereodem.sensor.estimation.adjust.model_sets import (
    MODEL_SETS,
    ModelSet,
    model_set,
    register_model_set,
)
from stereodem.sensor.estimation.adjust.result import AdjustmentResult
from stereodem.sensor.estimation.adjust.single import adjust_model, required_gcps

__all__ = [
    "adjust_model",
    "AdjustmentResult",
    "MODEL_SETS",
    "ModelSet",
    "model_set",
    "register_model_set",
    "required_gcps",
    "bundle_adjust",
    "BundleResult",
    "adjust_generic",
    "write_report",
]


def __getattr__(name):  # heavier parts imported on first use
    if name in ("bundle_adjust", "BundleResult"):
        from stereodem.sensor.estimation.adjust import bundle

        return getattr(bundle, name)
    if name == "adjust_generic":
        from stereodem.sensor.estimation.adjust.generic import adjust_generic

        return adjust_generic
    if name == "write_report":
        from stereodem.sensor.estimation.adjust.report import write_report

        return write_report
    raise AttributeError(name)
