"""Reliability of a least-squares adjustment: redundancy numbers, standardised residuals,
Baarda's data snooping, Pope's tau test, minimal detectable biases, the global variance test.

Everything works on the *decorrelated* (whitened) system ``A dx ~ e`` in which every
observation has unit a-priori variance (``A = W J``, ``e = W (f(x) - l)``, ``W^T W = P``).
Then (Baarda 1968; Förstner 1987; Bettemir 2006, §6.3 and Tables B.32/B.33):

* ``Q_xx = (A^T A)^-1`` and the hat matrix ``H = A Q_xx A^T``;
* redundancy numbers ``r_i = 1 - H_ii`` with ``sum r_i = n - u`` (the trace identity);
* standardised residuals ``w_i = e_i / sqrt(r_i)`` (normal N(0, 1) without a blunder, when
  the a-priori sigma is right) tested against ``k = z(1 - alpha/2)`` — Baarda data snooping;
  with an unknown sigma, Pope's ``tau_i = e_i / (sigma0_hat sqrt(r_i))`` against the tau
  distribution with ``f = n - u`` degrees of freedom;
* the non-centrality ``delta_0 = z(1 - alpha/2) + z(power)`` (4.13 for alpha = 0.001 and a
  power of 80 %), the minimal detectable bias of observation ``i`` (internal reliability)
  ``nabla_0 l_i = sigma_i delta_0 / sqrt(r_i)`` and its normalised effect on the parameters
  (external reliability) ``delta_0i = delta_0 sqrt((1 - r_i) / r_i) = delta_0 sqrt(H_ii / r_i)``.

Errata of the seed fixed here (notes §4.4 and §9.2 item 10): the threshold that matches
``alpha_0 = 0.001`` is 3.29, not the 1.96 the thesis used, and ``sigma_i = sigma_0 / sqrt(p_i)``
(not ``sigma_0 sqrt(p_i)``).
"""

from __future__ import annotations

import numpy as np

# the normal, t and chi-square quantiles from scipy.special, as scipy.stats computes them
# (importing scipy.stats costs ~0.2 s, paid by every command that imports the adjustment)
from scipy.special import chdtr, gammaincinv, ndtri, stdtrit

from stereodem.core.errors import InputError

__all__ = [
    "hat_diagonal",
    "redundancy_numbers",
    "standardized_residuals",
    "baarda_threshold",
    "pope_threshold",
    "noncentrality",
    "minimal_detectable_bias",
    "external_reliability",
    "variance_test",
    "outlier_test",
]


def hat_diagonal(A, Qxx) -> np.ndarray:
    """Diagonal of ``H = A Q_xx A^T`` without forming ``H`` (row-wise quadratic forms)."""
    A = np.asarray(A, dtype=np.float64)
    return np.einsum("ij,jk,ik->i", A, Qxx, A)


def redundancy_numbers(A, Qxx) -> np.ndarray:
    """Redundancy numbers ``r_i = 1 - (A Q_xx A^T)_ii`` of whitened observations (0..1)."""
    return np.clip(1.0 - hat_diagonal(A, Qxx), 0.0, 1.0)


#: redundancy number below which an observation counts as uncontrolled and is not tested (its
#: residual is ~0 whatever its error; dividing by sqrt(r) would only amplify rounding and the
#: last iteration's remainder), e.g. the along-track coordinates of along-track stereo ties
R_MIN = 1e-3


