"""Error statistics accumulated block by block, in memory independent of the number of cells.

:class:`StreamingStats` takes the height differences of a raster one block at a time and
gives the statistics of :func:`stereodem.post.stats.error_stats` for all of them, without
holding them:

* count, mean, std (Chan's pairwise merge of block means and squared deviations), RMSE, MAE,
  min and max are exact up to floating-point summation order (relative 1e-12);
* quantiles (median, P16/P84, LE90/LE95 = quantiles of ``|dh|``, NMAD = 1.4826 · median of
  ``|dh − median|``) come from a histogram of bin width ``resolution`` (default 2⁻¹⁰ m ≈ 1 mm)
  with values beyond ``± limit`` kept exactly. A quantile is numpy's ``linear`` quantile of
  the values with each binned value replaced by its bin centre, so it is within
  ``resolution / 2`` of numpy's; NMAD is within ``1.4826 · resolution`` (the median's error
  plus the binning of ``|dh − median|``). :data:`QUANTILE_ERROR` states both.

With ``covariate=True`` it also keeps, per bin, the sums of a covariate (the terrain slope)
needed for the least-squares line of ``|dh − median|`` against it
(:meth:`StreamingStats.abs_deviation_fit`, :func:`stereodem.post.stats.error_vs_slope`'s
numbers): the sums are exact except over the one bin holding the median (its cells'
deviations are within ``resolution`` of the truth).
"""

from __future__ import annotations

import math

import numpy as np

from stereodem.core.stats import NMAD_FACTOR

from .stats import STAT_KEYS, Z90, Z95

#: default histogram bin width (m): 2^-10 m, about 1 mm
RESOLUTION = 2.0**-10
#: values beyond ± this (m) are kept exactly instead of binned (blunders: few, far apart)
LIMIT = 1000.0


def quantile_error(resolution: float = RESOLUTION) -> dict:
    """Largest difference (m) of the streamed quantile statistics from numpy's exact ones."""
    return {"quantiles": resolution / 2.0, "nmad": NMAD_FACTOR * resolution}


QUANTILE_ERROR = quantile_error()


def _dot(a, b) -> float:
    """Σ a·b by numpy's pairwise summation: the same bits whatever the BLAS thread count
    (``np.dot`` of vectors is BLAS's ``ddot``, which OpenBLAS splits over its threads, so the
    rounding followed ``--workers``)."""
    return float(np.sum(np.multiply(a, b)))


