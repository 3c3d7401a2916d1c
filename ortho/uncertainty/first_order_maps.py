"""First-order orthoimage uncertainty maps: a coarse (x, y, h) lattice of exact propagations and
a cheap per-cell terrain step.

At a ground point of height ``h`` with terrain gradient ``g = (∂h/∂E, ∂h/∂N)``, the image-space
covariance ``S = J D Jᵀ`` (px²) moves to the ground through ``A_eff = A + ∂p/∂h gᵀ``
(:func:`stereodem.ortho.uncertainty.propagation.ground_covariance`). ``A_eff`` is a rank-1
update of the terrain-free ``A = ∂(col, row)/∂(E, N)``, so by Sherman–Morrison ::

    A_eff⁻¹ = M A⁻¹,    M = I − w gᵀ / (1 + gᵀw),    w = A⁻¹ ∂p/∂h

and the ground covariance is ``Σ = M Σ₀ Mᵀ`` with the flat-terrain covariance
``Σ₀ = A⁻¹ S A⁻ᵀ``; a source's horizontal variance is ``⟨MᵀM, Σ₀,k⟩``. ``Σ₀``, ``Σ₀,k``, ``w``
(the relief displacement per metre of height) and the image position depend only on the
position and the height, smoothly: they are evaluated exactly on a coarse lattice of the map
grid at two heights spanning the DEM, and interpolated — bilinear in (x, y), linear in h.
Per cell only the DEM height and gradient enter (``M``), a few float32 operations.

The cells are processed in blocks that lie inside one lattice column band, so that the
interpolation of every lattice field, at the cell's own height, is one small matrix product
per grid row (``numpy.matmul``); the DEM height and gradient are sampled with
:func:`cv2.remap`. Blocks run on threads (numpy and OpenCV release the GIL).

The interpolation error is measured, never assumed: the lattice is refined until the relative
error of σ_E, σ_N and σ_horizontal at check cells (lattice mid-cells and random cells) against the
exact per-cell propagation (:func:`stereodem.ortho.uncertainty.propagation.first_order`) is below
the tolerance, and the finished float32 maps are compared with the same exact values
(``UncertaintyMaps.interpolation_error``). Maps whose measured error still exceeds the tolerance
on the finest lattice (4 cells) are not returned: :class:`stereodem.core.errors.AccuracyError`.

The lattice carries the symmetric square root ``R`` of ``Σ₀`` (:func:`sqrt_psd`), and a cell's
covariance is ``(M R)(M R)ᵀ``: with one dominant input a ground component nearly vanishes
(σ_N of a roll bias on a north-south track), and ``M Σ₀ Mᵀ`` in float32 gave it as the square
root of rounding noise, off by up to ~√ε σ_horizontal (σ_N of 0.8 mm for 0.3 mm, ``sim_pb``'s
right image over the frame simulation's DEM: "interpolation error 0.0016 exceeds 0.001" and
exit 0; a yaw σ over rough terrain: 0.03 measured on every cell, a warning and exit 0).
"""

from __future__ import annotations

import functools
import logging
import time
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np
from scipy import ndimage

from stereodem.core.blocks import default_threads
from stereodem.core.errors import AccuracyError
from stereodem.core.stats import generator
from stereodem.ortho.drm import _lattice, bilinear_nan, crop_dem
from stereodem.ortho.uncertainty.propagation import (
    _ce90_table,
    ce90_from_cov,
    dem_gradient_arrays,
    dem_pixel_jacobian,
    first_order,
    ground_covariance,
    image_side,
)

log = logging.getLogger(__name__)

#: image-position and covariance fields interpolated in (x, y, h), in this order
H_FIELDS = ("col", "row", "r00", "r01", "r11", "w0", "w1")
#: DEM-pixel position and Jacobian ``∂(c, r)/∂(E, N)`` (x, y only)
XY_FIELDS = ("dem_col", "dem_row", "p00", "p01", "p10", "p11")
#: largest DEM side :func:`cv2.remap` samples (OpenCV's limit); larger DEMs use numpy
_REMAP_MAX = 32767


# ----------------------------------------------------------------------------- lattice


