"""``stereodem adjust IMG1 IMG2 IMG3 ... --model bundle``: bundle adjustment of N images.

Tie points, in order of preference: a tie CSV (``--ties``: ``point,image,col,row`` with the
image as its 1-based position on the command line or its file stem; or, for two images,
``col1,row1,col2,row2``), ASP binary match files (``--match``, repeatable: each names its two
images the ASP way, ``<prefix>-<stem1>__<stem2>.match``, and is checked against them:
:func:`stereodem.sensor.io.asp_match.check_match_images`), or automatic SIFT matches checked
through the models (:func:`stereodem.stereo.sparse.sparse_matches`) for every pair chosen by
overlap and base (:func:`stereodem.stereo.fusion.choose_pairs`). Pair matches sharing a pixel
are chained into tracks
(:func:`~stereodem.sensor.estimation.adjust.bundle_multi.tracks_from_pairs`). GCPs per image
(``--gcps`` for the first, ``--gcps2`` for the second, ``--image-gcps K=CSV`` for any); the datum is
held by the GCPs, else by the fixed images (``--fix K``, default the first). The adjusted models are
written as ``OUT/<stem>.model.json``.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from stereodem.core.errors import InputError
from stereodem.core.raster import check_writable
from stereodem.sensor.estimation.adjust import write_report
from stereodem.sensor.estimation.adjust.bundle_multi import (
    TieTracks,
    bundle_adjust_images,
    tracks_from_pairs,
)
from stereodem.sensor.io.asp_match import check_match_images, match_stems, read_match
from stereodem.sensor.io.gcps import csv_rows, read_gcps
from stereodem.sensor.io.sidecar import save_model
from stereodem.sensor.models.base import pair_height_bounds
from stereodem.stereo.fusion import choose_pairs
from stereodem.stereo.sparse import sparse_matches
from stereodem.stereo.ties import check_match_geometry

from .config import Config, InputSettings
from .multiview import reference_height
from .pipeline.inputs import image_model, open_image

log = logging.getLogger(__name__)

__all__ = ["run_bundle_images", "read_tracks", "tie_csv_rows", "match_ties"]


def tie_csv_rows(path, need, note="") -> tuple[list, list]:
    """The data rows (lists of strings, blank lines skipped) of the tie-point CSV ``path`` and
    the column index of each name in ``need`` (header required, case-insensitive); a missing
    or empty file or a header without them raises :class:`InputError` (``note`` ends that
    message)."""
    rows = csv_rows(path, "tie-point file")
    if not rows:
        raise InputError(f"{path}: empty tie-point file")
    head = [c.strip().lower() for c in rows[0]]
    if any(c not in head for c in need):
        raise InputError(f"{path}: tie-point header must contain {','.join(need)}{note}")
    return [head.index(c) for c in need], rows[1:]


def read_tracks(path, stems) -> TieTracks:  # noqa: F821
    """Tie observations from a CSV ``point,image,col,row`` (header required; ``image`` a
    1-based position in ``stems`` or one of the stems; ``point`` any label)."""
    ix, rows = tie_csv_rows(path, ["point", "image", "col", "row"], " (N images)")
    labels, imgs, cols, rws = [], [], [], []
    for n, r in enumerate(rows, start=2):
        try:
            p, im, c, rr = (r[k].strip() for k in ix)
            k = int(im) - 1 if im.isdigit() else stems.index(im)
            if not 0 <= k < len(stems):
                raise ValueError
            labels.append(p), imgs.append(k), cols.append(float(c)), rws.append(float(rr))
        except (ValueError, IndexError):
            raise InputError(
                f"{path}: line {n}: expected point,image,col,row with an image among "
                f"1..{len(stems)} or {', '.join(stems)}"
            ) from None
    _, point = np.unique(np.asarray(labels), return_inverse=True)
    t = TieTracks(point.ravel(), imgs, cols, rws)
    counts = np.bincount(t.point)
    if (counts < 2).any():
        raise InputError(f"{path}: {int((counts < 2).sum())} tie point(s) seen in one image only")
    return t


def match_ties(paths, images, models) -> dict:
    """``{(i, j): ties}`` from ASP match files, each refused in one line when it does not
    belong to two of ``images`` (name, image bounds, epipolar geometry)."""
    stems = [Path(p).stem for p in images]
    out = {}
    for path in paths:
        names = match_stems(path)
        if names is None:
            raise InputError(
                f"{path}: not named the ASP way (<prefix>-<image1>__<image2>.match), so "
                "its images are unknown"
            )
        a, b = names
        i = next((k for k, s in enumerate(stems) if a == s or a.endswith("-" + s)), None)
        j = next((k for k, s in enumerate(stems) if b == s), None)
        if i is None or j is None or i == j:
            raise InputError(
                f"{path}: matches images {a.rsplit('-', 1)[-1]!r} / {b!r}, not two of "
                f"{', '.join(stems)}"
            )
        m = read_match(path)
        lo, hi = pair_height_bounds(models[i], models[j])
        check_match_images(
            m,
            images[i],
            images[j],
            left_size=(models[i].width, models[i].height),
            right_size=(models[j].width, models[j].height),
        )
        if hi > lo:
            check_match_geometry(m, models[i], models[j], (lo, hi), names=(images[i], images[j]))
        t = m.ties()
        key = (i, j) if i < j else (j, i)
        t = t if i < j else t[:, [2, 3, 0, 1]]
        out[key] = np.concatenate([out[key], t]) if key in out else t
        log.info("%s: %d matches of %s / %s", path, len(t), images[i], images[j])
    return out


def _auto_ties(args, paths, models) -> dict:
    """Sparse SIFT matches checked through the models, for every usable pair."""
    h0 = reference_height(Config(InputSettings(), "."), models)
    plan = choose_pairs(models, h0, names=paths)
    imgs = {}
    out = {}
    for c in plan.pairs:
        for k in (c.i, c.j):
            if k not in imgs:
                imgs[k] = open_image(paths[k], band=args.band).image
        m = sparse_matches(imgs[c.i], imgs[c.j], models[c.i], models[c.j])
        out[(c.i, c.j)] = np.stack([m.col1, m.row1, m.col2, m.row2], -1)
        log.info(
            "adjust: %d automatic tie points between %s and %s", len(m), paths[c.i], paths[c.j]
        )
    return out


def run_bundle_images(args) -> str:
    """The bundle adjustment of ``args.image``, ``args.image2`` and ``args.more``; writes the
    adjusted models into the folder ``args.out`` (and the report); returns the summary line."""
    paths = [args.image, args.image2, *args.more]
    stems = [Path(p).stem for p in paths]
    if len(set(stems)) < len(stems):
        raise InputError(
            "bundle: two images with one file stem ("
            + ", ".join(s for s in stems if stems.count(s) > 1)
            + "): their models would overwrite each other"
        )
    out = Path(args.out)
    if out.suffix == ".json":
        raise InputError(
            f"{out}: with three or more images, -o is the folder of the adjusted models"
        )
    targets = [out / f"{s}.model.json" for s in stems]
    for t in targets:
        check_writable(t, args.overwrite)
    models = [image_model(p, band=args.band) for p in paths]
    gcps = [None] * len(paths)
    spec = [(0, args.gcps), (1, args.gcps2)] + [
        _image_gcps(s, len(paths)) for s in args.image_gcps or []
    ]
    for k, csv_path in spec:
        if csv_path:
            if gcps[k] is not None:
                raise InputError(f"{csv_path}: a second GCP file for image {k + 1} ({paths[k]})")
            gcps[k] = read_gcps(csv_path, vertical=args.vertical)
    if args.ties:
        tracks = read_tracks(args.ties, stems)
    else:
        pair_ties = (
            match_ties(args.match, paths, models) if args.match else _auto_ties(args, paths, models)
        )
        tracks = tracks_from_pairs(pair_ties)
    if tracks.n_points == 0:
        raise InputError("bundle: no tie point between the images")
    fixed = [k - 1 for k in args.fix] if args.fix else None
    res = bundle_adjust_images(
        models,
        tracks,
        names=args.param_set,
        gcps=gcps,
        fixed=fixed,
        sigma_tie_px=args.sigma_tie_px,
        sigma_px=args.sigma_px,
        snooping=not args.no_snooping,
        alpha=args.alpha,
        max_iterations=args.max_iterations,
    )
    from .adjust_cli import report_folder

    with report_folder(args, len(paths)) as rep:
        for m, t in zip(res.models, targets):
            save_model(m, t, overwrite=args.overwrite)
        if rep is not None:
            write_report(res, rep, overwrite=True)
    gaps = ", ".join(
        f"{i + 1}-{j + 1} {res.ray_gaps_before[(i, j)]['ray_gap_rms_m']:.2f}->"
        f"{res.ray_gaps_after.get((i, j), {}).get('ray_gap_rms_m', float('nan')):.2f}"
        for i, j in res.ray_gaps_before
    )
    return (
        f"bundle ({args.param_set}) of {len(paths)} images: {tracks.n_points} tie points "
        f"({len(tracks)} observations, {int(res.tie_rejected.sum())} rejected), tie RMSE "
        f"{res.tie_rmse_px:.3f} px, fixed: "
        f"{', '.join(str(k + 1) for k in res.fixed) or 'none (GCPs)'}; ray gap RMS (m) {gaps}; "
        f"models in {out}"
    )


def _image_gcps(text, n):
    k, sep, path = text.partition("=")
    if not sep or not k.strip().isdigit() or not 1 <= int(k) <= n:
        raise InputError(f"--image-gcps {text!r}: expected K=CSV with K in 1..{n}")
    return int(k) - 1, path
