"""Session 44's review on scenes of its own: a no-stone answer whose no-stone fit the data reject says so, as a
stone's poor fit does (planner.refine.no_stone_caveats; 2D and 3D); a new tissue modulus no longer rebuilds the
finite-strain shape (planner.finite_strain_response.SHAPE_YOUNGS_PA)."""
from __future__ import annotations

import dataclasses

import numpy as np

import planner.finite_strain_response as FS
from fem.scene import load
from fem.tip import contact_scene
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


def test_the_finite_strain_shape_does_not_depend_on_the_tissues_modulus():
    """F_neo-Hookean / F_linear under a rigid tip is the same for any modulus: the shape is built once, at
    SHAPE_YOUNGS_PA, for every modulus (a review's first run with a new modulus rebuilt it: 26 s). Checked by building
    it at two moduli on a coarse section, and every prior of the same geometry shares its key."""
    p = load("paper").prior().with_analysis(mesh_size_m=0.005, surface_refine=2.0)

    def at(e):
        return dataclasses.replace(p, tissue=dataclasses.replace(p.tissue, youngs_pa=e))
    a, b = FS.build_shape(at(2500.0)), FS.build_shape(at(6000.0))
    assert np.array_equal(a.x_m, b.x_m) and np.abs(a.g).max() > 0.1
    assert np.allclose(a.g, b.g, rtol=0, atol=1e-10)
    # (the study's 60 MPa tip is rigid to fem at all three: keyed without its modulus since session 58)
    assert (FS.at_shape_modulus(at(6000.0)).key() == FS.at_shape_modulus(at(1000.0)).key()
            == contact_scene(at(FS.SHAPE_YOUNGS_PA)).key())
