"""N-image bundle adjustment (issue 26 item 3): tie tracks, a simulated triplet with known
biases, the datum, and ``stereodem adjust IMG1 IMG2 IMG3 --model bundle``."""

import re

import numpy as np
import pytest
from scipy import ndimage

from stereodem.cli import main
from stereodem.core.errors import InputError
from stereodem.core.raster import write_geotiff
from stereodem.sensor.estimation.adjust.bundle_multi import (
    TieTracks,
    bundle_adjust_images,
    tracks_from_pairs,
)
from stereodem.sensor.io.asp_match import InterestPoints, MatchFile, write_match
from stereodem.sensor.io.gcps import ControlPoints, write_gcps
from stereodem.sensor.io.sidecar import load_model, save_model
from stereodem.sensor.models.corrected import ImageCorrectedModel
from stereodem.sensor.simulation.simulate import pushbroom_pair, simulate_views

#: shifts (col, row; px) of the true models from the delivered ones
BIASES = [(0.8, -0.6), (2.5, -1.5), (-1.8, 3.2)]


@pytest.fixture(scope="module")
def triplet():
    """Nominal pushbroom triplet (+15, 0, -15 deg along track, 1200 px, 15 m) and the true
    models, shifted by BIASES in image space."""
    angles = (15.0, 0.0, -15.0)
    pairs = [pushbroom_pair(7.0, 45.0, 1000.0, (1200, 1200), (angles[0], a)) for a in angles[1:]]
    nominal = [pairs[0][0], pairs[0][1], pairs[1][1]]
    truth = [ImageCorrectedModel(m, col_shift=c, row_shift=r) for m, (c, r) in zip(nominal, BIASES)]
    return [ImageCorrectedModel(m) for m in nominal], truth


def _observe(truth, n, sigma, rng):
    """n ground points seen by every true model: (lon, lat, h), observations per image."""
    c = rng.uniform(40, 1160, n)
    r = rng.uniform(40, 1160, n)
    h = rng.uniform(500, 1500, n)
    lon, lat = truth[0].localize(c, r, h)
    return (lon, lat, h), [
        np.column_stack(m.project(lon, lat, h)) + rng.normal(0, sigma, (n, 2)) for m in truth
    ]


def _tracks(obs):
    n = len(obs[0])
    xy = np.stack(obs, 1).reshape(-1, 2)
    return TieTracks(
        np.repeat(np.arange(n), len(obs)), np.tile(np.arange(len(obs)), n), xy[:, 0], xy[:, 1]
    )


def test_tracks_from_pairs_chain_matches():
    t01 = np.array([[10.0, 20.0, 11.0, 21.0], [30.0, 40.0, 31.0, 41.0]])
    t02 = np.array(
        [
            [10.0, 20.0, 12.5, 22.0],  # chains with the first 0-1 match
            [50.0, 60.0, 52.0, 62.0],
        ]
    )
    t12 = np.array(
        [
            [31.0, 41.0, 33.0, 44.0],  # chains with the second 0-1 match
            [11.0, 21.0, 99.0, 99.0],
        ]
    )  # image 2 at another pixel: inconsistent
    tr = tracks_from_pairs({(0, 1): t01, (0, 2): t02, (1, 2): t12})
    pts = {}
    for p, i, c, r in zip(tr.point, tr.image, tr.col, tr.row):
        pts.setdefault(int(p), {})[int(i)] = (c, r)
    tracks = sorted(pts.values(), key=lambda d: d[0] if 0 in d else (1e9, 0))
    # (10,20)-(11,21)-(12.5,22) is dropped with its inconsistent 1-2 match; the other chain
    # (30,40)-(31,41)-(33,44) is one point seen three times; (50,60)-(52,62) a pair
    assert tracks == [
        {0: (30.0, 40.0), 1: (31.0, 41.0), 2: (33.0, 44.0)},
        {0: (50.0, 60.0), 2: (52.0, 62.0)},
    ]
    pairs = tr.pairs()
    assert sorted(pairs) == [(0, 1), (0, 2), (1, 2)] and len(pairs[(0, 2)]) == 2
    np.testing.assert_array_equal(pairs[(1, 2)], [[31.0, 41.0, 33.0, 44.0]])


