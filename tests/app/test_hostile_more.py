"""Hostile inputs, second round (issue #24): the classes of input that still ended in a
traceback or a wrong product, checked in every command that takes them.

* an unknown or non-map CRS (``--crs``, ``--checkpoints-crs``, ``[gridding]/[ortho] crs``);
* ``-o`` under a regular file or in a read-only pseudo-file system (``/proc``);
* RPC files of every format whose normalisation offsets/scales are absurd (1e30, 1e-30);
* ``stereodem simulate`` with sizes past the Earth's horizon or the DEM;
* images with non-finite pixels (``inf`` columns, a defect of some L1 products): the rest of
  the image still gives a DEM (sparse stage and tiles) and an orthoimage;
* ``-o`` = the folder holding the inputs: the products go beside them when nothing of the
  user's would be replaced.

Each error case asserts exit status 1, exactly one ``stereodem CMD: error:`` line naming the
culprit, no traceback, and nothing written.
"""

from __future__ import annotations

import fnmatch
import importlib
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import rasterio
from helpers.cli_scene import HR, assert_clear_error, job_toml, run_cli, write_sim_scene
from rasterio.warp import Resampling, reproject

from stereodem.commands import COMMANDS
from stereodem.core import jsonutil
from stereodem.core.dem import DEM
from stereodem.core.errors import RPCError
from stereodem.core.stats import nmad
from stereodem.outlock import DEMO_TOML_STAMP, is_marker, is_stereodem_output
from stereodem.sensor.io.rpc_formats import read_rpc
from stereodem.sensor.models.rpc import NORMALISATION_BOUNDS, RPCModel

FILES = Path(__file__).resolve().parents[1] / "data" / "rpc_formats"


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    return write_sim_scene(tmp_path_factory.mktemp("sim"))


@pytest.fixture(scope="module")
def dems(tmp_path_factory):
    """Three 60 x 60 DEMs of the bundled SRTM tile (geoid heights): ``ref.tif`` and
    ``a.tif``/``b.tif`` (+1 m, +2 m), for the DEM-to-DEM commands."""
    d = tmp_path_factory.mktemp("dems")
    full = DEM.bundled()
    ref = DEM(full.heights[:60, :60].copy(), full.transform, full.crs, "geoid")
    ref.write(d / "ref.tif")
    DEM(ref.heights + 1.0, ref.transform, ref.crs, "geoid").write(d / "a.tif")
    DEM(ref.heights + 2.0, ref.transform, ref.crs, "geoid").write(d / "b.tif")
    return d


def _files(folder: Path) -> dict:
    return {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}


# ----------------------------------------------------------------------------- CRS


def _crs_cases():
    dem = lambda s, o, c: [
        "dem",
        s / "left.tif",
        s / "right.tif",
        "-o",
        o,
        "--workers",
        "1",
        *HR,
        "--crs",
        c,
    ]
    ortho = lambda s, o, c: [
        "ortho",
        s / "left.tif",
        "--dem",
        s / "truth_dem.tif",
        "-o",
        o / "o.tif",
        "--crs",
        c,
    ]
    unc = lambda s, o, c: [
        "uncertainty",
        s / "left.tif",
        "--dem",
        s / "truth_dem.tif",
        "--sigma",
        "roll_bias=1",
        "-o",
        o,
        "--crs",
        c,
    ]
    assess = lambda s, o, c: [
        "assess",
        s / "truth_dem.tif",
        "--ref",
        s / "truth_dem.tif",
        "--checkpoints",
        s / "points.csv",
        "--checkpoints-crs",
        c,
        "-o",
        o,
    ]
    mosaic = lambda s, o, c: [
        "mosaic",
        s / "truth_dem.tif",
        s / "truth_dem.tif",
        "-o",
        o / "m.tif",
        "--crs",
        c,
    ]
    return {
        "dem": (dem, "--crs"),
        "ortho": (ortho, "--crs"),
        "uncertainty": (unc, "--crs"),
        "assess": (assess, "--checkpoints-crs"),
        "mosaic": (mosaic, "--crs"),
    }


@pytest.mark.parametrize(
    "code_", ["EPSG:999999", "EPSG:4978", pytest.param("not a crs", marks=pytest.mark.slow)]
)
@pytest.mark.parametrize("command", sorted(_crs_cases()))
def test_unusable_crs_is_a_clear_error_in_every_command(command, code_, sim, tmp_path, capsys):
    build, option = _crs_cases()[command]
    code, _, err = run_cli(capsys, build(sim, tmp_path / "out", code_))
    assert_clear_error(code, err, command, rf"{option}: .*{re.escape(code_)}")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("section", ["gridding", "ortho"])
