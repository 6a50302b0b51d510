"""The localizer's fits take their Jacobian in closed form (planner.localize._jac; issue 19): every part of the forward
model is an interpolant, differentiated exactly. Checked column by column against central differences of the
residuals themselves (the shipped paper table, its finite-strain correction and contact onsets, with the stone's
share of the force at each onset since session 44; probe depths beyond
the table's levels; stones either side of the middle; the no-stone model; a surrogate without its own derivatives),
and the fits it drives against the same fits on scipy's finite differences (the previous method)."""
from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

import planner.localize as L
from fem.scene import Stone
from planner.finite_strain_response import prior_finite_strain
from planner.tissue_response import PriorResponse
from robot.records import read_records
from tests.test_localize import ToySurrogate, synth


def _meas(n=25, seed=3):
    """Probes anywhere on the section (also nearer a side than the table's probe positions reach), 2-7.5 mm deep
    (the table's levels end at 4 mm), with contact onsets."""
    rng = np.random.default_rng(seed)
    x = np.sort(np.r_[rng.uniform(0.0005, 0.004, 3), rng.uniform(0.004, 0.066, n - 6), rng.uniform(0.066, 0.0695, 3)])
    return L.Measurements(x, rng.uniform(0.002, 0.0075, n), rng.uniform(0.05, 0.3, n), np.full(n, 1e-3),
                          rng.uniform(2, 9, n), np.arange(n), rng.uniform(3e-4, 8e-4, n), np.full(n, 0.008))


def _points(fw, n, seed):
    """Parameter points (xs_mm, log s_mm, D_mm, *free nuisance) inside the fit's box, off the table's nodes."""
    rng = np.random.default_rng(seed)
    for _ in range(n):
        nu = np.array([rng.normal(0, 0.1), rng.normal(0, 0.2), rng.normal(0, 1), rng.normal(0, 20),
                       rng.normal(0, 0.05), rng.uniform(0, 2)])
        yield np.r_[rng.uniform(11, 59), math.log(rng.uniform(1.6, 20)), rng.uniform(4.5, 15), nu[fw.free]]


def _central(f, q, rel=1e-6):
    cols = []
    for j in range(len(q)):
        h = rel * max(1.0, abs(q[j]))
        e = np.zeros(len(q))
        e[j] = h
        cols.append((f(q + e) - f(q - e)) / (2 * h))
    return np.array(cols).T


def _assert_columns_close(J, Jn, tol):
    err = np.abs(J - Jn).max(axis=0) / (np.abs(Jn).max(axis=0) + 1e-12)
    assert err.max() < tol, err


@pytest.mark.parametrize("case", ["stone", "no-stone", "linear-tissue", "toy-surrogate"])
def test_the_residuals_jacobian_is_their_derivative(paper_prior, paper_surrogate, case):
    meas = _meas()
    fw = L._Forward(paper_prior, meas, ToySurrogate() if case == "toy-surrogate" else paper_surrogate, True,
                    False if case == "linear-tissue" else None)
    assert fw.free.all() == (case != "linear-tissue") and fw.free[:5].all()
    sig = np.full(len(meas), 1e-3)
    stone = case != "no-stone"

    def resid(q):
        nu = fw.full(q[3:] if stone else q)
        st = L._stone(q[:3]) if stone else None
        return np.concatenate([(meas.force_n - fw.forces(st, nu)) / sig, fw.extra(nu, st)])
    for q in _points(fw, 6, seed=len(case)):
        q = q if stone else q[3:]
        J = L._jac(fw, sig, q[:3] if stone else None, fw.full(q[3:] if stone else q))
        assert J.shape == (len(resid(q)), len(q))
        # central differences carry their own error (1e-6 steps over piecewise-linear tables): about 1e-8 here
        _assert_columns_close(J, _central(resid, q), 1e-5 if case == "toy-surrogate" else 1e-6)


def test_the_depth_held_profile_jacobian_follows_the_chain_rule(paper_prior, paper_surrogate):
    """The depth's profile fits (x, diameter, nuisance) with the depth held: log s = log(d - D/2)."""
    meas = _meas(seed=5)
    fw = L._Forward(paper_prior, meas, paper_surrogate, True)
    sig = np.full(len(meas), 1e-3)

    def resid(q):
        nu = fw.full(q[3:])
        st = L._stone(q[:3])
        return np.concatenate([(meas.force_n - fw.forces(st, nu)) / sig, fw.extra(nu, st)])
    for q in _points(fw, 4, seed=11):
        d_mm = math.exp(q[1]) + 0.5 * q[2]
        r, r_jac = L._depth_held(resid, lambda q: L._jac(fw, sig, q[:3], fw.full(q[3:])), d_mm)
        p = np.r_[q[0], q[2], q[3:]]
        assert np.array_equal(r(p), resid(np.r_[q[0], math.log(d_mm - 0.5 * q[2]), q[2], q[3:]]))
        _assert_columns_close(r_jac(p), _central(r, p), 1e-6)


