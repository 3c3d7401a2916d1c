"""Consecutive ASTER L1A granules of one pass joined into one strip (one model per band).

The granules of one pass are cut from one continuous acquisition: one orbit, one attitude,
one line clock (ASTER notes ``aster-l1a-format.md`` §1.2, §2.4; MicMac's strip merger joins
the lattices of consecutive scenes the same way, notes §2.3). So the strip is not stitched
from per-granule results: each band's lattices are put end to end on the first granule's
line numbering and its image lines concatenated, which gives one
:class:`~stereodem.sensor.models.aster.AsterModel` per band whose ephemeris and lattice span
the strip, and one stereo pair (3N, 3B) whose DEM has no seam to blend.

What is checked, in this order (each failure is one :class:`InputError` line naming the files):

1. metadata (:func:`pass_info`): the same WRS path (``ASTERSCENEID``, when present) and
   contiguous times (each granule starts after the previous one and before it ends, from
   ``RANGEBEGINNING/ENDING``, else the acquisition time);
2. geometry, per band (:func:`line_offset`): the next granule's lattice positions lie on the
   previous granule's ephemeris (within :data:`ORBIT_TOLERANCE_M`; another pass is km off)
   inside its time span (else no shared lines), at a whole number of lines (the line clocks
   agree within :data:`LINE_TOLERANCE`); the line offset comes from the geometry, not from
   ``ObservationTime`` (whose encoding is unverified, notes §4.5);
3. the overlapping image lines of the two granules agree (correlation at least
   :data:`MIN_OVERLAP_CORRELATION`: the same detector lines), and there is no gap.

Lines: the strip's line ``r`` of granule ``k`` is its own line ``r - first_line[k]``; in the
overlap the earlier granule gives the lines up to the middle of the overlap, the later one
the rest. The report (:attr:`AsterStrip.report`) gives per seam and band the offset, the
overlap, the orbit miss, the overlap correlation and how far the joined model departs from
the granule's own model over the granule (pixels).
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stereodem.core.errors import InputError
from stereodem.sensor.io.aster_l1a import open_aster_granule
from stereodem.sensor.io.aster_metadata import first_key
from stereodem.sensor.io.odl import flatten_odl
from stereodem.sensor.models.aster import AsterGeometry, AsterModel

#: largest distance (m) of a granule's satellite positions from the previous granule's
#: ephemeris at the matching time for one pass (real products: cm-level position noise;
#: the orbits of other passes are kilometres apart)
ORBIT_TOLERANCE_M = 50.0
#: largest departure (lines) of the line offset between granules from a whole number
LINE_TOLERANCE = 0.25
#: smallest correlation of the overlapping lines of consecutive granules
MIN_OVERLAP_CORRELATION = 0.9
#: largest time (s) between the end of one granule and the start of the next
MAX_GAP_S = 2.0
STRIP_BANDS = ("3N", "3B")


# ============================================================================ metadata


def _odl_time(flat: dict, date_key: str, time_key: str):
    date, tod = first_key(flat, date_key), first_key(flat, time_key)
    if date is None or tod is None:
        return None
    text = f"{date}T{str(tod).rstrip('Z')}"
    for fmt in ("%Y-%m-%dT%H:%M:%S.%f", "%Y-%m-%dT%H:%M:%S"):
        try:
            return _dt.datetime.strptime(text, fmt)
        except ValueError:
            continue
    return None


def pass_info(granule) -> dict:
    """``{"path", "granule_id", "wrs_path", "scene_row", "start", "stop"}`` of an opened
    granule (:class:`~stereodem.sensor.io.aster_l1a.AsterGranule`); ``None`` where absent.
    Times are naive UTC datetimes."""
    flat: dict = {}
    for tree in granule.odl.values():
        flat.update(flatten_odl(tree))
    sid = first_key(flat, "ASTERSCENEID")
    wrs = row = None
    if isinstance(sid, tuple) and len(sid) >= 2:
        wrs, row = int(sid[0]), int(sid[1])
    start = _odl_time(flat, "RANGEBEGINNINGDATE", "RANGEBEGINNINGTIME")
    stop = _odl_time(flat, "RANGEENDINGDATE", "RANGEENDINGTIME")
    if start is None and granule.metadata.get("acquisition_time"):
        start = _dt.datetime.fromisoformat(granule.metadata["acquisition_time"].rstrip("Z"))
    return dict(
        path=str(granule.path),
        granule_id=granule.granule_id,
        wrs_path=wrs,
        scene_row=row,
        start=start,
        stop=stop,
    )


def order_granules(granules) -> list:
    """The granules sorted by start time, checked to be consecutive granules of one pass
    by their metadata (see the module docstring, check 1); :class:`InputError` otherwise."""
    infos = [pass_info(g) for g in granules]
    names = [Path(i["path"]).name for i in infos]
    paths = {i["wrs_path"] for i in infos if i["wrs_path"] is not None}
    if len(paths) > 1:
        raise InputError(
            f"{', '.join(names)}: granules of different passes (WRS paths "
            f"{', '.join(str(i['wrs_path']) for i in infos)}); a strip joins "
            f"consecutive granules of one pass"
        )
    if any(i["start"] is None for i in infos):
        bad = [n for n, i in zip(names, infos) if i["start"] is None]
        raise InputError(
            f"{', '.join(bad)}: no acquisition time in the metadata; cannot order "
            f"the granules of a strip"
        )
    order = sorted(range(len(infos)), key=lambda k: infos[k]["start"])
    for a, b in zip(order[:-1], order[1:]):
        ia, ib = infos[a], infos[b]
        if ib["start"] <= ia["start"]:
            raise InputError(
                f"{names[a]}, {names[b]}: the same acquisition start "
                f"({ia['start'].isoformat()}): the same granule twice?"
            )
        end = ia["stop"] or ia["start"]
        gap = (ib["start"] - end).total_seconds()
        if gap > MAX_GAP_S:
            raise InputError(
                f"{names[a]}, {names[b]}: not consecutive granules of one pass "
                f"({names[b]} starts {gap:.0f} s after {names[a]} ends)"
            )
    return [granules[k] for k in order]


# ============================================================================ geometry


def line_offset(prev, nxt, names) -> dict:
    """Line of ``prev``'s numbering where ``nxt``'s line 0 lies (one band's models,
    :class:`~stereodem.sensor.models.aster.AsterModel`), from the satellite positions: each
    of ``nxt``'s lattice positions is placed on ``prev``'s ephemeris (the time of closest
    approach, Newton steps along the velocity). Returns ``{"offset_lines", "fraction",
    "orbit_miss_m", "shared_lattice_rows"}``; :class:`InputError` (naming ``names``) if the
    orbits differ, no lattice row falls in ``prev``'s span or the line clocks disagree."""
    lp = float(prev.line_period)
    eph = prev.ephemeris
    t_prev = prev.geometry.lattice_rows * lp
    p_next = nxt.geometry.satellite_positions
    rows_next = nxt.geometry.lattice_rows
    d = np.linalg.norm(prev.geometry.satellite_positions[None] - p_next[:, None], axis=-1)
    tau = t_prev[np.argmin(d, axis=1)]
    for _ in range(6):
        p, v = eph.state(tau)
        tau = tau - np.sum((p - p_next) * v, -1) / np.sum(v * v, -1)
    inside = (tau >= t_prev[0] - 1e-6) & (tau <= t_prev[-1] + 1e-6)
    a, b = names
    if not inside.any():
        after = (tau[0] - t_prev[-1]) / lp
        raise InputError(
            f"{a}, {b}: not consecutive granules ({b} starts about "
            f"{after:.0f} lines after the end of {a}'s lattice: no shared lines)"
        )
    miss = float(np.max(np.linalg.norm(eph.position(tau[inside]) - p_next[inside], axis=-1)))
    if miss > ORBIT_TOLERANCE_M:
        raise InputError(
            f"{a}, {b}: not one pass (the satellite positions of {b} are "
            f"{miss:.0f} m off {a}'s orbit)"
        )
    delta = tau[inside] / lp - rows_next[inside]
    off = float(np.median(delta))
    k = int(round(off))
    if abs(off - k) > LINE_TOLERANCE or np.ptp(delta) > 2 * LINE_TOLERANCE:
        raise InputError(
            f"{a}, {b}: the granules' lines are not on one line clock (offset "
            f"{off:.2f} lines, spread {np.ptp(delta):.2f})"
        )
    return dict(
        offset_lines=k,
        fraction=round(off - k, 4),
        orbit_miss_m=round(miss, 4),
        shared_lattice_rows=int(inside.sum()),
    )


