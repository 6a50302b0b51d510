"""Session 51: the depth limit a shallow stone's warning suggests is a planned depth (a surface fitted higher than
registered is indented deeper by the same plan), deep enough that the run's probes still feel the tissue, and never
below what the planner takes; a 2D fit that takes the tissue as stiffening at finite strain allows for the stone's own
finite strain."""
from __future__ import annotations

import functools
import math
from types import SimpleNamespace

from fem.contact import STONE_LAYER_MAX
from planner.refine import HINT_MARGIN, caveats, linear_range_depth_m


def _loc(rise_m=0.0, depth_m=0.007, diameter_m=0.008, detected=True):
    return SimpleNamespace(detected=detected, depth_m=depth_m, diameter_m=diameter_m, n_beyond_linear_range=4,
                           at_bound=[], dof_1=0, chi2_1=math.nan, chi2_fit=math.nan, surface_rise_at_stone_m=rise_m)


def test_the_suggested_depth_limit_is_the_planned_depth_that_keeps_the_true_one_within_the_model():
    top = 0.007 - 0.004
    covered = HINT_MARGIN * STONE_LAYER_MAX * top          # true indentation the linear model covers over the stone
    assert linear_range_depth_m(_loc()) == math.floor(covered * 1e4) / 1e4 == 0.002
    # a surface 0.6 mm higher than registered: a probe planned d deep indents d + 0.6 mm there
    assert linear_range_depth_m(_loc(rise_m=6e-4)) == math.floor((covered - 6e-4) * 1e4) / 1e4 == 0.0014
    assert "--depth-limit-m 0.0014" in caveats(_loc(rise_m=6e-4))
    # lower than registered: deeper
    assert "--depth-limit-m 0.0025 (on tissue stiffening at finite strain, x's sigma may" in caveats(_loc(rise_m=-5e-4))
    # nothing a probe could keep clear of (the fitted surface reaches the linear model's depth): the shallowest
    text = caveats(_loc(rise_m=2.5e-3))
    assert "readings pressed the tissue over it" in text
    assert "only for probes no deeper than 0.0 mm, but the planner takes no probe shallower than 1 mm: " \
        "--depth-limit-m 0.001 comes nearest" in text
    # nor one below the shallowest useful probe, which `palpate run --depth-limit-m` refuses (it suggested 0.0007)
    text = caveats(_loc(rise_m=1.3e-3))
    assert "--depth-limit-m 0.0007" not in text and "--depth-limit-m 0.001 comes nearest" in text
    assert math.isnan(linear_range_depth_m(_loc(depth_m=math.nan)))


def test_the_localization_reports_the_surface_rise_over_the_stone():
    """The localizer's JSON names the fitted surface's height over the stone (the offset plus the tilt there)."""
    from planner.localize import Localization
    d = Localization(detected=True, lr=30.0, lr_threshold=20.0, surface_rise_at_stone_m=4e-4).to_dict()
    assert d["evidence"]["surface_rise_at_stone_m"] == 4e-4


def test_the_fitted_rise_over_the_stone_is_the_offset_and_the_tilt_there(paper_prior, paper_surrogate):
    """On a study trial's records (tests/data/mismatch-hyper-trial-0043: the true surface is offset and tilted), the
    rise over the stone is the fitted offset plus the fitted tilt times the stone's distance from the section's
    middle: the surface the fit's own indentations use."""
    from pathlib import Path

    from planner.localize import Measurements, localize
    from robot.records import read_records
    data = Path(__file__).parent / "data" / "mismatch-hyper-trial-0043"
    meas = Measurements.from_records(read_records(data), statuses=("ok", "force_limit", "depth_limit"))
    loc = localize(paper_prior, meas, paper_surrogate)
    off, tilt = loc.nuisance["surface_offset_m"][0], loc.nuisance["surface_tilt_rad"][0]
    want = off + tilt * (loc.x_m - 0.5 * paper_prior.tissue.width_m)
    assert loc.detected and abs(tilt) > 1e-3         # the trial's surface is tilted: the tilt term counts
    assert math.isclose(loc.surface_rise_at_stone_m, want, rel_tol=1e-9, abs_tol=1e-12)


