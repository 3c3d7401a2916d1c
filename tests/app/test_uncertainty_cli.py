"""``stereodem uncertainty``: outputs, the adjustment-report covariance, hostile inputs."""

import json
import re

import numpy as np
import pytest
import rasterio
from affine import Affine

from stereodem.cli import main
from stereodem.core.dem import DEM
from stereodem.core.errors import InputError
from stereodem.core.raster import write_geotiff
from stereodem.ortho.drm import dem_gaps
from stereodem.ortho.grid import grid_for_model
from stereodem.ortho.uncertainty.covariance import assemble, read_adjust_report
from stereodem.ortho.uncertainty.propagation import covariance_matrix
from stereodem.sensor.io.sidecar import load_model, model_to_dict, save_model
from stereodem.sensor.models.corrected import ImageCorrectedModel
from stereodem.sensor.models.rpc import RPCModel
from stereodem.sensor.simulation.simulate import simulate_scene, write_scene

IMG = "pleiades/img_01_rpc.tif"


@pytest.fixture(scope="module")
def dem_path(tmp_path_factory, data_dir):
    m = RPCModel.from_file(data_dir / IMG)
    lon, lat = m.footprint(2300.0)
    w, s, e, n = lon.min() - 0.002, lat.min() - 0.002, lon.max() + 0.002, lat.max() + 0.002
    tr = Affine(5e-5, 0, w, 0, -5e-5, n)
    nx, ny = int((e - w) / 5e-5), int((n - s) / 5e-5)
    X, Y = tr @ np.meshgrid(np.arange(nx) + 0.5, np.arange(ny) + 0.5)
    Z = 2300 + 50 * np.sin((X - w) / 0.0015) * np.cos((Y - s) / 0.002)
    p = tmp_path_factory.mktemp("dem") / "dem.tif"
    DEM(Z.astype(np.float32), tr, "EPSG:4326", "ellipsoid").write(p)
    return p


def _report(path, model, names, cov):
    doc = {
        "model": model_to_dict(model),
        "parameters": [
            {
                "name": n,
                "value": 0.0,
                "std": float(np.sqrt(abs(cov[i][i]))) if i < len(cov) else 0.0,
                "unit": "px",
            }
            for i, n in enumerate(names)
        ],
        "covariance": cov,
    }
    path.write_text(json.dumps(doc))
    return path


def _run(data_dir, dem_path, out, *extra):
    return main(
        [
            "uncertainty",
            str(data_dir / IMG),
            "--dem",
            str(dem_path),
            "-o",
            str(out),
            "--res",
            "2",
            *extra,
        ]
    )


@pytest.mark.slow  # over 0.6 s: out of the fast subset (CI runs it)
def test_command_writes_maps_json_and_figure(data_dir, dem_path, tmp_path, capsys):
    out = tmp_path / "u"
    assert (
        _run(
            data_dir,
            dem_path,
            out,
            "--sigma",
            "col_shift=0.5",
            "--sigma",
            "row_shift=0.5",
            "--sigma",
            "dem_height=4",
            "--source-maps",
        )
        == 0
    )
    for n in ("sigma_horizontal", "sigma_east", "sigma_north", "ce90", "dominant_source"):
        assert (out / f"{n}.tif").exists()
    # each map says what it holds and in which unit, as the other products do (they had
    # neither a band description nor a unit)
    for n in ("sigma_horizontal", "sigma_east", "sigma_north", "ce90", "dominant_source"):
        with rasterio.open(out / f"{n}.tif") as f:
            assert f.descriptions[0] and f.units[0], n
            assert f.units[0] == ("1" if n == "dominant_source" else "metre"), n
    with rasterio.open(out / "dominant_source.tif") as f:
        assert "0 col_shift" in f.descriptions[0] and "2 dem_height" in f.descriptions[0]
    with rasterio.open(out / "share_dem_height.tif") as f:
        assert "dem_height" in f.descriptions[0] and f.units[0] == "1"
    with (
        rasterio.open(out / "sigma_horizontal.tif") as a,
        rasterio.open(out / "sigma_east.tif") as e,
        rasterio.open(out / "sigma_north.tif") as nn,
    ):
        sh, se, sn = a.read(1), e.read(1), nn.read(1)
        assert a.crs.to_epsg() == 32740 and a.res == (2.0, 2.0)
    ok = np.isfinite(sh)
    assert ok.mean() > 0.8
    assert np.allclose(sh[ok], np.hypot(se[ok], sn[ok]), rtol=1e-5)
    doc = json.loads((out / "sensitivity.json").read_text())
    assert set(doc["shares"]) == {"col_shift", "row_shift", "dem_height"}
    assert sum(doc["shares"].values()) == pytest.approx(1.0)
    assert (out / "uncertainty.png").stat().st_size > 10_000
    # refuses to overwrite
    assert _run(data_dir, dem_path, out, "--sigma", "col_shift=0.5") == 1
    assert "exists" in capsys.readouterr().err