def standardized_residuals(e, r, sigma0: float = 1.0, *, r_min: float = R_MIN) -> np.ndarray:
    """``w_i = e_i / (sigma0 sqrt(r_i))`` for whitened residuals ``e``; NaN where
    ``r_i < r_min`` (an uncontrolled observation cannot be tested)."""
    e, r = np.asarray(e, float), np.asarray(r, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(r > r_min, e / (sigma0 * np.sqrt(r)), np.nan)


def check_probability(name: str, value) -> float:
    """``value`` as a probability strictly between 0 and 1 (the tests' significance level
    ``alpha``, the power), else :class:`InputError` naming it: ``alpha = 2`` made every
    threshold NaN, against which no residual was ever an outlier ("outliers: none", data
    snooping silently off)."""
    v = float(value)
    if not 0.0 < v < 1.0:
        raise InputError(f"{name} must be a probability between 0 and 1 (exclusive), got {value}")
    return v


def baarda_threshold(alpha: float) -> float:
    """Critical value of data snooping, two-sided normal: ``z(1 - alpha/2)`` (3.29 for 0.001)."""
    alpha = check_probability("alpha (significance level of data snooping)", alpha)
    return float(ndtri(1.0 - alpha / 2.0))


def pope_threshold(alpha: float, dof: int) -> float:
    """Critical value of Pope's tau test with ``dof = n - u`` (Pope 1976).

    ``tau = sqrt(f) t / sqrt(f - 1 + t^2)`` with ``t = t_{f-1}(1 - alpha/2)``; NaN for f < 2.
    """
    alpha = check_probability("alpha (significance level of data snooping)", alpha)
    f = int(dof)
    if f < 2:
        return float("nan")
    t = stdtrit(f - 1, 1.0 - alpha / 2.0)
    return float(np.sqrt(f) * t / np.sqrt(f - 1 + t * t))


def noncentrality(alpha: float = 0.001, power: float = 0.80) -> float:
    """Baarda's ``delta_0 = z(1 - alpha/2) + z(power)``; 4.13 for alpha 0.001, power 0.80."""
    alpha = check_probability("alpha (significance level of data snooping)", alpha)
    power = check_probability("power (of the outlier tests)", power)
    return float(ndtri(1.0 - alpha / 2.0) + ndtri(power))


def minimal_detectable_bias(sigma, r, delta0: float) -> np.ndarray:
    """Internal reliability ``nabla_0 l_i = sigma_i delta_0 / sqrt(r_i)`` (units of sigma);
    inf where ``r_i = 0``."""
    sigma, r = np.asarray(sigma, float), np.asarray(r, float)
    with np.errstate(divide="ignore"):
        return np.where(r > 0, sigma * delta0 / np.sqrt(np.maximum(r, 1e-300)), np.inf)


def external_reliability(r, delta0: float) -> np.ndarray:
    """``delta_0i = delta_0 sqrt((1 - r_i) / r_i)``: the effect of an undetected minimal bias on
    the parameters, in units of their standard deviation (Bettemir's "network anomaly")."""
    r = np.asarray(r, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(r > 0, delta0 * np.sqrt((1.0 - r) / np.maximum(r, 1e-300)), np.inf)


def outlier_test(sigma_known: bool, alpha: float, power: float, threshold, delta0, snooping):
    """The ``test`` entry of an adjustment report: ``name`` (``baarda`` when the a-priori
    sigma is known, else Pope's ``pope``), ``alpha`` (significance per observation), ``power``,
    ``threshold`` (of ``|w|`` or ``|tau|``, unitless), ``delta0`` (:func:`noncentrality`) and
    ``snooping`` (whether outliers were rejected)."""
    return {
        "name": "baarda" if sigma_known else "pope",
        "alpha": alpha,
        "power": power,
        "threshold": float(threshold),
        "delta0": delta0,
        "snooping": bool(snooping),
    }


def variance_test(vtpv: float, dof: int, alpha: float = 0.05) -> dict:
    """Two-sided chi-square test of the a-posteriori variance factor against 1.

    Under H0 (a-priori sigmas right, no blunders) ``v^T P v ~ chi2(dof)``.
    """
    dof = int(dof)
    if dof <= 0:
        return {
            "statistic": float(vtpv),
            "dof": dof,
            "alpha": alpha,
            "lower": None,
            "upper": None,
            "p_value": None,
            "passed": None,
        }
    lo, hi = 2.0 * gammaincinv(dof / 2.0, np.array([alpha / 2.0, 1.0 - alpha / 2.0]))
    cdf = chdtr(dof, vtpv)
    return {
        "statistic": float(vtpv),
        "dof": dof,
        "alpha": alpha,
        "lower": float(lo),
        "upper": float(hi),
        "p_value": float(2.0 * min(cdf, 1.0 - cdf)),
        "passed": bool(lo <= vtpv <= hi),
    }
