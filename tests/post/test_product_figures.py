"""Quick looks of ``change``, ``stack`` and ``mosaic`` (:mod:`stereodem.post.product_figures`):
what a person reads off them, checked on the matplotlib Figure objects (as
``test_figures_read.py`` does), and that the commands write and list them."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from affine import Affine
from matplotlib.colors import BoundaryNorm
from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

from stereodem.cli import main
from stereodem.core.dem import DEM
from stereodem.core.errors import OutputExistsError
from stereodem.post import figures, product_figures

T = Affine(30.0, 0.0, 600000.0, 0.0, -30.0, 4390000.0)
CRS = "EPSG:32637"


def _map(fig):
    """The map axes of a figure (the one with an image) and its colour bar's axes."""
    ax = next(a for a in fig.axes if a.get_images())
    cbar = next(a for a in fig.axes if a is not ax)
    return ax, cbar


def _is_map(ax):
    assert any(isinstance(a, AnchoredSizeBar) for a in ax.artists)  # scale bar
    assert "km" in ax.get_xlabel() and "km" in ax.get_ylabel()
    im = ax.get_images()[0]
    assert im.cmap.get_bad()[3] == 0.0  # no data transparent (over the hatch)
    return im


def _field(shape=(80, 90), seed=0):
    rng = np.random.default_rng(seed)
    a = rng.normal(0.0, 1.0, shape)
    a[:10, :10] = np.nan  # a void
    return a


def test_change_maps_dh_diverging_at_zero_and_sigma_from_zero(tmp_path, captured):
    dh = _field() + 0.5
    sigma = np.abs(_field(seed=1)) + 0.2
    files = product_figures.change_figures(
        dh, sigma, T, CRS, tmp_path, names=("dem_2004.tif", "dem_2019.tif")
    )
    assert {k: p.name for k, p in files.items()} == product_figures.CHANGE_FIGURES
    assert all(p.is_file() for p in files.values())
    ax, cbar = _map(captured[0])
    im = _is_map(ax)
    assert im.norm.vmin == pytest.approx(-im.norm.vmax)  # centred at 0
    assert im.cmap(0.5)[:3] == pytest.approx((0.97, 0.97, 0.97), abs=0.04)  # white at 0
    title = ax.get_title()
    assert "dem_2019.tif − dem_2004.tif" in title and "% of cells beyond" in title
    share = float(re.search(r"([0-9.]+) % of cells beyond", title).group(1))
    fin = dh[np.isfinite(dh)]
    assert share == pytest.approx(100 * np.mean(np.abs(fin) > im.norm.vmax), abs=0.1)
    assert cbar.get_ylabel() == "dh = B − A (m)"
    ax, cbar = _map(captured[1])
    im = _is_map(ax)
    assert im.norm.vmin == 0.0 and im.norm.vmax == pytest.approx(
        np.nanpercentile(sigma, 98), rel=1e-6
    )
    assert "σ of dh" in ax.get_title() and "dem_2019.tif" in ax.get_title()
    assert "98th percentile" in ax.get_title() and "(m)" in cbar.get_ylabel()


@pytest.mark.slow
def test_stack_maps_rate_in_m_per_year_and_the_dates_per_cell(tmp_path, captured):
    n_obs = np.full((60, 70), 4, np.int16)
    n_obs[:, :7] = 3  # 10 %
    n_obs[:6, :] = 0  # no date: hatched
    rate = np.where(n_obs > 0, _field((60, 70)), np.nan)
    rates = {"rate": rate, "rate_sigma": np.abs(rate) / 3, "n_obs": n_obs}
    files = product_figures.stack_figures(rates, T, CRS, tmp_path, what="4 DEMs, 2004 to 2019")
    assert {k: p.name for k, p in files.items()} == product_figures.STACK_FIGURES
    (rate_ax, rate_cb), (sig_ax, sig_cb), (n_ax, n_cb) = map(_map, captured)
    im = _is_map(rate_ax)
    assert im.norm.vmin == pytest.approx(-im.norm.vmax)
    assert rate_cb.get_ylabel() == "rate (m/yr)" and "m/yr" in rate_ax.get_title()
    assert "|rate|" in rate_ax.get_title() and "4 DEMs, 2004 to 2019" in rate_ax.get_title()
    assert _is_map(sig_ax).norm.vmin == 0.0 and "(m/yr)" in sig_cb.get_ylabel()
    im = _is_map(n_ax)
    assert isinstance(im.norm, BoundaryNorm)  # one colour per count
    assert "no date" in n_ax.get_title()
    ticks = [t.get_text() for t in n_cb.get_yticklabels()]
    # the counted cells: 54 rows, 7 of 70 columns with 3 dates
    assert "3 (10 %)" in ticks and "4 (90 %)" in ticks
    drawn = np.ma.getmaskarray(im.get_array())  # cropped to the data, with a margin
    assert drawn[0].all() and not drawn[-1].any()  # no date: not drawn


