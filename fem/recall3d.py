"""A 3D scene's contact forces as fem computed them before: ``SurfaceModel3D.force_n`` through a ``fem.memo`` per
scene (fem.recall's 3D half; a 3D force costs about a millisecond: the simulated truth's grid and the prior's
force curves are most of ``palpate run block3d --sim`` when solved again)."""
from __future__ import annotations

from functools import lru_cache

from .contact3d import surface_model3d
from .memo import Memo, memo
from .recall import remembered, solver_version
from .scene_mesh import code_version
from .scene_mesh3d import code_version3d


@lru_cache(maxsize=64)
def _spec(scene) -> dict:
    # the whole scene (its tip too: an elastic tip's compliance is part of the force), fem's 3D code, the 2D code it
    # shares (fem.contact's depth checks, fem.tip's rigid-or-elastic decision) and the solver's
    return {"scene3d": scene.key(), "code": code_version3d(), "code2d": code_version(), "solver": solver_version()}


def _memo(scene) -> Memo:
    return memo("forces3d", _spec(scene), n_key=3, width=1)


def known(scene) -> bool:
    """Whether the scene's model answered before (so it builds: its memo holds what it computed)."""
    return len(_memo(scene)) > 0


def force_n(scene, x_m: float, y_m: float, depth_m: float) -> float:
    """``surface_model3d(scene).force_n(x_m, y_m, depth_m)``, remembered."""
    return remembered(_memo(scene), (float(x_m), float(y_m), float(depth_m)),
                      lambda: surface_model3d(scene).force_n(x_m, y_m, depth_m))
