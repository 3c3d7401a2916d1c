"""Local polynomial stand-ins for exact coordinate transforms of many points in a small extent.

PROJ costs ~150 ns a point for a UTM projection and ~80 ns for ECEF -> geodetic; a stereo
tile has ~250 000 points within a few kilometres, over which both transforms are smooth to a
degree that a cubic polynomial reproduces them to micrometres. :func:`fitted` therefore fits,
per tile, one polynomial per output to the exact transform at a Chebyshev lattice over the
points' bounding box, checks it against the exact transform at a second lattice (its corners
and edges included, where a polynomial's error peaks), and evaluates it for every point only
when the largest error found there is within the caller's tolerance; otherwise, or for few
points, the exact transform runs. This is GDAL's approximate transformer
(``GDALCreateApproxTransformer``: exact values at sample points, interpolation between, an
error threshold) with a polynomial in place of its linear interpolation; the exact values
always come from the exact transform (pyproj), nothing of the geodesy is written here.

The result depends only on the points (their bounding box), not on the machine's threads or
on how the points were split into jobs, so products stay bit-identical across worker counts.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence

import numpy as np

__all__ = ["MIN_POINTS", "TILE_TOLERANCE_M", "fitted"]

#: the tolerance of a stereo tile's ground points (ECEF -> geodetic, then the DEM's CRS):
#: 0.1 mm, a hundred-thousandth of a satellite pixel and far below any DEM's error
TILE_TOLERANCE_M = 1e-4

#: points evaluated at a time (their monomials, 10-20 rows of float64, stay in a core's cache)
CHUNK = 16384

#: below this many points the exact transform runs (the fit's fixed cost, ~0.3 ms, would not pay)
MIN_POINTS = 20_000


def _recipe(dims: int, degree: int) -> list[tuple[int, int]]:
    """The monomials of total degree <= ``degree`` in ``dims`` variables, graded (constant
    first), each as ``(parent, d)``: the earlier monomial that, times variable ``d``, gives
    it (the constant: ``(-1, -1)``)."""
    exps = [e for e in itertools.product(range(degree + 1), repeat=dims) if sum(e) <= degree]
    exps.sort(key=lambda e: (sum(e), tuple(-x for x in e)))
    index = {e: t for t, e in enumerate(exps)}
    out = []
    for e in exps:
        if not any(e):
            out.append((-1, -1))
            continue
        d = next(i for i, k in enumerate(e) if k)
        out.append((index[e[:d] + (e[d] - 1,) + e[d + 1 :]], d))
    return out


def _monomials(u: Sequence[np.ndarray], recipe) -> np.ndarray:
    """(terms, n) values of the monomials of ``recipe`` (:func:`_recipe`) at the normalised
    coordinates ``u``: one multiplication per term."""
    out = np.empty((len(recipe), u[0].size))
    for t, (parent, d) in enumerate(recipe):
        if parent < 0:
            out[t].fill(1.0)
        else:
            np.multiply(out[parent], u[d], out=out[t])
    return out


def _lattice(lo, hi, nodes: int, chebyshev: bool):
    """Points of a tensor lattice over the box ``lo..hi`` (one 1-D array per dimension):
    Chebyshev nodes (``nodes`` per axis, for the fit) or evenly spaced ones with the box's
    faces and corners (for the check)."""
    k = np.arange(nodes)
    g = np.cos(np.pi * (k + 0.5) / nodes) if chebyshev else np.linspace(-1.0, 1.0, nodes)
    axes = [0.5 * (a + b) + 0.5 * (b - a) * g for a, b in zip(lo, hi)]
    return [m.ravel() for m in np.meshgrid(*axes, indexing="ij")]


def fitted(
    transform: Callable[..., Sequence[np.ndarray]],
    coords: Sequence[np.ndarray],
    tolerance: Sequence[float],
    *,
    degree: int = 3,
    nodes: int = 6,
    check_nodes: int = 7,
) -> tuple[np.ndarray, ...] | None:
    """``transform(*coords)`` evaluated by a polynomial fitted to it, or None.

    Parameters
    ----------
    transform : callable
        The exact transform: ``transform(*arrays) -> tuple of arrays`` (vectorised, e.g. a
        pyproj ``Transformer.transform``).
    coords : sequence of 1-D float64 arrays
        The points (2 or 3 coordinates, same length); non-finite points give non-finite
        results, as from the exact transform.
    tolerance : sequence of float
        Largest absolute error accepted for each output, in its units.
    degree : int
        Total degree of the polynomials (3: micrometres over a stereo tile).
    nodes, check_nodes : int
        Lattice points per axis for the fit (Chebyshev nodes) and for the check (evenly
        spaced, corners included).

    Returns
    -------
    tuple of ndarray, or None
        The outputs at every point; None when there are fewer than :data:`MIN_POINTS`
        points, no finite point, or the check found an error above ``tolerance`` (the
        caller then runs the exact transform).
    """
    coords = [np.asarray(c, dtype=np.float64).ravel() for c in coords]
    n = coords[0].size
    if n < MIN_POINTS:
        return None
    finite = np.isfinite(coords[0])
    for c in coords[1:]:
        finite &= np.isfinite(c)
    if not finite.any():
        return None
    every = finite.all()
    lo = [float(c.min() if every else c[finite].min()) for c in coords]
    hi = [float(c.max() if every else c[finite].max()) for c in coords]
    centre = [0.5 * (a + b) for a, b in zip(lo, hi)]
    scale = [2.0 / (b - a) if b > a else 1.0 for a, b in zip(lo, hi)]

    box = (centre, scale)
    recipe = _recipe(len(coords), degree)
    fit_pts = _lattice(lo, hi, nodes, chebyshev=True)
    values = np.stack([np.asarray(v, np.float64) for v in transform(*fit_pts)])
    if not np.isfinite(values).all():
        return None
    design = _monomials(_normalised(fit_pts, box), recipe)
    coef = np.linalg.lstsq(design.T, values.T, rcond=None)[0]  # (terms, outputs)
    check_pts = _lattice(lo, hi, check_nodes, chebyshev=False)
    exact = np.stack([np.asarray(v, np.float64) for v in transform(*check_pts)])
    approx = _evaluate(coef, check_pts, box, recipe)
    err = np.max(np.abs(approx - exact), axis=1)
    if not (np.isfinite(err).all() and np.all(err <= np.asarray(tolerance, float))):
        return None
    return tuple(_evaluate(coef, coords, box, recipe))


def _normalised(pts, box):
    """``pts`` mapped to ``[-1, 1]`` over the bounding box ``box`` = (centres, scales)."""
    return [(p - c) * k for p, c, k in zip(pts, *box)]


def _evaluate(coef, pts, box, recipe):
    """``sum_t coef[t, k] * monomial_t`` at the points ``pts`` for every output ``k``, by
    chunks of :data:`CHUNK` points whose monomials stay in cache, with numpy's own
    sum-of-products loops (``einsum`` without ``optimize``; no BLAS, so a point's value
    depends neither on its chunk nor on the threads)."""
    n = pts[0].size
    out = np.empty((coef.shape[1], n))
    for s in range(0, n, CHUNK):
        part = slice(s, min(s + CHUNK, n))
        mono = _monomials(_normalised([p[part] for p in pts], box), recipe)
        np.einsum("tk,tn->kn", coef, mono, out=out[:, part], optimize=False)
    return out
