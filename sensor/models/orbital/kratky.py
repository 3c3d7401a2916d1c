"""Kratky's (1987, 1989) polynomial model of a linear-array image (Topan 2009 Eq. 3.23-3.24).

``[X Y Z]^T = [Xc Yc Zc]^T + r F_M(kappa, phi, omega) [x', y', -f]^T`` with the projection
centre a polynomial of the along-track image coordinate (``Xc = X_0 + X_1 x + X_2 x^2``,
likewise ``Yc``, ``Zc``), attitude angles linear in it (``(kappa, phi, omega)_0`` and their
rates) and a scale change along the scan line: the polynomial mapping of the exterior
orientation along the strip that Kratky used for SPOT. ``x`` is the normalised line
(:func:`._common.line_variable`); the frame is local east/north/up.

Parameter sets: ``kratky`` (default) adjusts the attitude offsets and rates and the
scan-line scale (7: the projection centres are held at the ephemeris, which fixes the
``phi``/``X`` and ``omega``/``Y`` correlation that makes the full set ill-conditioned);
``kratky-full`` adjusts all 16 coefficients.
"""

from __future__ import annotations

from stereodem.sensor.models.orbital.linecam import PolynomialLineCamera

_ATT = ("omega_0", "omega_1", "phi_0", "phi_1", "kappa_0", "kappa_1")


class KratkyModel(PolynomialLineCamera):
    """Kratky's model; build it with :meth:`from_model`."""

    ADJUSTABLE = (
        ("X_0", "X_1", "X_2", "Y_0", "Y_1", "Y_2", "Z_0", "Z_1", "Z_2") + _ATT + ("scan_scale",)
    )
    ADJUST_SETS = {"kratky": list(_ATT + ("scan_scale",)), "kratky-full": list(ADJUSTABLE)}
    MODEL_TYPE = "kratky"

    @staticmethod
    def _shape_initial(coef):
        coef = dict(coef)
        coef.update(omega_2=0.0, phi_2=0.0, kappa_2=0.0)
        return coef
