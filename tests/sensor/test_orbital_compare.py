"""``stereodem compare-models`` on the simulated ASTER 3N scene (orbital, physical and generic
models on one GCP/ICP split)."""

import csv

import numpy as np
import pytest
from helpers.orbital import aster_scene, control_points
from helpers.strict_json import strict_loads

from stereodem.cli import main
from stereodem.core.raster import write_geotiff
from stereodem.sensor.io.gcps import write_gcps
from stereodem.sensor.io.sidecar import save_model


@pytest.fixture(scope="module")
def image(tmp_path_factory):
    meta, _, _ = aster_scene()
    d = tmp_path_factory.mktemp("cmp")
    write_geotiff(d / "left.tif", np.zeros((16, 16), np.uint8), None, None, None)
    save_model(meta, d / "left.model.json")
    pts = control_points(30, n_icp=20, seed=11)
    g, i = pts["gcp"], pts["icp"]
    cat = {k: np.concatenate([g[k], i[k]]) for k in ("lon", "lat", "h", "col", "row")}
    role = ["gcp"] * 30 + ["check"] * 20
    write_gcps(
        d / "points.csv",
        [f"P{k:03d}" for k in range(50)],
        cat["lon"],
        cat["lat"],
        cat["h"],
        cat["col"],
        cat["row"],
        role=role,
    )
    return d


@pytest.mark.slow
def test_compare_models_table_json_figure(image, tmp_path, capsys):
    out = tmp_path / "cmp"
    rc = main(
        [
            "compare-models",
            str(image / "left.tif"),
            "--gcps",
            str(image / "points.csv"),
            "--models",
            "poly3d-1,attitude-bias-drift,eop-poly2,orun,toutin,kratky",
            "--counts",
            "3,10,30",
            "-o",
            str(out),
        ]
    )
    assert rc == 0
    rec = strict_loads((out / "compare.json").read_text())
    assert (out / "compare.md").exists() and (out / "compare.png").stat().st_size > 10000
    by = {(r["model"], r["n_gcp"]): r for r in rec}
    for k in ("model", "n_params", "gcp_rmse_px", "icp_rmse_px", "sigma0", "condition"):
        assert k in by[("eop-poly2", 30)]
    assert any("orun" in r["model"] for r in rec) and any("toutin" in r["model"] for r in rec)
    # same ICPs everywhere
    assert {r["n_icp"] for r in rec} == {20}
    # too few GCPs for Orun & Natarajan's 10 unknowns (3 of them weighted) or Toutin's 8 (2
    # weighted): refused with the count needed
    assert "at least 4 are needed" in by[("orun", 3)]["error"]
    assert "at least 4 are needed" in by[("toutin", 3)]["error"]
    # with 30 GCPs every orbital model is within 20 % of the rigorous model's ICP RMSE (noise
    # 0.3 px)
    rig = by[("attitude-bias-drift", 30)]["icp_rmse_px"]
    for m in ("eop-poly2", "orun", "toutin", "kratky"):
        assert by[(m, 30)]["icp_rmse_px"] < 1.2 * rig, m
    # with their weakly determined parameters weighted, Orun & Natarajan and Toutin are within
    # 20 % of the rigorous model from 10 GCPs on
    for m in ("orun", "toutin"):
        assert by[(m, 10)]["icp_rmse_px"] < 1.2 * by[("attitude-bias-drift", 10)]["icp_rmse_px"], m
    # and the affine-in-height generic model is worse than all of them
    assert by[("poly3d-1", 30)]["icp_rmse_px"] > rig


