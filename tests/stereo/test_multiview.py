"""N-view DEMs (issue 26 item 1): pair choice, per-cell fusion and its layers, and
``stereodem dem IMG1 IMG2 IMG3`` on a simulated pushbroom triplet."""

import json

import numpy as np
import pytest
import rasterio
from affine import Affine
from scipy.ndimage import map_coordinates

from stereodem.cli import main
from stereodem.config import Config, InputSettings, RunSettings, config_from_dict, load_config
from stereodem.core import geodesy
from stereodem.core.dem import DEM
from stereodem.core.errors import InputError
from stereodem.core.grid import MapGrid
from stereodem.core.raster import write_geotiff
from stereodem.core.stats import NMAD_FACTOR, nmad
from stereodem.multiview import multiview_stage
from stereodem.pipeline.job import run
from stereodem.sensor.io.sidecar import save_model
from stereodem.sensor.models.corrected import ImageCorrectedModel
from stereodem.sensor.models.pushbroom import PushbroomModel
from stereodem.sensor.simulation.simulate import simulate_views
from stereodem.stereo.fusion import FusionSettings, choose_pairs, fuse_dems, pair_sigma
from stereodem.stereo.pipeline import make_dem
from stereodem.stereo.pointcloud import FUSION_REJECTED, read_pairs
from stereodem.stereo.settings import GriddingSettings, RectificationSettings, StereoSettings

CRS = "EPSG:32633"


def _dem(heights, x0=500000.0, y1=4000000.0, posting=10.0, score=0.9, gap=0.5):
    h = np.asarray(heights, np.float32)
    g = MapGrid(
        Affine(posting, 0, x0, 0, -posting, y1), h.shape[1], h.shape[0], geodesy.utm_crs(15.0, 36.0)
    )
    return DEM(
        h,
        g.transform,
        g.crs,
        "ellipsoid",
        count=np.ones(h.shape, np.int32),
        score=np.full(h.shape, score, np.float32),
        ray_gap=np.full(h.shape, gap, np.float32),
    )


def test_fusion_layers_by_hand():
    """Three pair DEMs on offset lattices: a pair that disagrees is rejected, the layers are
    the numbers worked out by hand, and cells seen by fewer pairs have fewer heights."""
    a = _dem(np.full((4, 5), 100.0))
    b = _dem(np.full((4, 5), 101.0))
    c = _dem(np.full((4, 5), 130.0), x0=500010.0)  # one cell east: a 6-column union
    c.heights[0, 0] = 100.6
    f = fuse_dems([a, b, c], [1.0, 1.0, 1.0])
    assert f.grid.shape == (4, 6) and f.transform.c == 500000.0
    # cell (1, 1): heights 100, 101, 130 -> median 101, NMAD 1.4826; 130 lies 29 m off: rejected
    assert f.count[1, 1] == 2 and f.heights[1, 1] == pytest.approx(100.5)
    assert f.nmad[1, 1] == pytest.approx(NMAD_FACTOR * 1.0, rel=1e-6)
    # two kept heights of σ 1 m that scatter by 0.5 m about their mean: formal σ 1/sqrt(2)
    assert f.sigma[1, 1] == pytest.approx(1 / np.sqrt(2), rel=1e-6)
    # cell (0, 1): c's corner 100.6 agrees: mean of 100, 101, 100.6
    assert f.count[0, 1] == 3 and f.heights[0, 1] == pytest.approx(
        (100 + 101 + 100.6) / 3, abs=1e-4
    )
    # column 0: only a and b; column 5: only c (one height: no NMAD, σ the pair's)
    assert f.count[2, 0] == 2 and f.count[2, 5] == 1 and f.heights[2, 5] == pytest.approx(130.0)
    assert np.isnan(f.nmad[2, 5]) and f.sigma[2, 5] == pytest.approx(1.0)
    # per pair: c rejected wherever a and b also see the cell, except the corner that agrees
    assert [p["rejected"] for p in f.pairs] == [0, 0, 4 * 4 - 1]
    # heights that scatter more than their σ inflate the fused σ: sqrt(chi2 / (n - 1))
    g = fuse_dems([_dem(np.full((2, 2), 100.0)), _dem(np.full((2, 2), 104.0))], [1.0, 1.0])
    assert g.heights[0, 0] == pytest.approx(102.0) and g.count[0, 0] == 2
    assert g.sigma[0, 0] == pytest.approx(np.sqrt(8.0) / np.sqrt(2), rel=1e-6)
    # weights 1/σ²: the precise pair dominates
    w = fuse_dems([_dem(np.full((2, 2), 100.0)), _dem(np.full((2, 2), 101.0))], [1.0, 2.0])
    assert w.heights[0, 0] == pytest.approx((100 * 1 + 101 * 0.25) / 1.25, abs=1e-4)
    m = fuse_dems([a, b, c], [1.0, 1.0, 1.0], method="median")
    assert m.heights[1, 1] == pytest.approx(100.5) and m.heights[0, 1] == pytest.approx(100.6)