def test_a_suggested_depth_limit_leaves_the_probes_feeling_the_tissue(paper_prior):
    """A 3D block's shallow stone was told `--depth-limit-m 0.0011`, where its probes press 0.01 N against a 0.02 N
    contact threshold and feel nothing. The suggestion is now never shallower than the depth at which every probe of
    the run's plan presses CONTACT_MARGIN x the threshold; checked here against fem's own force at that depth."""
    from planner.plan import default_force_model, plan_raster
    from planner.refine import CONTACT_MARGIN, ProbeReach, contact_floor_m, depth_hint, probe_reach

    plan = plan_raster(paper_prior, n_waypoints=15)
    floor = contact_floor_m(plan)
    target = CONTACT_MARGIN * plan.motion.contact_threshold_n
    force = default_force_model(paper_prior)
    at_floor = [force(p.x_m, floor) for p in plan.probes]
    shallower = [force(p.x_m, floor - 2e-4) for p in plan.probes]
    assert min(at_floor) >= 0.95 * target, (floor, min(at_floor))        # continued by the exponent: within 5 %
    assert min(shallower) < target, (floor, min(shallower))              # and not needlessly deep
    assert 1e-3 < floor < plan.limits.depth_limit_m
    # the linear model over the stone asks for less: the floor is suggested instead, and says why
    reach = probe_reach(plan)
    assert reach == ProbeReach(floor, max(p.depth_m for p in plan.probes))
    text = depth_hint(_loc(depth_m=0.0055, diameter_m=0.008), reach)
    assert f"--depth-limit-m {floor:g} comes nearest" in text and "only from" in text
    # it asks for more: its own depth
    assert "--depth-limit-m 0.002" in depth_hint(_loc(), ProbeReach(1.5e-3, 0.004))
    # no shallower than the run went (the readings past the range were where the surface is higher): nothing to say
    assert depth_hint(_loc(rise_m=-2e-3), ProbeReach(1.5e-3, 0.003)) == ""
    # a plan that feels the tissue only at its own limit has no shallower floor: none is suggested
    soft = plan_raster(paper_prior, n_waypoints=5)
    for p in soft.probes:
        p.predicted_force_n = 0.5 * target
    assert contact_floor_m(soft) >= soft.limits.depth_limit_m and math.isnan(contact_floor_m(None))
    assert depth_hint(_loc(depth_m=0.0055, diameter_m=0.008), probe_reach(soft)) == ""


def _fit_study_trial(name, prior, surrogate, monkeypatch, fs_contrast_err):
    """A study trial's records (tests/data/NAME) localized with the finite-strain contrast allowance given."""
    from pathlib import Path

    import planner.localize as L
    from planner.localize import Measurements, localize
    from robot.records import read_records
    meas = Measurements.from_records(read_records(Path(__file__).parent / "data" / name),
                                     statuses=("ok", "force_limit", "depth_limit"))
    monkeypatch.setattr(L, "_LAST_FIT", {})            # (the last fit is remembered by its inputs, not this constant)
    monkeypatch.setattr(L, "FS_CONTRAST_ERR", fs_contrast_err)
    return localize(prior, meas, surrogate)


def test_a_finite_strain_fit_allows_for_the_stones_own_finite_strain(paper_prior, paper_surrogate, monkeypatch):
    """A neo-Hookean tissue's stone contrast differs from the linear contrast times the prior's finite-strain
    correction by 4-14 % over the stone and more on its flanks (bench/contrast_finite_strain.py); the localizer allowed
    1 %. On a study trial's records (neo-Hookean truth, the fit's amplitude about 1) the allowance widens the sigmas;
    a fit that keeps the tissue linear (a linear truth's trial) is not touched (its estimate bit for bit)."""
    from planner.localize import FS_CONTRAST_ERR
    assert FS_CONTRAST_ERR == 0.15
    fit = functools.partial(_fit_study_trial, prior=paper_prior, surrogate=paper_surrogate, monkeypatch=monkeypatch)
    allowed, without = fit("mismatch-hyper-trial-0043", fs_contrast_err=0.15), fit("mismatch-hyper-trial-0043",
                                                                                   fs_contrast_err=0.0)
    assert allowed.nuisance["finite_strain_in_estimate"]
    assert allowed.sigma_depth_m > without.sigma_depth_m and allowed.sigma_x_m > without.sigma_x_m
    assert allowed.chi2_fit < without.chi2_fit       # the readings' allowance in the fit's chi2
    assert allowed.lr == without.lr                  # the evidence is the first fit's: detection does not change
    linear1, linear0 = fit("mismatch-trial-0048", fs_contrast_err=0.15), fit("mismatch-trial-0048",
                                                                              fs_contrast_err=0.0)
    assert not linear1.nuisance["finite_strain_in_estimate"]
    assert (linear1.x_m, linear1.depth_m, linear1.sigma_x_m, linear1.sigma_depth_m) == \
        (linear0.x_m, linear0.depth_m, linear0.sigma_x_m, linear0.sigma_depth_m)
