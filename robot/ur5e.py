"""UR5e kinematics in plain numpy: nominal DH forward kinematics, a numerical inverse, and pose helpers.

Poses are ur_rtde's ``[x, y, z, rx, ry, rz]`` (m, rotation vector in rad) in the base frame; ``T`` denotes a 4x4
homogeneous transform. The DH parameters are the nominal ones (shared/REFERENCE.md); real arms are individually
calibrated, so poses computed here agree with a real controller's to a few millimetres only.
"""
from __future__ import annotations

import math

import numpy as np

D = np.array([0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996])
A = np.array([0.0, -0.425, -0.3922, 0.0, 0.0, 0.0])
ALPHA = np.array([math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0])
_CA, _SA = np.cos(ALPHA), np.sin(ALPHA)

# Tool pointing straight down (tool z = -base z), elbow up: a convenient home/seed configuration.
Q_HOME = np.array([0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0])


def rotvec_to_matrix(r) -> np.ndarray:
    r = np.asarray(r, dtype=float)
    th = math.sqrt(float(r @ r))
    if th < 1e-12:
        return np.eye(3)
    k = r / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * (K @ K)


_PI_BAND = 1e-6


def matrix_to_rotvec(R) -> np.ndarray:
    """Rotation vector of a rotation matrix, accurate to round-off at every angle including just short of pi (the
    tool-down orientation): the angle from atan2 (not acos), the axis near pi from the symmetric part.

    Within ``_PI_BAND`` of pi the direction is kept canonical (largest component positive) so that poses a round-off
    apart do not flip sign (r and -r are both ~pi); the length is then th or 2 pi - th, whichever makes the vector
    the exact rotation, so it may exceed pi by up to ``_PI_BAND`` (a valid rotation vector for URScript too)."""
    R = np.asarray(R, dtype=float)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    c = 0.5 * (np.trace(R) - 1.0)
    th = math.atan2(0.5 * float(np.linalg.norm(w)), c)
    if th < 1e-9:
        return w * 0.5
    if th > 0.5 * math.pi:      # axis from the symmetric part, sign from the skew part
        kk = (0.5 * (R + R.T) - c * np.eye(3)) / (1.0 - c)
        i = int(np.argmax(np.diag(kk)))
        k = kk[:, i] / math.sqrt(kk[i, i])
        k /= np.linalg.norm(k)              # k[i] > 0
        if math.pi - th < _PI_BAND:          # the same rotation as (k if k @ w >= 0 else -k) * th, exactly
            return k * (th if k @ w >= 0 else 2 * math.pi - th)
        return (k if k @ w >= 0 else -k) * th
    return w * (th / (2 * math.sin(th)))


def pose_to_T(pose) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rotvec_to_matrix(pose[3:6])
    T[:3, 3] = pose[:3]
    return T


def T_to_pose(T) -> list[float]:
    return [float(v) for v in (*T[:3, 3], *matrix_to_rotvec(T[:3, :3]))]


def pose_trans(a, b) -> list[float]:
    """Compose poses: ``b`` expressed in ``a``'s frame (URScript's pose_trans)."""
    return T_to_pose(pose_to_T(a) @ pose_to_T(b))


def pose_inv(p) -> list[float]:
    return T_to_pose(np.linalg.inv(pose_to_T(p)))


def rotation_angle(Ra, Rb) -> float:
    """Angle (rad) of the rotation taking Ra to Rb."""
    c = max(-1.0, min(1.0, 0.5 * (np.trace(np.asarray(Ra).T @ np.asarray(Rb)) - 1.0)))
    return math.acos(c)


def slerp_matrix(Ra, Rb, u: float) -> np.ndarray:
    """Rotation a fraction ``u`` of the way from Ra to Rb (geodesic)."""
    rel = matrix_to_rotvec(np.asarray(Ra).T @ np.asarray(Rb))
    return np.asarray(Ra) @ rotvec_to_matrix(u * rel)


def fk_flange(q) -> np.ndarray:
    """Flange transform in the base frame for joint angles ``q`` (rad)."""
    T = np.eye(4)
    for i in range(6):
        ct, st = math.cos(q[i]), math.sin(q[i])
        ca, sa = _CA[i], _SA[i]
        Ti = np.array([[ct, -st * ca, st * sa, A[i] * ct],
                       [st, ct * ca, -ct * sa, A[i] * st],
                       [0.0, sa, ca, D[i]],
                       [0.0, 0.0, 0.0, 1.0]])
        T = T @ Ti
    return T


def fk(q, tcp_offset=(0, 0, 0, 0, 0, 0)) -> list[float]:
    """TCP pose for joint angles ``q`` and a TCP offset (ur_rtde's setTcp pose)."""
    return T_to_pose(fk_flange(q) @ pose_to_T(tcp_offset))


def _err(T, Tgoal) -> np.ndarray:
    dp = Tgoal[:3, 3] - T[:3, 3]
    dr = T[:3, :3] @ matrix_to_rotvec(T[:3, :3].T @ Tgoal[:3, :3])
    return np.concatenate([dp, dr])


def ik(pose, q_seed=Q_HOME, tcp_offset=(0, 0, 0, 0, 0, 0), tol=1e-9, max_iter=100):
    """Joint angles reaching ``pose`` near ``q_seed`` (damped least squares); None if it does not converge."""
    Tgoal = pose_to_T(pose) @ np.linalg.inv(pose_to_T(tcp_offset))
    q = np.array(q_seed, dtype=float)
    lam, h = 1e-4, 1e-7
    for _ in range(max_iter):
        T = fk_flange(q)
        e = _err(T, Tgoal)
        if float(e @ e) < tol * tol:
            return q
        J = np.empty((6, 6))
        for j in range(6):
            dq = q.copy()
            dq[j] += h
            Tj = fk_flange(dq)
            J[:3, j] = (Tj[:3, 3] - T[:3, 3]) / h
            J[3:, j] = T[:3, :3] @ matrix_to_rotvec(T[:3, :3].T @ Tj[:3, :3]) / h
        q = q + np.linalg.solve(J.T @ J + lam * np.eye(6), J.T @ e)
    e = _err(fk_flange(q), Tgoal)
    return q if float(e @ e) < 1e-12 else None
