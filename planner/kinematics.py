"""UR5e kinematics: forward kinematics as CasADi SX (compiled to a Function once), a closed-form inverse in numpy
(the NLP's seed), the IK-branch indicators, and pose conversions for ur_rtde.

Conventions: standard DH (``Rz(q) Tz(d) Tx(a) Rx(alpha)``) with the nominal UR5e parameters of REFERENCE.md; the
chain ends at the flange (``tool0``); the TCP is the flange frame times ``tcp_offset`` (a ur_rtde pose, as given to
``setTcp``). Poses are ``[x, y, z, rx, ry, rz]`` (m, rotation vector) in the base frame.

IK branches (Hawkins' closed form has up to 8 solutions): ``shoulder`` = sign of the wrist centre's reach along the
arm's plane (+1: the usual pose, upper and fore arm reaching away from the base; -1: over the shoulder),
``elbow`` = sign(sin q3), ``wrist`` = sign(sin q5).
Their magnitudes measure the distance from the three UR singularities (shoulder: wrist centre on the cylinder
r = d4 about the base axis; elbow: arm stretched or folded; wrist: joint 6 parallel to joint 4).
"""
from __future__ import annotations

import functools
import math

import casadi as ca
import numpy as np
from scipy.spatial.transform import Rotation

D1, A2, A3, D4, D5, D6 = 0.1625, -0.425, -0.3922, 0.1333, 0.0997, 0.0996
DH_A = (0.0, A2, A3, 0.0, 0.0, 0.0)
DH_D = (D1, 0.0, 0.0, D4, D5, D6)
DH_ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)
# exact cos/sin of the twists (0, +-1) keep the expression graph small and free of 6e-17 terms
_CA = tuple(float(round(math.cos(a))) for a in DH_ALPHA)
_SA = tuple(float(round(math.sin(a))) for a in DH_ALPHA)

JOINT_LOWER_RAD = np.array([-2 * math.pi, -2 * math.pi, -math.pi, -2 * math.pi, -2 * math.pi, -2 * math.pi])
JOINT_UPPER_RAD = -JOINT_LOWER_RAD
MAX_JOINT_SPEED_RAD_S = math.pi      # every UR5e joint
MAX_JOINT_ACCEL_RAD_S2 = 40.0        # ur_rtde rejects more
REACH_M = 0.85
HOME_RAD = np.array([0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0])  # tool down, elbow up
DEFAULT_BRANCH = (1, 1, -1)          # (shoulder, elbow, wrist) of HOME_RAD


class KinematicsError(ValueError):
    """A pose the arm cannot reach (the message names it)."""


# ---------------------------------------------------------------------------------------------------------------
# CasADi (SX) forward kinematics

def _dh_sx(q, i):
    c, s = ca.cos(q), ca.sin(q)
    ca_, sa = _CA[i], _SA[i]
    a, d = DH_A[i], DH_D[i]
    return ca.vertcat(ca.horzcat(c, -s * ca_, s * sa, a * c),
                      ca.horzcat(s, c * ca_, -c * sa, a * s),
                      ca.horzcat(0, sa, ca_, d),
                      ca.horzcat(0, 0, 0, 1))


@functools.lru_cache(maxsize=None)
def fk_function() -> ca.Function:
    """``fk(q[6], T_tcp[4x4]) -> (T_base_tcp[4x4], p_wrist[3])``, built once per process.

    ``p_wrist`` is the wrist centre (origin of DH frame 4 shifted onto joint 5's axis: the flange origin minus d6 along
    the flange z axis), used for the shoulder-singularity indicator."""
    q = ca.SX.sym("q", 6)
    T_tcp = ca.SX.sym("T_tcp", 4, 4)
    T = ca.SX.eye(4)
    for i in range(6):
        T = T @ _dh_sx(q[i], i)
    p_wrist = T[:3, 3] - D6 * T[:3, 2]
    return ca.Function("ur5e_fk", [q, T_tcp], [T @ T_tcp, p_wrist], ["q", "T_tcp"], ["T", "p_wrist"])