def test_the_pieces_slopes_are_their_derivatives(paper_prior, paper_surrogate):
    """The interpolants' own derivatives: the contrast table (stone position, clearance, diameter, probe depth, on
    both sides of the middle), the prior's force and its inverse (depth, thickness), the finite-strain correction."""
    rng = np.random.default_rng(2)
    x0, d = rng.uniform(0.003, 0.067, 30), rng.uniform(0.0011, 0.0039, 30)     # inside the table's levels
    h = 1e-8
    for xs, s, D in ((0.0213, 0.005, 0.008), (0.0487, 0.012, 0.012), (0.0611, 0.003, 0.015)):
        S = paper_surrogate.contrast_slopes(x0, d, xs, s + D / 2, D)

        def c(xs=xs, s=s, D=D, d=d):
            return paper_surrogate.contrast(x0, d, xs, s + D / 2, D)
        num = [(c(xs=xs + h) - c(xs=xs - h)) / (2 * h),
               (c(s=s * math.exp(1e-6)) - c(s=s * math.exp(-1e-6))) / 2e-6,
               (c(D=D + h) - c(D=D - h)) / (2 * h), (c(d=d + h) - c(d=d - h)) / (2 * h)]
        for a, b in zip(S, num):
            assert np.abs(a - b).max() < 1e-6 * np.abs(b).max()
    resp = PriorResponse(paper_prior, x0)
    dd = rng.uniform(0.0003, 0.008, 30)
    for eta in (-0.12, 0.0, 0.07):
        F_d, F_eta = resp.force_slopes(dd, eta)
        num_d = (resp.force_n(dd + 1e-9, eta) - resp.force_n(dd - 1e-9, eta)) / 2e-9
        num_eta = (resp.force_n(dd, eta + 1e-6) - resp.force_n(dd, eta - 1e-6)) / 2e-6
        assert np.abs(F_d - num_d).max() < 1e-6 * np.abs(num_d).max()
        assert np.abs(F_eta - num_eta).max() < 1e-6 * np.abs(num_eta).max()
        f = resp.force_n(dd, eta)
        d_lf, d_eta = resp.depth_at_force_slopes(f, eta)
        num_lf = (resp.depth_at_force_m(f * math.exp(1e-6), eta) - resp.depth_at_force_m(f * math.exp(-1e-6), eta)) / 2e-6
        num_e = (resp.depth_at_force_m(f, eta + 1e-6) - resp.depth_at_force_m(f, eta - 1e-6)) / 2e-6
        assert np.abs(d_lf - num_lf).max() < 1e-6 * np.abs(num_lf).max()
        assert np.abs(d_eta - num_e).max() < 1e-6 * np.abs(num_e).max()
    g = prior_finite_strain(paper_prior).at(x0)
    assert np.abs(g.slope(dd) - (g.g(dd + 1e-9) - g.g(dd - 1e-9)) / 2e-9).max() < 1e-5 * np.abs(g.slope(dd)).max()


def _both(monkeypatch, prior, meas, sur, **kw):
    out = {}
    for mode in ("2-point", "analytic"):
        monkeypatch.setattr(L, "JACOBIAN", mode)
        monkeypatch.setattr(L, "_LAST_FIT", {})
        out[mode] = L.localize(prior, meas, sur, **kw)
    return out["2-point"], out["analytic"]


