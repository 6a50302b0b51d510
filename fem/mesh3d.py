"""Meshing a 3D block with glued spherical stones (gmsh tetrahedra, P1 or P2).

The block is [0, width] x [0, length] x [0, height] (z up, the top face at z = height). A stone's sphere surface is
a mesh surface shared by tissue and stone (glued = shared nodes). The element size is ``size_m`` far away,
``size_m / surface_refine`` on the probed patch of the top face (a centred square of side ``patch_m``; the whole
top face when None), growing linearly with the distance from it (slope GRADE), and ``2 size_m / surface_refine``
on the stones' surfaces, growing with the same slope.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from .elements3d import EDGES, nodes_ref, quadrature, shape_grad
from .mesh import _GMSH_LOCK, _start

GRADE = 0.5   # element size grows by this much per unit distance from the probed patch and from the stones


@dataclass
class Mesh3D:
    nodes: np.ndarray           # (N, 3) coordinates, m
    tets: np.ndarray            # (M, 4) or (M, 10) node indices, gmsh order (fem.elements3d)
    region: np.ndarray          # (M,) 0 = tissue, k = stone k-1
    order: int
    width_m: float
    length_m: float
    height_m: float
    top: np.ndarray = field(default=None)     # node indices on the top face z = height, sorted by (x, y)
    bottom: np.ndarray = field(default=None)  # node indices on the bottom face z = 0, sorted by (x, y)
    straightened: int = 0       # curved P2 elements that folded on a coarse sphere and were made straight

    def __post_init__(self):
        tol = 1e-9 * max(self.width_m, self.length_m, self.height_m)
        z = self.nodes[:, 2]
        if self.top is None:
            self.top = _sorted_xy(self.nodes, np.flatnonzero(np.abs(z - self.height_m) < tol))
        if self.bottom is None:
            self.bottom = _sorted_xy(self.nodes, np.flatnonzero(np.abs(z) < tol))

    dim = 3

    @property
    def tris(self) -> np.ndarray:      # the 2D Mesh's name for the connectivity (shared helpers use it)
        return self.tets

    @property
    def n_nodes(self) -> int:
        return len(self.nodes)

    @property
    def n_dofs(self) -> int:
        return 3 * len(self.nodes)

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The mesh as named arrays (``from_arrays`` rebuilds it; top and bottom are recomputed)."""
        return {"nodes": self.nodes, "tets": self.tets, "region": self.region, "order": np.int64(self.order),
                "size_m": np.array([self.width_m, self.length_m, self.height_m])}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> Mesh3D:
        """The mesh ``to_arrays`` wrote; ValueError if the arrays do not make a mesh."""
        w, ln, h = (float(v) for v in arrays["size_m"])
        mesh = cls(nodes=arrays["nodes"], tets=arrays["tets"], region=arrays["region"], order=int(arrays["order"]),
                   width_m=w, length_m=ln, height_m=h)
        nen = 4 if mesh.order == 1 else 10
        if (mesh.nodes.ndim != 2 or mesh.nodes.shape[1] != 3 or mesh.tets.shape[1:] != (nen,)
                or len(mesh.region) != len(mesh.tets) or mesh.tets.min() < 0 or mesh.tets.max() >= mesh.n_nodes
                or not np.all(np.isfinite(mesh.nodes))):
            raise ValueError("the arrays do not make a consistent 3D mesh")
        return mesh


def _sorted_xy(nodes: np.ndarray, idx: np.ndarray) -> np.ndarray:
    return idx[np.lexsort((nodes[idx, 1], nodes[idx, 0]))]


def _orient(mesh: Mesh3D) -> None:
    """Make every tetrahedron positively oriented (positive Jacobian): swap vertices 1 and 2 where it is not."""
    p = mesh.nodes[mesh.tets[:, :4]]
    det = np.einsum("mi,mi->m", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0])
    bad = det < 0
    if bad.any():
        perm = [0, 2, 1, 3]
        if mesh.order == 2:       # the mid-edge nodes follow their edges: (0,1)<->(2,0), (1,2) stays, (3,2)<->(3,1)
            perm += [4 + EDGES.index(e) for e in ((2, 0), (1, 2), (0, 1), (3, 0), (3, 1), (3, 2))]
        mesh.tets[bad] = mesh.tets[bad][:, perm]


def patch_bounds(width_m: float, length_m: float, patch_m: float | None) -> tuple[float, float, float, float]:
    """(x0, x1, y0, y1) of the probed square of the top face (the whole face when patch_m is None)."""
    if patch_m is None:
        return 0.0, width_m, 0.0, length_m
    return (0.5 * (width_m - patch_m), 0.5 * (width_m + patch_m), 0.5 * (length_m - patch_m),
            0.5 * (length_m + patch_m))


