"""core.ur5e's pose helpers against scipy's Rotation: the rotation-vector conversions at every angle, in particular
just short of pi (the tool-down orientation of every probe), where an acos-based angle loses ~1e-3 rad."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from core import ur5e


def _angle_between(Ra, Rb) -> float:
    """Angle of Ra^T Rb by scipy (independent of core.ur5e)."""
    return float(Rotation.from_matrix(np.asarray(Ra).T @ np.asarray(Rb)).magnitude())


def _random_axes(rng, n):
    k = rng.normal(size=(n, 3))
    return k / np.linalg.norm(k, axis=1, keepdims=True)


def _check(rotvecs, tol):
    for r in rotvecs:
        R = Rotation.from_rotvec(r).as_matrix()
        got = ur5e.matrix_to_rotvec(R)
        # compare rotations, not vectors: at pi, r and -r are the same rotation
        assert _angle_between(R, Rotation.from_rotvec(got).as_matrix()) < tol, (r, got)
        assert _angle_between(R, ur5e.rotvec_to_matrix(got)) < tol, (r, got)       # the round trip
        n = np.linalg.norm(got)
        assert n <= math.pi + ur5e._PI_BAND
        if n < math.pi - ur5e._PI_BAND:
            assert np.allclose(got, r, rtol=0, atol=tol), (r, got)                 # unique away from pi


def test_matrix_to_rotvec_random_rotations():
    rng = np.random.default_rng(0)
    R = Rotation.random(500, random_state=rng)
    _check(R.as_rotvec(), 1e-12)
    # ur5e.rotvec_to_matrix agrees with scipy on the same vectors
    for r in R.as_rotvec()[:100]:
        assert np.allclose(ur5e.rotvec_to_matrix(r), Rotation.from_rotvec(r).as_matrix(), atol=1e-14)


@pytest.mark.parametrize("eps", [1e-6, 5e-6, 1e-5, 1e-4, 1e-3, 1e-2])
def test_matrix_to_rotvec_near_pi(eps):
    rng = np.random.default_rng(int(1e6 * eps))
    k = np.vstack([_random_axes(rng, 200), np.eye(3), -np.eye(3), [[1.0, 0.0, 0.0]]])
    _check(k * (math.pi - eps), 1e-12)


def test_matrix_to_rotvec_at_pi_and_small_angles():
    rng = np.random.default_rng(1)
    k = _random_axes(rng, 100)
    _check(k * math.pi, 1e-12)
    for th in (0.0, 1e-12, 1e-9, 1e-6, 1e-3):
        _check(k[:10] * th, 1e-12)
    assert np.array_equal(ur5e.matrix_to_rotvec(np.eye(3)), np.zeros(3))


def test_sign_is_stable_at_pi():
    """Rotations a round-off apart near pi (the tool pointing down) get vectors a round-off apart, not r and -r."""
    rng = np.random.default_rng(2)
    for k in _random_axes(rng, 50):
        k = k if k[np.argmax(np.abs(k))] > 0 else -k
        base = ur5e.matrix_to_rotvec(Rotation.from_rotvec(k * math.pi).as_matrix())
        for d in (1e-12, 1e-9, 1e-7):
            for kd in (k, -k):                 # just short of pi about k and about -k: both ~pi about k
                got = ur5e.matrix_to_rotvec(Rotation.from_rotvec(kd * (math.pi - d)).as_matrix())
                assert np.linalg.norm(got - base) < 2 * d + 1e-12, (k, d, got, base)


def test_tool_down_pose_round_trip():
    """The tool-down pose written with 6 significant digits (what ur_rtde sends) keeps its rotation to round-off."""
    p = [0.4, -0.1, 0.2, 3.14159, 0.0, 0.0]          # 2.65e-6 rad short of pi
    q = ur5e.T_to_pose(ur5e.pose_to_T(p))
    assert _angle_between(ur5e.rotvec_to_matrix(p[3:]), Rotation.from_rotvec(q[3:]).as_matrix()) < 1e-12
    assert np.allclose(q[:3], p[:3], atol=0)


def test_vectorised_rotations_match_the_scalar_ones():
    """rotvecs_to_matrices / matrices_to_rotvecs (the simulated arm's move tapes) agree with the one-at-a-time
    functions to round-off at every angle: random, small, just short of pi (inside and outside the band), at pi.
    (Exactly at the 1e-12 rad identity cut-off the two may round to opposite sides: a 1e-12 rad difference.)"""
    rng = np.random.default_rng(3)
    k = _random_axes(rng, 60)
    ths = [0.0, 1e-13, 1e-11, 1e-9, 1e-6, 1e-3, 0.3, 1.5, 2.0, 3.0, math.pi - 1e-3, math.pi - 2e-6, math.pi - 5e-7,
           math.pi - 1e-12, math.pi]
    r = np.vstack([Rotation.random(200, random_state=rng).as_rotvec()] + [k * th for th in ths])
    M = ur5e.rotvecs_to_matrices(r)
    assert M.shape == (len(r), 3, 3)
    for ri, Mi in zip(r, M):
        assert np.allclose(Mi, ur5e.rotvec_to_matrix(ri), rtol=0, atol=2e-15)
    got = ur5e.matrices_to_rotvecs(M)
    for Mi, gi in zip(M, got):
        assert np.allclose(gi, ur5e.matrix_to_rotvec(Mi), rtol=0, atol=1e-14), (Mi, gi)
