"""Sanity of a stereo job: the checks that turn a quietly wrong DEM into a clear error or a
loud, machine-readable warning. :func:`stereodem.stereo.pipeline.make_dem` runs them on its
own inputs (:func:`check_pair`) and result (:meth:`CheckedPair.report`), so Python callers get
the refusals and findings of ``stereodem dem``; the input layer runs :func:`check_texture`.

Before the stereo work (errors, :class:`~stereodem.core.errors.InputError`):

* :func:`check_texture` — an image with nothing to match (constant, all zeros, all no-data);
* :func:`check_base` — a pair without a usable base: base-to-height ratio below
  :data:`MIN_BASE_TO_HEIGHT`, measured from the sensor models (the same image twice gives 0);
* :func:`check_seed_dem` — a seed DEM that does not cover the scene or whose heights are
  implausible for the models (outside their validity range: feet instead of metres, say).

Adjustments, reported as warnings (:func:`comparable_radiometry`): images of different bit
depth are brought to one radiometric scale before matching.

After the stereo work (:func:`check_result`, findings of severity ``"suspect"``): the
heights pile against a bound of the height search range
(:func:`stereodem.stereo.sparse_stage.height_pileup`, counted per tile), i.e. the terrain is
probably outside the range (a wrong ``--height-range``, a seed DEM in the wrong units). A suspect
result makes the command exit with status 1 unless ``--force``; the findings are written in
``dem_report.json`` / ``run.json`` under ``warnings`` either way.
"""

from __future__ import annotations

import logging
import os
from dataclasses import asdict, dataclass, field

import numpy as np

from stereodem.core.errors import DEMCoverageError, DEMError, InputError, StereodemError
from stereodem.sensor.models.base import pair_height_bounds

from .plan import base_to_height, seed_height_range

log = logging.getLogger(__name__)

__all__ = [
    "Finding",
    "SuspectResultError",
    "MIN_BASE_TO_HEIGHT",
    "check_base",
    "check_texture",
    "check_seed_dem",
    "comparable_radiometry",
    "check_result",
    "status",
    "CheckedPair",
    "check_pair",
]

#: Smallest usable base-to-height ratio. The height error of a match error of s pixels is
#: s x GSD / (B/H): at 0.02 and 0.2 px that is already 10 GSD (ASTER 3N/3B: B/H 0.6).
MIN_BASE_TO_HEIGHT = 0.02
#: Smallest share of neighbouring pixel pairs that must differ for an image to have texture.
MIN_TEXTURED_FRACTION = 0.05
#: Smallest share of the left image's footprint a seed DEM must cover.
MIN_SEED_COVERAGE = 0.5


@dataclass
class Finding:
    """One machine-readable sanity finding (``code``: stable identifier; ``severity``:
    ``"warning"`` informs, ``"suspect"`` fails the job unless forced)."""

    code: str
    severity: str
    message: str
    value: float | None = None
    limit: float | None = None

    def to_dict(self) -> dict:
        return asdict(self)


class SuspectResultError(StereodemError):
    """The result failed a sanity check; its products and report are kept for inspection."""


def status(findings) -> str:
    """``"suspect"`` when any finding is, else ``"ok"``."""
    return "suspect" if any(f["severity"] == "suspect" for f in findings) else "ok"


# ----------------------------------------------------------------------------- before


def check_texture(image, name: str):
    """:class:`InputError` if ``image`` has (almost) no valid pixel or no texture: fewer than
    :data:`MIN_TEXTURED_FRACTION` of horizontally neighbouring valid pixels differ."""
    rows = np.asarray(image[::4], dtype=np.float32)
    finite = np.isfinite(rows)
    if finite.mean() < 0.01:
        raise InputError(
            f"{name}: (almost) no valid pixel ({100 * finite.mean():.2f} % of the image)"
        )
    # pairs of valid neighbours that differ (boolean arrays: no float temporaries to touch)
    both = finite[:, 1:] & finite[:, :-1]
    differ = rows[:, 1:] != rows[:, :-1]
    differ &= both
    n = np.count_nonzero(both)
    frac = np.count_nonzero(differ) / n if n else 0.0
    if frac < MIN_TEXTURED_FRACTION:
        raise InputError(
            f"{name}: no texture to match ({100 * frac:.2f} % of neighbouring pixels "
            "differ; a constant or empty image?)"
        )