def test_unusable_crs_in_a_configuration(section, sim, tmp_path, capsys):
    cfg = job_toml(
        tmp_path / "job.toml", sim, tmp_path / "out", f'[{section}]\ncrs = "EPSG:999999"\n'
    )
    code, _, err = run_cli(capsys, ["run", cfg])
    assert_clear_error(code, err, "run", rf"\[{section}\] crs.*EPSG:999999")
    assert not (tmp_path / "out").exists()


# ----------------------------------------------------------------------------- -o unusable


def _out_cases(s, d):
    """``-o`` builders per command: ``s`` the simulated scene, ``d`` the small DEMs."""
    return {
        "dem": (lambda o: ["dem", s / "left.tif", s / "right.tif", "-o", o, "--workers", "1", *HR]),
        "ortho": (
            lambda o: ["ortho", s / "left.tif", "--dem", s / "truth_dem.tif", "-o", o / "o.tif"]
        ),
        "filter": (lambda o: ["filter", s / "truth_dem.tif", "-o", o / "clean.tif"]),
        "assess": (
            lambda o: ["assess", s / "truth_dem.tif", "--ref", s / "truth_dem.tif", "-o", o]
        ),
        "uncertainty": (
            lambda o: [
                "uncertainty",
                s / "left.tif",
                "--dem",
                s / "truth_dem.tif",
                "--sigma",
                "roll_bias=1",
                "-o",
                o,
            ]
        ),
        "adjust": (
            lambda o: [
                "adjust",
                s / "left.tif",
                "--gcps",
                s / "points.csv",
                "--model",
                "rpc-shift",
                "-o",
                o / "a.model.json",
            ]
        ),
        "compare-models": (
            lambda o: [
                "compare-models",
                s / "left.tif",
                "--gcps",
                s / "points.csv",
                "--models",
                "rpc-shift",
                "-o",
                o,
            ]
        ),
        "simulate": (lambda o: ["simulate", "--size", "64", "64", "-o", o]),
        "demo": (lambda o: ["demo", "-o", o]),
        "coregister": (
            lambda o: (
                ["coregister", d / "a.tif", "--ref", d / "ref.tif", "--chain", "vshift"] + ["-o", o]
            )
        ),
        "mosaic": (lambda o: ["mosaic", d / "a.tif", d / "b.tif", "-o", o / "m.tif"]),
        "stack": (
            lambda o: (
                ["stack", d / "a.tif", d / "b.tif", "--ref", d / "ref.tif"]
                + ["--dates", "2001-01-01,2005-01-01", "--chain", "vshift", "-o", o]
            )
        ),
        "change": (lambda o: ["change", d / "a.tif", d / "b.tif", "--chain", "vshift", "-o", o]),
        "batch": (
            lambda o: [
                "batch",
                job_toml(d / "job.toml", s, d / "ignored"),
                "--workers",
                "1",
                "-o",
                o,
            ]
        ),
    }


@pytest.mark.parametrize("where", ["under_a_file", "in_proc"])
@pytest.mark.parametrize(
    "command",
    [
        "dem",
        "ortho",
        "filter",
        "assess",
        "uncertainty",
        "adjust",
        "compare-models",
        "simulate",
        "demo",
        "coregister",
        "mosaic",
        "stack",
        "change",
        "batch",
    ],
)
def test_output_that_cannot_be_created_is_a_clear_error(
    command, where, sim, dems, tmp_path, capsys
):
    a_file = tmp_path / "a_file.txt"
    a_file.write_text("not a folder\n")
    out = a_file / "out" if where == "under_a_file" else Path("/proc/stereodem_test_out")
    if where == "in_proc" and not Path("/proc/self").is_dir():
        pytest.skip("no /proc here")
    argv = _out_cases(sim, dems)[command](out)
    before, inputs_before = _files(tmp_path), _files(dems)
    code, _, err = run_cli(capsys, argv)
    assert_clear_error(code, err, command, r"cannot be created|not a (writable )?folder")
    assert re.search(r"(a_file\.txt/out|stereodem_test_out)", err)  # names the -o given
    assert _files(tmp_path) == before and _files(dems) == inputs_before
    assert not Path("/proc/stereodem_test_out").exists()


def test_run_output_in_proc_is_a_clear_error(sim, tmp_path, capsys):
    cfg = job_toml(tmp_path / "job.toml", sim, Path("/proc/stereodem_test_out"))
    code, _, err = run_cli(capsys, ["run", cfg])
    assert_clear_error(code, err, "run", r"stereodem_test_out.*cannot be created|not writable")


# ----------------------------------------------------------------------------- absurd RPCs

