"""Orun & Natarajan (1994) pushbroom model ("trade-off" model; Topan 2009 Eq. 3.27-3.28,
Ok 2005 §3.2).

Because ``d omega`` cannot be told apart from ``dY`` nor ``d phi`` from ``dX`` over one
scene, the attitude is reduced to the heading ``kappa`` (quadratic in the line) and the image
tilt ``omega``; the projection centre is quadratic in the line::

    X = X_0 + a1 x + b1 x^2,  Y = Y_0 + a2 x + b2 x^2,  Z = Z_0 + a3 x + b3 x^2,
    kappa = kappa_0 + a4 x + b4 x^2,   R = R3(kappa) R1(omega)          (Topan 3.27, 3.28)

with ``x`` the normalised line (:func:`._common.line_variable`: ``x`` in [-1, 1], so each
coefficient is the change from the centre line to the last line, in metres or radians), in a
local east/north/up frame with its origin on the ellipsoid below the image centre, as Ok
computed it.

``omega`` is "the tilt angle of the image" (Topan's transcription): a known quantity of the
product, held at the metadata's value, not an unknown. Freeing it next to ``Y_0`` — the
trade-off the model is named after — makes the normal matrix near-singular (condition number
~1e8 on ASTER, against ~1e2-1e4 without it). ``phi`` (and the rates of ``omega``) are likewise
held at the metadata's values: zero pitch for a nadir image, the along-track tilt for a forward
or backward view (which Eq. 3.28 does not foresee), and the slow turn of the orbital frame
against the local ground frame (about 1 mrad/s).

Unknowns and their weights
--------------------------
Orun & Natarajan adjust ``X_0, Y_0, Z_0, kappa_0``, ``a1, a2, a4`` and ``b1, b2, b4``
(``a3, b3`` "highly correlated, eliminated"; 10 unknowns) starting from the ephemeris, and set
the ``a_i, b_i`` to zero on some runs. With 10 GCPs (20 observations) the three second-order
terms are weakly determined: they fit the GCPs' measurement noise and extrapolate it to the
check points (median ICP RMSE 1.1-1.3x the rigorous model's on ASTER 3N and 3B, up to
8x on single splits). They are
therefore weighted observations about their metadata values (:data:`PRIORS`, fictitious
observations of the adjustment engine): the curvature of the trajectory and of the heading
over a scene of a few seconds is what the ephemeris gives (it is in the initial values); the
error of ephemeris and attitude varies with the orbital period (~100 min), so its curvature
over a scene is far below the stated sigmas (2 m, 0.13 ASTER pixel; 3e-5 rad of heading turns
the ends of a 60 km line by +-0.9 m).

Parameter sets: ``orun`` (default, 10 parameters, 3 of them weighted) and ``orun-full``
(12: also ``a3, b3``, the height drift and curvature, ``b3`` weighted). With the weights the
model is within a few per cent of the rigorous one from 6 GCPs on (median over random splits,
``benchmarks/bench_orbital_splits.py``); below that every model, the rigorous one included, is
pixels off at the check points, and 3 GCPs are refused (4 needed).

Ok's thesis (§3.2) prints a different split (``omega`` quadratic, ``phi`` and ``kappa``
constant) and a wrong count; this module follows Topan's transcription of the 1994 paper.
"""

from __future__ import annotations

from stereodem.sensor.models.orbital.linecam import PolynomialLineCamera

_POS = ("X_0", "X_1", "X_2", "Y_0", "Y_1", "Y_2", "Z_0")
_HEADING = ("kappa_0", "kappa_1", "kappa_2")
#: A-priori standard deviations (m, rad) of the second-order coefficients about the metadata's
#: values (module docstring).
SECOND_ORDER_SIGMA = {"X_2": 2.0, "Y_2": 2.0, "Z_2": 2.0, "kappa_2": 3e-5}


class OrunNatarajanModel(PolynomialLineCamera):
    """Orun & Natarajan model; build it with :meth:`from_model` (a pushbroom, ASTER or RPC
    model of the image gives the initial values)."""

    ADJUSTABLE = _POS + ("Z_1", "Z_2") + _HEADING
    ADJUST_SETS = {
        "orun": list(_POS + _HEADING),
        "orun-full": list(ADJUSTABLE),
    }
    #: Weighted parameters of each set: name -> a-priori sigma about the initial value.
    PRIORS = {
        k: {n: s for n, s in SECOND_ORDER_SIGMA.items() if n in v} for k, v in ADJUST_SETS.items()
    }
    REFINE_FROZEN = ("omega_0", "phi_0", "phi_1")
    MODEL_TYPE = "orun-natarajan"

    @staticmethod
    def _shape_initial(coef):
        # omega and phi are not adjusted: held at the metadata's values (their rates over
        # the scene included: the orbital frame turns by ~1 mrad/s against the ground frame)
        return dict(coef)
