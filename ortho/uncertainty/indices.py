"""Variance-based sensitivity indices through SALib: extended FAST and Sobol (Saltelli).

The inputs are independent normals with the marginal σ of the covariance (FAST and Sobol do
not take correlated inputs; :func:`fast_indices` says so in its result when the covariance has
off-diagonal terms). Model evaluations are the exact ground displacements of
:func:`stereodem.ortho.uncertainty.sampling.ground_displacements`.

The frequency checks (:func:`interference_order`, :func:`efast_interference_free`,
:func:`sample_frequencies`) verify a FAST design: Cukier et al. (1973) call a frequency set
free of interferences to order M when no combination ``Σ aᵢωᵢ = 0`` with ``Σ|aᵢ| ≤ M+1``
exists.
"""

from __future__ import annotations

import warnings

import numpy as np

from stereodem.core.errors import InputError
from stereodem.ortho.uncertainty.sampling import ground_displacements


def _problem(names, D):
    sd = np.sqrt(np.clip(np.diag(np.asarray(D, float)), 0, None))
    live = np.flatnonzero(sd > 0)
    if live.size == 0:
        raise InputError("all input sigmas are zero: nothing to analyse")
    return (
        {
            "num_vars": int(live.size),
            "names": [names[k] for k in live],
            "bounds": [[0.0, float(sd[k])] for k in live],
            "dists": ["norm"] * int(live.size),
        },
        live,
    )


def _combine(S_E, S_N, VE, VN):
    """Horizontal index: the components' indices weighted by their variances."""
    V = VE + VN
    return np.where(V > 0, (S_E * VE + S_N * VN) / np.where(V > 0, V, 1), np.nan)


def fast_indices(
    model, lon, lat, h, names, D, crs, *, samples: int = 1000, M: int = 4, dem=None, seed=0
):
    """First-order (main-effect) and total extended-FAST indices of the E, N and horizontal
    ground displacement at each point.

    ``samples`` is the number of points per search curve (SALib's N; the model runs N·u times).
    Returns a dict with ``names``, ``S1``/``ST`` -> {"east", "north", "horizontal"} (u, n),
    ``variance`` (E, N) and ``correlation_ignored``.
    """
    from SALib.analyze import fast as fast_analyze
    from SALib.sample import fast_sampler

    problem, live = _problem(list(names), D)
    if samples <= 4 * M * M:
        raise InputError(
            f"FAST needs more than {4 * M * M} samples per curve (M={M}), got {samples}"
        )
    if seed == 0 and not hasattr(fast_sampler, "handle_seed"):
        # SALib < 1.6 seeds its (global, legacy) generator only for a nonzero seed (``if
        # seed:``): seed 0 drew other random phases at each call. Seeded as SALib seeds
        # any other integer there.
        np.random.seed(0)
    Xl = fast_sampler.sample(problem, samples, M=M, seed=seed)

    def analyze(Y):
        with warnings.catch_warnings():  # SALib warns about its bootstrap intervals,
            warnings.simplefilter("ignore")  # which are not used here
            r = fast_analyze.analyze(problem, Y, M=M, print_to_console=False, seed=seed)
        return np.nan_to_num(r["S1"]), np.nan_to_num(r["ST"])

    out, dE, dN = _indices_per_point(model, lon, lat, h, names, live, Xl, crs, dem, analyze)
    VE, VN = dE.var(0), dN.var(0)
    for key in ("S1", "ST"):
        out[key]["horizontal"] = _combine(out[key]["east"], out[key]["north"], VE, VN)
    out["variance"] = (VE, VN)
    Dm = np.asarray(D, float)
    out["correlation_ignored"] = bool(np.any(np.abs(Dm - np.diag(np.diag(Dm))) > 0))
    return out


def sobol_indices(model, lon, lat, h, names, D, crs, *, samples: int = 1024, dem=None, seed=0):
    """First-order and total Sobol indices (Saltelli sampling) of the E and N displacement at
    each point; ``samples`` is SALib's base N (a power of 2; the model runs N·(u+2) times)."""
    from SALib.analyze import sobol as sobol_analyze
    from SALib.sample import sobol as sobol_sample

    problem, live = _problem(list(names), D)
    Xl = sobol_sample.sample(problem, samples, calc_second_order=False, seed=seed)

    def analyze(Y):
        r = sobol_analyze.analyze(
            problem, Y, calc_second_order=False, print_to_console=False, seed=seed
        )
        return r["S1"], r["ST"]

    return _indices_per_point(model, lon, lat, h, names, live, Xl, crs, dem, analyze)[0]


def _indices_per_point(model, lon, lat, h, names, live, Xl, crs, dem, analyze):
    """Run the model on SALib's samples ``Xl`` (columns of the ``live`` inputs) and apply
    ``analyze(Y) -> (S1, ST)`` to the E and N displacement of each point; returns
    ``(indices dict, dE, dN)``."""
    X = np.zeros((Xl.shape[0], len(names)))
    X[:, live] = Xl
    dE, dN = ground_displacements(model, lon, lat, h, names, X, crs, dem=dem)
    out = {"names": [names[k] for k in live], "S1": {}, "ST": {}}
    for comp, Y in (("east", dE), ("north", dN)):
        s1, st = zip(*(analyze(Y[:, j]) for j in range(Y.shape[1])))
        out["S1"][comp], out["ST"][comp] = np.array(s1).T, np.array(st).T
    return out, dE, dN


# ----------------------------------------------------------------------------- frequency checks


def interference_order(freqs, max_order: int = 8) -> int | None:
    """Smallest ``Σ|aᵢ|`` of a non-trivial integer combination ``Σ aᵢωᵢ = 0`` (None if none up
    to ``max_order``). A set is interference-free to order M when this is > M + 1.

    Dynamic programme over the frequencies: the least cost of reaching each partial sum,
    separately for "all coefficients zero so far" and "some non-zero".
    """
    freqs = [int(f) for f in freqs]
    INF = 10**9
    zero_only = {0: 0}
    nonzero: dict[int, int] = {}
    for w in freqs:
        new_nz = dict(nonzero)
        for src_map in (zero_only, nonzero):
            for s, cost in src_map.items():
                for a in range(-max_order, max_order + 1):
                    if a == 0:
                        continue
                    c = cost + abs(a)
                    if c > max_order:
                        continue
                    t = s + a * w
                    if c < new_nz.get(t, INF):
                        new_nz[t] = c
        nonzero = new_nz
    best = nonzero.get(0)
    return best


def efast_interference_free(omega_i: int, complementary, M: int, N: int) -> bool:
    """Whether the extended-FAST design reads the first M harmonics of ``omega_i`` cleanly: no
    combination of the complementary frequencies with ``Σ|aⱼ| ≤ M`` reaches any harmonic
    ``p·omega_i`` (p ≤ M) and the harmonics stay below the Nyquist frequency ``N/2``."""
    comp = sorted({int(abs(c)) for c in complementary if c})
    reach = {0}
    for _ in range(M):
        reach = reach | {r + s * c for r in reach for c in comp for s in (-1, 1)}
    harmonics = {p * int(omega_i) for p in range(1, M + 1)}
    return not (reach & harmonics) and M * int(omega_i) < N / 2


def sample_frequencies(column, N: int) -> int:
    """Dominant search-curve frequency of one FAST sample column of length ``N`` (FFT peak)."""
    c = np.asarray(column, float)[:N]
    spec = np.abs(np.fft.rfft(c - c.mean()))
    return int(np.argmax(spec[1:]) + 1)
