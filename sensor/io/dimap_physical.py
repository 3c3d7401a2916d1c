"""Physical sensor model of SPOT-5 and Pleiades / SPOT 6-7 DIMAP products: ephemeris, attitude,
per-detector look angles and line dating, as a
:class:`~stereodem.sensor.models.pushbroom.PushbroomModel`.

Two schemas are read:

* **Pleiades / SPOT 6-7 DIMAP v2** (``PHR_Dimap_Document`` / ``Dimap_Document`` with
  ``Geometric_Data/.../Sensor_Model_Characteristics``): ephemeris ``Point_List`` (ECEF m, m/s,
  UTC), attitude quaternions as cubic polynomials of ``(t - OFFSET) / SCALE`` (t in UTC seconds
  of the day; ``Q0`` the scalar part; the rotation takes satellite-frame vectors to ECEF),
  ``SENSOR_LINE_PERIOD`` (ms) from ``UTC_Sensor_Model_Range/START``, and the viewing directions
  ``PsiX_Model``/``PsiY_Model`` (polynomials of the 0-based column): the look direction in the
  satellite frame is ``(psi_Y, -psi_X, 1)``, the polynomials being the direction's tangents.
  These conventions were fixed on the real product in ``tests/data/dimap``: against its corner
  coordinates first (the only one of 32 quaternion-order / rotation-direction / axis-sign
  readings that lands within metres; the next is 110 m off), then against the product's own
  RPC (column origin: 1-based columns put every point 1.0 px off; tangents: taking ``tan()``
  of the polynomials leaves a ``psi^3/3`` error of 1.35 px at the swath edges). With them the
  model agrees with the RPC to a few hundredths of a pixel over the image.
* **SPOT-5 DIMAP v1** (``Dimap_Document/Data_Strip``): ``Ephemeris/Points/Point`` (``Location``,
  ``Velocity``, ``TIME``), ``Attitudes/Corrected_Attitudes/Corrected_Attitude`` (``TIME``,
  ``Angles/ROLL, PITCH, YAW`` in rad), ``Sensor_Configuration/Instrument_Look_Angles_List/.../
  Look_Angles`` (``DETECTOR_ID``, ``PSI_X``, ``PSI_Y`` in rad) and ``Time_Stamp``
  (``LINE_PERIOD`` in ms, ``SCENE_CENTER_TIME``, ``SCENE_CENTER_LINE``), with the SPOT Geometry
  Handbook's frames: orbital frame from P and V (Topan Eq. 3.63), ``R_PO = Rx(-pitch)
  Ry(-roll) Rz(yaw)`` and look vector ``(-tan psi_y, tan psi_x, -1)`` (OSSIM / NASA ASP;
  :mod:`stereodem.sensor.models.orbital.topan_los`). No real SPOT-5 physical DIMAP with a
  licence allowing a copy was found; this reader is tested on files written by
  :func:`write_spot5_dimap` from a simulated model.

Both are converted to the pushbroom model's frames: the detectors' sight vectors in an
instrument frame (x along track, z down the boresight) and the attitude as body -> orbital
quaternions sampled along the image time.

DIMAP counts pixels from 1; stereodem from 0 (centre of the first pixel).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from stereodem.core.errors import SensorModelError
from stereodem.core.raster import write_text_atomic
from stereodem.sensor.geo.rotations import orbital_frame
from stereodem.sensor.models.ephemeris import Attitude, Ephemeris
from stereodem.sensor.models.orbital.topan_los import orbital_to_ecef, payload_to_orbital
from stereodem.sensor.models.pushbroom import DetectorArray, PushbroomModel

__all__ = ["read_dimap_physical", "write_spot5_dimap"]


def _time(text, path):
    try:
        return datetime.strptime(text.strip().rstrip("Z")[:26], "%Y-%m-%dT%H:%M:%S.%f")
    except (ValueError, AttributeError):
        try:
            return datetime.strptime(text.strip().rstrip("Z"), "%Y-%m-%dT%H:%M:%S")
        except (ValueError, AttributeError):
            raise SensorModelError(f"{path}: bad DIMAP time {text!r}") from None


def _floats(el, tag, path, n=None):
    node = el.find(tag)
    if node is None or node.text is None:
        raise SensorModelError(f"{path}: DIMAP element {tag} missing")
    try:
        v = np.array([float(x) for x in node.text.split()], float)
    except ValueError:
        raise SensorModelError(f"{path}: DIMAP element {tag} is not numeric") from None
    if n is not None and v.size != n:
        raise SensorModelError(f"{path}: DIMAP element {tag} has {v.size} values, expected {n}")
    return v


def read_dimap_physical(path, *, attitude_step: float = 0.05):
    """The physical model of a SPOT-5 or Pleiades / SPOT 6-7 DIMAP metadata file.

    Parameters
    ----------
    path : str or Path
        The DIMAP XML (``METADATA.DIM``, ``DIM_*.XML``).
    attitude_step : float
        Sampling of polynomial attitudes (Pleiades), seconds.

    Raises
    ------
    SensorModelError
        Unreadable file, or a DIMAP without the physical-model part (an RPC-only file).
    """
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as exc:
        raise SensorModelError(f"{path}: cannot read DIMAP XML ({exc})") from None
    smc = root.find(".//Sensor_Model_Characteristics")
    if smc is not None:
        return _pleiades(root, smc, path, attitude_step)
    if root.find(".//Data_Strip/Ephemeris") is not None:
        return _spot5(root, path)
    raise SensorModelError(
        f"{path}: no physical sensor model in this DIMAP (no "
        "Sensor_Model_Characteristics or Data_Strip/Ephemeris; an RPC-only file?)"
    )


def _size(root, path):
    try:
        return int(root.find(".//Raster_Dimensions/NCOLS").text), int(
            root.find(".//Raster_Dimensions/NROWS").text
        )
    except (AttributeError, ValueError):
        raise SensorModelError(f"{path}: DIMAP Raster_Dimensions/NCOLS, NROWS missing") from None


def _pleiades(root, smc, path, step):
    from stereodem.sensor.models.ephemeris import Ephemeris

    width, height = _size(root, path)
    points = smc.findall("Sensor_Ephemeris/Point_List/Point")
    if len(points) < 2:
        raise SensorModelError(f"{path}: fewer than 2 ephemeris points in Sensor_Ephemeris")
    epoch = _time(points[0].find("UTC_TIME").text, path)

    def sec(dt):
        return (dt - epoch).total_seconds()

    t_eph = np.array([sec(_time(p.find("UTC_TIME").text, path)) for p in points])
    pos = np.array([_floats(p, "LOCATION_VALUES", path, 3) for p in points])
    vel = np.array([_floats(p, "VELOCITY_VALUES", path, 3) for p in points])
    start = _time(smc.find("UTC_Sensor_Model_Range/START").text, path)
    line_period = float(_floats(smc, "SENSOR_LINE_PERIOD", path, 1)[0]) * 1e-3
    t0 = sec(start)
    coef = [
        _floats(smc, f"Sensor_Attitudes/Polynomial_Models/Q{k}/COEFFICIENTS", path)
        for k in range(4)
    ]
    offset = float(_floats(smc, "Sensor_Attitudes/OFFSET", path, 1)[0])
    scale = float(_floats(smc, "Sensor_Attitudes/SCALE", path, 1)[0])
    day = epoch.hour * 3600 + epoch.minute * 60 + epoch.second + epoch.microsecond * 1e-6
    t_att = np.arange(t0 - 0.5, t0 + height * line_period + 0.5, step)
    x = (t_att + day - offset) / scale
    q = np.stack([np.polynomial.polynomial.polyval(x, c) for c in coef], -1)  # Q0 scalar
    sat_to_ecef = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()
    cx = _floats(smc, "Sensor_Viewing_Model/Viewing_Directions/PsiX_Model/COEFFICIENTS", path)
    cy = _floats(smc, "Sensor_Viewing_Model/Viewing_Directions/PsiY_Model/COEFFICIENTS", path)
    cols = np.linspace(0.0, width - 1.0, 41)
    # the viewing-direction polynomials take the 0-based column (checked against the
    # product's own RPC: 1-based columns put every point 1.0 px off)
    psi_x = np.polynomial.polynomial.polyval(cols, cx)
    psi_y = np.polynomial.polynomial.polyval(cols, cy) * np.ones_like(cols)
    # the polynomials are the direction's tangents (checked against the product's RPC: taking
    # tan() of them leaves a psi^3/3 error, 1.35 px at the swath edges)
    sight = np.stack([psi_y, -psi_x, np.ones_like(cols)], -1)  # satellite frame
    eph = Ephemeris(t_eph, pos, vel)
    return _pushbroom(width, height, t0, line_period, eph, t_att, sat_to_ecef, sight, cols, path)


def _spot5(root, path):
    width, height = _size(root, path)
    ds = root.find(".//Data_Strip")
    points = ds.findall("Ephemeris/Points/Point")
    if len(points) < 2:
        raise SensorModelError(f"{path}: fewer than 2 ephemeris points in Data_Strip/Ephemeris")
    epoch = _time(points[0].find("TIME").text, path)

    def sec(text):
        return (_time(text, path) - epoch).total_seconds()

    t_eph = np.array([sec(p.find("TIME").text) for p in points])
    pos = np.array([[float(p.find(f"Location/{a}").text) for a in "XYZ"] for p in points])
    vel = np.array([[float(p.find(f"Velocity/{a}").text) for a in "XYZ"] for p in points])
    att = ds.findall("Attitudes/Corrected_Attitudes/Corrected_Attitude")
    if len(att) < 2:
        raise SensorModelError(f"{path}: fewer than 2 attitude samples in Corrected_Attitudes")
    t_att = np.array([sec(a.find("TIME").text) for a in att])
    ang = np.array(
        [[float(a.find(f"Angles/{k}").text) for k in ("ROLL", "PITCH", "YAW")] for a in att]
    )
    looks = ds.findall(
        ".//Instrument_Look_Angles_List/Instrument_Look_Angles/Look_Angles_List/Look_Angles"
    )
    if len(looks) < 2:
        raise SensorModelError(f"{path}: no per-detector Look_Angles in Sensor_Configuration")
    det = np.array([float(a.find("DETECTOR_ID").text) for a in looks]) - 1.0
    psi_x = np.array([float(a.find("PSI_X").text) for a in looks])
    psi_y = np.array([float(a.find("PSI_Y").text) for a in looks])
    ts = ds.find("Sensor_Configuration/Time_Stamp")
    if ts is None:
        raise SensorModelError(f"{path}: Sensor_Configuration/Time_Stamp missing")
    line_period = float(ts.find("LINE_PERIOD").text) * 1e-3
    t_c = sec(ts.find("SCENE_CENTER_TIME").text)
    r_c = float(ts.find("SCENE_CENTER_LINE").text) - 1.0
    t0 = t_c - r_c * line_period
    eph = Ephemeris(t_eph, pos, vel)
    p, v = eph.state(t_att)
    sat_to_ecef = orbital_to_ecef(p, v) @ payload_to_orbital(ang[:, 0], ang[:, 1], ang[:, 2])
    sight = np.stack([-np.tan(psi_y), np.tan(psi_x), -np.ones_like(psi_x)], -1)  # payload frame
    return _pushbroom(width, height, t0, line_period, eph, t_att, sat_to_ecef, sight, det, path)


#: Payload/satellite frame -> pushbroom instrument frame (x along track, y across, z down).
_TO_INSTRUMENT = {True: np.eye(3), False: np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, -1]])}


def _pushbroom(width, height, t0, line_period, eph, t_att, sat_to_ecef, sight, cols, path):
    """PushbroomModel of the DIMAP file ``path`` (named after it): image size (pixels), first
    line's time ``t0`` and ``line_period`` (s), the ECEF :class:`Ephemeris` ``eph``, the
    satellite -> ECEF rotations ``sat_to_ecef`` (n, 3, 3) at times ``t_att`` (s) and the sight
    vectors (satellite or payload frame, z along the boresight up or down) of the detectors at
    columns ``cols`` (0-based)."""
    z_down = bool(np.all(sight[:, 2] > 0))
    D = _TO_INSTRUMENT[z_down]  # instrument = D @ satellite
    inst = sight @ D.T
    p, v = eph.state(t_att)
    body_to_orb = np.swapaxes(orbital_frame(p, v), -1, -2) @ sat_to_ecef @ D.T
    quat = Rotation.from_matrix(body_to_orb).as_quat()
    order = np.argsort(cols)
    return PushbroomModel(
        width=width,
        height=height,
        ephemeris=eph,
        detectors=DetectorArray.from_sight_vectors(inst[order], np.asarray(cols)[order]),
        line_period=line_period,
        t0=t0,
        attitude=Attitude(t_att, quaternions=quat),
        name=path.stem,
    )


def write_spot5_dimap(
    path,
    *,
    width,
    height,
    epoch,
    ephemeris_times,
    positions,
    velocities,
    attitude_times,
    angles,
    psi_x,
    psi_y,
    line_period,
    center_line,
    center_time,
    overwrite=False,
):
    """Write a SPOT-5 DIMAP v1 physical-model file (the subset :func:`read_dimap_physical`
    reads), e.g. from a simulated scene. Times are seconds after ``epoch`` (a
    :class:`datetime.datetime`); ``line_period`` in seconds; ``center_line`` 0-based;
    angles in radians (roll, pitch, yaw per row; SPOT frames, see the module docstring)."""

    def ts(t):
        return (epoch + timedelta(seconds=float(t))).strftime("%Y-%m-%dT%H:%M:%S.%f")

    out = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        "<Dimap_Document>",
        f"<Raster_Dimensions><NCOLS>{int(width)}</NCOLS><NROWS>{int(height)}</NROWS><NBANDS>1</NBANDS>"
        "</Raster_Dimensions>",
        "<Data_Strip>",
        "<Ephemeris><Points>",
    ]
    for t, p, v in zip(ephemeris_times, positions, velocities):
        out.append(
            f"<Point><Location><X>{p[0]:.4f}</X><Y>{p[1]:.4f}</Y><Z>{p[2]:.4f}</Z></Location>"
            f"<Velocity><X>{v[0]:.7f}</X><Y>{v[1]:.7f}</Y><Z>{v[2]:.7f}</Z></Velocity>"
            f"<TIME>{ts(t)}</TIME></Point>"
        )
    out.append("</Points></Ephemeris><Attitudes><Corrected_Attitudes>")
    for t, a in zip(attitude_times, angles):
        out.append(
            f"<Corrected_Attitude><TIME>{ts(t)}</TIME><Angles><ROLL>{a[0]:.12e}</ROLL>"
            f"<PITCH>{a[1]:.12e}</PITCH><YAW>{a[2]:.12e}</YAW></Angles></Corrected_Attitude>"
        )
    out.append(
        "</Corrected_Attitudes></Attitudes><Sensor_Configuration><Time_Stamp>"
        f"<LINE_PERIOD>{line_period * 1e3:.12f}</LINE_PERIOD>"
        f"<SCENE_CENTER_TIME>{ts(center_time)}</SCENE_CENTER_TIME>"
        f"<SCENE_CENTER_LINE>{center_line + 1:.3f}</SCENE_CENTER_LINE></Time_Stamp>"
        "<Instrument_Look_Angles_List><Instrument_Look_Angles><Look_Angles_List>"
    )
    for k, (px, py) in enumerate(zip(psi_x, psi_y)):
        out.append(
            f"<Look_Angles><DETECTOR_ID>{k + 1}</DETECTOR_ID><PSI_X>{px:.15e}</PSI_X>"
            f"<PSI_Y>{py:.15e}</PSI_Y></Look_Angles>"
        )
    out.append(
        "</Look_Angles_List></Instrument_Look_Angles></Instrument_Look_Angles_List>"
        "</Sensor_Configuration></Data_Strip></Dimap_Document>"
    )
    return write_text_atomic(path, "\n".join(out) + "\n", overwrite=overwrite)
