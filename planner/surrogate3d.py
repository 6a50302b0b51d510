"""The 3D forward model for localization: the force contrast of a rigid spherical stone in a block, tabulated.

The contrast of a probe at surface position (x, y) and indentation d is ``F_stone(x, y, d) - F_prior(x, y, d)`` for a
candidate rigid sphere at (xs, ys), centre depth ``depth`` below the top face, diameter D. A 3D fem model per
candidate costs seconds to a minute (fem.contact3d), far too slow inside scipy's least_squares, so the contrast is
tabulated once per prior scene and interpolated (docs/surrogate3d.md has the design, the cost and the measurements):

* translation invariance: for each candidate (top clearance ``s = depth - D/2`` on a geometric grid, D on a uniform
  grid) ONE 3D model with the stone under the middle of the block; its contrast is sampled on rings around the stone
  (``Grid3D.n_angles`` directions, the directions that stay on the probed patch) at the probe levels
  ``levels_m`` and averaged over the directions: an axisymmetric profile C(d, r) of the lateral offset
  r = |(x, y) - (xs, ys)|. Beyond the largest offset the patch allows (its diagonal) the profile is continued by
  the power law of its last 4 mm (``_continue_in_r``);
* the prior's force is subtracted *on the candidate's own mesh* (the stone given the tissue's material): the two
  models share their discretization, so its ripple (about 0.1 mN at 3 mm on block3d's default mesh, as large as
  a deep stone's contrast) cancels instead of entering the table;
* the table's mesh is coarser than the scene's (``Grid3D.mesh_size_m``, ``grade``: 10 s per model instead of 50 s).
  Its contrast is 5-15 % larger than on the scene's own mesh, nearly a constant factor per candidate and level
  (the residual after scaling: 0.4 % of the peak), so a few grid candidates (``Grid3D.cal_nodes``) are solved again
  on the scene's own mesh and the table is scaled by their factor (``mesh_factor``; per level, linear in log s
  between them, constant beyond; D does not enter). docs/surrogate3d.md has the measurements.

Query (``Surrogate3D.contrast``): Catmull-Rom cubic weights (C1, exact on the nodes, linear functions reproduced)
over a 4-node stencil in each of log s, D, probe level and r: 256 table entries per probe, vectorised over probes
(~60 us for 100 probes). What it ignores: the block's side faces (the contrast of an off-centre stone is that of a
centred one; measured), the profile's departure from axisymmetry (about 1 % of the peak at 3 mm), probe levels
outside ``levels_m`` (clamped: the localizer extrapolates), stones leaving the table's box (clamped).

Modulus: with a rigid stone and a rigid tip the force is E times a function of the geometry and nu (as in 2D,
planner.surrogate.table_scene), so the table is keyed by the prior at unit modulus and scaled by E / youngs_ref_pa.
A behavioural fingerprint (``fingerprint``: fem's forces on a small block with a stone, 0.6 s) is stored with the
table and compared at load with today's (computed once per version of fem and its libraries, then read from the
disk cache: planner.fingerprint): a table built by a different fem is not used.

``python -m planner.surrogate3d [SCENE] [--check N]`` builds (or loads) the table and measures its error against
direct 3D fem on the scene's own mesh.
"""
from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fem import diskcache
from fem.contact3d import SurfaceModel3D, surface_model3d
from fem.mesh3d import grade_of, patch_bounds
from fem.model3d import build_model3d
from fem.scene import Analysis, Indenter, Scene, SceneError, Stone, Tissue, from_dict, load
from fem.scene_mesh3d import mesh_for3d
from fem.tip import contact_scene
from planner.fingerprint import cached_fingerprint
from planner.tasks import Runner, array_of, run_pieces

FORMAT = 1
BOTTOM_TISSUE_M = 1e-3      # a candidate keeps this much tissue below it (deeper grid nodes are extrapolated)

# The table's model error for a fit (python -m planner.surrogate3d block3d --check 2, docs/surrogate3d.md): REL_ERR,
# relative to the contrast, covers the table against direct fem's contrast on the scene's own mesh with the prior on
# the same mesh (RMS over a probe grid: 1.0-1.4 % for interior stones, 2.7-4.2 % for stones 15 mm from the patch's
# edge, the side faces' effect); ABS_ERR_N (at youngs_ref_pa; scaled with the modulus) covers the mesh ripple of
# fem's own contrast when the stone's and the prior's forces come from two different meshes, as in a simulated run
# (RMS 0.041-0.071 mN at 2-4 mm, whatever the stone).
REL_ERR = 0.05
ABS_ERR_N = 7.5e-5
# The table takes every stone's contrast as a stone's away from the block's side faces: biased near them (measured:
# planner.localize.SIDE_REACH3D_M, where a fitted stone that near is flagged).


def _geometric(lo: float, hi: float, n: int) -> tuple:
    """``n`` values from ``lo`` to ``hi`` in geometric progression, rounded to 12 significant digits: they key the
    table (``cache_path``), and numpy's own geomspace differs between versions in the last bit (2.4.6 against the
    shipped table's: two of its ten clearances), which renamed the table and left a fresh install without it."""
    return tuple(float(f"{v:.12g}") for v in np.geomspace(lo, hi, n))


@dataclass(frozen=True)
class Grid3D:
    """The table's candidate stones, probe levels and lateral offsets, and the mesh its models are solved on."""
    s_m: tuple = _geometric(1.5e-3, 36e-3, 10)            # top clearance s = depth - D/2 (geometric)
    diam_m: tuple = (5e-3, 8e-3, 11e-3, 14e-3, 17e-3)      # uniform
    levels_m: tuple = (1e-3, 1.5e-3, 2e-3, 2.5e-3, 3e-3, 3.5e-3, 4e-3, 4.5e-3)   # uniform
    dr_m: float = 0.5e-3
    r_max_m: float = 0.080          # the profile's extent (sampled up to the patch's half-diagonal, then continued)
    n_angles: int = 8               # directions around the stone (those whose probes stay on the patch are used)
    mesh_size_m: float = 0.016      # the table models' mesh (bulk size; the scene's surface_refine and patch kept)
    grade: float = 0.5
    cal_nodes: tuple = ((2, 1), (5, 2), (8, 3))   # (s, D) node indices solved again on the scene's own mesh

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in self.__dict__.items()}


