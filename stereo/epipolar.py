"""Epipolar resampling of a stereo pair, tile by tile, for any pair of sensor models.

Pushbroom and RPC images have no global epipolar geometry, but over a tile of a few hundred
pixels each camera is very nearly affine, so the affine fundamental matrix applies (de
Franchis et al., ICIP 2014; s2p ``rectification.py``). Per tile:

1. **Virtual correspondences** from the models alone: a grid of left pixels over the tile is
   localised at several heights spanning the tile's height range (``left.localize``) and
   projected into the right image (``right.project``).
2. **Fundamental matrix** of the tile: the affine one by the Gold Standard algorithm
   (Hartley & Zisserman alg. 14.1) for pushbroom/RPC pairs, or a general one (normalised
   8-point) for frame cameras, whose rectification is then projective.
3. **Rectifying maps**: s2p's similarities (rotation + common zoom + vertical shift, so that
   conjugate points share a row at the same row scale), then a horizontal shear/scale/shift of
   the right map (s2p ``register_with_shear``) so that the disparity is zero at the tile's mean
   height and small elsewhere.
4. **Quality and search range**: the residual vertical parallax of the virtual matches on a
   check grid distinct from the fitting grid (RMS and max, pixels) and the disparity range
   they span over the height range (plus a margin).

The rectified tile frame is chosen so that array index ``[v, u]`` of a rectified image is the
rectified coordinate ``(u, v)``; a left pixel ``(u, v)`` matches the right pixel
``(u - d, v)`` for a disparity ``d`` (the convention of
:func:`stereodem.stereo.match.match_rectified`). Triangulation never uses the approximation:
:meth:`EpipolarTile.to_image` maps matches back to each image's own coordinates, which are
intersected with the exact models.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import ndimage

from stereodem.core.errors import InputError, SensorModelError
from stereodem.sensor.models.frame import FrameCamera
from stereodem.stereo.tiling import Tile

log = logging.getLogger(__name__)

__all__ = [
    "EpipolarTile",
    "virtual_matches",
    "affine_fundamental_matrix",
    "rectifying_similarities",
    "rectify_tile",
    "apply_map",
    "vertical_offset_to_image_shift",
]


def virtual_matches(left, right, bounds, heights, *, n: int = 7, offset: float = 0.0):
    """Exact correspondences of the two models over an image rectangle and heights.

    Parameters
    ----------
    left, right : stereodem.sensor.models.base.SensorModel
    bounds : (col_min, row_min, col_max, row_max)
        Rectangle of the left image (pixels).
    heights : array_like
        Ellipsoidal heights (m) at which the grid is localised.
    n : int
        Grid points per axis of the rectangle.
    offset : float
        Shift of the grid nodes in units of the grid step (0.5 gives a grid staggered with
        respect to ``offset=0``, used to check a fit on points it did not see).

    Returns
    -------
    x1, x2 : ndarray (N, 2)
        Left and right ``(col, row)``; rows where the right projection failed are dropped.
    h : ndarray (N,)
        Height of each match (m).
    """
    c0, r0, c1, r1 = bounds
    t = (np.arange(n) + offset) / max(n - 1 + (offset > 0), 1)
    cols, rows, hs = np.meshgrid(
        c0 + t * (c1 - c0), r0 + t * (r1 - r0), np.asarray(heights, float), indexing="ij"
    )
    cols, rows, hs = cols.ravel(), rows.ravel(), hs.ravel()
    lon, lat = left.localize(cols, rows, hs)
    c2, r2 = right.project(lon, lat, hs)
    ok = np.isfinite(c2) & np.isfinite(r2) & np.isfinite(lon)
    return (np.column_stack([cols, rows])[ok], np.column_stack([c2, r2])[ok], hs[ok])


def affine_fundamental_matrix(x1, x2):
    """Affine fundamental matrix by the Gold Standard algorithm (H&Z alg. 14.1).

    ``[x2, y2, 1] F [x1, y1, 1]^T = 0`` for matches ``x1`` (left) and ``x2`` (right),
    arrays of shape (N, 2), N >= 4.
    """
    X = np.column_stack([x2, x1]).astype(float)
    mean = X.mean(axis=0)
    _, _, vt = np.linalg.svd(X - mean, full_matrices=False)
    N = vt[-1]
    return np.array([[0, 0, N[0]], [0, 0, N[1]], [N[2], N[3], -N @ mean]])


def rectifying_similarities(F):
    """s2p's rectifying similarities ``(S1, S2)`` (3x3) of an affine fundamental matrix.

    After them, conjugate points have equal rows: with ``F = [[0,0,a],[0,0,b],[c,d,e]]``,
    ``r = |(c,d)|``, ``s = |(a,b)|``, zoom ``z = sqrt(r/s)`` and ``t = e / (2 sqrt(rs))``,
    ``S1 = [z R1 | (0, t)]``, ``S2 = [R2 / z | (0, -t)]`` so that
    ``y1' - y2' = x2^T F x1 / sqrt(rs)``: both images get the same row scale.
    """
    a, b, c, d, e = F[0, 2], F[1, 2], F[2, 0], F[2, 1], F[2, 2]
    r, s = np.hypot(c, d), np.hypot(a, b)
    if r == 0 or s == 0:
        raise SensorModelError(
            "degenerate affine fundamental matrix (no stereo baseline in the tile)"
        )
    R1 = np.array([[d, -c], [c, d]]) / r
    R2 = np.array([[-b, a], [-a, -b]]) / s
    z = np.sqrt(r / s)
    t = 0.5 * e / np.sqrt(r * s)
    S1, S2 = np.eye(3), np.eye(3)
    S1[:2, :2], S1[1, 2] = z * R1, t
    S2[:2, :2], S2[1, 2] = R2 / z, -t
    return S1, S2


def _projective_rectification(x1, x2, size):
    """Rectifying homographies from a general fundamental matrix (frame cameras)."""
    F, _ = cv2.findFundamentalMat(x1.astype(np.float64), x2.astype(np.float64), cv2.FM_8POINT)
    if F is None or F.shape != (3, 3):
        raise SensorModelError("fundamental matrix estimation failed on the virtual matches")
    ok, H1, H2 = cv2.stereoRectifyUncalibrated(
        x1.astype(np.float64), x2.astype(np.float64), F, (int(size[0]), int(size[1]))
    )
    if not ok:
        raise SensorModelError("projective rectification failed on the virtual matches")
    return np.asarray(H1, float), np.asarray(H2, float)


def apply_map(H, x, y):
    """Apply a 3x3 map to points: returns ``(x', y')`` (affine or projective)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    w = H[2, 0] * x + H[2, 1] * y + H[2, 2]
    return ((H[0, 0] * x + H[0, 1] * y + H[0, 2]) / w, (H[1, 0] * x + H[1, 1] * y + H[1, 2]) / w)


