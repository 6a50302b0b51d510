"""Where to probe on a 3D block's top face: a region (a rectangle or any polygon in the tissue frame's (x, y)), filled
with a grid of waypoints and ordered to keep the tool's travel between probes short.

Tissue frame: origin at the top face's corner, x along ``tissue.width_m``, y along ``tissue.length_m``, z the outward
normal. fem's 3D contact model covers the probed patch only (``analysis.patch_m``: the centred square of the top face
that is condensed for contact), and a waypoint's whole footprint (a disk of the tip radius) must lie on it: the tip's
centre may go anywhere in the patch shrunk by the tip radius (``probe_bounds``). Every position is checked against
that square here, before fem is asked anything, and refused with a PlanError naming the option.

Order: boustrophedon (serpentine rows: every other row reversed), its rows along x or along y, whichever gives the
shorter tool travel (the rows along the finer spacing). On a full grid that is optimal: every move is one grid step
and only the ny - 1 row changes take the coarser one, which any order needs to reach every row; with equal spacings
it meets the simple bound (N - 1) x the smallest distance (``travel_lower_bound_m``, reported with every raster). On
a polygon whose rows are broken (a concave region) a row may end far from the next one's start.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from core.contracts import MIN_PROBE_SPACING_M, PlanError

EDGE_TOL_M = 1e-9       # points on a region's edge count as inside (to this tolerance)


def near_side_fraction(scene, reach_m: float) -> float:
    """The share of the probed area (``probe_bounds``) within ``reach_m`` of the block's side faces."""
    x0, x1, y0, y1 = probe_bounds(scene)
    t = scene.tissue
    inner = (max(min(x1, t.width_m - reach_m) - max(x0, reach_m), 0.0)
             * max(min(y1, t.length_m - reach_m) - max(y0, reach_m), 0.0))
    area = (x1 - x0) * (y1 - y0)
    return 1.0 - inner / area if area > 0 else 0.0


def probe_bounds(scene) -> tuple[float, float, float, float]:
    """(x0, x1, y0, y1): where a probe's centre may go on ``scene``'s top face: the probed patch
    (``analysis.patch_m``, the whole face when absent) shrunk by the tip radius on every side."""
    t, R = scene.tissue, scene.indenter.radius_m
    p = scene.analysis.patch_m
    if p is None:
        x0, x1, y0, y1 = 0.0, t.width_m, 0.0, t.length_m
    else:
        x0, x1 = 0.5 * (t.width_m - p), 0.5 * (t.width_m + p)
        y0, y1 = 0.5 * (t.length_m - p), 0.5 * (t.length_m + p)
    return x0 + R, x1 - R, y0 + R, y1 - R


def patch_square(scene) -> tuple[float, float, float, float]:
    """(x0, x1, y0, y1) of fem's probed patch (the whole face when ``analysis.patch_m`` is absent)."""
    R = scene.indenter.radius_m
    x0, x1, y0, y1 = probe_bounds(scene)
    return x0 - R, x1 + R, y0 - R, y1 + R