def test_fused_count_layer_says_stereo_pairs(tmp_path):
    """The fused ``count.tif`` holds stereo pairs per cell and its band description says so; a
    pair DEM's ``count.tif`` keeps its points-per-cell description."""
    f = fuse_dems([_dem(np.full((2, 3), 100.0)), _dem(np.full((2, 3), 101.0))], [1.0, 1.0])
    paths = f.write(tmp_path / "fused" / "dem.tif")
    with rasterio.open(paths["count"]) as ds:
        assert ds.descriptions == ("stereo pairs per cell (pair heights fused, after rejection)",)
        assert ds.read(1).tolist() == [[2, 2, 2], [2, 2, 2]]
    pair = _dem(np.full((2, 3), 100.0)).write(tmp_path / "pair" / "dem.tif")
    with rasterio.open(pair.with_name("count.tif")) as ds:
        assert ds.descriptions == ("space-intersected points per cell",)


def test_fused_dem_files_side_by_side_have_the_same_bytes(tmp_path):
    """``threads`` > 1 writes the fused DEM's files (the DEM, its layers and ``nmad.tif``)
    side by side, each on one GDAL thread: the same files, byte for byte, as one at a time."""
    rng = np.random.default_rng(1)
    dems = [_dem(100 + rng.normal(0, 1, (40, 50))) for _ in range(3)]
    f = fuse_dems(dems, [1.0, 1.0, 1.0])
    one = f.write(tmp_path / "one" / "dem.tif")
    three = f.write(tmp_path / "three" / "dem.tif", threads=3)
    assert set(one) == set(three) and "nmad" in one and "sigma" in one
    for name, path in one.items():
        assert path.read_bytes() == three[name].read_bytes(), name
    with rasterio.open(three["nmad"]) as ds:
        np.testing.assert_array_equal(ds.read(1), f.nmad.astype(np.float32))


def test_fusion_refuses_other_lattices():
    a = _dem(np.full((3, 3), 1.0))
    b = _dem(np.full((3, 3), 1.0), x0=500005.0)  # half a cell off
    with pytest.raises(InputError, match="not whole"):
        fuse_dems([a, b], [1.0, 1.0])
    with pytest.raises(InputError, match="one positive σ"):
        fuse_dems([a, a], [1.0])


@pytest.fixture(scope="module")
def triplet():
    """A pushbroom triplet (+15, 0, -15 deg: B/H 0.3, 0.6, 0.3) with noisy images (6 DN)."""
    return simulate_views(
        "pushbroom", angles=(15.0, 0.0, -15.0), size=(240, 240), seed=1, noise=6.0
    )