def _translation(tx, ty):
    T = np.eye(3)
    T[0, 2], T[1, 2] = tx, ty
    return T


@dataclass
class EpipolarTile:
    """Rectifying maps of one tile, with their quality figures and disparity search range.

    Attributes
    ----------
    tile : Tile
        The left-image tile whose points this rectification produces.
    H_left, H_right : ndarray (3, 3)
        Maps from each image's ``(col, row)`` to rectified ``(u, v)``; rectified array index
        ``[v, u]`` equals the rectified coordinate.
    shape : (rows, cols)
        Size of both rectified images.
    disparity_range : (float, float)
        Search range ``(dmin, dmax)`` in pixels (left ``u`` minus right ``u``), margin included.
    height_range : (float, float)
        Ellipsoidal heights (m) the range covers (before the pixel margin).
    residual_rms, residual_max : float
        Vertical parallax of the virtual check matches after rectification, pixels.
    method : str
        ``"affine"`` or ``"projective"``.
    px_per_m : float
        Disparity change per metre of height at the tile centre (pixels/m; the B/H ratio
        divided by the GSD).
    """

    tile: Tile
    H_left: np.ndarray
    H_right: np.ndarray
    shape: tuple
    disparity_range: tuple
    height_range: tuple
    residual_rms: float
    residual_max: float
    method: str
    px_per_m: float
    info: dict = field(default_factory=dict)

    @property
    def is_affine(self):
        return bool(
            np.allclose(self.H_left[2], [0, 0, 1]) and np.allclose(self.H_right[2], [0, 0, 1])
        )

    def rectify(self, left_image, right_image, *, interpolation: int = 3):
        """Resample both images into the tile's epipolar frame.

        Only the part of each image the frame needs is read, so whole scenes (or memory
        maps) can be passed. ``interpolation`` is the spline order (3: cubic B-spline, 1:
        bilinear). Returns two float32 arrays of :attr:`shape`, NaN outside the images.
        """
        return (
            _warp(left_image, self.H_left, self.shape, interpolation),
            _warp(right_image, self.H_right, self.shape, interpolation),
        )

    def to_image(self, u, v, disparity):
        """Map rectified matches back to image coordinates.

        Parameters
        ----------
        u, v : array_like
            Rectified left coordinates (pixels).
        disparity : array_like
            Disparity (left ``u`` minus right ``u``).

        Returns
        -------
        (col1, row1), (col2, row2) : tuples of ndarrays
            Left and right image coordinates.
        """
        u, v, disparity = np.broadcast_arrays(
            np.asarray(u, float), np.asarray(v, float), np.asarray(disparity, float)
        )
        c1, r1 = apply_map(np.linalg.inv(self.H_left), u, v)
        c2, r2 = apply_map(np.linalg.inv(self.H_right), u - disparity, v)
        return (c1, r1), (c2, r2)

    def summary(self) -> dict:
        """Plain-dict QA figures of the tile (for logs and reports)."""
        return dict(
            tile=list(self.tile.bounds),
            method=self.method,
            shape=list(self.shape),
            disparity_range=[float(x) for x in self.disparity_range],
            height_range=[float(x) for x in self.height_range],
            residual_rms_px=float(self.residual_rms),
            residual_max_px=float(self.residual_max),
            px_per_m=float(self.px_per_m),
        )


