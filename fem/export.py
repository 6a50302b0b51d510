"""Field export for ParaView: one VTU file (meshio) with the mesh, nodal displacement, stresses and strains.

P1 meshes are written as ``triangle``, P2 as ``triangle6`` (gmsh's node order, vertices then the mid-edge nodes of
edges 0-1, 1-2, 2-0, is VTK's quadratic-triangle order). Points are padded to 3D (z = 0) and the displacement is a
3-vector, so ParaView's "Warp By Vector" works on it directly. Cell data ``region``: 0 tissue, k stone k.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .mesh import Mesh

CELL_TYPE = {1: "triangle", 2: "triangle6"}


def to_meshio(mesh: Mesh, u: np.ndarray | None = None, point_data: dict[str, np.ndarray] | None = None,
              cell_data: dict[str, np.ndarray] | None = None):
    """A meshio.Mesh of ``mesh`` with displacement ``u`` (interleaved ux, uy; written as point vector "u") and
    further per-node scalars ``point_data`` and per-element scalars ``cell_data`` (``region`` always added)."""
    import meshio  # lazy: a heavy import, only needed when a file is written (keeps `import fem` fast)
    n = mesh.n_nodes
    points = np.zeros((n, 3))
    points[:, :2] = mesh.nodes
    pdata: dict[str, np.ndarray] = {}
    if u is not None:
        u = np.asarray(u, dtype=float)
        if u.shape != (2 * n,):
            raise ValueError(f"u must have 2 * n_nodes = {2 * n} entries, got {u.shape}")
        u3 = np.zeros((n, 3))
        u3[:, :2] = u.reshape(-1, 2)
        pdata["u"] = u3
    for k, v in (point_data or {}).items():
        v = np.asarray(v, dtype=float)
        if len(v) != n:
            raise ValueError(f"point data {k!r} has {len(v)} values for {n} nodes")
        pdata[k] = v
    cdata = {"region": [np.asarray(mesh.region, dtype=np.int32)]}
    for k, v in (cell_data or {}).items():
        v = np.asarray(v)
        if len(v) != len(mesh.tris):
            raise ValueError(f"cell data {k!r} has {len(v)} values for {len(mesh.tris)} elements")
        cdata[k] = [v]
    return meshio.Mesh(points, [(CELL_TYPE[mesh.order], np.asarray(mesh.tris, dtype=np.int64))],
                       point_data=pdata, cell_data=cdata)


def write_vtu(path: str | Path, mesh: Mesh, u: np.ndarray | None = None,
              point_data: dict[str, np.ndarray] | None = None,
              cell_data: dict[str, np.ndarray] | None = None) -> Path:
    """Write a VTU file (binary, zlib-compressed); returns the path. Parent directories are created."""
    path = Path(path)
    if path.suffix != ".vtu":
        raise ValueError(f"expected a .vtu path, got {path}")
    path.parent.mkdir(parents=True, exist_ok=True)
    to_meshio(mesh, u, point_data, cell_data).write(path, file_format="vtu")
    return path


def write_result_vtu(path: str | Path, result) -> Path:
    """Write a fem.uniform.UniformResult (or anything with ``model.mesh``, ``u`` and a ``nodal`` field dict):
    displacement, stresses (sxx_pa, syy_pa, sxy_pa, szz_pa, von_mises_pa) and strains (exx, eyy, gxy)."""
    if result.nodal is None:
        raise ValueError("the result has no full-field data: solve with full_field=True")
    return write_vtu(path, result.model.mesh, result.u, point_data=result.nodal)
