"""A two-image bundle with Topan's orbital model (simulated ASTER 3N/3B whose ephemeris and
attitude carry biases and drifts): GCPs, tie points and independent check points in both
images, through the adjustment engine's bundle."""

import numpy as np
import pytest

from stereodem.core import geodesy
from stereodem.sensor.estimation.adjust import bundle_adjust
from stereodem.sensor.geo.intersect import intersect_rays
from stereodem.sensor.io.gcps import ControlPoints
from stereodem.sensor.models.orbital import TopanLOSModel
from stereodem.sensor.models.orbital.topan_los import eop_set
from stereodem.sensor.simulation.control_points import (
    aster_pair_scene,
    points_at_pixels,
    random_pixels,
)

NOISE = 0.3


@pytest.fixture(scope="module")
def pair():
    mL, mR, tL, tR, dem = aster_pair_scene()
    rng = np.random.default_rng(4)
    P = points_at_pixels(tL, dem, *random_pixels(tL, 300, seed=4), noise_px=NOISE, seed=4)
    cR, rR = tR.project(P["lon"], P["lat"], P["h"])
    ok = np.isfinite(cR) & (cR > 20) & (cR < tR.width - 21) & (rR > 20) & (rR < tR.height - 21)
    idx = np.flatnonzero(ok)
    cRn, rRn = cR + rng.normal(0, NOISE, cR.size), rR + rng.normal(0, NOISE, cR.size)
    g, chk, tie = idx[:8], idx[8:48], idx[48:148]

    def points(col, row):
        sel = np.concatenate([g, chk])
        role = ["gcp"] * g.size + ["check"] * chk.size
        return ControlPoints(
            [f"P{k}" for k in sel],
            P["lon"][sel],
            P["lat"][sel],
            P["h"][sel],
            col[sel],
            row[sel],
            role=role,
        )

    ties = np.stack([P["col"][tie], P["row"][tie], cRn[tie], rRn[tie]], -1)
    return dict(
        meta=(mL, mR),
        gcps=(points(P["col"], P["row"]), points(cRn, rRn)),
        ties=ties,
        chk=(P["col"][chk], P["row"][chk], cRn[chk], rRn[chk]),
        truth=np.stack(geodesy.geodetic_to_ecef(P["lon"][chk], P["lat"][chk], P["h"][chk]), -1),
    )


def _ground_rmse(left, right, d):
    c1, r1, c2, r2 = d["chk"]
    p, _ = intersect_rays(*left.rays(c1, r1), *right.rays(c2, r2))
    return float(np.sqrt(np.mean(np.sum((p - d["truth"]) ** 2, -1))))  # metres, 3-D


@pytest.mark.slow
def test_pair_bundle_with_orbital_models(pair):
    mL, mR = pair["meta"]
    before = _ground_rmse(mL, mR, pair)
    kw = dict(gcps=pair["gcps"], sigma_px=NOISE, snooping=False)
    rig = bundle_adjust(mL, mR, pair["ties"], names=("attitude-bias-drift",) * 2, **kw)
    ref = _ground_rmse(rig.left, rig.right, pair)
    tl, tr = TopanLOSModel.from_model(mL), TopanLOSModel.from_model(mR)
    lin = bundle_adjust(tl, tr, pair["ties"], names=(eop_set("A_0") + eop_set("A_1"),) * 2, **kw)
    quad = bundle_adjust(tl, tr, pair["ties"], names=("eop-poly2",) * 2, **kw)
    got_lin, got_quad = (
        _ground_rmse(lin.left, lin.right, pair),
        _ground_rmse(quad.left, quad.right, pair),
    )
    assert before > 5 * ref  # the metadata is 100 m off in height
    # attitude offsets and rates of Topan's model: the rigorous model's ICP accuracy
    assert got_lin < 1.1 * ref
    # the full second-order set A with 8 GCPs: over-parameterised (worse conditioned, worse ICPs)
    assert quad.condition > 3 * lin.condition and got_quad > got_lin