def mesh_block(width_m: float, length_m: float, height_m: float, stones: list[tuple[float, float, float, float]],
               size_m: float, surface_refine: float = 8.0, order: int = 2, patch_m: float | None = None,
               focus: tuple[float, float, float, float] | None = None,
               cylinders_y: list[tuple[float, float, float]] = (), grade: float = GRADE) -> Mesh3D:
    """Mesh the block with spherical stones given as (x_m, y_m, z_centre_m, radius_m). focus = (x_m, y_m, size_m,
    radius_m): element size size_m within radius_m of the top-face point (x_m, y_m), growing with slope GRADE
    beyond it (for verification against local closed forms such as Hertz contact). cylinders_y: stones that are
    cylinders (x_m, z_centre_m, radius_m) through the whole block along y (the 2D-against-3D slab check); their
    regions follow the spheres'. grade: the size's growth per unit distance (default GRADE)."""
    import gmsh  # lazy: a heavy import, only needed on a cache miss
    with _GMSH_LOCK:
        _start(gmsh)
        try:
            occ = gmsh.model.occ
            box = occ.addBox(0, 0, 0, width_m, length_m, height_m)
            balls = [occ.addSphere(x, y, z, r) for x, y, z, r in stones]
            balls += [occ.addCylinder(x, 0, z, 0, length_m, 0, r) for x, z, r in cylinders_y]
            if balls:
                _, vmap = occ.fragment([(3, box)], [(3, b) for b in balls])
            occ.synchronize()
            if balls:
                stone_vols = [[t for _, t in vmap[1 + i]] for i in range(len(balls))]
                flat = {t for vs in stone_vols for t in vs}
                tissue_vols = [t for _, t in gmsh.model.getEntities(3) if t not in flat]
                stone_surfs = [t for _, t in gmsh.model.getBoundary([(3, v) for v in flat], oriented=False)]
            else:
                stone_vols, tissue_vols, stone_surfs = [], [box], []
            fine = size_m / surface_refine
            x0, x1, y0, y1 = patch_bounds(width_m, length_m, patch_m)
            f = gmsh.model.mesh.field
            dist = (f"Sqrt(Max(Max({x0} - x, x - {x1}), 0)^2 + Max(Max({y0} - y, y - {y1}), 0)^2 + "
                    f"({height_m} - z)^2)")
            fields = []
            me = f.add("MathEval")
            f.setString(me, "F", f"Min({size_m}, {fine} + {grade} * {dist})")
            fields.append(me)
            if stone_surfs:
                d = f.add("Distance")
                f.setNumbers(d, "SurfacesList", stone_surfs)
                f.setNumber(d, "Sampling", 60)
                th = f.add("Threshold")
                # at most the smallest stone's radius on its surface (about 6 elements round a great circle): a
                # coarser sphere left gmsh's surface mesher with degenerate triangles, and it crashed (segfault) on a
                # 5 mm stone meshed at 8 mm
                r_min = min([r for *_, r in stones] + [r for *_, r in cylinders_y])
                smin = min(2 * fine, size_m, r_min)
                f.setNumber(th, "InField", d)
                f.setNumber(th, "SizeMin", smin)
                f.setNumber(th, "SizeMax", size_m)
                f.setNumber(th, "DistMin", 0.0)
                f.setNumber(th, "DistMax", (size_m - smin) / grade)
                fields.append(th)
            if focus is not None:
                fx, fy, fsize, frad = focus
                fm = f.add("MathEval")
                f.setString(fm, "F", f"Min({size_m}, {fsize} + {grade} * "
                                     f"Max(0, Sqrt((x - {fx})^2 + (y - {fy})^2 + (z - {height_m})^2) - {frad}))")
                fields.append(fm)
            mn = f.add("Min")
            f.setNumbers(mn, "FieldsList", fields)
            f.setAsBackgroundMesh(mn)
            gmsh.option.setNumber("Mesh.MeshSizeMax", size_m)
            gmsh.option.setNumber("Mesh.Algorithm", 6)
            gmsh.option.setNumber("Mesh.Algorithm3D", 10)      # HXT: fast, and multithreaded where allowed
            gmsh.model.mesh.generate(3)
            if order == 2:
                gmsh.model.mesh.setOrder(2)
            return _extract(gmsh, [tissue_vols] + stone_vols, order, width_m, length_m, height_m)
        finally:
            gmsh.finalize()