def table_scene(prior: Scene, grid: Grid3D, youngs_pa: float = 1.0, own_mesh: bool = False) -> Scene:
    """The scene a table is computed on and keyed by: the prior without stones, its tissue at ``youngs_pa``, a
    rigid-treated tip as the rigid tip (fem.tip.contact_scene), the table's mesh options (with ``own_mesh``, the
    prior's: the calibration solves), load A at its default."""
    prior = contact_scene(prior)
    if not prior.is_3d:
        raise ValueError(f"scene {prior.name!r} is 2D: use planner.surrogate")
    if prior.indenter.youngs_pa is not None:
        raise ValueError("the 3D surrogate table is built for a tip fem treats as rigid; the 3D loop does not take an "
                         "elastic tip (fem.contact3d models one for simulate and predict)")
    t = prior.tissue       # (a block under 32 mm: the table's mesh at fem's coarsest, half its smallest side)
    coarse_mesh_m = min(grid.mesh_size_m, 0.5 * min(t.width_m, t.height_m, t.length_m))
    return dataclasses.replace(
        prior, name="surrogate3d-table", stones=(), tissue=dataclasses.replace(prior.tissue, youngs_pa=youngs_pa),
        analysis=dataclasses.replace(prior.analysis, mesh_size_m=prior.analysis.mesh_size_m if own_mesh else
                                     coarse_mesh_m, grade=prior.analysis.grade if own_mesh else grid.grade,
                                     top_displacement_m=Analysis().top_displacement_m))


def cache_path(prior: Scene, grid: Grid3D, root: Path | None = None) -> Path:
    """Where the table of ``prior`` lives in ``root`` (default: fem's disk cache directory)."""
    root = diskcache.cache_dir() if root is None else root
    key = hashlib.sha256(json.dumps({"scene": table_scene(prior, grid).key(), "grid": grid.to_dict(),
                                     "format": FORMAT}, sort_keys=True).encode()).hexdigest()[:16]
    return root / f"surrogate3d-{key}.npz"


def stone_scene(scene: Scene, x_m: float, y_m: float, depth_m: float, diam_m: float) -> Scene:
    return scene.with_stones([Stone(x_m=float(x_m), y_m=float(y_m), depth_m=float(depth_m), diameter_m=float(diam_m))])


def patch_centre(scene: Scene) -> tuple[float, float]:
    """(x, y) of the probed patch's centre: where the table's candidates sit."""
    x0, x1, y0, y1 = patch_bounds(scene.tissue.width_m, scene.tissue.length_m, scene.analysis.patch_m)
    return 0.5 * (x0 + x1), 0.5 * (y0 + y1)


def stone_model3d(scene: Scene) -> SurfaceModel3D:
    """fem's SurfaceModel3D of a one-off stone scene with its stones rigid, kept out of fem's disk cache."""
    return SurfaceModel3D(scene, model=build_model3d(scene, mesh=mesh_for3d(scene, use=False), rigid_stones=True))


def same_mesh_prior(scene: Scene, model: SurfaceModel3D) -> SurfaceModel3D:
    """The prior on a stone scene's own mesh: its stones given the tissue's material (so the discretization, and
    its error, is the stone model's)."""
    t = scene.tissue
    soft = scene.with_stones([dataclasses.replace(s, youngs_pa=t.youngs_pa, poisson=t.poisson) for s in scene.stones])
    return SurfaceModel3D(soft, model=build_model3d(soft, mesh=model.mesh, rigid_stones=False))


