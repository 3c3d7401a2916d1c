"""Stereo DEM with attitude-jitter correction of the second camera (ASTER 3B).

One round of the MMASTER-style correction (ASTER notes §7 item 12): a first DEM with the
nominal models, then the second camera's oscillation estimated per axis and fitted by a sum of
sines in time (:mod:`stereodem.sensor.estimation.jitter`), the second model corrected by that
time-varying attitude, and the DEM made again.

* ``roll`` (cross-track): from the matcher's residual vertical parallax, without any reference
  DEM. Tiles along the whole track (:func:`probe_tiles`) are rectified with the first DEM as
  the height guide and matched with a vertical search (:func:`measure_vertical_parallax`); each
  match's offset across its epipolar curve in the right image, divided by the roll sensitivity
  of the right model there, is a roll sample at the match's right-image acquisition time.
* ``pitch`` (along-track): from the first DEM's residuals against a reference DEM (a pitch
  moves the right image along the epipolar direction, where it reads as height).

The DEM is then made again. A roll oscillation changes the epipolar geometry within a tile,
which a tile's rectifying homography cannot follow; so the rerun matches the right image
resampled to the nominal geometry through the roll-corrected model
(:func:`resample_to_model`, the same correction in image space) with the nominal model (plus
any pitch correction), while the returned corrected model describes the original right image.
"""

from __future__ import annotations

import dataclasses
import logging

import cv2
import numpy as np
from scipy import ndimage

from stereodem.core.dem import ELLIPSOID, as_dem
from stereodem.core.errors import InputError
from stereodem.core.stats import nmad
from stereodem.sensor.estimation.jitter import (
    add_series,
    check_line_nyquist,
    check_slowest_frequency,
    cross_track_sensitivity,
    estimate_pitch_jitter,
    estimate_roll_jitter,
    fit_at_frequencies,
    roll_profile,
    with_attitude_sines,
)
from stereodem.stereo import epipolar
from stereodem.stereo.match import match_rectified
from stereodem.stereo.pipeline import PairInputs, dem_of_checked_pair, rectify_pair_tile
from stereodem.stereo.plan import plan_tiles
from stereodem.stereo.sanity import check_pair
from stereodem.stereo.settings import StereoSettings
from stereodem.stereo.sparse import distance_to_curves, epipolar_curves

log = logging.getLogger(__name__)

AXES = ("pitch", "roll")


def probe_tiles(
    left_model, right_model, settings: StereoSettings, height_range, *, tiles_across: int = 2
):
    """The tiles of the pair's tile plan in the ``tiles_across`` tile columns nearest the
    middle of the overlap: they cover the whole track (jitter is a function of time, i.e.
    of the image row) at a fraction of the cost of all tiles."""
    tiles = plan_tiles(left_model, right_model, settings.rectification, height_range)
    if not tiles:
        raise InputError("jitter: no tile of the left image overlaps the right image")
    cols = np.array(sorted({t.bounds[0] for t in tiles}), float)
    mid = 0.5 * (min(t.bounds[0] for t in tiles) + max(t.bounds[2] for t in tiles))
    centres = {c: c + 0.5 * settings.rectification.tile_size for c in cols}
    keep = sorted(cols, key=lambda c: abs(centres[c] - mid))[: max(1, int(tiles_across))]
    return [t for t in tiles if t.bounds[0] in keep]