def test_triplet_biases_recovered_with_gcps(triplet):
    delivered, truth = triplet
    rng = np.random.default_rng(1)
    _, obs = _observe(truth, 400, 0.2, rng)
    (lon, lat, h), gobs = _observe(truth, 12, 0.05, rng)
    gcps = []
    for o in gobs:
        g = ControlPoints.from_arrays(lon, lat, h, o[:, 0], o[:, 1])
        g.sigma_px[:] = 0.05
        gcps.append(g)
    res = bundle_adjust_images(
        delivered, _tracks(obs), names="rpc-shift", gcps=gcps, sigma_tie_px=0.2
    )
    est = np.asarray(res.values).reshape(3, 2)
    assert np.abs(est - np.asarray(BIASES)).max() <= 0.1, est
    assert 0.8 < res.sigma0 < 1.2 and res.tie_rmse_px < 0.4
    for k, before in res.ray_gaps_before.items():  # every pair's rays now meet
        assert res.ray_gaps_after[k]["ray_gap_rms_m"] < 0.5 * before["ray_gap_rms_m"]
    rep = res.to_report()
    assert rep["ties"]["n"] == 400 and set(rep["ray_gaps_after"]) == {"0-1", "0-2", "1-2"}


def test_datum_without_gcps(triplet):
    """Ties alone fix the images' relative orientation up to the datum. Two images held fixed
    give the third's bias; one fixed image leaves, on one orbit, the along-track shifts and
    the ties' heights trading off: held by datum priors (as the pair's bundle holds it), the
    models agree with each other (ray gaps gone), not necessarily with the ground. GCPs fix
    that."""
    delivered, truth = triplet
    rng = np.random.default_rng(2)
    only2 = [delivered[0].model, delivered[1].model, truth[2]]  # image 2 biased alone
    _, obs = _observe(only2, 400, 0.2, rng)
    res = bundle_adjust_images(delivered, _tracks(obs), fixed=[0, 1], sigma_tie_px=0.2)
    assert res.names == ["image2.col_shift", "image2.row_shift"]
    np.testing.assert_allclose(res.values, BIASES[2], atol=0.1)
    _, obs = _observe([delivered[0].model] + truth[1:], 400, 0.2, rng)  # image 0 right
    one = bundle_adjust_images(delivered, _tracks(obs), sigma_tie_px=0.2)  # image 0 fixed
    # the across-track shifts are observed; the along-track ones trade off with the ties'
    # heights (a common height offset moves each free image along its epipolar lines): held
    # by the datum priors about the start values (1 px), with a sigma that says so, instead
    # of a near-singular system (condition > 1e6, shifts anywhere along that direction)
    assert one.condition < 1e5
    np.testing.assert_allclose(one.values[[0, 2]], [BIASES[1][0], BIASES[2][0]], atol=0.1)
    assert (one.std[[1, 3]] > 0.3).all() and (np.abs(one.values[[1, 3]]) < 3.0).all()
    for k, before in one.ray_gaps_before.items():  # yet the three models now agree
        assert one.ray_gaps_after[k]["ray_gap_rms_m"] < 0.5 * before["ray_gap_rms_m"]
    with pytest.raises(InputError, match="fixed image index"):
        bundle_adjust_images(delivered, _tracks(obs), fixed=[5])


