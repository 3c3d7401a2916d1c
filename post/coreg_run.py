"""One co-registration job: read the DEM and the reference (DEM or altimetry points), reconcile
their vertical references, build the stable mask, fit the chain, write the products.

Products in the output folder (every write atomic, nothing written before the inputs are
checked):

* ``dem_coregistered.tif`` — the corrected DEM on the DEM's own grid (COG, vertical reference
  in the CRS);
* ``coregistration.json`` — the chain, each step's parameters with σ, the stable-terrain
  statistics before/after each step, the mask's share, per-point residuals for points;
* ``coreg_dh.png`` (dh before/after) and ``coreg_<step>.png`` (each bias curve with its fit).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import rasterio
from pyproj import Geod
from pyproj.exceptions import ProjError
from scipy import ndimage

from stereodem.core import geodesy, jsonutil
from stereodem.core.dem import DEM, to_vertical_of
from stereodem.core.errors import InputError, StereodemError, VerticalReferenceError
from stereodem.core.raster import write_text_atomic

from . import terrain
from .altimetry import AltimetryPoints, is_points_file, read_points
from .coreg import MIN_STABLE_FRACTION, CoregChain, bilinear, parse_chain, reference_on_grid
from .dates import DATE_TAGS, date_from_metadata
from .masks import StableMask, check_stable
from .track import TRACK_FRAME_TAG, TrackFrame, track_frame_of

log = logging.getLogger(__name__)

#: DEM tag holding the ground-track heading (degrees clockwise from north) of a stereodem DEM
TRACK_HEADING_TAG = "STEREODEM_TRACK_HEADING"


@dataclass
class CoregJob:
    """Inputs and options of a co-registration (paths, as on the command line)."""

    dem: str
    ref: str
    chain: str = "nuth_kaab"
    dem_vertical: str | None = None
    ref_vertical: str | None = None
    track_angle: float | None = None
    exclude: list = field(default_factory=list)
    include: list = field(default_factory=list)
    stable_mask: str | None = None
    min_slope: float | None = None
    max_slope: float | None = None
    outlier_nmad: float | None = 5.0
    max_samples: int = 200_000

    def check(self):
        """One-line :class:`InputError` for limits that cannot be honoured: slopes not in
        0–90 degrees or not finite, ``min_slope`` not below ``max_slope``, ``outlier_nmad``
        negative or not finite (``None`` or 0: no outlier rejection)."""
        for name, v in (("--min-slope", self.min_slope), ("--max-slope", self.max_slope)):
            if v is not None and not (np.isfinite(v) and 0.0 <= v <= 90.0):
                raise InputError(f"{name} must be a slope in degrees, 0 to 90, got {v:g}")
        if (
            self.min_slope is not None
            and self.max_slope is not None
            and not self.min_slope < self.max_slope
        ):
            raise InputError(
                f"--min-slope {self.min_slope:g} must be below --max-slope {self.max_slope:g}: "
                "no slope would be stable terrain"
            )
        v = self.outlier_nmad
        if v is not None and not (np.isfinite(v) and v >= 0.0):
            raise InputError(f"--outlier-nmad must be a number >= 0 (0: off), got {v:g}")

    def mask_sources(self) -> list[str]:
        """What restricts the stable terrain, as the options that said it (for messages)."""
        out = [f"--exclude {p}" for p in self.exclude or []]
        out += [f"--include {p}" for p in self.include or []]
        if self.stable_mask:
            out.append(f"--stable-mask {self.stable_mask}")
        if self.min_slope is not None:
            out.append(f"--min-slope {self.min_slope:g}")
        if self.max_slope is not None:
            out.append(f"--max-slope {self.max_slope:g}")
        return out


def track_heading(model, shape, h: float = 0.0) -> float:
    """Ground-track heading (degrees clockwise from north, 0–360) of a pushbroom-like image:
    the azimuth on the WGS84 ellipsoid from the image centre to the point 100 rows further
    (rows follow the satellite's motion), both localised at height ``h``."""
    rows, cols = shape[:2]
    c, r = (cols - 1) / 2.0, (rows - 1) / 2.0
    lon, lat = model.localize(np.array([c, c]), np.array([r, r + 100.0]), np.array([h, h]))
    az, _, _ = Geod(ellps="WGS84").inv(lon[0], lat[0], lon[1], lat[1])
    return float(az % 360.0)


def track_tags(model, shape, crs=None, heights=None) -> dict:
    """The DEM tags of the track of an image of ``shape`` seen by ``model``:
    ``STEREODEM_TRACK_HEADING`` (degrees clockwise from north) and, given the DEM's ``crs``,
    ``STEREODEM_TRACK_FRAME`` (:class:`~stereodem.post.track.TrackFrame`, fitted at the
    median of ``heights``, m). What the model cannot give is left out (a localisation failure
    never fails the DEM)."""
    tags = {}
    try:
        tags[TRACK_HEADING_TAG] = f"{track_heading(model, shape):.4f}"
    except (ValueError, ArithmeticError, NotImplementedError, StereodemError) as exc:
        log.info("no track heading for the DEM tags: %s", exc)
    if crs is not None:
        h = np.asarray(heights, np.float64) if heights is not None else np.zeros(1)
        h0 = float(np.nanmedian(h)) if np.isfinite(h).any() else 0.0

        try:
            tags[TRACK_FRAME_TAG] = TrackFrame.from_model(model, shape, crs, height=h0).to_tag()
        except (ValueError, ArithmeticError, NotImplementedError, StereodemError, ProjError) as exc:
            log.info("no track frame for the DEM tags: %s", exc)
    return tags


#: the tags of a stereodem DEM that stay true of a DEM made from it on its own grid (``stereodem
#: filter``'s clean DEM, ``stereodem coregister``'s corrected one): the track that
#: ``along_track``/``cross_track`` read and the acquisition date ``stereodem stack`` reads
CARRIED_TAGS = (TRACK_HEADING_TAG, TRACK_FRAME_TAG, *DATE_TAGS)


def carried_tags(path) -> dict:
    """The :data:`CARRIED_TAGS` of the DEM file ``path`` (none of an unreadable file), plus its
    acquisition date as ``ACQUISITION_DATE`` when only the ``run.json``/``dem_report.json``
    beside it gives one (:func:`stereodem.post.dates.date_from_metadata`): a DEM written into
    another folder keeps its date."""
    try:
        with rasterio.open(path) as ds:
            tags = ds.tags()
    except rasterio.errors.RasterioIOError:
        return {}
    out = {k: tags[k] for k in CARRIED_TAGS if tags.get(k)}
    if not any(k in out for k in DATE_TAGS):
        try:
            when = date_from_metadata(path)
        except InputError:  # an unreadable date beside it: the DEM is read without one
            when = None
        if when is not None:
            out["ACQUISITION_DATE"] = str(when)
    return out


def track_heading_of(path) -> float | None:
    """The ground-track heading a stereodem DEM carries in its tags, if any."""
    try:
        with rasterio.open(path) as ds:
            v = ds.tags().get(TRACK_HEADING_TAG)
    except rasterio.errors.RasterioIOError:
        return None
    try:
        return float(v) if v is not None else None
    except ValueError:
        return None


def reconcile(dem: DEM, ref):
    """Bring ``ref`` (DEM or points) to ``dem``'s vertical reference; a note says what was
    done. One-line :class:`VerticalReferenceError` when one side is unknown."""
    if dem.vertical is None and ref.vertical is None and isinstance(ref, AltimetryPoints):
        raise VerticalReferenceError(f"{ref.path or 'points'}: vertical reference unknown")
    # the one rule of assess, change and stack: the geoid other than EGM96 is said here too
    return to_vertical_of(ref, dem, name="reference")


def load_inputs(job: CoregJob):
    """The DEM, the reference (in the DEM's vertical reference), a note, and the track: the
    heading (``--track-angle`` or the DEM's tag) and the DEM's sensor-model track frame
    (:class:`~stereodem.post.track.TrackFrame`, None without ``--track-angle`` only)."""
    dem = DEM.from_file(job.dem, vertical=job.dem_vertical)
    if is_points_file(job.ref):
        ref = read_points(job.ref, vertical=job.ref_vertical)
    else:
        ref = DEM.from_file(job.ref, vertical=job.ref_vertical)
    ref, note = reconcile(dem, ref)
    return dem, ref, note, track_of(job.dem, dem.crs, job.track_angle)


def track_of(path, crs, track_angle: float | None = None):
    """``(heading, frame)`` of the DEM file ``path`` (in ``crs``): ``track_angle`` and no frame
    when given (an explicit heading wins), else the tags' heading and
    :class:`~stereodem.post.track.TrackFrame` (dropped, with a warning, when fitted in
    another CRS); ``(None, None)`` when the file says nothing."""
    if track_angle is not None:
        return float(track_angle), None
    if path is None:
        return None, None

    frame = track_frame_of(path)
    if frame is not None and not frame.matches(crs):
        log.warning(
            "%s: its track frame is for another CRS (%s); the heading is used", path, frame.crs
        )
        frame = None
    return track_heading_of(path), frame


def stable_mask(job: CoregJob, dem: DEM, ref) -> np.ndarray:
    """The stable mask of the job on the DEM grid (vectors, raster, slope; the outliers are
    left out later, by :func:`_fit`). One-line :class:`InputError` naming the options that
    did it when under 5 % of the DEM's valid cells are left, saying how much is."""
    sm = StableMask(
        exclude=list(job.exclude or []),
        include=list(job.include or []),
        raster=job.stable_mask,
        min_slope=job.min_slope,
        max_slope=job.max_slope,
        outlier_nmad=None,
    )
    slope = None
    if job.min_slope is not None or job.max_slope is not None:
        slope = terrain.slope_deg(dem.heights, dem.transform, dem.crs)
    m = sm.array(dem, slope=slope)
    sources = job.mask_sources()
    if sources:
        check_stable(
            m,
            np.isfinite(dem.heights),
            min_fraction=MIN_STABLE_FRACTION,
            what=f"{job.dem}: {', '.join(sources)}",
        )
    return m


def run(
    job: CoregJob, out_dir, *, overwrite: bool = False, figures: bool = True, creation_options=None
) -> dict:
    """Fit and apply the chain; write the products into ``out_dir`` (checked by the caller with
    :func:`stereodem.core.raster.check_output_dir`, created here once the fit succeeded).
    Returns the JSON report (a dict)."""
    needs_heading = any(
        s.strip().split(":")[0] in ("along_track", "cross_track") for s in job.chain.split(",")
    )
    job.check()
    chain = parse_chain(job.chain)  # bad text fails before any reading
    dem, ref, note, (heading, frame) = load_inputs(job)
    if needs_heading and heading is None and frame is None:
        raise InputError(
            f"{job.dem}: along_track/cross_track need the ground-track heading; the DEM "
            "carries none: give --track-angle DEG (clockwise from north)"
        )
    mask = stable_mask(job, dem, ref)
    chain, mask, n_outliers = _fit(chain, ref, dem, mask, (heading, frame), job)
    out = chain.apply(dem)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)  # only now: bad inputs leave nothing behind
    out.write(
        out_dir / "dem_coregistered.tif",
        overwrite=overwrite,
        creation_options=creation_options,
        tags=carried_tags(job.dem),  # its track and date, for a later chain or stack
    )
    report = {
        "dem": job.dem,
        "reference": job.ref,
        "reference_kind": "points" if isinstance(ref, AltimetryPoints) else "dem",
        "chain": job.chain,
        "vertical": note,
        "vertical_reference": dem.vertical,
        "track_heading_deg": heading,
        "track_frame": frame.describe() if frame is not None else None,
        "stable": _mask_summary(chain, mask, dem, job, ref, n_outliers),
        "steps": chain.report(),
        "sigma_note": "formal least-squares standard deviations (samples taken as independent)",
    }
    if isinstance(ref, AltimetryPoints):
        report["points"] = _point_residuals(ref, dem, out, mask)
    files = {"dem": str(out_dir / "dem_coregistered.tif")}
    if figures:
        from .coreg_figures import chain_figures

        files.update(chain_figures(chain, ref, dem, out, mask, out_dir, overwrite=overwrite))
    report["files"] = files
    write_text_atomic(
        out_dir / "coregistration.json",
        jsonutil.dumps(jsonutil.stamped(report)),
        overwrite=overwrite,
    )
    return report


