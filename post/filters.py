"""Blunder filters for stereo DEMs and a configurable chain that reports what each removed.

Every filter is a plain function of a height grid (float, NaN voids) and, where it needs them,
the matching layers (correlation score, ray gap, a reference DEM on the same grid, the
transform and CRS for metric slopes). It returns ``(mask, reason)``: a boolean array of the
*valid* cells it would remove and a :class:`Reason` code. :class:`FilterChain` applies a list
of steps in order, sets removed cells to NaN, writes the reason into a uint8 layer and counts
what each step removed; its ``params`` are plain dicts that go into reports.

Filters (with where they come from):

* :func:`score_filter` — correlation score below a threshold (ASP ``xcorr-threshold``).
* :func:`ray_gap_filter` — ray gap above an absolute limit and/or above ``factor`` times a
  robust percentile of the gaps (ASP ``--remove-outliers-params 75 3``,
  ``--max-valid-triangulation-error``).
* :func:`local_sigma_filter` — the Ok (2005) thesis's noise test: a cell more than k σ from
  the mean of its 8 valid neighbours (k = 2 in the thesis).
* :func:`failed_neighbours_filter` — the thesis's second test: ≥ 5 of the 8 neighbours failed.
* :func:`spike_filter` — residual to a robust local surface tested against a local NMAD.
* :func:`slope_filter` — slope above a limit (degrees, metric even on lon/lat grids).
* :func:`reference_filter` — |DEM − reference − median| above a limit.
* :func:`small_patch_filter` — connected blobs (neighbours within a height jump) smaller than a
  size limit, including islands of valid cells inside voids (OpenCV ``filterSpeckles``).
"""

from __future__ import annotations

import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from enum import IntEnum

import cv2
import numpy as np
from scipy import ndimage as ndi

from stereodem.core.blocks import (
    by_rows,
    default_threads,
    each_band,
    each_fixed_band,
    percentile_of_parts,
)
from stereodem.core.errors import InputError
from stereodem.core.morphology import square_dilation
from stereodem.core.stats import NMAD_FACTOR

from . import terrain

log = logging.getLogger(__name__)


class Reason(IntEnum):
    """Why a cell was removed (the value written into the ``removed`` layer)."""

    KEPT = 0
    SCORE = 1
    RAY_GAP = 2
    LOCAL_SIGMA = 3
    FAILED_NEIGHBOURS = 4
    SPIKE = 5
    SLOPE = 6
    REFERENCE = 7
    SMALL_PATCH = 8
    CLOUD = 9  #: cloud mask (:mod:`stereodem.post.clouds`, ``filter --cloud-*``)


class EditCode(IntEnum):
    """What the post stage did to a cell, beside :class:`Reason`: the edit mask written with a
    clean DEM (``dem_edit_mask.tif``) holds a :class:`Reason` for removed cells or one of these
    (255 = outside the grid's data)."""

    BORDER_RIM = 99  #: removed: rim of the matched area (partial correlation windows)
    FILLED_IDW = 100  #: hole filled by inverse-distance weighting
    FILLED_SEED = 101  #: large hole filled from the seed DEM


_RING8 = np.array([[1, 1, 1], [1, 0, 1], [1, 1, 1]], dtype=np.float64)


def _heights(heights) -> np.ndarray:
    z = np.asarray(heights, dtype=np.float64)
    if z.ndim != 2:
        raise InputError(f"expected a 2-D height grid, got shape {z.shape}")
    return z


def _layer(layer, shape, name) -> np.ndarray:
    a = np.asarray(layer, dtype=np.float64)
    if a.shape != tuple(shape):
        raise InputError(f"{name} layer has shape {a.shape}, the DEM {tuple(shape)}")
    return a


# ----------------------------------------------------------------------------- filters


