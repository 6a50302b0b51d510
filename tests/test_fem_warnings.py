"""fem's accuracy warnings state only what is computed for the scene at hand: no figures measured on another scene
(the paper scene's locking errors or round-off were once printed for every scene)."""
from __future__ import annotations

import dataclasses
import warnings

from fem import scene as S
from fem.model import warn_if_ill_conditioned, warn_if_locking


def _messages(fn, *args) -> list[str]:
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        fn(*args)
    return [str(x.message) for x in w]


def test_locking_warning_on_another_scene_states_only_its_own_figures():
    sc = S.load("healthy")
    sc = dataclasses.replace(sc, name="soft-gel", tissue=dataclasses.replace(sc.tissue, poisson=0.495))
    (msg,) = _messages(warn_if_locking, sc)
    assert "volumetric locking" in msg and "0.495" in msg and "soft-gel" in msg
    for paper_figure in ("paper", "+0.5 %", "+63 %", "0.4999"):
        assert paper_figure not in msg, msg
    assert f"{2 * 1.495 / (3 * 0.01):.3g}" in msg          # this scene's bulk-to-shear ratio


def test_ill_conditioning_warning_states_only_this_scene_s_figures():
    sc = S.load("paper-left")
    stiff = dataclasses.replace(sc.stones[0], youngs_pa=sc.tissue.youngs_pa * 3e9)
    (msg,) = _messages(warn_if_ill_conditioned, sc.with_stones([stiff]), [False])
    assert "round-off" in msg and "3.0e+09" in msg and "paper-left" in msg
    for paper_figure in ("4e-5", "6e-3", "1e10", "1e12"):
        assert paper_figure not in msg, msg


def test_no_warning_when_not_needed():
    sc = S.load("paper")
    assert _messages(warn_if_locking, sc) == []
    assert _messages(warn_if_ill_conditioned, sc, [True]) == []
