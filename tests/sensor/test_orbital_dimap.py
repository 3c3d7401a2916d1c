"""Physical DIMAP ingest: a real Pleiades product (tests/data/dimap, from CNES/shareloc) and a
SPOT-5 DIMAP written from a simulated SPOT-like model."""

import xml.etree.ElementTree as ET
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest

from stereodem.core import geodesy
from stereodem.core.errors import SensorModelError
from stereodem.sensor.io.dimap_physical import read_dimap_physical, write_spot5_dimap
from stereodem.sensor.io.rpc_formats import read_rpc
from stereodem.sensor.models.orbital import TopanLOSModel
from stereodem.sensor.models.pushbroom import PushbroomModel

DATA = Path(__file__).resolve().parents[1] / "data" / "dimap"
PHR = DATA / "PHRDIMAP_P1BP--2018122638935449CP_trimmed.XML"


def test_pleiades_dimap_lands_on_its_own_corner_coordinates():
    m = read_dimap_physical(PHR)
    assert (m.width, m.height) == (40000, 38248)
    root = ET.parse(PHR).getroot()
    vx = root.findall(".//Dataset_Frame/Vertex")
    lon = np.array([float(v.find("LON").text) for v in vx])
    lat = np.array([float(v.find("LAT").text) for v in vx])
    col = np.array([float(v.find("COL").text) for v in vx]) - 1
    row = np.array([float(v.find("ROW").text) for v in vx]) - 1
    h_geoid = float(root.find(".//DTM_Information/Altitudes_List/Altitudes/H_AVERAGE").text)
    h = h_geoid + float(geodesy.geoid_undulation(lon.mean(), lat.mean()))
    lo, la = m.localize(col, row, np.full(4, h))
    err = np.hypot((lo - lon) * 111320 * np.cos(np.radians(lat)), (la - lat) * 110900)
    # 0.5 m pixels; the corners' own heights are not given (relief 466-593 m at 17 deg incidence)
    assert np.max(err) < 20.0
    c, r = m.project(lo, la, np.full(4, h))
    assert np.max(np.abs(c - col)) < 1e-3 and np.max(np.abs(r - row)) < 1e-3


def test_pleiades_physical_model_agrees_with_the_products_rpc():
    """The vendor's RPC in the same file is a fit to its physical model: ours must agree to a
    small fraction of a pixel inside the RPC's height range (85 +- 575 m)."""
    m, rpc = read_dimap_physical(PHR), read_rpc(PHR)
    c, r = np.meshgrid(np.linspace(0, m.width - 1, 11), np.linspace(0, m.height - 1, 11))
    for h in (200.0, 400.0, 600.0):
        lon, lat = m.localize(c, r, h)
        pc, pr = rpc.project(lon, lat, h)
        assert np.max(np.hypot(pc - c, pr - r)) < 0.02


def test_pleiades_dimap_feeds_the_orbital_models():
    """Topan's quadratic EOPs on an agile satellite: Pleiades' attitude is a cubic in time
    (its DIMAP says so); over the 2.8 s strip the missing cubic term is 1.6 urad, 2.2 px of
    0.5 m at the first and last lines, nothing at the centre line."""
    m = read_dimap_physical(PHR)
    t = TopanLOSModel.from_model(m)
    cols, rows = np.meshgrid(np.linspace(0, m.width - 1, 5), np.linspace(0, m.height - 1, 5))
    lon, lat = m.localize(cols, rows, 550.0)
    c, r = t.project(lon, lat, 550.0)
    err = np.hypot(c - cols, r - rows)
    assert np.max(err) < 3.0  # pixels of 0.5 m: 1.5 m
    assert np.max(err[2]) < 0.01  # the centre line is exact


@pytest.fixture()
def spot5(tmp_path):
    """A SPOT-5-like scene (832 km, 5 m, 0.752 ms lines, 10 deg across track) written as DIMAP."""
    ref = PushbroomModel.synthetic(
        31.795,
        41.457,
        width=3000,
        height=3000,
        altitude=832e3,
        gsd=5.0,
        line_period=7.52e-4,
        cross_track_tilt_deg=10.0,
        ephemeris_step=30.0,
    )
    los = TopanLOSModel.from_model(ref)
    eph = ref.ephemeris
    sel = (eph.times > ref.t0 - 150) & (eph.times < ref.t0 + 150)
    t_att = np.arange(ref.t0 - 1.0, ref.t0 + 3.5, 0.125)  # 8 Hz
    rows = (t_att - ref.t0) / ref.line_period
    s = los._series(rows)
    ang = np.stack([s["roll"], s["pitch"], s["yaw"]], -1)
    cols = np.arange(ref.width, dtype=float)
    px, py = los.look_angles(cols)
    path = write_spot5_dimap(
        tmp_path / "METADATA.DIM",
        width=ref.width,
        height=ref.height,
        epoch=datetime(2003, 8, 13, 9, 0, 0),
        ephemeris_times=eph.times[sel],
        positions=eph.positions[sel],
        velocities=eph.velocities[sel],
        attitude_times=t_att,
        angles=ang,
        psi_x=px,
        psi_y=py,
        line_period=ref.line_period,
        center_line=1499.5,
        center_time=ref.t0 + 1499.5 * ref.line_period,
    )
    return ref, path


def test_spot5_dimap_round_trip(spot5):
    ref, path = spot5
    m = read_dimap_physical(path)
    cols, rows = np.meshgrid(np.linspace(0, 2999, 6), np.linspace(0, 2999, 6))
    lon, lat = ref.localize(cols, rows, 800.0)
    c, r = m.project(lon, lat, 800.0)
    assert np.max(np.hypot(c - cols, r - rows)) < 0.01


def test_dimap_without_physical_part(tmp_path):
    p = tmp_path / "RPC_only.XML"
    p.write_text("<Dimap_Document><Rational_Function_Model/></Dimap_Document>")
    with pytest.raises(
        SensorModelError, match="RPC_only.XML: no physical sensor model in this DIMAP"
    ):
        read_dimap_physical(p)
    bad = tmp_path / "broken.DIM"
    bad.write_text("<Dimap_Document><Data_Strip>")
    with pytest.raises(SensorModelError, match="broken.DIM: cannot read DIMAP XML"):
        read_dimap_physical(bad)