@pytest.fixture(scope="module")
def triplet_files(triplet, tmp_path_factory):
    """The delivered models as sidecars of three (blank) image files, with tie and GCP CSVs
    measured through the true models."""
    delivered, truth = triplet
    d = tmp_path_factory.mktemp("triplet")
    paths = []
    for k, m in enumerate(delivered):
        p = d / f"view{k}.tif"
        write_geotiff(
            p,
            np.zeros((m.height, m.width), np.uint8),
            tags={"STEREODEM_MODEL": f"view{k}.model.json"},
        )
        save_model(m.model, d / f"view{k}.model.json")
        paths.append(str(p))
    rng = np.random.default_rng(3)
    _, obs = _observe(truth, 300, 0.2, rng)
    rows = ["point,image,col,row"] + [
        f"t{i},{k + 1},{o[i, 0]:.4f},{o[i, 1]:.4f}" for i in range(300) for k, o in enumerate(obs)
    ]
    (d / "ties.csv").write_text("\n".join(rows) + "\n")
    (lon, lat, h), gobs = _observe(truth, 12, 0.05, rng)
    for k, o in enumerate(gobs):
        write_gcps(
            d / f"gcp{k}.csv",
            [f"G{i}" for i in range(12)],
            lon,
            lat,
            h,
            o[:, 0],
            o[:, 1],
            sigma_px=np.full(12, 0.05),
        )
    return d, paths, obs


@pytest.mark.slow
def test_adjust_cli_three_images(triplet_files, capsys):
    d, paths, _ = triplet_files
    out = d / "adjusted"
    argv = [
        "adjust",
        *paths,
        "--model",
        "bundle",
        "--ties",
        str(d / "ties.csv"),
        "--gcps",
        str(d / "gcp0.csv"),
        "--gcps2",
        str(d / "gcp1.csv"),
        "--image-gcps",
        f"3={d / 'gcp2.csv'}",
        "--sigma-tie-px",
        "0.2",
        "-o",
        str(out),
        "--report",
        str(d / "report"),
    ]
    assert main(argv) == 0
    line = capsys.readouterr().out
    assert (
        "bundle (rpc-shift) of 3 images: 300 tie points (900 observations" in line
        and "fixed: none" in line
    )
    for k, (c, r) in enumerate(BIASES):
        m = load_model(out / f"view{k}.model.json")
        p = m.parameters()
        assert abs(p["col_shift"] - c) <= 0.1 and abs(p["row_shift"] - r) <= 0.1
    rep = (d / "report" / "adjust_report.json").read_text()
    assert '"ray_gaps_after"' in rep and (d / "report" / "adjust_residuals_image2.png").is_file()
    assert main(argv) == 1  # no overwrite
    assert "exists" in capsys.readouterr().err


