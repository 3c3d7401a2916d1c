"""Rotation matrices and the orbital reference frame.

Conventions (Bettemir 2006, Ch. 2; ASTER L1A, notes §4.2)
--------------------------------------------------------
* ``R1, R2, R3`` are *passive* (frame) rotations about x, y, z:
  ``R3(t) = [[c, s, 0], [-s, c, 0], [0, 0, 1]]``.
* Attitude of the body frame relative to the orbital frame is roll ``omega`` (about x, along
  track), pitch ``phi`` (about y) and yaw ``kappa`` (about z), applied as Bettemir Eq. 4.7:
  ``D_O = Rz(kappa) Rx(omega) Ry(phi) D_B`` (active rotations), radians.
* Orbital frame (rows in ECEF): ``z = -r/|r|`` (geocentric nadir), ``y = -(r x v)/|r x v|``
  (negative orbit normal), ``x = y x z`` (about the flight direction), with ``v`` the
  **inertial** velocity expressed in ECEF axes, ``v_in = v_ecef + omega_E x r`` (notes
  aster-l1a-format §4.3; Bettemir Eq. 4.24 has the sign of this correction wrong).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from stereodem.core.geodesy import OMEGA_EARTH


def R1(t):
    """Passive rotation about x by angle ``t`` (rad); broadcasts to (..., 3, 3)."""
    t = np.asarray(t, float)
    c, s, o, z = np.cos(t), np.sin(t), np.ones_like(t), np.zeros_like(t)
    return np.stack(
        [np.stack([o, z, z], -1), np.stack([z, c, s], -1), np.stack([z, -s, c], -1)], -2
    )


def R2(t):
    """Passive rotation about y by angle ``t`` (rad)."""
    t = np.asarray(t, float)
    c, s, o, z = np.cos(t), np.sin(t), np.ones_like(t), np.zeros_like(t)
    return np.stack(
        [np.stack([c, z, -s], -1), np.stack([z, o, z], -1), np.stack([s, z, c], -1)], -2
    )


def R3(t):
    """Passive rotation about z by angle ``t`` (rad)."""
    t = np.asarray(t, float)
    c, s, o, z = np.cos(t), np.sin(t), np.ones_like(t), np.zeros_like(t)
    return np.stack(
        [np.stack([c, s, z], -1), np.stack([-s, c, z], -1), np.stack([z, z, o], -1)], -2
    )


def body_to_orbital(roll, pitch, yaw):
    """Matrix of Bettemir Eq. 4.7, ``D_O = M @ D_B``, from roll/pitch/yaw in radians.

    Equal to ``Rz(yaw) Rx(roll) Ry(pitch)`` with active rotations, i.e.
    ``[R2(pitch) R1(roll) R3(yaw)]^T`` with passive ones.
    """
    return np.swapaxes(R2(pitch) @ R1(roll) @ R3(yaw), -1, -2)


def inertial_velocity(r_ecef, v_ecef):
    """Inertial velocity in ECEF axes, ``v + omega_E x r`` (m/s)."""
    r = np.asarray(r_ecef, float)
    w = np.array([0.0, 0.0, OMEGA_EARTH])
    return np.asarray(v_ecef, float) + np.cross(w, r)


def orbital_frame(r_ecef, v_ecef, *, inertial: bool = True):
    """Orbital frame axes in ECEF.

    Parameters
    ----------
    r_ecef, v_ecef : array_like (..., 3)
        Satellite position (m) and Earth-fixed velocity (m/s) in ECEF.
    inertial : bool
        Build the frame with the inertial velocity (default, correct for ASTER and for the
        standard orbital reference frame). ``False`` uses ``v_ecef`` as given (it must then
        already be inertial).

    Returns
    -------
    M : ndarray (..., 3, 3)
        Columns are the orbital x, y, z axes in ECEF, so ``d_ecef = M @ d_orbital``.
    """
    r = np.asarray(r_ecef, float)
    v = inertial_velocity(r, v_ecef) if inertial else np.asarray(v_ecef, float)
    z = -r / np.linalg.norm(r, axis=-1, keepdims=True)
    h = np.cross(r, v)
    y = -h / np.linalg.norm(h, axis=-1, keepdims=True)
    x = np.cross(y, z)
    return np.stack([x, y, z], axis=-1)


def quaternion_to_matrix(q):
    """Rotation matrix of unit quaternions ``q = (q1, q2, q3, q4)`` with scalar ``q4`` last.

    Uses scipy's convention (active rotation, scalar last): ``M @ v`` rotates ``v``.
    """
    q = np.asarray(q, float)
    return Rotation.from_quat(q.reshape(-1, 4)).as_matrix().reshape(q.shape[:-1] + (3, 3))