class StreamingStats:
    """Statistics of values added block by block (see the module docstring for the error
    bounds of the quantiles).

    Parameters
    ----------
    resolution : float
        Histogram bin width (units of the values, metres for height differences).
    limit : float
        Values with ``|x| > limit`` are stored exactly (not binned).
    covariate : bool
        Keep the per-bin sums needed by :meth:`abs_deviation_fit`; :meth:`add` then needs ``w``
        and takes only the values where both ``x`` and ``w`` are finite.
    """

    def __init__(
        self, resolution: float = RESOLUTION, limit: float = LIMIT, covariate: bool = False
    ):
        self.resolution = float(resolution)
        self.limit = float(limit)
        self.covariate = covariate
        self.n = 0
        self._mean = 0.0
        self._m2 = 0.0  # sum of squared deviations from the mean
        self._sumsq = 0.0
        self._sumabs = 0.0
        self.min = math.inf
        self.max = -math.inf
        self._lo = 0  # bin index of counts[0]
        self.counts = np.zeros(0, np.int64)
        self._tail = []  # exact values beyond ± limit
        self._tail_w = []
        if covariate:
            self._bx = np.zeros(0)  # per bin: sum of x, of w, of w·x
            self._bw = np.zeros(0)
            self._bwx = np.zeros(0)
            self._sw = self._sww = 0.0  # Σw, Σw²

    # ------------------------------------------------------------------ adding
    def add(self, x, w=None):
        """Add the finite values of ``x`` (any shape; NaN/inf skipped), with the covariate
        ``w`` (same shape) when the accumulator keeps one."""
        x = np.asarray(x, dtype=np.float64).ravel()
        ok = np.isfinite(x)
        if self.covariate:
            w = np.asarray(w, dtype=np.float64).ravel()
            ok &= np.isfinite(w)
        if not ok.all():
            x = x[ok]
            w = w[ok] if self.covariate else None
        self.add_finite(x, w)

    def add_finite(self, x, w=None):
        """:meth:`add` for values known to be finite: ``x`` a 1-D float64 array (m), ``w``
        the covariate at the same cells (finite, float64) when the accumulator keeps one.
        The block's moments, histogram bins and covariate sums are the same numbers
        :meth:`add` gives, with fewer passes over ``x``."""
        if self.covariate:
            self._sw += float(w.sum())
            self._sww += _dot(w, w)
        if x.size == 0:
            return
        n = x.size
        mean = float(x.sum()) / n  # what x.mean() gives
        buf = np.subtract(x, mean)
        np.multiply(buf, buf, out=buf)
        m2 = float(buf.sum())
        np.multiply(x, x, out=buf)
        sumsq = float(buf.sum())
        np.abs(x, out=buf)
        sumabs = float(buf.sum())
        lo_x, hi_x = float(x.min()), float(x.max())
        self._merge_moments(n, mean, m2, sumsq, sumabs, lo_x, hi_x)
        if max(-lo_x, hi_x) > self.limit:
            far = buf > self.limit
            self._tail.append(x[far])
            near = ~far
            x = x[near]
            if self.covariate:
                self._tail_w.append(w[far])
                w = w[near]
            if x.size == 0:
                return
        self._add_to_histogram(x, w, buf[: x.size])

    def _add_to_histogram(self, x, w, work):
        """Count the values ``x`` (within ± limit) in their bins ``floor(x / resolution)``,
        with the per-bin covariate sums; ``work``: a float64 array of the size of ``x`` to
        use."""
        b = np.divide(x, self.resolution, out=work)
        np.floor(b, out=b)  # bin indices, exact integers in float64
        lo, hi = int(b.min()), int(b.max())
        self._grow(lo, hi)
        b -= lo
        rel = b.astype(np.intp)
        a = lo - self._lo  # the block's bins are counts[a : a + hi - lo + 1]
        sl = slice(a, a + hi - lo + 1)
        self.counts[sl] += np.bincount(rel, minlength=hi - lo + 1)
        if self.covariate:
            self._bx[sl] += np.bincount(rel, weights=x, minlength=hi - lo + 1)
            self._bw[sl] += np.bincount(rel, weights=w, minlength=hi - lo + 1)
            wx = np.multiply(w, x, out=work)  # the bins are in rel now
            self._bwx[sl] += np.bincount(rel, weights=wx, minlength=hi - lo + 1)

    def without_covariate(self) -> StreamingStats:
        """These values' statistics without the covariate: what an accumulator without one
        would hold had it been given the same values (the moments, histogram and tail
        copied; the per-bin covariate sums left out)."""
        out = StreamingStats(self.resolution, self.limit)
        out.n, out._mean, out._m2 = self.n, self._mean, self._m2
        out._sumsq, out._sumabs, out.min, out.max = self._sumsq, self._sumabs, self.min, self.max
        out._lo, out.counts, out._tail = self._lo, self.counts.copy(), list(self._tail)
        return out

    def _merge_moments(self, n, mean, m2, sumsq, sumabs, lo, hi):
        """Chan et al.'s pairwise update of count, mean and squared deviations (the first
        set is taken as it is, so one block added equals that block's own figures)."""
        if self.n == 0:
            self.n, self._mean, self._m2 = n, mean, m2
        else:
            delta = mean - self._mean
            tot = self.n + n
            self._m2 += m2 + delta * delta * self.n * n / tot
            self._mean += delta * n / tot
            self.n = tot
        self._sumsq += sumsq
        self._sumabs += sumabs
        self.min = min(self.min, lo)
        self.max = max(self.max, hi)

    def merge(self, other: StreamingStats) -> StreamingStats:
        """Add the values of ``other`` (same resolution, limit and covariate setting) into
        this accumulator; merging block accumulators in a fixed order gives the same result
        whichever thread computed which block. Returns self."""
        if (other.resolution, other.limit, other.covariate) != (
            self.resolution,
            self.limit,
            self.covariate,
        ):
            raise ValueError("accumulators with different resolution, limit or covariate")
        if other.n == 0:
            return self
        self._merge_moments(
            other.n, other._mean, other._m2, other._sumsq, other._sumabs, other.min, other.max
        )
        self._tail += other._tail
        self._tail_w += other._tail_w
        if self.covariate:
            self._sw += other._sw
            self._sww += other._sww
        if other.counts.size:
            self._grow(other._lo, other._lo + other.counts.size - 1)
            a = other._lo - self._lo
            sl = slice(a, a + other.counts.size)
            self.counts[sl] += other.counts
            if self.covariate:
                self._bx[sl] += other._bx
                self._bw[sl] += other._bw
                self._bwx[sl] += other._bwx
        return self

    def _grow(self, lo, hi):
        if self.counts.size == 0:
            self._lo = lo
            self._resize(0, hi - lo + 1)
            return
        cur_hi = self._lo + self.counts.size - 1
        before = max(0, self._lo - lo)
        after = max(0, hi - cur_hi)
        if before or after:
            self._resize(before, after)
            self._lo -= before

    def _resize(self, before, after):
        names = ["counts"] + (["_bx", "_bw", "_bwx"] if self.covariate else [])
        for name in names:
            a = getattr(self, name)
            setattr(self, name, np.pad(a, (before, after)))

    # ------------------------------------------------------------------ the value set
    def _support(self):
        """(values, weights) standing for every value added: bin centres with their counts,
        then the exact tail values with weight 1."""
        nz = np.flatnonzero(self.counts)
        v = (self._lo + nz + 0.5) * self.resolution
        c = self.counts[nz]
        if self._tail:
            t = np.concatenate(self._tail)
            v = np.concatenate([v, t])
            c = np.concatenate([c, np.ones(t.size, np.int64)])
        return v, c

    @staticmethod
    def _weighted_quantile(v, c, q):
        """numpy's ``linear`` quantile of the multiset where ``v[i]`` occurs ``c[i]`` times."""
        order = np.argsort(v, kind="stable")
        v, cum = v[order], np.cumsum(c[order])
        n = int(cum[-1])
        p = np.asarray(q, dtype=np.float64) * (n - 1)
        k = np.floor(p).astype(np.int64)
        f = p - k
        lo = v[np.searchsorted(cum, k, side="right")]
        hi = v[np.searchsorted(cum, np.minimum(k + 1, n - 1), side="right")]
        return lo + f * (hi - lo)

    def quantile(self, q):
        """Quantile(s) ``q`` in [0, 1] of the values (within ``resolution / 2``)."""
        if self.n == 0:
            return np.full(np.shape(q), np.nan) if np.ndim(q) else float("nan")
        return self._weighted_quantile(*self._support(), q)

    def abs_quantile(self, q, centre: float = 0.0):
        """Quantile(s) of ``|x − centre|`` (within ``resolution / 2`` for an exact ``centre``)."""
        if self.n == 0:
            return np.full(np.shape(q), np.nan) if np.ndim(q) else float("nan")
        v, c = self._support()
        return self._weighted_quantile(np.abs(v - centre), c, q)

    def count_outside(self, lo: float, hi: float) -> tuple[int, int]:
        """Numbers of values below ``lo`` and above ``hi`` (binned values by their bin centre)."""
        v, c = self._support()
        return int(c[v < lo].sum()), int(c[v > hi].sum())

    def histogram(self, edges):
        """Counts of the values in the bins ``edges`` (numpy.histogram's convention; binned
        values by their bin centre)."""
        v, c = self._support()
        return np.histogram(v, bins=edges, weights=c)[0].astype(np.int64)

    # ------------------------------------------------------------------ results
    def result(self, *, n_total: int | None = None) -> dict:
        """The :func:`~stereodem.post.stats.error_stats` dict of the values added."""
        total = int(self.n if n_total is None else n_total)
        out = dict.fromkeys(STAT_KEYS, float("nan"))
        out.update(
            n=int(self.n),
            n_total=total,
            valid_pct=(100.0 * self.n / total) if total else float("nan"),
        )
        if self.n == 0:
            return out
        med, p16, p84 = (float(v) for v in self.quantile([0.5, 0.16, 0.84]))
        le90, le95 = (float(v) for v in self.abs_quantile([0.90, 0.95]))
        std = math.sqrt(max(self._m2, 0.0) / self.n)
        out.update(
            mean=self._mean,
            median=med,
            std=std,
            rmse=math.sqrt(self._sumsq / self.n),
            mae=self._sumabs / self.n,
            nmad=NMAD_FACTOR * float(self.abs_quantile(0.5, med)),
            p16=p16,
            p84=p84,
            le90=le90,
            le95=le95,
            le90_gauss=Z90 * std,
            le95_gauss=Z95 * std,
            min=self.min,
            max=self.max,
        )
        return out

    def abs_deviation_fit(self, centre: float) -> dict:
        """Least-squares line of ``e = |x − centre|`` against the covariate ``w``:
        ``{"slope", "intercept", "r", "n"}`` (NaN with < 3 values or no spread of ``w``).

        Exact but for the bin holding ``centre``, whose values count with the sign of their
        bin mean (each of their ``e`` is then within ``resolution`` of the truth)."""
        if not self.covariate:
            raise ValueError("this accumulator keeps no covariate")
        out = {
            "slope": float("nan"),
            "intercept": float("nan"),
            "r": float("nan"),
            "n": int(self.n),
        }
        if self.n < 3:
            return out
        cnt = self.counts.astype(np.float64)
        with np.errstate(invalid="ignore", divide="ignore"):
            sign = np.sign(np.where(cnt > 0, self._bx / np.maximum(cnt, 1.0), centre) - centre)
        sum_e = _dot(sign, self._bx - centre * cnt)
        sum_we = _dot(sign, self._bwx - centre * self._bw)
        sum_w, sum_ww = float(self._sw), float(self._sww)
        if self._tail:
            t, tw = np.concatenate(self._tail), np.concatenate(self._tail_w)
            e = np.abs(t - centre)
            sum_e += float(e.sum())
            sum_we += _dot(tw, e)
        n = float(self.n)
        sum_x = self._mean * n
        sum_ee = self._sumsq - 2.0 * centre * sum_x + n * centre * centre  # Σ(x − c)²
        mw, me = sum_w / n, sum_e / n
        var_w = sum_ww / n - mw * mw
        var_e = sum_ee / n - me * me
        cov = sum_we / n - mw * me
        if not var_w > 1e-12 * max(sum_ww / n, 1e-300):
            return out
        b = cov / var_w
        out.update(
            slope=b,
            intercept=me - b * mw,
            r=cov / math.sqrt(var_w * var_e) if var_e > 0 else float("nan"),
        )
        return out