def test_the_fits_agree_with_the_finite_difference_fits(monkeypatch, paper_prior, paper_surrogate):
    """The same fits on scipy's finite differences (the previous method): a mismatch-study trial's records (a stone
    near an end under a tilted surface, tissue softer and thinner) and a synthetic paper-table stone; the estimates
    agree to a small fraction of their uncertainty and the closed form's chi2 is no worse."""
    data = Path(__file__).parent / "data" / "mismatch-trial-0048"
    meas = L.Measurements.from_records(read_records(data), statuses=("ok", "force_limit"))
    stone = tomllib.loads((data / "truth.toml").read_text())["stone"][0]
    x = np.linspace(0.005, 0.065, 21)
    cases = [(meas, stone["x_m"]),
             (synth(paper_prior, Stone(x_m=0.041, depth_m=0.018, diameter_m=0.010), x, sigma=5e-4, seed=2, sur=paper_surrogate), 0.041)]
    for meas, x_true in cases:
        fd, an = _both(monkeypatch, paper_prior, meas, paper_surrogate, profile=True)
        assert an.detected and fd.detected
        assert an.chi2_1 <= fd.chi2_1 * (1 + 1e-6) + 1e-6, (an.chi2_1, fd.chi2_1)
        assert abs(an.lr - fd.lr) <= 1e-3 * fd.lr + 0.5
        for k in ("x", "depth", "diameter"):
            a, b, sd = getattr(an, f"{k}_m"), getattr(fd, f"{k}_m"), getattr(fd, f"sigma_{k}_m")
            assert abs(a - b) < 0.05 * sd, (k, a, b, sd)
            assert getattr(an, f"sigma_{k}_m") == pytest.approx(sd, rel=0.02)
        for lvl in ("68", "95"):
            assert np.allclose(an.depth_interval_m[lvl], fd.depth_interval_m[lvl], atol=0.05 * fd.sigma_depth_m)
        assert abs(an.x_m - x_true) < 3 * an.sigma_x_m + 1e-3


def test_at_the_tables_ends_the_slopes_point_inwards(paper_surrogate):
    """A fit at a bound of the table (the smallest clearance, the first or last stone position) must see the
    parameter's effect: s = (s + D/2) - D/2 can land a hair outside the table, where the interpolant is held. The
    slope there is the inward one (a zero column would give that parameter no variance)."""
    sur = paper_surrogate
    x0, d = np.linspace(0.004, 0.066, 25) + 1.23e-4, np.full(25, 0.003)      # off the table's probe grid
    s0, xs0, xs1 = sur.s[0], sur.bounds["xs_m"][0], sur.bounds["xs_m"][1]
    outside = 0
    for D in np.linspace(sur.diam[0], sur.diam[-1], 40):
        dep = s0 + 0.5 * D
        outside += (dep - 0.5 * D) < s0
        S = sur.contrast_slopes(x0, d, 0.03, dep, D)
        inward = (sur.contrast(x0, d, 0.03, s0 * math.exp(1e-6) + 0.5 * D, D) - sur.contrast(x0, d, 0.03, dep, D)) / 1e-6
        assert np.abs(S[1] - inward).max() < 1e-4 * np.abs(inward).max(), D
    assert outside > 0                   # the round-off case occurs among these diameters
    for xs, step in ((xs0, 1e-8), (np.nextafter(xs0, 0.0), 1e-8), (xs1, -1e-8), (np.nextafter(xs1, 1.0), -1e-8)):
        S = sur.contrast_slopes(x0, d, xs, 0.02, 0.01)
        inward = (sur.contrast(x0, d, xs + step, 0.02, 0.01) - sur.contrast(x0, d, xs, 0.02, 0.01)) / step
        assert np.abs(S[0] - inward).max() < 1e-5 * np.abs(inward).max(), xs


def test_a_single_stones_two_rows_are_the_whole_slices(paper_prior, paper_surrogate):
    """One stone's contrast and slopes read only the two stone-position rows of a (s, D) slice of the table, blended
    alone (planner.surrogate: a third of the work): the same numbers, bit for bit, as reading them from the whole
    slice, whichever was blended first."""
    from planner.surrogate import Surrogate
    sur = paper_surrogate
    rng = np.random.default_rng(8)
    b = sur.bounds
    for trial in range(60):
        s = float(np.exp(rng.uniform(*np.log(b["s_m"]))))
        D = float(rng.uniform(*b["diam_m"]))
        x0, d = rng.uniform(0, sur.W, 30), rng.choice([0.003, 0.004, 0.0065], 30)
        xs = float(rng.uniform(*b["xs_m"]))
        rows_first, whole_first = (Surrogate.__new__(Surrogate) for _ in range(2))
        for t in (rows_first, whole_first):
            t.__dict__.update(sur.__dict__, _slices={}, _slopes={})
        whole_first.contrast_many(x0, d, np.linspace(b["xs_m"][0], b["xs_m"][1], 7), s + D / 2, D)
        k0 = int(np.clip(np.searchsorted(sur.xs, min(xs, sur.W - xs)) - 1, 0, len(sur.xs) - 2))
        assert np.array_equal(rows_first._slice(s, D, k0), whole_first._slice(s, D)[k0:k0 + 2])
        for fn in ("contrast", "contrast_slopes"):
            a = getattr(rows_first, fn)(x0, d, xs, s + D / 2, D)
            assert np.array_equal(a, getattr(whole_first, fn)(x0, d, xs, s + D / 2, D)), fn
            assert np.isfinite(a).all() and np.abs(a).max() > 0