@pytest.mark.slow  # two runs of the command, each over 0.6 s
def test_workers_1_and_2_write_the_same_files(data_dir, dem_path, tmp_path):
    """--workers 1 and 2 (issue 28): the maps' row blocks on the budget's threads, the GeoTIFFs
    written while the figure is drawn: the same maps, bit for bit, the same figure and report
    (its timings apart)."""
    sigmas = ("--sigma", "col_shift=0.5", "--sigma", "row_shift=0.5", "--sigma", "dem_height=4")
    outs = [tmp_path / f"w{w}" for w in (1, 2)]
    for w, out in zip((1, 2), outs):
        assert _run(data_dir, dem_path, out, *sigmas, "--workers", str(w)) == 0
    names = ("sigma_horizontal", "sigma_east", "sigma_north", "ce90", "dominant_source")
    for n in names:
        with rasterio.open(outs[0] / f"{n}.tif") as a, rasterio.open(outs[1] / f"{n}.tif") as b:
            assert a.read().tobytes() == b.read().tobytes(), n
    assert (outs[0] / "uncertainty.png").read_bytes() == (outs[1] / "uncertainty.png").read_bytes()
    one, two = (json.loads((o / "sensitivity.json").read_text()) for o in outs)
    assert one.pop("seconds").keys() == two.pop("seconds").keys()  # timings apart
    assert json.dumps(one) == json.dumps(two)


@pytest.mark.slow
def test_covariance_from_an_adjustment_report(data_dir, dem_path, tmp_path):
    rpc = RPCModel.from_file(data_dir / IMG)
    cov = [[0.25, 0.2], [0.2, 0.25]]
    rep = _report(
        tmp_path / "adjust_report.json",
        ImageCorrectedModel(rpc, col_shift=0.7),
        ["col_shift", "row_shift"],
        cov,
    )
    model, names, D = assemble(rpc, sigmas={"dem_height": 3.0}, report=read_adjust_report(rep))
    assert names == ["col_shift", "row_shift", "dem_height"]
    assert np.allclose(D, [[0.25, 0.2, 0], [0.2, 0.25, 0], [0, 0, 9.0]])
    assert model.parameters()["col_shift"] == 0.7  # the adjusted model is used
    out = tmp_path / "u"
    assert _run(data_dir, dem_path, out, "--covariance", str(rep)) == 0
    corr = json.loads((out / "sensitivity.json").read_text())
    rep0 = _report(
        tmp_path / "uncorrelated.json",
        ImageCorrectedModel(rpc, col_shift=0.7),
        ["col_shift", "row_shift"],
        [[0.25, 0.0], [0.0, 0.25]],
    )
    assert _run(data_dir, dem_path, tmp_path / "u0", "--covariance", str(rep0)) == 0
    unc = json.loads((tmp_path / "u0" / "sensitivity.json").read_text())
    # the correlation stretches the error ellipse: σ_h nearly the same, CE90 larger
    assert corr["grid"] == unc["grid"] and corr["grid"]["width"] < 800  # the image's own size
    assert corr["ce90_m_median"] > 1.03 * unc["ce90_m_median"]
    assert corr["sigma_horizontal_m"]["median"] == pytest.approx(
        unc["sigma_horizontal_m"]["median"], rel=0.01
    )


