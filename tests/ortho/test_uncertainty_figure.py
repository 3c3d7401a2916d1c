"""What a person reads off the uncertainty figure (``uncertainty.png``): map axes with their
units (km east/north on a projected grid, degrees on a geographic one: one rule,
:func:`stereodem.core.mapaxes.map_axes`), a scale bar, a colour bar in metres, and the shares
written inside their axes without covering each other or another bar. Checked on the
matplotlib Figure as saved, not on pixels."""

from __future__ import annotations

import numpy as np
import pytest
from affine import Affine
from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

from stereodem.core.grid import MapGrid
from stereodem.ortho.uncertainty import figure as F
from stereodem.ortho.uncertainty.maps import UncertaintyMaps


@pytest.fixture
def captured(monkeypatch):
    """Figures as drawn, just before they are saved."""
    figs = []
    save = F.save_png

    def keep(fig, *a, **k):
        fig.canvas.draw()  # the layout as written (text extents need a renderer)
        figs.append((fig, fig.canvas.get_renderer()))
        return save(fig, *a, **k)

    monkeypatch.setattr(F, "save_png", keep)
    return figs


def _maps(crs, transform, shares):
    grid = MapGrid(transform, 60, 50, crs)
    yy, xx = np.mgrid[0:50, 0:60]
    sE = (5 + 0.02 * xx + 0.01 * yy).astype(np.float32)
    sN = (2 + 0.01 * yy).astype(np.float32)
    sE[:5, :5] = sN[:5, :5] = np.nan  # no data
    names = list(shares)
    return UncertaintyMaps(
        grid,
        "first-order",
        names,
        names,
        sE,
        sN,
        np.hypot(sE, sN),
        np.zeros((50, 60), np.int16),
        shares,
        16,
        1e-5,
    )


UTM = ("EPSG:32637", Affine(15.0, 0, 618060.0, 0, -15.0, 4386930.0))
LONLAT = ("EPSG:4326", Affine(1.5e-4, 0, 40.38, 0, -1.5e-4, 39.62))
SHARES = {"roll_bias": 0.62, "pitch_bias": 0.32, "dem_height": 0.06 - 1e-4, "yaw": 1e-4}


def _draw(captured, tmp_path, crs, shares=SHARES):
    F.plot_uncertainty(_maps(*crs, shares), tmp_path / "u.png", title="left.tif")
    assert (tmp_path / "u.png").exists()
    fig, renderer = captured[-1]
    ax, bx = fig.axes[0], fig.axes[1]
    cbar = [a for a in fig.axes[2:] if a.get_ylabel() or a.get_xlabel()]
    return renderer, ax, bx, cbar


def test_projected_map_in_km_with_a_scale_bar_and_metre_colour_bar(captured, tmp_path):
    """The axes read "easting − 618060 (km)": a metre offset on a km axis, no scale bar."""
    _, ax, _, cbar = _draw(captured, tmp_path, UTM)
    assert ax.get_xlabel() == "easting (km)" and ax.get_ylabel() == "northing (km)"
    assert "−" not in ax.get_xlabel() + ax.get_ylabel()
    # ticks are the CRS's coordinates in km (618.5 km, not 0.44 of an offset)
    ticks = [t for t in ax.get_xticks() if ax.get_xlim()[0] <= t <= ax.get_xlim()[1]]
    fmt = ax.xaxis.get_major_formatter()
    assert all(618.0 <= float(fmt(t, 0)) <= 619.0 for t in ticks), [fmt(t, 0) for t in ticks]
    bars = [a for a in ax.artists if isinstance(a, AnchoredSizeBar)]
    assert len(bars) == 1
    assert bars[0].txt_label.get_text() in ("200 m", "100 m")  # a quarter of 900 m, rounded
    assert len(cbar) == 1 and "(m)" in cbar[0].get_ylabel()
    assert "σ" in cbar[0].get_ylabel()


def test_geographic_map_in_degrees_with_a_scale_bar(captured, tmp_path):
    """A lon/lat grid was labelled in km (degrees / 1000)."""
    _, ax, _, cbar = _draw(captured, tmp_path, LONLAT)
    assert ax.get_xlabel() == "longitude (°E)" and ax.get_ylabel() == "latitude (°N)"
    # the ticks are whole longitudes (40.382), not an offset's remainder (0.002 + 4.038e1)
    labels = [t.get_text().replace("−", "-") for t in ax.get_xticklabels() if t.get_text()]
    assert labels and all(40.37 < float(x) < 40.4 for x in labels), labels
    assert not ax.xaxis.get_offset_text().get_text()
    bars = [a for a in ax.artists if isinstance(a, AnchoredSizeBar)]
    assert len(bars) == 1 and bars[0].txt_label.get_text().endswith(" m")
    assert len(cbar) == 1 and "(m)" in cbar[0].get_ylabel()


@pytest.mark.parametrize("shares", [SHARES, {"roll_bias": 1.0}, {"a": 0.5, "b": 0.5}])
def test_share_texts_inside_the_axes_over_no_other_bar_or_text(captured, tmp_path, shares):
    """The values were written from the bar's end: over the bar, and a share of 1.000 beyond
    the axes (xlim 1)."""
    r, _, bx, _ = _draw(captured, tmp_path, UTM, shares)
    area = bx.get_window_extent(r)
    texts = [t for t in bx.texts]
    assert len(texts) == len(shares)
    assert {t.get_text() for t in texts} == {f"{v:.3f}" for v in shares.values()}
    boxes = [t.get_window_extent(r) for t in texts]
    bars = [p.get_window_extent(r) for p in bx.patches]
    for t, b in zip(texts, boxes):
        assert area.x0 <= b.x0 and b.x1 <= area.x1 and area.y0 <= b.y0 and b.y1 <= area.y1, (
            t.get_text(),
            b,
            area,
        )
        # a text is either wholly inside its own bar (contrasting colour) or off every bar
        own = [p for p in bars if p.y0 <= 0.5 * (b.y0 + b.y1) <= p.y1]
        assert len(own) == 1
        if own[0].x0 <= b.x0 and b.x1 <= own[0].x1:
            assert t.get_color() == "white"
        else:
            assert not any(b.overlaps(p) for p in bars), t.get_text()
    for i in range(len(boxes)):
        for j in range(i + 1, len(boxes)):
            assert not boxes[i].overlaps(boxes[j])