def test_choose_pairs_names_isolated_image(triplet):
    lo, hi = triplet.truth_dem.height_range()
    far = PushbroomModel.synthetic_pair(16.5, 37.5, width=240, height=240)[0]  # another scene
    plan = choose_pairs(triplet.models + [far], 0.5 * (lo + hi), names=["a", "b", "c", "far"])
    assert [(c.i, c.j) for c in plan.pairs] == [(0, 1), (0, 2), (1, 2)]
    bh = {(c.i, c.j): c.base_to_height for c in plan.pairs}
    assert bh[(0, 2)] == pytest.approx(2 * bh[(0, 1)], rel=0.05) and 0.25 < bh[(0, 1)] < 0.35
    assert plan.skipped == {3: "overlaps no other image"}
    assert plan.to_dict(["a", "b", "c", "far"])["skipped_images"][0]["name"] == "far"
    few = choose_pairs(triplet.models, 0.5 * (lo + hi), max_pairs=1)
    assert [(c.i, c.j) for c in few.pairs] == [(0, 2)]  # the widest base wins
    with pytest.raises(InputError, match="no usable pair"):
        choose_pairs(triplet.models, 0.5 * (lo + hi), min_base_to_height=0.9)


def _errors(dem_path, truth):
    with rasterio.open(dem_path) as ds:
        z = ds.read(1)
        rows, cols = np.mgrid[0 : ds.height, 0 : ds.width]
        t = ds.transform  # north-up
        x, y = t.c + (cols + 0.5) * t.a, t.f + (rows + 0.5) * t.e
        lon, lat = geodesy.crs_to_lonlat(x.ravel(), y.ravel(), ds.crs)
    return z - truth.sample(lon, lat).reshape(z.shape)


@pytest.mark.slow
def test_dem_cli_triplet(triplet, tmp_path, capsys):
    """The fused DEM of a simulated triplet against the truth, beside the best pair alone.

    What fusion gains here is coverage and robustness, not precision: on one orbit the two
    narrow pairs' height errors are largely the wide pair's (disparities add up:
    e01 B01 + e12 B12 ~ e02 B02, the shared images' errors), so no weighting of the three
    beats the wide pair by much; measured, the fused NMAD is 4 % above the wide pair's and
    30-40 % below the narrow pairs' (the real Pleiades triplet, benchmarks/bench_multiview.py,
    gains 4 % over its best pair).
    """
    paths = []
    for k, (img, model) in enumerate(zip(triplet.images, triplet.models)):
        p = tmp_path / f"view{k}.tif"
        write_geotiff(p, img, tags={"STEREODEM_MODEL": f"view{k}.model.json"})
        save_model(model, tmp_path / f"view{k}.model.json")
        paths.append(str(p))
    lo, hi = triplet.truth_dem.height_range()
    out = tmp_path / "out"
    hr = [str(lo - 50), str(hi + 50)]
    assert (
        main(
            ["dem", *paths, "-o", str(out), "--height-range", *hr, "--res", "30", "--workers", "1"]
        )
        == 0
    )
    assert "fused from 3 pair(s)" in capsys.readouterr().out
    rep = json.loads((out / "dem_report.json").read_text())["multiview"]
    assert [(r["left"], r["right"]) for r in rep["pair_runs"]] == [(0, 1), (0, 2), (1, 2)]
    assert all("base-to-height" in p["reason"] for p in rep["pairs"])
    err = _errors(out / "dem.tif", triplet.truth_dem)
    with rasterio.open(out / "count.tif") as ds:
        count = ds.read(1)
        # the fused count is of stereo pairs (a pair DEM's count.tif counts points)
        assert ds.descriptions == ("stereo pairs per cell (pair heights fused, after rejection)",)
    with rasterio.open(out / "nmad.tif") as ds:
        spread = ds.read(1)
    with rasterio.open(out / "dem_sigma_vertical.tif") as ds:
        sigma = ds.read(1)
    # the best pair alone (the wide base), on the same lattice
    with rasterio.open(out / "dem.tif") as ds:
        b = ds.bounds
        crs = ds.crs.to_wkt()
    st = StereoSettings(
        RectificationSettings(height_range=(lo - 50, hi + 50)),
        gridding=GriddingSettings(res=30.0, crs=crs, bounds=(b.left, b.bottom, b.right, b.top)),
    )
    best = make_dem(triplet.images[0], triplet.images[2], triplet.models[0], triplet.models[2], st)
    path = tmp_path / "best"
    best.write(path)
    e_best = _errors(path / "dem.tif", triplet.truth_dem)
    cells = np.isfinite(e_best)
    assert np.isfinite(err[cells]).all()  # covers every cell the best pair does
    assert np.isfinite(err).sum() >= cells.sum()
    fused_nmad, best_nmad = nmad(err[cells]), nmad(e_best[cells])
    assert fused_nmad <= 1.05 * best_nmad, (fused_nmad, best_nmad)
    narrow = make_dem(
        triplet.images[0], triplet.images[1], triplet.models[0], triplet.models[1], st
    )
    narrow.write(tmp_path / "narrow")
    e_narrow = _errors(tmp_path / "narrow" / "dem.tif", triplet.truth_dem)
    assert fused_nmad < 0.8 * nmad(e_narrow[np.isfinite(e_narrow)])
    # layers: count 0..3 and 0 exactly where there is no height; σ shrinks with more pairs;
    # the pairs' spread (nmad layer) is of the order of the pair errors
    valid = np.isfinite(err)
    assert count.max() == 3 and ((count == 0) == ~valid).all()
    assert np.nanmedian(sigma[count == 3]) < np.nanmedian(sigma[count == 1])
    assert np.isnan(spread[count <= 1]).all() and np.isfinite(spread[count == 3]).all()
    assert 0.3 * best_nmad < np.nanmedian(spread[count == 3]) < 3 * best_nmad
    # the σ of three pairs agreeing is below the wide pair's a-priori σ
    gsd = triplet.models[0].gsd(0.5 * (lo + hi))
    assert np.nanmedian(sigma[count == 3]) < pair_sigma(gsd, rep["pair_runs"][1]["base_to_height"])