@pytest.mark.parametrize(
    "args, message",
    [
        (["--sigma", "roll=1"], "valid: col_shift, row_shift"),
        (["--sigma", "col_shift=-1"], "non-negative"),
        (["--sigma", "col_shift=nan"], "non-negative"),
        (["--sigma", "col_shift"], "NAME=VALUE"),
        ([], "no input uncertainty"),
        (["--sigma", "col_shift=1", "--method", "monte-carlo", "--samples", "2"], "10..100000"),
        # tenth hostile round: "out of memory" after the first-order lattice, and an
        # OverflowError traceback squaring the sigma
        (["--sigma", "col_shift=1", "--method", "fast", "--samples", "99999999999"], "10..100000"),
        (["--sigma", "col_shift=1e308"], "square (the variance) is finite"),
    ],
)
def test_hostile_arguments_are_one_line_errors(data_dir, dem_path, tmp_path, capsys, args, message):
    assert _run(data_dir, dem_path, tmp_path / "x", *args) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("stereodem uncertainty: error:") and message in err
    assert len(err.splitlines()) == 1


def test_hostile_covariance_files(data_dir, dem_path, tmp_path, capsys):
    rpc = RPCModel.from_file(data_dir / IMG)
    other = RPCModel.from_file(data_dir / "pleiades" / "img_02_rpc.tif")
    cases = {
        "not_psd": (
            _report(
                tmp_path / "a.json",
                ImageCorrectedModel(rpc),
                ["col_shift", "row_shift"],
                [[1.0, 2.0], [2.0, 1.0]],
            ),
            "not positive semi-definite",
        ),
        "other_model": (
            _report(
                tmp_path / "b.json",
                ImageCorrectedModel(other),
                ["col_shift", "row_shift"],
                [[1.0, 0.0], [0.0, 1.0]],
            ),
            "covariance file for another model",
        ),
        "bad_names": (
            _report(
                tmp_path / "c.json",
                ImageCorrectedModel(rpc),
                ["col_shift", "roll"],
                [[1.0, 0.0], [0.0, 1.0]],
            ),
            "valid:",
        ),
        "shape": (
            _report(
                tmp_path / "d.json",
                ImageCorrectedModel(rpc),
                ["col_shift", "row_shift"],
                [[1.0, 0.0]],
            ),
            "expected 2 x 2",
        ),
    }
    (tmp_path / "e.json").write_text("{not json")
    cases["garbled"] = (tmp_path / "e.json", "not a JSON adjustment report")
    cases["missing"] = (tmp_path / "nope.json", "no such covariance file")
    for key, (path, message) in cases.items():
        assert _run(data_dir, dem_path, tmp_path / key, "--covariance", str(path)) == 1, key
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1, (key, err)
        assert str(path) in err or key == "bad_names", (key, err)


def test_api_rejects_non_psd_and_nan_sigma():
    with pytest.raises(InputError, match="positive semi-definite"):
        covariance_matrix(["a", "b"], covariance=[[1.0, 1.5], [1.5, 1.0]])
    with pytest.raises(InputError, match="non-negative"):
        covariance_matrix(["a"], sigmas={"a": float("nan")})
    with pytest.raises(InputError, match="not symmetric"):
        covariance_matrix(["a", "b"], covariance=[[1.0, 0.1], [0.0, 1.0]])


def test_bundle_report_uses_the_images_side(data_dir, tmp_path):
    """A pair (bundle) report: the side whose geometry is the image's is picked, with its block
    of the joint covariance."""
    left = RPCModel.from_file(data_dir / IMG)
    right = RPCModel.from_file(data_dir / "pleiades" / "img_02_rpc.tif")
    names = ["left.col_shift", "left.row_shift", "right.col_shift", "right.row_shift"]
    C = np.diag([0.04, 0.09, 0.16, 0.25])
    C[0, 2] = C[2, 0] = 0.03
    doc = {
        "model": {
            "left": model_to_dict(ImageCorrectedModel(left)),
            "right": model_to_dict(ImageCorrectedModel(right)),
        },
        "parameters": [
            {"name": n, "value": 0.0, "std": float(np.sqrt(C[i, i])), "unit": "px"}
            for i, n in enumerate(names)
        ],
        "covariance": C.tolist(),
    }
    p = tmp_path / "bundle.json"
    p.write_text(json.dumps(doc))
    rep = read_adjust_report(p)
    _, n_r, D_r = assemble(right, report=rep)
    assert n_r == ["col_shift", "row_shift"] and np.allclose(D_r, np.diag([0.16, 0.25]))
    _, n_l, D_l = assemble(left, report=rep)
    assert np.allclose(D_l, np.diag([0.04, 0.09]))


