"""Sparse matches between two images, checked through their sensor models.

SIFT keypoints (OpenCV, Lowe 2004) are detected in both images, matched by nearest
descriptor with Lowe's ratio test, and then checked geometrically through the two sensor
models: each left keypoint, localised at heights spanning the search range and projected by
the right model, traces its *epipolar curve* in the right image; a match is kept when its right
point lies on that curve up to one **relative image offset** common to all matches (the
pointing error of the pair, tens of pixels for raw RPCs) and a tolerance. No epipolar
constraint is imposed before that offset is known: the offset's component across the epipolar
curves is found as the consensus (a one-parameter RANSAC over all candidates) of the signed
distances of the right points to their curves, and only then are outliers rejected. Along the
curves an offset cannot be told from a height change; the check only bounds it
(``max_offset``).

This is the sparse stage of CARS and s2p (SIFT, ratio test, then a check through the
geometry), used here for the terrain height range (:mod:`stereodem.stereo.terrain`) and the
relative pointing correction (:mod:`stereodem.stereo.pointing`).

Keypoints are detected and matched on images reduced to at most ``max_size`` (512) pixels a side
(the cost of SIFT, about 0.5 s of CPU per megapixel, stays bounded for any scene size), then
each match is refined at full resolution by a vectorised ZNCC of 15 x 15 patches with a
parabolic sub-pixel peak (:func:`refine_matches`), so the matches keep full-resolution
precision.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import cv2
import numpy as np

from stereodem.core.blocks import each_band
from stereodem.core.errors import StereodemError
from stereodem.core.stretch import linear_to_uint8
from stereodem.sensor.models.base import pair_height_bounds

log = logging.getLogger(__name__)

__all__ = [
    "SparseMatches",
    "SparseMatchError",
    "sparse_matches",
    "epipolar_curves",
    "distance_to_curves",
    "refine_matches",
    "to_uint8",
    "zncc_scores",
]


class SparseMatchError(StereodemError):
    """Too few sparse matches for what was asked (height range, pointing correction)."""


@dataclass
class SparseMatches:
    """Sparse matches of a pair (pixel centres at integers, top-left pixel at (0, 0)).

    Attributes
    ----------
    col1, row1 : ndarray (N,)
        Left image positions, pixels.
    col2, row2 : ndarray (N,)
        Right image positions, pixels.
    score : ndarray (N,)
        ``1 - d1/d2`` of Lowe's ratio test (0..1, higher is more distinctive).
    cross : ndarray (N,)
        Signed distance (px) of each right point to its epipolar curve *before* any pointing
        correction, across the curve (positive to the left of the curve's direction of
        increasing height).
    height : ndarray (N,)
        Height (m) of the nearest point of the curve: a first height estimate per match.
    normal : ndarray (N, 2)
        Unit normal of the epipolar curve at that point, right image (col, row).
    direction : ndarray (N, 2)
        Unit direction of the curve (towards increasing height), right image (col, row).
    height_range : (float, float)
        Heights (m) spanned by the curves.
    offset_cross : float
        Consensus offset across the epipolar curves (px) found by the check.
    info : dict
        Counts and timings: keypoints, candidates after the ratio test, inliers, scale,
        seconds per stage.
    """

    col1: np.ndarray
    row1: np.ndarray
    col2: np.ndarray
    row2: np.ndarray
    score: np.ndarray
    cross: np.ndarray
    height: np.ndarray
    normal: np.ndarray
    direction: np.ndarray
    height_range: tuple
    offset_cross: float
    info: dict = field(default_factory=dict)

    def __len__(self):
        return len(self.col1)

    def subset(self, keep) -> SparseMatches:
        """The matches selected by a boolean mask or index array."""
        keep = np.asarray(keep)
        arrays = {
            k: getattr(self, k)[keep]
            for k in (
                "col1",
                "row1",
                "col2",
                "row2",
                "score",
                "cross",
                "height",
                "normal",
                "direction",
            )
        }
        return SparseMatches(
            **arrays,
            height_range=self.height_range,
            offset_cross=self.offset_cross,
            info=dict(self.info),
        )


# ----------------------------------------------------------------------------- images


def to_uint8(image, *, percentiles=(1.0, 99.0)):
    """8-bit version of an image of any dtype (percentile stretch; NaN/inf -> 0) and its mask
    of valid pixels."""
    a = np.asarray(image)
    if a.ndim == 3:  # band-last or band-first colour: mean of the bands
        a = a.mean(axis=-1 if a.shape[-1] <= 4 else 0)
    if a.ndim != 2:
        raise StereodemError(f"sparse matching: expected a 2-D image, got shape {a.shape}")
    a = a.astype(np.float32, copy=False)
    valid = np.isfinite(a)
    all_valid = bool(valid.all())
    v = a.ravel() if all_valid else a[valid]
    if v.size == 0:
        return np.zeros(a.shape, np.uint8), valid
    if v.size > 400_000:
        v = v[:: v.size // 400_000]
    lo, hi = np.percentile(v, percentiles)
    scale = 255.0 / max(float(hi - lo), 1e-12)
    # (a - lo) * scale + 0.5 clipped to 0..255, in float64 (by bands of rows); voids -> 0
    out = linear_to_uint8(a, lo, scale)
    if not all_valid:
        out[~valid] = 0
    return out, valid


def _sift(image8, mask, n_features, scale):
    """Keypoints (N, 2) in full-resolution pixels and descriptors (N, 128) float32."""
    if scale != 1.0:
        size = (max(1, round(image8.shape[1] * scale)), max(1, round(image8.shape[0] * scale)))
        image8 = cv2.resize(image8, size, interpolation=cv2.INTER_AREA)
        mask = cv2.resize(mask.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST)
    else:
        mask = mask.astype(np.uint8)
    mask = cv2.erode(mask, np.ones((5, 5), np.uint8))  # no keypoints on void edges
    sift = cv2.SIFT_create(nfeatures=int(n_features))
    kp, desc = sift.detectAndCompute(image8, mask * 255)
    if desc is None or not kp:
        return np.zeros((0, 2)), np.zeros((0, 128), np.float32)
    xy = np.array([k.pt for k in kp], dtype=np.float64)
    # OpenCV keypoints: pixel centres at integers, same as ours; rescale about the corner
    xy = (xy + 0.5) / scale - 0.5
    return xy, desc


def _keypoints_both(left_image, right_image, n_features, max_size, threads=None):
    """``((x1, d1), (x2, d2), scale)``: :func:`_sift` keypoints of both images at the common
    detection scale (larger side of the larger image reduced to ``max_size`` px).

    With a thread budget of 2 or more (``threads``, default ``cv2.getNumThreads()``) the two
    images are stretched and detected on two threads (numpy and OpenCV release the GIL);
    SIFT draws no random numbers, so the keypoints are those of the serial calls.
    """
    threads = int(cv2.getNumThreads()) if threads is None else int(threads)
    if threads < 2:
        (L8, Lv), (R8, Rv) = to_uint8(left_image), to_uint8(right_image)
        scale = min(1.0, max_size / max(L8.shape + R8.shape))
        return _sift(L8, Lv, n_features, scale), _sift(R8, Rv, n_features, scale), scale

    with ThreadPoolExecutor(2, thread_name_prefix="stereodem-sift") as ex:
        stretched = list(ex.map(to_uint8, (left_image, right_image)))  # 2-D uint8 + mask
        scale = min(1.0, max_size / max(stretched[0][0].shape + stretched[1][0].shape))
        fl, fr = ex.map(lambda av: _sift(av[0], av[1], n_features, scale), stretched)
    return fl, fr, scale


def _ratio_matches(d1, d2, ratio):
    """Nearest right descriptor for each left one, kept when d1 < ratio * d2 (Lowe's test)."""
    if len(d1) < 2 or len(d2) < 2:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    # approximate nearest neighbours (randomised k-d trees, as in Lowe 2004): the exact
    # brute-force search costs ~5 s for 20 000 x 20 000 descriptors, FLANN ~10x less
    # the randomised trees draw from OpenCV's global RNG: seed it so that a run is repeatable
    # (same matches, same pointing correction, same DEM whatever the worker count or resume)
    cv2.setRNGSeed(0)
    matcher = cv2.FlannBasedMatcher(dict(algorithm=1, trees=4), dict(checks=64))
    knn = matcher.knnMatch(
        np.ascontiguousarray(d1, np.float32), np.ascontiguousarray(d2, np.float32), k=2
    )
    pairs = np.array(
        [(m[0].queryIdx, m[0].trainIdx, m[0].distance, m[1].distance) for m in knn if len(m) == 2],
        dtype=np.float64,
    ).reshape(-1, 4)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(pairs[:, 3] > 0, pairs[:, 2] / pairs[:, 3], 1.0)
    keep = r < ratio
    i, j = pairs[keep, 0].astype(int), pairs[keep, 1].astype(int)
    # one-to-one: a right keypoint claimed by several left ones keeps none of them
    uniq, counts = np.unique(j, return_counts=True)
    single = np.isin(j, uniq[counts == 1])
    return i[single], j[single], 1.0 - r[keep][single]


def refine_matches(left, right, x1, x2, *, half: int = 7, search: int = 2, min_score: float = 0.6):
    """Refine matches at full resolution by ZNCC of small patches (vectorised over matches).

    The left point moves to its nearest pixel centre; a ``(2 half + 1)`` square patch around
    it is correlated with the right image at integer shifts of up to ``search`` px around the
    right point's nearest pixel, and the peak is located to sub-pixel precision by a parabola
    through its neighbours along each axis.

    Parameters
    ----------
    left, right : ndarray (rows, cols)
        Full-resolution images, any numeric dtype (NaN = void).
    x1, x2 : ndarray (N, 2)
        Matched (col, row) positions.

    Returns
    -------
    x1, x2 : ndarray (M, 2)
        Refined positions of the matches kept.
    score : ndarray (M,)
        Peak ZNCC.
    keep : ndarray (N,) bool
        Which input matches were kept (inside both images, peak not on the search border,
        score >= ``min_score``).
    """
    p1 = np.rint(x1).astype(np.int64)
    p2 = np.rint(x2).astype(np.int64)
    r = half + search
    inside = (
        (p1[:, 0] >= half)
        & (p1[:, 1] >= half)
        & (p1[:, 0] < left.shape[1] - half)
        & (p1[:, 1] < left.shape[0] - half)
        & (p2[:, 0] >= r)
        & (p2[:, 1] >= r)
        & (p2[:, 0] < right.shape[1] - r)
        & (p2[:, 1] < right.shape[0] - r)
    )
    idx = np.nonzero(inside)[0]
    if idx.size == 0:
        return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), inside
    oy, ox = np.mgrid[-half : half + 1, -half : half + 1]
    sy, sx = np.mgrid[-r : r + 1, -r : r + 1]

    def scores_of(band):  # the scores of matches idx[a:b]: each match's alone, so any split
        sel = idx[band[0] : band[1]]  # into bands on threads gives the same numbers
        T = left[p1[sel, 1, None, None] + oy, p1[sel, 0, None, None] + ox].astype(np.float64)
        S = right[p2[sel, 1, None, None] + sy, p2[sel, 0, None, None] + sx].astype(np.float64)
        return zncc_scores(T, S)

    scores = np.concatenate(each_band(scores_of, idx.size, min_rows=64))
    k = 2 * search + 1
    scores = np.where(np.isfinite(scores), scores, -np.inf)
    flat = scores.reshape(idx.size, -1).argmax(1)
    by, bx = np.divmod(flat, k)
    best = scores.reshape(idx.size, -1)[np.arange(idx.size), flat]
    interior = (by > 0) & (by < k - 1) & (bx > 0) & (bx < k - 1) & (best >= min_score)
    n = np.arange(idx.size)
    byc, bxc = np.clip(by, 1, k - 2), np.clip(bx, 1, k - 2)

    def vertex(a, b, c):
        with np.errstate(invalid="ignore", divide="ignore"):  # -inf scores next to void pixels
            den = a - 2 * b + c
            return np.where(den < 0, 0.5 * (a - c) / den, 0.0)

    fx = vertex(scores[n, byc, bxc - 1], scores[n, byc, bxc], scores[n, byc, bxc + 1])
    fy = vertex(scores[n, byc - 1, bxc], scores[n, byc, bxc], scores[n, byc + 1, bxc])
    ok = interior & np.isfinite(fx) & np.isfinite(fy)
    keep = np.zeros(len(x1), bool)
    keep[idx[ok]] = True
    y1 = p1[idx[ok]].astype(np.float64)
    y2 = np.stack(
        [p2[idx[ok], 0] + bx[ok] - search + fx[ok], p2[idx[ok], 1] + by[ok] - search + fy[ok]], -1
    )
    return y1, y2, best[ok], keep


