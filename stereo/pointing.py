"""Relative pointing correction of the right image from sparse matches.

Two sensor models delivered with a pair (raw RPCs above all) disagree by a few to tens of
pixels; the dense matcher, which searches along epipolar lines, then misses its matches. The
correction here is s2p's relative pointing correction (de Franchis et al. 2014, image-space
translation of the second image, Grodecki & Dial 2003) extended to an affine correction when
the matches support it, expressed as a
:class:`stereodem.sensor.models.corrected.ImageCorrectedModel` of the right model.

From two images alone only the component of the error **across** the epipolar curves is
observable: along them a shift is a height change. The estimate therefore moves the right
model across the mean epipolar direction only (a translation, or an affine field whose value
varies linearly over the image), unless a reference DEM is given: then each match's left
point is localised on the DEM and projected by the right model, and the full two-dimensional
offset (translation or affine) is estimated.

The affine field is kept when it explains the matches better than the translation by the
Bayesian information criterion (BIC); the residual across the epipolar curves is measured
through the models before and after the correction, and a warning is logged when its robust
spread (NMAD) stays above ``warn_px`` (0.5 px).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from stereodem.core.stats import nmad as _nmad
from stereodem.sensor.models.corrected import ImageCorrectedModel

from .sparse import SparseMatchError, SparseMatches, distance_to_curves, epipolar_curves

log = logging.getLogger(__name__)

__all__ = ["PointingCorrection", "relative_pointing", "cross_residuals"]


@dataclass
class PointingCorrection:
    """Result of :func:`relative_pointing`.

    Attributes
    ----------
    model : ImageCorrectedModel
        The corrected right model (the given right model wrapped).
    parameters : dict
        The correction's coefficients (:data:`stereodem.sensor.models.corrected.PARAMETERS`):
        pixels and pixels per pixel, added to the given right model's image coordinates.
    kind : {"translation", "affine"}
    along_observed : bool
        True when a reference DEM fixed the component along the epipolar curves.
    n_matches : int
        Matches used (inliers of the robust fit).
    before, after : dict
        Residual across the epipolar curves (px) through the models before and after the
        correction: ``median``, ``nmad``, ``rms``, ``p90_abs``.
    warning : str or None
        Set when the residual spread after the correction exceeds the threshold.
    """

    model: ImageCorrectedModel
    parameters: dict
    kind: str
    along_observed: bool
    n_matches: int
    before: dict
    after: dict
    warning: str | None = None
    info: dict = field(default_factory=dict)

    def summary(self) -> dict:
        """Plain-dict record for reports (JSON-serialisable)."""
        return dict(
            kind=self.kind,
            along_observed=self.along_observed,
            n_matches=self.n_matches,
            parameters={k: float(v) for k, v in self.parameters.items()},
            residual_before_px=self.before,
            residual_after_px=self.after,
            warning=self.warning,
            **self.info,
        )


def _stats(r):
    r = np.asarray(r, float)
    r = r[np.isfinite(r)]
    if r.size == 0:
        return dict(median=float("nan"), nmad=float("nan"), rms=float("nan"), p90_abs=float("nan"))
    return dict(
        median=float(np.median(r)),
        nmad=_nmad(r),
        rms=float(np.sqrt(np.mean(r * r))),
        p90_abs=float(np.percentile(np.abs(r), 90)),
    )


def cross_residuals(left, right, col1, row1, col2, row2, height_range, *, n_heights: int = 9):
    """Signed distance (px) of right points to the epipolar curves of their left points, with
    the given models (no offset allowed): the residual across the epipolar direction."""
    heights = np.linspace(height_range[0], height_range[1], n_heights)
    curves = epipolar_curves(left, right, col1, row1, heights)
    pts = np.stack([np.asarray(col2, float), np.asarray(row2, float)], -1)
    cross, _, _, _, _ = distance_to_curves(pts, curves, heights, extend=1e6)
    return cross


def _robust_lstsq(A, y, tol_floor, iterations=5):
    """Least squares with iterative rejection of residuals beyond max(3 NMAD, tol_floor)."""
    keep = np.isfinite(y) & np.all(np.isfinite(A), 1)
    x = None
    for _ in range(iterations):
        if keep.sum() < A.shape[1] + 2:
            break
        x, *_ = np.linalg.lstsq(A[keep], y[keep], rcond=None)
        res = y - A @ x
        lim = max(3.0 * _nmad(res[keep]), tol_floor)
        new = np.isfinite(res) & (np.abs(res) <= lim)
        if np.array_equal(new, keep):
            break
        keep = new
    if x is None:
        raise SparseMatchError(f"relative pointing: too few consistent matches ({int(keep.sum())})")
    return x, keep


def _bic_prefers_affine(res_t, res_a, n_extra):
    """BIC comparison of two nested least-squares fits on the same n points."""
    n = res_t.size
    rss_t, rss_a = float(np.sum(res_t**2)), float(np.sum(res_a**2))
    if rss_a <= 0 or rss_t <= 0:
        return False
    return n * np.log(rss_t / rss_a) > n_extra * np.log(n)


def relative_pointing(
    matches: SparseMatches,
    left,
    right,
    *,
    affine: str | bool = "auto",
    reference_dem=None,
    min_matches: int = 10,
    warn_px: float = 0.5,
    min_extent: float = 0.25,
) -> PointingCorrection:
    """Relative pointing correction of the right model from sparse matches.

    Parameters
    ----------
    matches : SparseMatches
        From :func:`stereodem.stereo.sparse.sparse_matches` with these ``left``/``right``.
    left, right : SensorModel
        The models the matches were checked with; ``right`` is the one corrected.
    affine : "auto", True or False
        Fit an affine field (True), a translation (False), or let the BIC decide ("auto");
        "auto" also requires the matches to span ``min_extent`` of the image in both
        directions.
    reference_dem : DEM, optional
        Fixes the component along the epipolar curves (see the module docstring).
    min_matches : int
        Fewer matches raise :class:`SparseMatchError`.
    warn_px : float
        Residual spread (NMAD, px) above which a warning is logged and recorded.

    Returns
    -------
    PointingCorrection
    """
    n = len(matches)
    if n < min_matches:
        raise SparseMatchError(
            f"relative pointing: only {n} sparse match(es) agree with the "
            f"models (need >= {min_matches})"
        )
    c2, r2 = matches.col2, matches.row2
    cm, rm = float(np.mean(c2)), float(np.mean(r2))
    sc = max(right.width, right.height) / 2.0  # conditioning of the affine terms
    u, v = (c2 - cm) / sc, (r2 - rm) / sc
    span_ok = (np.ptp(c2) >= min_extent * right.width) and (np.ptp(r2) >= min_extent * right.height)
    tol_floor = 0.3

    if reference_dem is None:
        nbar = np.mean(matches.normal, 0)
        nbar /= np.linalg.norm(nbar)
        y = matches.cross  # = n . (x2 - p), offset across the curves
        At = np.ones((n, 1))
        xt, keep_t = _robust_lstsq(At, y, tol_floor)
        Aa = np.stack([np.ones(n), u, v], -1)
        xa, keep_a = _robust_lstsq(Aa, y, tol_floor)
        both = keep_t & keep_a
        use_affine = (affine is True) or (
            affine == "auto"
            and span_ok
            and n >= 30
            and _bic_prefers_affine(y[both] - At[both] @ xt, y[both] - Aa[both] @ xa, 2)
        )
        t, a_u, a_v = xa if use_affine else np.array([xt[0], 0.0, 0.0])
        keep = keep_a if use_affine else keep_t
        # field across the curves: nbar * (t + a_u u + a_v v), back in pixel coordinates
        a_c, a_r = a_u / sc, a_v / sc
        s0 = t - a_c * cm - a_r * rm
        params = dict(
            col_shift=nbar[0] * s0,
            row_shift=nbar[1] * s0,
            col_drift_col=nbar[0] * a_c,
            col_drift_row=nbar[0] * a_r,
            row_drift_col=nbar[1] * a_c,
            row_drift_row=nbar[1] * a_r,
        )
        along = False
    else:
        loc = left.localize_dem(
            matches.col1, matches.row1, reference_dem, h0=float(np.median(matches.height))
        )
        with np.errstate(invalid="ignore"):
            pc, pr = right.project(loc.lon, loc.lat, loc.h)
        dc, dr = c2 - np.asarray(pc, float), r2 - np.asarray(pr, float)
        At = np.ones((n, 1))
        Aa = np.stack([np.ones(n), u, v], -1)
        fits = {}
        for name, A in (("translation", At), ("affine", Aa)):
            xc, kc = _robust_lstsq(A, dc, tol_floor)
            xr, kr = _robust_lstsq(A, dr, tol_floor)
            fits[name] = (xc, xr, kc & kr)
        both = fits["translation"][2] & fits["affine"][2]
        res = {
            k: np.concatenate(
                [
                    dc[both] - (At if k == "translation" else Aa)[both] @ f[0],
                    dr[both] - (At if k == "translation" else Aa)[both] @ f[1],
                ]
            )
            for k, f in fits.items()
        }
        use_affine = (affine is True) or (
            affine == "auto"
            and span_ok
            and n >= 30
            and _bic_prefers_affine(res["translation"], res["affine"], 4)
        )
        xc, xr, keep = fits["affine" if use_affine else "translation"]
        xc = np.resize(np.append(xc, [0.0, 0.0]), 3) if not use_affine else xc
        xr = np.resize(np.append(xr, [0.0, 0.0]), 3) if not use_affine else xr
        params = dict(
            col_shift=xc[0] - xc[1] * cm / sc - xc[2] * rm / sc,
            row_shift=xr[0] - xr[1] * cm / sc - xr[2] * rm / sc,
            col_drift_col=xc[1] / sc,
            col_drift_row=xc[2] / sc,
            row_drift_col=xr[1] / sc,
            row_drift_row=xr[2] / sc,
        )
        along = True
    if keep.sum() < min_matches:
        raise SparseMatchError(
            f"relative pointing: only {int(keep.sum())} match(es) agree on one "
            f"correction (need >= {min_matches})"
        )
    params = {k: float(v) for k, v in params.items()}
    corrected = ImageCorrectedModel(right, **params)
    sub = matches.subset(keep)
    before = cross_residuals(
        left, right, sub.col1, sub.row1, sub.col2, sub.row2, matches.height_range
    )
    after = cross_residuals(
        left, corrected, sub.col1, sub.row1, sub.col2, sub.row2, matches.height_range
    )
    sb, sa = _stats(before), _stats(after)
    kind = "affine" if use_affine else "translation"
    warning = None
    if not np.isfinite(sa["nmad"]) or sa["nmad"] > warn_px:
        warning = (
            f"relative pointing: the residual across the epipolar direction stays at "
            f"{sa['nmad']:.2f} px (NMAD) after the {kind} correction (> {warn_px:g} px); "
            f"the models may need a bundle adjustment"
        )
        log.warning(warning)
    log.info(
        "relative pointing (%s%s) of the right image: shift %.3f / %.3f px (col/row), "
        "%d matches; residual across the epipolar direction median %.3f -> %.3f px, "
        "NMAD %.3f -> %.3f px",
        kind,
        ", along fixed by the reference DEM" if along else "",
        params["col_shift"],
        params["row_shift"],
        int(keep.sum()),
        sb["median"],
        sa["median"],
        sb["nmad"],
        sa["nmad"],
    )
    return PointingCorrection(
        corrected,
        params,
        kind,
        along,
        int(keep.sum()),
        sb,
        sa,
        warning,
        dict(matches_span_ok=bool(span_ok)),
    )
