"""The 15 generic GCP-fitted models (:mod:`stereodem.sensor.models.generic`) through the same
statistics as the physical models.

:func:`adjust_generic` fits the model with :func:`~stereodem.sensor.models.generic.fit_model`
(its own linear / algebraic start and, for the rational functions, Tikhonov regularisation),
then hands the fitted model — whose coefficients are adjustable parameters
(``GenericModel.parameters()``) — to :func:`~.single.adjust_model` with every coefficient free:
the iterated least squares on the image residuals converges at once for the polynomials (they
are linear) and refines the projective/DLT forms, and the result carries sigma0, the
covariance, redundancy numbers, data snooping and check-point RMSE. The rational functions are
regularised about the fitted coefficients (Tikhonov, weight from the L-curve) because their
normal matrices are near-singular (Ok 2005, §6.2); for the 2nd and 3rd order ones (38 and 78
coefficients) the statistics are those of the regularised fit itself, without re-estimation
or snooping.
"""

from __future__ import annotations

from stereodem.core.errors import InputError
from stereodem.sensor.estimation.adjust.single import adjust_model
from stereodem.sensor.io.gcps import ControlPoints
from stereodem.sensor.models.generic import MODEL_NAMES, _form, fit_model

__all__ = ["adjust_generic"]


def adjust_generic(
    name: str, points: ControlPoints, *, image_size=None, crs=None, regularization="auto", **kwargs
):
    """Fit generic model ``name`` to the GCPs of ``points`` and adjust it with statistics.

    Parameters
    ----------
    name : str
        One of :data:`stereodem.sensor.models.generic.MODEL_NAMES`.
    points : ControlPoints
        GCPs (role ``gcp``) and check points (role ``check``).
    image_size : (width, height), optional
        Image size (default: the extent of the points).
    regularization : "auto", None, "lcurve", "gcv" or float
        ``"auto"``: the L-curve for the rational functions, none for the others; otherwise
        the Tikhonov weight (or its rule) of both the initial fit and the adjustment, refused
        (:class:`InputError`) for the models that are linear in their coefficients.
    **kwargs
        Passed to :func:`adjust_model` (``sigma_px``, ``snooping``, ``alpha`` ...).

    Returns
    -------
    AdjustmentResult
        ``model_set`` is ``name``; parameters ``c00, c01, ...`` (normalised, unit 1).
    """
    if name not in MODEL_NAMES:
        raise InputError(f"unknown generic model '{name}' (known: {', '.join(MODEL_NAMES)})")
    gcp = points.select("gcp")
    if image_size is None:
        image_size = (int(max(points.col.max(), 0)) + 1, int(max(points.row.max(), 0)) + 1)
    if regularization == "auto":
        model, _ = fit_model(name, *gcp.arrays(), crs=crs, image_size=image_size)
        regularization = "lcurve" if name.startswith("rational") else None
    else:  # the caller's choice, for the initial fit and the adjustment alike
        if regularization is not None and not _form(name).regularizable:
            # Tikhonov about the initial fit cannot move a least-squares fit of a model linear
            # in its coefficients: accepting the weight would change nothing but the report
            regularizable = ", ".join(n for n in MODEL_NAMES if _form(n).regularizable)
            raise InputError(
                f"generic model '{name}' is fitted exactly by linear least squares; "
                f"regularisation applies to {regularizable} (and to parameter sets "
                "of physical/RPC models)"
            )
        model, _ = fit_model(
            name, *gcp.arrays(), crs=crs, image_size=image_size, regularization=regularization
        )
    if name in ("rational-2", "rational-3"):
        # 38/78 coefficients, condition numbers 1e11-1e14: statistics of the regularised fit
        # itself (no re-estimation, hence no snooping, which would need a re-fit)
        kwargs.update(max_iterations=0, snooping=False)
    res = adjust_model(
        model,
        points,
        list(model.parameters()),
        regularization=regularization,
        check_inputs=False,
        what=f"generic model '{name}'",
        **kwargs,
    )
    res.model_set = name
    for k in range(len(res.units)):
        res.units[k] = "1"
    return res
