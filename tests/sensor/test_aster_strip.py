"""ASTER strips (issue 26, item 3): consecutive simulated granules of one pass, joined into
one model per band and one DEM with no step at the seam."""

from __future__ import annotations

import datetime as _dt
import json

import numpy as np
import pytest

from stereodem.cli import main
from stereodem.core.dem import DEM
from stereodem.core.errors import InputError
from stereodem.core.stats import nmad
from stereodem.post.assess import compare_on_reference_grid
from stereodem.post.seams import seam_step
from stereodem.sensor.io.aster_l1a import open_aster_granule
from stereodem.sensor.io.aster_strip import open_aster_strip
from stereodem.sensor.simulation.aster_granule import DEFAULT_START, write_v004
from stereodem.sensor.simulation.aster_strip import cut_granule, simulate_strip, write_strip
from stereodem.strip import strip_granules


@pytest.fixture(scope="module")
def strip3(tmp_path_factory):
    """Three consecutive granules of 200 x 160 3N lines (10 overlapping lines) and the truth."""
    strip = simulate_strip(3, size=(200, 160), seed=3)
    folder = tmp_path_factory.mktemp("strip")
    paths = write_strip(strip, folder)
    return strip, [str(p) for p in paths], folder


def test_simulated_granules_are_cut_from_one_pass(strip3):
    strip, paths, folder = strip3
    assert strip.advance == 150 and strip.heights[0] - strip.advance == 10
    assert len({p for p in paths}) == 3  # distinct granule ids
    long_n = strip.scene.left_model
    t = []
    for k, p in enumerate(paths):
        g = open_aster_granule(p)
        m = g.model("3N")
        # the granule's own model (read back from its lattice) is the pass's model moved on
        c, r = np.meshgrid(np.linspace(0, 199, 5), np.linspace(0, 159, 5))
        lon, lat = m.localize(c.ravel(), r.ravel(), np.full(c.size, 2000.0))
        cl, rl = long_n.project(lon, lat, np.full(c.size, 2000.0))
        assert np.max(np.hypot(cl - c.ravel(), rl - r.ravel() - strip.first_lines[k])) < 0.01
        np.testing.assert_array_equal(g.band("3N").dn(), strip.granules[k].bands["3N"].dn)
        t.append(strip.granules[k].bands["3N"].times[0])
    # one clock: lattice-row times advance by the granule advance in line periods
    np.testing.assert_allclose(np.diff(t), strip.advance * long_n.line_period, rtol=1e-9)
    cut = json.loads((folder / "strip.json").read_text())
    assert cut["first_lines"] == [0, 150, 300] and cut["overlap_3N"] == 10


def test_join_recovers_the_pass(strip3):
    strip, paths, _ = strip3
    s = open_aster_strip(paths[::-1])  # any order
    assert [g.path for g in s.granules] == paths
    for band, long_model, long_img in (
        ("3N", strip.scene.left_model, strip.scene.left),
        ("3B", strip.scene.right_model, strip.scene.right),
    ):
        b = s.band(band)
        assert b.first_lines == strip.first_lines  # from the orbit, not the names
        assert b.image.shape == long_img.shape
        # the joined model is the pass's model: same line numbering, same rays
        rng = np.random.default_rng(0)
        c = rng.uniform(0, b.model.width - 1, 200)
        r = rng.uniform(0, b.model.height - 1, 200)
        lon, lat = long_model.localize(c, r, np.full(200, 2500.0))
        cs, rs = b.model.project(lon, lat, np.full(200, 2500.0))
        assert np.max(np.hypot(cs - c, rs - r)) < 0.01
        for seam in b.seams:
            assert seam["overlap_correlation"] > 0.99 and seam["model_departure_px"] < 0.01
            assert seam["orbit_miss_m"] < 1.0
        # the joined image is the pass's image (radiance of the DN, fill = NaN)
        dn_valid = long_img > 0
        assert np.isfinite(b.image).sum() == dn_valid.sum()
    assert s.report["seams"]["3N"][0]["overlap_lines"] == 10
    assert "joined models" in s.report["method"]


def test_non_consecutive_granules_are_refused_in_one_line(strip3, tmp_path):
    _, paths, _ = strip3
    with pytest.raises(InputError) as e:
        open_aster_strip([paths[0], paths[2]])
    msg = str(e.value)
    assert "\n" not in msg and "not consecutive" in msg
    assert all(p.rsplit("/", 1)[-1] in msg for p in (paths[0], paths[2]))
    out = tmp_path / "out"
    assert main(["dem", paths[0], paths[2], "-o", str(out)]) == 1
    assert not out.exists()  # nothing written


def test_granules_of_another_pass_are_refused(strip3, tmp_path):
    strip, paths, _ = strip3
    later = DEFAULT_START + _dt.timedelta(days=16)  # the next repeat of the path
    g = cut_granule(
        strip.scene,
        strip.advance,
        strip.heights,
        row_step=strip.row_step,
        start=later,
        index=1,
        seed=3,
    )
    other = write_v004(g, tmp_path / f"{g.granule_id}.hdf")
    with pytest.raises(InputError) as e:
        open_aster_strip([paths[0], str(other)])
    msg = str(e.value)
    assert "not consecutive granules of one pass" in msg and other.name in msg
    assert "\n" not in msg