#: every RPC container of tests/data/rpc_formats, with the spelling of its LINE_SCALE (512)
LINE_SCALE_IN = {
    "RPC_PHR1A_P_pleiades-dimap2.XML": r"(<LINE_SCALE>)512",
    "PHRDIMAP_pleiades-dimap1.XML": r"(<Row><A>)512",
    "pleiades_worldview.XML": r"(<LINESCALE>)512",
    "pleiades.geom": r"(line_scale:\s+)512",
    "pleiades_ikonos_rpc.txt": r"(LINE_SCALE:\s+\+?)512",
    "pleiades_rpcm.json": r'("row_scale":\s*)512\.0',
    "pleiades_rpc.vrt": r'(<MDI key="LINE_SCALE">)512',
    "dg_scene_RPC.TXT": r"(LINE_SCALE:\s+\+?)512",
}


@pytest.mark.parametrize("value", ["1e30", "1e-30"])
@pytest.mark.parametrize("name", sorted(LINE_SCALE_IN))
def test_absurd_rpc_scale_in_every_format_names_the_file_and_key(name, value, tmp_path):
    text = (FILES / name).read_text()
    bad, n = re.subn(LINE_SCALE_IN[name], rf"\g<1>{value}", text, count=1)
    assert n == 1
    path = tmp_path / name
    path.write_text(bad)
    if name == "dg_scene_RPC.TXT":  # the sidecar of an image, read through GDAL
        shutil.copy(FILES / "dg_scene.tif", tmp_path / "dg_scene.tif")
        path = tmp_path / "dg_scene.tif"
    with pytest.raises(RPCError) as e:
        read_rpc(path)
    msg = str(e.value)
    assert "\n" not in msg and path.name in msg and "LINE_SCALE" in msg and "not plausible" in msg


@pytest.mark.parametrize("key", sorted(NORMALISATION_BOUNDS))
def test_every_absurd_rpb_normalisation_value_is_refused(key, tmp_path):
    m = read_rpc(FILES / "pleiades_rpcm.json")
    m.write_rpb(tmp_path / "ok.RPB")
    assert read_rpc(tmp_path / "ok.RPB").line_scale == m.line_scale  # the writer round-trips
    rpb_key = {
        "line_off": "lineOffset",
        "samp_off": "sampOffset",
        "line_scale": "lineScale",
        "samp_scale": "sampScale",
        "lat_off": "latOffset",
        "lon_off": "longOffset",
        "lat_scale": "latScale",
        "lon_scale": "longScale",
        "height_off": "heightOffset",
        "height_scale": "heightScale",
    }[key]
    lo, hi = NORMALISATION_BOUNDS[key]
    for value in [hi * 10, 1e30] + ([lo / 10] if lo > 0 else []):
        text = re.sub(
            rf"({rpb_key} = )[^;]*;", rf"\g<1>{value!r};", (tmp_path / "ok.RPB").read_text()
        )
        (tmp_path / "bad.RPB").write_text(text)
        with pytest.raises(RPCError, match=r"bad\.RPB.*not plausible"):
            read_rpc(tmp_path / "bad.RPB")


def test_absurd_rpb_sidecar_is_a_clear_error_in_ortho(sim, tmp_path, capsys):
    with rasterio.open(sim / "left.tif") as ds:
        prof, img = ds.profile, ds.read(1)
        m = RPCModel.from_rasterio(ds.rpcs, width=ds.width, height=ds.height)
    with rasterio.open(tmp_path / "plain.tif", "w", **prof) as out:  # no RPC tags, no sidecar
        out.write(img[None])
    m.write_rpb(tmp_path / "plain.RPB")
    text = (tmp_path / "plain.RPB").read_text()
    (tmp_path / "plain.RPB").write_text(re.sub(r"(lineScale = )[^;]*;", r"\g<1>1e30;", text))
    code, _, err = run_cli(
        capsys,
        [
            "ortho",
            tmp_path / "plain.tif",
            "--dem",
            sim / "truth_dem.tif",
            "-o",
            tmp_path / "out" / "o.tif",
        ],
    )
    assert_clear_error(code, err, "ortho", r"plain\.tif.*LINE_SCALE.*not plausible")
    assert not (tmp_path / "out").exists()


# ----------------------------------------------------------------------------- simulate sizes


@pytest.mark.parametrize("preset", ["aster", "frame", "pushbroom"])
@pytest.mark.parametrize(
    "size", [("100000000", "100000000"), ("1000000", "300"), ("300", "1000000")]
)
@pytest.mark.slow
def test_simulate_absurd_size_is_a_clear_error(preset, size, tmp_path, capsys):
    code, _, err = run_cli(
        capsys, ["simulate", "--preset", preset, "--size", *size, "-o", tmp_path / "out"]
    )
    assert_clear_error(code, err, "simulate", r"horizon|does not cover|memory")
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_simulate_absurd_right_size_of_a_granule(tmp_path, capsys):
    code, _, err = run_cli(
        capsys,
        [
            "simulate",
            "--format",
            "l1a-v004",
            "--size",
            "300",
            "300",
            "--right-size",
            "99999999999",
            "99999999",
            "-o",
            tmp_path / "out",
        ],
    )
    assert_clear_error(code, err, "simulate", r"horizon|does not cover|memory")
    assert not (tmp_path / "out").exists()


