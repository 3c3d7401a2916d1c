"""``stereodem mosaic`` / :mod:`stereodem.post.mosaic`: blending, statistics, CRSs and vertical
references, co-registration, block independence, bounded memory, bad input (issue 26 item 4).

Small synthetic DEMs (a smooth terrain on a UTM 37N lattice, 30 m) cut into overlapping
windows with known biases; every expectation is computed independently with numpy.
"""

from __future__ import annotations

import json
import logging
import re
import subprocess
import sys
import tracemalloc
import warnings

import cv2
import numpy as np
import pytest
import rasterio
from affine import Affine
from pyproj import CRS as PCRS
from pyproj.crs import CompoundCRS
from rasterio.warp import Resampling, calculate_default_transform, reproject

import stereodem.post.mosaic as pm
from stereodem.cli import main
from stereodem.core import geodesy, threads, warp
from stereodem.core.dem import DEM as _DEM
from stereodem.core.errors import InputError, VerticalReferenceError
from stereodem.core.grid import MapGrid
from stereodem.core.raster import write_geotiff
from stereodem.options import posting
from stereodem.post.mosaic import memory_bound, plan_mosaic, read_on_grid, run_mosaic
from stereodem.post.mosaic_coreg import DEMCorrection, fitter

CRS = "EPSG:32637"
RES = 30.0
X0, Y0 = 400_020.0, 4_400_010.0  # top-left corner of the truth lattice


def terrain(rows, cols, r0=0, c0=0):
    """Smooth terrain (m) on the truth lattice's cells [r0:r0+rows, c0:c0+cols]."""
    y = Y0 - (np.arange(r0, r0 + rows) + 0.5) * RES
    x = X0 + (np.arange(c0, c0 + cols) + 0.5) * RES
    xx, yy = np.meshgrid(x, y)
    return (1500 + 300 * np.sin(xx / 2500.0) * np.cos(yy / 1900.0) + 0.01 * (xx - X0)).astype(
        np.float32
    )


def write_dem(
    path,
    r0,
    c0,
    rows,
    cols,
    *,
    bias=0.0,
    noise=0.0,
    vertical="geoid",
    seed=0,
    sigma=None,
    heights=None,
):
    z = terrain(rows, cols, r0, c0) + np.float32(bias) if heights is None else heights
    if noise:
        z = z + np.random.default_rng(seed).normal(0, noise, z.shape).astype(np.float32)
    t = Affine(RES, 0, X0 + c0 * RES, 0, -RES, Y0 - r0 * RES)
    if sigma is None:
        write_geotiff(path, z, t, CRS, np.nan, vertical=vertical, descriptions="height")
    else:
        write_geotiff(
            path,
            np.stack([z, np.full_like(z, sigma)]),
            t,
            CRS,
            np.nan,
            vertical=vertical,
            descriptions=["height", "sigma (1-sigma)"],
        )
    return path


def read(path, band=1):
    with rasterio.open(path) as ds:
        return ds.read(band), ds.transform, ds


def on_truth(path):
    """The mosaic's band 1 and the truth under it (same lattice)."""
    with rasterio.open(path) as ds:
        z = ds.read(1)
        t = ds.transform
    c0 = int(round((t.c - X0) / RES))
    r0 = int(round((Y0 - t.f) / RES))
    return z, terrain(z.shape[0], z.shape[1], r0, c0)


@pytest.mark.slow  # over 0.6 s: out of the fast subset (CI runs it)
def test_blend_turns_the_seam_step_into_a_ramp(tmp_path):
    a = write_dem(tmp_path / "a.tif", 0, 0, 120, 200, bias=+1.0)
    b = write_dem(tmp_path / "b.tif", 0, 100, 120, 200, bias=-1.0)
    for method in ("first", "blend"):
        assert (
            main(
                [
                    "-q",
                    "mosaic",
                    str(a),
                    str(b),
                    "-o",
                    str(tmp_path / f"{method}.tif"),
                    "--method",
                    method,
                    "--blend-length",
                    "40",
                    "--block",
                    "64",
                ]
            )
            == 0
        )
    zf, truth = on_truth(tmp_path / "first.tif")
    zb, _ = on_truth(tmp_path / "blend.tif")
    ef, eb = zf - truth, zb - truth
    assert zb.shape == (120, 300) and np.isfinite(zb).all()
    # first: a 2 m step where DEM a ends (column 200); blend: a ramp, no step above 0.2 m
    step_first = np.nanmax(np.abs(np.diff(ef, axis=1)))
    step_blend = np.nanmax(np.abs(np.diff(eb, axis=1)))
    assert step_first > 1.9
    assert step_blend < 0.2, step_blend
    # far from the overlap each DEM alone: its own bias
    assert np.allclose(eb[:, :90], 1.0, atol=1e-3) and np.allclose(eb[:, 210:], -1.0, atol=1e-3)
    with rasterio.open(tmp_path / "blend.tif") as ds:
        assert ds.count == 3 and ds.descriptions[1].startswith("count")
        count = ds.read(2)
        assert ds.crs.to_epsg() in (None, 32637) or "EGM96" in ds.crs.to_wkt()
    assert count[:, 150].min() == 2 and count[:, 50].max() == 1
    rep = json.loads((tmp_path / "blend.json").read_text())
    assert rep["n_used"] == 2 and rep["vertical"] == "geoid" and rep["memory_bound_mb"] > 0