def test_compare_models_refuses_icps_outside_image(image, tmp_path, capsys):
    with open(image / "points.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    for r in rows:
        if r["role"] == "check":
            r["col"] = "99999"
            break
    bad = tmp_path / "bad.csv"
    with open(bad, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    rc = main(
        [
            "compare-models",
            str(image / "left.tif"),
            "--gcps",
            str(bad),
            "--models",
            "orun",
            "-o",
            str(tmp_path / "o"),
        ]
    )
    assert rc == 1
    assert (
        f"{bad}: 1 of 20 check points lie outside the 4100 x 4200 image {image / 'left.tif'}"
        in capsys.readouterr().err
    )


@pytest.mark.slow
def test_compare_models_over_random_splits(image, tmp_path):
    out = tmp_path / "spl"
    rc = main(
        [
            "compare-models",
            str(image / "left.tif"),
            "--gcps",
            str(image / "points.csv"),
            "--models",
            "orun,toutin",
            "--counts",
            "3,10",
            "--n-check",
            "20",
            "--splits",
            "3",
            "--sigma-px",
            "0.3",
            "-o",
            str(out),
        ]
    )
    assert rc == 0
    # strict JSON: a model with no ratio (undefined) is null, not NaN (which jq refuses)
    res = strict_loads((out / "splits.json").read_text())
    assert res["reference"] == "attitude-bias-drift" and res["splits"] == 3
    by = {(s["model"], s["n_gcp"]): s for s in res["summary"]}
    assert by[("attitude-bias-drift", 10)]["median_ratio"] == 1.0
    assert {r["split"] for r in res["records"]} == {0, 1, 2}
    # each split has its own check points: the reference's ICP RMSE differs between splits
    ref = [
        r["icp_rmse_px"]
        for r in res["records"]
        if r["model"] == "attitude-bias-drift" and r["n_gcp"] == 10
    ]
    assert len(set(np.round(ref, 9))) == 3
    assert by[("toutin", 3)]["refused"] == 3 and "at least 4" in by[("toutin", 3)]["error"]
    for m in ("orun", "toutin"):
        assert np.isfinite(by[(m, 10)]["median_ratio"]) and by[(m, 10)]["median_condition"] < 1e6
    assert "median ICP / attitude-bias-drift ICP" in (out / "splits.md").read_text()


def test_compare_models_refuses_negative_splits(image, tmp_path, capsys):
    rc = main(
        [
            "compare-models",
            str(image / "left.tif"),
            "--gcps",
            str(image / "points.csv"),
            "--models",
            "orun",
            "--splits",
            "-1",
            "-o",
            str(tmp_path / "x"),
        ]
    )
    assert rc == 1
    assert "--splits: expected a count >= 0, got -1" in capsys.readouterr().err


@pytest.fixture(scope="module")
def granule(tmp_path_factory):
    """A small simulated ASTER L1A V004 granule (3N 200 x 200, 3B in the real size ratio) with
    its check points (``col,row`` in 3N, ``col_right,row_right`` in 3B) and those points
    measured in 3B (``points_3b.csv``)."""
    from stereodem.sensor.simulation.aster_granule import (
        granule_right_size,
        write_granule_scene,
    )
    from stereodem.sensor.simulation.simulate import simulate_scene

    d = tmp_path_factory.mktemp("granule")
    sc = simulate_scene(
        "aster", size=(200, 200), right_size=granule_right_size((200, 200)), seed=3, n_points=20
    )
    path = write_granule_scene(sc, d, version=4, seed=3)
    with open(d / "points.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    with open(d / "points_3b.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["id", "lon", "lat", "h", "col", "row", "role"])
        for r in rows:
            w.writerow([r[k] for k in ("id", "lon", "lat", "h", "col_right", "row_right", "role")])
    return path


def _compare_granule(path, csv_name, out, *band):
    argv = ["compare-models", path, *band, "--gcps", path.parent / csv_name]
    argv += ["--models", "rpc-shift,attitude-bias", "--counts", "6", "-o", out]
    return main([str(a) for a in argv])


@pytest.mark.slow  # ~2 s: two compare-models runs end to end on a granule
def test_compare_models_takes_an_aster_granule(granule, image, tmp_path, capsys):
    """``compare-models`` on an ASTER L1A granule takes its band's model as ``adjust`` and
    ``uncertainty`` do: 3N by default, ``--band 3B`` for the backward band. Before: "no usable
    sensor model (no AST_L1A_....model.json sidecar; ...: no RPC model found ...)"."""
    for band, points in (((), "points.csv"), (("--band", "3B"), "points_3b.csv")):
        out = tmp_path / f"cmp{len(band)}"
        assert _compare_granule(granule, points, out, *band) == 0, capsys.readouterr().err
        rec = strict_loads((out / "compare.json").read_text())
        # the points are the band model's exact projections: both fits are exact at the ICPs
        assert {r["model"] for r in rec} == {"rpc-shift", "attitude-bias"}
        assert all(not r.get("error") and r["icp_rmse_px"] < 0.01 for r in rec), rec
    # the band is the one asked for: the 3B points do not fit 3N (the default)
    assert _compare_granule(granule, "points_3b.csv", tmp_path / "wrong") == 1
    assert "check points lie outside the 200 x 200 image" in capsys.readouterr().err
    # a band name on a GeoTIFF is refused as in the other commands
    assert _compare_granule(image / "left.tif", "points.csv", tmp_path / "x", "--band", "3B") == 1
    assert "band '3B' names an ASTER band, but this is not an ASTER granule" in (
        capsys.readouterr().err
    )