# ----------------------------------------------------------------------------- non-finite pixels


@pytest.fixture(scope="module")
def inf_pair(sim, tmp_path_factory):
    """The simulated pair as float32, the left image with +inf in columns 100..103 and NaN in
    column 200, -inf in column 150 of the right one."""
    d = tmp_path_factory.mktemp("inf")
    for name, cols in (("left", {np.inf: slice(100, 104), np.nan: 200}), ("right", {-np.inf: 150})):
        with rasterio.open(sim / f"{name}.tif") as ds:
            prof, tags, rpcs = ds.profile, ds.tags(), ds.rpcs
            img = ds.read(1).astype(np.float32)
        for value, c in cols.items():
            img[:, c] = value
        prof.update(dtype="float32", nodata=None)
        with rasterio.open(d / f"{name}.tif", "w", **prof, rpcs=rpcs) as out:
            out.write(img[None])
            out.update_tags(**{**tags, "STEREODEM_MODEL": f"{name}.model.json"})
        shutil.copy(sim / f"{name}.model.json", d / f"{name}.model.json")
    return d


def _dem_error_vs_truth(dem_path, truth_path):
    with rasterio.open(dem_path) as d, rasterio.open(truth_path) as t:
        z = d.read(1)
        ref = np.full(z.shape, np.nan, np.float32)
        reproject(
            t.read(1),
            ref,
            src_transform=t.transform,
            src_crs=t.crs,
            dst_transform=d.transform,
            dst_crs=d.crs,
            resampling=Resampling.bilinear,
            dst_nodata=np.nan,
        )
    e = (z - ref)[np.isfinite(z - ref)]
    return nmad(e), e.size


@pytest.mark.slow
def test_inf_columns_still_give_a_dem_through_the_sparse_stage(sim, inf_pair, tmp_path, capsys):
    """No height range: the sparse stage finds the terrain heights and the pointing from the
    rest of the image, the tiles match around the void columns; the DEM is about as complete
    and as accurate as the clean pair's."""
    code, _, err = run_cli(
        capsys,
        [
            "dem",
            inf_pair / "left.tif",
            inf_pair / "right.tif",
            "-o",
            tmp_path / "inf",
            "--workers",
            "1",
        ],
    )
    assert code == 0, err
    assert "RuntimeWarning" not in err
    code, _, err = run_cli(
        capsys,
        ["dem", sim / "left.tif", sim / "right.tif", "-o", tmp_path / "clean", "--workers", "1"],
    )
    assert code == 0, err
    nmad_inf, n_inf = _dem_error_vs_truth(tmp_path / "inf" / "dem.tif", sim / "truth_dem.tif")
    nmad_clean, n_clean = _dem_error_vs_truth(tmp_path / "clean" / "dem.tif", sim / "truth_dem.tif")
    print(
        f"DEM - truth NMAD: clean {nmad_clean:.2f} m ({n_clean} cells), inf columns "
        f"{nmad_inf:.2f} m ({n_inf} cells)"
    )
    assert n_inf >= 0.95 * n_clean
    assert nmad_inf <= nmad_clean + 0.5


def test_inf_pixels_are_no_data_in_the_orthoimage(sim, inf_pair, tmp_path, capsys):
    code, _, err = run_cli(
        capsys,
        ["ortho", inf_pair / "left.tif", "--dem", sim / "truth_dem.tif", "-o", tmp_path / "o.tif"],
    )
    assert code == 0, err
    with rasterio.open(tmp_path / "o.tif") as ds:
        o = ds.read(1)
    assert not np.isinf(o).any()
    assert 0.3 < np.isfinite(o).mean() < 1.0


# ----------------------------------------------------------------------------- -o = input folder


@pytest.mark.slow
def test_dem_into_the_folder_holding_its_inputs(sim, tmp_path, capsys):
    """``-o`` the inputs' own folder with --overwrite: nothing of the user's has a product's
    name, so the products are written beside the inputs, which stay byte-identical."""
    work = tmp_path / "work"
    shutil.copytree(sim, work)
    before = _files(work)
    code, _, err = run_cli(
        capsys,
        [
            "dem",
            work / "left.tif",
            work / "right.tif",
            "-o",
            work,
            "--overwrite",
            "--workers",
            "1",
            *HR,
        ],
    )
    assert code == 0, err
    after = _files(work)
    assert {p: after[p] for p in before} == before
    assert {"dem.tif", "score.tif", "dem_report.json"} <= {p.name for p in after}
    # a second run there replaces its own products, still not the user's files
    code, _, err = run_cli(
        capsys,
        [
            "dem",
            work / "left.tif",
            work / "right.tif",
            "-o",
            work,
            "--overwrite",
            "--workers",
            "1",
            *HR,
        ],
    )
    assert code == 0, err
    assert {p: _files(work)[p] for p in before} == before


