"""The optimal-design machinery behind bench/design_bound.py, against closed forms no one here tuned."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "bench"))
from design_bound import a_optimal  # noqa: E402

from planner.accuracy import peak_fit  # noqa: E402


def test_c_optimal_slope_design_is_the_two_ends():
    """Straight line y = a + b u on u in [-1, 1]: the best design for the slope puts half the probes at each end,
    var(b) = 1/N, against 3/N for an even spread (mean u^2 = 1/3): a gain of exactly 3."""
    u = np.linspace(-1, 1, 201)
    J = np.column_stack([np.ones_like(u), u])
    A = np.diag([0.0, 1.0])
    w, lower = a_optimal(J, A, iters=20000)
    var_b = np.linalg.inv(J.T @ (w[:, None] * J))[1, 1]
    even = np.linalg.inv(J.T @ J / len(u))[1, 1]
    assert abs(var_b - 1.0) < 1e-3 and lower <= var_b + 1e-12 and lower > 0.99
    assert abs(even / var_b - 1.0 / np.mean(u * u)) < 1e-3 * even      # 1 / mean(u^2) -> 3 as the grid refines
    assert w[0] + w[-1] > 0.99 and abs(w[0] - w[-1]) < 1e-3


def test_a_optimal_quadratic_matches_known_design():
    """Quadratic regression on [-1, 1], A-optimality for all three coefficients: the optimum is supported on
    {-1, 0, 1} with weights (1/4, 1/2, 1/4) (Kiefer; Pukelsheim, Optimal Design of Experiments, sec. 9.8)."""
    u = np.linspace(-1, 1, 101)
    J = np.column_stack([np.ones_like(u), u, u * u])
    w, lower = a_optimal(J, np.eye(3), iters=20000)
    phi = np.trace(np.linalg.inv(J.T @ (w[:, None] * J)))
    ref = np.zeros_like(u)
    ref[[0, 50, 100]] = (0.25, 0.5, 0.25)
    phi_ref = np.trace(np.linalg.inv(J.T @ (ref[:, None] * J)))
    assert abs(phi - phi_ref) < 1e-3 * phi_ref and lower <= phi + 1e-12
    assert abs(w[50] - 0.5) < 0.01 and abs(w[0] - 0.25) < 0.01


def test_peak_fit_finds_a_symmetric_bump_between_probes():
    """The model-free baseline is not a straw man: on a symmetric bump (a Lorentzian 24 mm wide at half height, on
    an offset) between probes 1.5 or 0.25 mm apart it is within 0.1 mm (a parabola over the half-height run)."""
    for n in (41, 241):
        x = np.linspace(0.005, 0.065, n)
        for centre in (0.0301, 0.03537, 0.041):
            c = 0.02 / (1 + ((x - centre) / 0.012) ** 2) + 0.001
            assert abs(peak_fit(x, c) - centre) < 1e-4


def test_bound_on_a_real_stone_is_consistent():
    """bound_one on the fem surrogate (the paper stone): the achieved joint gain lies below its certified bound and
    below each single-parameter bound, is at least about 1 (an even spread is itself a design), and the minimax gap
    is small."""
    from design_bound import bound_one

    from fem.scene import load
    from planner.surrogate import load_surrogate
    prior = load("paper").prior()
    r = bound_one(load_surrogate(prior), np.array([0.035, 0.025, 0.015]), prior.tissue.width_m)
    assert 0.98 <= r["gain_best"] <= r["gain_bound"] * (1 + 1e-9)
    assert r["gain_best"] <= min(r["gain_x_bound"], r["gain_depth_bound"]) * (1 + 1e-9)
    assert r["gain_x"] <= r["gain_x_bound"] * (1 + 1e-9) and r["gain_depth"] <= r["gain_depth_bound"] * (1 + 1e-9)
    assert r["gap"] < 0.1 and r["gain_bound"] < 5