def lattice_fields(model, dem, grid, u, v, D, names, groups, heights):
    """Exact terrain-free fields at map cells ``(u, v)`` for the two ``heights``.

    Returns
    -------
    hf : ndarray (2, n, 7 + 3 k)
        Per height: image col, row; ``R = Σ₀^½`` (r00, r01, r11, m: the symmetric square
        root, :func:`sqrt_psd`); ``w`` (m per m of height);
        then each source's ``Σ₀,k`` (3 entries, m²).
    xy : ndarray (n, 6)
        DEM pixel col, row (centres at integers) and ``∂(c, r)/∂(E, N)`` (p00, p01, p10, p11).
    sources : list of str
    """
    lon, lat = grid.lonlat(np.asarray(u, float), np.asarray(v, float))
    srcs = list(groups or {n: [n] for n in names})
    n = lon.size
    # both heights in one evaluation (the model calls, not the points, cost here)
    hh = np.repeat(np.asarray(heights, float), n)
    f = image_side(model, np.tile(lon, 2), np.tile(lat, 2), hh, names, D, grid.crs, groups=groups)
    zero = np.zeros((2 * n, 2))
    s0 = ground_covariance(f["A"], f["ph"], zero, f["S"])
    with np.errstate(all="ignore"):
        w = np.linalg.solve(f["A"], f["ph"][..., None])[..., 0]
    cols = [f["col"], f["row"], *sqrt_psd(*s0), w[:, 0], w[:, 1]]
    for s in srcs:
        cols.extend(ground_covariance(f["A"], f["ph"], zero, f["C"][s]))
    per_h = np.stack(cols, -1).reshape(2, n, -1)
    cd, rd, P = dem_pixel_jacobian(dem, lon, lat, grid.crs)
    xy = np.stack([cd, rd, P[:, 0, 0], P[:, 0, 1], P[:, 1, 0], P[:, 1, 1]], -1)
    return per_h, xy, srcs


def terrain_factor(w0, w1, gE, gN):
    """``M = I − w gᵀ/(1 + gᵀw)`` entries (m00, m01, m10, m11): the flat-terrain ground
    displacement turned into the displacement on a surface of gradient ``g`` (Sherman–Morrison
    form of ``A_eff⁻¹ A``)."""
    c = 1.0 / (1.0 + w0 * gE + w1 * gN)
    v0, v1 = c * w0, c * w1
    return 1.0 - v0 * gE, -v0 * gN, -v1 * gE, 1.0 - v1 * gN


def sqrt_psd(s00, s01, s11):
    """Symmetric square root ``R`` (r00, r01, r11) of the positive semi-definite 2 × 2
    ``S``: ``R = (S + √det I) / √(tr S + 2 √det)``, ``R R = S`` (0 where ``S`` is 0).

    The lattice carries ``R``, not ``S``: per cell the covariance is ``(M R)(M R)ᵀ``, whose
    diagonal is a sum of squares, so a component that nearly vanishes (a single input
    moving the ground along one direction: σ_N ≈ 0 under a roll bias) is not the difference
    of large float32 terms (``M S Mᵀ`` gave it as the square root of rounding noise,
    ~√ε σ_horizontal); and interpolating ``R`` keeps a near-singular covariance near
    singular (an interpolated ``S`` of a turning direction gains a minor axis of the order
    of the turn, ``R``'s only of its square)."""
    det = np.maximum(s00 * s11 - s01 * s01, 0.0)
    sd = np.sqrt(det)
    t = np.sqrt(np.maximum(s00 + s11 + 2.0 * sd, 0.0))
    with np.errstate(all="ignore"):
        inv = np.where(t > 0, 1.0 / t, 0.0)
    return (s00 + sd) * inv, s01 * inv, (s11 + sd) * inv


def root_congruence(m00, m01, m10, m11, r00, r01, r11):
    """``(M R)(M R)ᵀ`` of symmetric 2 × 2 ``R`` -> (g00, g01, g11): ``M S Mᵀ`` for
    ``S = R R`` with the diagonal a sum of squares (no cancellation)."""
    t00 = m00 * r00 + m01 * r01
    t01 = m00 * r01 + m01 * r11
    t10 = m10 * r00 + m11 * r01
    t11 = m10 * r01 + m11 * r11
    return t00 * t00 + t01 * t01, t00 * t10 + t01 * t11, t10 * t10 + t11 * t11


