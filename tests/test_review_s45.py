"""Session 45: the surrogate's error check skips what fem refuses; a run on a tissue the localizer has no finite-strain shape for says so and builds it before probing
(app.commands.run.prepare_finite_strain), where it was built silently inside the first fit (about half a minute)."""
from __future__ import annotations

import pytest

import app.commands.run as run_cmd
from app.errors import UsageError
from fem.scene import load
from planner.surrogate import check_error, load_surrogate


def test_a_missing_finite_strain_shape_is_built_before_probing_and_said(monkeypatch, capsys):
    prior = load("paper").prior()
    calls = []

    def fake(p, build=True):
        calls.append(build)
        return "shape" if build else None
    monkeypatch.setattr(run_cmd, "prior_finite_strain", fake)
    run_cmd.prepare_finite_strain(prior, "paper")
    err = capsys.readouterr().err
    assert calls == [False, True]
    assert f"building it before probing ({len(run_cmd.x_nodes(prior))} fem sweeps" in err
    assert "finite-strain shape built in" in err

    calls.clear()                                      # there already: nothing said, nothing built
    monkeypatch.setattr(run_cmd, "prior_finite_strain", lambda p, build=True: calls.append(build) or "shape")
    run_cmd.prepare_finite_strain(prior, "paper")
    assert calls == [False] and capsys.readouterr().err == ""

    def failing(p, build=True):
        if build:
            raise RuntimeError("contact did not converge")
    monkeypatch.setattr(run_cmd, "prior_finite_strain", failing)
    with pytest.raises(UsageError, match="paper cannot be modelled: contact did not converge"):
        run_cmd.prepare_finite_strain(prior, "paper")


def test_a_3d_prior_needs_no_finite_strain_shape(monkeypatch):
    monkeypatch.setattr(run_cmd, "prior_finite_strain", lambda p, build=True: pytest.fail("asked for a 3D prior"))
    run_cmd.prepare_finite_strain(load("block3d").prior(), "block3d")


def test_the_surrogates_error_check_leaves_out_the_probes_fem_refuses():
    """`python -m planner.surrogate paper --check N` crashed once fem refused a probe too near a shallow stone (a
    review): those probes are left out and counted, and the table still agrees with direct fem on the others (seed
    0: the first of 3 stones has 19 of its 61 probes refused; measured RMS 0.29 %, pointwise 1.1 % of the peak)."""
    prior = load("paper").prior()
    r = check_error(load_surrogate(prior, build=False), prior, n=3, seed=0)
    assert r["n_compared"] == 3 and r["probes_refused"] == sum(s["refused"] for s in r["stones"]) > 0
    assert r["rel_rms_max"] < 0.01 and r["rel_max_max"] < 0.03
