"""Meshing with gmsh: the tissue section with glued circular stones, and (for an elastic tip) the indenter.

A stone's boundary is a mesh curve shared by tissue and stone (glued = shared nodes). The element size is
``size_m`` at depth and ``size_m / surface_refine`` along the top surface and (half-way) around the stones.
"""
from __future__ import annotations

import math
import signal
import threading
from dataclasses import dataclass, field

import numpy as np

_GMSH_LOCK = threading.Lock()   # gmsh is a process-wide singleton


@dataclass
class Mesh:
    nodes: np.ndarray           # (N, 2) coordinates, m
    tris: np.ndarray            # (M, 3) or (M, 6) node indices, gmsh order
    region: np.ndarray          # (M,) 0 = tissue, k = stone k-1 (or the tip body)
    order: int
    width_m: float
    height_m: float
    top: np.ndarray = field(default=None)     # node indices on the top edge, sorted by x
    bottom: np.ndarray = field(default=None)  # node indices on the bottom edge, sorted by x

    def __post_init__(self):
        tol = 1e-9 * max(self.width_m, self.height_m)
        y = self.nodes[:, 1]
        if self.top is None:
            top = np.flatnonzero(np.abs(y - self.height_m) < tol)
            self.top = top[np.argsort(self.nodes[top, 0])]
        if self.bottom is None:
            bot = np.flatnonzero(np.abs(y) < tol)
            self.bottom = bot[np.argsort(self.nodes[bot, 0])]

    @property
    def n_nodes(self) -> int:
        return len(self.nodes)

    @property
    def n_dofs(self) -> int:
        return 2 * len(self.nodes)

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The mesh as named arrays (``from_arrays`` rebuilds it; top and bottom are recomputed)."""
        return {"nodes": self.nodes, "tris": self.tris, "region": self.region, "order": np.int64(self.order),
                "width_m": np.float64(self.width_m), "height_m": np.float64(self.height_m)}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> Mesh:
        """The mesh ``to_arrays`` wrote; ValueError if the arrays do not make a mesh."""
        mesh = cls(nodes=arrays["nodes"], tris=arrays["tris"], region=arrays["region"], order=int(arrays["order"]),
                   width_m=float(arrays["width_m"]), height_m=float(arrays["height_m"]))
        if (mesh.nodes.ndim != 2 or mesh.nodes.shape[1] != 2 or mesh.tris.shape[1:] != ((3,) if mesh.order == 1 else (6,))
                or len(mesh.region) != len(mesh.tris) or mesh.tris.min() < 0 or mesh.tris.max() >= mesh.n_nodes
                or not np.all(np.isfinite(mesh.nodes))):
            raise ValueError("the arrays do not make a consistent mesh")
        return mesh


def _start(gmsh):
    gmsh.initialize(readConfigFiles=False, interruptible=False)
    _rearm_sigterm()
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.option.setNumber("General.NumThreads", 1)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.Algorithm", 6)


def _rearm_sigterm() -> None:
    """gmsh's initialize sets SIGTERM's disposition back to the default at the C level while Python still reports
    its own handler, so a supervisor's SIGTERM after the first mesh killed palpate without a word (exit -15; a
    session-60 review) instead of raising KeyboardInterrupt as palpate's entry points arrange (app.entry): the
    handler Python believes in is installed again (main thread only; a worker thread's meshing leaves it as is)."""
    if threading.current_thread() is threading.main_thread():
        h = signal.getsignal(signal.SIGTERM)
        signal.signal(signal.SIGTERM, signal.SIG_DFL if h is None else h)


def _extract(gmsh, surfaces_by_region: list[list[int]], order: int, width: float, height: float) -> Mesh:
    tags, coords, _ = gmsh.model.mesh.getNodes()
    index = np.full(int(tags.max()) + 1, -1, dtype=np.int64)
    index[tags.astype(np.int64)] = np.arange(len(tags))
    nodes = coords.reshape(-1, 3)[:, :2].copy()
    etype = 2 if order == 1 else 9
    nen = 3 if order == 1 else 6
    tris, region = [], []
    for reg, surfs in enumerate(surfaces_by_region):
        for s in surfs:
            el = gmsh.model.mesh.getElementsByType(etype, s)[1]
            conn = index[el.astype(np.int64)].reshape(-1, nen)
            tris.append(conn)
            region.append(np.full(len(conn), reg))
    tris = np.vstack(tris)
    # drop nodes not used by any triangle (gmsh keeps geometry points), renumber compactly
    used = np.unique(tris)
    remap = np.full(len(nodes), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    mesh = Mesh(nodes=nodes[used], tris=remap[tris], region=np.concatenate(region), order=order,
                width_m=width, height_m=height)
    _orient(mesh)
    return mesh


def _orient(mesh: Mesh) -> None:
    """Make every triangle counter-clockwise (positive Jacobian)."""
    p = mesh.nodes[mesh.tris[:, :3]]
    det = (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1]) - (p[:, 2, 0] - p[:, 0, 0]) * (p[:, 1, 1] - p[:, 0, 1])
    bad = det < 0
    if bad.any():
        t = mesh.tris[bad]
        perm = [0, 2, 1] if mesh.order == 1 else [0, 2, 1, 5, 4, 3]
        mesh.tris[bad] = t[:, perm]


def mesh_section(width_m: float, height_m: float, stones: list[tuple[float, float, float]], size_m: float,
                 surface_refine: float = 4.0, order: int = 2,
                 focus: tuple[float, float, float] | None = None) -> Mesh:
    """Mesh the rectangle [0, width] x [0, height] with circular stones given as (x_m, y_centre_m, radius_m).
    focus = (x_m, size_m, radius_m): element size size_m within radius_m of the top-surface point x_m, growing by
    half the distance beyond it (for verification against local closed forms such as Hertz contact)."""
    import gmsh  # lazy: a heavy import, only needed on a cache miss (keeps `import fem` and CLI start-up fast)
    with _GMSH_LOCK:
        _start(gmsh)
        try:
            occ = gmsh.model.occ
            rect = occ.addRectangle(0, 0, 0, width_m, height_m)
            disks = [occ.addDisk(x, y, 0, r, r) for x, y, r in stones]
            if disks:
                _, fmap = occ.fragment([(2, rect)], [(2, d) for d in disks])
            occ.synchronize()
            if disks:
                stone_surfs = [[t for _, t in fmap[1 + i]] for i in range(len(disks))]
                flat = {t for ss in stone_surfs for t in ss}
                tissue_surfs = [t for _, t in gmsh.model.getEntities(2) if t not in flat]
            else:
                stone_surfs, tissue_surfs = [], [rect]
            tol = 1e-5 * max(width_m, height_m)   # OCC bounding boxes are padded by ~1e-7
            top_curves, stone_curves = [], []
            for _, c in gmsh.model.getEntities(1):
                x0, y0, _, x1, y1, _ = gmsh.model.getBoundingBox(1, c)
                if abs(y0 - height_m) < tol and abs(y1 - height_m) < tol:
                    top_curves.append(c)
                elif y0 > tol and y1 < height_m - tol and x0 > tol and x1 < width_m - tol:
                    stone_curves.append(c)
            fine = size_m / surface_refine
            fields = []
            f = gmsh.model.mesh.field
            for curves, smin, dist in ((top_curves, fine, TOP_BAND * height_m),
                                       (stone_curves, min(2 * fine, size_m), STONE_BAND * height_m)):
                if not curves:
                    continue
                d = f.add("Distance")
                f.setNumbers(d, "CurvesList", curves)
                f.setNumber(d, "Sampling", 400)
                th = f.add("Threshold")
                f.setNumber(th, "InField", d)
                f.setNumber(th, "SizeMin", smin)
                f.setNumber(th, "SizeMax", size_m)
                f.setNumber(th, "DistMin", 0.0)
                f.setNumber(th, "DistMax", dist)
                fields.append(th)
            if focus is not None:
                fx, fsize, frad = focus
                me = f.add("MathEval")
                f.setString(me, "F", f"Min({size_m}, {fsize} + 0.5 * "
                                     f"Max(0, Sqrt((x - {fx})^2 + (y - {height_m})^2) - {frad}))")
                fields.append(me)
            if fields:
                mn = f.add("Min")
                f.setNumbers(mn, "FieldsList", fields)
                f.setAsBackgroundMesh(mn)
            else:
                gmsh.option.setNumber("Mesh.MeshSizeMax", size_m)
            gmsh.option.setNumber("Mesh.MeshSizeMax", size_m)
            gmsh.model.mesh.generate(2)
            if order == 2:
                gmsh.model.mesh.setOrder(2)
            return _extract(gmsh, [tissue_surfs] + stone_surfs, order, width_m, height_m)
        finally:
            gmsh.finalize()


# The sizing law of mesh_section, shared with its estimate below: the size grows linearly from the fine size at the
# top surface (stone boundaries) to size_m at TOP_BAND (STONE_BAND) times the height from it.
TOP_BAND = 0.35
STONE_BAND = 0.15
# vertices per unit of integral(1 / h^2 dA): 2 / sqrt(3) for equilateral triangles of side h, times the factor
# calibrated on gmsh's meshes (tests/test_scene_validation.py checks the estimate within a factor 2)
VERTEX_DENSITY = 2.0 / math.sqrt(3.0) * 1.0


def estimate_nodes(width_m: float, height_m: float, stones: list[tuple[float, float, float]], size_m: float,
                   surface_refine: float = 4.0, order: int = 2) -> dict:
    """The node count mesh_section would produce, from its sizing law and without gmsh: integral of 1 / h(x, y)^2
    over the section (numerically, on a grid graded towards the top), times VERTEX_DENSITY; a P2 mesh has about 4
    nodes per vertex (vertices + edges). Returns {"vertices", "nodes", "dofs", "top_nodes"} (floats)."""
    fine = size_m / surface_refine
    # distances below the top: geometric near the surface (the size varies fastest there), linear below
    dy = np.unique(np.concatenate([[0.0], np.geomspace(min(fine, height_m) * 1e-2, height_m, 400),
                                   np.linspace(0.0, height_m, 401)]))
    dx = np.linspace(0.0, width_m, 401)
    X, D = np.meshgrid(dx, dy, indexing="ij")
    Y = height_m - D
    h = np.minimum(fine + (size_m - fine) * np.minimum(D / (TOP_BAND * height_m), 1.0), size_m)
    smin = min(2 * fine, size_m)
    for x, y, r in stones:
        dist = np.abs(np.hypot(X - x, Y - y) - r)
        h = np.minimum(h, smin + (size_m - smin) * np.minimum(dist / (STONE_BAND * height_m), 1.0))
    inner = np.trapezoid(1.0 / h ** 2, dy, axis=1)
    # boundary vertices: the area integral counts about half of them (half an element's area lies outside)
    side = float(np.trapezoid(1.0 / h[0], dy))
    boundary = width_m / fine + width_m / size_m + 2 * side + sum(2 * math.pi * r / smin for _, _, r in stones)
    vertices = VERTEX_DENSITY * float(np.trapezoid(inner, dx)) + 0.5 * boundary
    nodes = vertices if order == 1 else 4.0 * vertices
    top = (width_m / fine + 1) * (1 if order == 1 else 2)
    return {"vertices": vertices, "nodes": nodes, "dofs": 2.0 * nodes, "top_nodes": top}


def estimate_dofs_bound(width_m: float, height_m: float, stone_radii_m, size_m: float, surface_refine: float = 4.0,
                        order: int = 2) -> float:
    """An upper bound of ``estimate_nodes``'s "dofs" for the same scene, in closed form: its element size h never
    falls below min(fine, size_m), so each integral is bounded by its domain times the largest integrand (the
    trapezoid rule's weights are positive; equal when h is that minimum everywhere, hence a round-off margin)."""
    fine = size_m / surface_refine
    smin = min(2 * fine, size_m)
    hmin = min(fine, size_m)
    boundary = (width_m / fine + width_m / size_m + 2 * height_m / hmin
                + sum(2 * math.pi * r / smin for r in stone_radii_m))
    vertices = VERTEX_DENSITY * width_m * height_m / hmin ** 2 + 0.5 * boundary
    return 2.0 * (vertices if order == 1 else 4.0 * vertices) * (1.0 + 1e-9)     # the integrals' round-off


def mesh_tip(radius_m: float, size_m: float, order: int = 2) -> Mesh:
    """The lower half of a disk of radius R centred at (0, R): a cylindrical tip whose lowest point is the origin.
    Its flat top edge (y = R) is where the holder grips it. ``height_m`` = R, ``top`` = the gripped edge."""
    import gmsh  # lazy: a heavy import, only needed on a cache miss (keeps `import fem` and CLI start-up fast)
    with _GMSH_LOCK:
        _start(gmsh)
        try:
            occ = gmsh.model.occ
            disk = occ.addDisk(0, radius_m, 0, radius_m, radius_m)
            box = occ.addRectangle(-radius_m, radius_m, 0, 2 * radius_m, radius_m)
            out, _ = occ.cut([(2, disk)], [(2, box)])
            occ.synchronize()
            arc = [c for _, c in gmsh.model.getEntities(1)
                   if gmsh.model.getBoundingBox(1, c)[4] < radius_m * (1 - 1e-9)]
            f = gmsh.model.mesh.field
            d = f.add("Distance")
            f.setNumbers(d, "CurvesList", arc)
            f.setNumber(d, "Sampling", 400)
            th = f.add("Threshold")
            f.setNumber(th, "InField", d)
            f.setNumber(th, "SizeMin", size_m / 4)
            f.setNumber(th, "SizeMax", size_m)
            f.setNumber(th, "DistMin", 0.0)
            f.setNumber(th, "DistMax", 0.5 * radius_m)
            f.setAsBackgroundMesh(th)
            gmsh.option.setNumber("Mesh.MeshSizeMax", size_m)
            gmsh.model.mesh.generate(2)
            if order == 2:
                gmsh.model.mesh.setOrder(2)
            m = _extract(gmsh, [[t for _, t in out]], order, 2 * radius_m, radius_m)
            return m
        finally:
            gmsh.finalize()


def mesh_scene(scene) -> Mesh:
    """The mesh of a scene's tissue section and stones (fem.scene.Scene)."""
    t, a = scene.tissue, scene.analysis
    stones = [(s.x_m, t.height_m - s.depth_m, s.radius_m) for s in scene.stones]
    return mesh_section(t.width_m, t.height_m, stones, a.mesh_size_m, a.surface_refine, a.order)