def score_filter(heights, score, *, min_score: float = 0.5):
    """Cells whose correlation score is below ``min_score`` (NaN scores are kept)."""
    z = _heights(heights)
    s = _layer(score, z.shape, "score")
    with np.errstate(invalid="ignore"):
        return np.isfinite(z) & (s < min_score), Reason.SCORE


def ray_gap_filter(
    heights,
    ray_gap,
    *,
    max_gap: float | None = None,
    percentile: float | None = 75.0,
    factor: float = 3.0,
):
    """Cells whose ray gap (m) exceeds ``max_gap`` or ``factor`` × its ``percentile``.

    Either test may be disabled with ``None``; with both, a cell failing either is removed.
    """
    z = _heights(heights)
    g = _layer(ray_gap, z.shape, "ray gap")
    valid = np.isfinite(z) & np.isfinite(g)
    mask = np.zeros(z.shape, bool)
    if max_gap is not None:
        mask |= valid & (g > max_gap)
    if percentile is not None and valid.any():
        lim = factor * float(np.percentile(g[valid], percentile))
        mask |= valid & (g > lim)
    return mask, Reason.RAY_GAP


def _ring8(a):
    """Sum of the 8 neighbours (outside = 0); call it within a row band (:func:`by_rows`)."""
    return ndi.convolve(a, _RING8, mode="constant")