def _warp(image, H, shape, interpolation):
    """Warp ``image`` with the map ``H`` (image -> frame) into an array of ``shape``, NaN outside.

    ``interpolation`` is the spline order of :func:`scipy.ndimage.map_coordinates` (3: cubic
    B-spline, which reproduces polynomials up to degree 3 exactly; OpenCV's bicubic kernel
    (a = -0.75) does not even reproduce a linear ramp, an error of up to 0.05 grey level per
    unit gradient that would bias sub-pixel matching). No-data (NaN) pixels of the source make
    the output pixels whose interpolation support touches them NaN.
    """
    rows, cols = int(shape[0]), int(shape[1])
    ih, iw = image.shape[:2]
    Hinv = np.linalg.inv(H)
    out = np.full((rows, cols), np.nan, np.float32)
    # the part of the source the frame needs (frame corners back to the image, + 4 px)
    fc = np.array([0, cols - 1, cols - 1, 0], float)
    fr = np.array([0, 0, rows - 1, rows - 1], float)
    sc, sr = apply_map(Hinv, fc, fr)
    c0 = int(np.clip(np.floor(sc.min()) - 4, 0, iw))
    c1 = int(np.clip(np.ceil(sc.max()) + 5, 0, iw))
    r0 = int(np.clip(np.floor(sr.min()) - 4, 0, ih))
    r1 = int(np.clip(np.ceil(sr.max()) + 5, 0, ih))
    if c1 - c0 < 4 or r1 - r0 < 4:
        return out
    src = np.asarray(image[r0:r1, c0:c1], dtype=np.float64)
    nodata = ~np.isfinite(src)
    if nodata.any():
        src = np.where(nodata, np.nanmean(src) if (~nodata).any() else 0.0, src)
    order = int(interpolation)
    if np.array_equal(H[2], [0.0, 0.0, 1.0]):  # affine (pushbroom tiles: similarities)
        res, c, r = _affine_warp(src, Hinv, (rows, cols), c0, r0, order)
    else:
        v, u = np.mgrid[0:rows, 0:cols].astype(np.float64)
        c, r = apply_map(Hinv, u, v)
        c -= c0
        r -= r0
        res = ndimage.map_coordinates(src, [r, c], order=order, mode="nearest", prefilter=order > 1)
    h, w = src.shape
    ok = (c >= -0.5) & (c <= w - 0.5) & (r >= -0.5) & (r <= h - 0.5)
    if r0 > 0:
        ok &= r >= 1.0  # inside the crop's margin, not at a cropped edge
    if c0 > 0:
        ok &= c >= 1.0
    if r1 < ih:
        ok &= r <= h - 2.0
    if c1 < iw:
        ok &= c <= w - 2.0
    if nodata.any():
        bad = ndimage.map_coordinates(nodata.astype(np.float32), [r, c], order=1, mode="nearest")
        ok &= bad == 0
    np.copyto(out, res, where=ok, casting="same_kind")
    return out