@pytest.mark.slow
def test_run_into_the_folder_holding_its_inputs(sim, tmp_path, capsys):
    work = tmp_path / "work"
    shutil.copytree(sim, work)
    before = _files(work)
    cfg = job_toml(work / "job.toml", work, work, "[ortho]\nenabled = false\n")
    before[cfg] = cfg.read_bytes()
    code, _, err = run_cli(capsys, ["run", cfg, "--overwrite", "--workers", "1"])
    assert code == 0, err
    after = _files(work)
    assert {p: after[p] for p in before} == before
    assert (work / "dem.tif").is_file() and (work / "run.json").is_file()


def test_folder_holding_a_users_file_named_like_a_product_is_refused(sim, tmp_path, capsys):
    work = tmp_path / "work"
    shutil.copytree(sim, work)
    (work / "score.tif").write_text("the user's own score\n")
    before = _files(work)
    code, _, err = run_cli(
        capsys,
        [
            "dem",
            work / "left.tif",
            work / "right.tif",
            "-o",
            work,
            "--overwrite",
            "--workers",
            "1",
            *HR,
        ],
    )
    assert_clear_error(code, err, "dem", r"not a stereodem output.*score\.tif")
    assert _files(work) == before


# ----------------------------------------------------------------------------- mosaic --ref


@pytest.mark.parametrize("kind", ["points_csv", "no_crs"])
def test_mosaic_reference_that_is_not_a_dem_is_one_line(kind, dems, tmp_path, capsys):
    """An unreadable or CRS-less ``--ref`` is the reference's fault: refused once, naming it
    (not a warning per DEM, each skipped, then an error)."""
    if kind == "points_csv":
        ref = tmp_path / "points.csv"
        ref.write_text("lon,lat,h\n40.05,39.95,1000\n")
        message = r"points\.csv: cannot read the reference DEM"
    else:
        ref = tmp_path / "bare.tif"
        with rasterio.open(dems / "ref.tif") as ds:
            z, prof = ds.read(1), ds.profile
        prof.pop("crs", None)
        with rasterio.open(ref, "w", **prof) as out:
            out.write(z[None])
        message = r"bare\.tif: the reference DEM has no CRS"
    out = tmp_path / "m"
    code, _, err = run_cli(
        capsys,
        [
            "mosaic",
            dems / "a.tif",
            dems / "b.tif",
            "--ref",
            ref,
            "--coregister",
            "-o",
            out / "m.tif",
        ],
    )
    assert_clear_error(code, err, "mosaic", message)
    assert len(err.strip().splitlines()) == 1, err
    assert not out.exists()


# ------------------------------------------------ one overwrite policy for every output folder

#: command -> (argv builder(s, d, out), one of its products, what it writes first: the work
#: that a refusal must come before, "module:function")
FOLDER_COMMANDS = {
    "dem": (
        lambda s, d, o: ["dem", s / "left.tif", s / "right.tif", "-o", o, "--workers", "1", *HR],
        "score.tif",
        "stereodem.pipeline.inputs:load_pair",
    ),
    "run": (
        lambda s, d, o: [
            "run",
            job_toml(o.parent / "job.toml", s, o, "[ortho]\nenabled = false\n"),
            "--workers",
            "1",
        ],
        "dem.tif",
        "stereodem.pipeline.job:_run_in",
    ),
    "demo": (
        lambda s, d, o: ["demo", "-o", o, "--size", "100", "100"],
        "result",
        "stereodem.sensor.simulation.simulate:simulate_scene",
    ),
    "assess": (
        lambda s, d, o: ["assess", d / "a.tif", "--ref", d / "ref.tif", "-o", o],
        "report.md",
        "stereodem.pipeline.assessment:assess_stage",
    ),
    "coregister": (
        lambda s, d, o: (
            ["coregister", d / "a.tif", "--ref", d / "ref.tif"]
            + ["--chain", "vshift", "--no-figures", "-o", o]
        ),
        "dem_coregistered.tif",
        "stereodem.post.coreg_run:run",
    ),
    "compare-models": (
        lambda s, d, o: (
            ["compare-models", s / "left.tif", "--gcps", s / "points.csv"]
            + ["--models", "rpc-shift", "--counts", "6", "-o", o]
        ),
        "compare.md",
        "stereodem.sensor.estimation.compare:compare",
    ),
    "simulate": (
        lambda s, d, o: ["simulate", "--size", "64", "64", "-o", o],
        "truth_dem.tif",
        "stereodem.sensor.simulation.simulate:simulate_scene",
    ),
    "uncertainty": (
        lambda s, d, o: (
            ["uncertainty", s / "left.tif", "--dem", s / "truth_dem.tif"]
            + ["--sigma", "roll_bias=1", "--res", "150", "-o", o]
        ),
        "ce90.tif",
        "stereodem.ortho.uncertainty.maps:ortho_uncertainty_maps",
    ),
    "adjust": (
        lambda s, d, o: (
            ["adjust", s / "left.tif", "--gcps", s / "points.csv"]
            + ["--model", "rpc-shift", "-o", o.parent / "m.model.json", "--report", o]
        ),
        "adjust_report.md",
        "stereodem.sensor.estimation.adjust:adjust_model",
    ),
    "stack": (
        lambda s, d, o: (
            ["stack", d / "a.tif", d / "b.tif", "--ref", d / "ref.tif"]
            + ["--dates", "2001-01-01,2005-01-01", "--chain", "vshift", "-o", o]
        ),
        "rate.tif",
        "stereodem.post.stack_build:build_stack",
    ),
    "change": (
        lambda s, d, o: ["change", d / "a.tif", d / "b.tif", "--chain", "vshift", "-o", o],
        "dh.tif",
        "stereodem.post.change:dem_change",
    ),
}


