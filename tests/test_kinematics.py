"""UR5e kinematics: the DH forward kinematics (CasADi and numpy) against an independent product-of-exponentials
model, the closed-form IK, the branch indicators and the ur_rtde pose conversions."""
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from core import ur5e
from planner import kinematics as kin

# --- independent model: product of exponentials (Lynch & Park, Modern Robotics, UR5 example) with UR5e lengths,
# written in that book's space frame, which is the UR base frame turned by pi about z. No DH involved.
H1, L1, L2, W1, H2, W2 = 0.1625, 0.425, 0.3922, 0.1333, 0.0997, 0.0996


def _screw(w, p):
    w, p = np.asarray(w, float), np.asarray(p, float)
    return np.r_[w, -np.cross(w, p)]


_S = [_screw([0, 0, 1], [0, 0, 0]), _screw([0, 1, 0], [0, 0, H1]), _screw([0, 1, 0], [L1, 0, H1]),
      _screw([0, 1, 0], [L1 + L2, 0, H1]), _screw([0, 0, -1], [L1 + L2, W1, 0]),
      _screw([0, 1, 0], [L1 + L2, 0, H1 - H2])]
_M = np.array([[-1, 0, 0, L1 + L2], [0, 0, 1, W1 + W2], [0, 1, 0, H1 - H2], [0, 0, 0, 1.0]])
_BOOK_TO_BASE = np.diag([-1.0, -1.0, 1.0, 1.0])


def _se3(S, theta):
    """exp([S] theta) for a unit-axis screw (Rodrigues; checked against scipy's expm below)."""
    w, v = S[:3], S[3:]
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    s, c = math.sin(theta), math.cos(theta)
    T = np.eye(4)
    T[:3, :3] = np.eye(3) + s * K + (1 - c) * K @ K
    T[:3, 3] = (np.eye(3) * theta + (1 - c) * K + (theta - s) * K @ K) @ v
    return T


def test_screw_exponential_matches_expm():
    X = np.zeros((4, 4))
    S = _S[4]
    X[:3, :3] = [[0, -S[2], S[1]], [S[2], 0, -S[0]], [-S[1], S[0], 0]]
    X[:3, 3] = S[3:]
    np.testing.assert_allclose(_se3(S, 0.7), expm(X * 0.7), atol=1e-12)


def poe_flange(q):
    T = np.eye(4)
    for S, th in zip(_S, q):
        T = T @ _se3(S, th)
    return _BOOK_TO_BASE @ T @ _M


def poe_tcp(q, tcp_offset):
    """Base -> TCP, independent of planner.kinematics (used by test_planner too)."""
    X = np.eye(4)
    X[:3, :3] = Rotation.from_rotvec(tcp_offset[3:6]).as_matrix()
    X[:3, 3] = tcp_offset[:3]
    return poe_flange(q) @ X


joints = st.lists(st.floats(-2 * math.pi, 2 * math.pi, allow_nan=False), min_size=6, max_size=6)
within_limits = st.tuples(*[st.floats(float(lo) + 1e-6, float(hi) - 1e-6, allow_nan=False)
                            for lo, hi in zip(ur5e.JOINT_LOWER_RAD, ur5e.JOINT_UPPER_RAD)])


@settings(max_examples=40, deadline=None)
@given(joints)
def test_numpy_fk_matches_product_of_exponentials(q):
    np.testing.assert_allclose(ur5e.fk_flange(q), poe_flange(q), atol=1e-12)


def test_casadi_fk_function_matches_poe_with_tcp_offset():
    f = kin.fk_function()
    assert f is kin.fk_function()  # built once
    rng = np.random.default_rng(3)
    tcp = [0.01, -0.02, 0.12, 0.1, -0.2, 0.3]
    for _ in range(20):
        q = rng.uniform(-2 * math.pi, 2 * math.pi, 6)
        T, pw = f(q, ur5e.pose_to_T(tcp))
        np.testing.assert_allclose(np.array(T), poe_tcp(q, tcp), atol=1e-12)
        F = poe_flange(q)
        np.testing.assert_allclose(np.array(pw).ravel(), F[:3, 3] - ur5e.D6 * F[:3, 2], atol=1e-12)


def test_home_pose_is_tool_down_on_the_default_branch():
    T = ur5e.fk(ur5e.Q_HOME)
    np.testing.assert_allclose(T[:3, 2], [0, 0, -1], atol=1e-12)
    assert tuple(np.sign(ur5e.branch_indicators(ur5e.Q_HOME))) == ur5e.DEFAULT_BRANCH


@settings(max_examples=40, deadline=None)
@given(within_limits)
def test_closed_form_ik_recovers_the_configuration(q):
    q = np.asarray(q)
    ind = ur5e.branch_indicators(q)
    if np.min(np.abs(ind)) < 1e-3:
        return  # singular: q is not isolated
    T = ur5e.fk_flange(q)
    sols = ur5e.ik_flange(T)
    assert 1 <= len(sols) <= 8
    for s in sols:
        np.testing.assert_allclose(ur5e.fk_flange(s), T, atol=1e-9)
    wrapped = (sols - q + math.pi) % (2 * math.pi) - math.pi
    assert np.min(np.max(np.abs(wrapped), axis=1)) < 1e-7
    # the solution on q's own branch, unwrapped next to q, is q itself
    qb = ur5e.ik_on_branch(T, np.sign(ind), q)
    np.testing.assert_allclose(qb, q, atol=1e-7)


def test_ik_out_of_reach_is_empty():
    T = np.eye(4)
    T[:3, 3] = [1.5, 0.0, 0.2]
    assert len(ur5e.ik_flange(T)) == 0


def test_pose_conversion_round_trip_near_pi_and_sign_continuity():
    R = Rotation.from_rotvec([math.pi - 1e-4, 1e-3, 0]).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = [0.4, 0.0, 0.1]
    p = ur5e.T_to_pose(T)
    np.testing.assert_allclose(ur5e.pose_to_T(p), T, atol=1e-12)
    ref = [0, 0, 0, -p[3], -p[4], -p[5]]
    q = ur5e.T_to_pose(T, near=ref)     # the equivalent vector near the reference
    assert np.linalg.norm(np.subtract(q[3:], ref[3:])) < np.linalg.norm(np.subtract(p[3:], ref[3:]))
    np.testing.assert_allclose(ur5e.pose_to_T(q), T, atol=1e-9)


def test_unwrap_near_stays_within_limits():
    q = ur5e.unwrap_near([3.0, 0, 0, 0, 0, 0], [-3.0, 0, 0, 0, 0, 0])
    assert q[0] == pytest.approx(3.0 - 2 * math.pi)
