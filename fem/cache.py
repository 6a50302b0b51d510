"""The disk cache: a scene's mesh and its condensed surface operator, kept between runs.

"Skip what a scene doesn't need", across processes: a second run on the same scene skips meshing (gmsh) and the
Schur factorization. Entries are keyed by the scene's content (``Scene.key()``: the name is ignored), the options
that change the result, and a code version (a hash of the source files that produce the cached arrays plus gmsh's
version and the format number), so editing the mesher or the assembly invalidates old entries by itself.

What is stored (numpy ``.npz``, no pickle):
- ``mesh-<key>.npz``: nodes, triangles, regions (key: geometry and mesh options only, so scenes that differ only in
  moduli share a mesh).
- ``surface-<key>.npz``: the compliance C of the top surface (and an elastic tip's arc compliance). SuperLU's
  factors cannot be pickled and rebuilding a solver from stored L/U factors is slower in scipy than refactoring, so
  the factorization is *not* stored: a restored SurfaceModel answers force queries (the LCP needs only C) at once
  and factorizes K on the first request for fields (stresses, displacements). The restored C is bitwise the C a
  fresh build computes (tests check it), so the cache introduces no error.

Location: ``$PALPATE_CACHE_DIR`` or ``~/.cache/palpate``; ``PALPATE_CACHE=0`` disables it. Writes are atomic
(temporary file + rename); an unreadable or inconsistent entry is ignored with a warning and rebuilt.
"""
from __future__ import annotations

import functools
import hashlib
import json
import os
import tempfile
import warnings
from pathlib import Path

import numpy as np

FORMAT = 1
_SOURCES = ("mesh.py", "assembly.py", "elements.py", "model.py", "contact.py", "tip.py")
stats = {"mesh_hit": 0, "mesh_miss": 0, "surface_hit": 0, "surface_miss": 0, "corrupt": 0}


def enabled(use: bool | None = None) -> bool:
    if use is not None:
        return bool(use)
    return os.environ.get("PALPATE_CACHE", "1").strip().lower() not in ("0", "false", "no", "off")


def cache_dir() -> Path:
    d = os.environ.get("PALPATE_CACHE_DIR")
    return Path(d) if d else Path.home() / ".cache" / "palpate"


@functools.lru_cache(maxsize=1)
def code_version() -> str:
    from importlib import metadata
    try:
        gv = metadata.version("gmsh")
    except metadata.PackageNotFoundError:
        gv = "?"
    h = hashlib.sha256(f"format {FORMAT}; gmsh {gv}".encode())
    here = Path(__file__).resolve().parent
    for name in _SOURCES:
        h.update((here / name).read_bytes())
    return h.hexdigest()[:12]


def _digest(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:20]


def mesh_key(scene) -> str:
    t, a = scene.tissue, scene.analysis
    geo = {"w": t.width_m, "h": t.height_m, "stones": [(s.x_m, s.depth_m, s.diameter_m) for s in scene.stones],
           "order": a.order, "size": a.mesh_size_m, "refine": a.surface_refine}
    return _digest({"mesh": geo, "code": code_version()})


def surface_key(scene, options: dict) -> str:
    return _digest({"scene": scene.key(), "options": options, "code": code_version()})