def branch_indicators_sx(q, p_wrist):
    """(shoulder [m], elbow, wrist) indicators as CasADi expressions; see the module docstring."""
    return ca.vertcat(-(p_wrist[0] * ca.cos(q[0]) + p_wrist[1] * ca.sin(q[0])), ca.sin(q[2]), ca.sin(q[4]))


# ---------------------------------------------------------------------------------------------------------------
# numpy helpers

def dh_matrix(q: float, i: int) -> np.ndarray:
    c, s, ca_, sa, a, d = math.cos(q), math.sin(q), _CA[i], _SA[i], DH_A[i], DH_D[i]
    return np.array([[c, -s * ca_, s * sa, a * c], [s, c * ca_, -c * sa, a * s], [0, sa, ca_, d], [0, 0, 0, 1.0]])


def fk_flange(q) -> np.ndarray:
    T = np.eye(4)
    for i in range(6):
        T = T @ dh_matrix(float(q[i]), i)
    return T


def fk(q, tcp_offset=(0, 0, 0, 0, 0, 0)) -> np.ndarray:
    """Base->TCP transform (numpy, same DH as the CasADi Function)."""
    return fk_flange(q) @ pose_to_matrix(tcp_offset)


def fk_batch(Q, tcp_offset=(0, 0, 0, 0, 0, 0)) -> tuple[np.ndarray, np.ndarray]:
    """Many configurations (m, 6) at once through the compiled Function: (T (m, 4, 4), wrist centres (m, 3))."""
    Q = np.asarray(Q, dtype=float).reshape(-1, 6)
    T, pw = fk_function()(Q.T, pose_to_matrix(tcp_offset))
    m = Q.shape[0]
    return np.array(T).reshape(4, m, 4).transpose(1, 0, 2), np.array(pw).T.reshape(m, 3)


def rigid_inv(T) -> np.ndarray:
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


def branch_indicators(q) -> np.ndarray:
    T = fk_flange(q)
    pw = T[:3, 3] - D6 * T[:3, 2]
    return np.array([-(pw[0] * math.cos(q[0]) + pw[1] * math.sin(q[0])), math.sin(q[2]), math.sin(q[4])])


def pose_to_matrix(pose) -> np.ndarray:
    pose = np.asarray(pose, dtype=float)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(pose[3:6]).as_matrix()
    T[:3, 3] = pose[:3]
    return T


def matrix_to_pose(T, near=None) -> list[float]:
    """ur_rtde pose (SciPy's robust conversion, fine near pi). A tool pointing down is a rotation by nearly pi, where
    r and r (1 - 2 pi / |r|) describe (almost) the same rotation with opposite-looking vectors: given ``near`` (a
    previous pose), the equivalent rotation vector closest to its vector is returned, so neighbours read alike."""
    T = np.asarray(T, dtype=float)
    r = Rotation.from_matrix(T[:3, :3]).as_rotvec()
    if near is not None:
        th = float(np.linalg.norm(r))
        if th > 1e-9:
            alt = r * (1.0 - 2.0 * math.pi / th)
            ref = np.asarray(near, dtype=float)[3:6]
            if np.linalg.norm(alt - ref) < np.linalg.norm(r - ref):
                r = alt
    return [*map(float, T[:3, 3]), *map(float, r)]


def rotation_angle(Ra, Rb) -> float:
    """Angle of Ra^T Rb in rad."""
    c = (np.trace(np.asarray(Ra).T @ np.asarray(Rb)) - 1.0) / 2.0
    return float(math.acos(max(-1.0, min(1.0, c))))


# ---------------------------------------------------------------------------------------------------------------
# closed-form inverse kinematics (Hawkins 2013, "Analytic inverse kinematics for the Universal Robots UR-5/UR-10")