@pytest.mark.slow
def test_run_with_images_list(triplet, tmp_path):
    """``[inputs] images`` in a ``stereodem run`` configuration: the fused DEM goes through the
    filters and the orthoimage stage as a pair's does; raw/ holds the fused layers."""
    for k, (img, model) in enumerate(zip(triplet.images, triplet.models)):
        write_geotiff(tmp_path / f"v{k}.tif", img, tags={"STEREODEM_MODEL": f"v{k}.model.json"})
        save_model(model, tmp_path / f"v{k}.model.json")
    lo, hi = triplet.truth_dem.height_range()
    (tmp_path / "job.toml").write_text(
        f'[inputs]\nimages = ["v0.tif", "v1.tif", "v2.tif"]\n[output]\ndir = "out"\n'
        f"[rectification]\nheight_range = [{lo - 50:.0f}, {hi + 50:.0f}]\n[gridding]\nres = 30.0\n"
        f'[fusion]\nmax_pairs = 2\n[run]\nworkers = 1\n[dem]\npoint_cloud = "laz"\n'
    )
    cfg = load_config(tmp_path / "job.toml")
    info = run(cfg)
    out = tmp_path / "out"
    for name in (
        "raw/dem.tif",
        "raw/nmad.tif",
        "raw/dem_sigma_vertical.tif",
        "raw/count.tif",
        "dem.tif",
        "ortho_left.tif",
    ):
        assert (out / name).is_file(), name
    mv = info["stereo"]["info"]
    assert len(mv["pair_runs"]) == 2 and mv["pair_runs"][0]["right"] == 2  # widest base first
    assert sum(not p["selected"] for p in mv["pairs"]) == 1
    err, raw = (
        _errors(out / "dem.tif", triplet.truth_dem),
        _errors(out / "raw" / "dem.tif", triplet.truth_dem),
    )
    assert nmad(err[np.isfinite(err)]) <= nmad(raw[np.isfinite(raw)])  # the filters edit it
    # the point cloud of both pairs, classified by the filters' edit mask (with two pairs the
    # fusion rejects nothing: 3 x the NMAD of two heights exceeds their half-difference)
    laspy = pytest.importorskip("laspy")
    las = laspy.read(out / "dem.laz")
    pc = info["stages"]["point_cloud"]
    assert sorted(read_pairs(las)) == [r["pair_id"] for r in mv["pair_runs"]] == [0, 1]
    assert pc["n_points"] == len(las.points) == sum(r["n_points"] for r in mv["pair_runs"])
    # the points stay with the tile cache, for a later --resume (one folder per pair)
    kept = list((out / "tiles" / "points").rglob("points_*.npz"))
    assert sorted({p.parent.name for p in kept}) == ["pair_0", "pair_1"], kept
    with rasterio.open(out / "dem_edit_mask.tif") as ds:
        mask = ds.read(1)
        col, row = ~ds.transform @ (np.asarray(las.x), np.asarray(las.y))
    c, r = np.floor(col).astype(int), np.floor(row).astype(int)
    assert c.min() >= 0 and r.min() >= 0 and c.max() < mask.shape[1] and r.max() < mask.shape[0]
    cell_code, code = mask[r, c], np.asarray(las.edit_code)
    assert not (code == FUSION_REJECTED).any() and np.array_equal(code, cell_code)
    filtered = (cell_code >= 1) & (cell_code <= 99)
    assert filtered.any() and (~filtered).any()
    assert np.array_equal(np.asarray(las.classification) == 7, filtered)
    with pytest.raises(InputError, match="images or left/right"):
        config_from_dict(
            {"inputs": {"images": ["a.tif", "b.tif"], "left": "a.tif"}, "output": {"dir": "o"}}
        )


