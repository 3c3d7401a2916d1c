import numpy as np
import pytest
from scipy import stats as sst

from stereodem.core.errors import InputError
from stereodem.core.stats import nmad
from stereodem.post import stats as st


def test_error_stats_match_independent_numpy():
    rng = np.random.default_rng(3)
    x = rng.standard_t(4, 5001) * 3 + 1.5
    x_nan = np.concatenate([x, [np.nan] * 999])
    s = st.error_stats(x_nan)
    assert s["n"] == 5001 and s["n_total"] == 6000
    assert s["valid_pct"] == pytest.approx(100 * 5001 / 6000)
    assert s["mean"] == pytest.approx(x.sum() / x.size, rel=1e-12)
    assert s["median"] == pytest.approx(np.sort(x)[2500], rel=1e-12)
    assert s["std"] == pytest.approx(np.sqrt(np.sum((x - x.mean()) ** 2) / x.size), rel=1e-12)
    assert s["rmse"] == pytest.approx(np.sqrt(np.sum(x * x) / x.size), rel=1e-12)
    assert s["rmse"] ** 2 == pytest.approx(s["mean"] ** 2 + s["std"] ** 2, rel=1e-9)

    assert s["nmad"] == pytest.approx(sst.median_abs_deviation(x, scale=1 / 1.4826), rel=1e-12)
    assert s["le90"] == pytest.approx(sst.scoreatpercentile(np.abs(x), 90), rel=1e-12)
    assert s["le95"] == pytest.approx(sst.scoreatpercentile(np.abs(x), 95), rel=1e-12)
    assert s["p16"] == pytest.approx(sst.scoreatpercentile(x, 16), rel=1e-12)
    assert s["p84"] == pytest.approx(sst.scoreatpercentile(x, 84), rel=1e-12)
    assert s["le90_gauss"] == pytest.approx(sst.norm.ppf(0.95) * s["std"], rel=1e-12)
    assert s["le95_gauss"] == pytest.approx(sst.norm.ppf(0.975) * s["std"], rel=1e-12)
    assert (s["min"], s["max"]) == (x.min(), x.max())


def test_known_distribution_nmad_and_le90():
    sigma = 7.0
    x = np.random.default_rng(11).normal(0.0, sigma, 1_000_000)
    s = st.error_stats(x)
    assert abs(s["nmad"] / sigma - 1) < 0.01
    assert abs(s["le90"] / (1.645 * sigma) - 1) < 0.01
    assert abs(s["le95"] / (1.960 * sigma) - 1) < 0.01
    assert abs(nmad(x) - s["nmad"]) < 1e-12


def test_empty_stats_are_nan_not_errors():
    s = st.error_stats(np.full(10, np.nan))
    assert s["n"] == 0 and s["valid_pct"] == 0 and np.isnan(s["rmse"])


def test_binned_and_class_stats():
    rng = np.random.default_rng(0)
    slope = rng.uniform(0, 60, 20000)
    dh = rng.normal(0, 1 + 0.2 * slope)
    rows = st.binned_stats(dh, slope, st.DEFAULT_SLOPE_BINS, unit="deg", name="slope")
    assert [r["class"] for r in rows][0] == "0-5deg" and len(rows) == 6
    assert sum(r["n"] for r in rows) == dh.size
    sel = (slope >= 10) & (slope < 20)
    assert rows[2]["std"] == pytest.approx(np.std(dh[sel]))
    nm = [r["nmad"] for r in rows]
    assert all(b > a for a, b in zip(nm, nm[1:]))
    fit = st.error_vs_slope(dh, slope)
    assert fit["slope_m_per_deg"] > 0.1 and fit["r"] > 0.3
    trend = st.class_trend(rows)
    assert trend["r"] > 0.95
    lc = rng.integers(1, 4, dh.size)
    cl = st.class_stats(dh, lc, names={1: "water"})
    assert [c["class"] for c in cl] == ["water", "2", "3"]
    assert cl[1]["mean"] == pytest.approx(np.mean(dh[lc == 2]))
    with pytest.raises(InputError):
        st.binned_stats(dh, slope, [5, 1])
