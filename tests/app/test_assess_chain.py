"""``stereodem assess --coregister --chain``: the report describes the whole chain that was
applied (every step, its parameters with units) and its before/after table is of the DEM after
the whole chain, the same DEM the error analysis analyses (the section once said "Nuth & Kääb"
with its shift alone, and an "after" NMAD of 1.62 m beside the analysis's 0.74 m)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from stereodem.cli import main
from stereodem.core import jsonutil
from stereodem.core.dem import DEM
from stereodem.core.errors import InputError
from stereodem.post.assess import assess_dem
from stereodem.post.coreg import parameter_notes, parameter_text, parse_chain, step_line
from stereodem.post.synthetic import InjectedErrors, inject_errors

CHAIN = "nuth_kaab,deramp:1,along_track"


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("assess_chain")
    full = DEM.bundled()
    ref = DEM(full.heights[:120, :120].copy(), full.transform, full.crs, "geoid")
    dem, _ = inject_errors(
        ref,
        InjectedErrors(
            dx=20.0,
            dz=3.0,
            ramp_e=4.0,
            heading_deg=190.0,
            along_sines=[(2.0, 1500.0, 0.0)],
            seed=1,
        ),
    )
    noise = np.random.default_rng(0).normal(0.0, 0.3, ref.shape)
    DEM((dem.heights + noise).astype(np.float32), ref.transform, ref.crs, "geoid").write(
        d / "dem.tif"
    )
    ref.write(d / "ref.tif")
    return d


def test_parameter_text_gives_value_sigma_and_unit():
    p = {
        "dx": {"value": 7.96089, "sigma": 0.01352, "unit": "m"},
        "c_e1n0": {"value": 0.00031527, "sigma": 1.106e-06, "unit": "m/m"},
        "sine1_phase": {"value": 0.3077, "sigma": None, "unit": "rad"},
        "iterations": 2,
        "converged": True,
        "heading_deg": 192.0,
        "sign": "displacement of the DEM",
        "coordinates": "east/north: grid metres",
        "track": {"source": "left sensor model"},
    }
    assert parameter_text(p) == (
        "dx = 7.961 ± 0.014 m, c_e1n0 = 0.0003153 ± 1.1e-06 m/m, sine1_phase = 0.3077 rad, "
        "iterations = 2, converged = yes, heading_deg = 192 deg"
    )
    assert parameter_notes(p) == [
        "coordinates: east/north: grid metres",
        "track: left sensor model",
    ]


def test_assess_dem_applies_a_fitted_chain_as_it_is(files):
    """A chain already fitted (here on half the DEM) is not fitted again: the report's steps
    are its records."""
    d, r = DEM.from_file(files / "dem.tif"), DEM.from_file(files / "ref.tif")
    dem = DEM(d.heights[:50, :50].copy(), d.transform, d.crs, d.vertical)
    ref = DEM(r.heights[:50, :50].copy(), r.transform, r.crs, r.vertical)
    stable = np.zeros(dem.shape, bool)
    stable[:, :25] = True
    chain = parse_chain("vshift").fit(ref, dem, stable=stable)
    rec = chain.report()
    a = assess_dem(dem, ref, coregister=True, coregistration=chain)
    co = a.report["coregistration"]
    assert co["steps"] == rec and co["steps"][0]["after"]["n"] == int(stable.sum())


@pytest.mark.slow  # ~2 s: the error analysis's variogram
def test_assess_chain_reports_every_step_and_one_after(files, capsys):
    out = files / "report"
    argv = ["assess", str(files / "dem.tif"), "--ref", str(files / "ref.tif"), "--coregister"]
    argv += ["--chain", CHAIN, "--track-angle", "190", "--workers", "1", "-o", str(out)]
    assert main(argv) == 0
    stdout = capsys.readouterr().out
    rep = json.loads((out / "report.json").read_text())
    co, ea = rep["coregistration"], rep["error_analysis"]
    steps = [r["step"] for r in co["steps"]]
    assert steps == ["nuth_kaab", "deramp:1", "along_track"]
    assert co["method"] == "nuth_kaab + deramp:1 + along_track"
    # one fitted chain: the analysis's records are the report's
    assert ea["coregistration"]["steps"] == co["steps"]
    assert ea["of"] == f"the DEM after the co-registration chain {CHAIN}"
    # each step did its part, and the 'after' is after the whole chain (the injected noise
    # and the cubic resampling of a 20 m shift on rough 30 m terrain are left)
    nm = [co["steps"][0]["before"]["nmad"]] + [r["after"]["nmad"] for r in co["steps"]]
    assert all(b > a for b, a in zip(nm, nm[1:])), nm
    after = rep["after_coregistration"]["stats"]["nmad"]
    assert after < 0.7 < 2.0 < rep["stats"]["nmad"]
    assert after == pytest.approx(co["nmad_after"], rel=0.1)
    assert after == pytest.approx(ea["nmad_stable"], rel=0.1)
    # the Markdown: a title naming the chain, one row per step with its parameters and units
    md = (out / "report.md").read_text()
    assert "## Co-registration chain (nuth_kaab → deramp:1 → along_track)" in md
    assert "Nuth & Kääb)" not in md
    rows = {r.split(" | ")[0].lstrip("| "): r for r in md.splitlines() if r.startswith("| ")}
    assert re.search(r"dx = [-\d.]+ ± [\d.e-]+ m, dy = ", rows["nuth_kaab"])
    assert rows["deramp:1"].count("m/m") == 2
    assert "sine1_amplitude = " in rows["along_track"] and "heading_deg = 190 deg" in md
    assert f"| {steps[-1]} |" in md
    m = re.search(r"\| after \(whole chain\) \| (\d+) \|.*\| ([\d.]+) \| [\d.]+ \| [\d.]+ \|", md)
    assert m and float(re.split(r" \| ", m.group(0))[7]) == pytest.approx(after, abs=0.006)
    # the HTML: the same section
    html = (out / "report.html").read_text()
    assert "<h2>Co-registration chain (nuth_kaab → deramp:1 → along_track)</h2>" in html
    for s in steps:
        assert f"<tr><td>{s}</td>" in html
    assert "<td>after (whole chain)</td>" in html
    # the result lines: the chain with the NMAD after it, then every step's parameters
    lines = stdout.splitlines()
    head = next(ln for ln in lines if ln.startswith("co-registration "))
    assert head.startswith("co-registration nuth_kaab + deramp:1 + along_track: stable NMAD ")
    assert f"NMAD {after:.3f} m" in head
    for s in steps:
        assert any(ln.startswith(f"  {s}: ") for ln in lines), s
    assert any(ln.startswith("  deramp:1: ") and "m/m" in ln for ln in lines)


@pytest.mark.slow  # ~3 s: two fits, and assess's error analysis (its variogram)
@pytest.mark.parametrize("chain", ["nuth_kaab,deramp", CHAIN, "icp,vshift"])
def test_coregister_and_assess_print_the_same_line_for_a_step(chain, files, tmp_path, capsys):
    """One format for a fitted step's result line (``post.coreg.step_line``): ``coregister``
    printed "nuth_kaab: stable NMAD a -> b m (median, n)" and its shift with σ on a second line
    (no parameters for the other steps), ``assess --chain`` "nuth_kaab: dx = ... m along x
    (grid east), ..., dz = ... m." without σ, NMAD or sign, and the other steps' parameters."""
    dem, ref = str(files / "dem.tif"), str(files / "ref.tif")
    common = ["--chain", chain, "--track-angle", "190", "--workers", "1"]
    argv = ["coregister", dem, "--ref", ref, *common, "--no-figures", "-o", str(tmp_path / "c")]
    capsys.readouterr()
    assert main(argv) == 0
    coregister = capsys.readouterr().out.splitlines()
    argv = ["assess", dem, "--ref", ref, "--coregister", *common, "-o", str(tmp_path / "a")]
    assert main(argv) == 0
    assess = capsys.readouterr().out.splitlines()
    steps = json.loads((tmp_path / "c" / "coregistration.json").read_text())["steps"]
    lines = [step_line(r) for r in steps]
    assert len(lines) == len(chain.split(","))
    # coregister: one line per step, then the corrected DEM; assess: under its chain line
    assert coregister == [*lines, f"-> {tmp_path / 'c' / 'dem_coregistered.tif'}"]
    head = next(i for i, ln in enumerate(assess) if ln.startswith("co-registration "))
    assert assess[head + 1 :] == [f"  {ln}" for ln in lines]
    # each step's line: the stable NMAD around it, then its parameters
    for ln, r in zip(lines, steps):
        assert ln.startswith(
            f"{r['step']}: stable NMAD {r['before']['nmad']:.3f} -> {r['after']['nmad']:.3f} m "
        )
    shifts = {"nuth_kaab": "displaced from the reference by dx = ", "icp": "moved onto the ref"}
    for ln, r in zip(lines, steps):
        if r["step"] in shifts:
            assert shifts[r["step"]] in ln and " m along x (grid east)" in ln
        elif r["step"].startswith("deramp"):
            assert ln.count("m/m") == 2


