"""``stereodem adjust`` end to end on the real Pleiades RPC, and model sidecar round trips."""

import json
import re

import numpy as np
import pytest

from stereodem.cli import main
from stereodem.sensor.io.gcps import ControlPoints, write_gcps
from stereodem.sensor.io.sidecar import (
    load_image_model,
    load_model,
    model_from_dict,
    model_to_dict,
    save_model,
)
from stereodem.sensor.models.corrected import ImageCorrectedModel
from stereodem.sensor.models.rpc import RPCModel
from stereodem.sensor.simulation.simulate import simulate_scene, write_scene

BIAS = dict(col_shift=-4.1, row_shift=2.6)


@pytest.fixture(scope="module")
def image(data_dir):
    return data_dir / "pleiades" / "img_01_rpc.tif"


def _points(model, n, sigma, seed, role=None):
    rng = np.random.default_rng(seed)
    c = rng.uniform(5, model.width - 6, n)
    r = rng.uniform(5, model.height - 6, n)
    h = rng.uniform(0, 1500, n)
    lon, lat = model.localize(c, r, h)
    truth = ImageCorrectedModel(model, **BIAS)
    tc, tr = truth.project(lon, lat, h)
    return ControlPoints.from_arrays(
        lon, lat, h, tc + rng.normal(0, sigma, n), tr + rng.normal(0, sigma, n), role=role
    )


def test_corrected_rpc_sidecar_round_trip(image, tmp_path):
    rpc = RPCModel.from_file(image)
    m = ImageCorrectedModel(rpc, col_shift=1.5, row_drift_row=1e-5)
    path = save_model(m, tmp_path / "m.model.json")
    back = load_model(path)
    assert isinstance(back, ImageCorrectedModel) and isinstance(back.model, RPCModel)
    assert (
        (back.width, back.height)
        == (rpc.width, rpc.height)
        == (back.model.width, back.model.height)
    )
    assert back.parameters() == m.parameters()
    lon, lat = rpc.localize(
        np.array([10.0, 900.0]), np.array([20.0, 700.0]), np.array([100.0, 900.0])
    )
    np.testing.assert_allclose(
        np.stack(back.project(lon, lat, [100.0, 900.0])),
        np.stack(m.project(lon, lat, [100.0, 900.0])),
        atol=1e-9,
    )
    # an RPC whose size is not what its normalisation implies keeps it too
    odd = RPCModel.from_dict(rpc.to_dict(), width=777, height=555)
    assert (lambda b: (b.width, b.height))(model_from_dict(model_to_dict(odd))) == (777, 555)