def metric(m00, m01, m10, m11):
    """``MᵀM`` -> (q00, q01, q11): a source's horizontal variance is
    ``q00 c00 + 2 q01 c01 + q11 c11`` for its flat-terrain covariance ``c``."""
    return m00 * m00 + m10 * m10, m00 * m01 + m10 * m11, m01 * m01 + m11 * m11


def _node_lattice(grid, st):
    uu, vv = _lattice(grid, st)
    uu = np.minimum(uu, grid.width - 1).astype(float)
    vv = np.minimum(vv, grid.height - 1).astype(float)
    if uu.size > 1 and uu[-1] == uu[-2]:
        uu[-1] = uu[-2] + 1
    if vv.size > 1 and vv[-1] == vv[-2]:
        vv[-1] = vv[-2] + 1
    return uu, vv


def _weights(n_full, nodes, x=None):
    """Dense linear-interpolation matrix from lattice ``nodes`` to positions ``x``
    (default all cells ``0..n_full-1``)."""
    x = np.arange(n_full, dtype=float) if x is None else np.asarray(x, float)
    W = np.zeros((x.size, nodes.size))
    j = np.clip(np.searchsorted(nodes, x, side="right") - 1, 0, nodes.size - 2)
    t = np.clip((x - nodes[j]) / (nodes[j + 1] - nodes[j]), 0.0, 1.0)
    W[np.arange(x.size), j] = 1 - t
    W[np.arange(x.size), j + 1] = t
    return W


@functools.lru_cache(maxsize=1)
def _remap_is_exact() -> bool:
    """Whether :func:`cv2.remap` (``INTER_LINEAR``, float32 maps) interpolates at the map's
    positions themselves: OpenCV 5 does; 4.x rounds them to 1/32 of a pixel (its fixed-point
    tables), which moves a DEM height or gradient sampled between posts. Checked once, at
    positions between the 1/32 steps."""
    img = np.arange(16, dtype=np.float32).reshape(4, 4)
    xs = np.array([[0.01, 0.02, 1.3337, 2.49]], np.float32)
    got = cv2.remap(img, xs, np.zeros_like(xs), cv2.INTER_LINEAR)
    return bool(np.allclose(got, xs, rtol=0, atol=1e-5))


class Lattice:
    """The exact fields on lattice nodes ``uu`` × ``vv`` (grid cells) at ``heights``, the
    height-linear form ``f(h) = a + b (h − h_mid)`` of each, and point evaluation."""

    def __init__(self, model, dem, grid, D, names, groups, heights, st):
        self.uu, self.vv = _node_lattice(grid, st)
        self.step = st
        U, V = np.meshgrid(self.uu, self.vv)
        hf, xy, self.sources = lattice_fields(
            model, dem, grid, U.ravel(), V.ravel(), D, names, groups, heights
        )
        ny, nx = U.shape
        self.h_mid = 0.5 * (heights[0] + heights[1])
        self.h_lo, self.h_hi = float(heights[0]), float(heights[1])
        dh = float(heights[1] - heights[0])
        self.a = (0.5 * (hf[0] + hf[1])).reshape(ny, nx, -1)  # value at h_mid
        self.b = ((hf[1] - hf[0]) / dh).reshape(ny, nx, -1)  # per metre
        self.xy = xy.reshape(ny, nx, -1)
        self.n_nodes = U.size

    def at(self, u, v, h):
        """Fields at cells ``(u, v)`` and heights ``h`` (float64 bilinear): (hf, xy) with
        ``hf`` (n, 7 + 3k) at ``h`` and ``xy`` (n, 6)."""
        Wx, Wy = _weights(0, self.uu, u), _weights(0, self.vv, v)
        bil = lambda L: np.einsum("ni,ijf,nj->nf", Wy, L, Wx)
        dh = (np.asarray(h, float) - self.h_mid)[:, None]
        return bil(self.a) + dh * bil(self.b), bil(self.xy)


