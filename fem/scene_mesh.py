"""A scene's mesh, checked and kept between runs: from the disk cache (fem.diskcache), else meshed with gmsh.

"Skip what a scene doesn't need", across processes: a second run on the same scene skips meshing. Entries are
keyed by the geometry and mesh options only (scenes that differ only in moduli share a mesh) and by the code
version: a hash of the source files that produce cached arrays, gmsh's version and a format number, so editing
the mesher or the assembly invalidates old entries by itself.
"""
from __future__ import annotations

import functools
import importlib.util
import os
import re
import warnings
from pathlib import Path

import numpy as np

from . import diskcache
from .elements import nodes_ref, quadrature, shape_grad
from .mesh import Mesh, estimate_dofs_bound, estimate_nodes, mesh_scene
from .scene import Scene, SceneError

FORMAT = 2
# the modules whose code decides what the cache stores (meshes here, surface operators in fem.contact)
_SOURCES = ("scene_mesh.py", "mesh.py", "assembly.py", "elements.py", "model.py", "contact.py", "schur_lu.py", "tip.py",
            "influence.py", "stress.py", "guards.py")


@functools.lru_cache(maxsize=1)
def gmsh_version() -> str:
    """gmsh's version ("?" when it is not installed), without importing it: the ``GMSH_API_VERSION`` its module
    states near its top (importlib.metadata, 10 ms of imports, only when that line is missing)."""
    try:
        spec = importlib.util.find_spec("gmsh")
    except (ImportError, ValueError):          # a gmsh module already loaded without a spec (a stand-in)
        spec = None
    m = None
    if spec is not None and spec.origin:
        try:
            with open(spec.origin, encoding="utf-8", errors="replace") as f:
                m = re.search(r'^GMSH_API_VERSION\s*=\s*"([^"]+)"', f.read(8192), re.M)
        except OSError:
            pass
    if m:
        return m.group(1)
    import importlib.metadata as metadata  # lazy: only for a gmsh module that does not state its version
    try:
        return metadata.version("gmsh")
    except metadata.PackageNotFoundError:
        return "?"


def sources_version(sources: tuple[str, ...], tag: str) -> str:
    """A hash of fem's source files ``sources``, gmsh's version and ``tag``: a code version for cache keys."""
    here = Path(__file__).resolve().parent
    return diskcache.files_digest([here / name for name in sources], f"{tag}; gmsh {gmsh_version()}")


@functools.lru_cache(maxsize=1)
def code_version() -> str:
    return sources_version(_SOURCES, f"format {FORMAT}")


# Size caps, checked from the scene before gmsh runs (issue 13: a 1e-5 m mesh or a 1000 m tissue hung the machine).
# 2 million DOFs: a P2 mesh of about 250k vertices; meshing, assembly and the sparse LU then take minutes and a few GB
# (the study's finest runs have 40k DOFs). Override with $PALPATE_MAX_DOFS.
MAX_DOFS = 2_000_000
# The contact model keeps a dense compliance of the top nodes (8 n_top^2 bytes): 20000 top nodes are 3.2 GB.
MAX_TOP_NODES = 20_000


def max_dofs() -> int:
    """The DOF cap: $PALPATE_MAX_DOFS if set (a positive integer), else MAX_DOFS."""
    v = os.environ.get("PALPATE_MAX_DOFS", "").strip()
    if not v:
        return MAX_DOFS
    try:
        n = int(float(v))
    except (ValueError, OverflowError):      # not a number; inf
        raise SceneError(f"PALPATE_MAX_DOFS={v!r} must be a positive integer") from None
    if n <= 0:
        raise SceneError(f"PALPATE_MAX_DOFS={v!r} must be a positive integer")
    return n


def estimate_size(scene: Scene) -> dict:
    """The scene's mesh size without meshing (fem.mesh.estimate_nodes: within a factor 2 of gmsh's, tests check):
    {"vertices", "nodes", "dofs", "top_nodes"}."""
    t, a = scene.tissue, scene.analysis
    stones = [(s.x_m, t.height_m - s.depth_m, s.radius_m) for s in scene.stones]
    return estimate_nodes(t.width_m, t.height_m, stones, a.mesh_size_m, a.surface_refine, a.order)


def _what_to_change(scene: Scene) -> str:
    a = scene.analysis
    return (f"increase analysis.mesh_size_m (now {a.mesh_size_m:g} m) or lower analysis.surface_refine (now "
            f"{a.surface_refine:g}), or a smaller tissue (width_m {scene.tissue.width_m:g} m, height_m "
            f"{scene.tissue.height_m:g} m)")


def check_mesh_budget(scene: Scene) -> None:
    """SceneError if the scene's mesh would exceed the DOF cap (max_dofs()). The estimate (estimate_size, ~20 ms)
    is made only when its upper bound (fem.mesh.estimate_dofs_bound, a few us) exceeds the cap."""
    t, a = scene.tissue, scene.analysis
    cap = max_dofs()
    if estimate_dofs_bound(t.width_m, t.height_m, [s.radius_m for s in scene.stones], a.mesh_size_m,
                           a.surface_refine, a.order) <= cap:
        return
    est = estimate_size(scene)
    if est["dofs"] > cap:
        raise SceneError(f"scene {scene.name!r}: the mesh would have about {est['dofs']:.3g} DOFs "
                         f"(P{scene.analysis.order}), above the cap of {cap:.3g} ($PALPATE_MAX_DOFS): "
                         f"{_what_to_change(scene)}")


def check_surface_budget(scene: Scene) -> None:
    """SceneError if the contact model's dense top-surface compliance would exceed MAX_TOP_NODES."""
    a = scene.analysis
    n = (scene.tissue.width_m * a.surface_refine / a.mesh_size_m + 1) * a.order
    if n > MAX_TOP_NODES:
        raise SceneError(f"scene {scene.name!r}: the contact model would have about {n:.3g} top-surface nodes "
                         f"(a dense {8 * n * n / 1e9:.3g} GB compliance), above the cap of {MAX_TOP_NODES}: "
                         f"{_what_to_change(scene)}")


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
    (and stored). use: None follows $PALPATE_CACHE, False skips the disk cache. A scene whose mesh would exceed the
    DOF cap is refused first (check_mesh_budget)."""
    check_mesh_budget(scene)
    return diskcache.load_or_build("mesh", _mesh_spec(scene), build=lambda: checked_mesh(mesh_scene(scene), scene),
                                   to_arrays=Mesh.to_arrays, from_arrays=lambda d: _restored(d, scene), use=use)