def test_adjust_cli_rpc_shift(image, tmp_path, capsys):
    rpc = load_image_model(image)
    role = np.where(np.arange(24) < 12, "gcp", "check")
    pts = _points(rpc, 24, 0.25, seed=4, role=role)
    pts.sigma_px[:] = 0.25
    pts.col[3] += 6.0  # one blunder
    csv = write_gcps(tmp_path / "gcps.csv", pts)
    out, rep = tmp_path / "adj.model.json", tmp_path / "report"
    argv = [
        "adjust",
        str(image),
        "--gcps",
        str(csv),
        "--model",
        "rpc-shift",
        "-o",
        str(out),
        "--report",
        str(rep),
    ]
    assert main(argv) == 0
    line = capsys.readouterr().out
    assert "outliers: P004" in line
    # the fitted shifts in the result line too (they were in the report only), with units
    shifts = re.search(r"col_shift ([+-][\d.]+) ± \S+ px, row_shift ([+-][\d.]+) ± \S+ px", line)
    assert shifts, line
    model = load_model(out)
    assert isinstance(model, ImageCorrectedModel) and (model.width, model.height) == (
        rpc.width,
        rpc.height,
    )
    p = model.parameters()
    assert (
        abs(p["col_shift"] - BIAS["col_shift"]) < 0.3
        and abs(p["row_shift"] - BIAS["row_shift"]) < 0.3
    )
    assert abs(float(shifts[1]) - p["col_shift"]) < 1e-4
    assert abs(float(shifts[2]) - p["row_shift"]) < 1e-4
    report = json.loads((rep / "adjust_report.json").read_text())
    assert report["outliers"] == ["P004"]
    assert report["check_rmse_px"] < 2 * 0.25 * np.sqrt(2)
    assert {q["name"] for q in report["parameters"]} == {"col_shift", "row_shift"}
    assert report["model"]["type"] == "image_corrected"
    assert (rep / "adjust_report.md").read_text().startswith("# Adjustment report")
    png = (rep / "adjust_residuals.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10000
    # no overwrite without --overwrite
    assert main(argv) == 1
    assert "exists" in capsys.readouterr().err
    assert main(argv + ["--overwrite"]) == 0


def test_adjust_cli_errors(image, tmp_path, capsys):
    rpc = load_image_model(image)
    pts = _points(rpc, 1, 0.3, seed=1)
    csv = write_gcps(tmp_path / "one.csv", pts)
    assert (
        main(
            [
                "adjust",
                str(image),
                "--gcps",
                str(csv),
                "--model",
                "rpc-shift",
                "-o",
                str(tmp_path / "o.json"),
            ]
        )
        == 1
    )
    err = capsys.readouterr().err
    assert err.startswith("stereodem adjust: error:") and "need at least 2 GCPs" in err
    assert main(["adjust", str(image), "--model", "rpc-shift", "-o", str(tmp_path / "o.json")]) == 1
    assert "needs --gcps" in capsys.readouterr().err
    assert (
        main(
            [
                "adjust",
                str(image),
                "--gcps",
                str(csv),
                "--model",
                "bundle",
                "-o",
                str(tmp_path / "o.json"),
            ]
        )
        == 1
    )
    assert "needs IMAGE2" in capsys.readouterr().err


def test_adjust_cli_without_check_points_prints_no_nan(image, tmp_path, capsys):
    """No check point in the CSV: the summary said "check RMSE nan px"."""
    pts = _points(load_image_model(image), 8, 0.3, seed=2)
    csv = write_gcps(tmp_path / "g.csv", pts)
    argv = ["adjust", str(image), "--gcps", str(csv), "--model", "rpc-shift"]
    assert main(argv + ["-o", str(tmp_path / "o.model.json")]) == 0
    out = capsys.readouterr().out
    assert "check RMSE n/a (no check point)" in out and "nan" not in out, out


def test_adjust_cli_generic_model(image, tmp_path):
    rpc = load_image_model(image)
    pts = _points(rpc, 30, 0.3, seed=8, role=np.where(np.arange(30) < 20, "gcp", "check"))
    csv = write_gcps(tmp_path / "g.csv", pts)
    out = tmp_path / "generic.model.json"
    assert (
        main(
            [
                "adjust",
                str(image),
                "--gcps",
                str(csv),
                "--model",
                "poly3d-2",
                "--sigma-px",
                "0.3",
                "-o",
                str(out),
                "--report",
                str(tmp_path / "r"),
            ]
        )
        == 0
    )
    model = load_model(out)
    c, r = model.project(pts.lon, pts.lat, pts.h)
    rep = json.loads((tmp_path / "r" / "adjust_report.json").read_text())
    assert rep["model_set"] == "poly3d-2" and len(rep["parameters"]) == 20
    chk = pts.role == "check"
    np.testing.assert_allclose(
        np.sqrt(np.mean((c - pts.col)[chk] ** 2 + (r - pts.row)[chk] ** 2)),
        rep["check_rmse_px"],
        rtol=1e-4,
    )  # CRS re-read from its string: um-level


@pytest.mark.slow
def test_adjust_cli_bundle_with_automatic_ties(tmp_path):
    """End to end: a simulated pushbroom pair whose right model is delivered with an attitude
    bias; ``stereodem adjust L R --model bundle`` finds SIFT tie points checked through the
    models, adjusts both attitudes with 8 GCPs per image, and the adjusted models place the
    check points at the noise level."""
    pytest.importorskip("stereodem.stereo.sparse")

    scene = simulate_scene("pushbroom", size=(500, 500), seed=3, n_points=40, angles=(0.0, -27.6))
    out = write_scene(scene, tmp_path / "scene", fit_rpcs=False)
    bias = dict(roll_bias=4e-5, pitch_bias=-5e-5, yaw_bias=1e-4)
    save_model(scene.right_model.with_parameters(**bias), out / "right.model.json", overwrite=True)
    pts = scene.points
    role = ["gcp" if k < 8 else "check" for k in range(len(pts))]
    arr = {
        k: np.array([p[k] for p in pts])
        for k in ("id", "lon", "lat", "h", "col", "row", "col_right", "row_right")
    }
    write_gcps(
        tmp_path / "l.csv",
        arr["id"],
        arr["lon"],
        arr["lat"],
        arr["h"],
        arr["col"],
        arr["row"],
        role=role,
        sigma_px=0.05,
    )
    write_gcps(
        tmp_path / "r.csv",
        arr["id"],
        arr["lon"],
        arr["lat"],
        arr["h"],
        arr["col_right"],
        arr["row_right"],
        role=role,
        sigma_px=0.05,
    )
    argv = [
        "adjust",
        str(out / "left.tif"),
        str(out / "right.tif"),
        "--model",
        "bundle",
        "--set",
        "attitude-bias",
        "--gcps",
        str(tmp_path / "l.csv"),
        "--gcps2",
        str(tmp_path / "r.csv"),
        "-o",
        str(tmp_path / "L.model.json"),
        "--out2",
        str(tmp_path / "R.model.json"),
        "--report",
        str(tmp_path / "rep"),
    ]
    assert main(argv) == 0
    rep = json.loads((tmp_path / "rep" / "adjust_report.json").read_text())
    assert rep["ties"]["n"] > 50
    R = load_model(tmp_path / "R.model.json")
    chk = np.array(role) == "check"
    c, r = R.project(arr["lon"][chk], arr["lat"][chk], arr["h"][chk])
    before = scene.right_model.with_parameters(**bias).project(
        arr["lon"][chk], arr["lat"][chk], arr["h"][chk]
    )
    err = np.hypot(c - arr["col_right"][chk], r - arr["row_right"][chk])
    err0 = np.hypot(before[0] - arr["col_right"][chk], before[1] - arr["row_right"][chk])
    assert np.sqrt(np.mean(err0**2)) > 2.0
    assert np.sqrt(np.mean(err**2)) < 0.3
    for side in ("left", "right"):
        assert (tmp_path / "rep" / f"adjust_residuals_{side}.png").exists()


@pytest.mark.slow
def test_adjust_cli_regularization_is_honoured_or_refused(image, tmp_path, capsys):
    """``--regularization`` changes a rational generic model's fit and adjustment (it used to
    be ignored: the model files were byte-identical) and the report states the weight used; a
    model linear in its coefficients (poly3d-2) and ``bundle`` refuse it with a one-line error
    instead of ignoring it."""
    rpc = load_image_model(image)
    pts = _points(rpc, 30, 0.3, seed=8, role=np.where(np.arange(30) < 20, "gcp", "check"))
    csv = write_gcps(tmp_path / "g.csv", pts)
    reps = {}
    for reg in (None, "0.5"):
        out, rep = tmp_path / f"m{reg}.model.json", tmp_path / f"r{reg}"
        argv = [
            "adjust",
            str(image),
            "--gcps",
            str(csv),
            "--model",
            "rational-1",
            "--sigma-px",
            "0.3",
            "-o",
            str(out),
            "--report",
            str(rep),
        ] + (["--regularization", reg] if reg else [])
        assert main(argv) == 0
        reps[reg] = json.loads((rep / "adjust_report.json").read_text())
    assert reps["0.5"]["regularization"] == pytest.approx(0.5)
    assert reps[None]["regularization"] != pytest.approx(0.5)  # the L-curve's own weight
    assert (tmp_path / "mNone.model.json").read_bytes() != (
        tmp_path / "m0.5.model.json"
    ).read_bytes()
    for argv, what in (
        (
            [
                "adjust",
                str(image),
                "--gcps",
                str(csv),
                "--model",
                "poly3d-2",
                "--regularization",
                "gcv",
                "-o",
                str(tmp_path / "p.model.json"),
            ],
            "linear least squares",
        ),
        (
            [
                "adjust",
                str(image),
                str(image),
                "--model",
                "bundle",
                "--regularization",
                "gcv",
                "-o",
                str(tmp_path / "l.model.json"),
                "--out2",
                str(tmp_path / "r.model.json"),
            ],
            "--regularization is not available for --model bundle",
        ),
    ):
        capsys.readouterr()
        code = main(argv)
        err = capsys.readouterr().err
        assert code == 1 and what in err and "Traceback" not in err
    assert not any(
        (tmp_path / n).exists() for n in ("p.model.json", "l.model.json", "r.model.json")
    )