def check_base(left, right, height_range) -> float:
    """:class:`InputError` if the pair's base-to-height ratio is below
    :data:`MIN_BASE_TO_HEIGHT`; returns the ratio."""
    h0 = 0.5 * (float(height_range[0]) + float(height_range[1]))
    bh = base_to_height(left, right, h0)
    if not bh >= MIN_BASE_TO_HEIGHT:
        raise InputError(
            f"the pair has no usable stereo base: base-to-height ratio {bh:.3g} "
            f"(floor {MIN_BASE_TO_HEIGHT}); the two images see the ground from the "
            "same direction (the same image twice?)"
        )
    return bh


def check_seed_dem(seed, left, right, *, name: str = "seed DEM", samples: int = 7):
    """:class:`DEMError` if the seed DEM's heights lie outside the models' common validity
    range, :class:`DEMCoverageError` if it covers less than :data:`MIN_SEED_COVERAGE` of the
    left image's footprint (checked on a ``samples`` x ``samples`` grid of pixels). Only the
    seed's heights under the scene count (:func:`~stereodem.stereo.plan.seed_height_range`): a
    DEM far larger than the scene may hold heights the models were never meant for elsewhere;
    a DEM with no height under the scene is a :class:`DEMCoverageError`."""
    lo, hi = pair_height_bounds(left, right)
    try:
        hmin, hmax = seed_height_range(seed, left, right)
    except DEMCoverageError as exc:
        raise DEMCoverageError(
            f"{name} {str(exc).rstrip('.')}: is it the DEM of this scene?"
        ) from None
    if hmin < lo or hmax > hi:
        raise DEMError(
            f"{name} {seed.path or ''}: heights {hmin:.0f}..{hmax:.0f} m (ellipsoidal) "
            f"are implausible for the sensor models (valid {lo:.0f}..{hi:.0f} m): wrong "
            "units (feet?) or vertical reference?"
        )
    c, r = (
        a.ravel()
        for a in np.meshgrid(
            np.linspace(0, left.width - 1, samples), np.linspace(0, left.height - 1, samples)
        )
    )
    with np.errstate(invalid="ignore"):
        loc = left.localize_dem(c, r, seed, h0=0.5 * (hmin + hmax))
    cover = float(np.isfinite(np.asarray(loc.h, float)).mean())
    if cover < MIN_SEED_COVERAGE:
        raise DEMCoverageError(
            f"{name} {seed.path or ''}: covers {100 * cover:.0f} % of the left "
            f"image's footprint (at least {100 * MIN_SEED_COVERAGE:.0f} % needed); "
            "is it the DEM of this scene?"
        )
    return cover


def comparable_radiometry(left, right, left_dtype=None, right_dtype=None):
    """The two images on one radiometric scale when their files differ in bit depth.

    The matcher stretches both images jointly, so a 16-bit image beside an 8-bit one leaves
    the 8-bit one nearly black. The right image is mapped linearly so that its 1 and 99 %
    percentiles meet the left image's. Returns ``(left, right, findings)``.
    """
    if left_dtype is None or right_dtype is None or np.dtype(left_dtype) == np.dtype(right_dtype):
        return left, right, []
    pl = np.nanpercentile(np.asarray(left[::4, ::4], np.float32), [1.0, 99.0])
    pr = np.nanpercentile(np.asarray(right[::4, ::4], np.float32), [1.0, 99.0])
    if not (np.all(np.isfinite(pl)) and np.all(np.isfinite(pr))) or pr[1] <= pr[0]:
        return left, right, []
    gain = (pl[1] - pl[0]) / (pr[1] - pr[0])
    right = ((np.asarray(right, np.float32) - pr[0]) * np.float32(gain) + np.float32(pl[0])).astype(
        np.float32
    )
    msg = (
        f"the images differ in bit depth ({np.dtype(left_dtype).name} / "
        f"{np.dtype(right_dtype).name}): the right image was rescaled by {gain:.4g} for matching"
    )
    log.warning(msg)
    return left, right, [Finding("radiometry_rescaled", "warning", msg, float(gain)).to_dict()]