def _extract(gmsh, vols_by_region: list[list[int]], order: int, width: float, length: float,
             height: float) -> Mesh3D:
    tags, coords, _ = gmsh.model.mesh.getNodes()
    index = np.full(int(tags.max()) + 1, -1, dtype=np.int64)
    index[tags.astype(np.int64)] = np.arange(len(tags))
    nodes = coords.reshape(-1, 3).copy()
    etype, nen = (4, 4) if order == 1 else (11, 10)
    tets, region = [], []
    for reg, vols in enumerate(vols_by_region):
        for v in vols:
            el = gmsh.model.mesh.getElementsByType(etype, v)[1]
            conn = index[el.astype(np.int64)].reshape(-1, nen)
            tets.append(conn)
            region.append(np.full(len(conn), reg))
    tets = np.vstack(tets)
    used = np.unique(tets)
    remap = np.full(len(nodes), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    mesh = Mesh3D(nodes=nodes[used], tets=remap[tets], region=np.concatenate(region), order=order,
                  width_m=width, length_m=length, height_m=height)
    _orient(mesh)
    if order == 2:
        mesh.straightened = straighten_inverted(mesh)
    return mesh


def straighten_inverted(mesh: Mesh3D) -> int:
    """Put the mid-edge nodes of curved P2 elements whose Jacobian is not positive everywhere (at their nodes and
    at the points of the degree-5 rule used for curved elements) back on their straight edges; returns how many.
    A coarse mesh of a sphere folds a few such elements; their boundary then is a chord (as in 2D). A mid-edge node
    is shared: straightening one element can fold a neighbour on that edge, so this repeats until none is folded
    (it ends: an element with all its edges straight is its valid linear tetrahedron)."""
    pts = np.vstack([quadrature(5)[0], nodes_ref(2)])
    dN = shape_grad(2, pts)
    done = np.zeros(len(mesh.tets), dtype=bool)
    while True:
        J = np.einsum("mai,qaj->mqij", mesh.nodes[mesh.tets], dN)
        bad = np.flatnonzero(~(np.linalg.det(J).min(axis=1) > 0) & ~done)
        if len(bad) == 0:
            return int(done.sum())
        done[bad] = True
        t = mesh.tets[bad]
        for k, (a, b) in enumerate(EDGES):
            mesh.nodes[t[:, 4 + k]] = 0.5 * (mesh.nodes[t[:, a]] + mesh.nodes[t[:, b]])


def mesh_scene3d(scene) -> Mesh3D:
    """The mesh of a 3D scene's block and spherical stones (fem.scene.Scene with tissue.length_m)."""
    t, a = scene.tissue, scene.analysis
    stones = [(s.x_m, s.y_m, t.height_m - s.depth_m, s.radius_m) for s in scene.stones]
    # meshed in one order whatever the scene lists them in (gmsh's mesh follows the order its volumes are made in:
    # session 56's review listed two stones both ways and the force over one moved by 1.4 %, the load A peak by 4 %
    # to the other stone), then labelled in the scene's order (region k + 1 = scene.stones[k])
    order = sorted(range(len(stones)), key=lambda k: stones[k])
    mesh = mesh_block(t.width_m, t.length_m, t.height_m, [stones[k] for k in order], a.mesh_size_m,
                      a.surface_refine, a.order, a.patch_m, grade=grade_of(scene))
    if order != sorted(order):
        label = np.zeros(len(stones) + 1, dtype=mesh.region.dtype)
        label[1:] = np.array(order) + 1             # sorted stone j (region j + 1) is the scene's stone order[j]
        mesh = replace(mesh, region=label[mesh.region])
    return mesh


def grade_of(scene) -> float:
    """The scene's size growth rate (analysis.grade, GRADE when not given)."""
    return GRADE if scene.analysis.grade is None else scene.analysis.grade


def estimate_nodes3d(scene) -> dict:
    """The node count mesh_scene3d would produce, from its sizing law and without gmsh: the integral of 1 / h^3
    over the block (on a grid) times VERTEX_DENSITY3D; a P2 mesh has about 7.5 nodes per vertex (vertices + edges).
    Returns {"vertices", "nodes", "dofs", "top_nodes"} (floats; top_nodes: on the probed patch)."""
    t, a = scene.tissue, scene.analysis
    fine = a.mesh_size_m / a.surface_refine
    x0, x1, y0, y1 = patch_bounds(t.width_m, t.length_m, a.patch_m)
    n = 48
    xs, ys, zs = (np.linspace(0, L, n) for L in (t.width_m, t.length_m, t.height_m))
    X, Y, Z = np.meshgrid(xs, ys, zs, indexing="ij")
    dist = np.sqrt(np.maximum(np.maximum(x0 - X, X - x1), 0) ** 2 + np.maximum(np.maximum(y0 - Y, Y - y1), 0) ** 2
                   + (t.height_m - Z) ** 2)
    g = grade_of(scene)
    h = np.minimum(a.mesh_size_m, fine + g * dist)
    for s in scene.stones:
        d = np.abs(np.sqrt((X - s.x_m) ** 2 + (Y - s.y_m) ** 2 + (Z - t.height_m + s.depth_m) ** 2) - s.radius_m)
        h = np.minimum(h, np.minimum(2 * fine, a.mesh_size_m) + g * d)
    vol = t.width_m * t.length_m * t.height_m
    vertices = VERTEX_DENSITY3D * float(np.mean(1.0 / h ** 3)) * vol
    nodes = vertices if a.order == 1 else 7.5 * vertices
    top = (x1 - x0) * (y1 - y0) / fine ** 2 * 2 / math.sqrt(3) * (1 if a.order == 1 else 4)
    return {"vertices": vertices, "nodes": nodes, "dofs": 3.0 * nodes, "top_nodes": top}


# vertices per unit of integral(1 / h^3 dV), calibrated on gmsh's meshes (tests check the estimate within a factor 2)
VERTEX_DENSITY3D = 1.0
