"""The localizer's finite-strain term (planner.finite_strain_response, planner.localize): the prior's own
neo-Hookean correction g = F_nH / F_lin - 1 with a fitted amplitude a. Healthy neo-Hookean tissue is no stone and
gives a near 1, linear tissue a near 0, a stone in neo-Hookean tissue is found; a neo-Hookean mismatch-study trial
the localizer called a stone (LR 297) is not one any more; the table agrees with a fresh fem sweep between its
nodes; the term is off where fem's finite-strain model does not reach.

The synthetic neo-Hookean forces are fem's: at the table's own positions (and their mirror images) the force of
the prior as a neo-Hookean solid is F_lin (1 + g), exactly as the simulated truth computes it (fem.hypertruth)."""
from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path

import numpy as np
import pytest

from fem.contact import surface_model
from fem.hypertruth import HyperelasticForce
from fem.scene import load
from planner.finite_strain_response import prior_finite_strain, unsupported
from planner.localize import LR_THRESHOLD, Measurements, localize
from planner.refine import WEAK_LR
from robot.records import read_records

DEPTH_M = 0.004
SIGMA_N = 2e-4


@pytest.fixture(scope="module")
def probes(paper_prior):
    """The table's positions from 5 mm and their mirror images (19 probes), fem's linear force and the table's
    correction there at DEPTH_M (a sweep depth: no interpolation either)."""
    shape = prior_finite_strain(paper_prior)
    W = paper_prior.tissue.width_m
    half = shape.x_m[shape.x_m >= 0.005 - 1e-9]
    x = np.unique(np.round(np.concatenate([half, W - half]), 9))
    k = int(np.argmin(abs(shape.depth_m - DEPTH_M)))
    assert shape.depth_m[k] == pytest.approx(DEPTH_M)
    g = np.array([shape.g[int(np.argmin(abs(shape.x_m - min(v, W - v)))), k] for v in x])
    lin = surface_model(paper_prior)
    F = np.array([lin.force_n(float(v), DEPTH_M) for v in x])
    return x, F, g


def measurements(x, F, seed=0) -> Measurements:
    rng = np.random.default_rng(seed)
    n = len(x)
    return Measurements(x, np.full(n, DEPTH_M), F + rng.normal(0, SIGMA_N, n), np.full(n, SIGMA_N),
                        np.full(n, 5.0), np.arange(n))


def test_healthy_neo_hookean_tissue_is_no_stone_and_its_amplitude_is_near_one(paper_prior, paper_surrogate, probes):
    """The prior as a neo-Hookean solid, 30 % softer: no stone, a = 1, the stiffness scale 0.7 and no drift.
    Without the term the linear model follows the force's rise towards the sides (+17 % at 5 mm against +2.8 % in
    the middle at 4 mm) with artefacts (measured: stiffness 0.55, a drift of 3.3 mN/s, i.e. an offset of 16 mN)."""
    x, F, g = probes
    m = measurements(x, 0.7 * F * (1 + g))
    loc = localize(paper_prior, m, paper_surrogate)
    a, sd_a = loc.nuisance["finite_strain_amplitude"]
    assert not loc.detected and loc.lr < 9.0, loc.lr
    assert abs(a - 1.0) < 0.15 and 0.0 < sd_a < 0.4, (a, sd_a)      # measured 1.002 +- 0.25
    assert loc.nuisance["stiffness_scale"][0] == pytest.approx(0.7, rel=0.03)
    assert abs(loc.nuisance["sensor_drift_n_per_s"][0]) < 5e-4
    assert loc.chi2_0 < 2 * len(m)
    off = localize(paper_prior, m, paper_surrogate, finite_strain=False)
    assert off.nuisance["stiffness_scale"][0] < 0.6 and off.nuisance["sensor_drift_n_per_s"][0] > 2e-3


def test_linear_tissue_gives_an_amplitude_near_zero(paper_prior, paper_surrogate, probes):
    x, F, _ = probes
    loc = localize(paper_prior, measurements(x, 1.3 * F, seed=1), paper_surrogate)
    a, sd_a = loc.nuisance["finite_strain_amplitude"]
    assert not loc.detected and loc.lr < 9.0, loc.lr
    assert a < 0.15 and 0.0 < sd_a < 0.4, (a, sd_a)     # at its bound 0 too: a sigma from the inward difference
    assert loc.nuisance["stiffness_scale"][0] == pytest.approx(1.3, rel=0.03)