@pytest.fixture(scope="module")
def noisy(tmp_path_factory):
    """``ref.tif`` and ``a.tif``/``b.tif`` (+1 m, +2 m and noise of 0.3 m: a DEM identical to
    its reference up to a shift is refused by stack) on 60 x 60 cells of the bundled SRTM."""
    d = tmp_path_factory.mktemp("noisy")
    full = DEM.bundled()
    ref = DEM(full.heights[:60, :60].copy(), full.transform, full.crs, "geoid")
    ref.write(d / "ref.tif")
    rng = np.random.default_rng(0)
    for name, dz in (("a.tif", 1.0), ("b.tif", 2.0)):
        h = ref.heights + dz + rng.normal(0, 0.3, ref.heights.shape).astype(np.float32)
        DEM(h, ref.transform, ref.crs, "geoid").write(d / name)
    return d


def _no_work(monkeypatch, target):
    """Make the command's first work fail loudly: a refusal must come before it."""
    module, name = target.split(":")

    def work(*a, **k):
        raise AssertionError(f"{target} ran: the refusal came after the work started")

    monkeypatch.setattr(importlib.import_module(module), name, work)


@pytest.mark.parametrize("overwrite", [False, True], ids=["plain", "overwrite"])
@pytest.mark.parametrize("command", sorted(FOLDER_COMMANDS))
def test_a_users_file_named_like_a_product_is_refused_before_any_work(
    command, overwrite, sim, noisy, tmp_path, capsys, monkeypatch
):
    """Every command writing into a folder refuses one holding a file with one of its
    products' names, names that file, writes nothing and starts no work. Without --overwrite:
    the file "exists". With --overwrite, in a folder no run of the command wrote: "not a
    stereodem output". Before, assess, coregister, compare-models, simulate, uncertainty and
    adjust --report replaced the user's file with --overwrite (a user's report.md in -o .),
    and without it refused with "folder exists and is not empty", naming no file."""
    build, product, target = FOLDER_COMMANDS[command]
    out = tmp_path / "out"
    out.mkdir()
    (out / product).write_text("the user's own file named like a product\n")
    (out / "notes.txt").write_text("my notes\n")
    argv = build(sim, noisy, out) + (["--overwrite"] if overwrite else [])
    before = _files(tmp_path)
    _no_work(monkeypatch, target)
    code, _, err = run_cli(capsys, argv)
    name = re.escape(product)
    pattern = rf"not a stereodem output.*{name}" if overwrite else rf"{name}: exists"
    assert_clear_error(code, err, command, pattern)
    assert _files(tmp_path) == before
    assert sorted(p.name for p in out.iterdir()) == sorted([product, "notes.txt"])


#: command -> its marker: the record whose presence, written by stereodem, makes a folder a
#: previous run's output (outlock.Products.markers)
MARKER_OF = {
    "dem": "dem_report.json",
    "run": "run.json",
    "demo": "demo.toml",
    "assess": "report.json",
    "coregister": "coregistration.json",
    "compare-models": "compare.json",
    "simulate": "scene.json",
    "uncertainty": "sensitivity.json",
    "adjust": "adjust_report.json",
    "stack": "stack.json",
    "change": "change.json",
}