def _affine_warp(src, Hinv, shape, c0, r0, order):
    """The spline interpolation of :func:`_warp` for an affine map (``Hinv``: its inverse,
    frame -> image, last row 0, 0, 1):
    ``scipy.ndimage.affine_transform``, which computes each output pixel's source position
    itself (no coordinate arrays for it to read: about a fifth less time on a tile, less
    memory traffic), into float32 (the values rounded once, as before). Returns the warped
    crop and the source column and row of every output pixel (float64, broadcast from one
    row and one column: ``c = a u + b v + e``, the formula of :func:`apply_map` with its
    division by 1), relative to the crop at ``(c0, r0)``, for the validity tests."""
    rows, cols = shape
    a, t = Hinv[:2, :2], Hinv[:2, 2]  # source (col, row) = a @ (u, v) + t, as apply_map has it
    m = np.array([[a[1, 1], a[1, 0]], [a[0, 1], a[0, 0]]])  # (row, col) from (v, u)
    res = ndimage.affine_transform(
        src,
        m,
        offset=(t[1] - r0, t[0] - c0),
        output_shape=(rows, cols),
        output=np.float32,
        order=order,
        mode="nearest",
        prefilter=order > 1,
    )
    u = np.arange(cols, dtype=np.float64)
    v = np.arange(rows, dtype=np.float64)[:, None]
    c = (a[0, 0] * u + a[0, 1] * v + t[0]) - c0
    r = (a[1, 0] * u + a[1, 1] * v + t[1]) - r0
    return res, c, r


