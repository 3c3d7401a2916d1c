"""The commands that use an image's sensor model without its pixels (``adjust``,
``compare-models``, ``uncertainty``) check the image itself before any work, by the rule of
every image reader (``stereodem.pipeline.inputs.check_image``).

Before: a zero-byte file, a text file named ``.tif`` or an image cut short, with a model
sidecar beside it, was accepted (they read the sidecar alone): exit 0 and products written,
where ``ortho`` and ``dem`` said "PATH: cannot read the image (...)".
"""

from __future__ import annotations

import re
import shutil
import warnings

import pytest
import rasterio
from helpers.cli_scene import assert_clear_error, run_cli, write_sim_scene
from rasterio.errors import NotGeoreferencedWarning

from stereodem.sensor.io.sidecar import load_model


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    return write_sim_scene(tmp_path_factory.mktemp("sim"))


def _broken(kind, sim, d):
    """``d/bad.tif`` of ``kind``, with the left image's model sidecar beside it."""
    bad = d / "bad.tif"
    if kind == "zero_bytes":
        bad.write_bytes(b"")
    elif kind == "text_named_tif":
        bad.write_text("id,lon,lat,h,col,row\nthis is a text file renamed .tif\n")
    else:  # cut short: header intact, pixels lost (a partial copy)
        b = (sim / "left.tif").read_bytes()
        bad.write_bytes(b[: len(b) * 6 // 10])
    shutil.copy(sim / "left.model.json", d / "bad.model.json")
    return bad


def _argv(command, sim, img, out):
    """``command`` given ``img`` as its image, writing under ``out``."""
    pts, dem = sim / "points.csv", sim / "truth_dem.tif"
    return {
        "adjust": ["adjust", img, "--gcps", pts, "--model", "rpc-shift", "-o", out / "m.json"],
        # a generic model fitted to GCPs: the image's own model is not needed, the image is
        "adjust_generic": ["adjust", img, "--gcps", pts, "--model", "rational-1"]
        + ["-o", out / "m.json"],
        "adjust_bundle": ["adjust", sim / "left.tif", img, "--model", "bundle"]
        + ["-o", out / "l.json", "--out2", out / "r.json"],
        "adjust_bundle_3": ["adjust", sim / "left.tif", sim / "right.tif", img]
        + ["--model", "bundle", "-o", out],
        "compare-models": ["compare-models", img, "--gcps", pts, "--models", "rpc-shift"]
        + ["-o", out],
        "uncertainty": ["uncertainty", img, "--dem", dem, "--sigma", "col_shift=0.5"] + ["-o", out],
        "uncertainty_model_file": ["uncertainty", img, "--model", sim / "left.model.json"]
        + ["--dem", dem, "--sigma", "col_shift=0.5", "-o", out],
        "ortho": ["ortho", img, "--dem", dem, "-o", out / "o.tif"],
    }[command]


COMMANDS = [
    "adjust",
    "adjust_generic",
    "adjust_bundle",
    "adjust_bundle_3",
    "compare-models",
    "uncertainty",
    "uncertainty_model_file",
]


def _error_text(err) -> str:
    """The message of the one ``stereodem CMD: error: MESSAGE`` line."""
    (line,) = [ln for ln in err.splitlines() if "error:" in ln]
    return line.split(": error: ", 1)[1]


@pytest.mark.parametrize("kind", ["zero_bytes", "text_named_tif", "cut_short"])
@pytest.mark.parametrize("case", COMMANDS)
def test_an_unreadable_image_beside_its_sidecar_is_refused(case, kind, sim, tmp_path, capsys):
    bad = _broken(kind, sim, tmp_path)
    out = tmp_path / "out"
    command = case.split("_")[0]
    code, stdout, err = run_cli(capsys, [*_argv(case, sim, bad, out), "--workers", "1"])
    assert_clear_error(code, err, command, rf"{re.escape(str(bad))}: cannot read the image")
    if kind == "cut_short":
        assert "cut short or damaged" in err
    assert not out.exists()  # refused before any work: nothing written
    assert stdout == ""  # no result line
    # the wording of every image reader: ortho says the same of the same file
    code, _, ortho_err = run_cli(capsys, [*_argv("ortho", sim, bad, out), "--workers", "1"])
    assert code == 1
    assert _error_text(err) == _error_text(ortho_err)


def test_a_generic_model_of_an_image_without_a_model_describes_the_image(sim, tmp_path, capsys):
    """``adjust --model rational-1`` on an image without RPCs or a sidecar sized the fitted
    model by the GCPs' extent (268 x 285 here), and ``ortho`` refused the image with it
    ("image is 300x300 but its model describes 268x285"); the image's own size now."""
    with rasterio.open(sim / "left.tif") as ds:
        prof, data = ds.profile, ds.read(1)
    img = tmp_path / "bare.tif"
    with warnings.catch_warnings():  # sensor geometry: no geotransform by nature
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(img, "w", **prof) as out:  # no RPCs, no sidecar
            out.write(data[None])
    fitted = tmp_path / "fitted.model.json"
    argv = ["adjust", img, "--gcps", sim / "points.csv", "--model", "rational-1", "-o", fitted]
    code, _, err = run_cli(capsys, argv)
    assert code == 0, err
    assert (load_model(fitted).width, load_model(fitted).height) == (300, 300)
    argv = ["ortho", img, "--dem", sim / "truth_dem.tif", "--model", fitted]
    code, _, err = run_cli(capsys, [*argv, "-o", tmp_path / "o.tif", "--workers", "1"])
    assert code == 0, err


GARBLED_SIDECARS = {
    # what a broken copy or an edit leaves: not JSON, or JSON that is no whole model
    "invalid_json": ('{"type": "pushbroom", "width": 300,', r"not valid JSON"),
    "missing_key": ('{"type": "pushbroom", "version": 1}', r"garbled pushbroom model"),
    # the file named first, then what it is not (the RPC readers' path was mid-line before)
    "text": (
        "notes, not a model\n",
        r": neither a stereodem model file .* nor an RPC file \(no RPC",
    ),
}


@pytest.mark.parametrize("kind", sorted(GARBLED_SIDECARS))
@pytest.mark.parametrize("case", ["adjust_generic", "adjust", "compare-models", "uncertainty"])
def test_a_garbled_model_sidecar_is_refused_by_every_command(case, kind, sim, tmp_path, capsys):
    """A garbled ``<stem>.model.json`` beside the image is the error ``ortho`` gives, naming
    the sidecar, in every command that reads the image's model. Before, ``adjust --model
    rational-1`` (a generic model, which needs no model of the image) passed over it without a
    word and fitted its model (exit 0), where ``adjust --model rpc-shift`` and ``ortho``
    refused it."""
    text, problem = GARBLED_SIDECARS[kind]
    img = tmp_path / "img.tif"
    shutil.copy(sim / "left.tif", img)
    (tmp_path / "img.model.json").write_text(text)
    out = tmp_path / "out"
    code, stdout, err = run_cli(capsys, [*_argv(case, sim, img, out), "--workers", "1"])
    assert_clear_error(code, err, case.split("_")[0], rf"img\.model\.json.*{problem}")
    assert not out.exists() and stdout == ""
    code, _, ortho_err = run_cli(capsys, [*_argv("ortho", sim, img, out), "--workers", "1"])
    assert code == 1
    assert _error_text(err) == _error_text(ortho_err)


def test_a_generic_model_of_an_image_with_garbled_rpcs_is_refused(sim, tmp_path, capsys):
    """Only an image without any model may be given a generic model without a word
    (:class:`~stereodem.core.errors.NoSensorModelError`): RPCs that are there but garbled
    (an ``_RPC.TXT`` beside the image, cut short) are the error ``ortho`` gives."""
    with rasterio.open(sim / "left.tif") as ds:
        prof, data = ds.profile, ds.read(1)
    img = tmp_path / "badrpc.tif"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(img, "w", **prof) as out:
            out.write(data[None])
    (tmp_path / "badrpc_RPC.TXT").write_text("LINE_OFF: 150 pixels\nSAMP_OFF: 150 pixels\n")
    out = tmp_path / "out"
    code, _, err = run_cli(capsys, [*_argv("adjust_generic", sim, img, out), "--workers", "1"])
    assert_clear_error(code, err, "adjust", r"badrpc_RPC\.TXT: RPC key \w+ missing")
    code, _, ortho_err = run_cli(capsys, [*_argv("ortho", sim, img, out), "--workers", "1"])
    assert code == 1
    assert _error_text(err) == _error_text(ortho_err)
