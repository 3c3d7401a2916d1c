"""N-view DEMs: which pairs of N images to match, and the fusion of their DEMs per cell.

s2p and CARS make an N-view DSM from pairs: every pair is matched and intersected on its own
(here :func:`stereodem.stereo.pipeline.make_dem`, unchanged), on one common output lattice,
and the pair DEMs are then fused cell by cell. This module holds the two steps that are not
pair stereo:

* :func:`choose_pairs` — a pair is matched when the two images' footprints overlap
  (intersection over the smaller footprint, at a height inside the terrain's range) by at
  least ``min_overlap`` and its base-to-height ratio lies in ``[min_base_to_height,
  max_base_to_height]`` (too small a base gives noisy heights, too large one occlusions
  and poor correlation). Images in no chosen pair are named and skipped.
* :func:`fuse_dems` — per cell, the pair heights are compared with their median; a pair
  height further than ``k`` x max(its pair's σ, the cell's NMAD across pairs) from the
  median is rejected (the pair disagrees: a blunder, an occlusion seen by one pair only),
  and the rest are averaged with weights 1/σ² (``method="weighted"``, the default) or
  their median is kept (``method="median"``). σ of a pair is its a-priori height precision
  ``sigma_px x GSD / (B/H)`` (m): the matching error of ``sigma_px`` pixels turned into
  height by the pair's base.

Layers of the fused DEM (:class:`FusedDEM`, a :class:`~stereodem.core.dem.DEM` with its layers
plus ``nmad``): ``heights``; ``count``, the pair heights fused in the cell (after rejection);
``nmad``, the NMAD (m) of all pair heights of the cell about their median (NaN with fewer than two),
the pairs' agreement; ``sigma``, the σ (m) of the fused height: the formal σ of the weighted mean of
the kept heights, ``1 / sqrt(sum w)``, times ``sqrt(chi2 / (n - 1))`` when the kept heights scatter
more than their σ say (n ≥ 2); ``score`` and ``raygap``, the weighted means of the kept pairs'
layers. Written as a DEM's files (:meth:`stereodem.core.dem.DEM.write`: ``dem.tif``, ``count.tif``,
``score.tif``, ``raygap.tif``, ``dem_sigma_vertical.tif``) plus ``nmad.tif``.

Memory: the fusion holds the pair DEMs on the common lattice, 3 float32 layers per pair
(height, score, ray gap): 12 bytes x pairs x cells, and at its peak about as much again in
float32 temporaries plus the float64 temporaries of the per-cell NMAD (16 bytes x pairs x
cells), and the per-pair rejection mask kept with the result (1 byte x pairs x cells): about
40 bytes x pairs x cells (e.g. 3 pairs on a 10 000² lattice: 12 GB; a coarser
``--res`` or fewer pairs for larger scenes).
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass, field
from itertools import combinations
from pathlib import Path

import numpy as np
from affine import Affine
from shapely.geometry import Polygon

from stereodem.core import geodesy
from stereodem.core.dem import DEM
from stereodem.core.errors import InputError
from stereodem.core.grid import MapGrid
from stereodem.core.raster import write_geotiff
from stereodem.core.stats import nanmedian
from stereodem.core.stats import nmad as nmad_of

from .plan import base_to_height
from .settings import FUSION_ADJUST, FUSION_METHODS, FusionAdjust, FusionMethod

log = logging.getLogger(__name__)

__all__ = [
    "FusionSettings",
    "PairCandidate",
    "PairPlan",
    "choose_pairs",
    "union_grid",
    "on_grid",
    "FusedDEM",
    "fuse_dems",
    "pair_sigma",
]

#: default rejection factor: a pair height further than K x max(σ, NMAD) from the cell's median
REJECT_K = 3.0
#: default matching precision (pixels) behind each pair's a-priori height σ
SIGMA_PX = 0.3


@dataclass
class FusionSettings:
    """N-view DEMs: the pairs matched (:func:`choose_pairs`) and their fusion (:func:`fuse_dems`).

    Attributes
    ----------
    method : {"weighted", "median"}
        The kept pair heights' σ-weighted mean, or their median.
    reject_k : float
        A pair height further than ``reject_k`` x max(pair σ, cell NMAD) from the cell's median
        is rejected.
    sigma_px : float
        Matching precision (pixels) behind each pair's a-priori height σ.
    min_overlap : float
        Smallest footprint overlap (intersection / smaller footprint) of a matched pair.
    min_base_to_height, max_base_to_height : float
        Usable base-to-height range of a matched pair.
    max_pairs : int, optional
        At most this many pairs (the best overlap x base first); default all usable pairs.
    adjust : {"auto", "always", "never"}
        With three or more images, bring their models into agreement first
        (:func:`stereodem.stereo.ties.agree_models`: tie points seen in several images, bundle
        adjustment of image-space shifts): ``"auto"`` keeps the adjusted models when they cut
        the ties' reprojection RMS by ``adjust_min_gain`` or more.
    adjust_min_gain : float
        Fraction by which the adjustment must reduce the reprojection RMS to be kept (auto).
    """

    method: FusionMethod = "weighted"
    reject_k: float = REJECT_K
    sigma_px: float = SIGMA_PX
    min_overlap: float = 0.2
    min_base_to_height: float = 0.05
    max_base_to_height: float = 1.5
    max_pairs: int | None = None
    adjust: FusionAdjust = "auto"
    adjust_min_gain: float = 0.1

    def problems(self) -> list:
        """What is out of range (messages naming the key); empty when the settings are usable."""
        out = []
        if self.method not in FUSION_METHODS:
            out.append(
                f"method must be {' or '.join(map(repr, FUSION_METHODS))}, got {self.method!r}"
            )
        if not self.reject_k > 0:
            out.append(f"reject_k must be positive, got {self.reject_k}")
        if not self.sigma_px > 0:
            out.append(f"sigma_px must be positive, got {self.sigma_px}")
        if not 0.0 < self.min_overlap <= 1.0:
            out.append(f"min_overlap must be in (0, 1], got {self.min_overlap}")
        if not 0.0 < self.min_base_to_height < self.max_base_to_height:
            out.append(
                "min_base_to_height must be positive and below max_base_to_height, got "
                f"{self.min_base_to_height} / {self.max_base_to_height}"
            )
        if self.adjust not in FUSION_ADJUST:
            out.append(f"adjust must be {', '.join(map(repr, FUSION_ADJUST))}, got {self.adjust!r}")
        if not 0.0 <= self.adjust_min_gain < 1.0:
            out.append(f"adjust_min_gain must be in [0, 1), got {self.adjust_min_gain}")
        if self.max_pairs is not None and self.max_pairs < 1:
            out.append(f"max_pairs must be at least 1, got {self.max_pairs}")
        return out


@dataclass
class PairCandidate:
    """One pair of images ``(i, j)`` (indices into the job's image list; ``i`` is the left,
    reference image): footprint overlap (intersection over the smaller footprint, 0-1),
    base-to-height ratio, whether it is matched, and why (or why not)."""

    i: int
    j: int
    overlap: float
    base_to_height: float
    selected: bool = False
    reason: str = ""

    def to_dict(self, names=None) -> dict:
        d = dict(
            left=self.i,
            right=self.j,
            overlap=round(self.overlap, 4),
            base_to_height=round(self.base_to_height, 4),
            selected=self.selected,
            reason=self.reason,
        )
        if names is not None:
            d.update(left_name=str(names[self.i]), right_name=str(names[self.j]))
        return d


@dataclass
class PairPlan:
    """:func:`choose_pairs`'s answer: every candidate pair, the chosen ones (in order), and
    the images left out ``{index: reason}``."""

    candidates: list
    skipped: dict = field(default_factory=dict)

    @property
    def pairs(self) -> list:
        return [c for c in self.candidates if c.selected]

    @property
    def ranked(self) -> list:
        """The chosen pairs, the strongest geometry first (:func:`pair_rank`)."""
        return sorted(self.pairs, key=pair_rank)

    def to_dict(self, names=None) -> dict:
        return dict(
            pairs=[c.to_dict(names) for c in self.candidates],
            skipped_images=[
                dict(index=k, name=str(names[k]) if names is not None else None, reason=v)
                for k, v in sorted(self.skipped.items())
            ],
        )


def _footprints(models, height, crs):
    out = []
    for m in models:
        lon, lat = m.footprint(height)
        x, y = geodesy.lonlat_to_crs(np.asarray(lon, float), np.asarray(lat, float), crs)
        poly = Polygon(np.column_stack([x, y]))
        out.append(poly if poly.is_valid else poly.buffer(0))
    return out


def pair_rank(c: PairCandidate) -> float:
    """Sort key of pairs, best first: overlap x min(B/H, 0.6), negated (a base beyond ~0.6
    brings more occlusion than precision)."""
    return -c.overlap * min(c.base_to_height, 0.6)


def choose_pairs(
    models,
    height: float,
    *,
    min_overlap: float = 0.2,
    min_base_to_height: float = 0.05,
    max_base_to_height: float = 1.5,
    max_pairs: int | None = None,
    names=None,
) -> PairPlan:
    """The pairs of ``models`` to match for an N-view DEM.

    Parameters
    ----------
    models : list of SensorModel
        The images' models (at least two).
    height : float
        Ellipsoidal height (m) at which footprints and bases are compared (the terrain's middle).
    min_overlap : float
        Smallest footprint overlap (intersection / smaller footprint area) of a matched pair.
    min_base_to_height, max_base_to_height : float
        Usable base-to-height range (:func:`stereodem.stereo.plan.base_to_height`).
    max_pairs : int, optional
        Keep at most this many pairs, the largest ``overlap x min(B/H, 0.6)`` first (a base
        beyond ~0.6 brings more occlusion than precision); default all usable pairs.
    names : list, optional
        Image names for the log messages.

    Returns
    -------
    PairPlan
        Every pair considered (overlapping pairs in the order ``(0, 1), (0, 2), ...``) and the
        images left out. Raises :class:`InputError` when no pair is usable.
    """
    n = len(models)
    names = list(names) if names is not None else [f"image {k}" for k in range(n)]
    if n < 2:
        raise InputError(f"an N-view DEM needs at least two images, got {n}")
    crs = geodesy.utm_crs(*models[0].center_lonlat(height))
    feet = _footprints(models, height, crs)
    cands = []
    for i, j in combinations(range(n), 2):
        small = min(feet[i].area, feet[j].area)
        ov = float(feet[i].intersection(feet[j]).area / small) if small > 0 else 0.0
        if ov <= 0.0:
            continue
        try:
            bh = base_to_height(models[i], models[j], height)
        except InputError:
            bh = float("nan")
        c = PairCandidate(i, j, ov, bh)
        if ov < min_overlap:
            c.reason = f"overlap {100 * ov:.0f} % < {100 * min_overlap:.0f} %"
        elif not bh >= min_base_to_height:
            c.reason = f"base-to-height {bh:.3f} < {min_base_to_height:g} (too small a base)"
        elif bh > max_base_to_height:
            c.reason = f"base-to-height {bh:.3f} > {max_base_to_height:g} (too wide a base)"
        else:
            c.selected = True
            c.reason = f"overlap {100 * ov:.0f} %, base-to-height {bh:.3f}"
        cands.append(c)
    usable = sorted((c for c in cands if c.selected), key=pair_rank)
    if max_pairs is not None:
        for c in usable[max_pairs:]:
            c.selected = False
            c.reason += f"; not among the best {max_pairs} pair(s)"
    skipped = {}
    for k in range(n):
        mine = [c for c in cands if k in (c.i, c.j)]
        if any(c.selected for c in mine):
            continue
        if not any(c.overlap >= min_overlap for c in mine):
            skipped[k] = "overlaps no other image"
        else:
            skipped[k] = "no pair with a usable base-to-height ratio"
        log.warning("%s: %s; skipped", names[k], skipped[k])
    plan = PairPlan(cands, skipped)
    if not plan.pairs:
        raise InputError(
            "no usable pair among the images: "
            + "; ".join(f"{names[k]}: {why}" for k, why in sorted(skipped.items()))
        )
    return plan


def pair_sigma(gsd_m: float, base_to_height_ratio: float, sigma_px: float = SIGMA_PX) -> float:
    """A-priori height σ (m) of a pair: ``sigma_px`` pixels of matching error at GSD
    ``gsd_m`` (m) turned into height by the base-to-height ratio."""
    return float(sigma_px * gsd_m / base_to_height_ratio)


def union_grid(grids) -> MapGrid:
    """The smallest lattice holding every grid of ``grids`` (one CRS, one posting, cell
    edges on one lattice: the grids of pair DEMs made with the same CRS and posting)."""
    g0 = grids[0]
    p = g0.posting
    for g in grids[1:]:
        if g.crs != g0.crs or not np.isclose(g.posting, p, rtol=1e-9, atol=0):
            raise InputError("pair DEMs on different CRSs or postings cannot be fused")
    x0 = min(g.transform.c for g in grids)
    y1 = max(g.transform.f for g in grids)
    x1 = max(g.transform.c + g.width * p for g in grids)
    y0 = min(g.transform.f - g.height * p for g in grids)
    cols, rows = int(round((x1 - x0) / p)), int(round((y1 - y0) / p))
    return MapGrid(Affine(p, 0.0, x0, 0.0, -p, y1), cols, rows, g0.crs)


def on_grid(array, grid: MapGrid, target: MapGrid, fill=np.nan) -> np.ndarray:
    """``array`` (on ``grid``) pasted into ``target``, a lattice with the same cells
    (offsets a whole number of cells; :class:`InputError` otherwise)."""
    p = target.posting
    dc = (grid.transform.c - target.transform.c) / p
    dr = (target.transform.f - grid.transform.f) / p
    c0, r0 = int(round(dc)), int(round(dr))
    if abs(dc - c0) > 1e-6 or abs(dr - r0) > 1e-6:
        raise InputError(
            f"grid offset ({dc:.4f}, {dr:.4f}) cells is not whole: the pair DEMs "
            "are not on one lattice"
        )
    out = np.full(target.shape, fill, dtype=np.asarray(array).dtype)
    rs, cs = (
        slice(max(r0, 0), min(r0 + grid.height, target.height)),
        slice(max(c0, 0), min(c0 + grid.width, target.width)),
    )
    out[rs, cs] = array[rs.start - r0 : rs.stop - r0, cs.start - c0 : cs.stop - c0]
    return out


#: band description of a fused DEM's ``count.tif`` (a pair DEM's counts points: core.dem.LAYERS)
COUNT_DESCRIPTION = "stereo pairs per cell (pair heights fused, after rejection)"


@dataclass
class FusedDEM:
    """A DEM fused from pair DEMs on one lattice (layers in the module docstring).

    ``dem``: the fused heights as a :class:`~stereodem.core.dem.DEM` with its ``count`` (pair
    heights fused per cell), ``sigma``, ``score`` and ``ray_gap`` layers; ``nmad``: the pairs'
    spread per cell (m); ``pairs``: per pair, its σ (m) and its agreement with the fused DEM
    (median and NMAD of pair - fused, cells kept and rejected); ``rejected``: bool
    ``(pairs, rows, cols)``, True where the pair had a height that the rejection rule removed
    (the point cloud's :data:`~stereodem.stereo.pointcloud.FUSION_REJECTED` points)."""

    dem: DEM
    nmad: np.ndarray
    method: str = "weighted"
    pairs: list = field(default_factory=list)
    rejected: np.ndarray | None = None

    heights = property(lambda self: self.dem.heights)
    count = property(lambda self: self.dem.count)
    sigma = property(lambda self: self.dem.sigma)
    score = property(lambda self: self.dem.score)
    ray_gap = property(lambda self: self.dem.ray_gap)
    grid = property(lambda self: self.dem.grid)
    transform = property(lambda self: self.dem.transform)
    crs = property(lambda self: self.dem.crs)
    vertical = property(lambda self: self.dem.vertical)

    def prepare_write(self, path, *, overwrite=False, creation_options=None, threads=1):
        """The writes of :meth:`write`, prepared now (layers copied), run by the returned
        callable (e.g. on a :class:`stereodem.pipeline.job.BackgroundWriter`)."""
        nmad = functools.partial(
            write_geotiff,
            Path(path).with_name("nmad.tif"),
            self.nmad.astype(np.float32),
            self.dem.transform,
            self.dem.crs,
            np.nan,
            descriptions=["NMAD of the pair heights about their median"],
            units=["metre"],
            overwrite=overwrite,
        )
        return self.dem.prepare_write(
            path,
            overwrite=overwrite,
            creation_options=creation_options,
            layer_descriptions={"count": COUNT_DESCRIPTION},
            threads=threads,
            more={"nmad": nmad},
        )

    def write(self, path, *, overwrite=False, creation_options=None, threads=1) -> dict:
        """Write the fused DEM at ``path`` (``dem.tif``) with its layers beside it
        (:meth:`stereodem.core.dem.DEM.write`: ``count.tif``, ``score.tif``, ``raygap.tif``,
        ``<stem>_sigma_vertical.tif``) and ``nmad.tif``; COGs, written atomically, ``threads``
        files at a time (:meth:`stereodem.core.dem.DEM.prepare_write`). Returns their paths by
        layer."""
        return self.prepare_write(
            path, overwrite=overwrite, creation_options=creation_options, threads=threads
        )()


def fuse_dems(
    dems, sigmas, *, method: str = "weighted", k: float = REJECT_K, grid: MapGrid | None = None
) -> FusedDEM:
    """Fuse pair DEMs cell by cell (see the module docstring).

    Parameters
    ----------
    dems : list of DEM
        The pair DEMs (with ``score`` and ``ray_gap`` layers): one CRS, posting and vertical
        reference, lattices offset by whole cells.
    sigmas : list of float
        Each pair's a-priori height σ (m, :func:`pair_sigma`).
    method : {"weighted", "median"}
        The kept heights' σ-weighted mean, or their median.
    k : float
        Rejection factor.
    grid : MapGrid, optional
        The output lattice (default the union of the pair DEMs' grids).
    """
    if method not in FUSION_METHODS:
        raise InputError(f"unknown fusion method {method!r} ({' or '.join(FUSION_METHODS)})")
    if not dems:
        raise InputError("no pair DEM to fuse")
    if len(sigmas) != len(dems) or not all(np.isfinite(s) and s > 0 for s in sigmas):
        raise InputError(f"one positive σ per pair DEM is needed, got {list(sigmas)}")
    verticals = {d.vertical for d in dems}
    if len(verticals) > 1:
        raise InputError(f"pair DEMs on different vertical references {sorted(verticals)}")
    grid = grid or union_grid([d.grid for d in dems])
    H = np.stack([on_grid(d.heights.astype(np.float32), d.grid, grid) for d in dems])
    S = np.stack([on_grid(d.score.astype(np.float32), d.grid, grid) for d in dems])
    G = np.stack([on_grid(d.ray_gap.astype(np.float32), d.grid, grid) for d in dems])
    sig = np.asarray(sigmas, np.float32)[:, None, None]
    valid = np.isfinite(H)
    n_valid = valid.sum(axis=0)
    med = nanmedian(H, axis=0)
    dev = np.abs(H - med)
    nmad = np.where(n_valid >= 2, nmad_of(H, axis=0), np.nan).astype(np.float32)
    tol = k * np.maximum(sig, np.nan_to_num(nmad, nan=0.0)[None])
    keep = valid & (dev <= tol)
    w = np.where(keep, 1.0 / sig**2, 0.0).astype(np.float32)
    sw = w.sum(axis=0)
    count = keep.sum(axis=0).astype(np.int32)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = (w * np.where(keep, H, 0.0)).sum(axis=0) / sw
        if method == "median":
            fused = nanmedian(np.where(keep, H, np.nan), axis=0)
        else:
            fused = mean
        chi2 = (w * np.where(keep, H - mean, 0.0) ** 2).sum(axis=0)
        scale = np.where(count >= 2, np.sqrt(np.maximum(1.0, chi2 / np.maximum(count - 1, 1))), 1.0)
        sigma = np.where(count > 0, scale / np.sqrt(sw), np.nan)
        ws, wg = w * np.isfinite(S), w * np.isfinite(G)
        score = np.where(ws.sum(0) > 0, (ws * np.nan_to_num(S)).sum(0) / ws.sum(0), np.nan)
        gap = np.where(wg.sum(0) > 0, (wg * np.nan_to_num(G)).sum(0) / wg.sum(0), np.nan)
    fused = np.where(count > 0, fused, np.nan).astype(np.float32)
    stats = []
    for p in range(len(dems)):
        both = valid[p] & np.isfinite(fused)
        d = (H[p] - fused)[both]
        stats.append(
            dict(
                sigma_m=round(float(sigmas[p]), 4),
                cells=int(valid[p].sum()),
                kept=int(keep[p].sum()),
                rejected=int((valid[p] & ~keep[p]).sum()),
                median_vs_fused_m=round(float(np.median(d)), 4) if d.size else None,
                nmad_vs_fused_m=round(nmad_of(d), 4) if d.size else None,
            )
        )
    dem = DEM(
        fused,
        grid.transform,
        grid.crs,
        dems[0].vertical,
        count=count,
        score=score.astype(np.float32),
        ray_gap=gap.astype(np.float32),
        sigma=sigma.astype(np.float32),
    )
    return FusedDEM(dem, nmad, method, stats, valid & ~keep)