def test_a_stone_near_a_side_of_neo_hookean_tissue_is_found(paper_prior, paper_surrogate, probes):
    """A 12 mm stone 17 mm deep at x = 57 mm (where the eight-trial study lost two: the fit took the sides' rise
    for a thinner tissue) in the prior as a neo-Hookean solid: found at its place, a near 1."""
    x, F, g = probes
    C = paper_surrogate.contrast(x, np.full(len(x), DEPTH_M), 0.057, 0.017, 0.012)
    loc = localize(paper_prior, measurements(x, (F + C) * (1 + g), seed=2), paper_surrogate)
    assert loc.detected, loc.lr
    assert abs(loc.x_m - 0.057) < max(3 * loc.sigma_x_m, 5e-4), (loc.x_m, loc.sigma_x_m)
    assert abs(loc.depth_m - 0.017) < max(3 * loc.sigma_depth_m, 2e-3), (loc.depth_m, loc.sigma_depth_m)
    assert abs(loc.nuisance["finite_strain_amplitude"][0] - 1.0) < 0.3
    assert loc.nuisance["finite_strain_in_estimate"] and loc.nuisance["finite_strain_gain_chi2"] > 9.0


def test_a_stone_in_linear_tissue_is_estimated_without_the_term(paper_prior, paper_surrogate, probes):
    """The same stone in linear tissue: the term does not lower the stone fit's chi2 (measured 0.00), so the
    estimate is the one without it (a free let a weak or near-side stone's depth move by millimetres in the
    mismatch study's linear truths); the detection keeps it (LR within 1 % of the fit without it here)."""
    x, F, _ = probes
    C = paper_surrogate.contrast(x, np.full(len(x), DEPTH_M), 0.057, 0.017, 0.012)
    m = measurements(x, F + C, seed=3)
    loc, off = localize(paper_prior, m, paper_surrogate), localize(paper_prior, m, paper_surrogate, finite_strain=False)
    assert loc.detected and not loc.nuisance["finite_strain_in_estimate"]
    assert loc.nuisance["finite_strain_gain_chi2"] < 1.0 and loc.nuisance["finite_strain_amplitude"][0] < 0.15
    assert abs(loc.x_m - off.x_m) < 0.1 * off.sigma_x_m and abs(loc.depth_m - off.depth_m) < 0.1 * off.sigma_depth_m
    assert loc.lr == pytest.approx(off.lr, rel=0.01)


def test_a_healthy_neo_hookean_mismatch_trial_is_not_a_stone(paper_prior, paper_surrogate):
    """A mismatch-study trial (tests/data/mismatch-hyper-trial-0015: its 25 records and the truth they came from;
    ``palpate study mismatch --trials 12 --healthy 6 --seed 4 --hyperelastic``): healthy neo-Hookean tissue 1.8
    times as stiff, Poisson 0.447, 3.5 % thinner, the surface 0.59 mm high and tilted 30 mrad. Without the term:
    LR 297, a stone (and stiffness 1.39, thickness 0.82, a drift of 8 mN/s: artefacts); with it: no stone, a
    near 1 (measured 1.08 +- 0.05, LR 3.9)."""
    data = Path(__file__).parent / "data" / "mismatch-hyper-trial-0015"
    meas = Measurements.from_records(read_records(data), statuses=("ok", "force_limit"))
    loc = localize(paper_prior, meas, paper_surrogate)
    assert not loc.detected and loc.lr < 0.5 * LR_THRESHOLD, loc.lr
    assert 0.8 < loc.nuisance["finite_strain_amplitude"][0] < 1.4
    assert abs(loc.nuisance["sensor_drift_n_per_s"][0]) < 1e-3
    assert localize(paper_prior, meas, paper_surrogate, finite_strain=False).detected


