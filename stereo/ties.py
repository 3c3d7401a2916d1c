"""Tie points across N images, for the bundle adjustment before an N-view DEM.

Pairwise matches alone cannot tell whether three images agree: two rays always meet across
the epipolar direction once the pair's pointing is corrected, and along it any disagreement is
a height offset. A point seen in three images can: its three rays meet in one point only if
the models agree. :func:`multiview_ties` makes such points: the sparse matches of a pair
(:func:`stereodem.stereo.sparse.sparse_matches`, SIFT checked through the models) are
intersected, projected into every other image, and found there by correlation with the pair's
first image (:func:`stereodem.stereo.sparse.refine_matches`, within ``search`` px of the
prediction), giving tracks of up to N observations
(:class:`stereodem.sensor.estimation.adjust.bundle_multi.TieTracks`).
"""

from __future__ import annotations

import logging

import numpy as np

from stereodem.core.errors import InputError, StereodemError
from stereodem.sensor.estimation.adjust.bundle_multi import TieTracks, bundle_adjust_images
from stereodem.sensor.estimation.adjust.model_sets import image_corrected
from stereodem.sensor.geo.intersect import intersect_matches
from stereodem.sensor.models.base import pair_height_bounds

from .sparse import (
    SparseMatchError,
    distance_to_curves,
    epipolar_curves,
    refine_matches,
    sparse_matches,
)

log = logging.getLogger(__name__)

__all__ = ["multiview_ties", "agree_models", "check_match_geometry"]


def multiview_ties(
    images, models, pairs, *, search: int = 4, min_score: float = 0.7, height_range=None
) -> TieTracks:
    """Tie tracks over ``images`` from the sparse matches of each pair ``(i, j)`` of ``pairs``
    transferred into every other image (see the module docstring). A pair without sparse
    matches is skipped (logged). ``search`` (px) bounds the models' disagreement the transfer
    tolerates; ``min_score`` is the ZNCC a transferred point needs."""
    point, image, col, row = [], [], [], []
    base = 0
    for i, j in pairs:
        try:
            m = sparse_matches(images[i], images[j], models[i], models[j], height_range)
        except SparseMatchError as exc:
            log.warning("tie points of images %d/%d: %s", i, j, exc)
            continue
        n = len(m)
        x1 = np.column_stack([m.col1, m.row1])
        inter = intersect_matches(models[i], models[j], m.col1, m.row1, m.col2, m.row2)
        obs = {i: x1, j: np.column_stack([m.col2, m.row2])}
        for k in range(len(images)):
            if k in (i, j):
                continue
            with np.errstate(invalid="ignore"):
                c, r = models[k].project(inter.lon, inter.lat, inter.h)
            pred = np.column_stack([c, r])
            ok = np.all(np.isfinite(pred), axis=1)
            got = np.full((n, 2), np.nan)
            if ok.any():
                _, y2, _, keep = refine_matches(
                    images[i], images[k], x1[ok], pred[ok], search=search, min_score=min_score
                )
                got[np.flatnonzero(ok)[keep]] = y2
            obs[k] = got
        for k, xy in obs.items():
            found = np.all(np.isfinite(xy), axis=1)
            point.append(base + np.flatnonzero(found))
            image.append(np.full(int(found.sum()), k))
            col.append(xy[found, 0])
            row.append(xy[found, 1])
        base += n
        log.info(
            "tie points of images %d/%d: %d matches, %s transferred",
            i,
            j,
            n,
            {k: int(np.isfinite(v[:, 0]).sum()) for k, v in obs.items() if k not in (i, j)},
        )
    if not point:
        return TieTracks(np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0))
    p = np.concatenate(point)
    _, p = np.unique(p, return_inverse=True)
    return TieTracks(p.ravel(), np.concatenate(image), np.concatenate(col), np.concatenate(row))


def _across_epipolar_parameter(left, right, height_range) -> str:
    """The shift of ``right`` across its epipolar lines with ``left`` (``col_shift`` when the
    lines run along the rows, as for along-track stereo, else ``row_shift``)."""
    c, r = (left.width - 1) / 2, (left.height - 1) / 2
    curve = epipolar_curves(left, right, [c], [r], list(height_range))[0]
    d = curve[1] - curve[0]
    return "col_shift" if abs(d[1]) >= abs(d[0]) else "row_shift"