def test_adjust_cli_refuses_match_of_other_images(triplet_files, capsys):
    d, paths, obs = triplet_files
    good = MatchFile(
        InterestPoints(obs[0][:, 0], obs[0][:, 1]), InterestPoints(obs[1][:, 0], obs[1][:, 1])
    )
    # named right, but each point's partner is another point: the matches of other images
    other = MatchFile(good.left, InterestPoints(obs[1][::-1, 0], obs[1][::-1, 1]))
    write_match(d / "run-view0__view1.match", other)
    write_match(d / "run-view0__other.match", good)
    base = [
        "adjust",
        *paths,
        "--model",
        "bundle",
        "-o",
        str(d / "m"),
        "--gcps",
        str(d / "gcp0.csv"),
    ]
    assert main(base + ["--match", str(d / "run-view0__other.match")]) == 1
    err = capsys.readouterr().err
    assert (
        err.count("\n") == 1 and "run-view0__other.match: matches images 'view0' / 'other'" in err
    )
    assert main(base + ["--match", str(d / "run-view0__view1.match")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "across the epipolar curves" in err
    assert not (d / "m").exists()


def test_adjust_cli_pair_from_match_file(triplet_files, capsys):
    """A pair bundle from an ASP match file of the two images (named the ASP way)."""
    d, paths, obs = triplet_files
    write_match(
        d / "pair" / "run-view0__view2.match",
        MatchFile(
            InterestPoints(obs[0][:, 0], obs[0][:, 1]), InterestPoints(obs[2][:, 0], obs[2][:, 1])
        ),
    )
    argv = [
        "adjust",
        paths[0],
        paths[2],
        "--model",
        "bundle",
        "--match",
        str(d / "pair" / "run-view0__view2.match"),
        "--gcps",
        str(d / "gcp0.csv"),
        "--gcps2",
        str(d / "gcp2.csv"),
        "--sigma-tie-px",
        "0.2",
        "-o",
        str(d / "pair" / "a.model.json"),
        "--out2",
        str(d / "pair" / "b.model.json"),
    ]
    assert main(argv) == 0
    assert "bundle (rpc-shift): 300 ties (0 rejected)" in capsys.readouterr().out


@pytest.mark.slow
def test_adjust_cli_three_images_automatic_ties(tmp_path, capsys):
    """``stereodem adjust IMG1 IMG2 IMG3 --model bundle`` without ``--ties``/``--match``: SIFT tie
    points matched between every chosen pair of real (simulated) images and chained into tracks.

    The images are rendered through the true models (the nominal triplet shifted by BIASES in
    image space: the rendered images shifted by the same amounts), the sidecars hold the
    nominal models. GCPs on images 1 and 3 only: image 2's bias comes from the automatic ties
    alone, and is recovered within the CSV-ties test's 0.1 px like the others (measured
    0.01-0.02 px, 2800 ties of 0.07 px RMSE).
    """
    size = 400
    sc = simulate_views("pushbroom", angles=(15.0, 0.0, -15.0), size=(size, size), seed=1)
    truth = [
        ImageCorrectedModel(m, col_shift=c, row_shift=r) for m, (c, r) in zip(sc.models, BIASES)
    ]
    paths = []
    for k, (img, m) in enumerate(zip(sc.images, sc.models)):
        c, r = BIASES[k]  # the true image at (col, row) shows the nominal one's (col-c, row-r)
        moved = ndimage.shift(img.astype(np.float32), (r, c), order=3, mode="nearest")
        p = tmp_path / f"view{k}.tif"
        write_geotiff(
            p,
            np.clip(np.rint(moved), 0, 255).astype(np.uint8),
            tags={"STEREODEM_MODEL": f"view{k}.model.json"},
        )
        save_model(m, tmp_path / f"view{k}.model.json")
        paths.append(str(p))
    rng = np.random.default_rng(3)
    lo, hi = sc.truth_dem.height_range()
    c0, r0 = rng.uniform(40, size - 40, (2, 12))
    h = rng.uniform(lo, hi, 12)
    lon, lat = truth[0].localize(c0, r0, h)
    for k in (0, 2):
        col, row = truth[k].project(lon, lat, h) + rng.normal(0, 0.05, (2, 12))
        g = tmp_path / f"gcp{k}.csv"
        write_gcps(
            g, [f"G{i}" for i in range(12)], lon, lat, h, col, row, sigma_px=np.full(12, 0.05)
        )
    out = tmp_path / "adjusted"
    argv = ["adjust", *paths, "--model", "bundle", "--gcps", str(tmp_path / "gcp0.csv")]
    argv += ["--image-gcps", f"3={tmp_path / 'gcp2.csv'}", "-o", str(out)]
    assert main(argv) == 0
    line = capsys.readouterr().out
    n_points, n_obs = (int(v) for v in re.search(r"(\d+) tie points \((\d+) obs", line).groups())
    assert n_points > 1000 and n_obs > 2 * n_points, line  # tracks chained across 3 images
    before, after = zip(*(map(float, g) for g in re.findall(r"(\d+\.\d+)->(\d+\.\d+)", line)))
    assert len(after) == 3 and max(after) < 0.2 * min(before), line  # every pair's rays meet
    for k, (c, r) in enumerate(BIASES):
        p = load_model(out / f"view{k}.model.json").parameters()
        assert abs(p["col_shift"] - c) <= 0.1 and abs(p["row_shift"] - r) <= 0.1, (k, p)
    assert main(argv) == 1  # the models exist
    assert "view0.model.json: exists" in capsys.readouterr().err
    assert main(argv + ["--overwrite"]) == 0  # -o is a folder: --overwrite replaces the models