def _terrain_sigma_points(lat_, dem_e, garr, u, v):
    """σ_E², σ_N² ... at cells (u, v) from the lattice (float64, numpy sampling of the DEM):
    returns (g00, g01, g11, col, row, h)."""
    xy = lat_.at(u, v, np.full(np.shape(u), lat_.h_mid))[1]
    cd, rd = xy[:, 0], xy[:, 1]
    h = bilinear_nan(dem_e.heights, cd, rd)
    hf, _ = lat_.at(u, v, np.where(np.isfinite(h), h, lat_.h_mid))
    gc = np.nan_to_num(bilinear_nan(garr[0], cd, rd))
    gr = np.nan_to_num(bilinear_nan(garr[1], cd, rd))
    gE = gc * xy[:, 2] + gr * xy[:, 4]
    gN = gc * xy[:, 3] + gr * xy[:, 5]
    M = terrain_factor(hf[:, 5], hf[:, 6], gE, gN)
    g = root_congruence(*M, hf[:, 2], hf[:, 3], hf[:, 4])
    return g, hf[:, 0], hf[:, 1], h


def relative_error(got, exact):
    """Largest relative error of (σ_E, σ_N) pairs (n, 2) and of their σ_horizontal, a
    component counted relative to ``max(σ_component, 0.01 σ_horizontal)`` (so that a vanishing
    component does not blow the measure up); 0 for no points."""
    if not len(exact):
        return 0.0
    sh, gh = np.hypot(*exact.T), np.hypot(*got.T)
    den = np.maximum(exact, 0.01 * sh[:, None])
    return float(max(np.max(np.abs(got - exact) / den), np.max(np.abs(gh / sh - 1))))


# ----------------------------------------------------------------------------- per-cell blocks