def test_a_small_shallow_stone_at_the_end_gets_a_start_at_the_contrast_peak(paper_prior, paper_surrogate):
    """A mismatch-study trial (tests/data/mismatch-hyper-trial-0016: the coarse raster's 15 records and the truth;
    ``palpate study mismatch --hyperelastic --workers 2``, seed 1): a 4.2 mm stone 6.0 mm deep at x = 59.95 mm in
    neo-Hookean tissue half as stiff, the surface 0.86 mm low and tilted 26 mrad. The contrast peaks at 60.5 mm,
    but on the no-stone fit's surface every candidate start there ranked below central ones (chi2 43 against 27):
    all four starts went to the middle and the fit ended there (LR 8.5, below the refinement's 12: the run stopped,
    missed). With the best candidate at the peak always started: LR 18.9 at 60.0 mm (the whole run then refines
    there and finds it: x 60.00 +- 1.14 mm, depth 6.31 mm, LR 48). 60.0 mm was the table's last stone position
    then (at the fit's bound); since session 49 the table reaches 65 mm and these records give LR 26.7 at
    62.68 +- 0.62 mm, depth 8.12 +- 2.37 mm: 2.7 mm (4.4 sigma) towards the side, in tissue unlike the prior in
    five ways. The test guards the start at the peak: without it the fit ends mid-section, 25 mm away."""
    data = Path(__file__).parent / "data" / "mismatch-hyper-trial-0016"
    stone = tomllib.loads((data / "truth.toml").read_text())["stone"][0]
    meas = Measurements.from_records(read_records(data), statuses=("ok", "force_limit", "depth_limit"))
    assert len(meas) == 15
    loc = localize(paper_prior, meas, paper_surrogate)
    assert loc.lr > WEAK_LR, loc.lr                                         # measured 26.7 (8.5 before s48)
    assert abs(loc.x_m - stone["x_m"]) < 3.5e-3, loc.x_m                    # measured 62.68 mm
    assert abs(loc.depth_m - stone["depth_m"]) < 3e-3, loc.depth_m          # measured 8.12 mm


def test_the_table_agrees_with_a_fresh_sweep_between_its_nodes_on_the_mirrored_side(paper_prior):
    """A sweep at 52.5 mm (the mirror image of 17.5 mm, between the nodes at 15 and 20 mm): the table's PCHIP and
    mirror agree with it within 0.15 % of the force from 1 mm deep (measured 0.08 %)."""
    shape = prior_finite_strain(paper_prior)
    d, r = HyperelasticForce(paper_prior).ratio(0.0525)
    dd = shape.depth_m[shape.depth_m >= 1e-3 - 1e-12]
    got = shape.at(np.full(len(dd), 0.0525)).g(dd)
    assert np.max(np.abs(got - (np.interp(dd, d, r) - 1))) < 1.5e-3


def test_the_term_is_off_where_fems_finite_strain_model_does_not_reach(paper_prior):
    stress = paper_prior.with_analysis(plane="stress")
    soft_tip = dataclasses.replace(paper_prior, indenter=dataclasses.replace(paper_prior.indenter, youngs_pa=1e5))
    assert unsupported(paper_prior) == ""
    assert "plane strain" in unsupported(stress) and prior_finite_strain(stress) is None
    assert "rigid" in unsupported(soft_tip) and prior_finite_strain(soft_tip) is None
    with pytest.raises(ValueError, match="no stones"):
        prior_finite_strain(load("paper"))
    m = Measurements(np.linspace(0.01, 0.06, 6), np.full(6, DEPTH_M), np.full(6, 0.1), np.full(6, SIGMA_N),
                     np.ones(6), np.arange(6))
    with pytest.raises(ValueError, match="plane strain"):      # (refused before the surrogate is used)
        localize(stress, m, object(), finite_strain=True)


def test_the_shipped_table_is_the_current_codes(monkeypatch):
    """planner/data holds the paper prior's table under the key of fem's current code: a change to fem's linear or
    finite-strain code changes the key, and without this check every fresh machine would silently pay the sweeps
    (about 20 s) again. Regenerate: PALPATE_CACHE_DIR=DIR python -c "from fem.scene import load; from
    planner.finite_strain_response import prior_finite_strain; prior_finite_strain(load('paper').prior())", then
    copy DIR/hypershape-*.npz to planner/data/ (and remove the old one)."""
    import planner.finite_strain_response as fsr
    monkeypatch.setenv("PALPATE_CACHE", "0")
    monkeypatch.setattr(fsr, "_MEM", {})
    assert fsr.prior_finite_strain(load("paper").prior(), build=False) is not None