def ik_flange(T06, verify: bool = True) -> np.ndarray:
    """All closed-form solutions (k x 6, k <= 8, angles in (-pi, pi]) for a base->flange transform; may be empty.
    ``verify`` drops any that forward kinematics does not map back onto T06 (to 1e-7)."""
    T06 = np.asarray(T06, dtype=float)
    sols = []
    p05 = T06[:3, 3] - D6 * T06[:3, 2]
    r = math.hypot(p05[0], p05[1])
    if r < abs(D4):
        return np.zeros((0, 6))
    psi, phi = math.atan2(p05[1], p05[0]), math.acos(D4 / r)
    for q1 in (psi + phi + math.pi / 2, psi - phi + math.pi / 2):
        s1, c1 = math.sin(q1), math.cos(q1)
        c5 = (T06[0, 3] * s1 - T06[1, 3] * c1 - D4) / D6
        if abs(c5) > 1.0 + 1e-12:
            continue
        a5 = math.acos(max(-1.0, min(1.0, c5)))
        for q5 in (a5, -a5):
            s5 = math.sin(q5)
            if abs(s5) < 1e-9:
                q6 = 0.0  # wrist singular: q6 arbitrary
            else:
                # x and y axes of the base expressed in the flange frame (rows of R06)
                xx, xy = T06[0, 0], T06[0, 1]
                yx, yy = T06[1, 0], T06[1, 1]
                q6 = math.atan2((-xy * s1 + yy * c1) / s5, (xx * s1 - yx * c1) / s5)
            T01 = dh_matrix(q1, 0)
            T45, T56 = dh_matrix(q5, 4), dh_matrix(q6, 5)
            T14 = rigid_inv(T01) @ T06 @ rigid_inv(T45 @ T56)
            p13 = (T14 @ np.array([0.0, -D4, 0.0, 1.0]))[:3]
            n13 = float(np.linalg.norm(p13))
            c3 = (n13 ** 2 - A2 ** 2 - A3 ** 2) / (2 * A2 * A3)
            if abs(c3) > 1.0 + 1e-12:
                continue
            a3 = math.acos(max(-1.0, min(1.0, c3)))
            for q3 in (a3, -a3):
                q2 = -math.atan2(p13[1], -p13[0]) + math.asin(max(-1.0, min(1.0, A3 * math.sin(q3) / n13)))
                T13 = dh_matrix(q2, 1) @ dh_matrix(q3, 2)
                T34 = rigid_inv(T13) @ T14
                q4 = math.atan2(T34[1, 0], T34[0, 0])
                sols.append([q1, q2, q3, q4, q5, q6])
    out = np.array(sols, dtype=float).reshape(-1, 6)
    out = (out + math.pi) % (2 * math.pi) - math.pi
    if not verify:
        return out
    # keep only true solutions (guards the clamps above)
    keep = [k for k in range(len(out)) if np.allclose(fk_flange(out[k]), T06, atol=1e-7)]
    return out[keep]


def ik(T_base_tcp, tcp_offset=(0, 0, 0, 0, 0, 0), verify: bool = True) -> np.ndarray:
    """Closed-form solutions for a base->TCP transform."""
    return ik_flange(np.asarray(T_base_tcp) @ rigid_inv(pose_to_matrix(tcp_offset)), verify)


def _dh_batch(q, i) -> np.ndarray:
    c, s = np.cos(q), np.sin(q)
    ca_, sa, a, d = _CA[i], _SA[i], DH_A[i], DH_D[i]
    T = np.zeros(q.shape + (4, 4))
    T[..., 0, :] = np.stack([c, -s * ca_, s * sa, a * c], -1)
    T[..., 1, :] = np.stack([s, c * ca_, -c * sa, a * s], -1)
    T[..., 2, 1], T[..., 2, 2], T[..., 2, 3], T[..., 3, 3] = sa, ca_, d, 1.0
    return T


