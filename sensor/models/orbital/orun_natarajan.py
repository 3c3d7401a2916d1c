"""Orun & Natarajan (1994) pushbroom model ("trade-off" model; Topan 2009 Eq. 3.27-3.28,
Ok 2005 §3.2).

Because ``d omega`` cannot be told apart from ``dY`` nor ``d phi`` from ``dX`` over one
scene, the attitude is reduced to the image tilt ``omega`` (a constant) and the heading
``kappa`` (quadratic in the line); the projection centre is quadratic in the line::

    X = X_0 + a1 x + b1 x^2,  Y = Y_0 + a2 x + b2 x^2,  Z = Z_0 + a3 x + b3 x^2,
    kappa = kappa_0 + a4 x + b4 x^2,   R = R3(kappa) R1(omega)          (Topan 3.27, 3.28)

with ``x`` the normalised line (:func:`._common.line_variable`), in a local east/north/up
frame as Ok computed it. ``phi`` (and the rates of ``omega``) are not adjusted: they are held at
the metadata's values (zero pitch for a nadir image, the along-track tilt for a forward or
backward view, which Eq. 3.28 does not foresee, and the slow turn of the orbital frame against
the local ground frame, about 1 mrad/s).

Ok's thesis (§3.2) prints a different split (``omega`` quadratic, ``phi`` and ``kappa``
constant) and a wrong count; this module follows Topan's transcription of the 1994 paper.

Parameter sets: ``orun`` (default, 11 parameters) drops ``a3, b3`` as Orun & Natarajan did
("highly correlated, eliminated"); ``orun-full`` keeps all 13.
"""
from __future__ import annotations

from stereodem.sensor.models.orbital.linecam import PolynomialLineCamera

_POS = ("X_0", "X_1", "X_2", "Y_0", "Y_1", "Y_2", "Z_0")


class OrunNatarajanModel(PolynomialLineCamera):
    """Orun & Natarajan model; build it with :meth:`from_model` (a pushbroom, ASTER or RPC
    model of the image gives the initial values)."""

    ADJUSTABLE = _POS + ("Z_1", "Z_2", "kappa_0", "kappa_1", "kappa_2", "omega_0")
    ADJUST_SETS = {
        "orun": list(_POS + ("kappa_0", "kappa_1", "kappa_2", "omega_0")),
        "orun-full": list(ADJUSTABLE),
    }
    REFINE_FROZEN = ("phi_0", "phi_1")
    MODEL_TYPE = "orun-natarajan"

    @staticmethod
    def _shape_initial(coef):
        # omega and phi are not adjusted: held at the metadata's values (their rates over
        # the scene included: the orbital frame turns by ~1 mrad/s against the ground frame)
        return dict(coef)
