"""UR5e kinematics in plain numpy: the one DH table, forward kinematics, closed-form inverse kinematics (Hawkins),
IK branches, joint limits, and the pose helpers ur_rtde's poses need. planner.kinematics builds its CasADi forward
kinematics from the same table.

Conventions: standard DH (``Rz(q) Tz(d) Tx(a) Rx(alpha)``) with the nominal UR5e parameters (docs/reference.md); the
chain ends at the flange (``tool0``); the TCP is the flange frame times ``tcp_offset`` (a ur_rtde pose, as given to
``setTcp``). Poses are ``[x, y, z, rx, ry, rz]`` (m, rotation vector in rad) in the base frame; ``T`` is a 4x4
homogeneous transform. Real arms are individually calibrated, so poses computed here agree with a real controller's
to a few millimetres only.

IK branches (Hawkins' closed form has up to 8 solutions): ``shoulder`` = sign of the wrist centre's reach along the
arm's plane (+1: the usual pose, upper and fore arm reaching away from the base; -1: over the shoulder),
``elbow`` = sign(sin q3), ``wrist`` = sign(sin q5). Their magnitudes measure the distance from the three UR
singularities (shoulder: wrist centre on the cylinder r = d4 about the base axis; elbow: arm stretched or folded;
wrist: joint 6 parallel to joint 4).
"""
from __future__ import annotations

import math

import numpy as np

D1, A2, A3, D4, D5, D6 = 0.1625, -0.425, -0.3922, 0.1333, 0.0997, 0.0996
DH_A = (0.0, A2, A3, 0.0, 0.0, 0.0)
DH_D = (D1, 0.0, 0.0, D4, D5, D6)
DH_ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)
# exact cos/sin of the twists (0, +-1) keep expression graphs small and free of 6e-17 terms
DH_COS_ALPHA = tuple(float(round(math.cos(a))) for a in DH_ALPHA)
DH_SIN_ALPHA = tuple(float(round(math.sin(a))) for a in DH_ALPHA)
_CA, _SA = DH_COS_ALPHA, DH_SIN_ALPHA

JOINT_LOWER_RAD = np.array([-2 * math.pi, -2 * math.pi, -math.pi, -2 * math.pi, -2 * math.pi, -2 * math.pi])
JOINT_UPPER_RAD = -JOINT_LOWER_RAD
MAX_JOINT_SPEED_RAD_S = math.pi      # every UR5e joint
MAX_JOINT_ACCEL_RAD_S2 = 40.0        # ur_rtde rejects more
REACH_M = 0.85
Q_HOME = np.array([0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0])  # tool down, elbow up
DEFAULT_BRANCH = (1, 1, -1)          # (shoulder, elbow, wrist) of Q_HOME


# The seed for a start configuration above tissue in front of the arm (base rotated to face it, elbow up, tool down)
IK_SEED = np.array([math.pi, -1.4, 1.6, -1.77, -1.57, 0.0])


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


