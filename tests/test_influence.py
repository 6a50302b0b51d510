"""The influence operators (fem.influence) give the batched back-substitution's stresses and inversion verdicts."""
from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import warnings

import numpy as np
import pytest

import fem.influence as FI
from fem import scene as S
from fem.contact import SurfaceModel, load_or_build_surface
from fem.guards import InvertedElementsError

MESH = dict(mesh_size_m=0.004, surface_refine=4.0)
XS = np.array([0.0051, 0.012, 0.0297, 0.035, 0.0412, 0.0649])        # edges, over the stone, beside it


def _pair(scene):
    return SurfaceModel(scene, use_influence=False), SurfaceModel(scene)


def _same(a, b):
    assert b.force_n == a.force_n
    assert b.max_von_mises_pa == pytest.approx(a.max_von_mises_pa, rel=1e-10)
    assert b.max_von_mises_at_m == pytest.approx(a.max_von_mises_at_m, abs=1e-12)
    np.testing.assert_allclose(b.pressure_pa, a.pressure_pa, rtol=0, atol=1e-9 * a.pressure_pa.max())


@pytest.mark.parametrize("name", ["paper", "paper-left"])
def test_influence_matches_back_substitution(name):
    plain, fast = _pair(S.load(name).with_analysis(**MESH))
    assert fast.influence() is not None and plain.influence() is None
    for depth in (0.001, 0.004):
        for a, b in zip(plain.indent_many(XS, depth), fast.indent_many(XS, depth)):
            _same(a, b)


def test_fallbacks_give_the_same_answer(monkeypatch):
    """Window certificates that fail (a far bound forced up) fall back to the whole band and the plain check."""
    plain, fast = _pair(S.load("paper").with_analysis(**MESH))
    inf = fast.influence()
    fast._influence = dataclasses.replace(inf, vm_far=inf.vm_far + 1e9, g_far=inf.g_far + 1.0)
    calls = []
    monkeypatch.setattr(FI, "deformation", lambda *a, **k: calls.append(1) or deformation(*a, **k))
    for a, b in zip(plain.indent_many(XS, 0.003), fast.indent_many(XS, 0.003)):
        _same(a, b)
    assert len(calls) == len(XS)                    # every waypoint took the plain inversion check


deformation = FI.deformation


def test_operator_budget_keeps_back_substitution(monkeypatch):
    monkeypatch.setattr(FI, "MAX_OPERATOR_BYTES", 0)
    plain, fast = _pair(S.load("paper").with_analysis(**MESH))
    assert fast.influence() is None
    _same(plain.indent(0.035, 0.003), fast.indent(0.035, 0.003))