def _glacier_scene(tmp_path):
    """``dem.tif`` (the reference raised 3 m, a quarter of it thinned by 40 m), ``ref.tif`` and
    ``glacier.geojson`` outlining the thinned quarter."""
    full = DEM.bundled()
    ref = DEM(full.heights[:120, :120].copy(), full.transform, full.crs, "geoid")
    dem, _ = inject_errors(ref, InjectedErrors(dz=3.0, seed=2))
    h = dem.heights.copy()
    h[:60, :60] -= 40.0  # a glacier thinned by 40 m over a quarter of the area
    DEM(h, ref.transform, ref.crs, "geoid").write(tmp_path / "dem.tif")
    ref.write(tmp_path / "ref.tif")
    west, north = ref.transform @ (0, 0)
    east, south = ref.transform @ (60, 60)
    ring = [[west, north], [east, north], [east, south], [west, south], [west, north]]
    glacier = tmp_path / "glacier.geojson"
    feature = {
        "type": "Feature",
        "properties": {"name": "glacier"},
        "geometry": {"type": "Polygon", "coordinates": [ring]},
    }
    glacier.write_text(json.dumps({"type": "FeatureCollection", "features": [feature]}))
    return tmp_path / "dem.tif", tmp_path / "ref.tif", glacier


@pytest.mark.slow
def test_assess_coregister_fits_on_the_stable_terrain_outside_exclude(tmp_path, capsys):
    """``assess --coregister --exclude glacier.geojson``: the polygons were left out of the
    stable terrain only with an error-analysis option; alone, --exclude was ignored and Nuth &
    Kääb fitted the glacier's thinning too. Now the fit leaves them out (no analysis section
    is added), and --exclude with nothing that uses the stable terrain is refused."""
    dem, ref, glacier = _glacier_scene(tmp_path)
    base = ["assess", str(dem), "--ref", str(ref), "--workers", "1"]

    def dz(out, *more):
        assert main([*base, "--coregister", *more, "-o", str(out)]) == 0
        rep = json.loads((out / "report.json").read_text())
        assert "error_analysis" not in rep
        return rep["coregistration"]["steps"][0]["parameters"]["dz"]["value"]

    kept = dz(tmp_path / "all")
    left_out = dz(tmp_path / "stable", "--exclude", str(glacier))
    assert abs(left_out - 3.0) < 0.2 < abs(kept - 3.0)
    capsys.readouterr()
    assert main([*base, "--exclude", str(glacier), "-o", str(tmp_path / "no")]) == 1
    err = capsys.readouterr().err
    assert "--exclude leaves polygons out of the stable terrain" in err
    assert not (tmp_path / "no").exists()