def rectify_tile(
    left,
    right,
    tile: Tile,
    height_range,
    *,
    halo=(32, 16),
    method="auto",
    disparity_margin: float = 4.0,
    n_fit: int = 9,
    n_check: int = 8,
    n_heights: int = 5,
    mean_height=None,
) -> EpipolarTile:
    """Compute the epipolar rectification of one left-image tile.

    Parameters
    ----------
    left, right : stereodem.sensor.models.base.SensorModel
        Exact models of the two images.
    tile : Tile
        Left-image tile (its points are the ones kept downstream).
    height_range : (float, float)
        Ellipsoidal heights (m) of the terrain in the tile (include any margin wanted).
    halo : (int, int)
        Extra columns and rows (pixels) rectified around the tile so that correlation
        windows at its border see image content.
    method : {"auto", "affine", "projective"}
        ``"auto"`` uses projective maps for frame cameras and affine maps otherwise.
    disparity_margin : float
        Pixels added on both sides of the model-derived disparity range.
    n_fit, n_check, n_heights : int
        Virtual-match grid sizes: ``n_fit`` x ``n_fit`` x ``n_heights`` fitting points and a
        staggered ``n_check`` x ``n_check`` x ``n_heights + 1`` check grid.
    mean_height : float, optional
        Height (m) at which the disparity is made zero (default: middle of the range).

    Returns
    -------
    EpipolarTile
    """
    hmin, hmax = float(height_range[0]), float(height_range[1])
    if not (np.isfinite(hmin) and np.isfinite(hmax)) or hmax < hmin:
        raise InputError(f"unusable height range {height_range!r}")
    if hmax - hmin < 1.0:  # need some depth for the fundamental matrix
        mid = 0.5 * (hmin + hmax)
        hmin, hmax = mid - 0.5, mid + 0.5
    h0 = 0.5 * (hmin + hmax) if mean_height is None else float(mean_height)
    hx, hy = halo
    c0, r0, c1, r1 = tile.bounds
    outer = (c0 - hx, r0 - hy, c1 + hx, r1 + hy)
    # fit on a height span of at least 200 m: a wider span conditions F better
    span = max(hmax - hmin, 200.0)
    fit_h = np.linspace(h0 - span / 2, h0 + span / 2, n_heights)
    fit_h = np.unique(np.concatenate([fit_h, np.linspace(hmin, hmax, n_heights)]))
    x1, x2, _ = virtual_matches(left, right, outer, fit_h, n=n_fit)
    if len(x1) < 8:
        raise SensorModelError(
            f"tile {tile.bounds}: too few virtual matches ({len(x1)}); "
            "is the tile outside the right image's model domain?"
        )
    if method == "auto":
        method = (
            "projective"
            if isinstance(left, FrameCamera) and isinstance(right, FrameCamera)
            else "affine"
        )
    if method == "affine":
        F = affine_fundamental_matrix(x1, x2)
        H1, H2 = rectifying_similarities(F)
    elif method == "projective":
        H1, H2 = _projective_rectification(x1, x2, (c1 + hx + 1, r1 + hy + 1))
    else:
        raise InputError(f"unknown rectification method {method!r}")
    # shear/scale/shift of the right map: zero disparity at h0 (s2p register_with_shear)
    m1, m2, _ = virtual_matches(left, right, outer, [h0], n=n_fit)
    u1, v1 = apply_map(H1, m1[:, 0], m1[:, 1])
    u2, v2 = apply_map(H2, m2[:, 0], m2[:, 1])
    A = np.column_stack([u2, v2, np.ones_like(u2)])
    abc, *_ = np.linalg.lstsq(A, u1, rcond=None)
    if abs(abc[0]) < 1e-3:
        raise SensorModelError(
            f"tile {tile.bounds}: degenerate horizontal registration of the right image"
        )
    shear = np.eye(3)
    shear[0] = abc
    H2 = shear @ H2
    # frame: the rectified outer rectangle of the left tile, widened for the disparity range
    q1, q2, qh = virtual_matches(left, right, outer, np.linspace(hmin, hmax, n_heights), n=n_fit)
    qu1, qv1 = apply_map(H1, q1[:, 0], q1[:, 1])
    qu2, _ = apply_map(H2, q2[:, 0], q2[:, 1])
    d = qu1 - qu2
    dmin = float(np.min(d)) - disparity_margin
    dmax = float(np.max(d)) + disparity_margin
    oc = np.array([outer[0], outer[2], outer[2], outer[0]], float)
    orr = np.array([outer[1], outer[1], outer[3], outer[3]], float)
    fu, fv = apply_map(H1, oc, orr)
    u0, v0 = np.floor(fu.min()), np.floor(fv.min())
    width = int(np.ceil(fu.max()) - u0) + 1
    height = int(np.ceil(fv.max()) - v0) + 1
    # shift both maps so that the frame starts at (0, 0); room on the left/right for the
    # right image's content is the matcher's business (it sees NaN outside)
    T = _translation(-u0, -v0)
    H1, H2 = T @ H1, T @ H2
    # residual vertical parallax on a staggered check grid at n_heights + 1 heights
    k1, k2, _ = virtual_matches(
        left, right, outer, np.linspace(hmin, hmax, n_heights + 1), n=n_check, offset=0.5
    )
    _, kv1 = apply_map(H1, k1[:, 0], k1[:, 1])
    _, kv2 = apply_map(H2, k2[:, 0], k2[:, 1])
    res = kv1 - kv2
    rms = float(np.sqrt(np.mean(res**2))) if res.size else float("nan")
    rmax = float(np.max(np.abs(res))) if res.size else float("nan")
    # disparity per metre at the centre of the tile
    cc, rc = 0.5 * (c0 + c1), 0.5 * (r0 + r1)
    p1, p2, _ = virtual_matches(left, right, (cc, rc, cc, rc), [h0 - 50.0, h0 + 50.0], n=1)
    if len(p1) == 2:
        pu1, _ = apply_map(H1, p1[:, 0], p1[:, 1])
        pu2, _ = apply_map(H2, p2[:, 0], p2[:, 1])
        px_per_m = float(((pu1[1] - pu2[1]) - (pu1[0] - pu2[0])) / 100.0)
    else:
        px_per_m = float("nan")
    et = EpipolarTile(
        tile=tile,
        H_left=H1,
        H_right=H2,
        shape=(height, width),
        disparity_range=(dmin, dmax),
        height_range=(hmin, hmax),
        residual_rms=rms,
        residual_max=rmax,
        method=method,
        px_per_m=px_per_m,
        info=dict(n_fit=int(len(x1)), n_check=int(res.size)),
    )
    log.debug(
        "tile %s: %s rectification, residual y-parallax RMS %.4f px (max %.4f), "
        "disparity %.1f..%.1f px",
        tile.bounds,
        method,
        rms,
        rmax,
        dmin,
        dmax,
    )
    return et


# ----------------------------------------------------------------------------- relative pointing


def vertical_offset_to_image_shift(et: EpipolarTile, u, v, disparity, vertical):
    """Right-image shifts implied by measured vertical offsets in a rectified tile.

    A match ``left(u, v) ~ right(u - d, v - dv)`` says the right image content sits at rectified
    row ``v - dv`` instead of ``v``; returned are the right-image ``(dcol, drow)`` displacements
    (arrays) between the two back-projected positions: the models' prediction must move by
    them.
    """
    Hi = np.linalg.inv(et.H_right)
    c_obs, r_obs = apply_map(Hi, u - disparity, v - vertical)
    c_mod, r_mod = apply_map(Hi, u - disparity, v)
    return c_obs - c_mod, r_obs - r_mod