def _fit(chain: CoregChain, ref, dem, mask, track, job):
    """Fit ``chain``; with ``outlier_nmad``, cells whose first ``dh`` is beyond that many NMADs
    of the median (clouds, blunders) leave the stable terrain first (DEM references).
    Returns ``(chain, mask, n_outliers)``: the mask the fit used and the valid stable cells the
    outlier test removed."""
    n_outliers = 0
    if job.outlier_nmad and not isinstance(ref, AltimetryPoints):
        dh = dem.heights.astype(np.float64) - reference_on_grid(ref, dem)
        kept = mask & StableMask(outlier_nmad=job.outlier_nmad).array(
            dem, dh=np.where(mask, dh, np.nan)
        )
        n_outliers = int((mask & ~kept & np.isfinite(dh)).sum())
        mask = kept
    heading, frame = track
    chain = chain.fit(
        ref,
        dem,
        stable=mask,
        track_angle_deg=heading,
        track_frame=frame,
        max_samples=job.max_samples,
    )
    return chain, mask, n_outliers


def _mask_summary(chain, mask, dem, job, ref, n_outliers):
    """The stable terrain the fit used (after the outlier test), on the DEM's valid cells."""
    valid = np.isfinite(dem.heights)
    return {
        "stable_cells": int((mask & valid).sum()),
        "valid_cells": int(valid.sum()),
        "stable_fraction": float((mask & valid).sum() / max(valid.sum(), 1)),
        "samples_used": int(chain.sampler.rows.size) if chain.sampler is not None else 0,
        "min_slope_deg": job.min_slope,
        "max_slope_deg": job.max_slope,
        # points: no outlier test on the mask (each step's fit is robust)
        "outlier_nmad": None if isinstance(ref, AltimetryPoints) else (job.outlier_nmad or None),
        "outlier_cells": n_outliers,
    }


def _point_residuals(points: AltimetryPoints, dem: DEM, out: DEM, mask) -> dict:
    x, y = geodesy.lonlat_to_crs(points.lon, points.lat, dem.crs)
    c, r = ~dem.transform @ (np.asarray(x), np.asarray(y))
    rows, cols = np.asarray(r) - 0.5, np.asarray(c) - 0.5
    before = bilinear(dem.heights, rows, cols) - points.h
    after = bilinear(out.heights, rows, cols) - points.h

    used = ndimage.map_coordinates(mask.astype(np.uint8), [rows, cols], order=0, cval=0).astype(
        bool
    )
    return {
        "n": int(points.h.size),
        "n_on_dem": int(np.isfinite(before).sum()),
        "columns": ["lon", "lat", "h", "dh_before", "dh_after", "stable"],
        "rows": [
            [float(a), float(b), float(h), _f(u), _f(v), bool(w)]
            for a, b, h, u, v, w in zip(points.lon, points.lat, points.h, before, after, used)
        ],
    }


def _f(v):
    return float(v) if np.isfinite(v) else None