@pytest.mark.slow
def test_run_configuration_excludes_polygons_from_the_assessments_coregistration(tmp_path):
    """``[assess] exclude`` (a job's configuration): the assessment's Nuth & Kääb is fitted
    outside the polygons, as ``assess --exclude``; paths relative to the configuration; without
    ``coregister`` it is refused, and a missing file fails the job's input checks."""
    from stereodem.config import config_from_dict
    from stereodem.pipeline.assessment import assess_stage
    from stereodem.pipeline.inputs import check_inputs

    dem, ref, glacier = _glacier_scene(tmp_path)

    def cfg(**assess):
        raw = {
            "inputs": {"left": "l.tif", "right": "r.tif", "reference_dem": "ref.tif"},
            "output": {"dir": "out"},
            "assess": assess,
            "run": {"workers": 1},
        }
        return config_from_dict(raw, base=tmp_path, source="job.toml")

    c = cfg(exclude=["glacier.geojson"])
    assert c.assess.exclude == [str(glacier)]
    result, _ = assess_stage(c, str(dem), tmp_path / "rep")
    step = result.report["coregistration"]["steps"][0]
    assert abs(step["parameters"]["dz"]["value"] - 3.0) < 0.2
    assert "error_analysis" not in result.report
    with pytest.raises(InputError, match=r"\[assess\] exclude .* needs coregister = true"):
        cfg(exclude=["glacier.geojson"], coregister=False)
    with pytest.raises(
        InputError, match=r"missing.geojson: cannot read the \[assess\] exclude outlines \(No such"
    ):
        check_inputs(cfg(exclude=["missing.geojson"]))
    for bad in ("glacier.geojson", ["glacier.geojson", 5], [""], [float("nan")]):
        with pytest.raises(InputError, match=r"job.toml: \[assess\] exclude: expected a list"):
            cfg(exclude=bad)


