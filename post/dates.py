"""Acquisition dates of DEMs: given on the command line, in a CSV, or read from what stereodem
wrote with the DEM.

Where a DEM's date is found, in order:

1. the GeoTIFF tags ``ACQUISITION_DATE`` / ``ASTER_ACQUISITION_TIME`` / ``TIFFTAG_DATETIME``
   (``YYYY-MM-DD``, ISO 8601 or ``YYYY:MM:DD HH:MM:SS``);
2. the ``run.json`` or ``dem_report.json`` beside the DEM (written by ``stereodem run`` /
   ``stereodem dem``), whose ``input_metadata`` holds the granule's ``ASTER_ACQUISITION_TIME``.

Dates are ``numpy.datetime64[s]`` (UTC); rates use decimal years
(:func:`stereodem.sensor.simulation.multidate.decimal_year`).
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import rasterio

from stereodem.core.errors import InputError, not_found

DATE_TAGS = ("ACQUISITION_DATE", "ASTER_ACQUISITION_TIME", "TIFFTAG_DATETIME")
SIDECARS = ("run.json", "dem_report.json")


def parse_date(text, where: str = "") -> np.datetime64:
    """A date or date-time string -> ``datetime64[s]``; :class:`InputError` naming ``where``."""
    s = str(text).strip().rstrip("Z")
    if len(s) >= 19 and s[4] == ":" and s[7] == ":":  # TIFF "YYYY:MM:DD HH:MM:SS"
        s = s[:10].replace(":", "-") + "T" + s[11:]
    try:
        d = np.datetime64(s.replace(" ", "T"), "s")
    except ValueError:
        raise InputError(
            f"{where}: cannot read the date {text!r} (expected YYYY-MM-DD or ISO 8601)"
        ) from None
    if np.isnat(d):
        raise InputError(f"{where}: no date in {text!r}")
    return d


def date_from_metadata(path) -> np.datetime64 | None:
    """The date stereodem stored with DEM ``path`` (module docstring), or None."""
    path = Path(path)
    try:
        with rasterio.open(path) as ds:
            tags = ds.tags()
    except rasterio.errors.RasterioIOError:
        return None
    for k in DATE_TAGS:
        if tags.get(k):
            return parse_date(tags[k], f"{path} tag {k}")
    for name in SIDECARS:
        side = path.parent / name
        if side.is_file():
            try:
                meta = json.loads(side.read_text()).get("input_metadata") or {}
            except (OSError, ValueError):
                continue
            if meta.get("ASTER_ACQUISITION_TIME"):
                return parse_date(meta["ASTER_ACQUISITION_TIME"], f"{side}")
    return None


def read_dates_csv(path) -> dict:
    """A CSV of ``path,date`` rows (a header line is allowed) -> {resolved path: datetime64}."""
    out = {}
    try:
        rows = list(csv.reader(Path(path).read_text().splitlines()))
    except FileNotFoundError:
        raise InputError(not_found(path, "dates CSV")) from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read the dates CSV ({exc.strerror})") from None
    for i, row in enumerate(rows, start=1):
        if not row or not "".join(row).strip() or row[0].startswith("#"):
            continue
        if len(row) < 2:
            raise InputError(f"{path} line {i}: expected path,date, got {','.join(row)!r}")
        p, d = row[0].strip(), row[1].strip()
        if i == 1 and d.lower() in ("date", "time", "acquisition_date"):
            continue
        q = Path(p) if Path(p).is_absolute() else Path(path).parent / p
        out[str(q.resolve())] = parse_date(d, f"{path} line {i}")
    return out


def dem_dates(dems, dates=None, *, now=None) -> list:
    """The date of every DEM in ``dems`` (paths), checked.

    ``dates``: None (from metadata), a list of date strings (one per DEM, in order), or the path
    of a CSV (``path,date``). Raises :class:`InputError` (one line) for a DEM without a date, a
    count mismatch, a date in the future (after ``now``, default today UTC) or a date that
    repeats another DEM's.
    """
    dems = [str(p) for p in dems]
    if isinstance(dates, (str, Path)) and Path(str(dates).strip()).suffix.lower() in (
        ".csv",
        ".txt",
    ):
        table = read_dates_csv(dates)
        found = []
        for p in dems:
            d = table.get(str(Path(p).resolve()))
            if d is None:
                raise InputError(f"{p}: no date for this DEM in {dates}")
            found.append(d)
    elif dates is not None:
        items = [
            s for s in (dates.split(",") if isinstance(dates, str) else dates) if str(s).strip()
        ]
        if len(items) != len(dems):
            raise InputError(f"--dates: {len(items)} date(s) for {len(dems)} DEM(s)")
        found = [parse_date(s, f"--dates for {p}") for s, p in zip(items, dems)]
    else:
        found = []
        for p in dems:
            d = date_from_metadata(p)
            if d is None:
                raise InputError(
                    f"{p}: no acquisition date (no ACQUISITION_DATE tag, no run.json or "
                    "dem_report.json with a granule's acquisition time beside it); give "
                    "--dates D1,D2,... or a CSV path,date"
                )
            found.append(d)
    now = np.datetime64(now, "s") if now is not None else np.datetime64("now", "s")
    seen = {}
    for p, d in zip(dems, found):
        if d > now:
            raise InputError(f"{p}: date {d} is in the future")
        day = np.datetime64(d, "D")
        if day in seen:
            raise InputError(
                f"{p}: date {day} repeats that of {seen[day]} (one DEM per date; "
                "mosaic same-day DEMs first)"
            )
        seen[day] = p
    return found