@dataclass(frozen=True)
class Region:
    """A polygon on the top face, tissue-frame (x, y) vertices in m (either orientation, not self-intersecting)."""
    vertices_m: tuple[tuple[float, float], ...]
    option: str = "--polygon"       # the user's option that gave it (named in refusals)

    @staticmethod
    def rectangle(x0_m: float, y0_m: float, x1_m: float, y1_m: float, option: str = "--region") -> Region:
        if not (all(math.isfinite(v) for v in (x0_m, y0_m, x1_m, y1_m)) and x0_m <= x1_m and y0_m <= y1_m):
            raise PlanError(f"{option} {x0_m:g},{y0_m:g},{x1_m:g},{y1_m:g} must be finite x0,y0,x1,y1 (m) with "
                            f"x0 <= x1 and y0 <= y1")
        return Region(((x0_m, y0_m), (x1_m, y0_m), (x1_m, y1_m), (x0_m, y1_m)), option)

    @staticmethod
    def polygon(vertices_m, option: str = "--polygon") -> Region:
        """A polygon from (K, 2) vertices; PlanError naming ``option`` unless it has >= 3 finite vertices, a
        positive area and no crossing edges."""
        v = np.asarray(vertices_m, dtype=float)
        if v.ndim != 2 or v.shape[1] != 2 or len(v) < 3 or not np.all(np.isfinite(v)):
            raise PlanError(f"{option}: a polygon needs at least 3 finite (x, y) vertices in m, got "
                            f"{np.asarray(vertices_m).tolist()}")
        k = len(v)
        for i in range(k):
            for j in range(i + 1, k):
                if j == i + 1 or (i == 0 and j == k - 1):
                    continue
                if _segments_cross(v[i], v[(i + 1) % k], v[j], v[(j + 1) % k]):
                    raise PlanError(f"{option} {v.tolist()}: edges {i} and {j} cross (give the vertices in order "
                                    f"around the polygon)")
        if abs(_area(v)) <= 1e-12:
            raise PlanError(f"{option} {v.tolist()}: the polygon has no area")
        return Region(tuple(map(tuple, v.tolist())), option)

    @property
    def array(self) -> np.ndarray:
        return np.asarray(self.vertices_m, dtype=float)

    def bounds(self) -> tuple[float, float, float, float]:
        v = self.array
        return float(v[:, 0].min()), float(v[:, 0].max()), float(v[:, 1].min()), float(v[:, 1].max())

    def contains(self, points_m) -> np.ndarray:
        """Which of the (N, 2) points lie inside or on the edge (within EDGE_TOL_M)."""
        p = np.asarray(points_m, dtype=float).reshape(-1, 2)
        v = self.array
        a, b = v, np.roll(v, -1, axis=0)
        x, y = p[:, 0:1], p[:, 1:2]
        # even-odd rule by crossings of a ray towards +x
        cond = (a[:, 1] > y) != (b[:, 1] > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            xc = a[:, 0] + (y - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
        inside = (np.sum(cond & (x < xc), axis=1) % 2) == 1
        return inside | (_edge_distance(p, a, b) <= EDGE_TOL_M)


def _area(v: np.ndarray) -> float:
    return 0.5 * float(np.sum(v[:, 0] * np.roll(v[:, 1], -1) - np.roll(v[:, 0], -1) * v[:, 1]))


def _segments_cross(p1, p2, p3, p4) -> bool:
    def orient(a, b, c):
        return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
    d1, d2, d3, d4 = orient(p3, p4, p1), orient(p3, p4, p2), orient(p1, p2, p3), orient(p1, p2, p4)
    return (d1 * d2 < 0) and (d3 * d4 < 0)


def _edge_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N,) distance of each point to the nearest polygon edge a[i] -> b[i]."""
    ab = b - a
    L2 = np.maximum(np.sum(ab * ab, axis=1), 1e-300)
    t = np.clip(((p[:, None, :] - a[None]) * ab[None]).sum(axis=2) / L2, 0.0, 1.0)
    near = a[None] + t[..., None] * ab[None]
    return np.min(np.linalg.norm(p[:, None, :] - near, axis=2), axis=1)


def default_region(scene, margin_m: float | None = None) -> Region:
    """The probed patch minus ``margin_m`` on every side (default: the tip radius, i.e. the whole area a probe's
    footprint can cover, ``probe_bounds``). A margin below the tip radius is refused by ``check_positions``."""
    R = scene.indenter.radius_m
    margin = R if margin_m is None else float(margin_m)
    x0, x1, y0, y1 = patch_square(scene)
    if not (math.isfinite(margin) and 0 <= margin and x0 + margin <= x1 - margin and y0 + margin <= y1 - margin):
        raise PlanError(f"--margin-m {margin_m} must lie in [0, {0.5 * min(x1 - x0, y1 - y0):g}] m (half the probed "
                        f"patch, analysis.patch_m); at least the tip radius {R:g} m keeps the tip's footprint on it")
    return Region.rectangle(x0 + margin, y0 + margin, x1 - margin, y1 - margin, option="--margin-m")


def axis_positions(lo_m: float, hi_m: float, *, n: int | None = None, spacing_m: float | None = None) -> np.ndarray:
    """Evenly spaced positions on [lo, hi]: ``n`` with both ends included (the middle for n = 1), or as many as fit at
    ``spacing_m``, centred."""
    if n is not None:
        return np.array([0.5 * (lo_m + hi_m)]) if n == 1 else np.linspace(lo_m, hi_m, n)
    k = int(math.floor((hi_m - lo_m) / spacing_m + 1e-9))
    return 0.5 * (lo_m + hi_m) + spacing_m * (np.arange(k + 1) - 0.5 * k)


def grid_positions(region: Region, *, grid: tuple[int, int] | None = None,
                   spacing_m: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A grid over the region's bounding box, kept where inside the region: ``grid`` = (nx, ny) points along x and y
    (ends included), or ``spacing_m`` in both directions. Returns ((N, 2) positions, (N,) column index, (N,) row
    index), in row-major order (rows of equal y, x increasing; rows by increasing y)."""
    if (grid is None) == (spacing_m is None):
        raise PlanError("give either a grid (--grid NXxNY) or a spacing (--spacing-m), not both")
    if grid is not None:
        nx, ny = (int(v) for v in grid)
        if nx < 1 or ny < 1:
            raise PlanError(f"--grid {nx}x{ny}: both counts must be at least 1")
    elif not (spacing_m and math.isfinite(spacing_m) and spacing_m > 0):
        raise PlanError(f"--spacing-m must be positive, got {spacing_m}")
    x0, x1, y0, y1 = region.bounds()
    if grid is not None:
        for axis, n, lo, hi, other in (("x", nx, x0, x1, f"1x{ny}"), ("y", ny, y0, y1, f"{nx}x1")):
            if n > 1 and not hi - lo >= MIN_PROBE_SPACING_M * (n - 1):
                raise PlanError(f"{region.option}: the region spans {lo:g}..{hi:g} m in {axis}, so the grid's {n} "
                                f"points along {axis} would lie under {MIN_PROBE_SPACING_M:g} m apart (one spot for "
                                f"the arm): widen it, or give --grid {other} for a line")
    xs = axis_positions(x0, x1, n=None if grid is None else nx, spacing_m=spacing_m)
    ys = axis_positions(y0, y1, n=None if grid is None else ny, spacing_m=spacing_m)
    rows, cols = (a.ravel() for a in np.meshgrid(np.arange(len(ys)), np.arange(len(xs)), indexing="ij"))
    P = np.column_stack([xs[cols], ys[rows]])
    keep = region.contains(P)
    if not keep.any():
        raise PlanError(f"{region.option}: no grid point ({len(xs)} x {len(ys)} over x {x0:g}..{x1:g}, "
                        f"y {y0:g}..{y1:g} m) falls inside the region: enlarge it or refine the grid")
    return P[keep], cols[keep], rows[keep]


def travel_m(points_m) -> float:
    """Tool travel over the surface visiting the (N, 2) points in order (sum of straight moves), m."""
    p = np.asarray(points_m, dtype=float).reshape(-1, 2)
    return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))