@pytest.mark.slow
def test_models_that_disagree_are_adjusted_first(triplet, tmp_path):
    """Image 1's delivered model is 1.5 px off along track: its pairs' heights are offset
    (opposite signs for 0-1 and 1-2). The bundle adjustment before the pairs removes the
    disagreement (the wide pair 0-2 is the datum) and the fused DEM is better for it."""
    paths = []
    for k, (img, model) in enumerate(zip(triplet.images, triplet.models)):
        write_geotiff(tmp_path / f"v{k}.tif", img, tags={"STEREODEM_MODEL": f"v{k}.model.json"})
        save_model(
            ImageCorrectedModel(model, row_shift=1.5) if k == 1 else model,
            tmp_path / f"v{k}.model.json",
        )
        paths.append(str(tmp_path / f"v{k}.tif"))
    lo, hi = triplet.truth_dem.height_range()
    out = {}
    for adjust in ("never", "auto"):
        cfg = Config(
            inputs=InputSettings(images=paths),
            output_dir=str(tmp_path / "o"),
            stereo=StereoSettings(
                RectificationSettings(height_range=(lo - 50, hi + 50)),
                gridding=GriddingSettings(res=30.0),
            ),
            run=RunSettings(workers=1),
            fusion=FusionSettings(adjust=adjust),
        )
        out[adjust] = multiview_stage(cfg, paths)
    adj = out["auto"].report["adjustment"]
    assert out["never"].report["adjustment"] is None and adj["applied"]
    assert adj["reprojection_rms_px_after"] < 0.5 * adj["reprojection_rms_px_before"]
    # the rays of image 1 miss their points by metres before, not after; the pairwise ray
    # gaps cannot see it (the error lies along the epipolar lines)
    before, after = (
        adj["point_ray_gaps_before"]["rms_m_per_image"],
        adj["point_ray_gaps_after"]["rms_m_per_image"],
    )
    assert after[1] < 0.3 * before[1], (before, after)
    assert adj["datum"].startswith("image 0 fixed, image 2")
    # image 1's delivered row_shift of 1.5 px is adjusted back to the true 0
    assert abs(adj["parameters"]["image1.row_shift"][0]) < 0.2, adj["parameters"]

    def spread(prod):  # pair medians against the fused DEM: how far the pairs disagree
        meds = [r["fusion"]["median_vs_fused_m"] for r in prod.report["pair_runs"]]
        return max(meds) - min(meds)

    assert spread(out["auto"]) < 0.5 * spread(out["never"])
    errs = {}
    for k, prod in out.items():
        prod.fused.write(tmp_path / k / "dem.tif")
        e = _errors(tmp_path / k / "dem.tif", triplet.truth_dem)
        errs[k] = (nmad(e[np.isfinite(e)]), abs(float(np.nanmedian(e))))
    assert errs["auto"][0] <= errs["never"][0] and errs["auto"][1] < 1.0, errs


