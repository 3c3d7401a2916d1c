"""End to end (issue 27): ASTER L1A granules simulated at four dates with a thinning inside an
outline -> ``stereodem dem`` on each -> ``stereodem stack`` (dates from the DEMs' metadata) ->
the rate map against the truth. Slow (about a minute on two cores)."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio
import shapely

from stereodem.cli import main
from stereodem.core.dem import DEM
from stereodem.core.stats import nmad
from stereodem.post import warp
from stereodem.post.synthetic_series import write_polygons
from stereodem.sensor.simulation.multidate import simulate_granule_series, thinning_truth


@pytest.mark.slow
def test_granules_to_rate_map(tmp_path, capsys):
    dem = DEM.bundled()
    dates = ["2004-08-01", "2009-07-20", "2014-08-05", "2019-07-28"]
    outline = shapely.Point(40.425, 39.58).buffer(0.02)
    recs = simulate_granule_series(
        dem,
        dates,
        outline_lonlat=outline,
        t_ref=2000.13,
        out_dir=tmp_path / "granules",
        size=(300, 300),
        seed=5,
    )
    dems = []
    for r in recs:
        o = tmp_path / "runs" / r["date"]
        assert main(["-q", "dem", str(r["granule"]), "-o", str(o), "--workers", "2"]) == 0
        dems.append(str(o / "dem.tif"))
    truth0 = DEM.from_file(recs[0]["folder"] / "truth_dem.tif")
    g = truth0.grid
    h_ref = warp.to_grid(
        dem.heights, dem.transform, dem.crs, g.transform, g.crs, g.shape, resampling="cubic"
    )
    ref = DEM(h_ref, g.transform, g.crs, "geoid", None).to_reference("ellipsoid")
    ref.write(tmp_path / "ref.tif")
    gl = write_polygons(tmp_path / "outline.gpkg", [outline], "EPSG:4326")
    out = tmp_path / "stack"
    rc = main(
        [
            "stack",
            *dems,
            "--ref",
            str(tmp_path / "ref.tif"),
            "--exclude",
            str(gl),
            "--workers",
            "2",
            "-o",
            str(out),
        ]
    )
    err = capsys.readouterr().err
    assert rc == 0, err
    rate = rasterio.open(out / "rate.tif").read(1)
    truth = thinning_truth(dem.grid, dem.heights, outline, t_ref=2000.13)
    true_rate = warp.to_grid(
        truth.rate, dem.transform, dem.crs, g.transform, g.crs, g.shape, resampling="nearest"
    )
    inside = true_rate < 0
    fin = np.isfinite(rate)
    assert (inside & fin).sum() > 5000
    assert abs(np.nanmean(rate[inside] - true_rate[inside])) < 0.1
    assert nmad(rate[~inside & fin]) < 0.2