def _neighbour_moments(z):
    """Count, mean and std of the valid 8-neighbours of every cell (outside = missing)."""
    v = np.isfinite(z)
    z0 = np.where(v, z, 0.0)
    n = _ring8(v.astype(np.float64))
    s1 = _ring8(z0)
    s2 = _ring8(z0 * z0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = s1 / n
        var = np.maximum(s2 / n - mean * mean, 0.0)
    return n, mean, np.sqrt(var)


def local_sigma_filter(
    heights, *, k: float = 2.0, min_deviation: float = 0.0, min_neighbours: int = 3
):
    """The Ok (2005) local test: |z − mean₈| > max(k·σ₈, ``min_deviation``).

    ``mean₈`` and ``σ₈`` are the mean and standard deviation of the valid 8-neighbours; cells
    with fewer than ``min_neighbours`` valid neighbours are not tested. The thesis used
    k = 2 and no floor; on noisy but sound terrain that removes several per cent of good cells,
    so the default chain uses a larger k and a floor in metres. Computed whole in row bands
    on threads (local within one row: the same mask as one call on the grid).
    """

    def band(z):
        n, mean, sd = _neighbour_moments(z)
        with np.errstate(invalid="ignore"):
            return (
                np.isfinite(z)
                & (n >= min_neighbours)
                & (np.abs(z - mean) > np.maximum(k * sd, min_deviation))
            )

    return by_rows(band, _heights(heights), halo=1), Reason.LOCAL_SIGMA


def failed_neighbours_filter(heights, *, min_failed: int = 5):
    """The Ok (2005) test: valid cells with ≥ ``min_failed`` void 8-neighbours (cells beyond
    the grid edge do not count as failed); in row bands on threads."""

    def band(z):
        fin = np.isfinite(z)
        return fin & (_ring8((~fin).astype(np.float64)) >= min_failed)

    return by_rows(band, _heights(heights), halo=1), Reason.FAILED_NEIGHBOURS


#: rows of the bands :func:`_fill_nearest` works in, and the rows each band reads beyond its
#: own (more than 3·√2: a void cell within 3 cells of a valid one has its nearest valid cell
#: within 4.3 cells, inside the band)
FILL_BAND_ROWS, FILL_HALO_ROWS = 256, 8


def _fill_nearest(z):
    """``z`` with the void cells within 3 cells (8-connected) of a valid one set to the height
    of their nearest valid cell (Euclidean): all that the spike filter's 5 x 5 prediction and
    7 x 7 median read. Computed in bands of :data:`FILL_BAND_ROWS` rows on the budget's
    threads (a band's distance transform sees its neighbours' rows within
    :data:`FILL_HALO_ROWS`); the bands do not depend on the threads, so neither does the
    result. Void cells farther from data get the nearest valid height of their band's rows,
    or 0 where these have none. (The whole grid's transform took 0.3-0.5 s on one core for a
    2527 x 2382 ASTER DEM; the bands 0.2 s on one, 0.12 s on two.)"""
    v = np.isfinite(z)
    if v.all():
        return z
    out = np.empty_like(z)
    rows = z.shape[0]

    def band(b):
        r0, r1 = b
        a0, a1 = max(0, r0 - FILL_HALO_ROWS), min(rows, r1 + FILL_HALO_ROWS)
        vb = v[a0:a1]
        if not vb.any():
            out[r0:r1] = 0.0
            return
        idx = ndi.distance_transform_edt(~vb, return_distances=False, return_indices=True)
        out[r0:r1] = z[a0:a1][tuple(i[r0 - a0 : r1 - a0] for i in idx)]

    each_fixed_band(band, rows, FILL_BAND_ROWS)
    return out


def _quadratic_kernel(half: int):
    """Correlation kernel giving the value at the centre of a least-squares quadratic surface
    fitted to the (2·half+1)² window without its centre cell."""
    yy, xx = np.mgrid[-half : half + 1, -half : half + 1]
    x, y = xx.ravel().astype(float), yy.ravel().astype(float)
    a = np.stack([np.ones_like(x), x, y, x * x, y * y, x * y], 1)
    w = np.ones(x.size)
    w[x.size // 2] = 0.0
    coef = np.linalg.solve(a.T @ (w[:, None] * a), (a * w[:, None]).T)
    return coef[0].reshape(2 * half + 1, 2 * half + 1)


def _nanmedian_last(t):
    """``np.nanmedian(t, axis=-1)`` (same values; NaN where a row has no finite value),
    vectorised: one sort along the last axis instead of numpy's per-row loop (NumPy's SIMD
    sort of 1024 values beats ``np.partition`` around the two middle ones: 43 vs 97 ms on the
    granule's 5900 blocks)."""
    s = np.sort(t, axis=-1)  # NaNs sort last
    n = np.count_nonzero(np.isfinite(t), axis=-1)
    lo = np.take_along_axis(s, np.maximum((n - 1) // 2, 0)[..., None], -1)[..., 0]
    hi = np.take_along_axis(s, np.maximum(n // 2, 0)[..., None], -1)[..., 0]
    with np.errstate(invalid="ignore"):
        med = np.where(n % 2 == 1, lo, (lo + hi) / 2.0)
    return np.where(n > 0, med, np.nan)


def _block_scale(r, valid, block: int):
    """Local NMAD of ``r`` in ``block``×``block`` tiles, bilinearly resampled to full size."""
    rows, cols = r.shape
    nb_r, nb_c = max(1, -(-rows // block)), max(1, -(-cols // block))
    pad = np.full((nb_r * block, nb_c * block), np.nan)
    np.copyto(pad[:rows, :cols], r, where=valid)
    blocks = pad.reshape(nb_r, block, nb_c, block)  # a view: rows of blocks first

    def nmad_of_blocks(a):  # each block alone: any split into rows of blocks gives the same
        t = a.transpose(0, 2, 1, 3).reshape(a.shape[0], nb_c, -1)  # this band's copy
        med = _nanmedian_last(t)
        dev = np.subtract(t, med[..., None], out=t)  # this band's blocks only: no other reads them
        with np.errstate(invalid="ignore"):
            return NMAD_FACTOR * _nanmedian_last(np.abs(dev, out=dev))

    def global_nmad():
        rv = r[valid]  # a copy: the global NMAD is computed in it
        np.subtract(rv, np.median(rv), out=rv)
        return NMAD_FACTOR * np.median(np.abs(rv, out=rv), overwrite_input=True)

    # with threads to spare, the global NMAD (0.1 s, serial) beside the blocks' ones
    with ThreadPoolExecutor(1, thread_name_prefix="stereodem-nmad") as ex:
        pending = ex.submit(global_nmad) if default_threads() > 1 else None
        scale = by_rows(nmad_of_blocks, blocks, halo=0, min_rows=4)
        glob = pending.result() if pending is not None else global_nmad()
    scale = np.where(np.isfinite(scale), scale, glob).astype(np.float32)
    if scale.shape == (1, 1):
        return np.full(r.shape, float(scale[0, 0]))
    return cv2.resize(scale, (cols, rows), interpolation=cv2.INTER_LINEAR).astype(np.float64)


def _correlate_at(a, rows, cols, kern):
    """``ndi.correlate(a, kern, mode="nearest")`` at the cells ``(rows, cols)`` only (1-D): the
    same float64 values, because SciPy sums weight × value over the kernel's non-zero weights
    (``|w| > eps``) in C order starting from 0.0, as this does (tested bit for bit)."""
    h, w = a.shape
    hr, hc = kern.shape[0] // 2, kern.shape[1] // 2
    out = np.zeros(rows.size)
    for (dy, dx), wt in np.ndenumerate(kern):
        if abs(wt) > np.finfo(np.float64).eps:
            r = np.clip(rows + (dy - hr), 0, h - 1)
            c = np.clip(cols + (dx - hc), 0, w - 1)
            out += a[r, c] * wt
    return out


def _median_at(z, rows, cols, size: int):
    """``ndi.median_filter(z, size, mode="nearest")`` evaluated only at the cells ``(rows,
    cols)`` (same values, 1-D): each cell's window gathered with its indices clipped to the
    grid (the nearest-value edge), without padding the grid."""
    half = size // 2
    off = np.arange(-half, half + 1)
    out = np.empty(rows.size)
    h, w = z.shape
    for a in range(0, rows.size, 65536):  # bounded working memory
        r = np.clip(rows[a : a + 65536, None, None] + off[None, :, None], 0, h - 1)
        c = np.clip(cols[a : a + 65536, None, None] + off[None, None, :], 0, w - 1)
        out[a : a + 65536] = np.median(z[r, c].reshape(r.shape[0], -1), axis=1)
    return out


def spike_filter(
    heights,
    *,
    k: float = 5.0,
    min_deviation: float = 5.0,
    window: int = 5,
    median_size: int = 7,
    block: int = 32,
    iterations: int = 4,
):
    """Spikes and pits: residual to a local surface fitted around each cell, against a local
    robust scale.

    1. Every cell is predicted by a least-squares quadratic surface fitted to its
       ``window``×``window`` neighbourhood without itself (a fixed linear kernel);
       ``r = z − prediction`` (voids are first filled with the nearest valid height).
    2. The scale of ``r`` is its NMAD in ``block``-sized tiles, resampled bilinearly (so rough
       mountains get a looser limit than flat plains); a cell is flagged if
       |r| > max(k · scale, ``min_deviation``).
    3. Flagged cells are replaced by a ``median_size`` median in a working copy and the
       prediction is repeated (``iterations`` times), so that blunders do not spoil the
       prediction of their neighbours and clumps are peeled from their edges; the cells
       flagged in the last pass are removed.
    """
    z = _heights(heights)
    valid = np.isfinite(z)
    if valid.sum() < 9:
        return np.zeros(z.shape, bool), Reason.SPIKE
    zf = _fill_nearest(z)
    kern = _quadratic_kernel(window // 2)

    def predict(a):  # the quadratic-surface prediction, in row bands
        return by_rows(lambda b: ndi.correlate(b, kern, mode="nearest"), a, halo=window // 2)

    r = zf - predict(zf)
    limit = np.maximum(k * _block_scale(r, valid, block), min_deviation)
    flag = valid & (np.abs(r) > limit)
    del r
    first = flag  # the flags of every cell whose window no replaced cell reaches
    work = replaced = None
    for _ in range(max(0, iterations - 1)):
        if not flag.any():
            break
        # replaced cells take the median of the filled heights, computed there as they are
        # added (a cell once replaced stays replaced)
        todo = flag if replaced is None else flag & ~replaced
        rr, cc = np.nonzero(todo)
        if work is None:
            work = zf.copy()
        work[rr, cc] = _median_at(zf, rr, cc, median_size)
        replaced = flag if replaced is None else replaced | flag
        # the prediction changes only where the window reaches a replaced cell: predicted
        # again there (the values the whole grid's correlation gives), kept elsewhere
        ar, ac = np.nonzero(square_dilation(replaced, kern.shape[0]))
        new = first.copy()
        with np.errstate(invalid="ignore"):
            again = np.abs(zf[ar, ac] - _correlate_at(work, ar, ac, kern)) > limit[ar, ac]
        new[ar, ac] = valid[ar, ac] & again
        if np.array_equal(new, flag):
            break
        flag = new
    return flag, Reason.SPIKE


def slope_filter(heights, transform, crs, *, max_slope: float = 70.0):
    """Cells whose slope (degrees, central differences in metres) exceeds ``max_slope``."""
    z = _heights(heights)
    s = terrain.slope_deg(z, transform, crs)
    with np.errstate(invalid="ignore"):
        return np.isfinite(z) & (s > max_slope), Reason.SLOPE


def reference_filter(heights, reference, *, max_diff: float = 100.0, centre: bool = True):
    """Cells with |z − reference − c| > ``max_diff`` (m), c the median difference when
    ``centre`` (so a datum offset does not remove the whole DEM), else 0. The reference must
    be on the same grid and vertical reference."""
    z = _heights(heights)
    ref = _layer(reference, z.shape, "reference")
    dh = z - ref
    ok = np.isfinite(dh)
    c = float(np.median(dh[ok])) if (centre and ok.any()) else 0.0
    with np.errstate(invalid="ignore"):
        return ok & (np.abs(dh - c) > max_diff), Reason.REFERENCE


def small_patch_filter(
    heights,
    *,
    max_size: int = 10,
    max_jump: float | None = None,
    jump_percentile: float = 99.0,
    jump_factor: float = 2.0,
    min_jump: float = 10.0,
):
    """Blobs of fewer than ``max_size`` cells, where a blob is a 4-connected set of valid
    cells whose neighbours differ by at most ``max_jump`` metres.

    This removes small valid islands inside voids and small clumps standing off the terrain.
    ``max_jump`` defaults to ``jump_factor`` × the ``jump_percentile`` of the neighbour height
    differences (at least ``min_jump``), so it adapts to the relief and the grid spacing.
    Implemented with OpenCV's ``filterSpeckles`` on heights quantised to int16, in row bands
    on the budget's threads (each with ``max_size`` + 1 rows of halo: the same blobs as on the
    whole grid). The jump percentile is NumPy's linear one, computed in float64 from the
    exact order statistics (:func:`stereodem.core.blocks.percentile_of_parts`).
    """
    z = _heights(heights)
    valid = np.isfinite(z)
    if not valid.any():
        return np.zeros(z.shape, bool), Reason.SMALL_PATCH
    rows = z.shape[0]

    need_jumps = max_jump is None

    def jumps_and_range(band):  # a band's finite jumps (to the right, to the row below)
        r0, r1 = band
        zb = z[r0:r1]
        fin = zb[np.isfinite(zb)]
        span = (fin.min(), fin.max()) if fin.size else (np.inf, -np.inf)
        if not need_jumps:
            return (), span
        jx = np.abs(np.diff(zb, axis=1))
        jy = np.abs(np.diff(z[r0 : min(rows, r1 + 1)], axis=0))
        return (jx[np.isfinite(jx)], jy[np.isfinite(jy)]), span

    # on the budget's threads: a percentile of all the jumps, a min and a max, whatever the
    # bands (the same numbers as on the whole grid)
    parts = each_band(jumps_and_range, rows)
    if need_jumps:
        jumps = [a for js, _ in parts for a in js]
        max_jump = (
            max(min_jump, jump_factor * percentile_of_parts(jumps, jump_percentile))
            if any(a.size for a in jumps)
            else min_jump
        )
        del jumps
    lo = float(min(span[0] for _, span in parts))
    hi = float(max(span[1] for _, span in parts))
    del parts
    q = max((hi - lo) / 60000.0, max_jump / 30000.0, 1e-3)  # metres per quantum
    max_diff = int(np.floor(max_jump / q))

    def speckles(zb):  # a band (and its halo) quantised, its blobs of <= max_size cells cleared
        vb = np.isfinite(zb)
        out = np.full(zb.shape, -32768, dtype=np.int16)
        out[vb] = np.round((zb[vb] - lo) / q - 30000.0).astype(np.int16)
        cv2.filterSpeckles(out, -32768, int(max_size), max_diff)
        return out

    # a blob of at most max_size cells lies within max_size rows of each of its cells, and a
    # larger one reaching out of a band's window has more than max_size cells inside it: with
    # that halo, each band finds the blobs the whole grid has (exact, tested)
    out = by_rows(speckles, z, halo=int(max_size) + 1)
    return valid & (out == -32768), Reason.SMALL_PATCH


# ----------------------------------------------------------------------------- chain


@dataclass
class FilterStep:
    """One step of a :class:`FilterChain`: a filter name and its keyword options.

    ``name`` is one of :data:`FILTERS`' keys (``"score"``, ``"ray_gap"``, ``"local_sigma"``,
    ``"failed_neighbours"``, ``"spike"``, ``"slope"``, ``"reference"``, ``"small_patch"``).
    """

    name: str
    params: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.name not in FILTERS:
            raise InputError(f"unknown filter {self.name!r}; choose from {sorted(FILTERS)}")


@dataclass
class FilterResult:
    """Output of :meth:`FilterChain.apply`.

    Attributes
    ----------
    heights : ndarray float32, NaN where voids or removed.
    removed : ndarray uint8, the :class:`Reason` of each removed cell (0 = kept or void).
    report : list of dict, one per step: ``step``, ``reason``, ``params``, ``removed`` (count),
        ``removed_pct`` (of the cells valid at the start), or ``skipped`` with why.
    """

    heights: np.ndarray
    removed: np.ndarray
    report: list

    @property
    def removed_mask(self):
        return self.removed > 0


def _run_step(step, z, layers):
    name, p = step.name, step.params
    if name == "score":
        if layers.get("score") is None:
            return None, "no score layer"
        return score_filter(z, layers["score"], **p)
    if name == "ray_gap":
        if layers.get("ray_gap") is None:
            return None, "no ray-gap layer"
        return ray_gap_filter(z, layers["ray_gap"], **p)
    if name == "reference":
        if layers.get("reference") is None:
            return None, "no reference DEM"
        return reference_filter(z, layers["reference"], **p)
    if name == "slope":
        if layers.get("transform") is None or layers.get("crs") is None:
            return None, "no transform/CRS for metric slopes"
        return slope_filter(z, layers["transform"], layers["crs"], **p)
    return FILTERS[name](z, **p)


FILTERS = {
    "score": score_filter,
    "ray_gap": ray_gap_filter,
    "local_sigma": local_sigma_filter,
    "failed_neighbours": failed_neighbours_filter,
    "spike": spike_filter,
    "slope": slope_filter,
    "reference": reference_filter,
    "small_patch": small_patch_filter,
}


class FilterChain:
    """An ordered list of :class:`FilterStep` applied one after the other.

    Steps that need a layer that is not given (score, ray gap, reference, transform/CRS) are
    skipped and say so in the report. Each step sees the DEM as left by the previous ones.
    """

    def __init__(self, steps):
        self.steps = [
            s
            if isinstance(s, FilterStep)
            else FilterStep(*s)
            if isinstance(s, tuple)
            else FilterStep(**s)
            for s in steps
        ]

    @property
    def params(self) -> list:
        return [{"step": s.name, "params": dict(s.params)} for s in self.steps]

    def apply(
        self, heights, *, score=None, ray_gap=None, reference=None, transform=None, crs=None
    ) -> FilterResult:
        """Run the chain on ``heights`` (2-D, NaN voids) or a :class:`stereodem.core.dem.DEM` (whose
        transform and CRS are then used)."""
        if hasattr(heights, "heights") and hasattr(heights, "transform"):
            transform = transform or heights.transform
            crs = crs or heights.crs
            heights = heights.heights
        z = _heights(heights).copy()
        n0 = int(np.isfinite(z).sum())
        removed = np.zeros(z.shape, np.uint8)
        layers = dict(
            score=score, ray_gap=ray_gap, reference=reference, transform=transform, crs=crs
        )
        report = []
        for step in self.steps:
            mask, reason = _run_step(step, z, layers)
            entry = {"step": step.name, "params": dict(step.params)}
            if mask is None:
                entry["skipped"] = reason
                log.info("filter %s skipped: %s", step.name, reason)
            else:
                mask &= np.isfinite(z)
                n = int(mask.sum())
                z[mask] = np.nan
                removed[mask] = int(reason)
                entry.update(
                    reason=int(reason),
                    reason_name=Reason(reason).name.lower(),
                    removed=n,
                    removed_pct=100.0 * n / n0 if n0 else 0.0,
                )
                log.info("filter %s removed %d cells (%.3f %%)", step.name, n, entry["removed_pct"])
            report.append(entry)
        return FilterResult(z.astype(np.float32), removed, report)


def default_chain(*, thesis: bool = False) -> FilterChain:
    """The default blunder chain for stereo DEMs.

    Score (< 0.5) and ray-gap (> 3 × P75) steps run when those layers are given. Then spikes
    (k = 5 local NMADs, at least 5 m), small patches (< 10 cells), the Ok local test with k = 3
    and a 10 m floor, and the ≥ 5-failed-neighbours test. ``thesis=True`` uses the thesis's
    own k = 2 without a floor.
    """
    local = {"k": 2.0} if thesis else {"k": 3.0, "min_deviation": 10.0}
    return FilterChain(
        [
            FilterStep("score", {"min_score": 0.5}),
            FilterStep("ray_gap", {"percentile": 75.0, "factor": 3.0}),
            FilterStep("spike", {"k": 5.0, "min_deviation": 5.0}),
            FilterStep("small_patch", {"max_size": 10}),
            FilterStep("local_sigma", local),
            FilterStep("failed_neighbours", {"min_failed": 5}),
        ]
    )


def border_rim(heights, cells: int) -> np.ndarray:
    """Valid cells within ``cells`` cells (a square neighbourhood) of a void or of the grid's
    edge: the rim along the border of the overlap, where matches used partial windows
    (removed as :attr:`EditCode.BORDER_RIM`). ``heights``: the stereo DEM as matched (the
    pipeline takes the rim of the matched area, not of the holes its blunder filters make)."""
    valid = np.isfinite(heights)
    cells = int(cells)
    if cells <= 64:  # OpenCV's erosion (0.01-0.07 s on 5000^2 cells up to here)
        k = 2 * cells + 1
        kept = cv2.erode(valid.astype(np.uint8), np.ones((k, k), np.uint8), borderValue=0)
        return valid & (kept == 0)
    # wider: the chessboard distance of each valid cell to the nearest void, the outside
    # counted as void, the same erosion at any width (its kernel grew with ``cells``:
    # 99999999999 was a ValueError)
    padded = np.pad(valid.astype(np.uint8), 1)
    distance = cv2.distanceTransform(padded, cv2.DIST_C, 3)[1:-1, 1:-1]
    return valid & (distance <= cells)