def agree_models(
    images,
    models,
    pairs,
    *,
    height_range=None,
    min_gain: float = 0.1,
    sigma_tie_px: float = 0.3,
    force: bool = False,
) -> tuple:
    """Bring the models of N images into agreement before their pair DEMs are fused.

    Tie tracks (:func:`multiview_ties`, from the first pair of ``pairs``, the best) are
    adjusted (:func:`~stereodem.sensor.estimation.adjust.bundle_multi.bundle_adjust_images`,
    image-space shifts). Datum: the best pair — its first image held fixed, its second free
    only across its epipolar lines (the shift along them is a height offset of the whole
    scene, not observable without GCPs); every other image free (``rpc-shift``). The adjusted
    models replace the given ones when they reduce the tracks' reprojection RMS by at least
    ``min_gain`` (a fraction: the models disagreed beyond the matching noise), or always with
    ``force``. Returns ``(models, report)``: the report holds the tracks, the reprojection RMS
    and the rays' distances from their points (``point_ray_gaps_*``, m: what a disagreement
    along the epipolar lines shows in) before and after, the per-pair ray gaps (which see only
    the part across them), the shifts and whether they were applied.
    """
    i, j = pairs[0]
    report = dict(datum=f"image {i} fixed, image {j} free across its epipolar lines only")
    tracks = multiview_ties(images, models, pairs[:1], height_range=height_range)
    counts = np.bincount(tracks.point) if len(tracks) else np.zeros(0, int)
    report.update(
        tie_points=int(tracks.n_points),
        observations=int(len(tracks)),
        points_by_images_seen={int(k): int(v) for k, v in enumerate(np.bincount(counts)) if v},
    )
    if not (counts >= 3).any():
        report.update(applied=False, reason="no tie point seen in three images")
        return models, report
    wrapped = [image_corrected(m) for m in models]
    names = ["rpc-shift"] * len(models)
    names[i] = None
    span = height_range or pair_height_bounds(models[i], models[j])
    names[j] = [_across_epipolar_parameter(models[i], models[j], span)]
    try:
        before = bundle_adjust_images(
            wrapped, tracks, names=None, fixed=list(range(len(models))), sigma_tie_px=sigma_tie_px
        )
        res = bundle_adjust_images(
            wrapped, tracks, names=names, fixed=[i], sigma_tie_px=sigma_tie_px
        )
    except StereodemError as exc:
        report.update(applied=False, reason=f"adjustment failed: {exc}")
        return models, report
    gain = 1.0 - res.tie_rmse_px / before.tie_rmse_px
    applied = bool(force or gain >= min_gain)
    report.update(
        applied=applied,
        reason=(
            ("forced" if force else f"reprojection RMS down {100 * gain:.0f} %")
            if applied
            else f"reprojection RMS down only {100 * gain:.0f} % "
            f"(< {100 * min_gain:.0f} %): the models agree"
        ),
        reprojection_rms_px_before=round(before.tie_rmse_px, 4),
        reprojection_rms_px_after=round(res.tie_rmse_px, 4),
        reprojection_rms_px_per_image_before=[round(v, 4) for v in before.image_rmse_px()],
        reprojection_rms_px_per_image_after=[round(v, 4) for v in res.image_rmse_px()],
        parameters={
            n: [round(float(v), 4), round(float(s), 4)]
            for n, v, s in zip(res.names, res.values, res.std)
        },
        rejected_points=int(res.tie_rejected.sum()),
        point_ray_gaps_before=before.point_ray_gaps(),
        point_ray_gaps_after=res.point_ray_gaps(),
        ray_gaps_before={f"{a}-{b}": v for (a, b), v in res.ray_gaps_before.items()},
        ray_gaps_after={f"{a}-{b}": v for (a, b), v in res.ray_gaps_after.items()},
    )
    return (res.models if applied else models), report


def check_match_geometry(
    match,
    left_model,
    right_model,
    height_range,
    *,
    names=("left", "right"),
    max_cross_px: float = 50.0,
) -> float:
    """Refuse (:class:`~stereodem.core.errors.InputError`, one line) matches of an ASP match
    file (:class:`stereodem.sensor.io.asp_match.MatchFile`) that do not belong to the two
    models' images: the median distance (px) of the right points across the epipolar curves
    of the left points (heights ``height_range``, m) must stay below ``max_cross_px`` (a
    pointing bias of a few pixels passes; other images do not). Returns that median."""
    path = match.path or "match file"
    heights = np.linspace(float(height_range[0]), float(height_range[1]), 5)
    curves = epipolar_curves(left_model, right_model, match.left.x, match.left.y, heights)
    cross, _, _, _, _ = distance_to_curves(
        np.column_stack([match.right.x, match.right.y]), curves, heights, extend=1e6
    )
    med = float(np.nanmedian(np.abs(cross))) if np.isfinite(cross).any() else float("inf")
    if not med <= max_cross_px:
        raise InputError(
            f"{path}: its points lie {med:.0f} px (median) across the epipolar "
            f"curves of {names[0]} / {names[1]}: the match file of other images"
        )
    return med