@pytest.mark.slow  # ~2 s: two assessments with a co-registration chain and its variogram
def test_assess_stage_converts_the_dems_vertical_reference_once(files, tmp_path, monkeypatch):
    """With a co-registration chain (an error-analysis job) ``assess_stage`` brings the DEM to
    the reference's vertical reference to fit the chain, and ``assess_dem`` did it again: two
    full-grid geoid lookups of the DEM (and any conversion warning said twice). It is given
    the converted DEM now: one conversion, the same report."""
    from stereodem.config import config_from_dict
    from stereodem.pipeline import assessment
    from stereodem.post.error_analysis import ErrorAnalysisJob

    ref = DEM.from_file(files / "ref.tif").to_reference("ellipsoid")  # the DEM is geoid
    ref.write(tmp_path / "ref_ellipsoid.tif")
    raw = {
        "inputs": {"left": "l.tif", "right": "r.tif", "reference_dem": "ref_ellipsoid.tif"},
        "output": {"dir": "out"},
        "assess": {"coregister": True},
        "run": {"workers": 1},
    }
    cfg = config_from_dict(raw, base=tmp_path, source="job.toml")
    conversions = []
    to_reference = DEM.to_reference

    def counted(self, to):
        if self.vertical != to:
            conversions.append((self.path, self.vertical, to))
        return to_reference(self, to)

    monkeypatch.setattr(DEM, "to_reference", counted)

    def report(name):
        job = ErrorAnalysisJob(chain="nuth_kaab,deramp")
        result, _ = assessment.assess_stage(
            cfg, str(files / "dem.tif"), tmp_path / name, error_analysis=job, analysis=False
        )
        for step in result.report["coregistration"]["steps"]:
            step.pop("seconds")
        return jsonutil.dumps(result.report)  # NaN (a class without cells) as null

    once = report("once")
    assert conversions == [(str(files / "dem.tif"), "geoid", "ellipsoid")]
    assert json.loads(once)["vertical"]["note"] == "DEM converted from geoid to ellipsoid (EGM96)"
    # the same report as assess_dem converting the DEM itself (as before: twice)
    assess_dem_itself = assessment.assess_dem

    def without_reconciled(*args, reconciled=None, **kw):
        return assess_dem_itself(*args, **kw)

    monkeypatch.setattr(assessment, "assess_dem", without_reconciled)
    conversions.clear()
    assert report("twice") == once
    assert len(conversions) == 2