def test_maps_are_decimated_for_display(tmp_path, captured):
    big = np.ones((3 * figures.DISPLAY_CELLS, 50))
    product_figures.magnitude_map_png(
        big, tmp_path / "s.png", transform=T, crs=CRS, title="t", label="σ (m)"
    )
    assert max(captured[0].axes[0].get_images()[0].get_array().shape) <= figures.DISPLAY_CELLS


def _dems(tmp_path):
    b = DEM.bundled()
    z = b.heights[:60, :80].astype(np.float32)
    DEM(z[:, :50].copy(), T, CRS, "geoid").write(tmp_path / "a.tif")
    DEM(z[:, 30:].copy() + 1.0, T @ Affine.translation(30, 0), CRS, "geoid").write(
        tmp_path / "b.tif"
    )
    return [str(tmp_path / "a.tif"), str(tmp_path / "b.tif")]


@pytest.mark.slow
def test_mosaic_writes_its_hillshade_and_count_beside_it(tmp_path, captured):
    out, dems = tmp_path / "m.tif", _dems(tmp_path)
    assert main(["-q", "mosaic", *dems, "-o", str(out), "--workers", "1"]) == 0
    rep = json.loads((tmp_path / "m.json").read_text())
    assert rep["figures"] == {"hillshade": "m_hillshade.png", "count": "m_count.png"}
    assert (tmp_path / "m_hillshade.png").is_file() and (tmp_path / "m_count.png").is_file()
    hs, count = captured
    ax, cbar = _map(hs)
    assert "m.tif" in ax.get_title() and "2 DEMs" in ax.get_title()
    assert "(m)" in cbar.get_ylabel()
    ax, cbar = _map(count)
    _is_map(ax)
    assert "m.tif" in ax.get_title() and "no DEM" in ax.get_title()
    ticks = [t.get_text() for t in cbar.get_yticklabels()]
    # 50 + 50 columns over 80: 20 columns with both DEMs
    assert ticks == ["1 (75 %)", "2 (25 %)"]
    # a PNG of the same name is a product: refused without --overwrite, before any work
    (tmp_path / "n_count.png").write_bytes(b"the user's")
    rc = main(["-q", "mosaic", *dems, "-o", str(tmp_path / "n.tif")])
    assert rc == 1 and not (tmp_path / "n.tif").exists()
    assert (tmp_path / "n_count.png").read_bytes() == b"the user's"


def test_mosaic_statistic_alone_draws_that_statistic(tmp_path):
    paths = product_figures.mosaic_figure_paths(tmp_path / "m.tif", "nmad")
    assert {k: p.name for k, p in paths.items()} == {"nmad": "m_nmad.png"}
    assert set(product_figures.mosaic_figure_paths("m.tif", "count")) == {"count"}
    assert set(product_figures.mosaic_figure_paths("m.tif", "median")) == {"hillshade", "count"}


def test_figures_follow_the_overwrite_policy(tmp_path):
    (tmp_path / "dh_map.png").write_bytes(b"x")
    with pytest.raises(OutputExistsError):
        product_figures.change_figures(
            _field(), np.abs(_field()), T, CRS, tmp_path, names=("a.tif", "b.tif")
        )
    assert (tmp_path / "dh_map.png").read_bytes() == b"x"
    product_figures.change_figures(
        _field(), np.abs(_field()), T, CRS, tmp_path, names=("a.tif", "b.tif"), overwrite=True
    )
    assert (tmp_path / "dh_map.png").read_bytes()[:4] == b"\x89PNG"