@pytest.mark.slow  # over 0.5 s: out of the fast subset (CI runs it)
def test_dem_cli_names_and_skips_an_isolated_image(triplet, tmp_path, capsys):
    """An image that overlaps no other is named and skipped; the others make the DEM. The
    same image twice is refused in one line, nothing written."""
    far = PushbroomModel.synthetic_pair(16.5, 37.5, width=240, height=240)[0]  # another scene
    rng = np.random.default_rng(0)
    items = [
        (triplet.images[0], triplet.models[0]),
        (triplet.images[2], triplet.models[2]),
        (rng.integers(0, 255, (240, 240)).astype(np.uint8), far),
    ]
    paths = []
    for k, (img, model) in enumerate(items):
        write_geotiff(tmp_path / f"i{k}.tif", img, tags={"STEREODEM_MODEL": f"i{k}.model.json"})
        save_model(model, tmp_path / f"i{k}.model.json")
        paths.append(str(tmp_path / f"i{k}.tif"))
    lo, hi = triplet.truth_dem.height_range()
    hr = [str(lo - 50), str(hi + 50)]
    assert (
        main(
            [
                "dem",
                *paths,
                "-o",
                str(tmp_path / "out"),
                "--height-range",
                *hr,
                "--res",
                "30",
                "--workers",
                "1",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "fused from 1 pair(s)" in out and f"skipped {paths[2]}: overlaps no other image" in out
    rep = json.loads((tmp_path / "out" / "dem_report.json").read_text())["multiview"]
    assert rep["skipped_images"] == [dict(index=2, name=paths[2], reason="overlaps no other image")]
    assert (
        main(
            ["dem", paths[0], paths[1], paths[0], "-o", str(tmp_path / "o2"), "--height-range", *hr]
        )
        == 1
    )
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "given more than once" in err
    assert not (tmp_path / "o2").exists() or not any((tmp_path / "o2").iterdir())


def _at_points(path, x, y):
    """The raster interpolated bilinearly at map points (NaN next to voids and outside)."""
    with rasterio.open(path) as ds:
        a = ds.read(1).astype(np.float64)
        col, row = ~ds.transform @ (np.asarray(x), np.asarray(y))
    return map_coordinates(a, [row - 0.5, col - 0.5], order=1, cval=np.nan)


@pytest.mark.slow
def test_dem_cli_triplet_point_cloud(triplet, tmp_path, capsys):
    """``stereodem dem IMG1 IMG2 IMG3 --point-cloud las``: one cloud of every chosen pair's
    points, ``source_pair`` = the pair's ``pair_id`` in the report (and in the cloud's VLR), the
    points whose pair height the fusion rejected in their cell classified as noise (edit code
    98), and the points on the fused DEM.

    The pair-cloud test's bounds (median |z - DEM| < 1.5 m, |median z - DEM| < 0.2 m, ASTER pair
    of B/H 0.6) are for another scene: here the images are noisier (6 DN) and the narrow pairs
    have half the base, so a point's scatter about the DEM is set per pair in its a-priori σ
    (0.3 px x GSD / (B/H), 7.6 m wide, 15 m narrow; measured 0.24 σ wide, 0.35-0.36 σ narrow:
    1.9 m and 5.2-5.5 m); a shift of the points by half a cell (15 m) moves the median by
    0.8-2 m and one cell by 2-3.7 m, which the 0.2 m bias bound catches.
    """
    laspy = pytest.importorskip("laspy")
    paths = []
    for k, (img, model) in enumerate(zip(triplet.images, triplet.models)):
        p = tmp_path / f"view{k}.tif"
        write_geotiff(p, img, tags={"STEREODEM_MODEL": f"view{k}.model.json"})
        save_model(model, tmp_path / f"view{k}.model.json")
        paths.append(str(p))
    lo, hi = triplet.truth_dem.height_range()
    out = tmp_path / "out"
    argv = ["dem", *paths, "-o", str(out), "--height-range", str(lo - 50), str(hi + 50)]
    assert main(argv + ["--res", "30", "--workers", "1", "--point-cloud", "las"]) == 0
    assert "points of 3 pair(s)" in capsys.readouterr().out
    rep = json.loads((out / "dem_report.json").read_text())
    runs, pc = rep["multiview"]["pair_runs"], rep["point_cloud"]
    las = laspy.read(out / "dem.las")
    assert not (out / "tiles").exists()  # the pairs' point files are removed after the merge
    # the pair list: id -> images, in the report and in the cloud's VLR
    expected = {r["pair_id"]: [paths[r["left"]], paths[r["right"]]] for r in runs}
    assert sorted(expected) == [0, 1, 2]
    assert pc["pairs"] == {str(k): v for k, v in expected.items()}
    assert read_pairs(las) == expected
    # every pair's points, and only its own: the counts are the pair runs'
    sp = np.asarray(las.source_pair)
    assert np.array_equal(np.asarray(las.point_source_id), sp)
    assert pc["n_points"] == len(las.points) == sum(r["n_points"] for r in runs)
    for r in runs:
        assert int((sp == r["pair_id"]).sum()) == r["n_points"] > 10000, r["pair_id"]
    # the fusion's rejections: class 7 exactly where edit code 98, in as many cells as the
    # report counts at most, far from the fused DEM
    z = np.asarray(las.z)
    dem = _at_points(out / "dem.tif", las.x, las.y)
    assert np.isfinite(dem).mean() > 0.97
    code, cls = np.asarray(las.edit_code), np.asarray(las.classification)
    rejected = code == FUSION_REJECTED
    assert set(np.unique(code)) <= {0, FUSION_REJECTED}  # `dem` does not filter
    assert np.array_equal(cls == 7, rejected) and np.all(cls[~rejected] == 1)
    assert pc["classes"]["of which rejected by the N-view fusion"] == int(rejected.sum())
    with rasterio.open(out / "dem.tif") as ds:
        col, row = ~ds.transform @ (np.asarray(las.x), np.asarray(las.y))
    cell = np.floor(row).astype(np.int64) * 100_000 + np.floor(col).astype(np.int64)
    for r in runs:
        mine = rejected & (sp == r["pair_id"])
        assert 0 < np.unique(cell[mine]).size <= r["fusion"]["rejected"], r
    d = z - dem
    ok = np.isfinite(d)
    assert np.median(np.abs(d[rejected & ok])) > 5 * np.median(np.abs(d[~rejected & ok]))
    # the kept points lie on the fused DEM
    kept = ok & ~rejected
    bias = float(np.median(d[kept]))
    print(f"median z - fused DEM over {kept.sum()} kept points: {bias:+.3f} m")
    assert abs(bias) < 0.2, bias
    for r in runs:
        m = kept & (sp == r["pair_id"])
        spread = float(np.median(np.abs(d[m])))
        print(f"pair {r['pair_id']}: median |z - DEM| {spread:.2f} m, σ {r['fusion']['sigma_m']} m")
        assert spread < 0.5 * r["fusion"]["sigma_m"], (r["pair_id"], spread)