@pytest.mark.parametrize("command", sorted(FOLDER_COMMANDS))
def test_a_users_file_named_like_a_marker_does_not_open_the_folder_to_overwrite(
    command, sim, noisy, tmp_path, capsys, monkeypatch
):
    """A folder counted as a previous run's output when a file with the name of one of the
    command's markers was in it, whatever it held: the user's own report.json beside their
    report.md let ``assess --overwrite`` replace the report.md. A marker counts when
    stereodem wrote it (its record carries stereodem's version); the folder is refused,
    naming the files, and nothing is touched."""
    build, product, target = FOLDER_COMMANDS[command]
    marker = MARKER_OF[command]
    out = tmp_path / "out"
    out.mkdir()
    mine = "title = 'mine'\n" if marker.endswith(".toml") else '{"my": "own record"}\n'
    (out / marker).write_text(mine)
    (out / product).write_text("the user's own file named like a product\n")
    argv = build(sim, noisy, out) + ["--overwrite"]
    before = _files(tmp_path)
    _no_work(monkeypatch, target)
    code, _, err = run_cli(capsys, argv)
    assert_clear_error(code, err, command, rf"not a stereodem output.*{re.escape(product)}")
    assert _files(tmp_path) == before


def test_a_marker_counts_when_stereodem_wrote_it(tmp_path):
    cases = {
        "stamped.json": (jsonutil.dumps(jsonutil.stamped({"a": 1})), True),
        "provenance.json": ('{"provenance": {"stereodem_version": "0.9"}}', True),
        "list.json": (jsonutil.dumps([jsonutil.stamped({"a": 1})] * 2), True),
        "users.json": ('{"my": "report"}', False),
        "empty.json": ("", False),
        "version_not_text.json": ('{"stereodem_version": 3}', False),
        "garbled.json": ("{not json", False),
        "binary.json": (b"\xff\xfe\x00", False),
        "demo.toml": (DEMO_TOML_STAMP + "; run again with ...\n", True),
        "users.toml": ("title = 'mine'\n", False),
    }
    for name, (text, expected) in cases.items():
        p = tmp_path / name
        p.write_bytes(text if isinstance(text, bytes) else text.encode())
        assert is_marker(p) is expected, name
    (tmp_path / "folder.json").mkdir()
    assert not is_marker(tmp_path / "folder.json") and not is_marker(tmp_path / "none.json")
    assert is_stereodem_output(tmp_path, ("users.json", "stamped.json"))
    assert not is_stereodem_output(tmp_path, ("users.json", "users.toml", "none.json"))


#: command -> (argv builder(s, d, out) with an input in ``out`` named like a product, the
#: input's name there, the file it is a copy of (s: the scene, d: the DEMs))
INPUT_AS_PRODUCT = {
    "dem": (
        lambda s, d, o: ["dem", o / "score.tif", s / "right.tif", "-o", o, "--workers", "1", *HR],
        "score.tif",
        ("s", "left.tif"),
    ),
    "assess": (
        lambda s, d, o: ["assess", d / "a.tif", "--ref", o / "report.json", "-o", o],
        "report.json",
        ("d", "ref.tif"),
    ),
    "coregister": (
        lambda s, d, o: (
            ["coregister", o / "dem_coregistered.tif", "--ref", d / "ref.tif"]
            + ["--chain", "vshift", "-o", o]
        ),
        "dem_coregistered.tif",
        ("d", "a.tif"),
    ),
    "compare-models": (
        lambda s, d, o: (
            ["compare-models", s / "left.tif", "--gcps", o / "compare.md"]
            + ["--models", "rpc-shift", "-o", o]
        ),
        "compare.md",
        ("s", "points.csv"),
    ),
    "simulate": (
        lambda s, d, o: ["simulate", "--dem", o / "truth_dem.tif", "--size", "64", "64", "-o", o],
        "truth_dem.tif",
        ("s", "truth_dem.tif"),
    ),
    "simulate-texture": (
        lambda s, d, o: (
            ["simulate", "--texture", o / "truth_ortho.tif"] + ["--size", "64", "64", "-o", o]
        ),
        "truth_ortho.tif",
        ("s", "truth_ortho.tif"),
    ),
    "uncertainty": (
        lambda s, d, o: (
            ["uncertainty", s / "left.tif", "--dem", o / "ce90.tif"]
            + ["--sigma", "roll_bias=1", "-o", o]
        ),
        "ce90.tif",
        ("s", "truth_dem.tif"),
    ),
    "adjust": (
        lambda s, d, o: (
            ["adjust", s / "left.tif", "--gcps", o / "adjust_report.md"]
            + ["--model", "rpc-shift", "-o", o.parent / "m.model.json", "--report", o]
        ),
        "adjust_report.md",
        ("s", "points.csv"),
    ),
    "stack": (
        lambda s, d, o: (
            ["stack", d / "a.tif", d / "b.tif", "--ref", o / "rate.tif"]
            + ["--dates", "2001-01-01,2005-01-01", "-o", o]
        ),
        "rate.tif",
        ("d", "ref.tif"),
    ),
    "change": (
        lambda s, d, o: ["change", d / "a.tif", o / "dh.tif", "-o", o],
        "dh.tif",
        ("d", "b.tif"),
    ),
}