def test_strip_inputs(strip3, tmp_path):
    _, paths, folder = strip3
    assert strip_granules([str(folder)]) == paths  # a folder of granules
    assert strip_granules(paths[:2]) == paths[:2]
    assert strip_granules(paths[:2], band="3N") is None  # --band 3N: a pair of bands
    assert strip_granules([paths[0]]) is None  # one granule: its own pair
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no ASTER L1A granule"):
        strip_granules([str(tmp_path / "empty")])


@pytest.mark.slow
def test_strip_dem_has_no_step_at_the_seam(strip3, tmp_path):
    """Two adjacent granules: the strip DEM's error does not step across the seam line
    (<= 0.5 m) and its NMAD against the truth is a single granule's within 10 % (same cells)."""
    strip, paths, folder = strip3
    truth = DEM.from_file(folder / "truth_dem.tif")
    lo, hi = truth.height_range()
    common = ["--res", "30", "--height-range", f"{lo - 100:.0f}", f"{hi + 100:.0f}"]
    out = tmp_path / "strip"
    assert main(["dem", paths[0], paths[1], "-o", str(out), *common]) == 0
    report = json.loads((out / "dem_report.json").read_text())
    seam = report["strip"]["seams"]["3N"][0]
    assert seam["offset_lines"] == 150 and seam["overlap_lines"] == 10
    dem = DEM.from_file(out / "dem.tif")
    model = open_aster_strip(paths[:2]).band("3N").model
    step = seam_step(dem, truth, model, seam["seam_line"], half_width=strip.row_step)
    assert step["n_before"] > 300 and step["n_after"] > 300
    assert abs(step["step_m"]) <= 0.5, step
    d_strip = compare_on_reference_grid(dem, truth).dh
    for k in (0, 1):
        single = tmp_path / f"g{k}"
        assert main(["dem", paths[k], "-o", str(single), *common]) == 0
        d_one = compare_on_reference_grid(DEM.from_file(single / "dem.tif"), truth).dh
        same = np.isfinite(d_strip) & np.isfinite(d_one)
        assert same.sum() > 0.9 * np.isfinite(d_one).sum()  # the strip covers the granule
        assert abs(nmad(d_strip[same]) / nmad(d_one[same]) - 1.0) <= 0.10


def test_join_of_granules_whose_lattices_are_out_of_phase(strip3, tmp_path):
    """A granule cut 143 lines on (not a whole number of 15-line lattice steps): the joined
    lattice is irregular, the line offset still comes out of the orbit and the joined model
    still is the pass's."""
    strip, paths, _ = strip3
    g = cut_granule(strip.scene, 143, strip.heights, row_step=strip.row_step, index=1, seed=3)
    other = write_v004(g, tmp_path / f"{g.granule_id}.hdf")
    s = open_aster_strip([paths[0], str(other)])
    for band, long_model in (("3N", strip.scene.left_model), ("3B", strip.scene.right_model)):
        b = s.band(band)
        assert b.first_lines == [0, 143]
        assert b.seams[0]["fraction"] == 0.0 and b.seams[0]["orbit_miss_m"] < 0.01
        rows = b.model.geometry.lattice_rows
        assert np.unique(np.diff(rows)).size > 1  # irregular lattice
        c = np.linspace(0, b.model.width - 1, 9)
        r = np.linspace(0, b.model.height - 1, 9)
        lon, lat = long_model.localize(c, r, np.full(9, 2200.0))
        cs, rs = b.model.project(lon, lat, np.full(9, 2200.0))
        assert np.max(np.hypot(cs - c, rs - r)) < 0.01


@pytest.mark.slow
def test_granule_point_clouds_name_their_pair(strip3, tmp_path, capsys):
    """``dem G.hdf --point-cloud``: the report and the cloud's pair list name the granule's
    bands (they said the granule and "None"); ``dem G1 G2 --point-cloud`` (a strip) names its
    pair in the cloud too and prints the cloud's line, as the pair and N-view routes do."""
    laspy = pytest.importorskip("laspy")
    from stereodem.stereo.pointcloud import read_pairs

    strip, paths, folder = strip3
    lo, hi = DEM.from_file(folder / "truth_dem.tif").height_range()
    common = ["--height-range", f"{lo - 100:.0f}", f"{hi + 100:.0f}", "--point-cloud", "las"]
    one = tmp_path / "one"
    assert main(["dem", paths[0], "-o", str(one), *common]) == 0
    report = json.loads((one / "dem_report.json").read_text())
    names = [f"{paths[0]} (3N)", f"{paths[0]} (3B)"]
    assert [report["left"], report["right"]] == names
    assert report["point_cloud"]["pairs"] == {"0": names}
    with laspy.open(one / "dem.las") as f:
        assert read_pairs(f.header) == {0: names}
    capsys.readouterr()
    two = tmp_path / "strip"
    assert main(["dem", paths[0], paths[1], "-o", str(two), *common]) == 0
    assert f"point cloud {two / 'dem.las'}: " in capsys.readouterr().out
    with laspy.open(two / "dem.las") as f:
        assert read_pairs(f.header) == {0: ["3N strip", "3B strip"]}