def forces_at(model: SurfaceModel3D, x: np.ndarray, y: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Forces at waypoints (NaN where fem refuses one: off the patch, or deeper than a shallow stone allows)."""
    out = np.full(len(x), np.nan)
    for k in range(len(x)):
        try:
            out[k] = model.force_n(float(x[k]), float(y[k]), float(d[k]))
        except ValueError:
            pass
    return out


def ring_points(scene: Scene, grid: Grid3D, xc: float, yc: float) -> tuple[np.ndarray, ...]:
    """The sampled waypoints around a stone at (xc, yc): (level index, r index, x, y, d), for every direction and
    offset whose probe stays on the probed patch."""
    t, a, R = scene.tissue, scene.analysis, scene.indenter.radius_m
    x0, x1, y0, y1 = patch_bounds(t.width_m, t.length_m, a.patch_m)
    r = np.arange(0.0, grid.r_max_m + 1e-12, grid.dr_m)
    th = 2 * np.pi * np.arange(grid.n_angles) / grid.n_angles
    J, X, Y = [], [], []
    for j, rj in enumerate(r):
        for k, tk in enumerate(th if rj > 0 else th[:1]):
            x, y = xc + rj * np.cos(tk), yc + rj * np.sin(tk)
            if x0 + R <= x <= x1 - R and y0 + R <= y <= y1 - R:
                J.append(j)
                X.append(x)
                Y.append(y)
    J, X, Y = np.array(J), np.array(X), np.array(Y)
    nl = len(grid.levels_m)
    L = np.repeat(np.arange(nl), len(J))
    lv = np.asarray(grid.levels_m)
    return L, np.tile(J, nl), np.tile(X, nl), np.tile(Y, nl), lv[L]


# A coarse mesh can fold an element between a small shallow stone and the top face (gmsh's mesh of that one
# geometry): the candidate is then meshed again with the stone moved by a tenth of a millimetre (its profile is
# sampled around where it is; a 0.1 mm shift changes the contrast far below the table's error).
MESH_RETRY_SHIFTS_M = ((0.0, 0.0), (1.0e-4, 0.6e-4), (-0.7e-4, 1.1e-4), (0.4e-4, -1.3e-4))


def placed_stone_model(scene: Scene, xs_m: float, ys_m: float, depth_m: float, diam_m: float):
    """(the stone scene, its ``stone_model3d``): a stone the mesher cannot place is moved by a fraction of a
    millimetre (MESH_RETRY_SHIFTS_M; the scene says where it went)."""
    for k, (dx, dy) in enumerate(MESH_RETRY_SHIFTS_M):
        st = stone_scene(scene, xs_m + dx, ys_m + dy, depth_m, diam_m)
        try:
            with warnings.catch_warnings():
                warnings.filterwarnings("ignore", message=".*straightened.*")
                return st, stone_model3d(st)
        except SceneError:
            if k == len(MESH_RETRY_SHIFTS_M) - 1:
                raise


def _one_candidate(shared: dict, cand: tuple[float, float]) -> np.ndarray:
    """The contrast profile (levels x offsets; NaN beyond the sampled offsets) of one grid candidate (s_m, diam_m),
    centred on the patch. Runs on a worker (planner.tasks)."""
    scene = from_dict(shared["scene"])
    grid = Grid3D(**{k: tuple(v) if isinstance(v, list) else v for k, v in shared["grid"].items()})
    s, D = cand
    st, model = placed_stone_model(scene, *patch_centre(scene), s + D / 2, D)
    xc, yc = st.stones[0].x_m, st.stones[0].y_m
    L, J, X, Y, d = ring_points(scene, grid, xc, yc)
    f_stone = forces_at(model, X, Y, d)
    prior = same_mesh_prior(st, model)
    del model
    c = f_stone - forces_at(prior, X, Y, d)
    nr = int(round(grid.r_max_m / grid.dr_m)) + 1
    out = np.full((len(grid.levels_m), nr), np.nan)
    for lv in range(len(grid.levels_m)):
        for j in np.unique(J):
            v = c[(L == lv) & (J == j)]
            v = v[np.isfinite(v)]
            if len(v):
                out[lv, j] = v.mean()
    return out


def _continue_in_depth(f: np.ndarray, levels: np.ndarray) -> None:
    """Fill NaN levels (fem refused them over a shallow stone) from the deepest computed ones at the same offset:
    the contrast ~ d^p with p from the last two computed levels (1.5 with fewer), in place."""
    for b in range(f.shape[1]):
        ok = np.flatnonzero(~np.isnan(f[:, b]))
        if len(ok) == 0 or len(ok) == len(levels):
            continue
        i1 = ok[-1]
        p = 1.5
        if len(ok) >= 2 and f[ok[-2], b] > 0 and f[i1, b] > 0:
            p = float(np.clip(np.log(f[i1, b] / f[ok[-2], b]) / np.log(levels[i1] / levels[ok[-2]]), 0.5, 4.0))
        for a in np.flatnonzero(np.isnan(f[:, b])):
            f[a, b] = f[i1, b] * (levels[a] / levels[i1]) ** p


def _continue_in_r(f: np.ndarray, dr: float, fit_m: float = 4e-3) -> None:
    """Continue each level's profile beyond its last sampled offset r1 by C(r1) (r1 / r)^q, q the log-slope over
    the last ``fit_m`` (at least 2), in place; 0 for a non-positive end."""
    for a in range(f.shape[0]):
        ok = np.flatnonzero(np.isfinite(f[a]))
        j1 = ok[-1]
        j0 = max(ok[0], j1 - int(round(fit_m / dr)))
        r = np.arange(f.shape[1]) * dr
        c1, c0 = f[a, j1], f[a, j0]
        q = 2.0
        if c1 > 0 and c0 > c1 and j0 > 0:
            q = max(q, float(np.log(c0 / c1) / np.log(r[j1] / r[j0])))
        tail = np.arange(j1 + 1, f.shape[1])
        f[a, tail] = c1 * (r[j1] / r[tail]) ** q if c1 > 0 else 0.0
        f[a, :j1] = np.where(np.isfinite(f[a, :j1]), f[a, :j1], np.interp(r[:j1], r[ok], f[a, ok]))


def _fill_invalid(table: np.ndarray, valid: np.ndarray, logs: np.ndarray) -> None:
    """Grid candidates too deep for the block (left out): linear extrapolation in log s from the two shallower
    nodes, so the cubic stencil stays smooth near the bottom (the table's bounds keep a fit above it)."""
    for j in range(table.shape[1]):
        for i in range(table.shape[0]):
            if not valid[i, j] and i >= 2:
                t = (logs[i] - logs[i - 1]) / (logs[i - 1] - logs[i - 2])
                table[i, j] = table[i - 1, j] + t * (table[i - 1, j] - table[i - 2, j])


def candidate_ok(scene: Scene, s_m: float, diam_m: float) -> bool:
    """Whether a candidate (top clearance, diameter) fits in the block with 1 mm of tissue below it."""
    return s_m + diam_m <= scene.tissue.height_m - BOTTOM_TISSUE_M


# what a build's ``progress(done, total, elapsed_s, what)`` counts (session 51's review: the calibration's stones were
# counted on as more "candidate stones")
CANDIDATES = "candidate stones"
CALIBRATION = "calibration stones (the table's on the scene's own mesh)"


def build_table3d(prior: Scene, grid: Grid3D = Grid3D(), runner: Runner | None = None, progress=None,
                  store: Path | None = None) -> dict:
    """Solve every grid candidate on ``table_scene(prior)`` at the prior's own modulus (``youngs_ref_pa``) on
    ``runner`` (planner.tasks; default serial); finished candidates are kept in ``store`` (a re-run resumes).
    ``progress(done, total, elapsed_s, what)`` as candidates finish (``what``: CANDIDATES, CALIBRATION). Returns the arrays ``Surrogate3D`` reads."""
    runner = runner or Runner(workers=1, progress=progress is None)
    scene = table_scene(prior, grid, prior.tissue.youngs_pa)
    logs = np.log(grid.s_m)
    valid = np.array([[candidate_ok(scene, s, D) for D in grid.diam_m] for s in grid.s_m])
    cands = [(float(s), float(D)) for i, s in enumerate(grid.s_m) for j, D in enumerate(grid.diam_m) if valid[i, j]]
    idx = [(i, j) for i in range(len(grid.s_m)) for j in range(len(grid.diam_m)) if valid[i, j]]
    nr = int(round(grid.r_max_m / grid.dr_m)) + 1
    table = np.zeros((len(grid.s_m), len(grid.diam_m), len(grid.levels_m), nr))
    t0 = time.perf_counter()
    done = {"n": 0}
    lv = np.asarray(grid.levels_m)

    def arrived(n, res):
        prof = np.array(res, float)
        _continue_in_depth(prof, lv)
        _continue_in_r(prof, grid.dr_m)
        table[idx[n]] = prof
        done["n"] += 1
        if progress:
            progress(done["n"], len(cands), time.perf_counter() - t0, CANDIDATES)
    shared = {"scene": scene.to_dict(), "grid": grid.to_dict()}
    run_pieces(_one_candidate, shared, cands, [f"cand-{i}-{j}" for i, j in idx], runner=runner, store=store,
               desc="surrogate3d candidates", on_result=arrived,
               shape=array_of((len(grid.levels_m), nr)))
    _fill_invalid(table, valid, logs)
    cal_s, factors = calibrate3d(prior, grid, table, valid, runner=runner, store=store, progress=progress)
    return {"s_m": np.array(grid.s_m), "diam_m": np.array(grid.diam_m), "levels_m": lv,
            "dr_m": np.array(grid.dr_m), "table": table, "valid": valid,
            "cal_s_m": cal_s, "cal_factor": factors, "cal_mesh": own_mesh(prior),
            "patch_xy_m": np.array(_probe_region(scene)), "youngs_ref_pa": np.array(scene.tissue.youngs_pa),
            "height_m": np.array(scene.tissue.height_m), "build_s": np.array(time.perf_counter() - t0)}


def own_mesh(prior: Scene) -> np.ndarray:
    """(mesh_size_m, grade) of the prior's own mesh: what a table's calibration is for (the table scene keeps the
    prior's surface refinement, patch and order, and replaces these two by the grid's)."""
    a = prior.analysis
    return np.array([a.mesh_size_m, grade_of(prior)], float)


def calibrate3d(prior: Scene, grid: Grid3D, table: np.ndarray, valid: np.ndarray, runner: Runner | None = None,
                store: Path | None = None, progress=None) -> tuple[np.ndarray, np.ndarray]:
    """(cal_s_m, cal_factor): the grid's calibration candidates solved again on the prior's own mesh, and per
    candidate and level the factor that turns the table's profile into that mesh's (``mesh_factor``). None to do
    (empty arrays) when the prior's own mesh is the table's. ``progress(done, total, elapsed_s, CALIBRATION)``."""
    runner = runner or Runner(workers=1, progress=progress is None)
    if np.allclose(own_mesh(prior), [grid.mesh_size_m, grid.grade]):
        return np.zeros(0), np.ones((0, len(grid.levels_m)))
    own = table_scene(prior, grid, prior.tissue.youngs_pa, own_mesh=True)
    cal = [(i, j) for i, j in grid.cal_nodes if valid[i, j]]
    factors = np.ones((len(cal), len(grid.levels_m)))
    t0 = time.perf_counter()

    def calibrated(n, res):
        factors[n] = mesh_factor(np.array(res, float), table[cal[n]], grid.dr_m)
        if progress:
            progress(n + 1, len(cal), time.perf_counter() - t0, CALIBRATION)
    run_pieces(_one_candidate, {"scene": own.to_dict(), "grid": grid.to_dict()},
               [(float(grid.s_m[i]), float(grid.diam_m[j])) for i, j in cal], [f"cal-{i}-{j}" for i, j in cal],
               runner=runner, store=store, desc="surrogate3d calibration", on_result=calibrated,
               shape=array_of((len(grid.levels_m), int(round(grid.r_max_m / grid.dr_m)) + 1)))
    return np.array([grid.s_m[i] for i, _ in cal]).reshape(-1), factors


def mesh_factor(own: np.ndarray, table: np.ndarray, dr: float, r_fit_m: float = 0.028) -> np.ndarray:
    """Per level, the factor that best turns a table profile (levels x offsets) into the same candidate's profile
    on the scene's own mesh (NaN where not sampled): least squares weighted by r (the area of a ring) over
    r <= r_fit_m; a level with fewer than 3 samples (fem refused it over a shallow stone) takes the nearest
    shallower level's factor."""
    r = np.arange(table.shape[-1]) * dr
    out = np.full(table.shape[0], np.nan)
    for a in range(table.shape[0]):
        ok = np.isfinite(own[a]) & (r <= r_fit_m) & (r > 0)
        if ok.sum() >= 3:
            out[a] = np.sum(r[ok] * own[a, ok] * table[a, ok]) / np.sum(r[ok] * table[a, ok] ** 2)
        elif a > 0:
            out[a] = out[a - 1]
    return np.where(np.isfinite(out), out, 1.0)


def _probe_region(scene: Scene) -> tuple[float, float, float, float]:
    """(x0, x1, y0, y1): where the tip's axis may go on the probed patch (the patch shrunk by the tip radius)."""
    t, R = scene.tissue, scene.indenter.radius_m
    x0, x1, y0, y1 = patch_bounds(t.width_m, t.length_m, scene.analysis.patch_m)
    return x0 + R, x1 - R, y0 + R, y1 - R


def _catmull_rom(u: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Stencil indices (.., 4) into an axis padded by one ghost node at each end (padded index = node + 1) and the
    Catmull-Rom weights of the fractional node coordinate u (clamped to [0, n - 1])."""
    u = np.clip(u, 0.0, n - 1)
    i = np.minimum(np.floor(u).astype(int), n - 2)
    t = (u - i)[..., None]
    t2, t3 = t * t, t * t * t
    w = np.concatenate([(-t3 + 2 * t2 - t), (3 * t3 - 5 * t2 + 2), (-3 * t3 + 4 * t2 + t), (t3 - t2)], axis=-1) / 2
    return i[..., None] + np.arange(4), w


def _pad(T: np.ndarray, axis: int, even: bool = False) -> np.ndarray:
    """One ghost node at each end of ``axis``: linear extrapolation (or, with ``even``, the mirror at the start:
    the profile is even in r)."""
    T = np.moveaxis(T, axis, 0)
    first = T[1] if even else 2 * T[0] - T[1]
    out = np.concatenate([first[None], T, (2 * T[-1] - T[-2])[None]])
    return np.moveaxis(out, 0, axis)


class Surrogate3D:
    """The tabulated contrast (module doc). With a ``prior`` the table is scaled to the prior's tissue modulus."""

    def __init__(self, data: dict, prior: Scene | None = None,
                 calibration: tuple[np.ndarray, np.ndarray] | None = None):
        """calibration: (cal_s_m, cal_factor) for the prior's own mesh (``calibration_for``); default: the data's
        own (the mesh it was built for)."""
        self.data = data             # the arrays as read (what --ship writes)
        self.scale = float(prior.tissue.youngs_pa / float(data["youngs_ref_pa"])) if prior is not None else 1.0
        self.s = np.asarray(data["s_m"], float)
        self.logs = np.log(self.s)
        self.diam = np.asarray(data["diam_m"], float)
        self.levels = np.asarray(data["levels_m"], float)
        self.dr = float(data["dr_m"])
        self.height_m = float(data["height_m"])
        self.region = tuple(float(v) for v in np.asarray(data["patch_xy_m"]))
        self.build_s = float(data.get("build_s", 0.0))
        self.rel_err = REL_ERR
        self.abs_err_n = ABS_ERR_N * self.scale
        T = np.asarray(data["table"], float) * self.scale
        cal_s, cal_f = calibration or (data.get("cal_s_m", np.zeros(0)), data.get("cal_factor"))
        cal_s = np.asarray(cal_s, float)
        self.calibration = (cal_s, cal_f)
        if len(cal_s):             # the mesh factor, linear in log s between the calibration nodes (module doc)
            o = np.argsort(cal_s)
            fac = np.asarray(cal_f, float)[o]
            self.mesh_factor = np.stack([np.interp(self.logs, np.log(cal_s[o]), fac[:, a])
                                         for a in range(len(self.levels))], axis=1)     # (n_s, levels)
            T = T * self.mesh_factor[:, None, :, None]
        else:
            self.mesh_factor = np.ones((len(self.s), len(self.levels)))
        self.nr = T.shape[-1]
        for ax, even in ((0, False), (1, False), (2, False), (3, True)):
            T = _pad(T, ax, even)
        self.T = T
        self._profiles: dict[tuple[float, float], np.ndarray] = {}
        self._stencils: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}

    def bounds(self) -> dict:
        """The box the table covers (a fit stays inside it): top clearance, diameter, the stone centre's (x, y)
        region (the probe region), and the block's height (a stone keeps 1 mm of tissue below it)."""
        x0, x1, y0, y1 = self.region
        return {"s_m": (float(self.s[0]), float(self.s[-1])), "diam_m": (float(self.diam[0]), float(self.diam[-1])),
                "xs_m": (x0, x1), "ys_m": (y0, y1), "height_m": self.height_m}

    def profile(self, stone_depth_m: float, diam_m: float) -> np.ndarray:
        """The candidate's padded profile (levels + 2, offsets + 2): the (log s, D) interpolation done once, and
        remembered for the last few hundred (depth, D) (a finite-difference Jacobian's position and nuisance steps
        ask for the same one: 7 of its 9 columns in the 3D fit). Read-only."""
        key = (float(stone_depth_m), float(diam_m))
        C = self._profiles.get(key)
        if C is None:
            s = max(key[0] - 0.5 * key[1], 1e-6)
            h_s = self.logs[1] - self.logs[0]
            h_d = self.diam[1] - self.diam[0]
            i_s, w_s = _catmull_rom(np.asarray((np.log(s) - self.logs[0]) / h_s), len(self.s))
            i_d, w_d = _catmull_rom(np.asarray((key[1] - self.diam[0]) / h_d), len(self.diam))
            C = np.einsum("i,j,ijkl->kl", w_s, w_d, self.T[np.ix_(i_s, i_d)])
            C.flags.writeable = False
            if len(self._profiles) >= 512:
                self._profiles.clear()
            self._profiles[key] = C
        return C

    def _stencil(self, key: tuple, make) -> tuple[np.ndarray, np.ndarray]:
        """``make()`` (a Catmull-Rom stencil), remembered under ``key`` (the exact inputs it depends on) for the last
        few dozen: a finite-difference Jacobian's steps move the stone's position (the radial stencil), the surface
        (the probes' depth stencil) or neither, one parameter at a time. The same numbers as computing them again;
        read-only."""
        v = self._stencils.get(key)
        if v is None:
            if len(self._stencils) >= 64:
                self._stencils.clear()
            v = self._stencils[key] = make()
            for a in v:
                a.flags.writeable = False
        return v

    def contrast(self, x_m, y_m, depth_m, xs_m: float, ys_m: float, stone_depth_m: float,
                 diam_m: float) -> np.ndarray:
        """The contrast (N) at probes (x_m, y_m, depth_m: arrays, broadcast) for a stone at (xs_m, ys_m),
        ``stone_depth_m`` (centre below the surface), ``diam_m``."""
        x, y, d = np.broadcast_arrays(np.asarray(x_m, float), np.asarray(y_m, float), np.asarray(depth_m, float))
        C = self.profile(stone_depth_m, diam_m)
        i_r, w_r = self._stencil(("r", x.shape, x.tobytes(), y.tobytes(), float(xs_m), float(ys_m)),
                                 lambda: _catmull_rom(np.hypot(x - float(xs_m), y - float(ys_m)) / self.dr, self.nr))
        h_l = self.levels[1] - self.levels[0]
        i_l, w_l = self._stencil(("depth", d.shape, d.tobytes()),
                                 lambda: _catmull_rom((d - self.levels[0]) / h_l, len(self.levels)))
        vals = C[i_l[..., :, None], i_r[..., None, :]]
        return np.einsum("...a,...b,...ab->...", w_l, w_r, vals)


SHIPPED = Path(__file__).resolve().parent / "data"

# The fingerprint's small block: the table scene's tissue material, tip and element order on a 30 x 30 x 20 mm
# block with a 6 mm stone, coarse (about a second of fem).
FP_POINTS = ((0.015, 0.015), (0.018, 0.015), (0.015, 0.019))
FP_DEPTH_M = 0.002


def fingerprint(scene: Scene) -> np.ndarray:
    """What fem computes *now* on a small block like ``scene`` (its tissue material, tip and order) with and
    without a centred rigid stone at a few probes: a table whose stored fingerprint differs was built by a
    different fem (mesher, elements, contact) and is rebuilt. A behavioural check, not a source hash."""
    t = scene.tissue
    small = Scene(name="surrogate3d-fingerprint", tissue=Tissue(width_m=0.030, length_m=0.030, height_m=0.020,
                                                                youngs_pa=t.youngs_pa, poisson=t.poisson),
                  indenter=Indenter(shape=scene.indenter.shape, radius_m=0.004),
                  analysis=Analysis(order=scene.analysis.order, mesh_size_m=0.008, surface_refine=4.0,
                                    patch_m=0.020, grade=0.5))
    st = stone_scene(small, 0.015, 0.015, 0.009, 0.008)
    m = stone_model3d(st)
    pts = np.array(FP_POINTS)
    d = np.full(len(pts), FP_DEPTH_M)
    return np.concatenate([forces_at(m, pts[:, 0], pts[:, 1], d),
                           forces_at(same_mesh_prior(st, m), pts[:, 0], pts[:, 1], d)])


def _fingerprint_now(own: Scene) -> np.ndarray:
    """``fingerprint(own)``, read from fem's disk cache when today's fem and libraries computed it before
    (planner.fingerprint)."""
    return cached_fingerprint("fingerprint3d", {"scene": own.key(), "format": FORMAT}, lambda: fingerprint(own))


def table_candidates(prior: Scene, grid: Grid3D) -> list[Path]:
    """Where a table may be read from, in order: the disk cache (unless PALPATE_CACHE=0), then the shipped data."""
    return ([cache_path(prior, grid)] if diskcache.enabled() else []) + [cache_path(prior, grid, SHIPPED)]


_MEM: dict[tuple, Surrogate3D] = {}


def _fingerprint_ok(d: dict, fp: np.ndarray, scale: float) -> bool:
    return ("fingerprint" in d and d["fingerprint"].shape == fp.shape
            and np.allclose(d["fingerprint"] * scale, fp, rtol=1e-7, atol=1e-12 * scale))


def load_surrogate3d(prior: Scene, build: bool = True, runner: Runner | None = None, progress=None,
                     grid: Grid3D = Grid3D(), check: bool = True) -> Surrogate3D:
    """The 3D surrogate of a prior scene (no stones): from memory, the disk cache or planner/data, provided its
    fingerprint matches what fem computes now (0.6 s, once per version of fem and its libraries: planner.fingerprint);
    else built (``build_table3d`` on ``runner``; minutes) and
    written to the cache. FileNotFoundError when there is none and ``build`` is False."""
    if prior.stones:
        raise ValueError("the surrogate is built on the prior scene (no stones); pass scene.prior()")
    path = cache_path(prior, grid)
    mem_key = (str(path), prior.tissue.youngs_pa, tuple(own_mesh(prior)))
    if mem_key in _MEM:
        return _MEM[mem_key]
    own = table_scene(prior, grid, prior.tissue.youngs_pa)
    fp, data = None, None
    for cand in table_candidates(prior, grid):
        d = diskcache.read(cand)
        if d is None:
            continue
        if check:
            fp = _fingerprint_now(own) if fp is None else fp
            if not _fingerprint_ok(d, fp, float(prior.tissue.youngs_pa / float(d["youngs_ref_pa"]))):
                print(f"surrogate3d: {cand} was built by a different fem (fingerprint differs): not used",
                      file=sys.stderr)
                continue
        data = d
        break
    if data is None:
        if not build:
            raise FileNotFoundError(f"no valid 3D surrogate table at {path}")
        store = path.with_suffix(".parts") if diskcache.enabled() else None
        data = build_table3d(prior, grid, runner=runner, progress=progress, store=store)
        data["fingerprint"] = _fingerprint_now(own) if fp is None else fp
        if diskcache.enabled():
            diskcache.write(path, data)
    sur = Surrogate3D(data, prior, calibration_for(prior, grid, data, build=build, runner=runner, progress=progress))
    _MEM[mem_key] = sur
    return sur


def calibration_for(prior: Scene, grid: Grid3D, data: dict, build: bool = True, runner: Runner | None = None,
                    progress=None) -> tuple[np.ndarray, np.ndarray]:
    """(cal_s_m, cal_factor) of a table for the prior's own mesh: none on the table's own mesh, the table's stored
    one when it was built for this mesh (``cal_mesh``), else from the disk cache or solved now (``calibrate3d``: three
    candidates on the prior's mesh, minutes) and cached. A table calibrated for one mesh is never applied to a scene
    meshed otherwise. FileNotFoundError when it is missing and ``build`` is False."""
    mine = own_mesh(prior)
    if np.allclose(mine, [grid.mesh_size_m, grid.grade]):
        return np.zeros(0), np.ones((0, len(grid.levels_m)))
    if "cal_mesh" in data and np.allclose(data["cal_mesh"], mine):
        return data["cal_s_m"], data["cal_factor"]
    path = cache_path(prior, grid).with_name(f"{cache_path(prior, grid).stem}-cal-{mine[0]:.6g}-{mine[1]:.6g}.npz")
    d = diskcache.read(path) if diskcache.enabled() else None
    if d is None:
        if not build:
            raise FileNotFoundError(f"no 3D surrogate calibration for the mesh (mesh_size_m, grade) = {tuple(mine)}")
        table = np.asarray(data["table"], float) * float(prior.tissue.youngs_pa / float(data["youngs_ref_pa"]))
        cal_s, fac = calibrate3d(prior, grid, table, np.asarray(data["valid"], bool), runner=runner, progress=progress,
                                 store=path.with_suffix(".parts") if diskcache.enabled() else None)
        d = {"cal_s_m": cal_s, "cal_factor": fac}
        if diskcache.enabled():
            diskcache.write(path, d)
    return d["cal_s_m"], d["cal_factor"]


# -- measuring the error against direct fem ---------------------------------------------------------------------

CHECK_STONES = ((0.035, 0.035), (0.020, 0.035), (0.035, 0.020), (0.022, 0.048))   # centred, then off-centre


def probe_grid(scene: Scene, n: int = 9) -> tuple[np.ndarray, np.ndarray]:
    """An n x n grid of probe positions over the probe region."""
    x0, x1, y0, y1 = _probe_region(scene)
    X, Y = np.meshgrid(np.linspace(x0, x1, n), np.linspace(y0, y1, n), indexing="ij")
    return X.ravel(), Y.ravel()


def check_stones(sur: Surrogate3D, n_random: int, seed: int = 0) -> list[tuple[float, float, float, float]]:
    """Stones (xs, ys, depth, diam) to check: a centred one and three off-centre ones (x, y of CHECK_STONES; a
    12 mm stone 25 mm deep, between grid nodes), then random ones inside the table's box."""
    rng = np.random.default_rng(seed)
    out = [(x, y, 0.025, 0.012) for x, y in CHECK_STONES]
    b = sur.bounds()
    while len(out) < len(CHECK_STONES) + n_random:
        D = rng.uniform(6e-3, 16e-3)
        s = float(np.exp(rng.uniform(np.log(2e-3), np.log(30e-3))))
        if s + D > b["height_m"] - 4e-3:
            continue
        out.append((rng.uniform(*b["xs_m"]), rng.uniform(*b["ys_m"]), s + D / 2, D))
    return out


def direct_contrasts(prior: Scene, stones, levels=(2e-3, 3e-3, 4e-3), n_grid: int = 9, same_mesh: bool = True,
                     progress=None) -> dict:
    """Direct 3D fem contrasts at ``stones`` (xs, ys, depth, diam) on the prior's own analysis over an n_grid^2
    probe grid at ``levels``: the stone scene's force minus the prior's, each on its own mesh (``direct``: what a
    simulated run sees) and, with ``same_mesh``, minus the prior on the stone's mesh (``same``: the table's
    definition, without the mesh ripple). NaN where fem refuses a waypoint."""
    base = surface_model3d(prior)
    X, Y = probe_grid(prior, n_grid)
    rows = []
    for k, (xs, ys, depth, D) in enumerate(stones):
        t0 = time.perf_counter()
        st = stone_scene(prior, xs, ys, depth, D)
        m = stone_model3d(st)
        dd = [np.full(len(X), d) for d in levels]
        f_stone = [forces_at(m, X, Y, d) for d in dd]
        row = {"xs_m": xs, "ys_m": ys, "depth_m": depth, "diam_m": D,
               "direct_n": [(f - forces_at(base, X, Y, d)).tolist() for f, d in zip(f_stone, dd)]}
        if same_mesh:
            pm = same_mesh_prior(st, m)
            row["same_n"] = [(f - forces_at(pm, X, Y, d)).tolist() for f, d in zip(f_stone, dd)]
            del pm
        del m
        row["solve_s"] = time.perf_counter() - t0
        rows.append(row)
        if progress:
            progress(k + 1, len(stones), row)
    return {"probe_grid": n_grid, "x_m": X.tolist(), "y_m": Y.tolist(), "levels_m": list(levels), "stones": rows}


def check_error(sur: Surrogate3D, direct: dict) -> dict:
    """The table's errors against ``direct_contrasts``: per stone and level, absolute (N) and relative to the
    peak of the direct contrast, against the direct and (when computed) the same-mesh contrast."""
    X, Y = np.array(direct["x_m"]), np.array(direct["y_m"])
    out = []
    for r in direct["stones"]:
        row = {k: r[k] for k in ("xs_m", "ys_m", "depth_m", "diam_m")}
        row["levels"] = []
        for a, d in enumerate(direct["levels_m"]):
            true = np.array(r["direct_n"][a], float)
            ok = np.isfinite(true)
            est = sur.contrast(X[ok], Y[ok], d, r["xs_m"], r["ys_m"], r["depth_m"], r["diam_m"])
            e = est - true[ok]
            lv = {"depth_m": d, "n": int(ok.sum()), "peak_contrast_n": float(np.max(np.abs(true[ok]))),
                  "peak_est_n": float(np.max(np.abs(est))), "rms_err_n": float(np.sqrt(np.mean(e ** 2))),
                  "max_err_n": float(np.max(np.abs(e)))}
            if "same_n" in r:
                same = np.array(r["same_n"][a], float)[ok]
                lv.update({"peak_same_n": float(np.max(np.abs(same))),
                           "rms_err_same_n": float(np.sqrt(np.mean((est - same) ** 2))),
                           "max_err_same_n": float(np.max(np.abs(est - same))),
                           "rms_ripple_n": float(np.sqrt(np.mean((true[ok] - same) ** 2)))})
            row["levels"].append(lv)
        out.append(row)
    return {"stones": out, "summary": summary(out)}


def summary(rows: list) -> dict:
    """Medians and maxima over stones and levels of the relative (to the peak of the direct contrast) and absolute
    errors, against the direct contrast and (when measured) the same-mesh one."""
    lvs = [lv for r in rows for lv in r["levels"]]
    out = {}
    for tag, key in (("direct", ""), ("same_mesh", "_same")):
        if f"rms_err{key}_n" not in lvs[0]:
            continue
        rel_rms = np.array([lv[f"rms_err{key}_n"] / lv["peak_contrast_n"] for lv in lvs])
        rel_max = np.array([lv[f"max_err{key}_n"] / lv["peak_contrast_n"] for lv in lvs])
        abs_rms = np.array([lv[f"rms_err{key}_n"] for lv in lvs])
        out[tag] = {"rel_rms_median": float(np.median(rel_rms)), "rel_rms_max": float(rel_rms.max()),
                    "rel_max_median": float(np.median(rel_max)), "rel_max_max": float(rel_max.max()),
                    "abs_rms_median_n": float(np.median(abs_rms)), "abs_rms_max_n": float(abs_rms.max())}
    if "rms_ripple_n" in lvs[0]:
        out["ripple_rms_n"] = {"median": float(np.median([lv["rms_ripple_n"] for lv in lvs])),
                               "max": float(np.max([lv["rms_ripple_n"] for lv in lvs]))}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m planner.surrogate3d", description=__doc__.splitlines()[0])
    p.add_argument("scene", nargs="?", default="block3d")
    p.add_argument("--workers", type=int, default=1, help="dask LocalCluster workers (1: serial)")
    p.add_argument("--scheduler", help="an existing dask scheduler (tcp://HOST:PORT) instead")
    p.add_argument("--check", type=int, default=-1, metavar="N",
                   help="measure the error at 4 fixed stones and N random ones (direct fem, ~2 min each)")
    p.add_argument("--levels-mm", default="2,3,4", help="probe levels of the check (mm, comma-separated)")
    p.add_argument("--no-same-mesh", action="store_true", help="only the direct contrast (half the check's cost)")
    p.add_argument("--direct", metavar="PATH", help="keep fem's check contrasts there (read back when it exists)")
    p.add_argument("--json", metavar="PATH", help="write the measurements there")
    p.add_argument("--ship", action="store_true", help="also write the table (float32) to planner/data/")
    a = p.parse_args(argv)
    prior = load(a.scene).prior()
    t0 = time.perf_counter()
    sur = load_surrogate3d(prior, runner=Runner(workers=a.workers, scheduler=a.scheduler),
                           progress=lambda i, n, t, what: print(f"  surrogate3d: {i}/{n} {what}, {t:.0f} s",
                                                          file=sys.stderr, flush=True))
    path = cache_path(prior, Grid3D())
    print(f"surrogate3d for {a.scene}: {path} ({time.perf_counter() - t0:.1f} s; built in {sur.build_s:.0f} s)")
    if a.ship:
        d = {k: np.asarray(v) for k, v in sur.data.items()}
        d["table"] = d["table"].astype(np.float32)
        if len(sur.calibration[0]):          # the calibration for the scene's own mesh, as used: shipped with it
            d.update(cal_s_m=np.asarray(sur.calibration[0], float), cal_factor=np.asarray(sur.calibration[1], float),
                     cal_mesh=own_mesh(prior))
        SHIPPED.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(cache_path(prior, Grid3D(), SHIPPED), **d)
        print(f"shipped: {cache_path(prior, Grid3D(), SHIPPED)}")
    if a.check >= 0:
        levels = tuple(float(v) * 1e-3 for v in a.levels_mm.split(","))
        direct = None
        if a.direct and Path(a.direct).exists():
            direct = json.loads(Path(a.direct).read_text())       # fem's contrasts from an earlier check
        if direct is None:
            direct = direct_contrasts(prior, check_stones(sur, a.check), levels=levels,
                                      same_mesh=not a.no_same_mesh, progress=lambda k, n, r: print(
                                          f"  check {k}/{n}: stone ({r['xs_m'] * 1e3:.1f}, {r['ys_m'] * 1e3:.1f}) mm, "
                                          f"depth {r['depth_m'] * 1e3:.1f}, D {r['diam_m'] * 1e3:.1f}: "
                                          f"{r['solve_s']:.0f} s", file=sys.stderr, flush=True))
            if a.direct:
                Path(a.direct).write_text(json.dumps(direct))
        res = check_error(sur, direct)
        for r in res["stones"]:
            print(f"stone ({r['xs_m'] * 1e3:.1f}, {r['ys_m'] * 1e3:.1f}) mm, depth {r['depth_m'] * 1e3:.1f}, D "
                  f"{r['diam_m'] * 1e3:.1f}: " + "; ".join(
                      f"d={lv['depth_m'] * 1e3:.0f} peak {lv['peak_contrast_n'] * 1e3:.3f} mN, rms "
                      f"{lv['rms_err_n'] / lv['peak_contrast_n']:.1%} max {lv['max_err_n'] / lv['peak_contrast_n']:.1%}"
                      + (f" (same-mesh rms {lv['rms_err_same_n'] / lv['peak_contrast_n']:.1%}, ripple "
                         f"{lv['rms_ripple_n'] * 1e3:.3f} mN)" if "rms_err_same_n" in lv else "")
                      for lv in r["levels"]))
        print(json.dumps(res["summary"], indent=1))
        if a.json:
            Path(a.json).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