def _overlap_correlation(a, b) -> float:
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 16:
        return float("nan")
    x, y = a[ok].astype(np.float64), b[ok].astype(np.float64)
    if x.std() == 0 or y.std() == 0:
        return float("nan")
    return float(np.corrcoef(x, y)[0, 1])


def _model_departure(strip_model, model, first_line: int, n: int = 7) -> float:
    """Largest image distance (px) between ``model`` and the strip model (shifted by
    ``first_line``) at an n x n grid of the granule's pixels localised at the terrain's
    middle height of the lattice (0 m)."""
    c, r = np.meshgrid(np.linspace(0, model.width - 1, n), np.linspace(0, model.height - 1, n))
    lon, lat = model.localize(c.ravel(), r.ravel(), np.zeros(c.size))
    cs, rs = strip_model.project(lon, lat, np.zeros(c.size))
    return float(np.max(np.hypot(cs - c.ravel(), rs - first_line - r.ravel())))


@dataclass
class StripBand:
    """One band of a strip: the joined image (float32, NaN at fill), its joined model, and
    where each granule's line 0 lies in the strip's lines."""

    band: str
    image: np.ndarray
    model: object
    first_lines: list
    seams: list = field(default_factory=list)  #: per seam: offset, overlap, checks


def join_band(granules, band: str, *, radiometric: bool = True) -> StripBand:
    """Join band ``band`` of ordered consecutive granules (see the module docstring)."""
    bands = [g.band(band) for g in granules]
    models = [b.model for b in bands]
    names = [Path(g.path).name for g in granules]
    m0 = models[0]
    for m, name in zip(models[1:], names[1:]):
        if m.width != m0.width or not np.array_equal(
            m.geometry.lattice_cols, m0.geometry.lattice_cols
        ):
            raise InputError(
                f"{names[0]}, {name}: band {band} has {m0.width} and {m.width} "
                f"detectors / different lattice columns: not one instrument's pass"
            )
    firsts, seams = [0], []
    for k in range(1, len(models)):
        s = line_offset(models[k - 1], models[k], (names[k - 1], names[k]))
        firsts.append(firsts[-1] + s["offset_lines"])
        end_prev = firsts[k - 1] + models[k - 1].height
        s["overlap_lines"] = int(end_prev - firsts[k])
        if s["overlap_lines"] < 0:
            raise InputError(
                f"{names[k - 1]}, {names[k]}: band {band} lines "
                f"{end_prev}..{firsts[k] - 1} of the strip are missing"
            )
        s["seam_line"] = int((firsts[k] + end_prev) // 2)
        s["granules"] = [names[k - 1], names[k]]
        seams.append(s)
    # the lattice: every granule's rows on the strip's numbering, later rows past the last one
    keep_rows, pieces = -np.inf, []
    for m, f0 in zip(models, firsts):
        g = m.geometry
        rows = g.lattice_rows + f0
        sel = rows > keep_rows + 0.5
        pieces.append((g, sel, f0))
        keep_rows = rows[sel][-1] if sel.any() else keep_rows

    def stack(attr):
        parts = [getattr(g, attr) for g, _, _ in pieces]
        if any(p is None for p in parts):
            return None
        return np.concatenate([p[sel] for p, (_, sel, _) in zip(parts, pieces)])

    lattice = np.concatenate([g.lattice[sel] + np.array([0.0, f0]) for g, sel, f0 in pieces])
    conv = {g.velocity_convention for g, _, _ in pieces}
    rows_total = firsts[-1] + models[-1].height
    geom = AsterGeometry(
        lattice=lattice,
        sight_vectors=stack("sight_vectors"),
        world_sight_vectors=stack("world_sight_vectors"),
        satellite_positions=stack("satellite_positions"),
        image_cols=int(m0.width),
        image_rows=int(rows_total),
        path=f"{granules[0].path} +{len(granules) - 1}",
        satellite_velocities=stack("satellite_velocities"),
        velocity_convention=conv.pop() if len(conv) == 1 else "unknown",
        observation_times=stack("observation_times"),
    )
    model = AsterModel(
        geom,
        line_period=m0.line_period,
        inertial_frame=m0.inertial_frame,
        velocity_method=m0.velocity_method,
        name=f"strip_{band}",
    )
    # the image: each granule's lines, the overlap split at its middle
    image = np.full((rows_total, m0.width), np.nan, np.float32)
    for k, (b, f0) in enumerate(zip(bands, firsts)):
        img = b.image(radiometric)
        lo = seams[k - 1]["seam_line"] if k else f0
        hi = seams[k]["seam_line"] if k < len(seams) else f0 + img.shape[0]
        image[lo:hi] = img[lo - f0 : hi - f0]
        if k:
            s = seams[k - 1]
            prev, pf = bands[k - 1].image(radiometric), firsts[k - 1]
            ov = slice(f0, pf + prev.shape[0])
            s["overlap_correlation"] = round(
                _overlap_correlation(
                    prev[ov.start - pf : ov.stop - pf], img[ov.start - f0 : ov.stop - f0]
                ),
                4,
            )
            if s["overlap_lines"] > 0 and not s["overlap_correlation"] >= MIN_OVERLAP_CORRELATION:
                raise InputError(
                    f"{names[k - 1]}, {names[k]}: the overlapping band {band} lines "
                    f"differ (correlation {s['overlap_correlation']:.2f}): not the "
                    f"same lines of one pass"
                )
    for k, s in enumerate(seams, 1):
        s["model_departure_px"] = round(_model_departure(model, models[k], firsts[k]), 6)
    return StripBand(band, image, model, firsts, seams)


@dataclass
class AsterStrip:
    """Consecutive granules of one pass joined (:func:`open_aster_strip`)."""

    granules: list  #: AsterGranule, in time order
    bands: dict  #: "3N" / "3B" -> StripBand
    report: dict

    def band(self, name: str) -> StripBand:
        return self.bands[name]


def open_aster_strip(paths, *, radiometric: bool = True) -> AsterStrip:
    """Open the granules ``paths`` (any order), check that they are consecutive granules of
    one pass and join their 3N and 3B bands (see the module docstring)."""
    if len(paths) < 2:
        raise InputError("a strip needs at least two granules")
    granules = order_granules([open_aster_granule(p) for p in paths])
    bands = {b: join_band(granules, b, radiometric=radiometric) for b in STRIP_BANDS}
    infos = [pass_info(g) for g in granules]
    report = dict(
        method="joined models: each band's lattices and image lines put end to end on the first "
        "granule's line numbering (one orbit, attitude and line clock for the pass), one "
        "AsterModel per band spanning the strip, one stereo pair, one DEM",
        why="the granules of a pass are cut from one acquisition (one orbit, attitude and line "
        "clock), so the joined model is the pass's own and the DEM has no seam to blend; "
        "per-granule DEMs would repeat the sparse stage and the relative pointing per "
        "granule and need an adjustment on the overlap to remove the steps these make",
        granules=[
            dict(
                path=i["path"],
                granule_id=i["granule_id"],
                wrs_path=i["wrs_path"],
                scene_row=i["scene_row"],
                start=i["start"].isoformat() if i["start"] else None,
                **{f"first_line_{b}": bands[b].first_lines[k] for b in STRIP_BANDS},
                **{f"lines_{b}": g.band(b).model.height for b in STRIP_BANDS},
            )
            for k, (i, g) in enumerate(zip(infos, granules))
        ],
        seams={b: bands[b].seams for b in STRIP_BANDS},
        size={b: [int(bands[b].model.width), int(bands[b].model.height)] for b in STRIP_BANDS},
    )
    return AsterStrip(granules, bands, report)


__all__ = [
    "AsterStrip",
    "StripBand",
    "join_band",
    "line_offset",
    "open_aster_strip",
    "order_granules",
    "pass_info",
]