@pytest.mark.slow
def test_blend_does_not_depend_on_the_block_size(tmp_path):
    paths = []
    for i in range(4):
        z = terrain(90, 110, 13 * i, 37 * i) + np.float32(0.5 * i)
        if i == 1:
            z[30:50, 40:70] = np.nan  # a void inside one DEM: weights fall towards it too
        paths.append(
            write_dem(tmp_path / f"d{i}.tif", 13 * i, 37 * i, 90, 110, heights=z, noise=0.2, seed=i)
        )
    outs = []
    for block in (16, 40, 512):
        plan = plan_mosaic(paths, block=block, blend_length=12)
        run_mosaic(plan, tmp_path / f"m{block}.tif")
        outs.append(read(tmp_path / f"m{block}.tif")[0])
    np.testing.assert_allclose(outs[0], outs[2], atol=2e-5, equal_nan=True)
    np.testing.assert_allclose(outs[1], outs[2], atol=2e-5, equal_nan=True)
    # and equals the blend computed on whole arrays: each DEM on the full grid, its distance to
    # its nearest void or edge inside the mosaic, weights min(d, 12)^2
    g = plan.grid
    num = np.zeros(g.shape)
    den = np.zeros(g.shape)
    for src in plan.sources:
        z = read_on_grid(src, g, 0, 0, g.height, g.width).astype(np.float64)
        v = np.isfinite(z)
        d = cv2.distanceTransform(v.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        w = np.minimum(d, 12.0) ** 2
        num += np.where(v, w * np.nan_to_num(z), 0.0)
        den += w
    with np.errstate(invalid="ignore"):
        np.testing.assert_allclose(outs[2], num / den, atol=1e-4, equal_nan=True)


def _stack(tmp_path, k=5):
    """k DEMs on the same 40 x 50 cells (noise, biases, a void each) and their stack."""
    paths, layers = [], []
    for i in range(k):
        z = (
            terrain(40, 50, 5, 5)
            + np.float32(0.3 * i)
            + np.random.default_rng(i).normal(0, 1.0, (40, 50)).astype(np.float32)
        )
        z[i * 6 : i * 6 + 5, 10:20] = np.nan
        paths.append(write_dem(tmp_path / f"s{i}.tif", 5, 5, 40, 50, heights=z))
        layers.append(z)
    return paths, np.stack(layers)


@pytest.mark.parametrize(
    "method", ["first", "last", "min", "max", "mean", "median", "count", "stddev", "nmad"]
)
@pytest.mark.slow
def test_statistics_of_the_stack_match_numpy(tmp_path, method):
    paths, st = _stack(tmp_path)
    plan = plan_mosaic(paths, method=method, block=16)
    run_mosaic(plan, tmp_path / "m.tif")
    z = read(tmp_path / "m.tif")[0]
    n = np.isfinite(st).sum(axis=0)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        first_idx = np.argmax(np.isfinite(st), axis=0)
        last_idx = st.shape[0] - 1 - np.argmax(np.isfinite(st[::-1]), axis=0)
        med = np.nanmedian(st, axis=0)
        expect = {
            "first": np.take_along_axis(st, first_idx[None], 0)[0],
            "last": np.take_along_axis(st, last_idx[None], 0)[0],
            "min": np.nanmin(st, axis=0),
            "max": np.nanmax(st, axis=0),
            "mean": np.nanmean(st, axis=0),
            "median": med,
            "count": n.astype(np.float32),
            "stddev": np.where(n >= 2, np.nanstd(st, axis=0), np.nan),
            "nmad": np.where(n >= 2, 1.4826 * np.nanmedian(np.abs(st - med), axis=0), np.nan),
        }[method]
    np.testing.assert_allclose(z, expect, atol=2e-3, equal_nan=True)
    with rasterio.open(tmp_path / "m.tif") as ds:
        assert ds.count == (1 if method in ("count", "stddev", "nmad") else 3)


def test_sigma_layers_weight_the_blend_and_propagate(tmp_path):
    a = write_dem(tmp_path / "a.tif", 0, 0, 200, 200, bias=+1.0, sigma=1.0)
    b = write_dem(tmp_path / "b.tif", 0, 0, 200, 200, bias=-1.5, sigma=2.0)
    plan = plan_mosaic([a, b], blend_length=10)
    assert plan.use_sigma
    rep = run_mosaic(plan, tmp_path / "m.tif")
    assert rep["sigma_weighting"]
    z, truth = on_truth(tmp_path / "m.tif")
    sig = read(tmp_path / "m.tif", 3)[0]
    inner = (slice(20, 180), slice(20, 180))  # both edge weights at their cap: 1/σ² alone
    expect = (1.0 / 1 * 1.0 + 1.0 / 4 * -1.5) / (1.0 + 0.25)
    np.testing.assert_allclose((z - truth)[inner], expect, atol=1e-3)
    np.testing.assert_allclose(sig[inner], np.sqrt(1.0 / (1.0 + 0.25)), atol=1e-4)
    # without σ: the plain blend (equal weights inside)
    run_mosaic(plan_mosaic([a, b], blend_length=10, use_sigma=False), tmp_path / "n.tif")
    z2, _ = on_truth(tmp_path / "n.tif")
    np.testing.assert_allclose((z2 - truth)[inner], -0.25, atol=1e-3)


def test_dems_in_another_crs_are_reprojected(tmp_path):
    a = write_dem(tmp_path / "a.tif", 0, 0, 100, 100)
    # the same terrain as a geographic DEM (EPSG:4326, ~20 m), overlapping a on its east side

    src_t = Affine(RES, 0, X0 + 60 * RES, 0, -RES, Y0)
    src = terrain(100, 100, 0, 60)
    t, w, h = calculate_default_transform(
        CRS,
        "EPSG:4326",
        100,
        100,
        *rasterio.transform.array_bounds(100, 100, src_t),
        resolution=0.0002,
    )
    dst = np.full((h, w), np.nan, np.float32)
    reproject(
        src,
        dst,
        src_transform=src_t,
        src_crs=CRS,
        dst_transform=t,
        dst_crs="EPSG:4326",
        resampling=Resampling.cubic,
        dst_nodata=np.nan,
    )
    b = tmp_path / "b_geographic.tif"
    write_geotiff(b, dst, t, "EPSG:4326", np.nan, vertical="geoid")
    assert (
        main(["-q", "mosaic", str(a), str(b), "-o", str(tmp_path / "m.tif"), "--method", "mean"])
        == 0
    )
    rep = json.loads((tmp_path / "m.json").read_text())
    assert rep["reprojected"] == [str(b)] and rep["grid"]["posting"] == RES
    z, truth = on_truth(tmp_path / "m.tif")
    assert z.shape[1] >= 155  # reaches b's eastern part
    err = (z - truth)[5:-5, 5:150]
    assert np.nanmedian(np.abs(err)) < 0.5, np.nanmedian(np.abs(err))  # resampling, not CRS errors
    assert np.isfinite(z[5:-5, 120:150]).mean() > 0.95


@pytest.mark.slow
def test_vertical_references_reconciled_or_refused(tmp_path, capsys):
    a = write_dem(tmp_path / "geoid.tif", 0, 0, 60, 80, vertical="geoid")
    # the same heights above the ellipsoid: H + N
    t = Affine(RES, 0, X0 + 40 * RES, 0, -RES, Y0)
    H = terrain(60, 80, 0, 40)
    cc, rr = np.meshgrid(np.arange(80) + 0.5, np.arange(60) + 0.5)
    lon, lat = geodesy.crs_to_lonlat(*(t @ (cc, rr)), CRS)
    N = geodesy.geoid_undulation(lon, lat)
    assert np.abs(N).min() > 5  # the conversion matters here
    write_geotiff(
        tmp_path / "ell.tif", (H + N).astype(np.float32), t, CRS, np.nan, vertical="ellipsoid"
    )
    assert (
        main(["-q", "mosaic", str(a), str(tmp_path / "ell.tif"), "-o", str(tmp_path / "m.tif")])
        == 0
    )
    z, truth = on_truth(tmp_path / "m.tif")
    assert np.nanmax(np.abs(z - truth)) < 0.02
    rep = json.loads((tmp_path / "m.json").read_text())
    assert rep["vertical_conversions"] == [
        dict(path=str(tmp_path / "ell.tif"), vertical="ellipsoid", to="geoid")
    ]
    # an ellipsoidal mosaic on request
    assert (
        main(
            [
                "-q",
                "mosaic",
                str(a),
                str(tmp_path / "ell.tif"),
                "-o",
                str(tmp_path / "e.tif"),
                "--vertical",
                "ellipsoid",
            ]
        )
        == 0
    )
    with rasterio.open(tmp_path / "e.tif") as ds:
        ze = ds.read(1)
    assert np.nanmax(np.abs(ze[:, 40:] - (H + N))) < 0.02
    # a DEM that does not say, among DEMs that do: refused in one line, nothing written
    write_geotiff(
        tmp_path / "unknown.tif", terrain(60, 80), Affine(RES, 0, X0, 0, -RES, Y0), CRS, np.nan
    )
    capsys.readouterr()
    rc = main(["mosaic", str(a), str(tmp_path / "unknown.tif"), "-o", str(tmp_path / "u.tif")])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and len(err.splitlines()) == 1 and "unknown.tif" in err and "vertical" in err
    assert not (tmp_path / "u.tif").exists() and not (tmp_path / "u.json").exists()
    assert (
        main(
            [
                "-q",
                "mosaic",
                str(a),
                str(tmp_path / "unknown.tif"),
                "-o",
                str(tmp_path / "u.tif"),
                "--dem-vertical",
                "geoid",
            ]
        )
        == 0
    )
    with pytest.raises(VerticalReferenceError):
        plan_mosaic([tmp_path / "unknown.tif"], vertical="ellipsoid")


@pytest.mark.slow
def test_dems_outside_the_extent_are_named_and_skipped(tmp_path, capsys):
    a = write_dem(tmp_path / "a.tif", 0, 0, 50, 50)
    b = write_dem(tmp_path / "b.tif", 0, 40, 50, 50)
    far = write_dem(tmp_path / "far.tif", 400, 400, 30, 30)
    bounds = [X0, Y0 - 50 * RES, X0 + 90 * RES, Y0]
    rc = main(
        [
            "mosaic",
            str(a),
            str(b),
            str(far),
            "-o",
            str(tmp_path / "m.tif"),
            "--bounds",
            *map(str, bounds),
        ]
    )
    out = capsys.readouterr().out
    assert rc == 0 and "skipped" in out and "far.tif" in out
    rep = json.loads((tmp_path / "m.json").read_text())
    assert rep["n_used"] == 2 and [s["path"] for s in rep["skipped"]] == [str(far)]
    # without bounds it is kept, and named as overlapping no other DEM
    plan = plan_mosaic([a, b, far])
    assert plan.report["islands"] == [str(far)] and plan.report["n_used"] == 3


@pytest.mark.parametrize(
    "which, method, words",
    [
        (["void"], "blend", "void.tif: no valid height over the mosaic's extent"),
        (["void", "void2"], "count", "void.tif, .*void2.tif: no valid height"),
        (["a"], "nmad", "a.tif: no cell of the mosaic has valid heights from two DEMs"),
    ],
)
def test_a_mosaic_without_a_valid_cell_is_refused(tmp_path, capsys, which, method, words):
    """All-void DEMs (or one DEM with nmad) made an all-void mosaic, reported as written with
    "0.0 % valid" and exit status 0."""
    void = np.full((8, 8), np.nan, np.float32)
    write_dem(tmp_path / "a.tif", 0, 0, 8, 8)
    write_dem(tmp_path / "void.tif", 0, 0, 8, 8, heights=void)
    write_dem(tmp_path / "void2.tif", 4, 4, 8, 8, heights=void)
    out = tmp_path / "m.tif"
    argv = ["mosaic", *(str(tmp_path / f"{w}.tif") for w in which), "-o", str(out)]
    capsys.readouterr()
    assert main([*argv, "--method", method]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert re.search(words, err), err
    assert not out.exists() and not (tmp_path / "m.json").exists()


def test_a_mosaic_keeps_its_dems_geoid_and_says_when_geoids_are_mixed(tmp_path, caplog):
    """Tiles of heights above EGM2008 (the Copernicus DEM's geoid) made a mosaic labelled
    EGM96 (EPSG:5773 in its CRS, "height above the EGM96 geoid"); EGM2008 and EGM96 tiles were
    blended without a word (their seams carry the separation of the two geoids)."""
    egm08 = PCRS("EPSG:3855")
    for name, r0 in (("a", 0), ("b", 40)):
        z, t = terrain(50, 50, r0, 0), Affine(RES, 0, X0, 0, -RES, Y0 - r0 * RES)
        write_geotiff(tmp_path / f"{name}.tif", z, t, CRS, np.nan, vertical="geoid")
        write_geotiff(  # the same above EGM2008
            tmp_path / f"{name}08.tif",
            z,
            t,
            PCRS.from_user_input(CompoundCRS("x", [PCRS(CRS), egm08])),
            np.nan,
            vertical="geoid",
        )
    caplog.clear()
    rep = run_mosaic(plan_mosaic([tmp_path / "a08.tif", tmp_path / "b08.tif"]), tmp_path / "m.tif")
    assert rep["geoid"] == "EGM2008 height" and "separation" not in caplog.text
    with rasterio.open(tmp_path / "m.tif") as ds:
        assert "EGM2008" in ds.crs.to_wkt() and "EGM96" not in ds.crs.to_wkt()
        assert ds.descriptions[0] == "height above the EGM2008 geoid"
    back = _DEM.from_file(tmp_path / "m.tif")
    assert back.vertical == "geoid" and back.geoid_crs.name == "EGM2008 height"
    # EGM2008 and EGM96 tiles: mosaicked, and said
    rep = run_mosaic(plan_mosaic([tmp_path / "a08.tif", tmp_path / "b.tif"]), tmp_path / "x.tif")
    assert "EGM2008 height and EGM96 height" in caplog.text and "a08.tif" in caplog.text
    # EGM96 tiles alone: EGM96, nothing said
    caplog.clear()
    rep = run_mosaic(plan_mosaic([tmp_path / "a.tif", tmp_path / "b.tif"]), tmp_path / "e.tif")
    assert rep["geoid"] == "EGM96 height" and not caplog.text
    with rasterio.open(tmp_path / "e.tif") as ds:
        assert ds.descriptions[0] == "height above the EGM96 geoid"


def test_an_all_void_dem_beside_a_valid_one_is_not_counted_as_used(tmp_path, capsys):
    """A DEM whose footprint meets the mosaic but holds no valid height was reported among
    the DEMs used ("2 of 2 DEMs")."""
    write_dem(tmp_path / "a.tif", 0, 0, 8, 8)
    write_dem(tmp_path / "void.tif", 4, 4, 8, 8, heights=np.full((8, 8), np.nan, np.float32))
    out = tmp_path / "m.tif"
    argv = ["mosaic", str(tmp_path / "a.tif"), str(tmp_path / "void.tif"), "-o", str(out)]
    assert main(argv) == 0
    said = capsys.readouterr().out
    assert "1 of 2 DEMs" in said and "skipped" in said and "void.tif" in said, said
    rep = json.loads((tmp_path / "m.json").read_text())
    assert rep["n_used"] == 1
    assert rep["skipped"] == [
        dict(path=str(tmp_path / "void.tif"), reason="no valid height over the mosaic's extent")
    ]


@pytest.mark.slow
def test_bad_inputs_are_one_line_errors_and_write_nothing(tmp_path, capsys):
    a = write_dem(tmp_path / "a.tif", 0, 0, 50, 50)
    garbage = tmp_path / "garbage.tif"
    garbage.write_bytes(b"not a tiff at all")
    nocrs = tmp_path / "nocrs.tif"
    with rasterio.open(
        nocrs, "w", driver="GTiff", width=10, height=10, count=1, dtype="float32"
    ) as ds:
        ds.write(np.ones((1, 10, 10), np.float32))
    nogt = tmp_path / "nogt.tif"  # a CRS but no geotransform ("not north-up" before)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(
            nogt,
            "w",
            driver="GTiff",
            width=10,
            height=10,
            count=1,
            dtype="float32",
            crs="EPSG:32637",
        ) as ds:
            ds.write(np.ones((1, 10, 10), np.float32))
    cases = [
        ([str(a), str(garbage)], "garbage.tif"),
        ([str(a), str(nocrs)], "no CRS"),
        ([str(a), str(nogt)], "nogt.tif: the DEM has no geotransform"),
        ([str(a), str(tmp_path / "missing.tif")], "missing.tif"),
        ([str(a), str(a)], "given twice"),
        ([str(a), "--coregister"], "--ref"),
        # before: taken and ignored without --coregister, whatever it said
        ([str(a), "--coreg-chain", "abc"], "--coreg-chain is used with --coregister"),
        ([str(a), "--coreg-chain", "nuth_kaab"], "--coreg-chain is used with --coregister"),
        ([str(a), "--method", "blend", "--block", "4"], "--block"),
    ]
    for args, words in cases:
        capsys.readouterr()
        rc = main(["mosaic", *args, "-o", str(tmp_path / "m.tif")])
        err = capsys.readouterr().err.strip()
        assert rc == 1, args
        assert len(err.splitlines()) == 1 and words in err and "Traceback" not in err, err
        assert not (tmp_path / "m.tif").exists() and not (tmp_path / "m.json").exists()
    # the output is an input, or exists
    assert main(["mosaic", str(a), "-o", str(a)]) == 1
    assert main(["-q", "mosaic", str(a), "-o", str(tmp_path / "m.tif")]) == 0
    capsys.readouterr()
    assert main(["mosaic", str(a), "-o", str(tmp_path / "m.tif")]) == 1
    assert "--overwrite" in capsys.readouterr().err
    assert main(["-q", "mosaic", str(a), "-o", str(tmp_path / "m.tif"), "--overwrite"]) == 0
    assert not list(tmp_path.glob(".*part")) and not list(tmp_path.glob(".*blocks.tif"))


@pytest.mark.slow
def test_coregistration_to_a_reference_first(tmp_path):
    ref = write_dem(tmp_path / "ref.tif", 0, 0, 160, 160)
    # a DEM displaced 45 m east and 30 m north, 4 m high: its features sit east/north of the truth's
    t = Affine(RES, 0, X0 + 20 * RES + 45.0, 0, -RES, Y0 - 20 * RES + 30.0)
    z = terrain(120, 120, 20, 20) + np.float32(4.0)
    write_geotiff(tmp_path / "shifted.tif", z, t, CRS, np.nan, vertical="geoid")
    far = write_dem(tmp_path / "far.tif", 600, 600, 40, 40)
    args = [
        "-q",
        "mosaic",
        str(tmp_path / "shifted.tif"),
        str(far),
        "-o",
        str(tmp_path / "m.tif"),
        "--ref",
        str(ref),
        "--coregister",
    ]
    assert main(args) == 0
    rep = json.loads((tmp_path / "m.json").read_text())
    c = rep["coregistration"][str(tmp_path / "shifted.tif")]
    assert abs(c["dx"] - 45.0) < 3 and abs(c["dy"] - 30.0) < 3 and abs(c["dz"] - 4.0) < 0.5, c
    assert [s["path"] for s in rep["skipped"]] == [str(far)]
    zm, truth = on_truth(tmp_path / "m.tif")
    err = (zm - truth)[5:-5, 5:-5]
    assert np.nanmedian(np.abs(err)) < 0.5
    # an unknown chain is a one-line error
    assert main(args[1:] + ["--coreg-chain", "bias+tilt", "--overwrite"]) == 1


@pytest.mark.slow
def test_coregistration_log_line_says_grid_metres(tmp_path, caplog):
    """The INFO line of a co-registered DEM words the shift as the reports do (one rule,
    post.shift_units.shift_phrase/shift_units): along the grid's x/y axes, grid metres on a
    projected grid with the scale factor, as the JSON record's horizontal_unit says."""
    ref = write_dem(tmp_path / "ref.tif", 0, 0, 160, 160)
    t = Affine(RES, 0, X0 + 20 * RES + 45.0, 0, -RES, Y0 - 20 * RES + 30.0)
    dem = tmp_path / "shifted.tif"
    write_geotiff(dem, terrain(120, 120, 20, 20), t, CRS, np.nan, vertical="geoid")
    args = ["mosaic", str(dem), "-o", str(tmp_path / "m.tif"), "--ref", str(ref), "--coregister"]
    with caplog.at_level(logging.INFO, logger="stereodem.post.mosaic"):
        assert main(args) == 0
    c = json.loads((tmp_path / "m.json").read_text())["coregistration"][
        str(tmp_path / "shifted.tif")
    ]
    assert c["horizontal_unit"].startswith("grid metres")
    lines = [r.getMessage() for r in caplog.records if "co-registered" in r.getMessage()]
    assert len(lines) == 1, lines
    assert f"dx = {c['dx']:+.2f} m along x (grid east)" in lines[0]
    assert f"dy = {c['dy']:+.2f} m along y (grid north)" in lines[0]
    k = c["scale_factor"][1]
    assert 0.9996 < k < 1.0004  # UTM: grid metres within 0.04 % of ground metres, said
    assert "dx, dy are grid metres" in lines[0] and f"scale factor k = {k:.6g}" in lines[0]


@pytest.mark.slow
def test_coregistration_chain_of_the_coreg_module(tmp_path, capsys):
    """--coreg-chain goes through stereodem.post.coreg.parse_chain: shift + offset steps are
    applied (nuth_kaab then vshift, summed), a surface step is refused in one line."""
    ref = write_dem(tmp_path / "ref.tif", 0, 0, 160, 160)
    t = Affine(RES, 0, X0 + 20 * RES - 35.0, 0, -RES, Y0 - 20 * RES + 25.0)
    z = terrain(120, 120, 20, 20) - np.float32(6.0)
    write_geotiff(tmp_path / "shifted.tif", z, t, CRS, np.nan, vertical="geoid")
    args = [
        "-q",
        "mosaic",
        str(tmp_path / "shifted.tif"),
        "-o",
        str(tmp_path / "m.tif"),
        "--ref",
        str(ref),
        "--coregister",
        "--coreg-chain",
        "nuth_kaab, vshift",
    ]
    assert main(args) == 0
    c = json.loads((tmp_path / "m.json").read_text())["coregistration"][
        str(tmp_path / "shifted.tif")
    ]
    assert abs(c["dx"] + 35.0) < 3 and abs(c["dy"] - 25.0) < 3 and abs(c["dz"] + 6.0) < 0.5, c
    assert c["method"] == "nuth_kaab + vshift" and [s["step"] for s in c["steps"]] == [
        "nuth_kaab",
        "vshift",
    ]
    # the vshift step found what nuth_kaab left: their sum is the offset applied
    nk, vs = (s["parameters"]["dz"]["value"] for s in c["steps"])
    assert c["dz"] == pytest.approx(nk + vs) and abs(vs) < 0.5
    zm, truth = on_truth(tmp_path / "m.tif")
    assert np.nanmedian(np.abs((zm - truth)[5:-5, 5:-5])) < 0.5
    # the Python hook gives the same kind of correction

    corr = fitter("nuth_kaab,vshift")(_DEM.from_file(ref), _DEM.from_file(tmp_path / "shifted.tif"))
    assert isinstance(corr, DEMCorrection) and abs(corr.dx + 35.0) < 3
    # a step that changes the surface cannot be applied by the mosaic: one line, nothing written
    capsys.readouterr()
    out = tmp_path / "m2.tif"
    assert main(args[1:4] + [str(out)] + args[5:-1] + ["nuth_kaab,deramp:1"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "deramp" in err and "stereodem coregister" in err, err
    assert not out.exists()


@pytest.mark.slow
def test_dask_gives_the_serial_mosaic(tmp_path):
    pytest.importorskip("dask.distributed")
    paths = [
        write_dem(tmp_path / f"d{i}.tif", 20 * i, 30 * i, 70, 90, bias=0.4 * i) for i in range(3)
    ]
    plan = plan_mosaic(paths, block=32, blend_length=8)
    run_mosaic(plan, tmp_path / "serial.tif")
    rep = run_mosaic(plan, tmp_path / "dask.tif", dask="threads", workers=2)
    assert rep["dask"] == "threads"
    serial, parallel = read(tmp_path / "serial.tif")[0], read(tmp_path / "dask.tif")[0]
    if np.lib.NumpyVersion(np.__version__) >= "2.0.0" and int(cv2.__version__.split(".")[0]) >= 5:
        np.testing.assert_array_equal(serial, parallel)
    else:  # measured on the declared minimum versions (numpy 1.24, OpenCV 4.8): 2 of 16,500
        np.testing.assert_array_equal(np.isnan(serial), np.isnan(parallel))  # cells 1 ulp apart
        np.testing.assert_array_max_ulp(
            serial[~np.isnan(serial)], parallel[~np.isnan(parallel)], maxulp=1
        )


@pytest.mark.slow
def test_dask_a_dem_that_does_not_read_is_the_one_line_error(tmp_path, capsys):
    """A DEM damaged in a block the checks do not probe fails on a Dask worker; its error
    reaches the command as itself: one line naming it, exit status 1, nothing written (it came
    back as a bare ``Exception`` holding its repr, GDAL's error in its chain not unpickling,
    and the command printed a traceback)."""
    pytest.importorskip("dask.distributed")
    from helpers.damage import damage_a_middle_block

    d = _DEM.bundled()
    _DEM(d.heights[:300, :600].copy(), d.transform, d.crs, d.vertical).write(tmp_path / "ok.tif")
    assert damage_a_middle_block(tmp_path / "ok.tif", tmp_path / "bad.tif")
    capsys.readouterr()
    out = tmp_path / "m.tif"
    args = ["mosaic", str(tmp_path / "ok.tif"), str(tmp_path / "bad.tif"), "-o", str(out)]
    rc = main([*args, "--dask", "threads", "--workers", "2"])
    err = [ln for ln in capsys.readouterr().err.splitlines() if "error" in ln.lower()]
    assert rc == 1 and len(err) == 1, err
    assert (
        err[0].startswith("stereodem mosaic: error: ") and "bad.tif: cannot read the DEM" in err[0]
    )
    assert not out.exists() and not out.with_suffix(".json").exists()


@pytest.mark.slow  # a subprocess with a Dask cluster (~4 s)
@pytest.mark.parametrize("cluster", ["threads", "local"])
def test_dask_a_failed_block_prints_nothing_but_the_error(tmp_path, cluster):
    """The command's whole stderr is its one error line: the cluster was closed under the
    blocks still running, and every worker logged "WARNING distributed.worker.state_machine:
    Async instruction for <Task cancelled ...> ended with CancelledError" above it (`--dask
    local` from its worker processes, `--dask threads` in the command's). The blocks under
    way now end before the cluster closes."""
    pytest.importorskip("dask.distributed")
    from helpers.damage import damage_a_middle_block

    d = _DEM.bundled()
    _DEM(d.heights[:300, :600].copy(), d.transform, d.crs, d.vertical).write(tmp_path / "ok.tif")
    assert damage_a_middle_block(tmp_path / "ok.tif", tmp_path / "bad.tif")
    args = ["mosaic", str(tmp_path / "ok.tif"), str(tmp_path / "bad.tif"), "-o"]
    r = subprocess.run(
        [sys.executable, "-m", "stereodem.cli", *args, str(tmp_path / "m.tif")]
        + ["--dask", cluster, "--workers", "2", "--block", "64"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 1
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "bad.tif: cannot read the DEM" in lines[0], r.stderr


def test_dask_local_cluster_is_workers_processes_sharing_the_cores(tmp_path, monkeypatch):
    """``--dask local``: ``--workers`` processes (default all cores, as its help says; it
    was 1), each pinned to its share of the cores (a Dask worker plugin), not to all of them."""
    distributed = pytest.importorskip("dask.distributed")

    seen = {}

    class Stop(Exception):
        pass

    class FakeCluster:
        def __init__(self, **kw):
            seen["cluster"] = kw

        def close(self):
            pass

    class FakeClient:
        def __init__(self, cluster):
            pass

        def register_plugin(self, plugin, name):
            seen["plugin_threads"] = plugin.threads

        def nthreads(self):
            raise Stop

        def close(self):
            pass

    monkeypatch.setattr(distributed, "LocalCluster", FakeCluster)
    monkeypatch.setattr(distributed, "Client", FakeClient)
    monkeypatch.setattr(threads, "cores", lambda: 4)
    paths = [write_dem(tmp_path / f"d{i}.tif", 20 * i, 30 * i, 40, 50) for i in range(2)]
    plan = plan_mosaic(paths, block=32)
    for workers, n, per_worker in ((None, 4, 1), (2, 2, 2), (8, 8, 1)):
        seen.clear()
        with pytest.raises(Stop):
            run_mosaic(plan, tmp_path / "m.tif", dask="local", workers=workers, overwrite=True)
        assert seen["cluster"]["n_workers"] == n and seen["cluster"]["threads_per_worker"] == 1
        assert seen["plugin_threads"] == per_worker


def _traced_peak(tmp_path, n_side, method):
    """Python-heap peak (numpy arrays included) of a mosaic of n_side x n_side DEMs of 120²
    cells."""
    paths = [
        write_dem(
            tmp_path / f"{method}{n_side}_{i}_{j}.tif",
            100 * i,
            100 * j,
            120,
            120,
            bias=0.1 * (i + j),
        )
        for i in range(n_side)
        for j in range(n_side)
    ]
    plan = plan_mosaic(paths, method=method, block=64, blend_length=16)
    tracemalloc.start()
    run_mosaic(plan, tmp_path / f"{method}{n_side}.tif")
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return peak, plan


@pytest.mark.parametrize("method", ["blend", "median"])
@pytest.mark.slow
def test_memory_depends_on_the_block_not_on_the_mosaic(tmp_path, method):
    small, _ = _traced_peak(tmp_path, 2, method)  # 220² cells
    large, plan_l = _traced_peak(tmp_path, 4, method)  # 420² cells: 3.6x the area
    gdal = (32 + 32 + 8) * 2**20  # GDAL caches are not traced
    assert large < memory_bound(plan_l) - gdal, (large, memory_bound(plan_l) - gdal)
    assert large < 1.3 * small, (small, large)
    # a full-array mosaic would hold the grid: 420² float64 sums alone are 1.4 MB per layer
    assert large < 8 * 420 * 420 * 3


def test_a_failure_half_way_leaves_nothing(tmp_path, monkeypatch):
    paths = [write_dem(tmp_path / f"d{i}.tif", 0, 60 * i, 80, 100) for i in range(3)]
    plan = plan_mosaic(paths, block=32)
    real, calls = pm.read_on_grid, []

    def flaky(*a, **k):
        calls.append(1)
        if len(calls) > 5:
            raise pm.DEMError("d1.tif: cannot read the DEM (simulated I/O error)")
        return real(*a, **k)

    monkeypatch.setattr(pm, "read_on_grid", flaky)
    with pytest.raises(pm.DEMError):
        run_mosaic(plan, tmp_path / "m.tif")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d0.tif", "d1.tif", "d2.tif"]


@pytest.mark.slow
def test_scaled_and_feet_dems_are_mosaicked_in_metres(tmp_path):
    """The mosaic read each DEM's stored values as they were: an int16 DEM stored as
    decimetres (GDAL scale 0.1) came out ten times too high (11 473 m for 1147 m of terrain)
    and one in feet 3.28 times; so did a reference cropped for --coregister."""
    a = write_dem(tmp_path / "a.tif", 0, 0, 40, 40)
    t = Affine(RES, 0, X0 + 20 * RES, 0, -RES, Y0)
    dm = np.round(terrain(40, 40, 0, 20) * 10).astype(np.int16)
    kw = dict(driver="GTiff", width=40, height=40, count=1, crs=CRS, transform=t)
    with rasterio.open(tmp_path / "dm.tif", "w", dtype="int16", nodata=-32768, **kw) as ds:
        ds.write(dm, 1)
        ds.scales = (0.1,)
    ft = terrain(40, 40, 20, 0) / np.float32(0.3048)
    write_geotiff(tmp_path / "ft.tif", ft, Affine(RES, 0, X0, 0, -RES, Y0 - 20 * RES), CRS, np.nan)
    with rasterio.open(tmp_path / "ft.tif", "r+", IGNORE_COG_LAYOUT_BREAK="YES") as ds:
        ds.units = ("ft",)
    out = tmp_path / "m.tif"
    args = ["-q", "mosaic", str(a), str(tmp_path / "dm.tif"), str(tmp_path / "ft.tif")]
    assert main(args + ["-o", str(out), "--method", "max", "--dem-vertical", "geoid"]) == 0
    z, truth = on_truth(out)
    assert z.shape == (60, 60) and np.isfinite(z).mean() > 0.8
    assert np.nanmax(np.abs(z - truth)) < 0.06  # decimetre rounding, float32 feet
    ref = pm.crop_reference(tmp_path / "dm.tif", (X0 + 600, Y0 - 1200, X0 + 1800, Y0), CRS)
    assert np.nanmax(np.abs(ref.heights - terrain(40, 40, 0, 20))) < 0.06


def test_undeclared_nodata_and_implausible_heights_are_no_data_once_warned(tmp_path, caplog):
    """The mosaic did not apply DEM.from_file's reading rules: in a DEM with no nodata value
    declared, -9999 (and a 1e30 fill) were mosaicked as heights (the blend of a -9999 hole with
    its neighbour a ramp down to -9999 m; a warped DEM's -9999 smeared into the cells around
    it), and a reference cropped for --coregister kept them as well. They are no-data, with
    one warning per file (not one per block)."""
    kw = dict(driver="GTiff", count=1, crs=CRS, dtype="float32")  # no nodata value
    a = terrain(40, 40)
    a[10:14, 10:14] = -9999.0
    a[30, 5] = 1e30
    with rasterio.open(
        tmp_path / "a.tif",
        "w",
        width=40,
        height=40,
        transform=Affine(RES, 0, X0, 0, -RES, Y0),
        **kw,
    ) as ds:
        ds.write(a, 1)
    # b: half a cell off the lattice (read through GDAL's warper), a -9999 hole over a's own
    t = Affine(RES, 0, X0 + 20.5 * RES, 0, -RES, Y0 - 0.5 * RES)
    xx, yy = t @ np.meshgrid(np.arange(40) + 0.5, np.arange(40) + 0.5)
    b = (1500 + 300 * np.sin(xx / 2500.0) * np.cos(yy / 1900.0) + 0.01 * (xx - X0)).astype(
        np.float32
    )
    b[20:26, 20:26] = -9999.0
    with rasterio.open(tmp_path / "b.tif", "w", width=40, height=40, transform=t, **kw) as ds:
        ds.write(b, 1)
    plan = plan_mosaic([tmp_path / "a.tif", tmp_path / "b.tif"], block=16, dem_vertical="geoid")
    with caplog.at_level("WARNING", logger="stereodem"):
        run_mosaic(plan, tmp_path / "m.tif")
    z, truth = on_truth(tmp_path / "m.tif")
    assert np.nanmin(z) > 1000 and np.nanmax(z) < 2000  # terrain 1200..1800 m: no fill value
    assert np.isnan(z[10:14, 10:14]).all() and np.isnan(z[30, 5])  # a alone there
    assert np.nanmax(np.abs(z - truth)) < 5.0  # (bilinear on b: ~2 m; a smeared -9999: 100s)
    said = [r.getMessage() for r in caplog.records if "read as no-data" in r.getMessage()]
    assert len(said) == 2, said  # once per file, not per block (12 blocks)
    (sa,) = [m for m in said if "a.tif" in m]
    assert "a.tif: 17 cell(s)" in sa and "-9999, 1e+30" in sa
    assert any("b.tif" in m and "-9999 without a nodata value" in m for m in said)
    # the reference of --coregister, cropped: the same rules
    caplog.clear()
    with caplog.at_level("WARNING", logger="stereodem"):
        ref = pm.crop_reference(tmp_path / "a.tif", (X0, Y0 - 40 * RES, X0 + 40 * RES, Y0), CRS)
    assert np.isnan(ref.heights).sum() == 17 and np.nanmin(ref.heights) > 1000
    assert "a.tif: 17 cell(s)" in caplog.text


@pytest.mark.slow
def test_dems_either_side_of_the_antimeridian_are_mosaicked_side_by_side(tmp_path):
    """Geographic tiles at 179.9..180 E and -180..-179.9 E made a mosaic 360 degrees wide
    (36 000 x 10 cells, 0.1 % valid), and a projected DEM crossing 180 (its footprint from
    179.98 to -179.98) was skipped as outside a geographic mosaic."""

    def height(lon, lat):  # smooth across the antimeridian
        return 1000 + 20 * np.sin(np.radians((lon - 180.0) % 360.0) * 50) + 100 * (lat - 65)

    def tile(name, west):
        t = Affine(0.01, 0, west, 0, -0.01, 65.1)
        lon, lat = t @ np.meshgrid(np.arange(10) + 0.5, np.arange(10) + 0.5)
        z = height(lon, lat).astype(np.float32)
        return write_geotiff(tmp_path / name, z, t, "EPSG:4326", np.nan, vertical="geoid")

    east, west = tile("e.tif", 179.9), tile("w.tif", -180.0)
    # UTM zone 1N across 180 E at 65.05 N
    x0, y0 = geodesy.lonlat_to_crs(180.0, 65.05, "EPSG:32601")
    t = Affine(200, 0, float(x0) - 2000, 0, -200, float(y0) + 2000)
    x, y = t @ np.meshgrid(np.arange(20) + 0.5, np.arange(20) + 0.5)
    z = height(*geodesy.crs_to_lonlat(x, y, "EPSG:32601")).astype(np.float32)
    write_geotiff(tmp_path / "utm.tif", z, t, "EPSG:32601", np.nan, vertical="geoid")
    for first, second, extent in ((east, west, (179.9, 180.1)), (west, east, (-180.1, -179.9))):
        out = tmp_path / f"m_{first.stem}.tif"
        args = ["-q", "mosaic", str(first), str(second), str(tmp_path / "utm.tif")]
        assert main(args + ["-o", str(out), "--method", "mean"]) == 0
        rep = json.loads(out.with_suffix(".json").read_text())
        assert rep["n_used"] == 3 and not rep["skipped"]
        with rasterio.open(out) as ds:
            zm, tm = ds.read(1), ds.transform
        assert zm.shape == (10, 20) and (tm.c, tm.c + 20 * tm.a) == pytest.approx(extent)
        lon, lat = tm @ np.meshgrid(np.arange(20) + 0.5, np.arange(10) + 0.5)
        assert np.all(np.abs(zm - height(lon, lat)) < 0.5)


def test_lon_lat_dems_keep_their_unequal_postings(tmp_path):
    """Lon/lat DEMs at high latitude have more degrees of longitude than of latitude per cell
    (the Copernicus DEM above 70 N: 3" by 1"; here 0.003 by 0.001 degrees at 78 N): the mosaic
    took the x posting for both axes, so two such tiles (78 N, either side of 180) made a
    mosaic of a third of the rows, every cell resampled; it is the first DEM's lattice, the
    tiles' cells copied."""

    def height(lon, lat):
        return 500 + 30 * np.sin(np.radians((lon - 180.0) % 360.0) * 80) + 200 * (lat - 78)

    def tile(name, west, cols):
        t = Affine(0.003, 0, west, 0, -0.001, 78.03)
        lon, lat = t @ np.meshgrid(np.arange(cols) + 0.5, np.arange(30) + 0.5)
        z = height(lon, lat).astype(np.float32)
        return write_geotiff(tmp_path / name, z, t, "EPSG:4326", np.nan, vertical="geoid")

    east, west = tile("e.tif", 179.94, 22), tile("w.tif", -180.0, 20)  # 2 columns of overlap
    out = tmp_path / "m.tif"
    assert main(["-q", "mosaic", str(east), str(west), "-o", str(out)]) == 0
    with rasterio.open(out) as ds:
        zm, tm = ds.read(1), ds.transform
    assert (tm.a, -tm.e) == pytest.approx((0.003, 0.001))
    assert zm.shape == (30, 40) and (tm.c, tm.f) == pytest.approx((179.94, 78.03))
    lon, lat = tm @ np.meshgrid(np.arange(40) + 0.5, np.arange(30) + 0.5)
    assert np.abs(zm - height(lon, lat)).max() < 1e-3


def test_a_reference_across_the_antimeridian_is_cropped_for_coregister(tmp_path):
    """mosaic --coregister of a UTM zone 1 DEM across 180 E against a lon/lat reference at
    179.98..180.02 E ended in a traceback (rasterio's WindowError): the DEM's footprint in
    the reference's CRS came back as west 179.98 > east -179.98."""
    x0, y0 = geodesy.lonlat_to_crs(180.0, 60.0, "EPSG:32601")
    b = (float(x0) - 500, float(y0) - 500, float(x0) + 500, float(y0) + 500)
    t = Affine(0.001, 0, 179.98, 0, -0.001, 60.02)
    write_geotiff(tmp_path / "r.tif", np.full((40, 40), 9.0, np.float32), t, "EPSG:4326", np.nan)
    ref = pm.crop_reference(tmp_path / "r.tif", b, "EPSG:32601", margin_cells=0)
    assert ref.transform.c == pytest.approx(179.99, abs=0.002) and ref.shape[1] < 30


@pytest.mark.slow
def test_result_line_gives_the_posting_with_its_unit(tmp_path, capsys):
    """`stereodem mosaic` (and dem, uncertainty) say "cells at 30 m", not "cells at 30":
    a bare number did not say metres or degrees (a lon/lat grid's 0.000833)."""
    a = write_dem(tmp_path / "a.tif", 0, 0, 40, 40)
    assert main(["mosaic", str(a), "-o", str(tmp_path / "m.tif")]) == 0
    assert f"cells at {RES:g} m," in capsys.readouterr().out
    t = Affine(30.0, 0, 500000, 0, -30.0, 4e6)
    assert posting(MapGrid(t, 4, 4, PCRS("EPSG:32637"))) == "30 m"
    assert posting(MapGrid(t, 4, 4, PCRS("EPSG:32637+5773"))) == "30 m"  # compound
    g = MapGrid(Affine(0.000833, 0, 40, 0, -0.000833, 39), 4, 4, PCRS("EPSG:4326"))
    assert posting(g) == "0.000833°"
    assert posting(MapGrid(t, 4, 4, PCRS("EPSG:2227"))) == "30 US survey foot"


def test_plan_mosaic_of_dem_objects_or_one_path_is_clear(tmp_path):
    """``plan_mosaic([dem_a, dem_b])`` with DEM objects raised pathlib's TypeError from
    inside; one path (not in a list) was taken character by character."""
    a = write_dem(tmp_path / "a.tif", 0, 0, 40, 40)
    with pytest.raises(InputError, match=r"reads its DEMs from files.*got a DEM"):
        plan_mosaic([a, _DEM.from_file(a)])
    assert plan_mosaic(a).grid.shape == plan_mosaic([a]).grid.shape


#: tolerance (m) of a warp's values where GDAL's chunks differ: its approximate transformer
#: puts a cell within TRANSFORM_TOLERANCE_PX (1e-3 source pixel) of exact, and _polar_dem's
#: heights step by at most 19 m between neighbouring cells
CHUNKS_ATOL_M = 0.02


def _polar_dem(tmp_path, rows=330, cols=340):
    """A textured DEM (relief, ripples of ~300 m and 2 m noise: smoothing shows) on a 10 m UTM
    33N lattice at 78 N, whose 30 m EPSG:3413 mosaic grid (151 x 150 cells, more than the
    warped VRT's 128-row blocks) is turned ~58 degrees against it."""
    rng = np.random.default_rng(3)
    y, x = np.mgrid[0:rows, 0:cols] / max(rows, cols)
    z = 1000 + 300 * np.sin(6 * x) * np.cos(4 * y) + 50 * np.sin(40 * x + 3 * y)
    z = (z + rng.normal(0, 2, z.shape)).astype(np.float32)
    z[150:162, 60:70] = np.nan  # a void
    t = Affine(10.0, 0, 500000.0, 0, -10.0, 8700000.0)
    path = write_geotiff(tmp_path / "utm.tif", z, t, "EPSG:32633", np.nan, vertical="geoid")
    return path, z, t


def _tiled_read(src, g, size):
    """``read_on_grid`` of the whole grid in windows of ``size`` cells."""
    out = np.full(g.shape, np.nan, np.float32)
    for r0 in range(0, g.height, size):
        for c0 in range(0, g.width, size):
            rows, cols = min(size, g.height - r0), min(size, g.width - c0)
            out[r0 : r0 + rows, c0 : c0 + cols] = read_on_grid(src, g, r0, c0, rows, cols)
    return out


def _whole_grid_warp(z, st, g):
    """The DEM's bilinear warp of the whole grid in one piece with one kernel scale."""
    scale = warp.kernel_scales(st, "EPSG:32633", g.transform, g.crs, g.shape)
    assert 0.3 < scale[0] < 0.35 and 0.3 < scale[1] < 0.35  # 3 times coarser, a little more
    return warp.to_grid(z, st, "EPSG:32633", g.transform, g.crs, g.shape, kernel_scale=scale)


def test_a_dem_in_another_crs_is_read_alike_in_any_window(tmp_path):
    """GDAL's warper widens the bilinear kernel by a scale it computes per chunk (the chunk's
    size over its source window's bounding box): a window read from a grid turned against
    the DEM (UTM 33N onto EPSG:3413) is warped in the VRT's 128-row blocks, whose tall
    source windows widen it more than a read of the whole grid in one piece (here 7.5 m at
    most, half the cells off by over 1 cm, 10 m cells onto 30 m). With one kernel scale for
    the grid (:func:`stereodem.core.warp.kernel_scales`) windows of any size give the whole
    grid's read, and that is ``core.warp.to_grid``'s warp of the whole grid with that scale
    (bit for bit here; the tolerance is :data:`CHUNKS_ATOL_M`)."""
    path, z, st = _polar_dem(tmp_path)
    plan = plan_mosaic([path], crs="EPSG:3413", res=30)
    g, src = plan.grid, plan.sources[0]
    assert plan.report["reprojected"] == [str(path)] and g.height > 128
    whole = read_on_grid(src, g, 0, 0, g.height, g.width)
    assert np.isfinite(whole).mean() > 0.4
    for size in (40, 80):
        tiled = _tiled_read(src, g, size)
        np.testing.assert_allclose(
            tiled, whole, rtol=0, atol=CHUNKS_ATOL_M, equal_nan=True, err_msg=size
        )
    exact = _whole_grid_warp(z, st, g)
    np.testing.assert_allclose(whole, exact, rtol=0, atol=CHUNKS_ATOL_M, equal_nan=True)


@pytest.mark.slow
def test_a_mosaic_in_another_crs_does_not_depend_on_the_block_size(tmp_path):
    """The blend of a DEM warped onto a turned grid in blocks of 16 cells (halo included) is
    that of one 512-cell block, and both are the DEM's warp of the whole grid with one kernel
    scale. On a mosaic extent 1000 km wider (south and east) the DEM is read with the same
    values: its kernel scale is taken at its footprint (that at the grid's centre, 72 N
    against 78 N, differs by 1.4 %: 0.21 m at most, 0.02 m median)."""
    path, z, st = _polar_dem(tmp_path)
    outs = []
    for block in (16, 512):
        plan = plan_mosaic([path], crs="EPSG:3413", res=30, block=block, blend_length=8)
        run_mosaic(plan, tmp_path / f"m{block}.tif")
        outs.append(read(tmp_path / f"m{block}.tif")[0])
    np.testing.assert_allclose(outs[0], outs[1], rtol=0, atol=CHUNKS_ATOL_M, equal_nan=True)
    g = plan.grid
    exact = _whole_grid_warp(z, st, g)
    np.testing.assert_allclose(outs[1], exact, rtol=0, atol=CHUNKS_ATOL_M, equal_nan=True)
    w, s, e, n = g.bounds
    wide = plan_mosaic([path], crs="EPSG:3413", res=30, bounds=(w, s - 1e6, e + 1e6, n))
    gw = wide.grid
    assert gw.transform.c == g.transform.c and gw.transform.f == g.transform.f  # same corner
    there = read_on_grid(wide.sources[0], gw, 0, 0, g.height, g.width)
    np.testing.assert_allclose(there, exact, rtol=0, atol=CHUNKS_ATOL_M, equal_nan=True)
