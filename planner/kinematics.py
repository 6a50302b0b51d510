"""UR5e forward kinematics as CasADi SX, compiled to a Function once per process: the planner's NLP is built on it.
The DH table, the closed-form inverse, the IK branches and the pose helpers are core.ur5e's (one table for the
planner, the driver and the simulators)."""
from __future__ import annotations

import functools

import casadi as ca
import numpy as np

from core.ur5e import D6, DH_A, DH_COS_ALPHA, DH_D, DH_SIN_ALPHA, pose_to_T


def _dh_sx(q, i):
    c, s = ca.cos(q), ca.sin(q)
    ca_, sa = DH_COS_ALPHA[i], DH_SIN_ALPHA[i]
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


def fk_batch(Q, tcp_offset=(0, 0, 0, 0, 0, 0)) -> tuple[np.ndarray, np.ndarray]:
    """Many configurations (m, 6) at once through the compiled Function: (T (m, 4, 4), wrist centres (m, 3))."""
    Q = np.asarray(Q, dtype=float).reshape(-1, 6)
    T, pw = fk_function()(Q.T, pose_to_T(tcp_offset))
    m = Q.shape[0]
    return np.array(T).reshape(4, m, 4).transpose(1, 0, 2), np.array(pw).T.reshape(m, 3)
