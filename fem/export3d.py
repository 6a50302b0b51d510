"""3D field export for ParaView: one VTU file (meshio) with the tetrahedral mesh, displacement and nodal fields.

P1 meshes are written as ``tetra``, P2 as ``tetra10``: VTK's quadratic tetrahedron orders its mid-edge nodes
(0,1), (1,2), (2,0), (0,3), (1,3), (2,3), gmsh's (fem.elements3d) (0,1), (1,2), (2,0), (3,0), (3,2), (3,1): the
last two are swapped on writing. Cell data ``region``: 0 tissue, k stone k.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .mesh3d import Mesh3D

CELL_TYPE = {1: "tetra", 2: "tetra10"}
TO_VTK = {1: [0, 1, 2, 3], 2: [0, 1, 2, 3, 4, 5, 6, 7, 9, 8]}


def write_vtu3d(path: str | Path, mesh: Mesh3D, u: np.ndarray | None = None,
                point_data: dict[str, np.ndarray] | None = None) -> Path:
    """Write a VTU file with displacement ``u`` (3N interleaved; point vector "u") and per-node scalars."""
    import meshio  # lazy: only needed when a file is written
    path = Path(path)
    if path.suffix != ".vtu":
        raise ValueError(f"expected a .vtu path, got {path}")
    n = mesh.n_nodes
    pdata: dict[str, np.ndarray] = {}
    if u is not None:
        u = np.asarray(u, dtype=float)
        if u.shape != (3 * n,):
            raise ValueError(f"u must have 3 * n_nodes = {3 * n} entries, got {u.shape}")
        pdata["u"] = u.reshape(-1, 3)
    for k, v in (point_data or {}).items():
        v = np.asarray(v, dtype=float)
        if len(v) != n:
            raise ValueError(f"point data {k!r} has {len(v)} values for {n} nodes")
        pdata[k] = v
    cells = [(CELL_TYPE[mesh.order], np.asarray(mesh.tets[:, TO_VTK[mesh.order]], dtype=np.int64))]
    path.parent.mkdir(parents=True, exist_ok=True)
    meshio.Mesh(mesh.nodes, cells, point_data=pdata,
                cell_data={"region": [np.asarray(mesh.region, dtype=np.int32)]}).write(path, file_format="vtu")
    return path
