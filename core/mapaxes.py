"""Map axes of every figure: extent in map units, axis labels with their units, tick format
and a scale bar (one rule for the assessment, co-registration and uncertainty figures).

Projected grids are drawn in kilometres east/north (the ticks are the CRS's own coordinates,
written in km: "easting (km)" 618.5, not an offset in metres on a km axis), geographic grids
in degrees of longitude/latitude (the ticks whole coordinates, no offset) with the aspect of
the mean parallel; the scale bar is in
metres or kilometres of ground either way. matplotlib is loaded with this module (figure
modules only import it, DESIGN.md: imports).
"""

from __future__ import annotations

import numpy as np
from matplotlib.patches import Rectangle
from matplotlib.ticker import FuncFormatter
from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar
from pyproj import CRS

from stereodem.core.geodesy import metres_per_degree


def nice_length(x):
    """The largest 1, 2 or 5 × 10^k not above ``x``."""
    if x <= 0:
        return 0.0
    p = 10 ** np.floor(np.log10(x))
    return float(max(s for s in (1, 2, 5, 10) if s * p <= x) * p)


def map_axes(ax, transform, crs, shape, *, hatch_no_data: bool = True):
    """Extent for imshow in map units, axis labels and tick format, and a scale bar
    (an :class:`~mpl_toolkits.axes_grid1.anchored_artists.AnchoredSizeBar`, lower left).

    ``transform``, ``shape`` (rows, cols): the raster drawn; ``crs``: its CRS (None: a
    projected one in metres). ``hatch_no_data``: a light hatching under the raster, so that
    cells without data (transparent) read as such. Returns the ``extent`` to pass to
    ``imshow`` (left, right, bottom, top).
    """
    rows, cols = shape
    x0, y0 = transform @ (0, 0)
    x1, y1 = transform @ (cols, rows)
    extent = (x0, x1, y1, y0)
    geographic = crs is not None and CRS.from_user_input(crs).is_geographic
    if geographic:
        ax.set_xlabel("longitude (°E)")
        ax.set_ylabel("latitude (°N)")
        lat = 0.5 * (y0 + y1)
        m_per_unit = float(metres_per_degree(lat)[0])  # along the parallel
        ax.set_aspect(1.0 / np.cos(np.radians(lat)))
        for axis in (ax.xaxis, ax.yaxis):  # whole degrees on the ticks, no "+4.038e1" offset
            axis.get_major_formatter().set_useOffset(False)
    else:
        ax.set_xlabel("easting (km)")
        ax.set_ylabel("northing (km)")
        km = FuncFormatter(lambda v, _: f"{v / 1000:g}")
        ax.xaxis.set_major_formatter(km)
        ax.yaxis.set_major_formatter(km)
        m_per_unit = 1.0
        ax.set_aspect("equal")
    ax.tick_params(labelsize=8)
    ax.yaxis.set_tick_params(rotation=90)
    width_m = abs(x1 - x0) * m_per_unit
    length_m = nice_length(width_m / 4)
    if length_m > 0:
        label = f"{length_m / 1000:g} km" if length_m >= 1000 else f"{length_m:g} m"
        bar = AnchoredSizeBar(
            ax.transData,
            length_m / m_per_unit,
            label,
            "lower left",
            pad=0.4,
            sep=3,
            borderpad=0.6,
            frameon=True,
            size_vertical=0,
            fontproperties={"size": 8},
        )
        bar.patch.set_alpha(0.8)
        ax.add_artist(bar)
    ax.set_facecolor("white")
    if hatch_no_data:
        ax.add_patch(
            Rectangle(
                (min(x0, x1), min(y0, y1)),
                abs(x1 - x0),
                abs(y1 - y0),
                fill=False,
                hatch="////",
                edgecolor="0.82",
                linewidth=0,
                zorder=0,
            )
        )  # no data
    return extent