# ----------------------------------------------------------------------------- after


def check_result(info) -> list[dict]:
    """Findings about a stereo result from its run figures (``info`` of
    :func:`stereodem.stereo.pipeline.make_dem`): a ``height_pileup`` flagged suspect (too many
    heights at a bound of their tile's search range) is a ``heights_at_search_bound`` finding."""
    out = []
    pile = info.height_pileup or {}
    if pile.get("suspect"):
        share = max(pile["low_share"], pile["high_share"])
        side = "lower" if pile["low_share"] >= pile["high_share"] else "upper"
        out.append(
            Finding(
                "heights_at_search_bound",
                "suspect",
                f"{100 * share:.0f} % of the heights lie at the {side} end of the height search "
                "range: the terrain is probably outside the range (check --height-range, or the "
                "seed DEM's units and vertical reference)",
                round(share, 4),
            ).to_dict()
        )
    for f in out:
        log.warning("suspect result: %s", f["message"])
    return out


# ----------------------------------------------------------------------------- both


@dataclass
class CheckedPair:
    """A pair that passed :func:`check_pair`: the images to match (the right one on the left's
    radiometric scale when their bit depths differ), the base-to-height ratio and the
    findings so far (dicts of :class:`Finding`)."""

    left: np.ndarray
    right: np.ndarray
    base_to_height: float
    findings: list = field(default_factory=list)

    def report(self, products):
        """Record the checks in ``products.info`` (``base_to_height``, ``warnings`` with the
        result's own findings, ``status``); returns ``products``."""
        info = products.info
        info.base_to_height = round(self.base_to_height, 4)
        info.warnings = self.findings + check_result(info)
        info.status = status(info.warnings)
        return products


def check_pair(
    left_image,
    right_image,
    left_model,
    right_model,
    height_range=None,
    seed_dem=None,
    left_dtype=None,
    right_dtype=None,
) -> CheckedPair:
    """The checks of a pair before any stereo work, in order: image arrays that match their
    models, the seed DEM (:func:`check_seed_dem`), the stereo base at the middle of the
    height range (given, else the seed DEM's, else the models' common range:
    :func:`check_base`), one radiometric scale (:func:`comparable_radiometry`; the bit depths
    default to the arrays' dtypes). Raises :class:`InputError` subclasses with one-line
    messages; returns a :class:`CheckedPair`."""
    for name, img, mdl in (("left", left_image, left_model), ("right", right_image, right_model)):
        if isinstance(img, (str, os.PathLike)):
            raise InputError(
                f"{name} image: expected a 2-D array; {img} is a path: read it first "
                "(stereodem.read_image)"
            )
        if np.ndim(img) != 2:
            raise InputError(f"{name} image: expected a 2-D array, got shape {np.shape(img)}")
        if img.shape != (mdl.height, mdl.width):
            raise InputError(
                f"{name} image: shape {img.shape} differs from its model's "
                f"{(mdl.height, mdl.width)} (rows, cols)"
            )
    if seed_dem is not None:
        check_seed_dem(seed_dem, left_model, right_model)
    hr = height_range
    if hr is None and seed_dem is not None:
        hr = seed_height_range(seed_dem, left_model, right_model)
    if hr is None:
        hr = pair_height_bounds(left_model, right_model)
    bh = check_base(left_model, right_model, hr)
    left, right, findings = comparable_radiometry(
        left_image,
        right_image,
        left_dtype or getattr(left_image, "dtype", None),
        right_dtype or getattr(right_image, "dtype", None),
    )
    return CheckedPair(left, right, bh, findings)
