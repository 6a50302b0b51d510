"""Session 44's review on scenes of its own: a no-stone answer whose no-stone fit the data reject says so, as a
stone's poor fit does (planner.refine.no_stone_caveats; 2D and 3D)."""
from __future__ import annotations

from planner.localize import Localization
from planner.localize3d import Localization3D
from planner.refine import describe
from planner.refine3d import describe3d


def test_a_no_stone_answer_from_a_poor_fit_is_warned():
    # the review's healthy soft block under a high surface: chi2 65.8 without a stone, 25 degrees of freedom with one
    poor = Localization(detected=False, lr=1.5, lr_threshold=20.0, chi2_0=65.8, chi2_1=64.3, dof_1=25,
                        peak_contrast_n=0.001)
    assert describe(poor).startswith("no stone (LR 1.5 < 20") and \
        "warning: poor fit without a stone: chi2 66 on 28 degrees of freedom" in describe(poor)
    fine = Localization(detected=False, lr=1.5, lr_threshold=20.0, chi2_0=45.0, chi2_1=43.5, dof_1=25,
                        peak_contrast_n=0.001)          # 28 + 4 sqrt(56) = 57.9: within
    assert "warning" not in describe(fine)
    assert "warning" not in describe(Localization(detected=False, lr=float("nan"), lr_threshold=float("nan")))
    poor3 = Localization3D(detected=False, lr=3.4, lr_threshold=25.0, chi2_0=90.0, chi2_1=86.6, dof_1=24,
                           peak_contrast_n=0.001)       # 28 + 4 sqrt(56) = 57.9
    assert "poor fit without a stone: chi2 90 on 28 degrees of freedom" in describe3d(poor3)
