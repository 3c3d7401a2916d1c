"""The library checks its own inputs (issue #23): ``make_dem`` from Python gives the same
one-line refusals and the same rasters as ``stereodem dem`` on the same files and settings."""

from __future__ import annotations

import json

import pytest
import rasterio

from stereodem import cli
from stereodem.core.dem import DEM
from stereodem.core.errors import StereodemError
from stereodem.core.raster import image_dtype, read_image
from stereodem.core.threads import thread_budget
from stereodem.dem_cli import config_from_args
from stereodem.sensor.io.sidecar import load_image_model
from stereodem.sensor.simulation.simulate import simulate_scene, write_scene
from stereodem.stereo.pipeline import make_dem

HR = ["--height-range", "1000", "3500"]  # the simulated terrain lies at ~1790..2870 m


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    d = tmp_path_factory.mktemp("sim")
    write_scene(simulate_scene("aster", size=(300, 300), seed=0, n_points=20), d, overwrite=True)
    with rasterio.open(d / "truth_dem.tif") as ds:
        prof, z = ds.profile, ds.read(1)
    with rasterio.open(d / "seed_feet.tif", "w", **prof) as out:  # heights in feet
        out.write((z * 3.28084)[None].astype(prof["dtype"]))
    return d


def _cli(argv, capsys):
    code = cli.main([str(a) for a in argv])
    return code, capsys.readouterr().err.strip()


def _python(sim, left, right, argv):
    """``make_dem`` on the files of ``argv`` (a ``stereodem dem`` command line), with the
    settings that command line builds."""
    args = cli.build_parser("dem").parse_args([str(a) for a in argv])
    cfg = config_from_args(args)
    seed = (
        DEM.from_file(cfg.inputs.seed_dem, vertical=cfg.inputs.seed_dem_vertical)
        if cfg.inputs.seed_dem
        else None
    )
    return make_dem(
        read_image(left),
        read_image(right),
        load_image_model(left),
        load_image_model(right),
        cfg.stereo,
        seed_dem=seed,
        left_dtype=image_dtype(left),
        right_dtype=image_dtype(right),
    )


@pytest.mark.parametrize("case", ["same_image_twice", "seed_dem_in_feet"])
def test_make_dem_refuses_what_the_command_refuses(sim, tmp_path, capsys, case):
    left, right, extra = sim / "left.tif", sim / "right.tif", list(HR)
    if case == "same_image_twice":
        right = left
    else:
        extra = ["--seed-dem", sim / "seed_feet.tif", "--dem-vertical", "ellipsoid"]
    argv = ["dem", left, right, "-o", tmp_path / "out", "--workers", "1", *extra]
    code, err = _cli(argv, capsys)
    assert code == 1 and err.startswith("stereodem dem: error: ")
    with pytest.raises(StereodemError) as exc:
        _python(sim, left, right, argv)
    assert err == f"stereodem dem: error: {exc.value}"
    assert ("base" if case == "same_image_twice" else "implausible") in err
    assert not (tmp_path / "out" / "dem.tif").exists()


@pytest.mark.slow
def test_make_dem_gives_the_commands_rasters(sim, tmp_path, capsys):
    argv = [
        "dem",
        sim / "left.tif",
        sim / "right.tif",
        "-o",
        tmp_path / "out",
        "--workers",
        "1",
        *HR,
    ]
    code, err = _cli(argv, capsys)
    assert code == 0, err
    # the command runs under its thread budget (--workers 1): the library call at the same
    # thread count (older BLAS/OpenCV builds round differently with more threads)
    with thread_budget(1):
        products = _python(sim, sim / "left.tif", sim / "right.tif", argv)
    for name, layer in (
        ("dem", products.dem.heights),
        ("score", products.dem.score),
        ("count", products.dem.count),
        ("raygap", products.dem.ray_gap),
    ):
        with rasterio.open(tmp_path / "out" / f"{name}.tif") as ds:
            assert ds.read(1).tobytes() == layer.tobytes(), name
    assert products.info.status == "ok" and products.info.base_to_height > 0.5


def test_a_model_that_sees_no_ground_is_named_not_its_coordinates(sim, tmp_path, capsys):
    # a sidecar tilt of 89.9 degrees: "PushbroomModel: non-finite ground coordinates given
    # (25 value(s))" came from inside the base-to-height check
    model = json.loads((sim / "left.model.json").read_text())
    model["cross_track_tilt_deg"] = 89.9
    (tmp_path / "left.tif").write_bytes((sim / "left.tif").read_bytes())
    (tmp_path / "left.model.json").write_text(json.dumps(model))
    code, err = _cli(
        ["dem", tmp_path / "left.tif", sim / "right.tif", "-o", tmp_path / "out", "--workers", 1],
        capsys,
    )
    assert code == 1 and len(err.splitlines()) == 1
    assert "the left image's sensor model localises none of its pixels on the Earth" in err


def test_a_path_given_as_an_image_says_to_read_it(sim):
    """``make_dem("left.tif", ...)`` said "expected a 2-D array, got shape ()"."""
    with pytest.raises(StereodemError, match=r"left image: .*left.tif is a path: read it first"):
        make_dem(
            str(sim / "left.tif"),
            read_image(sim / "right.tif"),
            load_image_model(sim / "left.tif"),
            load_image_model(sim / "right.tif"),
        )