def _write(path: Path, arrays: dict) -> None:
    """Atomic write: a temporary file in the same directory, renamed over the entry."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.stem + ".", suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as f:
                np.savez(f, **arrays)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    except OSError as e:   # a read-only or full disk must not stop an analysis
        warnings.warn(f"palpate cache: could not write {path}: {e}", stacklevel=3)


def _read(path: Path, required: tuple[str, ...]) -> dict | None:
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            out = {k: z[k] for k in z.files}
        missing = [k for k in required if k not in out]
        if missing:
            raise ValueError(f"missing arrays {missing}")
        return out
    except Exception as e:  # noqa: BLE001 - any damage means: ignore the entry and rebuild
        stats["corrupt"] += 1
        warnings.warn(f"palpate cache: ignoring unreadable entry {path} ({type(e).__name__}: {e}); rebuilding",
                      stacklevel=3)
        return None


def _jacobians(mesh) -> np.ndarray:
    """(M,) smallest Jacobian determinant of each element over its quadrature points and its nodes."""
    from .elements import nodes_ref, quadrature, shape_grad
    pts = np.vstack([quadrature(2 * (mesh.order - 1))[0], nodes_ref(mesh.order)])
    J = np.einsum("mai,qaj->mqij", mesh.nodes[mesh.tris], shape_grad(mesh.order, pts))
    return (J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]).min(axis=1)


def checked_mesh(mesh, scene):
    """A mesh whose elements all have positive Jacobians. Curved P2 elements squeezed into a thin gap (a stone a
    fraction of an element below the surface or beside an edge) can invert; their edges are then straightened
    (the stone boundary is a chord there, an error of order gap^2 / R in its position, with a warning). A mesh
    that still has inverted elements is refused with a SceneError saying what to change."""
    from .scene import SceneError
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


def mesh_for(scene, use: bool | None = None):
    """The scene's mesh (every element checked for a positive Jacobian): from the disk cache, else meshed with gmsh
    (and stored)."""
    from .mesh import Mesh, mesh_scene
    if not enabled(use):
        return checked_mesh(mesh_scene(scene), scene)
    path = cache_dir() / f"mesh-{mesh_key(scene)}.npz"
    d = _read(path, ("nodes", "tris", "region", "order"))
    if d is not None:
        t = scene.tissue
        try:
            mesh = Mesh(nodes=d["nodes"], tris=d["tris"], region=d["region"], order=int(d["order"]),
                        width_m=t.width_m, height_m=t.height_m)
            if (mesh.order != scene.analysis.order or mesh.tris.max() >= mesh.n_nodes
                    or mesh.region.max() > len(scene.stones) or not np.all(np.isfinite(mesh.nodes))):
                raise ValueError("inconsistent with the scene")
            stats["mesh_hit"] += 1
            return mesh
        except Exception as e:  # noqa: BLE001
            stats["corrupt"] += 1
            warnings.warn(f"palpate cache: ignoring entry {path} ({e}); rebuilding", stacklevel=2)
    stats["mesh_miss"] += 1
    mesh = checked_mesh(mesh_scene(scene), scene)
    _write(path, {"nodes": mesh.nodes, "tris": mesh.tris, "region": mesh.region, "order": np.int64(mesh.order)})
    return mesh


def load_or_build_surface(scene, options: dict, use: bool | None = None):
    """A SurfaceModel restored from the disk cache (compliance, tip), else built and stored."""
    from .contact import SurfaceModel
    from .model import build_model
    from .tip import TipCompliance
    if not enabled(use):
        return SurfaceModel(scene, model=build_model(scene, mesh=mesh_for(scene, use=False),
                                                     rigid_stones=options.get("rigid_stones", "auto")), **options)
    path = cache_dir() / f"surface-{surface_key(scene, options)}.npz"
    d = _read(path, ("C",))
    model = build_model(scene, mesh=mesh_for(scene, use=True), rigid_stones=options.get("rigid_stones", "auto"))
    if d is not None:
        C = d["C"]
        n_top = len(model.mesh.top)
        if C.shape == (n_top, n_top) and np.all(np.isfinite(C)):
            tip = None
            if "tip_C" in d:
                tip = TipCompliance.__new__(TipCompliance)
                tip.C, tip.s = d["tip_C"], d["tip_s"]
            stats["surface_hit"] += 1
            return SurfaceModel(scene, model=model, _compliance=C, _tip=tip, **options)
        stats["corrupt"] += 1
        warnings.warn(f"palpate cache: ignoring entry {path} (compliance of shape {C.shape}, expected "
                      f"({n_top}, {n_top}) and finite); rebuilding", stacklevel=2)
    stats["surface_miss"] += 1
    sm = SurfaceModel(scene, model=model, **options)
    arrays = {"C": sm.C}
    if sm.tip is not None:
        arrays.update(tip_C=sm.tip.C, tip_s=sm.tip.s)
    _write(path, arrays)
    return sm


def clear(directory: Path | None = None) -> int:
    """Delete the cache's entries; returns how many."""
    d = directory or cache_dir()
    n = 0
    for f in list(d.glob("mesh-*.npz")) + list(d.glob("surface-*.npz")) + list(d.glob("*.tmp")):
        f.unlink(missing_ok=True)
        n += 1
    return n
