"""DEM stacks (issue 27): per-cell rates with outlier rejection, cloud masks, hypsometric
fill and volumes, the Zarr container, dates, and the stack/change commands with their bad
inputs. Small synthetic inputs (a crop of the bundled real SRTM tile)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine
from pyproj import CRS
from scipy import ndimage

import stereodem.post.biascorr as biascorr
import stereodem.post.spatialstats as ss
import stereodem.post.stack_build as sb
from stereodem.cli import main
from stereodem.core import geodesy
from stereodem.core.dem import DEM
from stereodem.core.errors import DEMError, InputError
from stereodem.core.grid import MapGrid
from stereodem.core.raster import write_geotiff
from stereodem.core.stats import nmad
from stereodem.core.threads import pool_initializer, worker_threads
from stereodem.post import stack as st
from stereodem.post.change import dem_change
from stereodem.post.clouds import GROW_BY_DISTANCE, CloudSettings, cloud_mask, grow_mask
from stereodem.post.dates import date_from_metadata, dem_dates
from stereodem.post.gp import GPSettings, gp_rates
from stereodem.post.rates import RateSettings, fit_rates, noise_limit
from stereodem.post.spatialstats import VariogramModel
from stereodem.post.stack import MASK_CLOUD
from stereodem.post.stack_build import (
    BuildSettings,
    add_dem,
    build_stack,
    check_inputs,
    exclude_mask,
    header_bounds_lonlat,
)
from stereodem.post.synthetic import InjectedErrors
from stereodem.post.synthetic_series import (
    dem_series,
    glacier_outline,
    utm_reference,
    write_polygons,
)
from stereodem.post.volumes import hypsometric_fill
from stereodem.sensor.simulation.multidate import thinning_truth, write_dem_series

TIMES = np.array([2003.5, 2007.6, 2011.5, 2015.6, 2019.55])


# ----------------------------------------------------------------------------- rates


def test_rates_noise_only_match_the_formal_sigma():
    rng = np.random.default_rng(0)
    n = 40_000
    true = rng.uniform(-2, 0, n)
    sig = np.array([2.0, 3.0, 2.5, 2.0, 3.0])
    h = 1500 + true * (TIMES[:, None] - 2010) + rng.normal(0, 1, (5, n)) * sig[:, None]
    r = fit_rates(h, TIMES, sig)
    limit = noise_limit(TIMES, sig)
    full = r["n_obs"] == 5
    assert np.allclose(r["rate_sigma"][full], limit, rtol=1e-5)
    err = r["rate"] - true
    assert abs(np.std(err) / limit - 1) < 0.03
    assert abs(np.mean(err)) < 3 * limit / np.sqrt(n)
    assert (r["n_obs"] >= 4).mean() > 0.999  # k = 4 rejects almost nothing from noise


@pytest.mark.parametrize("index", [0, 2, 4])
def test_rates_reject_a_blunder_anywhere_in_the_series(index):
    rng = np.random.default_rng(index)
    n = 2000
    h = 1000 - 1.0 * (TIMES[:, None] - 2010) + rng.normal(0, 2, (5, n))
    h[index] += 60.0  # 30 σ: a blunder the line must not follow
    r = fit_rates(h, TIMES, np.full(5, 2.0), settings=RateSettings(max_deviation=np.inf))
    assert (~r["kept"][index]).mean() > 0.99
    assert np.all(r["n_rejected"] >= 1)
    assert abs(np.mean(r["rate"]) + 1.0) < 0.02
    assert nmad(r["rate"] + 1.0) < 1.3 * noise_limit(TIMES[np.arange(5) != index], np.full(4, 2.0))


def test_rates_masks_min_obs_and_gross_deviation():
    h = np.tile((100 + 0.5 * (TIMES - 2010))[:, None], (1, 4)).astype(np.float32)
    h[1:, 0] = np.nan  # one observation: no rate
    valid = np.ones(h.shape, bool)
    valid[:3, 1] = False  # two left by the mask
    h[2, 2] = 900.0  # a cloud top, dropped by the temporal median
    r = fit_rates(h, TIMES, np.full(5, 1.0), valid=valid)
    assert np.isnan(r["rate"][0]) and r["n_obs"][0] == 1
    assert r["n_obs"][1] == 2 and r["rate"][1] == pytest.approx(0.5, abs=1e-4)
    assert (
        r["n_obs"][2] == 4 and not r["kept"][2, 2] and r["rate"][2] == pytest.approx(0.5, abs=1e-4)
    )
    assert r["rate"][3] == pytest.approx(0.5, abs=1e-4) and r["n_rejected"][3] == 0


def test_rates_refuse_repeated_dates_and_bad_sigma():
    h = np.zeros((3, 2))
    with pytest.raises(InputError, match="repeated"):
        fit_rates(h, [2001.0, 2001.0, 2005.0], np.ones(3))
    with pytest.raises(InputError, match="positive"):
        fit_rates(h, [2001.0, 2003.0, 2005.0], np.array([1.0, 0.0, 1.0]))


# ----------------------------------------------------------------------------- clouds, fill


def test_cloud_mask_signs_and_growth():
    rng = np.random.default_rng(1)
    ref = rng.normal(2000, 50, (60, 60)).astype(np.float32)
    h = ref + 4.0 + rng.normal(0, 2, ref.shape).astype(np.float32)
    h[20:30, 20:30] += 400.0  # cloud top
    score = np.full(ref.shape, 0.9, np.float32)
    score[40:45, 5:10] = 0.1  # low matcher score
    radiance = np.full(ref.shape, 60.0, np.float32)
    radiance[5:8, 40:50] = 200.0  # bright
    m, info = cloud_mask(
        h,
        settings=CloudSettings(max_deviation=50, min_score=0.5, max_radiance=150, grow=2),
        reference=ref,
        score=score,
        radiance=radiance,
    )
    assert m[20:30, 20:30].all() and m[18, 25] and not m[16, 25]  # grown by 2 cells
    assert m[40:45, 5:10].all() and m[5:8, 40:50].all()
    assert info["deviation_pct"] == pytest.approx(100 * 100 / 3600, abs=0.01)
    assert info["dh_nmad"] == pytest.approx(2.0, rel=0.15)
    off, info0 = cloud_mask(h, settings=CloudSettings(max_deviation=None), reference=ref)
    assert not off.any() and info0["cloud_pct"] == 0


@pytest.mark.parametrize("cells", [1, GROW_BY_DISTANCE, GROW_BY_DISTANCE + 1, 40, 10**11])
def test_a_grow_of_any_size_is_the_iterated_cross_dilation(cells):
    # before: --cloud-grow 99999999999 was an OverflowError from scipy's iteration count (a
    # traceback), and a grow of thousands of cells thousands of passes over the mask
    rng = np.random.default_rng(2)
    mask = np.zeros((70, 90), bool)
    mask[rng.integers(0, 70, 12), rng.integers(0, 90, 12)] = True
    mask[30:33, 0:4] = True  # touching the border
    expected = ndimage.binary_dilation(mask, iterations=min(cells, 160))  # 160: rows + cols
    np.testing.assert_array_equal(grow_mask(mask, cells), expected)
    assert not grow_mask(np.zeros((5, 5), bool), cells).any()


def test_hypsometric_fill_uses_the_local_elevation_bands():
    z = np.tile(np.linspace(2000, 3000, 80), (60, 1))  # elevation rises east
    rate = (-3 + 0.002 * (z - 2000)).astype(np.float32)  # thinning weaker higher up
    inside = np.zeros(z.shape, bool)
    inside[10:50, 5:75] = True
    holes = np.zeros(z.shape, bool)
    holes[20:40, 30:45] = True
    v = rate.copy()
    v[holes] = np.nan
    v[~inside] = 5.0  # outside must not leak in
    filled, where, bands = hypsometric_fill(v, z, inside, band_width=50)
    assert where.sum() == holes.sum()
    assert np.abs(filled[holes] - rate[holes]).max() < 0.05 + 1e-6  # half a band of 0.1 m/yr
    assert sum(b["n_filled"] for b in bands) == holes.sum()


# ----------------------------------------------------------------------------- container


def _grid(n=40):
    return MapGrid(Affine(30, 0, 500000, 0, -30, 4400000), n + 10, n, CRS.from_epsg(32637))


@pytest.mark.slow  # over 0.6 s: out of the fast subset (CI runs it)
def test_zarr_stack_round_trip_reads_with_plain_xarray(tmp_path):
    import xarray as xr  # optional (the stack extra)

    g = _grid()
    dates = [np.datetime64(d) for d in ("2004-07-01", "2011-08-02", "2019-07-20")]
    ref = np.full(g.shape, 1000, np.float32)
    rng = np.random.default_rng(2)
    hs = [ref + rng.normal(0, 1, g.shape).astype(np.float32) for _ in dates]
    store = tmp_path / "stack.zarr"
    st.create_stack(store, g, dates, reference=ref, stable=np.ones(g.shape, np.uint8), chunk=16)
    for i, h in enumerate(hs):
        m = np.zeros(g.shape, np.uint8)
        m[0, i] = st.MASK_CLOUD
        st.write_date(store, i, h, m, 1.5 + i)
    ds = xr.open_zarr(store)  # plain xarray, no stereodem reader
    assert ds["height"].dims == ("time", "y", "x")
    assert np.array_equal(ds["height"].values, np.stack(hs))
    assert ds["sigma"].values.tolist() == [1.5, 2.5, 3.5]
    assert ds["mask"].values[2, 0, 2] == st.MASK_CLOUD
    assert list(ds["time"].values.astype("datetime64[D]")) == dates
    assert ds["x"].values[0] == 500015.0 and ds["y"].values[0] == 4399985.0
    assert "UTM zone 37N" in ds["spatial_ref"].attrs["crs_wkt"]
    assert st.stack_grid(ds) == g
    rio = pytest.importorskip("rioxarray")
    assert rio and ds.rio.crs.to_epsg() == 32637
    assert tuple(ds.rio.transform())[:6] == tuple(g.transform)[:6]


# ----------------------------------------------------------------------------- dates


def test_dates_from_metadata_csv_and_list(tmp_path):
    a, b = tmp_path / "a" / "dem.tif", tmp_path / "b.tif"
    a.parent.mkdir()
    for p in (a, b):
        write_geotiff(
            p, np.ones((8, 8), np.float32), Affine(30, 0, 5e5, 0, -30, 4.4e6), "EPSG:32637"
        )
    (a.parent / "run.json").write_text(
        json.dumps({"input_metadata": {"ASTER_ACQUISITION_TIME": "2005-06-07T08:30:01Z"}})
    )
    with pytest.raises(Exception, match="b.tif: no acquisition date"):
        dem_dates([a, b])
    csv = tmp_path / "dates.csv"
    csv.write_text("path,date\na/dem.tif,2004-01-02\nb.tif,2010-03-04\n")
    got = dem_dates([a, b], str(csv))
    assert [str(d) for d in got] == ["2004-01-02T00:00:00", "2010-03-04T00:00:00"]

    assert str(date_from_metadata(a)) == "2005-06-07T08:30:01"
    assert [str(d)[:10] for d in dem_dates([a, b], "2001-01-01,2002-02-02")] == [
        "2001-01-01",
        "2002-02-02",
    ]


# ----------------------------------------------------------------------------- commands


@pytest.fixture(scope="module")
def series(tmp_path_factory):
    """Four dated DEMs of a 70 x 70 crop of the bundled SRTM (90 m) with shift, offset, ramp,
    correlated noise, a cloud in one and a thinning inside an outline; reference and outline."""
    d = tmp_path_factory.mktemp("series")
    ref = utm_reference(DEM.bundled(), 70, 90.0, centre_lonlat=(40.4, 39.6))
    outline = glacier_outline(ref.grid, radius=0.2)
    truth = thinning_truth(ref.grid, ref.heights, outline, t_ref=2000.1)
    dates = ["2004-07-01", "2009-08-01", "2014-07-15", "2019-07-20"]
    noise = VariogramModel(np.array([200.0]), np.array([4.0]))
    specs = [
        InjectedErrors(
            dx=25 - 15 * k, dy=10 * k - 15, dz=2.0 - k, ramp_e=2.0 - k, noise=noise, seed=k
        )
        for k in range(4)
    ]
    clouds = [None, {"centre": (18, 20), "radius": 7, "top": 3600.0}, None, None]
    ser = dem_series(truth, dates, specs, clouds=clouds, vertical="geoid")
    paths = write_dem_series([s.dem for s in ser], dates, d / "dems")
    ref.path = str(d / "ref.tif")
    ref.write(ref.path)
    write_polygons(d / "glacier.gpkg", [outline], ref.crs)
    return dict(
        dir=d,
        paths=[str(p) for p in paths],
        ref=ref.path,
        truth=truth,
        series=ser,
        outline=str(d / "glacier.gpkg"),
        dates=dates,
    )


def _run(argv, capsys):
    rc = main(argv)
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


@pytest.mark.slow
def test_stack_command_recovers_the_rate_and_masks_the_cloud(series, tmp_path, capsys):
    import xarray as xr  # optional (the stack extra)

    out = tmp_path / "out"
    rc, _so, se = _run(
        [
            "stack",
            *series["paths"],
            "--ref",
            series["ref"],
            "--chain",
            "nuth_kaab,deramp:1",
            "--exclude",
            series["outline"],
            "--outlines",
            series["outline"],
            "--workers",
            "2",
            "--chunk",
            "32",
            "-o",
            str(out),
        ],
        capsys,
    )
    assert rc == 0, se
    with rasterio.open(out / "rate.tif") as ds:
        rate = ds.read(1)
        assert ds.crs.to_epsg() == series["truth"].grid.crs.to_epsg()
    n_obs = rasterio.open(out / "n_obs.tif").read(1)
    true = series["truth"].rate
    inside = true != 0
    cloud = series["series"][1].cloud
    err = rate - true
    assert abs(np.nanmean(err[inside])) < 0.1
    limit = noise_limit([2004.5, 2009.58, 2014.54, 2019.55], np.full(4, 2.0))
    assert nmad(rate[~inside & ~cloud]) < 1.3 * limit
    assert np.all(n_obs[cloud] == 3)  # the cloud date left out there
    assert np.nanmax(np.abs(err[cloud])) < 5 * limit  # and nothing of it in the rate
    ds = xr.open_zarr(out / "stack.zarr")
    assert ds.sizes["time"] == 4 and (ds["mask"].values[1][cloud] & 2).all()
    vol = json.loads((out / "volumes.json").read_text())["polygons"][0]
    truth_vol = float(true[inside].mean()) * vol["area_m2"]
    assert abs(vol["volume_rate_m3_per_yr"] - truth_vol) < 2 * vol["volume_rate_sigma"]
    summary = json.loads((out / "stack.json").read_text())
    assert summary["status"] == "ok" and len(summary["dems"]) == 4
    assert summary["figures"] == {
        k: f"{k}.png" for k in ("rate_map", "rate_sigma_map", "n_obs_map")
    }
    assert all((out / f).is_file() for f in summary["figures"].values())
    # the same folder again: refused without --overwrite, replaced with it
    rc, _, se = _run(
        ["stack", *series["paths"], "--ref", series["ref"], "--chain", "vshift", "-o", str(out)],
        capsys,
    )
    assert rc == 1 and "--overwrite" in se
    rc, _, se = _run(
        [
            "stack",
            *series["paths"][:2],
            "--ref",
            series["ref"],
            "--chain",
            "vshift",
            "-o",
            str(out),
            "--overwrite",
        ],
        capsys,
    )
    assert rc == 0, se
    assert xr.open_zarr(out / "stack.zarr").sizes["time"] == 2


@pytest.mark.slow
def test_change_command_gives_dh_and_sigma(series, tmp_path, capsys):
    out = tmp_path / "chg"
    a, b = series["paths"][0], series["paths"][3]
    rc, _so, se = _run(["change", a, b, "--exclude", series["outline"], "-o", str(out)], capsys)
    assert rc == 0, se
    dh = rasterio.open(out / "dh.tif").read(1)
    sig = rasterio.open(out / "dh_sigma.tif").read(1)
    true = series["truth"].rate * (2019.55 - 2004.5)
    inside = true != 0
    assert abs(np.nanmean(dh[inside] - true[inside])) < 1.0
    st = ~inside & np.isfinite(dh)
    assert 0.5 < nmad(dh[st]) / np.nanmedian(sig[st]) < 1.5  # σ map says the dispersion
    info = json.loads((out / "change.json").read_text())
    assert info["years"] == pytest.approx(15.05, abs=0.01)
    # the quick looks, listed in change.json and a product of the folder
    assert info["figures"] == {"dh_map": "dh_map.png", "dh_sigma_map": "dh_sigma_map.png"}
    assert all((out / f).read_bytes()[:4] == b"\x89PNG" for f in info["figures"].values())


def _without_seconds(x):
    """A report without its timings (``seconds`` keys)."""
    if isinstance(x, dict):
        return {k: _without_seconds(v) for k, v in x.items() if k != "seconds"}
    if isinstance(x, list):
        return [_without_seconds(v) for v in x]
    return x


@pytest.mark.slow
def test_change_command_is_the_same_on_any_number_of_workers(series, tmp_path, capsys, monkeypatch):
    """--workers 1 and 2 write the same dh, σ map and report, to the bit: the warp, the
    curvature's row bands and the σ map's bins and cells on threads (issue 28). Small pieces
    so that a 70 x 70 grid is cut as a large one is."""
    monkeypatch.setattr(biascorr, "CURVATURE_BAND_ROWS", 8)
    monkeypatch.setattr(ss, "CHUNK", 500)
    a, b = series["paths"][0], series["paths"][3]
    outs = []
    for workers in ("1", "2"):
        out = tmp_path / f"chg{workers}"
        rc, _so, se = _run(
            ["change", a, b, "--exclude", series["outline"], "--workers", workers, "-o", str(out)],
            capsys,
        )
        assert rc == 0, se
        outs.append(out)
    for name in ("dh.tif", "dh_sigma.tif"):
        one, two = (rasterio.open(o / name).read(1) for o in outs)
        assert one.tobytes() == two.tobytes(), name
    one, two = (_without_seconds(json.loads((o / "change.json").read_text())) for o in outs)
    assert json.dumps(one) == json.dumps(two)
    rc, _so, se = _run(["change", a, b, "--workers", "0", "-o", str(tmp_path / "w0")], capsys)
    assert rc == 1 and "--workers must be at least 1" in se and not (tmp_path / "w0").exists()


@pytest.mark.parametrize(
    "case", ["no_dates", "single", "no_overlap", "future", "repeated", "count", "reference"]
)
def test_stack_bad_input_is_one_line_and_writes_nothing(series, tmp_path, capsys, case):
    paths = series["paths"][:3]
    extra = []
    if case == "no_dates":
        bare = tmp_path / "bare.tif"
        write_geotiff(
            bare, np.ones((20, 20), np.float32), Affine(90, 0, 5e5, 0, -90, 4.4e6), "EPSG:32637"
        )
        paths = [paths[0], str(bare)]
        expect = "no acquisition date"
    elif case == "single":
        paths = paths[:1]
        expect = "at least 2 DEMs"
    elif case == "no_overlap":
        far = tmp_path / "far.tif"
        write_geotiff(
            far,
            np.ones((20, 20), np.float32),
            Affine(90, 0, 2e5, 0, -90, 1.0e6),
            "EPSG:32637",
            tags={"ACQUISITION_DATE": "2012-01-01"},
        )
        paths = [paths[0], str(far)]
        expect = "does not overlap"
    elif case == "future":
        extra = ["--dates", "2004-07-01,2009-08-01,2999-01-01"]
        expect = "in the future"
    elif case == "repeated":
        extra = ["--dates", "2004-07-01,2009-08-01,2009-08-01"]
        expect = "repeats"
    elif case == "reference":  # the reference as a date: no error against itself
        paths = [paths[0], series["ref"]]
        extra = ["--dates", "2004-07-01,2012-01-01"]
        expect = f"{series['ref']}: its heights equal the reference's"
    else:
        extra = ["--dates", "2004-07-01,2009-08-01"]
        expect = "2 date"
    out = tmp_path / "out"
    rc, _so, se = _run(["stack", *paths, "--ref", series["ref"], *extra, "-o", str(out)], capsys)
    assert rc == 1
    assert len(se.strip().splitlines()) == 1 and expect in se and "Traceback" not in se
    if case == "reference":  # refused while the stack is built: the folder says so
        status = json.loads((out / "stack.json").read_text())
        assert status["status"] == "failed" and expect in status["error"]
    else:  # refused before the output folder is touched
        assert not out.exists()


def test_gp_rate_is_wls_without_the_nonlinear_part_and_wider_with_it():
    rng = np.random.default_rng(4)
    h = 500 - 0.8 * (TIMES[:, None] - 2010) + rng.normal(0, 2, (5, 300))
    h[1, :100] = np.nan  # two observation patterns
    sig = np.array([2.0, 2.5, 2.0, 3.0, 2.0])
    w = fit_rates(h, TIMES, sig, settings=RateSettings(k=1e9, max_deviation=np.inf))
    g0 = gp_rates(h, TIMES, sig, settings=GPSettings(sigma_f=1e-6))
    assert np.allclose(g0["rate"], w["rate"], atol=1e-4)
    assert np.allclose(g0["rate_sigma"], w["rate_sigma"], rtol=1e-4)
    g = gp_rates(h, TIMES, sig, settings=GPSettings(sigma_f=3.0, length=4.0))
    assert np.all(g["rate_sigma"] > w["rate_sigma"])
    assert g["n_obs"][0] == 4 and g["n_obs"][-1] == 5


def test_filter_uses_the_cloud_mask(series, tmp_path, capsys):
    out = tmp_path / "clean.tif"
    rc, _so, se = _run(
        [
            "filter",
            series["paths"][1],
            "-o",
            str(out),
            "--seed-dem",
            series["ref"],
            "--cloud-max-dev",
            "50",
            "--no-fill",
            "--no-filters",
        ],
        capsys,
    )
    assert rc == 0, se
    z = rasterio.open(out).read(1)
    edit = rasterio.open(tmp_path / "clean_edit_mask.tif").read(1)
    cloud = series["series"][1].cloud
    assert np.isnan(z[cloud]).all() and (edit[cloud] == 9).all()
    assert np.isfinite(z[~cloud]).mean() > 0.9
    rc, _, se = _run(
        ["filter", series["paths"][1], "-o", str(tmp_path / "c2.tif"), "--cloud-max-dev", "50"],
        capsys,
    )
    assert rc == 1 and "--seed-dem" in se and len(se.strip().splitlines()) == 1


@pytest.mark.slow  # over 0.5 s: out of the fast subset (CI runs it)
def test_stack_default_chain_leaves_out_along_track_without_a_heading(series, tmp_path, capsys):
    out = tmp_path / "o"
    rc, _so, se = _run(
        ["stack", *series["paths"][:2], "--ref", series["ref"], "-o", str(out)], capsys
    )
    assert rc == 0, se
    dems = json.loads((out / "stack.json").read_text())["dems"]
    assert [d["chain"] for d in dems] == ["nuth_kaab,deramp:1"] * 2
    assert [r["step"] for r in dems[0]["coregistration"]] == ["nuth_kaab", "deramp:1"]


@pytest.mark.slow
def test_parallel_build_writes_the_same_stack(series, tmp_path):
    import xarray as xr  # optional (the stack extra)

    ref = DEM.from_file(series["ref"])
    dates = [np.datetime64(d) for d in series["dates"][:3]]
    s = BuildSettings(chain="nuth_kaab", chunk=32)
    one = build_stack(series["paths"][:3], dates, ref, tmp_path / "a.zarr", s, workers=1)
    two = build_stack(series["paths"][:3], dates, ref, tmp_path / "b.zarr", s, workers=2)
    a, b = xr.open_zarr(tmp_path / "a.zarr"), xr.open_zarr(tmp_path / "b.zarr")
    assert np.array_equal(a["height"].values, b["height"].values, equal_nan=True)
    assert np.array_equal(a["mask"].values, b["mask"].values)
    assert [r["sigma"] for r in one] == [r["sigma"] for r in two]


def test_parallel_build_pins_each_process_to_its_share_of_the_cores(series, tmp_path, monkeypatch):
    """The build's processes are pinned as the tile pool's are (issue 28): spawned, they
    took the parent's whole thread budget each (2 processes x 2 BLAS/OpenCV/GDAL threads on 2
    cores)."""
    seen = {}

    class Stop(Exception):
        pass

    def pool(**kw):
        seen.update(kw)
        raise Stop

    monkeypatch.setattr(sb, "ProcessPoolExecutor", pool)
    ref = DEM.from_file(series["ref"])
    dates = [np.datetime64(d) for d in series["dates"][:3]]
    s = BuildSettings(chain="vshift", chunk=32)
    with pytest.raises(Stop):
        build_stack(series["paths"][:3], dates, ref, tmp_path / "a.zarr", s, workers=2)
    assert seen["max_workers"] == 2 and seen["initializer"] is pool_initializer
    assert seen["initargs"][0] == worker_threads(2) and seen["initargs"][2] is sb._init_worker


def test_dates_csv_missing_is_one_line(tmp_path):
    with pytest.raises(InputError, match="cannot read the dates CSV"):
        dem_dates(["a.tif", "b.tif"], str(tmp_path / "nope.csv"))


def test_stack_uses_the_score_and_radiance_layers_beside_a_dem(series, tmp_path):
    d = tmp_path / "run"
    d.mkdir()
    dem = d / "dem.tif"
    shutil.copy(series["paths"][0], dem)
    with rasterio.open(dem) as ds:
        t, crs, shape = ds.transform, ds.crs.to_wkt(), ds.shape
    score = np.full(shape, 0.9, np.float32)
    score[40:50, 40:50] = 0.2
    radiance = np.full(shape, 80.0, np.float32)
    radiance[5:12, 50:60] = 220.0
    write_geotiff(d / "score.tif", score, t, crs)
    write_geotiff(d / "ortho_left.tif", radiance, t, crs)
    ref = DEM.from_file(series["ref"])
    s = BuildSettings(
        chain="vshift",
        cloud=CloudSettings(max_deviation=None, min_score=0.5, max_radiance=150, grow=1),
    )
    h, flags, sigma, rec = add_dem(ref, dem, s, exclude_mask([], ref))
    cloud = (flags & MASK_CLOUD) > 0
    assert cloud[42:48, 42:48].all() and cloud[7:10, 52:58].all()
    assert rec["score_layer"] and rec["radiance_layer"]
    assert rec["clouds"]["score_pct"] > 0 and rec["clouds"]["radiance_pct"] > 0
    assert cloud.mean() < 0.1 and sigma > 0


def test_header_footprint_of_a_south_up_or_ungeoreferenced_dem(tmp_path):
    """``ds.bounds`` of a south-up grid has its bottom above its top: in a geographic CRS the
    footprint came out inverted and `change`/`stack` refused the DEM as not overlapping the
    reference; a file without a geotransform was said not to overlap either."""
    prof = dict(driver="GTiff", width=4, height=3, count=1, dtype="float32", crs="EPSG:4326")
    t = Affine(0.01, 0, 40.0, 0, 0.01, 39.0)  # rows going north
    with rasterio.open(tmp_path / "south_up.tif", "w", transform=t, **prof) as ds:
        ds.write(np.ones((1, 3, 4), np.float32))
    b = header_bounds_lonlat(tmp_path / "south_up.tif")
    assert b == pytest.approx((40.0, 39.0, 40.04, 39.03))
    with rasterio.open(tmp_path / "no_transform.tif", "w", **prof) as ds:
        ds.write(np.ones((1, 3, 4), np.float32))
    with pytest.raises(DEMError, match=r"no_transform\.tif: the DEM has no geotransform"):
        header_bounds_lonlat(tmp_path / "no_transform.tif")


def test_a_projected_dem_across_the_antimeridian_overlaps_its_reference(tmp_path):
    """GDAL gives the footprint of a UTM zone 1 DEM across 180 E as west 179.98 > east
    -179.98: `stack` refused it as not overlapping a reference over the same ground."""
    x0, y0 = geodesy.lonlat_to_crs(180.0, 60.0, "EPSG:32601")
    t = Affine(100, 0, float(x0) - 1000, 0, -100, float(y0) + 1000)
    prof = dict(driver="GTiff", width=20, height=20, count=1, dtype="float32")
    for name in ("a.tif", "b.tif"):
        with rasterio.open(tmp_path / name, "w", crs="EPSG:32601", transform=t, **prof) as ds:
            ds.write(np.full((1, 20, 20), 500.0, np.float32))
    ref = DEM(
        np.full((30, 30), 500.0, np.float32), Affine(0.001, 0, 179.985, 0, -0.001, 60.015), 4326
    )
    check_inputs([tmp_path / "a.tif", tmp_path / "b.tif"], ref)  # no NoOverlapError
    far = DEM(ref.heights, Affine(0.001, 0, 170.0, 0, -0.001, 60.015), 4326, path="far.tif")
    with pytest.raises(InputError, match="does not overlap the reference far.tif"):
        check_inputs([tmp_path / "a.tif", tmp_path / "b.tif"], far)


def test_change_no_overlap_names_dem_a_not_a_reference(tmp_path, capsys):
    """``stereodem change A B``: B beside A is refused naming A as DEM_A (the command has no
    reference), one line, nothing written."""
    z = np.full((20, 20), 100.0, np.float32)
    a, b = tmp_path / "a.tif", tmp_path / "b.tif"
    write_geotiff(a, z, Affine(90, 0, 5e5, 0, -90, 4.4e6), "EPSG:32637")
    write_geotiff(b, z, Affine(90, 0, 2e5, 0, -90, 1.0e6), "EPSG:32637")
    out = tmp_path / "out"
    rc, _so, se = _run(["change", str(a), str(b), "-o", str(out)], capsys)
    assert rc == 1 and len(se.strip().splitlines()) == 1, se
    assert f"does not overlap DEM_A {a}" in se and "reference" not in se
    assert not out.exists()


def test_dem_change_takes_dem_paths(tmp_path):
    """``dem_change("a.tif", "b.tif")`` raised AttributeError ('str' object has no attribute
    'vertical'); every other public DEM function takes a path too."""
    full = DEM.bundled()
    a = DEM(full.heights[:80, :80].copy(), full.transform, full.crs, "geoid")
    noise = np.random.default_rng(0).normal(0, 0.3, a.shape).astype(np.float32)
    b = DEM(a.heights + 2.0 + noise, a.transform, a.crs, "geoid")
    pa, pb = a.write(tmp_path / "a.tif"), b.write(tmp_path / "b.tif")
    out = dem_change(pa, pb, chain="vshift")
    assert abs(float(np.nanmedian(out["dh"]))) < 0.05
    with pytest.raises(DEMError, match="expected a DEM or a path, got ndarray"):
        dem_change(a.heights, b)


def _stack_argv(paths, ref, out, *more):
    return [
        *("stack", *map(str, paths), "--ref", str(ref), "--chain", "vshift", "-o", str(out)),
        *more,
    ]


@pytest.mark.slow
def test_a_failed_stack_is_run_again_without_overwrite(series, tmp_path, capsys, monkeypatch):
    """A stack that failed on an unreadable DEM left stack.json and stack.zarr, and the same
    command, once the DEM was mended, was refused without --overwrite. Its stack.json says
    failed and records the inputs: the same inputs replace its files; other inputs, and a
    finished stack, still need --overwrite. (A DEM damaged where its header and first and
    last blocks are read is refused before any work; one damaged elsewhere fails while the
    stack is built: that is made here by a DEM whose reading fails in the build.)"""
    dems = tmp_path / "dems"
    shutil.copytree(series["dir"] / "dems", dems)
    paths = sorted(dems.glob("*.tif"))[:3]
    damaged = {str(paths[2])}
    add_dem = sb.add_dem

    def failing(reference, path, *args):
        if str(path) in damaged:
            raise DEMError(f"{path}: cannot read the DEM (its pixels do not decode)")
        return add_dem(reference, path, *args)

    monkeypatch.setattr(sb, "add_dem", failing)
    one_worker = ("--workers", "1")  # in this process: the build's failure is made here

    out = tmp_path / "out"
    rc, _so, se = _run(_stack_argv(paths, series["ref"], out, *one_worker), capsys)
    assert rc == 1 and f"{paths[2]}: cannot read the DEM" in se, se
    failed = json.loads((out / "stack.json").read_text())
    assert failed["status"] == "failed"
    assert failed["inputs"] == sorted(str(Path(p).resolve()) for p in [*paths, series["ref"]])
    # the store is built under a hidden name and moved into place once complete: none is left
    assert sorted(p.name for p in out.iterdir()) == ["stack.json"]
    # other inputs: the failed job is not theirs
    rc, _so, se = _run(_stack_argv(paths[:2], series["ref"], out, *one_worker), capsys)
    assert rc == 1 and "stack.json: exists" in se and "--overwrite" in se, se
    assert json.loads((out / "stack.json").read_text()) == failed
    damaged.clear()  # mended
    rc, _so, se = _run(_stack_argv(paths, series["ref"], out, *one_worker), capsys)
    assert rc == 0, se
    assert json.loads((out / "stack.json").read_text())["status"] == "ok"
    assert not list(out.glob(".stereodem-*"))  # the failed job's files gone
    # a finished stack
    rc, _so, se = _run(_stack_argv(paths, series["ref"], out, *one_worker), capsys)
    assert rc == 1 and "--overwrite" in se, se
    # replaced with --overwrite by a rerun that fails while building: it comes back whole
    # (it was deleted before the rerun started)
    finished = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    record = (out / "stack.json").read_text()
    damaged.add(str(paths[2]))
    rc, _so, se = _run(_stack_argv(paths, series["ref"], out, *one_worker, "--overwrite"), capsys)
    assert rc == 1 and f"{paths[2]}: cannot read the DEM" in se, se
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == finished
    assert (out / "stack.json").read_text() == record


@pytest.mark.slow
@pytest.mark.parametrize("how", ["interrupted", "killed"])
def test_an_interrupted_or_killed_stack_is_run_again_without_overwrite(
    series, tmp_path, capsys, monkeypatch, how
):
    """Ctrl-C while the rates are fitted (stack.json: interrupted), or a job killed outright
    (stack.json still says running, its lock gone): the same command runs again without
    --overwrite and its hint says so."""
    paths, out = series["paths"][:2], tmp_path / "out"
    argv = _stack_argv(paths, series["ref"], out)
    if how == "interrupted":

        def stopped(*args, **kwargs):
            raise KeyboardInterrupt

        monkeypatch.setattr(st, "stack_rates", stopped)
        rc, _so, se = _run(argv, capsys)
        assert rc == 130 and "run the same command again" in se, se
        assert json.loads((out / "stack.json").read_text())["status"] == "interrupted"
        monkeypatch.undo()
    else:
        from stereodem.core import jsonutil
        from stereodem.outlock import job_inputs

        out.mkdir()
        (out / "stack.zarr").mkdir()
        record = {"status": "running", "inputs": job_inputs([*paths, series["ref"]])}
        (out / "stack.json").write_text(jsonutil.dumps(jsonutil.stamped(record)))
    assert (out / "stack.zarr").exists()
    rc, _so, se = _run(argv, capsys)
    assert rc == 0, se
    assert json.loads((out / "stack.json").read_text())["status"] == "ok"


@pytest.mark.slow
def test_a_failed_stack_beside_the_users_files_still_needs_overwrite(series, tmp_path, capsys):
    """Only the unfinished job's own files are replaced without --overwrite: a stack.json of
    the user's (not written by stereodem) saying failed with the same inputs, or a file of
    the user's beside a failed job's products, keep the folder refused without it."""
    from stereodem.core import jsonutil
    from stereodem.outlock import job_inputs

    paths = series["paths"][:2]
    record = {"status": "failed", "inputs": job_inputs([*paths, series["ref"]])}
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "stack.json").write_text(json.dumps(record))  # no stereodem stamp
    rc, _so, se = _run(_stack_argv(paths, series["ref"], mine), capsys)
    assert rc == 1 and "stack.json: exists" in se and "--overwrite" in se, se
    assert json.loads((mine / "stack.json").read_text()) == record
    beside = tmp_path / "beside"
    beside.mkdir()
    (beside / "stack.json").write_text(jsonutil.dumps(jsonutil.stamped(record)))
    (beside / "notes.txt").write_text("mine")
    rc, _so, se = _run(_stack_argv(paths, series["ref"], beside), capsys)
    assert rc == 1 and "notes.txt" in se and "--overwrite" in se, se
    rc, _so, se = _run([*_stack_argv(paths, series["ref"], beside), "--overwrite"], capsys)
    assert rc == 0, se
    assert (beside / "notes.txt").read_text() == "mine"