def refine_offsets(left, right, disparity, vertical, *, window: int = 9, iterations: int = 3):
    """Sub-pixel refinement of a match ``left(u, v) ~ right(u - d, v - dv)`` by least squares
    on the image gradients (Lucas-Kanade over a ``window`` x ``window`` box, both offsets).

    The matcher's parabola through three correlation values is biased towards whole pixels
    ("pixel locking"), which shrinks a sub-pixel oscillation of the vertical offset; the
    gradient solution is unbiased to first order. Per iteration the right image is warped
    (bicubic) by the current offsets and the 2 x 2 normal equations of ``left - warped =
    -R_x dd - R_y dv`` (window means removed: offsets of radiometry do not matter) are solved
    per pixel. Returns refined ``(disparity, vertical)`` (float32, NaN where the window holds
    no data or the system is singular).
    """
    f32 = np.float32
    h, w = left.shape
    k = (int(window), int(window))
    bad_l = ~np.isfinite(left)
    L = np.nan_to_num(left).astype(f32)
    R = np.nan_to_num(right).astype(f32)
    rx = cv2.Sobel(R, cv2.CV_32F, 1, 0, ksize=1, scale=0.5)
    ry = cv2.Sobel(R, cv2.CV_32F, 0, 1, ksize=1, scale=0.5)
    uu, vv = np.meshgrid(np.arange(w, dtype=f32), np.arange(h, dtype=f32))
    dd = np.asarray(disparity, f32).copy()
    dv = np.asarray(vertical, f32).copy()
    ok = np.isfinite(dd) & np.isfinite(dv)
    lm = L - cv2.boxFilter(L, -1, k)
    for _ in range(iterations):
        mx, my = uu - np.nan_to_num(dd), vv - np.nan_to_num(dv)
        args = (cv2.INTER_CUBIC, None, cv2.BORDER_CONSTANT, np.nan)
        rw = cv2.remap(right.astype(f32), mx, my, *args)
        gx = cv2.remap(rx, mx, my, cv2.INTER_LINEAR)
        gy = cv2.remap(ry, mx, my, cv2.INTER_LINEAR)
        bad = bad_l | ~np.isfinite(rw)
        rw = np.nan_to_num(rw)
        e = lm - (rw - cv2.boxFilter(rw, -1, k))
        a = cv2.boxFilter(gx * gx, -1, k)
        b = cv2.boxFilter(gx * gy, -1, k)
        c = cv2.boxFilter(gy * gy, -1, k)
        p = cv2.boxFilter(gx * e, -1, k)
        q = cv2.boxFilter(gy * e, -1, k)
        det = a * c - b * b
        with np.errstate(divide="ignore", invalid="ignore"):
            dd -= (c * p - b * q) / det
            dv -= (a * q - b * p) / det
        ok &= cv2.boxFilter(bad.astype(f32), -1, k, normalize=False) < 0.5
        ok &= det > 1e-6 * (a + c) ** 2
    dd[~ok] = np.nan
    dv[~ok] = np.nan
    return dd, dv


def measure_vertical_parallax(
    left_image,
    right_image,
    left_model,
    right_model,
    settings,
    height_range,
    *,
    seed_dem=None,
    vertical_search: int = 2,
    tiles_across: int = 2,
    stride: int = 4,
    n_heights: int = 5,
    sensitivity_points: int = 200,
    seed: int = 0,
):
    """Residual vertical parallax of dense matches along the track.

    Each probe tile (:func:`probe_tiles`) is rectified (height range from ``seed_dem`` under
    the tile, else ``height_range``) and matched by ZNCC with a vertical search of
    ``+-vertical_search`` rows (:func:`stereodem.stereo.match.match_rectified`); every
    ``stride``-th matched pixel in each direction is mapped back to both images, and its
    right-image point's signed distance across the epipolar curve of its left point is
    measured through the models (:func:`stereodem.stereo.sparse.distance_to_curves`). The roll
    sensitivity (px/rad, :func:`~stereodem.sensor.estimation.jitter.cross_track_sensitivity`)
    is the median over ``sensitivity_points`` matches of the tile.

    Returns a dict of arrays over all matches: ``time`` (right-image acquisition time, s),
    ``cross_px``, ``sensitivity_px_per_rad``, ``col_right``, ``row_right``, plus ``tiles``
    (per-tile summaries).
    """
    rect = settings.rectification
    inputs = PairInputs(
        left_image, right_image, left_model, right_model, tuple(height_range), seed_dem=seed_dem
    )
    rng = np.random.default_rng(seed)
    out = {k: [] for k in ("time", "cross_px", "sensitivity_px_per_rad", "col_right", "row_right")}
    summaries = []
    for tile in probe_tiles(
        left_model, right_model, settings, height_range, tiles_across=tiles_across
    ):
        et, hr = rectify_pair_tile(tile, inputs, rect)
        lr, rr = et.rectify(left_image, right_image)
        if not (np.isfinite(lr).any() and np.isfinite(rr).any()):
            continue
        m = match_rectified(lr, rr, et.disparity_range, "ncc", vertical_search=vertical_search)
        disp, vert = refine_offsets(lr, rr, m.disparity, m.vertical)
        # keep refined offsets that stay within half a pixel of the matcher's
        ok = np.isfinite(disp) & np.isfinite(vert)
        with np.errstate(invalid="ignore"):
            ok &= (np.abs(disp - m.disparity) < 0.5) & (np.abs(vert - m.vertical) < 0.5)
        sub = np.zeros_like(ok)
        sub[::stride, ::stride] = ok[::stride, ::stride]
        v, u = np.nonzero(sub)
        if v.size == 0:
            continue
        d = disp[v, u].astype(float)
        dv = vert[v, u].astype(float)
        c1, r1 = epipolar.apply_map(np.linalg.inv(et.H_left), u, v)
        c2, r2 = epipolar.apply_map(np.linalg.inv(et.H_right), u - d, v - dv)
        inside = tile.contains(c1, r1)
        c1, r1, c2, r2 = c1[inside], r1[inside], c2[inside], r2[inside]
        if c1.size < 10:
            continue
        heights = np.linspace(hr[0], hr[1], n_heights)
        curves = epipolar_curves(left_model, right_model, c1, r1, heights)
        cross, _, h, normal, _ = distance_to_curves(
            np.stack([c2, r2], -1), curves, heights, extend=1e6
        )
        pick = rng.choice(c1.size, min(sensitivity_points, c1.size), replace=False)
        lon, lat = left_model.localize(c1[pick], r1[pick], h[pick])
        sens = float(
            np.nanmedian(cross_track_sensitivity(right_model, lon, lat, h[pick], normal[pick]))
        )
        out["time"].append(np.asarray(right_model.line_time(r2), float))
        out["cross_px"].append(cross)
        out["sensitivity_px_per_rad"].append(np.full(cross.size, sens))
        out["col_right"].append(c2)
        out["row_right"].append(r2)
        summaries.append(
            dict(
                tile=list(tile.bounds),
                n=int(cross.size),
                median_cross_px=float(np.nanmedian(cross)),
                sensitivity_px_per_rad=sens,
            )
        )
    if not summaries:
        raise InputError("jitter: no probe tile gave vertical-parallax matches")
    res = {k: np.concatenate(v) for k, v in out.items()}
    res["tiles"] = summaries
    return res


