"""The ``"ncc"`` matcher: zero-mean normalised cross-correlation (ZNCC) block matching.

ZNCC over a square window for all pixels at once (:mod:`.window_stats`), streaming over the
disparities and keeping only best-so-far arrays; coarse-to-fine on a Gaussian pyramid, each
finer level searching ``+/- margin`` around the upsampled, hole-filled coarse disparity
(:mod:`.seed`); sub-pixel peak (parabola or V fit), left-right check, score threshold and
texture mask (:func:`_match_ncc`, called by :func:`stereodem.stereo.match.match_rectified`)."""

from __future__ import annotations

import math
from typing import NamedTuple

import cv2
import numpy as np

from stereodem.core.errors import InputError
from stereodem.core.morphology import square_dilation

from .images import _gather_cols
from .pyramid import build_pyramid, upsample_field
from .seed import _fill_seed
from .window_stats import _box_mean, _window_stats

F32 = np.float32

#: ``subpixel`` choices of :func:`stereodem.stereo.match.match_rectified`
SUBPIXELS: tuple[str, ...] = ("parabola", "vfit")


def _warp_cols(a, seed):
    """``a(x - seed(x, y), y)`` by bicubic interpolation; NaN outside ``a`` and where the
    4x4 support touches no-data."""
    h, w = a.shape
    map_x = (np.arange(w, dtype=F32)[None, :] - seed).astype(F32)
    map_y = np.broadcast_to(np.arange(h, dtype=F32)[:, None], (h, w))
    nan = ~np.isfinite(a)
    src = np.where(nan, F32(0), a) if nan.any() else a
    out = cv2.remap(
        src,
        map_x,
        np.ascontiguousarray(map_y),
        cv2.INTER_CUBIC,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=np.nan,
    )
    if nan.any():
        bad = cv2.remap(
            nan.astype(F32),
            map_x,
            np.ascontiguousarray(map_y),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=1.0,
        )
        out[square_dilation(bad > 0, 3)] = np.nan
    # outside the image
    out[(map_x < 0) | (map_x > w - 1)] = np.nan
    return out


def _shift_rows(a, dy):
    """``out[y] = a[y - dy]`` with NaN rows entering."""
    if dy == 0:
        return a
    out = np.full_like(a, np.nan)
    if dy > 0:
        out[dy:] = a[:-dy]
    else:
        out[:dy] = a[-dy:]
    return out


