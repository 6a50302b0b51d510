"""A scene's mesh, checked and kept between runs: from the disk cache (fem.diskcache), else meshed with gmsh.

"Skip what a scene doesn't need", across processes: a second run on the same scene skips meshing. Entries are
keyed by the geometry and mesh options only (scenes that differ only in moduli share a mesh) and by the code
version: a hash of the source files that produce cached arrays, gmsh's version and a format number, so editing
the mesher or the assembly invalidates old entries by itself.
"""
from __future__ import annotations

import functools
import warnings
from importlib import metadata
from pathlib import Path

import numpy as np

from . import diskcache
from .elements import nodes_ref, quadrature, shape_grad
from .mesh import Mesh, mesh_scene
from .scene import Scene, SceneError

FORMAT = 2
# the modules whose code decides what the cache stores (meshes here, surface operators in fem.contact)
_SOURCES = ("scene_mesh.py", "mesh.py", "assembly.py", "elements.py", "model.py", "contact.py", "tip.py")


@functools.lru_cache(maxsize=1)
def code_version() -> str:
    try:
        gv = metadata.version("gmsh")
    except metadata.PackageNotFoundError:
        gv = "?"
    here = Path(__file__).resolve().parent
    return diskcache.files_digest([here / name for name in _SOURCES], f"format {FORMAT}; gmsh {gv}")


def mesh_key(scene: Scene) -> str:
    """The cache key of a scene's mesh: geometry and mesh options (not the moduli), and the code version."""
    return diskcache.digest(_mesh_spec(scene))


def _mesh_spec(scene: Scene) -> dict:
    t, a = scene.tissue, scene.analysis
    geo = {"w": t.width_m, "h": t.height_m, "stones": [(s.x_m, s.depth_m, s.diameter_m) for s in scene.stones],
           "order": a.order, "size": a.mesh_size_m, "refine": a.surface_refine}
    return {"mesh": geo, "code": code_version()}


def _jacobians(mesh: Mesh) -> np.ndarray:
    """(M,) smallest Jacobian determinant of each element over its quadrature points and its nodes."""
    pts = np.vstack([quadrature(2 * (mesh.order - 1))[0], nodes_ref(mesh.order)])
    J = np.einsum("mai,qaj->mqij", mesh.nodes[mesh.tris], shape_grad(mesh.order, pts))
    return (J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]).min(axis=1)


def checked_mesh(mesh: Mesh, scene: Scene) -> Mesh:
    """A mesh whose elements all have positive Jacobians. Curved P2 elements squeezed into a thin gap (a stone a
    fraction of an element below the surface or beside an edge) can invert; their edges are then straightened
    (the stone boundary is a chord there, an error of order gap^2 / R in its position, with a warning). A mesh
    that still has inverted elements is refused with a SceneError saying what to change."""
    det = _jacobians(mesh)
    if np.all(det > 0) and np.all(np.isfinite(mesh.nodes)):
        return mesh
    bad = np.flatnonzero(~(det > 0))
    if mesh.order == 2:
        t = mesh.tris[bad]
        for mid, (a, b) in zip((3, 4, 5), ((0, 1), (1, 2), (2, 0))):
            mesh.nodes[t[:, mid]] = 0.5 * (mesh.nodes[t[:, a]] + mesh.nodes[t[:, b]])
        det = _jacobians(mesh)
        if np.all(det > 0):
            warnings.warn(f"scene {scene.name!r}: {len(bad)} curved P2 element(s) inverted in a thin gap (a stone "
                          f"close to an edge) were straightened; refine the mesh there for a curved boundary",
                          stacklevel=3)
            return mesh
    gaps = []
    t = scene.tissue
    for i, s in enumerate(scene.stones):
        g = min(s.depth_m - s.radius_m, t.height_m - s.depth_m - s.radius_m, s.x_m - s.radius_m,
                t.width_m - s.x_m - s.radius_m)
        gaps.append(f"stone[{i}] {g * 1e3:.3g} mm from an edge")
    a = scene.analysis
    raise SceneError(f"scene {scene.name!r}: the mesh has {int((det <= 0).sum())} inverted element(s) "
                     f"({'; '.join(gaps) or 'no stones'}; top-surface element size "
                     f"{a.mesh_size_m / a.surface_refine * 1e3:.3g} mm): use a finer mesh (smaller mesh_size_m or "
                     f"larger surface_refine) so elements fit in the gap")


def _restored(arrays: dict[str, np.ndarray], scene: Scene) -> Mesh:
    mesh = Mesh.from_arrays(arrays)
    t = scene.tissue
    if (mesh.order != scene.analysis.order or mesh.region.max() > len(scene.stones)
            or (mesh.width_m, mesh.height_m) != (t.width_m, t.height_m)):
        raise ValueError("inconsistent with the scene")
    return mesh


def mesh_for(scene: Scene, use: bool | None = None) -> Mesh:
    """The scene's mesh (every element checked for a positive Jacobian): from the disk cache, else meshed with gmsh
    (and stored). use: None follows $PALPATE_CACHE, False skips the disk cache."""
    return diskcache.load_or_build("mesh", _mesh_spec(scene), build=lambda: checked_mesh(mesh_scene(scene), scene),
                                   to_arrays=Mesh.to_arrays, from_arrays=lambda d: _restored(d, scene), use=use)