def test_inversion_found_from_the_operators():
    """A stone 0.2 mm under the surface, the 4 mm load scaled from a shallow one (the waypoint check bypassed):
    the operators flag the elements under the tip and the exact check on them refuses, as the plain check does."""
    stone = S.Stone(x_m=0.035, depth_m=0.0052, diameter_m=0.010)
    sc = S.load("paper").with_stones([stone]).with_analysis(mesh_size_m=0.003, surface_refine=8.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        sm = SurfaceModel(sc)
    idx, f, _ = sm.contact_forces(0.035, 0.00014)
    inf = sm.influence()
    inf.check(sm.model, idx, f, 0.035, full=None, what="shallow", hint="h")      # the real load: fine
    big = f * (0.004 / 0.00014)
    F = np.zeros((len(sm.top), 1))
    F[idx, 0] = big
    with pytest.raises(InvertedElementsError, match="turn inside out") as plain:
        sm.check_deformation(sm.displacements(F), [0.035], [0.004])
    with pytest.raises(InvertedElementsError, match="turn inside out") as fast:
        inf.check(sm.model, idx, big, 0.035, full=None, what="scene", hint="h")
    n_bad = lambda e: int(str(e.value).split(" of ")[0].rsplit(" ", 1)[1])  # noqa: E731
    assert n_bad(fast) == n_bad(plain)


def test_disk_round_trip(tmp_path, monkeypatch):
    monkeypatch.setenv("PALPATE_CACHE_DIR", str(tmp_path))
    sc = S.load("healthy").with_analysis(**MESH)
    built = load_or_build_surface(sc, {}, use=True)
    r0 = built.indent(0.03, 0.003)                 # one waypoint: no operators built (the back-substitution)
    assert not any(tmp_path.rglob("influence*")) and built._influence is None
    again = load_or_build_surface(sc, {}, use=True)
    assert again.influence() is not None and any(tmp_path.rglob("influence*"))
    for k, v in built.influence().to_arrays().items():
        np.testing.assert_array_equal(again.influence().to_arrays()[k], v)
    _same(r0, again.indent(0.03, 0.003))
    arrays = built.influence().to_arrays()
    arrays["g"] = arrays["g"][:, :-1]
    with pytest.raises(ValueError, match="do not fit"):
        FI.Influence.from_arrays(arrays, built.model, built.band_m, len(built.top))


def test_cached_scene_predicts_without_scipy(tmp_path):
    """Start-up (issue 19): with the surface and influence operators on disk, a new process predicts forces and
    stresses with numpy alone (scipy, a third of a second to import, is not loaded)."""
    code = ("import sys, numpy as np\n"
            "from fem import scene as S\n"
            "from fem.contact import surface_model\n"
            f"sc = S.load('paper').with_analysis(mesh_size_m={MESH['mesh_size_m']}, "
            f"surface_refine={MESH['surface_refine']})\n"
            "m = surface_model(sc)\n"
            "r = m.indent_many(np.linspace(0.006, 0.064, 60), 0.003)\n"
            "print(m.influence() is not None, min(x.max_von_mises_pa for x in r) > 0, "
            "any(k.startswith('scipy') for k in sys.modules))\n")
    env = dict(os.environ, PALPATE_CACHE_DIR=str(tmp_path), PALPATE_CACHE="1")
    run = lambda: subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,  # noqa: E731
                                 check=True).stdout.split()
    assert run() == ["True", "True", "True"]         # cold: meshed, factorized and built (scipy needed)
    assert run() == ["True", "True", "False"]        # cached: numpy only


def test_warm_started_sweep_gives_each_waypoints_own_answer():
    """indent_many starts each LCP from its neighbour's contact width (same depth): the forces are each waypoint's
    cold solve's (the solver is exact from any start), across a depth change and over the stone."""
    sm = SurfaceModel(S.load("paper").with_analysis(**MESH))
    xs = np.r_[np.linspace(0.0055, 0.0645, 30), np.linspace(0.0645, 0.0055, 7)]
    depths = np.r_[np.full(20, 0.003), np.full(10, 0.0045), np.full(7, 0.001)]
    for r, x, d in zip(sm.indent_many(xs, depths, stresses=False), xs, depths):
        idx, f, _ = sm.contact_forces(float(x), float(d))
        np.testing.assert_allclose(r.nodal_force_n_per_m, f, rtol=1e-12, atol=1e-12 * f.max())


def test_depth_sweep_gives_each_depths_own_force():
    """force_curve_n starts each depth's LCP from the contact the shallower one reached: the forces are the cold
    solves' exactly (the same final active set, solved the same way), over the depths the localizer tabulates
    (0.06 to 0.96 tip radii: planner.tissue_response), over the stone, beside it and at the section's ends."""
    sm = SurfaceModel(S.load("paper").with_analysis(**MESH))
    R = sm.scene.indenter.radius_m
    depths = np.exp(np.linspace(np.log(0.06 * R), np.log(0.96 * R), 32))
    for x in (0.0, 0.0051, 0.0297, 0.035, 0.07):
        cold = np.array([sm.force_n(x, float(d)) for d in depths])
        np.testing.assert_array_equal(sm.force_curve_n(x, depths), cold)
        assert np.all(np.diff(cold) > 0)                    # the sweep covers contact growing with depth