def _subpixel(c0, cm, cp, method):
    """Offset of the correlation peak from the integer maximum (in [-0.5, 0.5]).

    ``cm``/``cp`` are the scores at ``k - 1`` / ``k + 1``; NaN where they are missing or
    where the integer maximum is not a peak (the true maximum lies outside the range).
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        if method == "parabola":
            den = cm - 2 * c0 + cp
            delta = (cm - cp) / (2 * den)
            ok = den < 0
        elif method == "vfit":
            lo = np.minimum(cm, cp)
            den = c0 - lo
            delta = (cp - cm) / (2 * den)
            ok = den > 0
        else:  # pragma: no cover - checked in match_rectified
            raise InputError(f"unknown subpixel method {method!r}")
    ok &= (c0 >= cm) & (c0 >= cp)
    delta = np.where(ok, np.clip(delta, -0.5, 0.5), np.nan)
    # a flat peak (both neighbours equal to the maximum) has no defined optimum
    return delta.astype(F32, copy=False)


class _Scan(NamedTuple):
    score: np.ndarray  # best ZNCC (-inf where none)
    k: np.ndarray  # offset of the best (int32)
    cm: np.ndarray  # ZNCC at k - 1
    cp: np.ndarray  # ZNCC at k + 1
    back_score: np.ndarray | None
    back_k: np.ndarray | None


def _scan(ref, tgt, klo, khi, window, min_std, back=False):
    """Stream ZNCC(ref(x), tgt(x - k)) over integer offsets ``klo..khi``.

    The scores at ``klo - 1`` and ``khi + 1`` are computed too, only as neighbours for the
    sub-pixel fit.  With ``back``, also tracks for every ``tgt`` pixel the best offset of the
    ``ref`` pixel matching it (the "right" disparity map, free for a full search).
    Memory: a dozen image-sized float32 arrays whatever the number of offsets.
    """
    h, w = ref.zero.shape
    pl = max(khi + 1, 0)
    pr = max(1 - klo, 0)
    padded = np.full((h, w + pl + pr), np.nan, dtype=F32)
    padded[:, pl : pl + w] = tgt
    t = _window_stats(padded, window, min_std)
    # columns of tgt's border are not windows leaving tgt: re-validate them by the NaN pad
    r = ref

    best = np.full((h, w), -np.inf, dtype=F32)
    bk = np.full((h, w), klo - 1, dtype=np.int32)
    cm = np.full((h, w), np.nan, dtype=F32)
    cp = np.full((h, w), np.nan, dtype=F32)
    if back:
        bbest = np.full((h, w), -np.inf, dtype=F32)
        bbk = np.full((h, w), klo - 1, dtype=np.int32)
        bupd = np.empty((h, w), dtype=bool)
    prod = np.empty((h, w), dtype=F32)
    boxed = np.empty((h, w), dtype=F32)
    tmp = np.empty((h, w), dtype=F32)
    c = np.empty((h, w), dtype=F32)
    cprev = np.full((h, w), np.nan, dtype=F32)
    upd = np.empty((h, w), dtype=bool)
    upd_prev = np.zeros((h, w), dtype=bool)
    have_prev = False
    for k in range(klo - 1, khi + 2):
        sl = slice(pl - k, pl - k + w)
        cv2.multiply(r.zero, t.zero[:, sl], dst=prod)
        _box_mean(prod, window, dst=boxed)
        np.multiply(r.mean, t.mean[:, sl], out=tmp)
        np.subtract(boxed, tmp, out=c)
        np.multiply(c, r.inv, out=c)
        np.multiply(c, t.inv[:, sl], out=c)
        if have_prev:
            np.copyto(cp, c, where=upd_prev)
        if klo <= k <= khi:
            np.greater(c, best, out=upd)
            np.copyto(best, c, where=upd)
            np.copyto(bk, k, where=upd)
            np.copyto(cm, cprev, where=upd)
            upd, upd_prev = upd_prev, upd
            have_prev = True
            if back and abs(k) < w:
                # tgt pixel xt = x - k is matched by ref pixel x = xt + k (at |k| >= w no
                # pixel has a partner inside the other image)
                if k >= 0:
                    cs, bs = c[:, k:], np.s_[:, : w - k]
                else:
                    cs, bs = c[:, : w + k], np.s_[:, -k:]
                bb = bbest[bs]
                m = bupd[bs]
                np.greater(cs, bb, out=m)
                np.copyto(bb, cs, where=m)
                np.copyto(bbk[bs], k, where=m)
        else:
            have_prev = False
        c, cprev = cprev, c
    # cp of a maximum found at the very last offset was filled at khi + 1
    return _Scan(best, bk, cm, cp, bbest if back else None, bbk if back else None)


def _lr_check(d_left, d_right, tol):
    """Mask of left pixels whose disparity agrees with the right map within ``tol`` px."""
    h, w = d_left.shape
    cols = np.arange(w, dtype=F32)[None, :]
    with np.errstate(invalid="ignore"):
        xr = np.rint(cols - d_left)
        xr = np.where(np.isfinite(xr), xr, -1).astype(np.int64)
        back = _gather_cols(d_right, xr)
        return np.abs(d_left - back) <= tol


def _match_pass(ref, tgt, seed, klo, khi, window, min_std, subpixel, vertical, back=False):
    """One ZNCC pass: ``ref(x, y)`` against ``tgt`` warped by a seed and shifted by ``k``.

    ``seed`` is a float seed disparity map ``S`` (None: a plain full search over
    ``klo..khi``): ``tgt`` is first warped (bicubic) to ``tgt'(x) = tgt(x - S(x), y - dy)``,
    then ``ref(x)`` is correlated with ``tgt'(x - k)``, so the window follows the seed
    surface and the disparity is ``k + S(x - k)`` plus the sub-pixel offset.  Returns disparity
    (float, NaN where no peak), score, vertical offset, and (with ``back``) the integer disparity
    map of ``tgt`` seen from ``tgt`` (full search only).
    """
    h, w = ref.shape
    rstats = _window_stats(ref, window, min_std)
    cols = np.arange(w, dtype=np.int64)[None, :]
    best = None
    per_dy = []
    for dy in range(-vertical, vertical + 1):
        t = _shift_rows(tgt, dy)
        if seed is not None:
            t = _warp_cols(t, seed)
        s = _scan(rstats, t, klo, khi, window, min_std, back=back and dy == 0)
        per_dy.append(s.score)
        if best is None:
            best, best_dy = s, np.full((h, w), dy, dtype=np.int32)
            back_res = (s.back_score, s.back_k)
            continue
        better = s.score > best.score
        best = _Scan(
            *(
                np.where(better, new, old) if new is not None else old
                for new, old in zip(s[:4], best[:4])
            ),
            None,
            None,
        )
        best_dy[better] = dy
    score = best.score
    found = np.isfinite(score)
    delta = _subpixel(score, best.cm, best.cp, subpixel)
    k = best.k
    if seed is not None:
        base = _gather_cols(seed, cols - k, fill=np.nan)
    else:
        base = 0
    disp = (k + base + delta).astype(F32)
    disp[~found] = np.nan
    score = np.where(found, score, np.nan).astype(F32)
    vert = None
    if vertical:
        stack = np.stack(per_dy)  # (2v+1, H, W)
        i = best_dy + vertical
        vm = np.take_along_axis(stack, np.clip(i - 1, 0, 2 * vertical)[None], 0)[0]
        vp = np.take_along_axis(stack, np.clip(i + 1, 0, 2 * vertical)[None], 0)[0]
        vm = np.where(i - 1 >= 0, vm, np.nan)
        vp = np.where(i + 1 <= 2 * vertical, vp, np.nan)
        dv = _subpixel(best.score, vm, vp, "parabola")
        # the edge of the vertical range keeps the integer offset
        vert = (best_dy + np.where(np.isfinite(dv), dv, 0)).astype(F32)
        vert[np.isnan(disp)] = np.nan
    back_disp = None
    if back and back_res[0] is not None:
        bs, bk = back_res
        back_disp = np.where(np.isfinite(bs), bk, np.nan).astype(F32)
    return disp, score, vert, back_disp


def _auto_levels(lo, hi, shape):
    levels = 0
    span = hi - lo
    while span / 2**levels > 24 and min(shape) / 2 ** (levels + 1) >= 48 and levels < 6:
        levels += 1
    return levels


def _forward_seed(seed_left, w):
    """Right-image seed from a left-image seed by forward projection (foreground wins)."""
    h = seed_left.shape[0]
    xr = np.rint(np.arange(w)[None, :] - seed_left).astype(np.int64)
    ok = np.isfinite(seed_left) & (xr >= 0) & (xr < w)
    out = np.full(h * w, -np.inf, dtype=F32)
    rows = np.broadcast_to(np.arange(h)[:, None], (h, w))
    np.maximum.at(out, (rows[ok] * w + xr[ok]), seed_left[ok])
    out = out.reshape(h, w)
    out[~np.isfinite(out)] = np.nan
    return out


def _match_ncc(
    left,
    right,
    lo,
    hi,
    range_maps,
    *,
    window,
    min_score,
    min_std,
    lr_tolerance,
    subpixel,
    levels,
    margin,
    vertical_search,
):
    """The ``"ncc"`` matcher of :func:`stereodem.stereo.match.match_rectified` (checked
    arguments): ZNCC block matching of the rectified pair (float32 images, rows = epipolar
    lines), disparity ``x_left - x_right`` in pixels within ``lo..hi`` or, with
    ``range_maps`` (per-pixel min and max, pixels), around their midpoints (one level);
    otherwise coarse to fine over ``levels`` pyramid levels (None: :func:`_auto_levels`), each
    finer level searching ``±margin`` pixels around the coarser level's left-right checked
    seeds. Both directions are matched (the right map by flipping the pair) for the left-right
    check (``lr_tolerance`` pixels, None: none); cells below ``min_score``, failing the check
    or outside the range are NaN.

    Returns ``(disparity, score, vertical, info)``: float32 maps of the left image's grid
    (``vertical``: the row offsets found by ``vertical_search``, else None) and
    ``{"levels": levels}``.
    """
    h, w = left.shape
    flip = np.s_[:, ::-1]

    def both_ways(L, R, seedL, seedR, klo, khi, vert):
        """Left and right disparity maps at one level (right by flipping the pair)."""
        if seedL is None:
            dL, sL, vL, dR = _match_pass(
                L, R, None, klo, khi, window, min_std, subpixel, vert, back=vert == 0
            )
            if dR is None:  # with vertical search the back map is computed separately
                dRf, _, _, _ = _match_pass(
                    R[flip], L[flip], None, klo, khi, window, min_std, subpixel, vert
                )
                dR = dRf[flip]
            return dL, sL, vL, dR
        outs = []
        for ref, tgt, seed in ((L, R, seedL), (R[flip], L[flip], seedR[flip])):
            outs.append(
                _match_pass(
                    ref,
                    tgt,
                    np.ascontiguousarray(seed, dtype=F32),
                    klo,
                    khi,
                    window,
                    min_std,
                    subpixel,
                    vert,
                )
            )
        (dL, sL, vL, _), (dRf, _, _, _) = outs
        return dL, sL, vL, np.ascontiguousarray(dRf[flip])

    if range_maps is not None:
        dmin_map, dmax_map = range_maps
        seedL = (0.5 * (dmin_map + dmax_map)).astype(F32)
        half = 0.5 * (dmax_map - dmin_map)
        m = int(math.ceil(np.nanmax(half)))
        mid = float(np.nanmedian(seedL))
        seedR = _fill_seed(_forward_seed(seedL, w), mid)
        seedL = _fill_seed(seedL, mid)
        dL, sL, vL, dR = both_ways(left, right, seedL, seedR, -m, m, vertical_search)
        levels = 0
    else:
        if levels is None:
            levels = _auto_levels(lo, hi, left.shape)
        pl = build_pyramid(left, levels)
        pr = build_pyramid(right, levels)
        f = 2**levels
        clo, chi = math.floor(lo / f), math.ceil(hi / f)
        seedL = seedR = None
        # the coarse levels' seeds are always left-right checked (at least 1 px); the caller's
        # lr_tolerance (None: no check) applies to the result
        seed_tol = 1.0 if lr_tolerance is None else max(lr_tolerance, 1.0)
        for lev in range(levels, -1, -1):
            L, R = pl[lev], pr[lev]
            vert = math.ceil(vertical_search / 2**lev)
            if seedL is None:
                dL, sL, vL, dR = both_ways(L, R, None, None, clo, chi, vert)
            else:
                seedL = upsample_field(seedL, L.shape)
                seedR = upsample_field(seedR, L.shape)
                dL, sL, vL, dR = both_ways(L, R, seedL, seedR, -margin, margin, vert)
            if lev > 0:
                okL = _lr_check(dL, dR, seed_tol)
                okR = _lr_check(dR[flip], dL[flip], seed_tol)[flip]
                fb = 0.5 * (lo + hi) / 2**lev
                seedL = _fill_seed(np.where(okL & (sL >= min(min_score, 0.3)), dL, np.nan), fb)
                seedR = _fill_seed(np.where(okR, dR, np.nan), fb)
    valid = np.isfinite(dL)
    if lr_tolerance is not None:
        valid &= _lr_check(dL, dR, lr_tolerance)
    if min_score is not None:
        with np.errstate(invalid="ignore"):
            valid &= sL >= min_score
    if range_maps is not None:
        with np.errstate(invalid="ignore"):
            valid &= (dL >= range_maps[0] - 0.5) & (dL <= range_maps[1] + 0.5)
    else:
        with np.errstate(invalid="ignore"):
            valid &= (dL >= lo - 0.5) & (dL <= hi + 0.5)
    disp = np.where(valid, dL, np.nan).astype(F32)
    vert = None
    if vertical_search:
        vert = np.where(valid, vL, np.nan).astype(F32)
    return disp, sL.astype(F32), vert, {"levels": levels}