class _Blocks:
    """Per-block evaluation of the maps (float32)."""

    def __init__(self, lat_, dem_e, garr, grid, model, outputs, source_maps):
        self.L, self.grid, self.model = lat_, grid, model
        self.k = len(lat_.sources)
        # each grid row between two lattice rows: index and weight (linear along y)
        y = np.arange(grid.height, dtype=float)
        vv = lat_.vv
        self.jy = np.clip(np.searchsorted(vv, y, side="right") - 1, 0, vv.size - 2)
        self.sy = np.clip((y - vv[self.jy]) / (vv[self.jy + 1] - vv[self.jy]), 0.0, 1.0)[:, None]
        self.dh_range = (lat_.h_lo - lat_.h_mid, lat_.h_hi - lat_.h_mid)
        z = np.asarray(dem_e.heights, np.float32)
        gc, gr = garr
        self.voids = bool(np.isnan(gc).any() or np.isnan(gr).any())
        # OpenCV's remap where it interpolates float maps exactly (5.x); 4.x rounds positions
        # to 1/32 of a post, which the maps' measured error would then show (0.016 on a
        # frame camera's yaw over rough terrain: AccuracyError)
        self.use_remap = max(z.shape) <= _REMAP_MAX and _remap_is_exact()
        # voids as 0 with a validity channel: cv2.remap multiplies a NaN neighbour of no
        # weight into NaN, so cells beside a void are taken by the exact rule (bilinear_nan)
        self.dem3 = (
            np.ascontiguousarray(
                np.stack(
                    [
                        np.nan_to_num(z),
                        np.nan_to_num(gc).astype(np.float32),
                        np.nan_to_num(gr).astype(np.float32),
                        np.isfinite(z).astype(np.float32),
                    ],
                    -1,
                )
            )
            if self.use_remap
            else None
        )
        self.dem_e, self.garr = dem_e, garr
        self.out = outputs
        self.source_maps = source_maps
        self.skipped = []

    def bands(self, rows_per_block):
        uu = self.L.uu.astype(int)
        H, W = self.grid.height, self.grid.width
        out = []
        for i in range(uu.size - 1):
            c0, c1 = uu[i], (uu[i + 1] if i < uu.size - 2 else W)
            c1 = min(c1, W)
            if c1 <= c0:
                continue
            for r0 in range(0, H, rows_per_block):
                out.append((i, c0, c1, r0, min(H, r0 + rows_per_block)))
        return out

    def _outside(self, ya0, ya1, yb0, yb1):
        """Whether the block's image positions all fall on one side outside the image: the
        interpolated position is bilinear in (x, y) between these lattice columns and rows and
        linear in h, so its extremes are on the block's lattice rows/columns and heights."""
        lo, hi = self.dh_range
        m = self.model
        for j, size in ((0, m.width), (1, m.height)):
            a = np.concatenate([ya0[:, j], ya1[:, j]])
            b = np.concatenate([yb0[:, j], yb1[:, j]])
            ext = np.concatenate([a + b * lo, a + b * hi])
            if ext.max() < -0.5 or ext.min() > size - 0.5:
                return True
        return False

    def run(self, i, c0, c1, r0, r1):
        """One block: rows r0:r1, columns c0:c1 (inside lattice column band i). Writes the
        outputs and returns the per-source variance totals over its valid cells."""
        f32 = np.float32
        L, k = self.L, self.k
        x = np.arange(c0, c1, dtype=float)
        t = np.clip((x - L.uu[i]) / (L.uu[i + 1] - L.uu[i]), 0.0, 1.0)
        tx1 = t.astype(f32)[None, :]
        tx0 = (1.0 - t).astype(f32)[None, :]
        nb, nw = r1 - r0, c1 - c0
        j, sy = self.jy[r0:r1], self.sy[r0:r1]
        # lattice columns i and i + 1 interpolated along y to the block's rows, float32 (nb, fields)
        along_y = lambda F, c: ((1.0 - sy) * F[j, c] + sy * F[j + 1, c]).astype(f32)
        ya0, ya1 = along_y(L.a, i), along_y(L.a, i + 1)
        yb0, yb1 = along_y(L.b, i), along_y(L.b, i + 1)
        if self._outside(ya0, ya1, yb0, yb1):
            self.skipped.append(1)
            return np.zeros(k)
        x0, x1 = along_y(L.xy, i), along_y(L.xy, i + 1)
        # DEM position, then the DEM height and gradient at it
        cd = x0[:, 0:1] * tx0 + x1[:, 0:1] * tx1
        rd = x0[:, 1:2] * tx0 + x1[:, 1:2] * tx1
        if self.use_remap:
            s = cv2.remap(
                self.dem3,
                cd,
                rd,
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=(0, 0, 0, 0),
            )
            h, gc, gr, valid = s[..., 0], s[..., 1], s[..., 2], s[..., 3]
            h[valid <= 0] = np.nan
            edge = (valid > 0) & (valid < 1 - 1e-6)  # beside a void or the DEM's border
            if edge.any():
                ce, re_ = cd[edge], rd[edge]
                h[edge] = bilinear_nan(self.dem_e.heights, ce, re_, dtype=f32)
                gc[edge] = bilinear_nan(self.garr[0], ce, re_, dtype=f32)
                gr[edge] = bilinear_nan(self.garr[1], ce, re_, dtype=f32)
        else:
            h = bilinear_nan(self.dem_e.heights, cd, rd, dtype=f32)
            gc = bilinear_nan(self.garr[0], cd, rd, dtype=f32)
            gr = bilinear_nan(self.garr[1], cd, rd, dtype=f32)
        if self.voids:
            gc, gr = np.nan_to_num(gc), np.nan_to_num(gr)
        dh = h - f32(L.h_mid)
        # interpolation in x and h (and the map-axis gradient) as one product per grid row:
        # out[y, :, x] = B[y] @ R[y, :, x]
        R = np.empty((nb, 8, nw), f32)
        R[:, 0], R[:, 1] = tx0, tx1
        np.multiply(dh, tx0, out=R[:, 2])
        np.multiply(dh, tx1, out=R[:, 3])
        np.multiply(gc, tx0, out=R[:, 4])
        np.multiply(gc, tx1, out=R[:, 5])
        np.multiply(gr, tx0, out=R[:, 6])
        np.multiply(gr, tx1, out=R[:, 7])
        nf = len(H_FIELDS)
        B = np.zeros((nb, nf + 2, 8), f32)
        B[:, :nf, 0], B[:, :nf, 1] = ya0[:, :nf], ya1[:, :nf]
        B[:, :nf, 2], B[:, :nf, 3] = yb0[:, :nf], yb1[:, :nf]
        # gE = gc p00 + gr p10, gN = gc p01 + gr p11
        for o, (pc, pr) in ((nf, (2, 4)), (nf + 1, (3, 5))):
            B[:, o, 4], B[:, o, 5], B[:, o, 6], B[:, o, 7] = (
                x0[:, pc],
                x1[:, pc],
                x0[:, pr],
                x1[:, pr],
            )
        O = np.matmul(B, R)
        col, row, r00, r01, r11, w0, w1, gE, gN = (O[:, j] for j in range(nf + 2))
        m = self.model
        ok = (col >= -0.5) & (col <= m.width - 0.5) & (row >= -0.5) & (row <= m.height - 0.5)
        ok &= np.isfinite(h)
        with np.errstate(all="ignore"):
            M = terrain_factor(w0, w1, gE, gN)
            g00, g01, g11 = root_congruence(*M, r00, r01, r11)
            sE, sN = np.sqrt(g00), np.sqrt(g11)
        ok &= np.isfinite(sE) & np.isfinite(sN)
        nan = f32(np.nan)
        self.out["sE"][r0:r1, c0:c1] = np.where(ok, sE, nan)
        self.out["sN"][r0:r1, c0:c1] = np.where(ok, sN, nan)
        with np.errstate(all="ignore"):
            self.out["c90"][r0:r1, c0:c1] = np.where(ok, ce90_from_cov(g00, g01, g11), nan)
        # per-source horizontal variance ⟨MᵀM, Σ₀,k⟩, interpolated in x and h likewise
        q00, q01, q11 = metric(*M)
        dh = np.where(ok, dh, f32(0))
        R2 = np.empty((nb, 12, nw), f32)
        for j, q in enumerate((q00, q01 + q01, q11)):
            qm = np.where(ok, q, f32(0))
            np.multiply(qm, tx0, out=R2[:, j])
            np.multiply(qm, tx1, out=R2[:, 3 + j])
            np.multiply(R2[:, j], dh, out=R2[:, 6 + j])
            np.multiply(R2[:, 3 + j], dh, out=R2[:, 9 + j])
        B2 = np.empty((nb, k, 12), f32)
        for j in range(3):
            sl = slice(nf + j, nf + 3 * k, 3)
            B2[:, :, j], B2[:, :, 3 + j] = ya0[:, sl], ya1[:, sl]
            B2[:, :, 6 + j], B2[:, :, 9 + j] = yb0[:, sl], yb1[:, sl]
        C = np.matmul(B2, R2)  # (nb, k, nw)
        best = C[:, 0].copy()
        dom = np.zeros((nb, nw), np.int16)
        for s_ in range(1, k):
            better = C[:, s_] > best
            np.copyto(best, C[:, s_], where=better)
            np.copyto(dom, s_, where=better)
        np.copyto(dom, -1, where=~ok)
        self.out["dom"][r0:r1, c0:c1] = dom
        if self.source_maps:
            with np.errstate(all="ignore"):
                V = np.where(ok, g00 + g11, nan)
                for s_, name in enumerate(L.sources):
                    self.out["share_" + name][r0:r1, c0:c1] = C[:, s_] / V
        # totals over valid cells: Σ_y Σ_m (Σ_x R2) B2
        rsum = np.matmul(R2, np.ones(nw, f32)).astype(np.float64)  # (nb, 12)
        return np.einsum("ym,ykm->k", rsum, B2.astype(np.float64))