def zncc_scores(T, S):
    """ZNCC of templates ``T`` (N, w, w) at every integer shift inside search windows ``S``
    (N, w + 2 s, w + 2 s): shape (N, 2 s + 1, 2 s + 1), NaN where a window or the template
    holds NaN (void) or is flat.

    Vectorised over the matches: the cross terms are one batched FFT correlation
    (``numpy.fft.rfft2`` over the patch axes; the circular correlation equals the linear one
    at the shifts kept), the windows' means and energies box sums of cumulative sums, so the
    cost does not grow with the number of shifts.
    """
    n, w = T.shape[0], T.shape[1]
    k = S.shape[1] - w + 1
    t_void = ~np.isfinite(T).all(axis=(1, 2))
    T = np.where(np.isfinite(T), T, 0.0)
    T = T - T.mean(axis=(1, 2), keepdims=True)
    tn = np.sqrt(np.einsum("nij,nij->n", T, T))
    void = ~np.isfinite(S)
    S = np.where(void, 0.0, S)
    S = S - S.mean(axis=(1, 2), keepdims=True)  # better conditioned energies

    def box(a):  # sums over every w x w window
        c = np.zeros((a.shape[0], a.shape[1] + 1, a.shape[2] + 1))
        c[:, 1:, 1:] = a.cumsum(1).cumsum(2)
        return c[:, w:, w:] - c[:, :-w, w:] - c[:, w:, :-w] + c[:, :-w, :-w]

    # T has zero mean, so sum(T * (P - mean P)) = sum(T * P): a plain correlation
    shape = S.shape[1:]
    cross = np.fft.irfft2(np.fft.rfft2(S) * np.conj(np.fft.rfft2(T, s=shape)), s=shape)[:, :k, :k]
    total, energy = box(S), box(S * S)
    var = np.maximum(energy - total * total / (w * w), 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        scores = cross / (tn[:, None, None] * np.sqrt(var))
    bad = (box(void.astype(np.float64)) > 0.5) | t_void[:, None, None]
    scores[bad] = np.nan
    return scores.reshape(n, k, k)


# ----------------------------------------------------------------------------- geometry


def epipolar_curves(left, right, col1, row1, heights):
    """Right-image epipolar curves of left pixels: shape (N, K, 2) for K heights (col, row).

    Each left pixel is localised by the left model at each height and projected by the right
    model. NaN where a model fails.
    """
    col1 = np.asarray(col1, float).ravel()
    row1 = np.asarray(row1, float).ravel()
    heights = np.asarray(heights, float)
    cc = np.repeat(col1[:, None], heights.size, 1).ravel()
    rr = np.repeat(row1[:, None], heights.size, 1).ravel()
    hh = np.tile(heights, col1.size)
    with np.errstate(all="ignore"):
        lon, lat = left.localize(cc, rr, hh)
        c2, r2 = right.project(lon, lat, hh)
    return np.stack([np.asarray(c2, float), np.asarray(r2, float)], -1).reshape(
        col1.size, heights.size, 2
    )


def distance_to_curves(points, curves, heights, *, extend: float = 0.0):
    """Nearest point of each polyline curve to a point.

    Parameters
    ----------
    points : ndarray (N, 2)
        Right-image points.
    curves : ndarray (N, K, 2)
        Polylines from :func:`epipolar_curves` (K >= 2, heights increasing).
    heights : ndarray (K,)
        Heights of the polyline vertices, metres.
    extend : float
        Pixels by which the first and last segments are prolonged beyond the ends.

    Returns
    -------
    cross : ndarray (N,)
        Signed distance across the curve (px), positive to the left of its direction.
    along : ndarray (N,)
        Distance beyond the curve's ends along it (px, 0 inside).
    height : ndarray (N,)
        Height (m) interpolated at the nearest point (extrapolated on the prolongations).
    normal, direction : ndarray (N, 2)
        Unit normal and direction of the nearest segment.
    """
    p = np.asarray(points, float)[:, None, :]
    a, b = curves[:, :-1, :], curves[:, 1:, :]
    seg = b - a
    length = np.linalg.norm(seg, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = seg / length[..., None]
        t = np.sum((p - a) * u, -1)
    k = seg.shape[1]
    lo = np.zeros_like(t)
    hi = length.copy()
    lo[:, 0] = -extend
    hi[:, k - 1] += extend
    tc = np.clip(t, lo, hi)
    foot = a + tc[..., None] * u
    dist = np.linalg.norm(p - foot, axis=-1)
    dist = np.where(np.isfinite(dist), dist, np.inf)
    best = np.argmin(dist, axis=1)
    n = np.arange(len(best))
    ub = u[n, best]
    normal = np.stack([ub[:, 1], -ub[:, 0]], -1)  # direction rotated by -90 degrees
    d = p[:, 0, :] - a[n, best]
    cross = np.sum(d * normal, -1)
    tb = t[n, best]
    beyond = np.maximum(np.maximum(lo[n, best] - tb, tb - hi[n, best]), 0.0)
    hs = np.asarray(heights, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = tb / length[n, best]
    height = hs[best] + frac * (hs[best + 1] - hs[best])
    bad = ~np.isfinite(dist[n, best])
    cross[bad] = np.nan
    return cross, beyond, height, normal, ub


def _consensus(values, tol):
    """Value with the most others within ``tol`` (1-D RANSAC over all candidates), refined by
    the median of its inliers; returns (value, inlier mask)."""
    v = np.asarray(values, float)
    ok = np.isfinite(v)
    s = np.sort(v[ok])
    if s.size == 0:
        return np.nan, np.zeros(v.shape, bool)
    count = np.searchsorted(s, s + tol, "right") - np.searchsorted(s, s - tol, "left")
    best = s[np.argmax(count)]
    with np.errstate(invalid="ignore"):
        inl = ok & (np.abs(v - best) <= tol)
    centre = float(np.median(v[inl]))
    with np.errstate(invalid="ignore"):
        inl = ok & (np.abs(v - centre) <= tol)
    return centre, inl


# ----------------------------------------------------------------------------- matching


def sparse_matches(
    left_image,
    right_image,
    left_model,
    right_model,
    height_range=None,
    *,
    ratio: float = 0.75,
    max_offset: float = 50.0,
    tolerance: float = 2.0,
    max_size: int = 512,
    n_features: int = 4000,
    n_heights: int = 5,
    refine: bool = True,
    left_window: tuple | None = None,
    threads: int | None = None,
) -> SparseMatches:
    """SIFT matches between two images, checked through their sensor models.

    Parameters
    ----------
    left_image, right_image : ndarray (rows, cols)
        Images of any numeric dtype (NaN = void).
    left_model, right_model : SensorModel
        Their sensor models (uncorrected: the check allows a relative offset).
    height_range : (float, float), optional
        Heights (m above the ellipsoid) the ground may take; default the models' common
        validity range.
    ratio : float
        Lowe's ratio-test threshold (nearest / second-nearest descriptor distance).
    max_offset : float
        Largest relative image offset (px) between the models that the check allows, across
        and along the epipolar curves.
    tolerance : float
        Largest distance (px, full resolution) of a right point from its epipolar curve once
        the consensus offset is removed (at least the detection scale's pixel when the
        matches are not refined).
    max_size : int
        Keypoints are detected and matched on images reduced so that their larger side is at
        most this (cost bounded for any scene size), then refined at full resolution.
    n_features : int
        Cap on SIFT keypoints per image.
    n_heights : int
        Vertices of each epipolar polyline.
    refine : bool
        Refine the matches at full resolution (:func:`refine_matches`); without it the
        positions keep the detection scale's precision.
    left_window : (col0, row0, col1, row1), optional
        Keep only left keypoints inside this box.
    threads : int, optional
        The two images are stretched and their keypoints detected concurrently when this is
        2 or more (default: the process's thread budget, ``cv2.getNumThreads()``); the
        matches do not depend on it.

    Returns
    -------
    SparseMatches
        Raises :class:`SparseMatchError` when no match survives.
    """
    t0 = time.perf_counter()
    times = {}
    if height_range is None:
        height_range = pair_height_bounds(left_model, right_model)
    hlo, hhi = (float(v) for v in height_range)
    if not (np.isfinite(hlo) and np.isfinite(hhi) and hhi > hlo):
        raise SparseMatchError(f"sparse matching: unusable height range {hlo:g}..{hhi:g} m")
    (x1, d1), (x2, d2), scale = _keypoints_both(
        left_image, right_image, n_features, max_size, threads
    )
    times["sift"] = time.perf_counter() - t0
    if left_window is not None:
        c0, r0, c1, r1 = left_window
        k = (x1[:, 0] >= c0) & (x1[:, 0] <= c1) & (x1[:, 1] >= r0) & (x1[:, 1] <= r1)
        x1, d1 = x1[k], d1[k]
    t1 = time.perf_counter()
    i, j, score = _ratio_matches(d1, d2, ratio)
    times["match"] = time.perf_counter() - t1
    info = dict(
        keypoints=[int(len(x1)), int(len(x2))],
        candidates=int(len(i)),
        scale=scale,
        ratio=ratio,
        max_offset_px=max_offset,
    )
    t2 = time.perf_counter()
    heights = np.linspace(hlo, hhi, max(2, int(n_heights)))
    p1, p2 = x1[i], x2[j]
    tol = float(tolerance)
    if refine:
        t3 = time.perf_counter()
        # patches are gathered from the images as they are (no full-size float copy)
        p1, p2, _, kept = refine_matches(
            np.asarray(left_image),
            np.asarray(right_image),
            p1,
            p2,
            search=max(2, int(np.ceil(1.5 / scale))),
        )
        score = score[kept]
        times["refine"] = time.perf_counter() - t3
    else:
        tol = max(tol, 1.0 / scale)
    t2 = time.perf_counter()
    curves = epipolar_curves(left_model, right_model, p1[:, 0], p1[:, 1], heights)
    cross, beyond, h, normal, direction = distance_to_curves(p2, curves, heights, extend=max_offset)
    with np.errstate(invalid="ignore"):
        plausible = np.isfinite(cross) & (np.abs(cross) <= max_offset) & (beyond <= 0)
    offset, inl = _consensus(np.where(plausible, cross, np.nan), tol)
    times["check"] = time.perf_counter() - t2
    times["total"] = time.perf_counter() - t0
    info.update(inliers=int(inl.sum()), seconds=times)
    if not inl.any():
        raise SparseMatchError(
            f"sparse matching: no match agrees with the sensor models "
            f"({len(x1)}/{len(x2)} keypoints, {len(i)} after the ratio test, "
            f"heights {hlo:.0f}..{hhi:.0f} m, offsets up to {max_offset:g} px)"
        )
    log.info(
        "sparse matches: %d/%d keypoints, %d after the ratio test, %d agree with the "
        "models (offset across the epipolar curves %.2f px, scale %.2f, %.1f s)",
        len(x1),
        len(x2),
        len(i),
        inl.sum(),
        offset,
        scale,
        times["total"],
    )
    k = np.nonzero(inl)[0]
    return SparseMatches(
        p1[k, 0],
        p1[k, 1],
        p2[k, 0],
        p2[k, 1],
        score[k],
        cross[k],
        h[k],
        normal[k],
        direction[k],
        (hlo, hhi),
        float(offset),
        info,
    )