def serpentine(points_m, col: np.ndarray, row: np.ndarray, along: str) -> np.ndarray:
    """Boustrophedon order of grid points: rows of equal ``row`` index (``along`` = "x") or of equal ``col`` index
    (``along`` = "y"), every other one reversed. Returns the permutation."""
    major, minor = (row, col) if along == "x" else (col, row)
    order = np.lexsort((minor, major))
    out, flip = [], False
    for m in np.unique(major[order]):
        seg = order[major[order] == m]
        out.append(seg[::-1] if flip else seg)
        flip = not flip
    return np.concatenate(out)


@dataclass
class AreaRaster:
    """The waypoints of an area raster in probing order and how their order was chosen."""
    positions_m: np.ndarray          # (N, 2) tissue-frame (x, y), in probing order
    region: Region
    order: str                       # "serpentine-x" (rows along x) or "serpentine-y"
    travel_m: float                  # tool travel between probes over the surface, this order
    travel_row_major_m: float        # the same points in plain row-major order (rows along x, each left to right)
    travel_lower_bound_m: float      # (N - 1) x the smallest distance between two points: no order does better

    def to_dict(self) -> dict:
        return {"region_m": [list(v) for v in self.region.vertices_m], "order": self.order,
                "n": int(len(self.positions_m)), "travel_m": self.travel_m,
                "travel_row_major_m": self.travel_row_major_m, "travel_lower_bound_m": self.travel_lower_bound_m}


