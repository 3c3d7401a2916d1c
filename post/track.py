"""The along/cross-track frame of a DEM made from a pushbroom image, from its sensor model.

A satellite's ground track is not a straight line at one heading over a scene in general (the
Earth turns under the orbit, the orbit curves, the attitude drifts), so the along-track
coordinate of a DEM cell is taken from the left sensor model itself: the image row that sees the
cell (rows follow the acquisition time of a pushbroom image) and the image column, each a
polynomial of the cell's map coordinates and height, scaled to metres by the ground distance
between rows (columns) at the image centre:

    along(x, y, h) = m_per_row · row(x, y, h),      cross(x, y, h) = m_per_col · col(x, y, h)

``x, y`` in the DEM's CRS, normalised as ``u = (x − x0)/scale``, ``v = (y − y0)/scale``, and
``w = (h − h0)/1000`` (ellipsoidal metres); the polynomials are of order :data:`ORDER` in
``u, v`` plus ``w·(1, u, v)`` (the parallax of an off-nadir view: ASTER 3N points up to 8.55°
across the track, 0.15 m of ground per metre of height), fitted by least squares on a grid of
image points localised at ``h0`` (the DEM's median height) and ``h0 ± 500 m``. Without heights
``w = 0``. The fit's RMS (m) is stored with it.

The frame travels in the DEM's GeoTIFF tags (:data:`TRACK_FRAME_TAG`, JSON) beside the heading
(``STEREODEM_TRACK_HEADING``); :mod:`stereodem.post.biascorr`'s ``along_track`` and
``cross_track`` use it when present, the straight track of the heading otherwise.
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass

import numpy as np
import rasterio
from pyproj import CRS, Geod

from stereodem.core import geodesy

log = logging.getLogger(__name__)

#: DEM tag holding the track frame (JSON of :class:`TrackFrame`)
TRACK_FRAME_TAG = "STEREODEM_TRACK_FRAME"
#: order of the row/column polynomials of the map coordinates
ORDER = 3
#: image points per side of the fitting grid
GRID_POINTS = 15


#: metres of height per unit of ``w``
H_SCALE = 1000.0


def _terms(u, v, w, order):
    """Columns u^i v^j (i + j <= order, constant first), then w, w·u, w·v."""
    u, v, w = np.broadcast_arrays(*(np.asarray(a, np.float64) for a in (u, v, w)))
    cols = [u ** (k - j) * v**j for k in range(order + 1) for j in range(k + 1)]
    return np.stack(cols + [w, w * u, w * v], -1)


def n_terms(order: int) -> int:
    return (order + 1) * (order + 2) // 2 + 3


@dataclass
class TrackFrame:
    """Along/cross-track metres of map points of one CRS, from a sensor model (see module).

    Attributes
    ----------
    crs : str
        The CRS of ``x, y`` (WKT or authority string).
    x0, y0, scale : float
        Normalisation of the map coordinates (CRS units).
    order : int
    along, cross : list of float
        Polynomial coefficients (metres) of the along-track (row) and cross-track (column)
        coordinates.
    m_per_row, m_per_col : float
        Ground metres between successive rows (columns) at the image centre.
    fit_rms_m : float
        RMS of the polynomial fit on the grid of image points (metres, along and cross).
    height_m : float
        Ellipsoidal height at which the image points were localised.
    """

    crs: str
    x0: float
    y0: float
    scale: float
    order: int
    along: list
    cross: list
    m_per_row: float
    m_per_col: float
    fit_rms_m: float
    height_m: float

    # ------------------------------------------------------------------ evaluation
    def coords(self, x, y, h=None):
        """Along- and cross-track metres of map points ``x, y`` (arrays, this frame's CRS) at
        ellipsoidal heights ``h`` (m; None or NaN: the frame's ``height_m``)."""
        w = 0.0
        if h is not None:
            w = (np.asarray(h, np.float64) - self.height_m) / H_SCALE
            w = np.where(np.isfinite(w), w, 0.0)
        a = _terms(
            (np.asarray(x, np.float64) - self.x0) / self.scale,
            (np.asarray(y, np.float64) - self.y0) / self.scale,
            w,
            self.order,
        )
        return a @ np.asarray(self.along), a @ np.asarray(self.cross)

    def grid_coords(self, transform, rows, cols, h=None):
        """Along/cross metres at cell-centre indices ``rows, cols`` (integers or fractional)
        of a grid with GDAL ``transform`` in this frame's CRS, at heights ``h`` (m)."""
        x, y = transform @ (np.asarray(cols, np.float64) + 0.5, np.asarray(rows, np.float64) + 0.5)
        return self.coords(x, y, h)

    def matches(self, crs) -> bool:
        """Whether ``crs`` is the CRS the frame was fitted in."""
        try:
            return CRS.from_user_input(self.crs).equals(
                CRS.from_user_input(crs), ignore_axis_order=True
            )
        except Exception:  # noqa: BLE001 - unreadable: no match
            return False

    def describe(self) -> dict:
        """What a report says about the frame."""
        return {
            "source": "left sensor model (image row/column as polynomials of map x, y, h)",
            "order": self.order,
            "fit_rms_m": self.fit_rms_m,
            "m_per_row": self.m_per_row,
            "m_per_col": self.m_per_col,
        }

    # ------------------------------------------------------------------ tags
    def to_tag(self) -> str:
        return json.dumps(asdict(self), separators=(",", ":"))

    @classmethod
    def from_tag(cls, text: str | None) -> TrackFrame | None:
        """The frame of a tag value, None when absent or unreadable."""
        if not text:
            return None
        try:
            d = json.loads(text)
            f = cls(**d)
            n = n_terms(f.order)
            if len(f.along) != n or len(f.cross) != n or not np.all(np.isfinite(f.along + f.cross)):
                return None
            return f
        except (ValueError, TypeError):
            return None

    # ------------------------------------------------------------------ fitting
    @classmethod
    def from_model(
        cls,
        model,
        shape,
        crs,
        *,
        height: float = 0.0,
        order: int = ORDER,
        points: int = GRID_POINTS,
    ) -> TrackFrame:
        """Fit the frame of an image of ``shape`` (rows, cols) seen by ``model`` in map CRS
        ``crs``, its points localised at ellipsoidal ``height`` and ``height ± 500`` m."""
        rows, cols = shape[:2]
        r, c = np.meshgrid(
            np.linspace(0, rows - 1, points), np.linspace(0, cols - 1, points), indexing="ij"
        )
        r, c = np.tile(r.ravel(), 3), np.tile(c.ravel(), 3)
        hh = float(height) + np.repeat([0.0, -500.0, 500.0], points * points)
        lon, lat = model.localize(c, r, hh)
        x, y = (np.asarray(v, np.float64) for v in geodesy.lonlat_to_crs(lon, lat, crs))
        # ground metres per row / column at the image centre
        rc, cc = (rows - 1) / 2.0, (cols - 1) / 2.0
        lo, la = model.localize(
            np.array([cc, cc, cc + 1.0]), np.array([rc, rc + 1.0, rc]), np.full(3, float(height))
        )

        g = Geod(ellps="WGS84")
        m_row = float(g.inv(lo[0], la[0], lo[1], la[1])[2])
        m_col = float(g.inv(lo[0], la[0], lo[2], la[2])[2])
        ok = np.isfinite(x) & np.isfinite(y)
        if ok.sum() < 2 * n_terms(order) or not (m_row > 0 and m_col > 0):
            raise ValueError("too few localised image points for the track frame")
        x0, y0 = float(np.mean(x[ok])), float(np.mean(y[ok]))
        scale = float(max(np.ptp(x[ok]), np.ptp(y[ok])) / 2.0) or 1.0
        a = _terms((x[ok] - x0) / scale, (y[ok] - y0) / scale, (hh[ok] - height) / H_SCALE, order)
        along, *_ = np.linalg.lstsq(a, m_row * r[ok], rcond=None)
        cross, *_ = np.linalg.lstsq(a, m_col * c[ok], rcond=None)
        res = np.concatenate([a @ along - m_row * r[ok], a @ cross - m_col * c[ok]])
        crs_text = CRS.from_user_input(crs).to_string()
        return cls(
            crs_text,
            x0,
            y0,
            scale,
            int(order),
            along.tolist(),
            cross.tolist(),
            m_row,
            m_col,
            float(np.sqrt(np.mean(res**2))),
            float(height),
        )


def track_frame_of(path) -> TrackFrame | None:
    """The track frame a stereodem DEM carries in its tags, if any."""
    try:
        with rasterio.open(path) as ds:
            return TrackFrame.from_tag(ds.tags().get(TRACK_FRAME_TAG))
    except rasterio.errors.RasterioIOError:
        return None
