"""The result of an adjustment and its JSON report (``adjust_report.json``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from stereodem.sensor.estimation.adjust import reliability as rel
from stereodem.sensor.io.sidecar import model_to_dict

__all__ = ["AdjustmentResult", "ParameterEstimate", "fit_statistics", "rmse"]


def rmse(res) -> float:
    """Radial RMSE of (n, 2) pixel residuals, ``sqrt(mean(dc^2 + dr^2))``; NaN when empty."""
    res = np.asarray(res, float).reshape(-1, 2)
    res = res[np.all(np.isfinite(res), axis=1)]
    return float(np.sqrt(np.mean(np.sum(res**2, axis=1)))) if len(res) else float("nan")


def _axis_rmse(res):
    res = np.asarray(res, float).reshape(-1, 2)
    res = res[np.all(np.isfinite(res), axis=1)]
    return [float(v) for v in np.sqrt(np.mean(res**2, axis=0))] if len(res) else [None, None]


def _num(v):
    v = float(v)
    return v if np.isfinite(v) else None


def fit_statistics(vtpv: float, dof: int, n_observations: int, sigma_known: bool, alpha=0.05):
    """The :class:`ParameterEstimate` fields of a fit's statistics, from ``vtpv`` (weighted sum of
    squared residuals), the redundancy ``dof`` and the number of observations: ``sigma0``
    (a-posteriori standard deviation of unit weight, ``sqrt(vtpv / dof)``; NaN without
    redundancy), ``sigma_known``, ``dof``, ``n_observations`` and ``chi2_test``
    (:func:`.reliability.variance_test` at level ``alpha`` when the a-priori sigma is known; else
    the statistic only, not tested)."""
    return dict(
        sigma0=math.sqrt(vtpv / dof) if dof > 0 else float("nan"),
        sigma_known=sigma_known,
        dof=dof,
        n_observations=n_observations,
        chi2_test=rel.variance_test(vtpv, dof, alpha)
        if sigma_known
        else {
            "statistic": vtpv,
            "dof": dof,
            "alpha": alpha,
            "passed": None,
            "note": "a-priori sigma unknown: sigma0 estimated, not tested",
        },
    )


@dataclass
class ParameterEstimate:
    """What every adjustment (single image or bundle) estimates and reports.

    Attributes
    ----------
    names, values, initial_values, std, units : the parameters (``std`` a posteriori)
    covariance : (u, u) covariance of the parameters
    condition : condition number of the equilibrated normal matrix
    sigma0 : a-posteriori standard deviation of unit weight
    sigma_known : whether the a-priori observation sigmas were given
    dof, n_observations : redundancy and number of observations
    chi2_test : dict of :func:`.reliability.variance_test`
    outliers : list of dict (``id``, ``reason``, ``statistic``) in rejection order
    test : the outlier test (``name``: baarda or pope, ``alpha``, ``power``, ``threshold``,
        ``delta0``, ``snooping``)
    iterations, converged, tolerance : the iteration (criterion ``max |dx_k| / sigma_k <
        tolerance``)
    """

    names: list
    values: np.ndarray
    initial_values: np.ndarray
    std: np.ndarray
    units: list
    covariance: np.ndarray
    condition: float
    sigma0: float
    sigma_known: bool
    dof: int
    n_observations: int
    chi2_test: dict
    outliers: list = field(kw_only=True)
    test: dict = field(kw_only=True)
    iterations: int = field(kw_only=True)
    converged: bool = field(kw_only=True)
    tolerance: float = field(kw_only=True)

    def parameters_text(self, most: int = 6) -> str:
        """The estimated parameters for a result line: ``"col_shift +2.49982 ± 0.00016 px,
        row_shift -1.50005 ± 0.00016 px"``; more than ``most`` of them: only how many (the
        report lists them)."""
        if len(self.names) > most:
            return f"{len(self.names)} parameters (in the report)"
        return ", ".join(
            f"{n} {float(v):+.6g} ± {float(sd):.2g}" + (f" {u}" if u else "")
            for n, v, sd, u in zip(self.names, self.values, self.std, self.units)
        )

    @property
    def correlation(self) -> np.ndarray:
        s = np.sqrt(np.diag(self.covariance))
        with np.errstate(divide="ignore", invalid="ignore"):
            return self.covariance / np.outer(s, s)

    def _estimate_report(self, n_unknowns: int, priors: dict | None = None) -> dict:
        """The report entries ``sigma0`` ... ``condition`` (JSON-ready; NaN -> null)."""
        priors = priors or {}
        return {
            "sigma0": _num(self.sigma0),
            "sigma0_a_priori": 1.0,
            "sigma_known": self.sigma_known,
            "chi2_test": self.chi2_test,
            "dof": int(self.dof),
            "n_observations": int(self.n_observations),
            "n_unknowns": int(n_unknowns),
            "parameters": [
                {
                    "name": n,
                    "value": float(v),
                    "initial": float(v0),
                    "std": _num(s),
                    "unit": u,
                    **({"prior_std": priors[n]} if n in priors else {}),
                }
                for n, v, v0, s, u in zip(
                    self.names, self.values, self.initial_values, self.std, self.units
                )
            ],
            "covariance": [[_num(v) for v in row] for row in self.covariance],
            "correlation": [[_num(v) for v in row] for row in self.correlation],
            "condition": _num(self.condition),
        }

    def _test_report(self) -> dict:
        """The report entries ``outlier_details`` ... ``converged``."""
        return {
            "outlier_details": self.outliers,
            "test": self.test,
            "iterations": int(self.iterations),
            "converged": bool(self.converged),
        }


@dataclass
class AdjustmentResult(ParameterEstimate):
    """Estimated parameters, their precision and the reliability of the observations.

    Arrays over points follow ``gcp_ids`` (every point of role ``gcp``, outliers included:
    their residuals are those of the final model, their ``w``/``redundancy``/``mdb`` NaN)
    and ``check_ids``. Residuals are ``model(ground) - measured`` in pixels (col, row).

    Attributes
    ----------
    model : the adjusted model (same protocol as the input)
    names, values, initial_values, std, units : parameters (``std`` a posteriori: scaled by
        ``sigma0`` when the a-priori sigma is unknown, else the a-priori propagation)
    covariance, correlation : (u, u)
    condition : condition number of the equilibrated normal matrix
    sigma0 : a-posteriori standard deviation of unit weight
    sigma_known : whether the a-priori observation sigmas were given (Baarda's test and the
        chi-square test apply) or assumed 1 px (Pope's tau test)
    chi2_test : dict of :func:`.reliability.variance_test`
    redundancy, w, mdb : (n_gcp, 2) redundancy numbers, standardised residuals (w, or Pope's
        tau when sigma is unknown), minimal detectable biases (px)
    external_reliability : (n_gcp, 2) ``delta_0 sqrt((1 - r) / r)``
    residuals_px, check_residuals_px : (n, 2)
    ground_residuals_m : (n_gcp, 3) east/north/up residuals of ground observations (zeros
        when the ground coordinates were fixed)
    outliers : list of dict (``id``, ``reason``, ``statistic``) in rejection order
    """

    model: object
    gcp_ids: np.ndarray
    check_ids: np.ndarray
    gcp_points: object
    check_points: object
    residuals_px: np.ndarray
    check_residuals_px: np.ndarray
    ground_residuals_m: np.ndarray
    redundancy: np.ndarray
    w: np.ndarray
    mdb: np.ndarray
    external_reliability: np.ndarray
    model_set: str | None = None
    priors: dict = field(default_factory=dict)
    regularization: float = 0.0
    initial_model: object = None
    variance_components: dict | None = None
    #: "converged" (criterion met) or "stalled" (line search stopped below STATIONARY_SIGMA)
    status: str = "converged"
    max_correction: float = float("nan")  #: last max |dx_k| / sigma_k

    # ---------------------------------------------------------------- derived
    @property
    def outlier_mask(self) -> np.ndarray:
        bad = {o["id"] for o in self.outliers}
        return np.array([i in bad for i in self.gcp_ids], dtype=bool)

    @property
    def gcp_rmse_px(self) -> float:
        """Radial RMSE of the GCPs kept in the adjustment (px)."""
        return rmse(self.residuals_px[~self.outlier_mask])

    @property
    def check_rmse_px(self) -> float:
        """Radial RMSE of the independent check points (px); NaN without check points."""
        return rmse(self.check_residuals_px)

    @property
    def n_unknowns(self) -> int:
        return len(self.names)

    @property
    def parameters(self) -> dict:
        """``{name: value}`` of the estimated parameters."""
        return dict(zip(self.names, (float(v) for v in self.values)))

    # ---------------------------------------------------------------- report
    def to_report(self) -> dict:
        """The content of ``adjust_report.json`` (JSON-ready; NaN -> null)."""
        out_mask = self.outlier_mask
        points = []
        for k, pid in enumerate(self.gcp_ids):
            points.append(
                {
                    "id": str(pid),
                    "role": "gcp",
                    "col": float(self.gcp_points.col[k]),
                    "row": float(self.gcp_points.row[k]),
                    "residual_px": [_num(v) for v in self.residuals_px[k]],
                    "w": [_num(v) for v in self.w[k]],
                    "r": [_num(v) for v in self.redundancy[k]],
                    "mdb_px": [_num(v) for v in self.mdb[k]],
                    "ground_residual_m": [_num(v) for v in self.ground_residuals_m[k]],
                    "outlier": bool(out_mask[k]),
                }
            )
        for k, pid in enumerate(self.check_ids):
            points.append(
                {
                    "id": str(pid),
                    "role": "check",
                    "col": float(self.check_points.col[k]),
                    "row": float(self.check_points.row[k]),
                    "residual_px": [_num(v) for v in self.check_residuals_px[k]],
                    "w": None,
                    "r": None,
                    "mdb_px": None,
                    "ground_residual_m": None,
                    "outlier": False,
                }
            )
        try:
            model_dict = model_to_dict(self.model)
        except Exception as exc:  # a model without a serialiser still gets its statistics
            model_dict = {"type": type(self.model).__name__, "error": str(exc)}
        return {
            "model": model_dict,
            "model_set": self.model_set,
            **self._estimate_report(self.n_unknowns, self.priors),
            "points": points,
            "gcp_rmse_px": _num(self.gcp_rmse_px),
            "gcp_rmse_col_row_px": _axis_rmse(self.residuals_px[~out_mask]),
            "check_rmse_px": _num(self.check_rmse_px),
            "check_rmse_col_row_px": _axis_rmse(self.check_residuals_px),
            "n_gcp": int(len(self.gcp_ids) - out_mask.sum()),
            "n_check": int(len(self.check_ids)),
            "outliers": [o["id"] for o in self.outliers],
            **self._test_report(),
            "status": self.status,
            "max_correction": _num(self.max_correction),
            "convergence_criterion": f"max |dx_k| / sigma_k < {self.tolerance:g}",
            "regularization": _num(self.regularization),
            "redundancy_sum": _num(np.nansum(self.redundancy)),
            "variance_components": self.variance_components,
        }
