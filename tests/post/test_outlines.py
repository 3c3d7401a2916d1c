"""One numbering of the polygons of an outlines file (``post.masks.read_outlines``), shared by
``assess --outlines`` (report.json's ``polygon``, report.md's ``#label``) and ``stack
--outlines`` (volumes.json's ``id``): the polygon's own ``id``/``name`` attribute, else its
1-based feature number in the file."""

from __future__ import annotations

import json

import numpy as np
import pytest
from affine import Affine
from pyproj import CRS

from stereodem.core.grid import MapGrid
from stereodem.post.error_analysis import markdown_lines
from stereodem.post.masks import read_outlines
from stereodem.post.spatialstats import VariogramModel
from stereodem.post.volumes import outline_changes

GRID = MapGrid(Affine(30, 0, 500000, 0, -30, 4400000), 40, 30, CRS.from_epsg(32637))


def _square(c0, r0, n=8):
    t = GRID.transform
    return [
        [
            list(t @ (c, r))
            for c, r in [(c0, r0), (c0 + n, r0), (c0 + n, r0 + n), (c0, r0 + n), (c0, r0)]
        ]
    ]


def _geojson(path, props):
    """Features: a point (not a polygon) first, then one square per ``props`` entry."""
    feats = [
        {
            "type": "Feature",
            "properties": props[0],
            "geometry": {"type": "Point", "coordinates": [500100.0, 4399900.0]},
        }
    ] + [
        {
            "type": "Feature",
            "properties": p,
            "geometry": {"type": "Polygon", "coordinates": _square(2 + 10 * k, 2)},
        }
        for k, p in enumerate(props)
    ]
    crs = {"type": "name", "properties": {"name": "urn:ogc:def:crs:EPSG::32637"}}
    path.write_text(json.dumps({"type": "FeatureCollection", "crs": crs, "features": feats}))
    return path


@pytest.mark.parametrize(
    "props, labels",
    [
        ([{"area": 1.0}, {"area": 2.0}], [2, 3]),  # no name: 1-based feature numbers
        ([{"ID": 7, "name": "a"}, {"ID": 9, "name": "b"}], [7, 9]),  # id first
        ([{"name": "Rhone"}, {"name": "Aletsch"}], ["Rhone", "Aletsch"]),
        ([{"name": "x"}, {"name": "x"}], [2, 3]),  # not unique: numbers
        ([{"name": "x"}, {"name": None}], [2, 3]),  # one missing: numbers
    ],
)
def test_outlines_are_labelled_by_one_rule_in_assess_and_stack(tmp_path, props, labels):
    path = _geojson(tmp_path / "o.geojson", props)
    outlines = read_outlines(path, GRID.crs)
    assert [o.label for o in outlines] == labels
    # stack: volumes.json's ids
    rate = np.full(GRID.shape, -1.0, np.float32)
    ref = np.full(GRID.shape, 100.0)
    model = VariogramModel(np.array([100.0]), np.array([1.0]))
    vols = outline_changes(rate, np.full_like(rate, 0.5), ref, outlines, GRID, model)
    assert [v["id"] for v in vols] == labels
    # assess: report.json's polygon and the report's line
    section = {
        "stable_cells": 1,
        "nmad_stable": 1.0,
        "variogram": {"model": {"ranges_m": [100.0], "sills": [1.0]}},
        "heteroscedasticity": {},
        "area_means": [
            dict(
                file=str(path),
                polygon=o.label,
                mean_dh=0.0,
                sigma_mean=1.0,
                n_cells=64,
                n_effective=2.0,
                sigma_naive=0.1,
            )
            for o in outlines
        ],
    }
    md = "\n".join(markdown_lines(section))
    for lab in labels:
        assert f"o.geojson #{lab}: mean dh" in md