def resample_to_model(image, model, actual, height: float, *, row_step: int = 4, n_cols: int = 11):
    """``image`` (taken by the camera ``actual``, e.g. a jitter-corrected model) resampled to
    the geometry of ``model`` (the nominal one): output pixel ``(c, r)`` is the ground point
    ``model`` sees there (at ``height``) as ``actual`` sees it.

    The shift ``actual.project(model.localize(c, r, h)) - (c, r)`` is computed exactly every
    ``row_step`` rows at ``n_cols`` columns (an attitude oscillation is a function of the
    line time: 4 rows of 2.2 ms resolve a few Hz) and interpolated bilinearly; the image is
    sampled by cubic B-spline interpolation (``scipy.ndimage``, which reproduces linear
    intensity ramps exactly: OpenCV's bicubic kernel, Keys a = -0.75, displaces them by up to
    0.05 px depending on the sub-pixel position). NaN outside the image and next to its
    NaN cells. A roll shifts the ground by an angle, so the shift hardly depends on
    ``height``.
    """
    h_img, w_img = image.shape
    rows = np.r_[np.arange(0, h_img - 1, row_step), h_img - 1].astype(float)
    cols = np.linspace(0, w_img - 1, n_cols)
    cc, rr = np.meshgrid(cols, rows)
    lon, lat = model.localize(cc, rr, np.full(cc.shape, float(height)))
    ca, ra = actual.project(lon, lat, np.full(cc.shape, float(height)))
    grid = np.stack([np.asarray(ca) - cc, np.asarray(ra) - rr]).astype(np.float32)
    mc = np.interp(np.arange(w_img), cols, np.arange(n_cols)).astype(np.float32)
    mr = np.interp(np.arange(h_img), rows, np.arange(rows.size)).astype(np.float32)

    src = np.asarray(image, np.float32)
    void = ~np.isfinite(src)
    fill = float(np.mean(src, where=~void)) if (~void).any() else 0.0
    coef = ndimage.spline_filter(np.where(void, np.float32(fill), src), order=3, output=np.float32)
    void_f = void.astype(np.float32)
    out = np.empty((h_img, w_img), np.float32)
    for r0 in range(0, h_img, 512):
        r1 = min(h_img, r0 + 512)
        gc, gr = np.meshgrid(mc, mr[r0:r1])
        dc = cv2.remap(grid[0], gc, gr, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        dr = cv2.remap(grid[1], gc, gr, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        pc, pr = np.meshgrid(
            np.arange(w_img, dtype=np.float32), np.arange(r0, r1, dtype=np.float32)
        )
        pc += dc
        pr += dr
        blk = ndimage.map_coordinates(
            coef, [pr, pc], order=3, prefilter=False, output=np.float32, mode="nearest"
        )
        outside = (pc < -0.5) | (pc > w_img - 0.5) | (pr < -0.5) | (pr > h_img - 0.5)
        if void.any():
            outside |= (
                cv2.remap(
                    void_f,
                    pc,
                    pr,
                    cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT,
                    borderValue=1.0,
                )
                > 0
            )
        blk[outside] = np.nan
        out[r0:r1] = blk
    return out


def correct_roll_jitter(
    left_image,
    right_image,
    left_model,
    right_model,
    settings,
    dem,
    *,
    n_sines: int = 1,
    f_range=(0.2, 8.0),
    vertical_search: int = 2,
    rounds: int = 2,
):
    """Roll jitter of ``right_model`` from the residual vertical parallax, corrected.

    ``dem`` (a first stereo DEM, ellipsoidal) guides the rectification of the probe tiles.
    Each round measures the vertical parallax through the current right model
    (:func:`measure_vertical_parallax`), fits a sum of sines to the roll profile
    (:func:`~stereodem.sensor.estimation.jitter.estimate_roll_jitter`) and adds it to the
    model's attitude; later rounds re-measure through the corrected model and fit what is
    left at the first round's frequencies (linear least squares), added as phasors (a few
    per cent of the amplitude escape the first round). Returns ``(corrected model,
    SineSeries of the total correction, info)``; ``info`` holds the fit, the number of
    matches and the vertical-parallax NMAD (px) before and after each round.
    """
    lo, hi = (float(np.nanpercentile(dem.heights, p)) for p in (0.5, 99.5))

    model, total, rounds_info = right_model, None, []
    period = 8 * abs(float(right_model.line_period))
    for _ in range(max(1, int(rounds))):
        vp = measure_vertical_parallax(
            left_image,
            right_image,
            left_model,
            model,
            settings,
            (lo, hi),
            seed_dem=dem,
            vertical_search=vertical_search,
        )
        if total is None:  # periodogram + non-linear fit of the tones
            fit, _ = estimate_roll_jitter(
                vp["time"],
                vp["cross_px"],
                vp["sensitivity_px_per_rad"],
                n_sines=n_sines,
                f_range=f_range,
                bin_seconds=period,
            )
            total = fit
        else:  # later rounds: what is left, at the same frequencies
            t, roll, _ = roll_profile(
                vp["time"], vp["cross_px"], vp["sensitivity_px_per_rad"], bin_seconds=period
            )
            fit = fit_at_frequencies(t, roll, total.frequencies, t_ref=total.t_ref)
            total = add_series(total, fit)
        model = _with_fitted_sines(right_model, total, "roll", f_range)
        rounds_info.append(
            dict(
                n_matches=int(vp["cross_px"].size),
                cross_px_nmad=nmad(vp["cross_px"]),
                amplitudes_rad=fit.amplitudes.tolist(),
                frequencies_hz=fit.frequencies.tolist(),
            )
        )
    corrected = model
    info = {
        **total.to_dict(),
        "rounds": rounds_info,
        "sensitivity_px_per_rad": float(np.median(vp["sensitivity_px_per_rad"])),
    }
    return corrected, total, info


def _with_fitted_sines(model, series, axis, f_range):
    """:func:`with_attitude_sines` of a fitted ``series``, its refusal (an amplitude beyond an
    oscillation's) naming the band it was fitted over."""
    try:
        return with_attitude_sines(model, series, axis=axis)
    except InputError as err:
        raise InputError(
            f"the jitter fit over {f_range[0]:g}..{f_range[1]:g} Hz ([jitter] min_frequency, "
            f"max_frequency) found no oscillation the image can carry: {err}"
        ) from None


def dem_with_jitter_correction(
    left_image,
    right_image,
    left_model,
    right_model,
    reference=None,
    settings: StereoSettings | None = None,
    *,
    seed_dem=None,
    n_sines: int = 1,
    f_range=(0.2, 8.0),
    runner=None,
    axes=("pitch",),
    vertical_search: int = 2,
    roll_rounds: int = 2,
    left_dtype=None,
    right_dtype=None,
    points_dir=None,
    pair_id: int = 0,
):
    """``(products, corrected_right_model, fits, first_products)``; ``runner``, ``points_dir``
    and ``pair_id`` as :func:`~stereodem.stereo.pipeline.make_dem`'s (only the final DEM, the
    one made with the corrected model, writes its points). ``corrected_right_model`` describes the
    given right image (nominal model plus the fitted attitude oscillations).

    ``axes`` names the oscillations estimated: ``"roll"`` from the residual vertical parallax
    of the matches (no reference needed), ``"pitch"`` from the first DEM's residuals against
    ``reference`` (a DEM or path covering the scene). ``fits`` maps each axis to its
    :class:`~stereodem.sensor.estimation.jitter.SineSeries` (rad) and ``products.info.jitter``
    holds them per axis. The first DEM is made on ellipsoidal heights whatever
    ``settings.gridding.geoid`` says; without a height range or ``seed_dem`` the reference
    (if any) sets the tiles' height ranges. ``roll_rounds``: see :func:`correct_roll_jitter`.
    The pair is checked once, as by :func:`~stereodem.stereo.pipeline.make_dem` (``left_dtype``,
    ``right_dtype`` as there), and the checks are reported in the final products' ``info``.
    """
    axes = tuple(axes)
    if not axes or any(a not in AXES for a in axes):
        raise InputError(f"jitter axes must be among {', '.join(AXES)}, got {axes}")
    if "pitch" in axes and reference is None:
        raise InputError("pitch jitter needs a reference DEM")
    # before the first DEM: the band searched must be one the right image's lines can sample
    if hasattr(right_model, "line_time"):  # a pushbroom camera
        check_line_nyquist(
            right_model,
            f_range[1],
            "the upper frequency of the jitter band ([jitter] max_frequency)",
        )
        span = abs(
            float(right_model.line_time(right_model.height - 1)) - float(right_model.line_time(0))
        )
        check_slowest_frequency(
            f_range[0],
            span,
            f"{right_model.name}: the jitter band's lower frequency ([jitter] min_frequency)",
        )
    settings = settings or StereoSettings()
    ref = as_dem(reference) if reference is not None else None
    seed = seed_dem if seed_dem is not None or settings.rectification.height_range else ref
    first_settings = dataclasses.replace(
        settings, gridding=dataclasses.replace(settings.gridding, geoid=False)
    )
    checked = check_pair(
        left_image,
        right_image,
        left_model,
        right_model,
        settings.rectification.height_range,
        as_dem(seed) if seed is not None else None,
        left_dtype,
        right_dtype,
    )
    left_image, right_image = checked.left, checked.right
    first = dem_of_checked_pair(
        left_image,
        right_image,
        left_model,
        right_model,
        first_settings,
        seed_dem=seed,
        runner=runner,
    )
    d0 = first.dem
    if d0.vertical != ELLIPSOID:  # pragma: no cover - geoid=False above
        raise AssertionError("first DEM must be ellipsoidal")
    corrected, fits, info = right_model, {}, {}
    right_for_dem, model_for_dem = right_image, right_model
    if "roll" in axes:
        corrected, fit, info["roll"] = correct_roll_jitter(
            left_image,
            right_image,
            left_model,
            right_model,
            settings,
            d0,
            n_sines=n_sines,
            f_range=f_range,
            vertical_search=vertical_search,
            rounds=roll_rounds,
        )
        fits["roll"] = fit
        # the rerun's tiles are rectified by one homography each, which cannot follow an
        # oscillation of the epipolar geometry within a tile: the right image is resampled to
        # the nominal geometry through the corrected model instead (the same correction, in
        # image space), so that the rectified tiles carry no vertical parallax
        right_for_dem = resample_to_model(
            right_image, right_model, corrected, float(np.nanmedian(d0.heights))
        )
    if "pitch" in axes:
        fit, diag = estimate_pitch_jitter(
            d0, ref, left_model, right_model, n_sines=n_sines, f_range=f_range
        )
        corrected = _with_fitted_sines(corrected, fit, "pitch", f_range)
        model_for_dem = _with_fitted_sines(right_model, fit, "pitch", f_range)
        fits["pitch"] = fit
        info["pitch"] = {**fit.to_dict(), "sensitivity_m_per_rad": diag["sensitivity_m_per_rad"]}
    final = dem_of_checked_pair(
        left_image,
        right_for_dem,
        left_model,
        model_for_dem,
        settings,
        seed_dem=seed,
        runner=runner,
        points_dir=points_dir,
        pair_id=pair_id,
    )
    final.info.jitter = info
    checked.report(final)
    return final, corrected, fits, first