@pytest.mark.slow  # over 0.6 s (the command writes its figure): out of the fast subset (CI runs it)
def test_dem_covering_part_of_the_image_is_a_warning(tmp_path, caplog):
    """A DEM under the western part of the image only: the maps are nodata over the rest, and
    the command said nothing (ortho warns); now a warning naming the DEM and the share of the
    image without a height (none with the DEM covering the image)."""
    sc = simulate_scene("aster", size=(100, 100), seed=0, n_points=1)
    write_geotiff(tmp_path / "img.tif", sc.left)
    save_model(sc.left_model, tmp_path / "img.model.json")
    dem = sc.truth_dem
    part = tmp_path / "part.tif"
    DEM(dem.heights[:, : dem.heights.shape[1] // 3], dem.transform, dem.crs, "ellipsoid").write(
        part
    )
    argv = ["uncertainty", str(tmp_path / "img.tif"), "--dem", str(part)]
    with caplog.at_level("WARNING"):
        assert main(argv + ["--sigma", "dem_height=4", "-o", str(tmp_path / "u")]) == 0
    msg = [r.getMessage() for r in caplog.records if "no DEM height under" in r.getMessage()]
    assert len(msg) == 1 and "part.tif" in msg[0], caplog.text
    assert 20 < float(msg[0].split("no DEM height under ")[1].split("%")[0]) < 95, msg[0]

    grid = grid_for_model(sc.left_model, dem)
    assert dem_gaps(sc.left_model, dem, grid)["n_no_height"] == 0


@pytest.mark.slow
def test_ortho_and_uncertainty_report_the_same_dem_gap(tmp_path, caplog):
    """On one image and DEM (a hole, and the DEM stopping short of the image), `ortho` said
    "no DEM height under 5.1% of the image footprint" (its map cells) and `uncertainty`
    "17.5% of the image" (a 21 x 21 image lattice); both now count the footprint's map cells
    without a height on the same grid (ortho.drm.dem_gaps' rule) and say it in one wording."""
    sc = simulate_scene("aster", size=(120, 120), seed=1, n_points=1)
    write_geotiff(tmp_path / "img.tif", sc.left)
    save_model(sc.left_model, tmp_path / "img.model.json")
    dem = sc.truth_dem
    h = dem.heights.copy()
    rng = np.random.default_rng(0)
    h[rng.random(h.shape) < 0.04] = np.nan  # scattered voids: the old figures differed most
    r, c = h.shape
    h[r // 2 - 8 : r // 2 + 8, c // 2 - 8 : c // 2 + 8] = np.nan  # a hole under the image
    h = h[:, : 3 * c // 5]  # stops short of the image's eastern part
    DEM(h, dem.transform, dem.crs, "ellipsoid").write(tmp_path / "gappy.tif")
    img, gappy = str(tmp_path / "img.tif"), str(tmp_path / "gappy.tif")
    figures = {}
    for cmd, extra, out in (
        ("ortho", [], "ortho.tif"),
        ("uncertainty", ["--sigma", "dem_height=4"], "uncertainty"),
    ):
        caplog.clear()
        with caplog.at_level("WARNING"):
            assert main([cmd, img, "--dem", gappy, *extra, "-o", str(tmp_path / out)]) == 0
        (msg,) = [r.getMessage() for r in caplog.records if "no DEM height" in r.getMessage()]
        m = re.search(r"no DEM height under ([\d.]+)% of the image", msg)
        assert m and "gappy.tif" in msg, msg
        n = re.search(r"image footprint \((\d+) map cell", msg)
        figures[cmd] = (float(m.group(1)), int(n.group(1)) if n else None)
    assert figures["ortho"] == figures["uncertainty"], figures
    assert 10 < figures["ortho"][0] < 90, figures


@pytest.fixture(scope="module")
def physical_scene(tmp_path_factory):
    """A small simulated scene written as the simulator writes it: ``left.tif`` with RPCs and
    its physical model sidecar ``left.model.json``, the true DEM."""
    d = tmp_path_factory.mktemp("phys")
    write_scene(simulate_scene("aster", size=(100, 100), seed=0, n_points=4), d, overwrite=True)
    return d


def _unc(d, out, *extra):
    argv = ["uncertainty", d / "left.tif", "--dem", d / "truth_dem.tif", "-o", out, *extra]
    return main([str(a) for a in argv])


def _median_sigma(out):
    return json.loads((out / "sensitivity.json").read_text())["sigma_horizontal_m"]["median"]


@pytest.mark.slow  # five runs of the command
def test_rpc_parameters_with_a_physical_sidecar(physical_scene, tmp_path, capsys):
    """An image with a physical sidecar: the image-space parameters (col_shift ..., what
    adjust's rpc-* sets estimate for any model) were refused ("unknown parameter(s) col_shift,
    row_shift for AsterModel"), as was the adjust report of such a set, and there was no
    --model to take the image's RPCs or an adjusted model file as ortho does."""
    d = physical_scene
    sig = ("--sigma", "col_shift=0.5", "--sigma", "row_shift=0.5")
    assert _unc(d, tmp_path / "phys", *sig) == 0, capsys.readouterr().err
    doc = json.loads((tmp_path / "phys" / "sensitivity.json").read_text())
    assert set(doc["shares"]) == {"col_shift", "row_shift"}
    phys = _median_sigma(tmp_path / "phys")
    assert 5 < phys < 20  # 0.5 px per axis of a 15 m image: ~10.6 m
    # the RPCs (fitted to the same geometry) give the same σ
    assert _unc(d, tmp_path / "rpc", "--model", "rpc", *sig) == 0, capsys.readouterr().err
    assert _median_sigma(tmp_path / "rpc") == pytest.approx(phys, rel=0.01)
    # an rpc-shift adjustment report of the physical model, and its adjusted model as --model
    physical = load_model(d / "left.model.json")
    adjusted = ImageCorrectedModel(physical, col_shift=0.2)
    rep = _report(
        tmp_path / "adjust_report.json",
        adjusted,
        ["col_shift", "row_shift"],
        [[0.25, 0], [0, 0.25]],
    )
    assert _unc(d, tmp_path / "cov", "--covariance", rep) == 0, capsys.readouterr().err
    assert _median_sigma(tmp_path / "cov") == pytest.approx(phys, rel=0.01)
    save_model(adjusted, tmp_path / "adj.model.json")
    argv = ("--model", tmp_path / "adj.model.json", "--sigma", "col_shift=0.5")
    assert _unc(d, tmp_path / "file", *argv) == 0, capsys.readouterr().err
    # a physical parameter with an image-space one: one line saying why
    capsys.readouterr()
    code = _unc(d, tmp_path / "mix", "--sigma", "col_shift=0.5", "--sigma", "roll_bias=1e-5")
    err = capsys.readouterr().err.strip()
    assert code == 1 and len(err.splitlines()) == 1, err
    assert "col_shift" in err and "roll_bias" in err and "cannot be propagated together" in err


def test_model_option_errors_are_one_line(data_dir, dem_path, tmp_path, capsys):
    """--model physical without a sidecar, a missing model file, --gcps without a generic model,
    a generic model without --gcps: one line each, before any work."""
    cases = [
        (["--model", "physical"], "no physical model sidecar"),
        (["--model", str(tmp_path / "nope.model.json")], "not auto, rpc, physical"),
        (["--gcps", str(tmp_path / "p.csv")], "only used with a generic --model"),
        (["--model", "rational-1"], "needs --gcps"),
    ]
    for extra, message in cases:
        code = _run(data_dir, dem_path, tmp_path / "x", *extra, "--sigma", "col_shift=1")
        err = capsys.readouterr().err.strip()
        assert code == 1 and message in err and len(err.splitlines()) == 1, (extra, err)
        assert not (tmp_path / "x").exists()


def test_maps_known_to_be_wrong_are_an_error_naming_the_files(
    data_dir, dem_path, tmp_path, capsys, monkeypatch
):
    """Maps whose measured interpolation error exceeds the tolerance were written with a
    warning and exit 0 ("interpolation error 0.76"); now exit 1, one line naming the image
    and the DEM, and no maps."""
    from stereodem.ortho.uncertainty import first_order_maps

    monkeypatch.setattr(first_order_maps, "relative_error", lambda got, exact: 0.76)
    out = tmp_path / "u"
    assert _run(data_dir, dem_path, out, "--res", "12", "--sigma", "col_shift=0.5") == 1
    err = capsys.readouterr().err
    assert "error:" in err and str(dem_path) in err and "img_01_rpc.tif" in err, err
    assert "0.76" in err and "no maps written" in err, err
    assert not (out / "sigma_horizontal.tif").exists()