def area_raster(scene, *, region: Region | None = None, grid: tuple[int, int] | None = None,
                spacing_m: float | None = None, margin_m: float | None = None) -> AreaRaster:
    """The grid over ``region`` (default: ``default_region(scene, margin_m)``) in the shorter of the two serpentine
    orders, checked against the probed patch (``check_positions``)."""
    region = region or default_region(scene, margin_m)
    P, col, row = grid_positions(region, grid=grid, spacing_m=spacing_m)
    check_positions(scene, P, option=region.option)
    best = None
    for along in ("x", "y"):
        perm = serpentine(P, col, row, along)
        t = travel_m(P[perm])
        if best is None or t < best[0] - 1e-12:
            best = (t, perm, along)
    t, perm, along = best
    return AreaRaster(positions_m=P[perm], region=region, order=f"serpentine-{along}", travel_m=t,
                      travel_row_major_m=travel_m(P), travel_lower_bound_m=travel_lower_bound_m(P))


def travel_lower_bound_m(points_m) -> float:
    """(N - 1) x the smallest distance between two distinct points: a bound below any visiting order's travel."""
    p = np.asarray(points_m, dtype=float).reshape(-1, 2)
    if len(p) < 2:
        return 0.0
    best = np.inf
    for i in range(0, len(p), 256):          # in blocks: (256, N) distances at a time
        d = np.linalg.norm(p[i:i + 256, None] - p[None], axis=2)
        d[np.arange(len(d)), np.arange(i, i + len(d))] = np.inf
        best = min(best, float(d.min()))
    return float((len(p) - 1) * best)


def check_positions(scene, positions_m, option: str = "positions") -> np.ndarray:
    """The (N, 2) positions as an array; PlanError naming ``option`` unless every one lies on the block's top face
    with the tip's footprint on fem's probed patch (``probe_bounds``)."""
    P = np.asarray(positions_m, dtype=float)
    if P.ndim != 2 or P.shape[1] != 2 or len(P) == 0 or not np.all(np.isfinite(P)):
        raise PlanError(f"{option}: a 3D scene's waypoints are finite tissue-frame (x, y) pairs in m, (N, 2); got "
                        f"an array of shape {P.shape}")
    x0, x1, y0, y1 = probe_bounds(scene)
    tol = 1e-12
    bad = np.flatnonzero((P[:, 0] < x0 - tol) | (P[:, 0] > x1 + tol) | (P[:, 1] < y0 - tol) | (P[:, 1] > y1 + tol))
    if len(bad):
        k = int(bad[0])
        t = scene.tissue
        where = ("off the block's top face" if not (0 <= P[k, 0] <= t.width_m and 0 <= P[k, 1] <= t.length_m)
                 else "outside fem's probed patch")
        raise PlanError(f"{option}: waypoint (x, y) = ({P[k, 0]:.6g}, {P[k, 1]:.6g}) m is {where} ({len(bad)} of "
                        f"{len(P)} waypoints are): a probe's centre must lie in x {x0:.6g}..{x1:.6g}, y {y0:.6g}.."
                        f"{y1:.6g} m (the probed patch, {_patch_said(scene.analysis.patch_m)}, shrunk by the tip "
                        f"radius {scene.indenter.radius_m:g} m)")
    return P


def default_block_pose(width_m: float, length_m: float, height_m: float) -> list[float]:
    """The block's tissue frame in the base frame when nobody says otherwise, like the 2D section's
    (``raster.default_tissue_pose``): on the arm's table (top face ``height_m`` above the base plane), tissue x along
    base y, tissue z = base z (up, the tool points straight down), the face's middle 0.40 m in front of the base on
    its x axis. Tissue y then runs along base -x."""
    return [0.40 + 0.5 * length_m, -0.5 * width_m, float(height_m), 0.0, 0.0, math.pi / 2]


def _patch_said(patch_m) -> str:
    """``analysis.patch_m`` as a person reads it: None is the whole top face."""
    return "the whole top face (analysis.patch_m not given)" if patch_m is None else f"analysis.patch_m = {patch_m:g} m"
