"""A 3D scene's mesh, checked and kept between runs: from the disk cache (fem.diskcache), else meshed with gmsh.

As fem.scene_mesh for 2D: entries are keyed by the geometry and mesh options (not the moduli) and by a code version
(a hash of the 3D sources that decide what is stored, gmsh's version and a format number). Scenes whose mesh would
exceed the DOF cap ($PALPATE_MAX_DOFS) are refused before gmsh runs.
"""
from __future__ import annotations

import functools
import warnings

import numpy as np

from . import diskcache
from .elements3d import nodes_ref, quadrature, shape_grad
from .mesh3d import Mesh3D, estimate_nodes3d, mesh_scene3d
from .scene import Scene, SceneError
from .scene_mesh import max_dofs, sources_version

FORMAT = 1
_SOURCES = ("scene_mesh3d.py", "mesh3d.py", "assembly3d.py", "elements3d.py", "model3d.py", "contact3d.py", "condense.py",
            "tip3d.py", "interior_factor.py", "schur_lu.py")


@functools.lru_cache(maxsize=1)
def code_version3d() -> str:
    return sources_version(_SOURCES, f"3d format {FORMAT}")


def check_mesh_budget3d(scene: Scene) -> dict:
    """SceneError if the 3D scene's mesh would exceed the DOF cap (max_dofs()); else its estimate."""
    est = estimate_nodes3d(scene)
    cap = max_dofs()
    a, t = scene.analysis, scene.tissue
    if est["dofs"] > cap:
        raise SceneError(f"scene {scene.name!r}: the 3D mesh would have about {est['dofs']:.3g} DOFs "
                         f"(P{a.order} tetrahedra), above the cap of {cap:.3g} ($PALPATE_MAX_DOFS): increase "
                         f"analysis.mesh_size_m (now {a.mesh_size_m:g} m) or lower analysis.surface_refine (now "
                         f"{a.surface_refine:g}) or analysis.patch_m (now {a.patch_m}), or a smaller block "
                         f"({t.width_m:g} x {t.length_m:g} x {t.height_m:g} m)")
    return est


def _mesh_spec(scene: Scene) -> dict:
    t, a = scene.tissue, scene.analysis
    geo = {"w": t.width_m, "l": t.length_m, "h": t.height_m,
           "stones": [(s.x_m, s.y_m, s.depth_m, s.diameter_m) for s in scene.stones],
           "order": a.order, "size": a.mesh_size_m, "refine": a.surface_refine, "patch": a.patch_m,
           "grade": a.grade}
    return {"mesh3d": geo, "code": code_version3d()}


def jacobians3d(mesh: Mesh3D) -> np.ndarray:
    """(M,) smallest Jacobian determinant of each element over its quadrature points and its nodes."""
    pts = np.vstack([quadrature(2 * (mesh.order - 1))[0], nodes_ref(mesh.order)])
    J = np.einsum("mai,qaj->mqij", mesh.nodes[mesh.tets], shape_grad(mesh.order, pts))
    return np.linalg.det(J).min(axis=1)


def checked_mesh3d(mesh: Mesh3D, scene: Scene) -> Mesh3D:
    """The mesh if every element has a positive Jacobian, else a SceneError saying what to change."""
    if mesh.straightened:
        warnings.warn(f"scene {scene.name!r}: {mesh.straightened} curved P2 element(s) folded on a coarse stone "
                      f"surface were straightened; refine the mesh there for a curved boundary", stacklevel=3)
    det = jacobians3d(mesh)
    if np.all(det > 0) and np.all(np.isfinite(mesh.nodes)):
        return mesh
    a = scene.analysis
    raise SceneError(f"scene {scene.name!r}: the 3D mesh has {int((~(det > 0)).sum())} inverted element(s) (a "
                     f"stone close to a face?): use a finer mesh (smaller mesh_size_m, now {a.mesh_size_m:g} m, or "
                     f"larger surface_refine, now {a.surface_refine:g})")


def _restored(arrays: dict[str, np.ndarray], scene: Scene) -> Mesh3D:
    mesh = Mesh3D.from_arrays(arrays)
    t = scene.tissue
    if (mesh.order != scene.analysis.order or mesh.region.max() > len(scene.stones)
            or (mesh.width_m, mesh.length_m, mesh.height_m) != (t.width_m, t.length_m, t.height_m)):
        raise ValueError("inconsistent with the scene")
    return mesh


def mesh_for3d(scene: Scene, use: bool | None = None) -> Mesh3D:
    """The 3D scene's checked mesh: from the disk cache, else meshed with gmsh (and stored). use: None follows
    $PALPATE_CACHE, False skips the disk cache."""
    if not scene.is_3d:
        raise SceneError(f"scene {scene.name!r} is 2D (no tissue.length_m); use fem.scene_mesh.mesh_for")
    check_mesh_budget3d(scene)
    return diskcache.load_or_build("mesh3d", _mesh_spec(scene),
                                   build=lambda: checked_mesh3d(mesh_scene3d(scene), scene),
                                   to_arrays=Mesh3D.to_arrays, from_arrays=lambda d: _restored(d, scene), use=use)