def first_order_maps(
    model,
    dem,
    grid,
    D,
    names,
    groups=None,
    *,
    step=None,
    tolerance=1e-3,
    n_check=400,
    seed=0,
    source_maps=False,
    threads=None,
    cells_per_block: int = 32768,
):
    """First-order σ_E, σ_N, CE90, dominant source and variance shares on ``grid``.

    Parameters as :func:`stereodem.ortho.uncertainty.maps.ortho_uncertainty_maps` (``model``
    adjustable, ``dem`` ellipsoidal, ``D`` checked). ``step`` fixes the lattice spacing (cells);
    by default it starts at 256 cells and is halved until the measured relative error of
    σ_E, σ_N and σ_horizontal at the check cells is below ``tolerance`` (a component is
    counted relative to ``max(σ_component, 0.01 σ_horizontal)``, :func:`relative_error`).

    Raises
    ------
    AccuracyError
        The measured error (lattice or finished maps) exceeds ``tolerance`` at the finest
        lattice (4 cells); with ``step`` given, a warning instead (the caller's lattice).

    Returns
    -------
    dict with sE, sN, c90 (float32 maps), dom (int16), share maps, shares, sources, step,
    interpolation_error (end-to-end: the float32 maps against exact per-cell propagation),
    and details.
    """
    from stereodem.ortho.uncertainty.maps import UncertaintyMaps

    t0 = time.perf_counter()
    rng = generator(seed)
    dem_e = crop_dem(dem, grid)
    z = dem_e.heights
    lo, hi = float(np.nanmin(z)), float(np.nanmax(z))
    pad = max(1.0, 0.02 * (hi - lo))
    heights = (lo - pad, hi + pad)
    garr = dem_gradient_arrays(dem_e)
    near_void = None
    if np.isnan(z).any():
        near_void = ndimage.binary_dilation(np.isnan(z), iterations=3)
    big = max(grid.width, grid.height)
    st = int(step or min(256, max(1, 2 ** int(np.ceil(np.log2(max(big, 2) / 2))))))
    # check cells: integer cells nearest to lattice mid-cells and random cells; exact values once
    while True:
        lat_ = Lattice(model, dem_e, grid, D, names, groups, heights, st)
        uu, vv = lat_.uu, lat_.vv
        ny, nx = vv.size, uu.size
        m = min(n_check // 2, (ny - 1) * (nx - 1))
        cell = rng.choice((ny - 1) * (nx - 1), size=m, replace=False)
        cu = np.concatenate(
            [
                np.floor(0.5 * (uu[cell % (nx - 1)] + uu[cell % (nx - 1) + 1])),
                rng.integers(0, grid.width, n_check - m),
            ]
        ).astype(float)
        cv = np.concatenate(
            [
                np.floor(0.5 * (vv[cell // (nx - 1)] + vv[cell // (nx - 1) + 1])),
                rng.integers(0, grid.height, n_check - m),
            ]
        ).astype(float)
        cu, cv = np.minimum(cu, grid.width - 1), np.minimum(cv, grid.height - 1)
        g, col, row, h = _terrain_sigma_points(lat_, dem_e, garr, cu, cv)
        ok = (
            np.isfinite(h)
            & (col >= -0.5)
            & (col <= model.width - 0.5)
            & (row >= -0.5)
            & (row <= model.height - 0.5)
        )
        # check cells off void edges: there the slope rule (one-sided beside a void) is
        # discontinuous in position, and a cell may fall on either side of it
        lon_a, lat_a = grid.lonlat(cu, cv)
        dc, dr, _ = dem_pixel_jacobian(dem_e, lon_a, lat_a, grid.crs)
        if near_void is not None:
            ok &= ~near_void[
                np.clip(np.floor(np.nan_to_num(dr)).astype(int), 0, z.shape[0] - 1),
                np.clip(np.floor(np.nan_to_num(dc)).astype(int), 0, z.shape[1] - 1),
            ]
        lon, lat = grid.lonlat(cu[ok], cv[ok])
        exact = first_order(model, lon, lat, dem_e.sample(lon, lat), names, D, grid.crs, dem=dem_e)
        exact = np.stack([exact.sigma_east, exact.sigma_north], -1)
        with np.errstate(invalid="ignore"):
            inter = np.sqrt(np.stack([g[0][ok], g[2][ok]], -1))
        good = np.all(np.isfinite(exact) & np.isfinite(inter), -1) & (np.hypot(*exact.T) > 0)
        err = relative_error(inter[good], exact[good])
        # the DEM position (reported: the σ errors above already carry its effect through the
        # height and slope; at a void edge, where the exact slope rule is discontinuous, a
        # cell can change side; cv2.remap itself rounds positions to 1/32 post)
        xy = lat_.at(cu, cv, np.full(cu.shape, lat_.h_mid))[1]
        err_dem = float(np.max(np.hypot(xy[:, 0] - dc, xy[:, 1] - dr)))
        log.debug(
            "uncertainty lattice step %d: relative error %.2e, DEM position %.2e px",
            st,
            err,
            err_dem,
        )
        if step is not None or err <= tolerance or st <= 4:
            break
        st //= 2
    lattice_err = err
    shape = grid.shape
    out = {
        "sE": np.full(shape, np.nan, np.float32),
        "sN": np.full(shape, np.nan, np.float32),
        "c90": np.full(shape, np.nan, np.float32),
        "dom": np.full(shape, -1, np.int16),
    }
    if source_maps:
        out.update({"share_" + s: np.full(shape, np.nan, np.float32) for s in lat_.sources})
    t1 = time.perf_counter()
    blk = _Blocks(lat_, dem_e, garr, grid, model, out, source_maps)
    bw = int(np.max(np.diff(uu)))
    jobs = blk.bands(max(8, cells_per_block // max(bw, 1)))
    _ce90_table()  # tabulated once, before the threads
    # the process's thread budget (as every library routine), not the machine's cores
    n_threads = max(1, default_threads() if threads is None else int(threads))
    totals = np.zeros(len(lat_.sources))
    if n_threads > 1:
        with ThreadPoolExecutor(n_threads) as pool:
            for part in pool.map(lambda a: blk.run(*a), jobs):
                totals += part
    else:
        for a in jobs:
            totals += blk.run(*a)
    t2 = time.perf_counter()
    tot = totals.sum()
    srcs = lat_.sources
    shares = {s_: float(totals[k] / tot) if tot > 0 else float("nan") for k, s_ in enumerate(srcs)}
    # end-to-end error of the finished float32 maps at the check cells
    iu, iv = cu[ok][good].astype(int), cv[ok][good].astype(int)
    got = np.stack([out["sE"][iv, iu], out["sN"][iv, iu]], -1).astype(float)
    fin = np.all(np.isfinite(got), -1)
    map_err = relative_error(got[fin], exact[good][fin])
    err = max(lattice_err, map_err)
    if err > tolerance:
        what = (
            f"uncertainty maps: the measured relative interpolation error {err:.3g} "
            f"(lattice {lattice_err:.3g}, finished maps {map_err:.3g}) exceeds the tolerance "
            f"{tolerance:.3g} on a lattice of {st} cells"
        )
        if step is not None:  # the caller fixed the lattice: its choice, said
            log.warning("%s (step fixed by the caller)", what)
        else:  # never maps known to be off by more than the tolerance
            raise AccuracyError(
                f"{what}, the finest the maps refine to: the σ vary faster than the lattice "
                "resolves there (or the float32 cells differ from the exact propagation); "
                "no maps written"
            )
    details = {
        "n_lattice_nodes": int(lat_.n_nodes),
        "lattice_heights_m": list(heights),
        "seconds": {
            "lattice_and_check": round(t1 - t0, 3),
            "cells": round(t2 - t1, 3),
            "n_blocks": len(jobs),
            "n_blocks_outside": int(sum(blk.skipped)),
        },
        "interpolation_error_lattice": lattice_err,
        "interpolation_error_maps": map_err,
        "dem_position_error_px": err_dem,
        "n_check_cells": int(good.sum()),
        "terrain": "each cell's own DEM height and slope (central-difference gradient, "
        "one-sided beside voids)",
    }
    kept = {s_: out["share_" + s_] for s_ in srcs} if source_maps else {}
    return UncertaintyMaps(
        grid,
        "first-order",
        list(names),
        srcs,
        out["sE"],
        out["sN"],
        out["c90"],
        out["dom"],
        shares,
        st,
        err,
        kept,
        details,
    )