@pytest.mark.parametrize("case", sorted(INPUT_AS_PRODUCT))
def test_an_input_named_like_a_product_is_refused_even_with_overwrite(
    case, sim, noisy, tmp_path, capsys
):
    """An input in the output folder under one of the command's products' names is refused
    with --overwrite too, even in a folder a previous run wrote (its marker there), and
    nothing is written. Before, ``simulate --dem s/truth_dem.tif -o s --overwrite`` (and
    --texture s/truth_ortho.tif) replaced its own input, as did assess, compare-models and
    adjust --report with an input named like one of their products; stack and change
    checked the products of every command (a DEM named dem.tif was refused by change)."""
    build, name, (where, src) = INPUT_AS_PRODUCT[case]
    command = case.split("-texture")[0]
    out = tmp_path / "out"
    out.mkdir()
    shutil.copy((sim if where == "s" else noisy) / src, out / name)
    before = _files(tmp_path)
    code, _, err = run_cli(capsys, [*build(sim, noisy, out), "--overwrite"])
    culprit = rf"{re.escape(name)}: (this input is a product|the output would replace the input)"
    assert_clear_error(code, err, command, culprit)
    assert _files(tmp_path) == before


#: the commands whose previous products a quick run replaces (dem, run and demo: above and
#: in test_hostile.py)
QUICK = ["assess", "coregister", "compare-models", "simulate", "uncertainty", "adjust"]
QUICK += ["stack", "change"]


#: the ones that take a second or more (a whole assessment, maps, a stack): the full suite's
_SLOWER = {"assess", "uncertainty", "stack", "simulate", "change"}


@pytest.mark.parametrize(
    "command", [pytest.param(c, marks=pytest.mark.slow) if c in _SLOWER else c for c in QUICK]
)
def test_overwrite_replaces_the_commands_products_and_nothing_else(
    command, sim, noisy, tmp_path, capsys
):
    """With --overwrite a command replaces the products of its previous run in the folder
    and leaves a file of the user's (another name) untouched; everything else it writes there
    is one of its declared products. Before, stack and change removed every command's
    products (a dem.tif of a run in the folder), and the other commands had no list."""
    build, _, _ = FOLDER_COMMANDS[command]
    out = tmp_path / "out"
    code, _, err = run_cli(capsys, build(sim, noisy, out))
    assert code == 0, err
    first = _files(out)
    (out / "notes.txt").write_text("my notes\n")
    if command != "change":  # a product of another command: not this one's
        (out / "dh.tif").write_text("change's, not this command's\n")
    keep = {p: b for p, b in _files(out).items() if p not in first}

    for p in first:  # stale versions of every product but the run's record: all replaced
        if not is_marker(p):
            p.write_bytes(b"stale")
    code, _, err = run_cli(capsys, [*build(sim, noisy, out), "--overwrite"])
    assert code == 0, err
    after = _files(out)
    assert {p: after[p] for p in keep} == keep  # the user's files untouched
    assert all(after.get(p) not in (None, b"stale") for p in first), sorted(
        p.name for p in first if after.get(p) in (None, b"stale")
    )
    if command == "adjust":  # --report: adjust_cli.report_products
        products = ("adjust_report.json", "adjust_report.md", "adjust_residuals*.png")
    else:
        products = importlib.import_module(COMMANDS[command][0]).PRODUCTS.names
    for p in set(after) - set(keep):
        top = p.relative_to(out).parts[0]
        assert any(fnmatch.fnmatch(top, pat) for pat in products), (command, top)


@pytest.mark.parametrize(
    "argv",
    [
        ["assess", "{dir}", "--ref", "{dem}", "-o", "{out}"],
        ["assess", "{dem}", "--ref", "{dir}", "-o", "{out}"],
        ["filter", "{dir}", "-o", "{out}/clean.tif"],
        ["change", "{dem}", "{dir}", "-o", "{out}"],
        ["coregister", "{dir}", "--ref", "{dem}", "-o", "{out}"],
    ],
    ids=lambda a: " ".join(a[:2]).replace("{", "").replace("}", ""),
)
def test_a_directory_for_a_dem_is_one_clear_line(argv, tmp_path, capsys):
    """A folder where a DEM file is expected: "PATH: is a directory, not a DEM file"
    (``core.raster.unreadable``), not GDAL's "not recognized as being in a supported file
    format"; nothing written."""
    folder = tmp_path / "scene"
    folder.mkdir()
    dem = tmp_path / "dem.tif"
    DEM.bundled().write(dem)
    out = tmp_path / "out"
    names = {"dir": folder, "dem": dem, "out": out}
    code, _, err = run_cli(capsys, [a.format(**names) for a in argv])
    assert_clear_error(code, err, argv[0], re.escape(f"{folder}: is a directory, not a DEM file"))
    assert not out.exists()
