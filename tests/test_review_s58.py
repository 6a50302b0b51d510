"""Session 58: a block whose probed patch is too big for the dense compliance is refused before its stiffness is
assembled (the refusal took 30 s on a 2 mm mesh of a 60 mm face, 18 s of it assembling what was then thrown away;
12 s since, the meshing)."""
from __future__ import annotations

import pytest

import fem.contact3d as contact3d
from fem.model3d import Model3D
from fem.scene import SceneError, load


def test_a_patch_too_big_is_refused_before_the_stiffness_is_assembled(monkeypatch):
    sc = load("block3d").prior().with_analysis(mesh_size_m=0.02, surface_refine=2.0)
    monkeypatch.setattr(contact3d, "MAX_PATCH_NODES", 10)
    monkeypatch.setattr(Model3D, "K", property(lambda self: pytest.fail("the stiffness was assembled")))
    with pytest.raises(SceneError, match=r"top nodes .* above 10: lower analysis\.patch_m or analysis\.surface_refine"):
        contact3d.SurfaceModel3D(sc)