def rotvecs_to_matrices(r) -> np.ndarray:
    """``rotvec_to_matrix`` over an (N, 3) array of rotation vectors: (N, 3, 3); the same formula, to round-off."""
    r = np.asarray(r, dtype=float).reshape(-1, 3)
    th = np.sqrt(np.einsum("ij,ij->i", r, r))
    big = th >= 1e-12
    k = np.zeros_like(r)
    k[big] = r[big] / th[big, None]
    K = np.zeros((len(r), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    M = np.eye(3) + np.sin(th)[:, None, None] * K + (1 - np.cos(th))[:, None, None] * (K @ K)
    M[~big] = np.eye(3)
    return M


def matrices_to_rotvecs(R) -> np.ndarray:
    """``matrix_to_rotvec`` over an (N, 3, 3) array of rotation matrices: (N, 3), the same branches (small angles,
    the symmetric part's axis beyond pi / 2, the canonical direction within ``_PI_BAND`` of pi), to round-off."""
    R = np.asarray(R, dtype=float).reshape(-1, 3, 3)
    w = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    c = 0.5 * (np.trace(R, axis1=1, axis2=2) - 1.0)
    th = np.arctan2(0.5 * np.linalg.norm(w, axis=1), c)
    out = np.empty_like(w)
    small, big = th < 1e-9, th > 0.5 * math.pi
    mid = ~small & ~big
    out[small] = 0.5 * w[small]
    out[mid] = w[mid] * (th[mid] / (2 * np.sin(th[mid])))[:, None]
    if big.any():
        Rb, cb, wb, tb = R[big], c[big], w[big], th[big]
        kk = (0.5 * (Rb + Rb.transpose(0, 2, 1)) - cb[:, None, None] * np.eye(3)) / (1.0 - cb)[:, None, None]
        i = np.argmax(np.diagonal(kk, axis1=1, axis2=2), axis=1)
        n = np.arange(len(i))
        k = kk[n, :, i] / np.sqrt(kk[n, i, i])[:, None]
        k /= np.linalg.norm(k, axis=1)[:, None]
        pos = np.einsum("ij,ij->i", k, wb) >= 0
        band = math.pi - tb < _PI_BAND
        length = np.where(band, np.where(pos, tb, 2 * math.pi - tb), tb)
        sign = np.where(band | pos, 1.0, -1.0)
        out[big] = k * (sign * length)[:, None]
    return out


def pose_to_T(pose) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rotvec_to_matrix(pose[3:6])
    T[:3, 3] = pose[:3]
    return T


def T_to_pose(T, near=None) -> list[float]:
    """ur_rtde pose of a transform. A tool pointing down is a rotation by nearly pi, where r and r (1 - 2 pi / |r|)
    describe (almost) the same rotation with opposite-looking vectors: given ``near`` (a previous pose), the equivalent
    rotation vector closest to its vector is returned, so neighbours read alike."""
    T = np.asarray(T, dtype=float)
    r = matrix_to_rotvec(T[:3, :3])
    if near is not None:
        th = float(np.linalg.norm(r))
        if th > 1e-9:
            alt = r * (1.0 - 2.0 * math.pi / th)
            ref = np.asarray(near, dtype=float)[3:6]
            if np.linalg.norm(alt - ref) < np.linalg.norm(r - ref):
                r = alt
    return [float(v) for v in (*T[:3, 3], *r)]


def pose_trans(a, b) -> list[float]:
    """Compose poses: ``b`` expressed in ``a``'s frame (URScript's pose_trans)."""
    return T_to_pose(pose_to_T(a) @ pose_to_T(b))


def rotation_angle(Ra, Rb) -> float:
    """Angle (rad) of the rotation taking Ra to Rb."""
    c = max(-1.0, min(1.0, 0.5 * (np.trace(np.asarray(Ra).T @ np.asarray(Rb)) - 1.0)))
    return math.acos(c)


def slerp_matrix(Ra, Rb, u: float) -> np.ndarray:
    """Rotation a fraction ``u`` of the way from Ra to Rb (geodesic)."""
    rel = matrix_to_rotvec(np.asarray(Ra).T @ np.asarray(Rb))
    return np.asarray(Ra) @ rotvec_to_matrix(u * rel)



# ---------------------------------------------------------------------------------------------------------------
# forward kinematics

def dh_matrix(q: float, i: int) -> np.ndarray:
    c, s, ca_, sa, a, d = math.cos(q), math.sin(q), _CA[i], _SA[i], DH_A[i], DH_D[i]
    return np.array([[c, -s * ca_, s * sa, a * c], [s, c * ca_, -c * sa, a * s], [0, sa, ca_, d], [0, 0, 0, 1.0]])


def fk_flange(q) -> np.ndarray:
    T = np.eye(4)
    for i in range(6):
        T = T @ dh_matrix(float(q[i]), i)
    return T


def joint_origins(q) -> np.ndarray:
    """(5, 3): the base-frame origins of DH frames 1-5 for joint angles ``q`` (shoulder, elbow, the three wrist
    joints; the links are not modelled, only where their joints sit)."""
    T, out = np.eye(4), []
    for i in range(5):
        T = T @ dh_matrix(float(q[i]), i)
        out.append(T[:3, 3].copy())
    return np.array(out)


def fk(q, tcp_offset=(0, 0, 0, 0, 0, 0)) -> np.ndarray:
    """Base->TCP transform for joint angles ``q`` (rad) and a TCP offset (ur_rtde's setTcp pose)."""
    return fk_flange(q) @ pose_to_T(tcp_offset)


def fk_pose(q, tcp_offset=(0, 0, 0, 0, 0, 0)) -> list[float]:
    """TCP pose (ur_rtde ``[x, y, z, rx, ry, rz]``) for joint angles ``q``."""
    return T_to_pose(fk(q, tcp_offset))


def rigid_inv(T) -> np.ndarray:
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


def branch_indicators(q) -> np.ndarray:
    T = fk_flange(q)
    pw = T[:3, 3] - D6 * T[:3, 2]
    return np.array([-(pw[0] * math.cos(q[0]) + pw[1] * math.sin(q[0])), math.sin(q[2]), math.sin(q[4])])


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


def ik_all(T_base_tcp, tcp_offset=(0, 0, 0, 0, 0, 0), verify: bool = True) -> np.ndarray:
    """Closed-form solutions for a base->TCP transform."""
    return ik_flange(np.asarray(T_base_tcp) @ rigid_inv(pose_to_T(tcp_offset)), verify)


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
        T_tcp_inv = rigid_inv(pose_to_T(tcp_offset))
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


def ik(pose, q_seed=IK_SEED, tcp_offset=(0, 0, 0, 0, 0, 0)) -> np.ndarray | None:
    """The joint angles reaching TCP ``pose`` (ur_rtde pose) nearest ``q_seed`` (each joint unwrapped towards the
    seed within the joint limits); None if the pose is out of reach."""
    sols = ik_all(pose_to_T(pose), tcp_offset)
    if len(sols) == 0:
        return None
    seed = np.asarray(q_seed, dtype=float)
    sols = [unwrap_near(q, seed) for q in sols]
    return min(sols, key=lambda q: float(np.sum((q - seed) ** 2)))
