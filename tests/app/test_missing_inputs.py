"""A missing input file reads the same in every command: "PATH: cannot read the WHAT (No such
file or directory)" (:func:`stereodem.core.errors.not_found`), the wording of every reader that
cannot read its file.

Before, a missing image read "PATH: image not found" from the model loader (``dem``, ``ortho``,
``compare-models``, ``uncertainty``, ``adjust --model rpc-shift``) but "PATH: cannot read the
image (PATH: No such file or directory)" where the model came from elsewhere (``adjust
--model rational-1``, ``ortho``/``uncertainty --model FILE``); other inputs read "PATH: match
file not found", "PATH: no such file", "PATH: no such file or folder", "PATH: configuration
file not found" or GDAL's "cannot read the DEM (PATH: No such file or directory)".
"""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers.cli_scene import assert_clear_error, run_cli, write_sim_scene

from stereodem.core.errors import not_found


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    return write_sim_scene(tmp_path_factory.mktemp("sim"))


def _cases(s, m, o):
    """name -> (argv with the missing file ``m``, what ``m`` is) on the scene ``s``, writing
    under ``o``."""
    dem, pts, model = s / "truth_dem.tif", s / "points.csv", s / "left.model.json"
    unc = ["--dem", dem, "--sigma", "col_shift=0.5", "-o", o]
    return {
        # a missing image, whatever gives its model
        "dem": (["dem", m, s / "right.tif", "-o", o], "image"),
        "ortho": (["ortho", m, "--dem", dem, "-o", o / "o.tif"], "image"),
        "ortho_model_file": (
            ["ortho", m, "--model", model, "--dem", dem, "-o", o / "o.tif"],
            "image",
        ),
        "uncertainty": (["uncertainty", m, *unc], "image"),
        "uncertainty_model_file": (["uncertainty", m, "--model", model, *unc], "image"),
        "adjust": (
            ["adjust", m, "--gcps", pts, "--model", "rpc-shift", "-o", o / "m.json"],
            "image",
        ),
        "adjust_generic": (
            ["adjust", m, "--gcps", pts, "--model", "rational-1", "-o", o / "m.json"],
            "image",
        ),
        "compare-models": (["compare-models", m, "--gcps", pts, "-o", o], "image"),
        # the other inputs
        "assess": (["assess", m, "--ref", dem, "-o", o], "DEM"),
        "mosaic": (["mosaic", m, dem, "-o", o / "m.tif"], "DEM"),
        "adjust_gcps": (
            ["adjust", s / "left.tif", "--gcps", m, "--model", "rpc-shift", "-o", o / "m.json"],
            "GCP file",
        ),
        "coregister_points": (
            ["coregister", dem, "--ref", m.with_suffix(".parquet"), "-o", o],
            "points",
        ),
        "coregister_exclude": (
            ["coregister", dem, "--ref", dem, "--exclude", m.with_suffix(".geojson"), "-o", o],
            "vector file",
        ),
        "info": (["info", m.with_suffix(".hdf")], "ASTER granule"),
        "run": (["run", m.with_suffix(".toml")], "configuration file"),
    }


CASES = sorted(_cases(Path("s"), Path("m"), Path("o")))


@pytest.mark.parametrize("case", CASES)
def test_a_missing_input_file_reads_the_same_in_every_command(case, sim, tmp_path, capsys):
    missing, out = tmp_path / "nope.tif", tmp_path / "out"
    argv, what = _cases(sim, missing, out)[case]
    path = next(a for a in argv if str(a).startswith(str(missing.with_suffix(""))))
    code, stdout, err = run_cli(capsys, argv)
    command = case.split("_")[0]
    assert_clear_error(code, err, command, ".")
    assert err.strip() == f"stereodem {command}: error: {not_found(path, what)}"
    assert not out.exists() and stdout == ""