def _inv_batch(T) -> np.ndarray:
    Ti = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    Ti[..., :3, :3] = Rt
    Ti[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    Ti[..., 3, 3] = 1.0
    return Ti


def ik_branch_batch(T06, branch) -> np.ndarray:
    """The closed-form solution on ``branch`` (shoulder, elbow, wrist signs) for many base->flange transforms
    (m, 4, 4) at once, vectorized; (m, 6) with NaN rows where the pose has no solution on that branch. Same
    equations as ``ik_flange``; the branch picks one of the two roots at each of the three choices."""
    T06 = np.asarray(T06, dtype=float).reshape(-1, 4, 4)
    sh, el, wr = (float(b) for b in branch)
    with np.errstate(invalid="ignore", divide="ignore"):
        p05 = T06[:, :3, 3] - D6 * T06[:, :3, 2]
        r = np.hypot(p05[:, 0], p05[:, 1])
        psi, phi = np.arctan2(p05[:, 1], p05[:, 0]), np.arccos(D4 / r)    # NaN inside the shoulder cylinder
        q1a, q1b = psi + phi + np.pi / 2, psi - phi + np.pi / 2
        ind_a = -(p05[:, 0] * np.cos(q1a) + p05[:, 1] * np.sin(q1a))
        q1 = np.where(np.sign(ind_a) == sh, q1a, q1b)
        s1, c1 = np.sin(q1), np.cos(q1)
        c5 = (T06[:, 0, 3] * s1 - T06[:, 1, 3] * c1 - D4) / D6
        q5 = wr * np.arccos(c5)
        s5 = np.sin(q5)
        q6 = np.arctan2((-T06[:, 0, 1] * s1 + T06[:, 1, 1] * c1) / s5, (T06[:, 0, 0] * s1 - T06[:, 1, 0] * c1) / s5)
        T14 = _inv_batch(_dh_batch(q1, 0)) @ T06 @ _inv_batch(_dh_batch(q5, 4) @ _dh_batch(q6, 5))
        p13 = np.einsum("mij,j->mi", T14, [0.0, -D4, 0.0, 1.0])[:, :3]
        n13 = np.linalg.norm(p13, axis=1)
        q3 = el * np.arccos((n13 ** 2 - A2 ** 2 - A3 ** 2) / (2 * A2 * A3))
        q2 = -np.arctan2(p13[:, 1], -p13[:, 0]) + np.arcsin(A3 * np.sin(q3) / n13)
        T34 = _inv_batch(_dh_batch(q2, 1) @ _dh_batch(q3, 2)) @ T14
        q4 = np.arctan2(T34[:, 1, 0], T34[:, 0, 0])
    Q = np.column_stack([q1, q2, q3, q4, q5, q6])
    Q = (Q + np.pi) % (2 * np.pi) - np.pi
    bad = ~np.all(np.isfinite(Q), axis=1) | (np.abs(s5) < 1e-9) | (np.abs(np.sin(q3)) < 1e-9)
    Q[bad] = np.nan
    return Q


def unwrap_near(q, q_ref) -> np.ndarray:
    """q shifted by multiples of 2 pi, joint by joint, to lie nearest q_ref (within the joint limits)."""
    q = np.asarray(q, dtype=float).copy()
    q_ref = np.asarray(q_ref, dtype=float)
    for j in range(6):
        k = round((q_ref[j] - q[j]) / (2 * math.pi))
        cand = q[j] + 2 * math.pi * k
        if JOINT_LOWER_RAD[j] <= cand <= JOINT_UPPER_RAD[j]:
            q[j] = cand
    return q


def ik_on_branch(T_base_tcp, branch, q_near, tcp_offset=(0, 0, 0, 0, 0, 0), T_tcp_inv=None) -> np.ndarray | None:
    """The closed-form solution on ``branch`` (signs of shoulder, elbow, wrist) nearest ``q_near``; None if none.
    ``T_tcp_inv`` (the inverse TCP transform) may be passed to save recomputing it."""
    best, best_d = None, math.inf
    if T_tcp_inv is None:
        T_tcp_inv = rigid_inv(pose_to_matrix(tcp_offset))
    T06 = np.asarray(T_base_tcp) @ T_tcp_inv
    pw = T06[:3, 3] - D6 * T06[:3, 2]          # the wrist centre is fixed by the pose: no FK per solution
    for q in ik_flange(T06, verify=False):
        signs = np.sign([-(pw[0] * math.cos(q[0]) + pw[1] * math.sin(q[0])), math.sin(q[2]), math.sin(q[4])])
        if not np.array_equal(signs, np.asarray(branch)):
            continue
        q = unwrap_near(q, q_near)
        d = float(np.sum((q - q_near) ** 2))
        if d < best_d:
            best, best_d = q, d
    if best is not None and not np.allclose(fk_flange(best), T06, atol=1e-7):
        return None
    return best
