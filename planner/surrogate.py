"""A fem-built forward model of the force contrast a buried stone adds: fast enough for a least-squares fit.

The contrast of a probe at surface position x0 and depth d is ``F_stone(x0, d) - F_prior(x0, d)``: the force the
tissue with a (rigid) stone pushes back with, minus fem's prediction for the stone-free prior. A full fem surface
model per candidate stone costs ~0.7 s, far too slow inside an optimizer, so the contrast is tabulated once per prior
scene on a grid of candidate stones and interpolated:

* stone grid: top clearance ``s = depth - diameter/2`` (geometric nodes, the contrast falls steeply with s), diameter
  D, lateral position xs over the left half of the section (``_grid_xs``) (the section, its supports and the load are mirror
  symmetric, so a stone at xs > W/2 is the mirror image of one at W - xs);
* per stone: the contrast at probe depths ``levels_m`` and probe positions x0 on a 0.5 mm grid over the whole surface.

Query (``contrast``): cubic Lagrange weights in (log s, D) over a 4 x 4 stencil; in xs, the two neighbouring grid
stones' contrast curves are *shifted* to the query position (the contrast is nearly translation invariant; the shift
keeps a peak sharp where plain interpolation in xs would smear it) and blended linearly (this carries the slow edge
correction); linear in x0 and in probe depth. Candidate stones are rigid (the paper's 5 GPa stone is treated as rigid
by fem: a stone 10^6 times stiffer than tissue).

What selects a table (``table_scene``): only what changes the answer. In linear elasticity with a rigid stone and a
rigid tip, the force is proportional to the tissue's Young's modulus at fixed Poisson ratio (the stiffness matrix is
E times a matrix of the geometry and nu; the contact constraints are displacements), so the key holds the tissue at a
unit modulus and a table built at ``youngs_ref_pa`` serves every modulus, scaled by E / youngs_ref_pa
(tests/test_table_keys.py checks this against direct fem at another modulus). A tip fem treats as rigid (its
relative compliance rho = E (1 - nu_tip^2) / (E_tip (1 - nu^2)) below fem.tip.TIP_TOLERANCE = 1e-3: the force
changes by about rho; the study's 60 MPa tip: 4.5e-5) keys as the rigid tip; an elastic tip keys by E_tip / E. The
key thus holds: the tissue's width, height and Poisson ratio; the tip's shape, radius and thickness (and E_tip / E
for an elastic tip); the analysis' plane, order, mesh size, surface refinement and formulation; the grid. Not: the
scene's name, the tissue modulus, the stones, a rigid-treated tip's modulus, load A's top displacement.

The table is cached on disk (``$PALPATE_CACHE_DIR`` or ``~/.cache/palpate``; ``surrogate-<key>.npz``) and carries a
behavioural fingerprint of the fem that built it (``fingerprint``: fem's forces for the prior and one grid stone at a
few probes, computed at the prior's own modulus (0.4-0.9 s; once per version of fem and its libraries, then read
from the disk cache: planner.fingerprint) and compared with the stored one scaled; a mismatch means rebuild). It is built once (3-7 min on 2 cores; 471 fem models on the paper section, fewer where wide stones leave a narrow or thin one (426 on 55 x 45 mm), more on a section wider than 70 mm, which keeps the positions near its sides and adds some towards its middle (``_grid_xs``: 727 on 200 x 50 mm, 8 min); on dask.distributed with
``planner.tasks``) and read in milliseconds. A table for the built-in paper tissue is shipped in planner/data/ (same
file name, same check).
``python -m planner.surrogate [SCENE] [--check N]`` builds it and measures the interpolation error against direct fem.
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import hashlib
import json
import math
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.arrays import clip
from fem import contact as fem_contact
from fem import diskcache
from fem.contact import SurfaceModel, surface_model
from fem.model import build_model
from fem.scene import STRAIN_MAX, Analysis, SceneError, Stone, from_dict, load
from fem.scene_mesh import mesh_for
from fem.tip import contact_scene
from planner.fingerprint import cached_fingerprint
from planner.tasks import Runner, array_of, run_pieces

FORMAT = 3           # 2: keyed by table_scene (unit modulus), youngs_ref_pa stored; 3: forces past the crush limit


@dataclass(frozen=True)
class Grid:
    s_m: tuple = (1.5e-3, 2.2e-3, 3.2e-3, 4.5e-3, 6.2e-3, 8.5e-3, 11.5e-3, 15.5e-3, 20.5e-3, 27e-3, 36e-3)
    diam_m: tuple = (4e-3, 6e-3, 8.5e-3, 11e-3, 14e-3, 17e-3)
    xs_m: tuple = (5e-3, 7.5e-3, 10e-3, 15e-3, 20e-3, 25e-3, 30e-3, 35e-3)   # left half of 70 mm (_grid_xs)
    levels_m: tuple = (1e-3, 1.5e-3, 2e-3, 2.5e-3, 3e-3, 3.5e-3, 4e-3)
    dx0_m: float = 0.5e-3

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in self.__dict__.items()}


def table_scene(prior, youngs_pa: float = 1.0):
    """The scene a table is computed on and keyed by (module doc): the prior with only what changes the contrast,
    its tissue at modulus ``youngs_pa`` (an elastic tip's modulus scaled with it), load A's option at its default."""
    prior = contact_scene(prior)
    scale = youngs_pa / prior.tissue.youngs_pa
    ind = prior.indenter
    if ind.youngs_pa is not None:
        ind = dataclasses.replace(ind, youngs_pa=ind.youngs_pa * scale)
    return dataclasses.replace(prior, name="surrogate-table", stones=(),
                               tissue=dataclasses.replace(prior.tissue, youngs_pa=youngs_pa), indenter=ind,
                               analysis=dataclasses.replace(prior.analysis,
                                                            top_displacement_m=Analysis().top_displacement_m))


def cache_path(prior, grid: Grid, root: Path | None = None) -> Path:
    """Where the table of ``prior`` lives in ``root`` (default: fem's disk cache directory)."""
    root = diskcache.cache_dir() if root is None else root
    key = hashlib.sha256(json.dumps(_key(table_scene(prior), grid), sort_keys=True).encode()).hexdigest()[:16]
    return root / f"surrogate-{key}.npz"


def _key(scene, grid: Grid) -> dict:
    """What a table (and its fingerprint) is keyed by: the scene, the grid and FORMAT; on a section wider than 70 mm
    also its stone positions (since session 50 they are not the grid's scaled ones there: ``_grid_xs``; a section
    up to 70 mm keeps its key, and its table)."""
    key = {"scene": scene.key(), "grid": grid.to_dict(), "format": FORMAT}
    if scene.tissue.width_m > REF_WIDTH_M:
        key["xs_m"] = [repr(float(x)) for x in _grid_xs(scene, grid)]
    return key


FP_X = (0.012, 0.024, 0.030, 0.036, 0.047)      # fingerprint probe positions (fraction of 70 mm; scaled)
FP_STONE = (4, 3, 4)                            # grid node (s, diameter, xs) of the fingerprint stone


def fingerprint(prior, grid: Grid) -> np.ndarray:
    """What fem computes *now* for one grid stone and the prior at a few probes (4 mm): a table whose stored
    fingerprint differs was built by a different fem (mesher, elements, contact...) and is rebuilt. A behavioural
    check, not a source hash: refactoring fem without changing its numbers keeps the table."""
    W = prior.tissue.width_m
    x0 = np.asarray(FP_X) * W / 0.070
    # the deepest level, within fem's range on a thin section or under a small tip (else every force is refused)
    lv = [min(grid.levels_m[-1], 0.9 * STRAIN_MAX * prior.tissue.height_m, 0.9 * prior.indenter.radius_m)]
    i, j, k = fingerprint_stone(prior, grid)
    s, D, xs = grid.s_m[i], grid.diam_m[j], _grid_xs(prior, grid)[k]
    st = stone_model(prior.with_stones([Stone(x_m=float(xs), depth_m=float(s + D / 2), diameter_m=float(D))]))
    return np.concatenate([_forces(surface_model(prior), lv, x0)[0], _forces(st, lv, x0)[0]])


def fingerprint_stone(prior, grid: Grid) -> tuple[int, int, int] | None:
    """The grid node (s, diameter, xs) of the fingerprint stone: FP_STONE (clamped to a small grid) where it fits in
    the section; in a section too thin or narrow for it, the one nearest to it that fits (shallower, then smaller);
    None when none does."""
    i0, j0, k0 = (min(a, len(v) - 1) for a, v in zip(FP_STONE, (grid.s_m, grid.diam_m, grid.xs_m)))
    xs = _grid_xs(prior, grid)
    for i, j in sorted(((i, j) for i in range(i0 + 1) for j in range(j0 + 1)), key=lambda t: (-t[1], -t[0])):
        for k in sorted(range(len(xs)), key=lambda m: (abs(m - k0), -m)):
            s, D = grid.s_m[i], grid.diam_m[j]
            if fits_sideways(prior, float(xs[k]), s + D / 2, D):
                return i, j, k
    return None


def _fingerprint_now(own, grid: Grid) -> np.ndarray:
    """``fingerprint(own, grid)``, read from fem's disk cache when today's fem and libraries computed it before
    (planner.fingerprint: the same numbers, without the 0.7 s of a mesh and a factorization per process)."""
    return cached_fingerprint("fingerprint", _key(own, grid), lambda: fingerprint(own, grid))


REF_WIDTH_M = 0.070        # the section Grid.xs_m is laid out for (its last position is the middle)
FAR_SPACING_M = 20e-3      # on a wider section, the widest spacing of the positions beyond Grid.xs_m's last


def _grid_xs(prior, grid: Grid) -> np.ndarray:
    """The stone positions (left half) of ``grid`` on the prior's section. Up to 70 mm wide: Grid.xs_m scaled with
    the width. Wider (since session 52): Grid.xs_m's positions stay where they are (their distances from the side:
    5, 7.5, 10 mm, then every 5 mm to 35 mm), and the rest of the half-width up to the middle is split evenly in
    steps of at most FAR_SPACING_M; a rest shorter than Grid.xs_m's last step moves the last position to the
    middle instead (continuous at 70 mm).

    Why: the side changes a stone's contrast most within some 35 mm of it, on sections 25 to 100 mm tall alike, so
    the table's shift-and-blend in xs (module doc) needs close positions there and only there. Direct fem on
    200 x 50, 240 x 100 and 200 x 25 mm sections (8 mm stone, top 11 or 6 mm deep, probes 4 mm deep), the blend of
    two positions' shifted contrasts against the contrast midway, RMS relative to its peak: 15-35 mm 2.1-3.1 %,
    15-25 mm 1.0-1.6 %, 25-35 mm 0.3-0.5 %; beyond 35 mm, 20 mm apart 0.15-0.65 % and 40 mm apart 0.04-0.35 % (the
    localizer allows 1 %). A big deep stone feels the side further in (17 mm, its top 18.5 mm deep, on 200 x 50 mm:
    35-55 mm 1.00 %, 35-51.25 mm, the 200 mm section's own step, 0.75 %; a session-52 review). Session 50's rule (the positions within 15 mm of the side kept, the other four spread
    evenly) left 15-36.25 mm between positions on a 200 mm section, and stones there came out 5.5-7.9 sigma off
    (docs/mismatch.md, "Wide sections")."""
    g = np.asarray(grid.xs_m, float)
    W = prior.tissue.width_m
    if W <= REF_WIDTH_M:
        return g * W / REF_WIDTH_M
    rest = W / 2 - g[-1]
    if len(g) > 1 and rest < g[-1] - g[-2]:
        return np.r_[g[:-1], W / 2]
    n = math.ceil(rest / FAR_SPACING_M - 1e-9)
    return np.r_[g, g[-1] + rest * np.arange(1, n + 1) / n]


def stone_model(scene):
    """fem's SurfaceModel of a one-off scene (a candidate or random stone), kept out of fem's disk cache (hundreds
    of meshes used once would only fill it). Its stones are rigid, whatever the tissue's modulus (the table's
    candidates are rigid stones; fem would make a 5 GPa stone rigid on 2.5 kPa tissue anyway)."""
    return SurfaceModel(scene, model=build_model(scene, mesh=mesh_for(scene, use=False), rigid_stones=True))


def _one_stone(shared: dict, stone: tuple[float, float, float]) -> np.ndarray:
    """Force curves (levels, x0) of one grid stone (xs_m, depth_m, diameter_m). Runs on a worker (planner.tasks)."""
    prior = from_dict(shared["prior"])
    xs, depth, diam = stone
    model = stone_model(prior.with_stones([Stone(x_m=xs, depth_m=depth, diameter_m=diam)]))
    return _forces(model, shared["levels_m"], shared["x0_m"])


@contextlib.contextmanager
def _past_the_crush_limit():
    """fem's linear model asked past its crush limit over a shallow stone (fem.contact.STONE_LAYER_MAX: a waypoint
    pressing more than 75 % of the tissue layer above a stone is refused, since the tissue is crushed there): the
    table's entries there are the linear model's own forces, smooth in the stone's clearance, as the shipped table's
    were built before the limit existed (session 49 measured the alternative, entries continued in depth from the
    last allowed level: on the mismatch study's records, linear tissue's shallow stones' depths fell within 2 sigma
    in 67 % of cases, against 100 % with these). The localizer gives the readings past the limit a model error of
    half the contrast (planner.localize.CRUSH_REL_ERR), and the simulated truth continues its force itself."""
    with _LIFT_LOCK:           # a worker of a user's dask cluster may run several stones at once, in threads:
        if _LIFTED[0] == 0:    # the limit comes back when the last of them is done, not when the first is
            _LIFTED[1] = fem_contact.STONE_LAYER_MAX
            fem_contact.STONE_LAYER_MAX = math.inf
        _LIFTED[0] += 1
    try:
        yield
    finally:
        with _LIFT_LOCK:
            _LIFTED[0] -= 1
            if _LIFTED[0] == 0:
                fem_contact.STONE_LAYER_MAX = _LIFTED[1]


_LIFT_LOCK = threading.Lock()
_LIFTED = [0, None]            # (builds in progress in this process, fem's limit to restore)


def _forces(model, levels, x0, past_crush: bool = True) -> np.ndarray:
    """Force curves (levels x positions), past the crush limit too (``_past_the_crush_limit``; ``past_crush``
    False: refused there). Where fem refuses a waypoint the force is continued from the deepest allowed levels with
    their local power law (``_continue_in_depth``)."""
    with _past_the_crush_limit() if past_crush else contextlib.nullcontext():
        out = model.force_grid_n(x0, levels)
    if np.isnan(out).any():
        _continue_in_depth(out, np.asarray(levels, float))
    return out


def _continue_in_depth(f: np.ndarray, levels: np.ndarray) -> None:
    """Fill NaN force entries (levels x positions) from the deepest computed levels at the same position: F ~ d^p
    with p from the last two computed levels (1.5, Hertz, with fewer), in place; 0 where none was computed."""
    for b in range(f.shape[1]):
        ok = np.flatnonzero(~np.isnan(f[:, b]))
        if len(ok) == 0:
            f[:, b] = 0.0
            continue
        i1 = ok[-1]
        p = 1.5
        if len(ok) >= 2 and f[ok[-2], b] > 0 and f[i1, b] > 0:
            p = float(np.log(f[i1, b] / f[ok[-2], b]) / np.log(levels[i1] / levels[ok[-2]]))
        for a in np.flatnonzero(np.isnan(f[:, b])):
            f[a, b] = f[i1, b] * (levels[a] / levels[i1]) ** p


def fits_sideways(prior, x_m: float, depth_m: float, diam_m: float) -> bool:
    """Whether a stone at (x_m, depth_m) of diameter diam_m lies inside the section by fem's own rule (fem.scene:
    not touching a side)."""
    try:
        prior.with_stones([Stone(x_m=x_m, depth_m=depth_m, diameter_m=diam_m)])
    except SceneError:
        return False
    return True


def check_table_fits(prior, grid: Grid = Grid()) -> None:
    """ValueError naming the section's size unless a table can be built for it: a fingerprint stone fits
    (``fingerprint_stone``), and the smallest diameter fits at the middle (elsewhere stones that leave a side are
    extrapolated: ``_fill_sideways``; those that leave the bottom: ``_fill_invalid``)."""
    t = prior.tissue
    xs = _grid_xs(prior, grid)
    if fingerprint_stone(prior, grid) is None or not fits_sideways(prior, float(xs[-1]), grid.s_m[0] + grid.diam_m[0] / 2,
                                                                    grid.diam_m[0]):
        raise ValueError(f"the section (tissue.width_m = {t.width_m:g} m, height_m = {t.height_m:g} m) is too small "
                         f"for the localizer's table: its smallest stone ({grid.diam_m[0] * 1e3:g} mm across, its top "
                         f"{grid.s_m[0] * 1e3:g} mm deep) must fit inside it")


def build_table(prior, grid: Grid = Grid(), workers: int = 2, progress=None, runner: Runner | None = None,
                store: Path | None = None) -> dict:
    """Run fem for every grid stone on ``table_scene(prior)`` at the prior's own modulus (``youngs_ref_pa``), on
    ``runner`` (planner.tasks; default a LocalCluster of ``workers``, serial for 1); finished stones are kept in
    ``store`` (a re-run resumes). ``progress(done, total, elapsed_s)`` as stones finish. Returns the arrays that
    ``Surrogate`` reads."""
    prior = table_scene(prior, prior.tissue.youngs_pa)
    check_table_fits(prior, grid)
    runner = runner or Runner(workers=workers, progress=progress is None)
    W = prior.tissue.width_m
    x0 = np.arange(0.0, W + 1e-12, grid.dx0_m)
    xs = _grid_xs(prior, grid)
    stones, idx = [], []
    H = prior.tissue.height_m
    inside = np.zeros((len(grid.s_m), len(grid.diam_m), len(xs)), bool)
    for i, s in enumerate(grid.s_m):
        for j, D in enumerate(grid.diam_m):
            if s + D > H - 1e-3:
                continue                  # the stone would leave the bottom: filled by extrapolation below
            for k, x in enumerate(xs):
                if not fits_sideways(prior, float(x), float(s + D / 2), float(D)):
                    continue              # it would leave the side of a narrow section: filled by extrapolation
                inside[i, j, k] = True
                stones.append((float(x), float(s + D / 2), float(D)))
                idx.append((i, j, k))
    table = np.zeros((len(grid.s_m), len(grid.diam_m), len(xs), len(grid.levels_m), len(x0)))
    t0 = time.perf_counter()
    base = _forces(surface_model(prior), grid.levels_m, x0)      # the prior's force, subtracted from every stone's
    done = {"n": 0}

    def arrived(n, res):
        i, j, k = idx[n]
        table[i, j, k] = res - base
        done["n"] += 1
        if progress and (done["n"] % 20 == 0 or done["n"] == len(stones)):
            progress(done["n"], len(stones), time.perf_counter() - t0)
    shared = {"prior": prior.to_dict(), "levels_m": list(grid.levels_m), "x0_m": x0}
    run_pieces(_one_stone, shared, stones, [f"stone-{i}-{j}-{k}" for i, j, k in idx], runner=runner, store=store,
               desc="surrogate stones", on_result=arrived,
               shape=array_of((len(grid.levels_m), len(x0))))
    _fill_sideways(table, inside, xs, grid, H)
    _fill_invalid(table, grid, H)
    return {"s_m": np.array(grid.s_m), "diam_m": np.array(grid.diam_m), "xs_m": xs,
            "levels_m": np.array(grid.levels_m), "x0_m": x0, "table": table, "width_m": np.array(W),
            "youngs_ref_pa": np.array(prior.tissue.youngs_pa), "build_s": np.array(time.perf_counter() - t0)}


def _fill_sideways(table: np.ndarray, inside: np.ndarray, xs: np.ndarray, grid: Grid, H: float) -> None:
    """Grid stones that would leave the side of the section (the wide ones at the positions 5 and 7.5 mm from a
    side on a 70 mm section, since session 49: 41 of 512 entries; more on a narrower one, as the positions scale with
    the width and the diameters do not): linear extrapolation in x from the two nearest positions where that
    (clearance, diameter) fits (the value there with one; from the next smaller diameter where none does). Such a
    stone is not a physical one: the entries only keep the interpolation stencils defined."""
    for i, s in enumerate(grid.s_m):
        for j, D in enumerate(grid.diam_m):
            if s + D > H - 1e-3 or inside[i, j].all():
                continue
            ok = np.flatnonzero(inside[i, j])
            for k in np.flatnonzero(~inside[i, j]):
                if len(ok) >= 2:
                    a, b = sorted(ok, key=lambda m: (abs(m - k), m))[:2]
                    t = (xs[k] - xs[a]) / (xs[b] - xs[a])
                    table[i, j, k] = table[i, j, a] + t * (table[i, j, b] - table[i, j, a])
                elif len(ok) == 1:
                    table[i, j, k] = table[i, j, ok[0]]
                else:               # (check_table_fits: the smallest diameter fits somewhere)
                    table[i, j, k] = table[i, j - 1, k]


def _fill_invalid(table: np.ndarray, grid: Grid, H: float) -> None:
    """Grid stones too deep for the section (s + D > H - 1 mm): linear extrapolation in log s from the two shallower
    nodes, so the cubic stencil stays smooth near the bottom. A fit never ends there (see localize's bounds)."""
    ls = np.log(grid.s_m)
    for j, D in enumerate(grid.diam_m):
        for i, s in enumerate(grid.s_m):
            if s + D > H - 1e-3 and i >= 2:
                t = (ls[i] - ls[i - 1]) / (ls[i - 1] - ls[i - 2])
                table[i, j] = table[i - 1, j] + t * (table[i - 1, j] - table[i - 2, j])


def _lagrange4(nodes: np.ndarray, u: float) -> tuple[np.ndarray, np.ndarray]:
    """Indices (4) and cubic Lagrange weights of u over the 4-node stencil around it (clamped to the range)."""
    n = len(nodes)
    u = min(max(u, nodes[0]), nodes[-1])
    i = min(max(int(np.searchsorted(nodes, u)) - 2, 0), n - 4)
    st = nodes[i:i + 4]
    w = np.ones(4)
    for a in range(4):
        for b in range(4):
            if a != b:
                w[a] *= (u - st[b]) / (st[a] - st[b])
    return np.arange(i, i + 4), w


def _lagrange4_slope(nodes: np.ndarray, u: float) -> np.ndarray:
    """d/du of ``_lagrange4``'s weights at u: 0 outside the nodes' range, where the weights are held; at an end, and
    within round-off of it (a fit at its bound there: s = (s + D/2) - D/2 may land a hair outside), the slope
    inwards."""
    tol = 1e-9 * (nodes[-1] - nodes[0])
    if not nodes[0] - tol <= u <= nodes[-1] + tol:
        return np.zeros(4)
    u = min(max(u, nodes[0]), nodes[-1])
    i = min(max(int(np.searchsorted(nodes, u)) - 2, 0), len(nodes) - 4)
    st = nodes[i:i + 4]
    dw = np.zeros(4)
    for a in range(4):
        for c in range(4):
            if c != a:
                term = 1.0 / (st[a] - st[c])
                for b in range(4):
                    if b != a and b != c:
                        term *= (u - st[b]) / (st[a] - st[b])
                dw[a] += term
    return dw


def modulus_scale(data: dict, prior) -> float:
    """The factor that turns a table built at its ``youngs_ref_pa`` into the prior's forces (module doc)."""
    return float(prior.tissue.youngs_pa / float(data["youngs_ref_pa"]))


class Surrogate:
    """The tabulated contrast; ``contrast(x0_m, depth_m, xs_m, stone_depth_m, diam_m)`` per probe (N). With a
    ``prior`` the table is scaled to the prior's tissue modulus (``modulus_scale``)."""

    def __init__(self, data: dict, prior=None):
        self.prior = prior
        self.scale = modulus_scale(data, prior) if prior is not None else 1.0
        self.s = np.asarray(data["s_m"])
        self.logs = np.log(self.s)
        self.diam = np.asarray(data["diam_m"])
        self.xs = np.asarray(data["xs_m"])
        self.levels = np.asarray(data["levels_m"])
        self.x0 = np.asarray(data["x0_m"])
        self.T = np.ascontiguousarray(np.asarray(data["table"]) * self.scale if self.scale != 1.0 else data["table"])
        self.W = float(data["width_m"])
        self.build_s = float(data.get("build_s", 0.0))
        self._slices: dict[tuple[float, float], np.ndarray] = {}
        self._slopes: dict[tuple[float, float], tuple[np.ndarray, np.ndarray]] = {}

    # parameter box the table covers (a fit stays inside it)
    @property
    def bounds(self) -> dict:
        return {"xs_m": (self.xs[0], self.W - self.xs[0]), "s_m": (self.s[0], self.s[-1]),
                "diam_m": (self.diam[0], self.diam[-1])}

    def _slice(self, s: float, diam_m: float, k0: int | None = None) -> np.ndarray:
        """The table interpolated to clearance ``s`` and diameter ``diam_m``: (nxs, nlev, nx0); with ``k0`` its rows
        k0 and k0 + 1 only (2, nlev, nx0): all a single stone's stencil reads (a third of the work on the shipped
        tables; the same numbers as the whole slice's rows). Remembered for the last few hundred (s, D): a fit's
        candidates and its Jacobian's x and nuisance steps ask for the same ones."""
        C = self._slices.get((s, diam_m))
        if C is not None:
            return C if k0 is None else C[k0:k0 + 2]
        key = (s, diam_m) if k0 is None else (s, diam_m, k0)
        C = self._slices.get(key)
        if C is None:
            i_s, w_s = _lagrange4(self.logs, float(np.log(s)))
            i_d, w_d = _lagrange4(self.diam, diam_m)
            C = self._blend(i_s, w_s, i_d, w_d, k0)
            if len(self._slices) >= 512:
                self._slices.clear()
            self._slices[key] = C
        return C

    def _blend(self, i_s: np.ndarray, w_s: np.ndarray, i_d: np.ndarray, w_d: np.ndarray,
               k0: int | None = None) -> np.ndarray:
        """sum over i, j of w_s[i] w_d[j] T[i_s[i], i_d[j]]: (nxs, nlev, nx0), or its rows k0, k0 + 1. The stencils
        are 4 consecutive nodes, so the table is read through a view (a fancy index copied 0.8 MB: 4 times the
        time, the same sums); each output element sums its 16 terms alike however many are computed."""
        v = self.T[i_s[0]:i_s[0] + 4, i_d[0]:i_d[0] + 4]
        if k0 is not None:
            v = v[:, :, k0:k0 + 2]
        return np.einsum("ij,ijm->m", np.outer(w_s, w_d), v.reshape(4, 4, -1)).reshape(v.shape[2:])

    def _slice_slopes(self, s: float, diam_m: float, k0: int) -> tuple[np.ndarray, np.ndarray]:
        """d/d(log s) and d/d(diam_m) of ``_slice`` (at fixed s and fixed diameter respectively), rows k0 and
        k0 + 1, remembered alike."""
        key = (s, diam_m, k0)
        v = self._slopes.get(key)
        if v is None:
            i_s, w_s = _lagrange4(self.logs, float(np.log(s)))
            i_d, w_d = _lagrange4(self.diam, diam_m)
            dw_s, dw_d = _lagrange4_slope(self.logs, float(np.log(s))), _lagrange4_slope(self.diam, diam_m)
            v = (self._blend(i_s, dw_s, i_d, w_d, k0), self._blend(i_s, w_s, i_d, dw_d, k0))
            if len(self._slopes) >= 32:       # (a fit's Jacobians rarely revisit an (s, D))
                self._slopes.clear()
            self._slopes[key] = v
        return v

    def contrast_slopes(self, x0_m, depth_m, xs_m: float, stone_depth_m: float, diam_m: float) -> np.ndarray:
        """The derivatives of ``contrast`` at each probe, (4, n probes): with respect to the stone's position xs_m,
        the log of its clearance s = stone_depth_m - diam_m / 2 (the table's own variable), its diameter at fixed
        clearance, and the probe's depth. Exact for the interpolant (linear in xs, probe position and depth, cubic
        Lagrange in log s and diameter), one-sided at its nodes; 0 where the interpolant holds a clamped value."""
        st = _Stencil.of(self, x0_m, depth_m, [float(xs_m)])
        k0 = int(st.k[0])
        s = stone_depth_m - 0.5 * diam_m
        C = self._slice(max(s, 1e-6), float(diam_m), k0)                  # rows k0, k0 + 1
        Cs, CD = self._slice_slopes(max(s, 1e-6), float(diam_m), k0) if s > 1e-6 else (0.0 * C, 0.0 * C)
        t = float(st.t[0])
        dk = self.xs[k0 + 1] - self.xs[k0]
        dwk = 1.0 / dk if -1e-9 <= t <= 1.0 + 1e-9 else 0.0          # (inwards at an end)
        lev = self.levels
        du = np.where((st.d >= lev[0]) & (st.d <= lev[-1]), 1.0 / (lev[st.il + 1] - lev[st.il]), 0.0)
        h = self.x0[1] - self.x0[0]
        out = np.zeros((4, len(st.d)))
        vals = []
        wl = st.wl
        for kk, wkk, xq_raw, ix, wx in st.nodes():
            b = st.base(C, kk - k0, ix)
            c00, c01, c10, c11 = st.corners(C, b)
            lo, hi = (1 - wx) * c00 + wx * c01, (1 - wx) * c10 + wx * c11
            vals.append(((1 - wl) * lo + wl * hi)[0])
            d_xq = ((1 - wl) * (c01 - c00) + wl * (c11 - c10))
            inside = (xq_raw >= self.x0[0]) & (xq_raw <= self.x0[-1])
            out[0] -= wkk[0] * np.where(inside, d_xq / h, 0.0)[0]         # xq = x0 - xs + node: d xq / d xs = -1
            for j, T in ((1, Cs), (2, CD)):
                a, b2 = st.levels_at(T, b, wx)
                out[j] += wkk[0] * ((1 - wl) * a + wl * b2)[0]
            out[3] += wkk[0] * (hi - lo)[0] * du
        out[0] = (-1.0 if st.mirror[0] else 1.0) * (out[0] + (vals[1] - vals[0]) * dwk)
        return out

    def contrast(self, x0_m, depth_m, xs_m: float, stone_depth_m: float, diam_m: float) -> np.ndarray:
        return self.contrast_many(x0_m, depth_m, [float(xs_m)], stone_depth_m, diam_m)[0]

    def contrast_many(self, x0_m, depth_m, xs_m, stone_depth_m: float, diam_m: float) -> np.ndarray:
        """``contrast`` for stones at each of the positions ``xs_m`` (same depth and size): (len(xs_m), n probes)."""
        st = _Stencil.of(self, x0_m, depth_m, xs_m)
        k0 = int(st.k[0]) if len(st.k) and (st.k == st.k[0]).all() else None    # one stencil: its two rows only
        C = self._slice(max(stone_depth_m - 0.5 * diam_m, 1e-6), float(diam_m), k0)   # (nxs or 2, nlev, nx0)
        out = np.zeros((len(st.k), len(st.d)))
        for kk, wkk, _, ix, wx in st.nodes():
            lo, hi = st.levels_at(C, st.base(C, kk if k0 is None else kk - k0, ix), wx)
            out += wkk[:, None] * ((1 - st.wl) * lo + st.wl * hi)
        return out


@dataclass(frozen=True)
class _Stencil:
    """Where the probes (x0, depth) and the stones' positions fall in the table: the two neighbouring stone-position
    nodes and their weights, the depth levels, and per node the probe-position cells. Stones right of the middle
    are taken as their mirror images (the probes mirrored with them). ``contrast_many`` sums the table over it,
    ``contrast_slopes`` differentiates the same sum."""
    sur: Surrogate
    xs: np.ndarray           # the stones' positions, mirrored into the left half
    mirror: np.ndarray       # which were mirrored
    X0: np.ndarray           # (n stones, n probes): probe positions, mirrored with their stone
    k: np.ndarray            # the stone-position node below each stone
    t: np.ndarray            # its weight towards the node above, before clamping to [0, 1]
    d: np.ndarray            # probe depths
    il: np.ndarray           # the level below each depth
    wl: np.ndarray           # the weight of the level above (clamped)

    @staticmethod
    def of(sur: Surrogate, x0_m, depth_m, xs_m) -> _Stencil:
        x0 = np.asarray(x0_m, float)
        d = np.broadcast_to(np.asarray(depth_m, float), x0.shape)
        xs = np.asarray(xs_m, float)
        mirror = xs > 0.5 * sur.W                  # mirror image
        xs = np.where(mirror, sur.W - xs, xs)
        X0 = np.where(mirror[:, None], sur.W - x0[None, :], x0[None, :])
        k = clip(np.searchsorted(sur.xs, xs) - 1, 0, len(sur.xs) - 2)
        t = (xs - sur.xs[k]) / (sur.xs[k + 1] - sur.xs[k])
        # probe depth: linear between levels (clamped)
        u = clip(np.interp(d, sur.levels, np.arange(len(sur.levels))), 0, len(sur.levels) - 1)
        il = np.minimum(np.floor(u).astype(int), len(sur.levels) - 2)
        return _Stencil(sur, xs, mirror, X0, k, t, d, il, u - il)

    def nodes(self):
        """For the node below and the node above each stone: (node, weight, unclamped probe-position coordinate,
        cell, weight in the cell)."""
        x0 = self.sur.x0
        h = x0[1] - x0[0]
        wk = clip(self.t, 0.0, 1.0)
        for kk, wkk in ((self.k, 1.0 - wk), (self.k + 1, wk)):
            xq_raw = self.X0 - self.xs[:, None] + self.sur.xs[kk][:, None]
            v = (clip(xq_raw, x0[0], x0[-1]) - x0[0]) / h
            ix = np.minimum(np.floor(v).astype(int), len(x0) - 2)
            yield kk, wkk, xq_raw, ix, v - ix

    def base(self, T: np.ndarray, kk: np.ndarray, ix: np.ndarray) -> np.ndarray:
        """Flat indices into T (n, nlev, nx0; C-contiguous) of each probe's cell in row kk: level below, left end."""
        return (kk[:, None] * T.shape[1] + self.il) * T.shape[2] + ix

    @staticmethod
    def corners(T: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """T at the cells ``b`` (``base``): (below left, below right, above left, above right) -- what
        T[kk, il, ix], T[kk, il, ix + 1], T[kk, il + 1, ix], T[kk, il + 1, ix + 1] read, in one gather each."""
        t = T.reshape(-1)
        n = T.shape[2]
        return t[b], t[b + 1], t[b + n], t[b + n + 1]

    def levels_at(self, T: np.ndarray, b: np.ndarray, wx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """T at the probes' cells ``b`` (``base``), linear in the probe's position: on the level below, the one
        above."""
        c00, c01, c10, c11 = self.corners(T, b)
        return (1 - wx) * c00 + wx * c01, (1 - wx) * c10 + wx * c11


_MEM: dict[str, Surrogate] = {}


SHIPPED = Path(__file__).resolve().parent / "data"      # tables shipped with the source (checked like any other)


def table_candidates(prior, grid: Grid) -> list[Path]:
    """Where a table may be read from, in order: the disk cache (unless PALPATE_CACHE=0), then the shipped data."""
    return ([cache_path(prior, grid)] if diskcache.enabled() else []) + [cache_path(prior, grid, SHIPPED)]


def load_surrogate(prior, grid: Grid = Grid(), build: bool = True, workers: int = 2, progress=None,
                   check: bool = True, runner: Runner | None = None) -> Surrogate:
    """The surrogate of a prior scene (stone-free): from memory, the disk cache or the tables shipped in
    planner/data, provided its fingerprint matches what fem computes now (``fingerprint``: 0.7 s, once per version
    of fem and its libraries, then from the disk cache); else built with fem (minutes) and written to the cache."""
    if prior.stones:
        raise ValueError("the surrogate is built on the prior scene (no stones); pass scene.prior()")
    path = cache_path(prior, grid)
    mem_key = (str(path), prior.tissue.youngs_pa)
    if mem_key in _MEM:
        return _MEM[mem_key]
    own = table_scene(prior, prior.tissue.youngs_pa)     # the prior as fem computes it, at its own modulus
    fp = None
    data = None
    for cand in table_candidates(prior, grid):
        d = diskcache.read(cand)
        if d is None:
            continue
        if "youngs_ref_pa" not in d:
            print(f"surrogate: {cand} has no youngs_ref_pa (an older format): not used", file=sys.stderr)
            continue
        if check:
            fp = _fingerprint_now(own, grid) if fp is None else fp
            if "fingerprint" not in d or d["fingerprint"].shape != fp.shape or not np.allclose(
                    d["fingerprint"] * modulus_scale(d, prior), fp, rtol=1e-7, atol=1e-12 * modulus_scale(d, prior)):
                print(f"surrogate: {cand} was built by a different fem (fingerprint differs): not used",
                      file=sys.stderr)
                continue
        data = d
        break
    if data is None:
        if not build:
            raise FileNotFoundError(f"no valid surrogate table at {path}")
        store = path.with_suffix(".parts") if diskcache.enabled() else None     # finished stones: resumable
        data = build_table(prior, grid, workers=workers, progress=progress, runner=runner, store=store)
        data["fingerprint"] = _fingerprint_now(own, grid) if fp is None else fp
        if diskcache.enabled():
            diskcache.write(path, data)
    sur = Surrogate(data, prior)
    _MEM[mem_key] = sur
    return sur


BOTTOM_CLEARANCE_M = 3e-3      # random stones keep this far from the tissue's bottom


def random_stones(bounds: dict, width_m: float, height_m: float, n: int, rng) -> list[tuple[float, float, float]]:
    """``n`` random rigid stones (x_m, top depth s_m, diameter_m) inside a table's bounds and inside the tissue:
    the stone's bottom at least BOTTOM_CLEARANCE_M above the tissue's bottom, 1 mm from the side edges."""
    out = []
    for _ in range(n):
        D = rng.uniform(*bounds["diam_m"])
        s_hi = min(bounds["s_m"][1], height_m - BOTTOM_CLEARANCE_M - D)
        if s_hi <= bounds["s_m"][0]:
            raise ValueError(f"tissue height {height_m} m leaves no room for a {D * 1e3:.1f} mm stone")
        s = float(np.exp(rng.uniform(np.log(bounds["s_m"][0]), np.log(s_hi))))
        xs = float(rng.uniform(max(bounds["xs_m"][0], D / 2 + 1e-3), min(bounds["xs_m"][1], width_m - D / 2 - 1e-3)))
        out.append((xs, s, float(D)))
    return out


def check_error(sur: Surrogate, prior, n: int = 10, seed: int = 0, depth_m: float = 0.004) -> dict:
    """Interpolation error against direct fem at ``n`` random rigid stones inside the table's box: the error of the
    contrast over the surface, relative to the stone's peak contrast (RMS and max over the profile). A probe fem
    refuses (the tip would reach too close to a shallow stone: ValueError) is left out of its stone's profile and
    counted (``refused``); a stone with every probe refused is left out of the summary."""
    rng = np.random.default_rng(seed)
    m0 = surface_model(prior)
    x0 = np.linspace(0.005, prior.tissue.width_m - 0.005, 61)
    rows = []
    b = sur.bounds
    for xs, s, D in random_stones(b, sur.W, prior.tissue.height_m, n, rng):
        m1 = stone_model(prior.with_stones([Stone(x_m=xs, depth_m=s + D / 2, diameter_m=D)]))
        true = np.full(len(x0), np.nan)
        for i, x in enumerate(x0):
            try:
                true[i] = m1.force_n(float(x), depth_m) - m0.force_n(float(x), depth_m)
            except ValueError:
                pass
        ok = np.isfinite(true)
        row = {"xs_m": xs, "depth_m": s + D / 2, "diam_m": D, "refused": int((~ok).sum())}
        if ok.any():
            err = sur.contrast(x0[ok], depth_m, xs, s + D / 2, D) - true[ok]
            row.update(peak_contrast_n=float(np.max(np.abs(true[ok]))), rms_err_n=float(np.sqrt(np.mean(err ** 2))),
                       max_err_n=float(np.max(np.abs(err))))
        rows.append(row)
    rows_ok = [r for r in rows if "peak_contrast_n" in r]
    if not rows_ok:
        raise ValueError(f"fem refused every probe of all {n} stones at {depth_m * 1e3:g} mm: check a shallower depth")
    rel_rms = np.array([r["rms_err_n"] / r["peak_contrast_n"] for r in rows_ok])
    rel_max = np.array([r["max_err_n"] / r["peak_contrast_n"] for r in rows_ok])
    return {"n": n, "n_compared": len(rows_ok), "probes_refused": sum(r["refused"] for r in rows),
            "probe_depth_m": depth_m, "rel_rms_median": float(np.median(rel_rms)),
            "rel_rms_max": float(rel_rms.max()), "rel_max_median": float(np.median(rel_max)),
            "rel_max_max": float(rel_max.max()), "abs_max_err_n": float(max(r["max_err_n"] for r in rows_ok)),
            "stones": rows}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m planner.surrogate", description=__doc__.splitlines()[0])
    p.add_argument("scene", nargs="?", default="paper")
    p.add_argument("--workers", type=int, default=2, help="dask LocalCluster workers (1: serial)")
    p.add_argument("--scheduler", help="an existing dask scheduler (tcp://HOST:PORT) instead")
    p.add_argument("--check", type=int, default=0, metavar="N", help="measure the error at N random stones")
    p.add_argument("--json", metavar="PATH")
    p.add_argument("--ship", action="store_true", help="also write the table (float32) to planner/data/")
    a = p.parse_args(argv)
    prior = load(a.scene).prior()
    t0 = time.perf_counter()
    sur = load_surrogate(prior, runner=Runner(workers=a.workers, scheduler=a.scheduler), progress=lambda i, n, t: print(
        f"  surrogate: {i}/{n} stones, {t:.0f} s", file=sys.stderr, flush=True))
    print(f"surrogate for {a.scene}: {cache_path(prior, Grid())} ({time.perf_counter() - t0:.1f} s; "
          f"built in {sur.build_s:.0f} s)")
    if a.ship:
        with np.load(cache_path(prior, Grid())) as z:
            d = {k: z[k] for k in z.files}
        d["table"] = d["table"].astype(np.float32)      # 1e-7 relative: far below the interpolation error
        SHIPPED.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(cache_path(prior, Grid(), SHIPPED), **d)
        print(f"shipped: {cache_path(prior, Grid(), SHIPPED)}")
    if a.check:
        r = check_error(sur, prior, n=a.check)
        print(f"interpolation error at {r['n_compared']} of {a.check} random stones ({r['probes_refused']} probes "
              f"fem refuses near shallow stones left out; relative to peak contrast): RMS median "
              f"{r['rel_rms_median']:.3%}, max {r['rel_rms_max']:.3%}; pointwise max median {r['rel_max_median']:.3%}"
              f", max {r['rel_max_max']:.3%}; largest absolute {r['abs_max_err_n'] * 1e3:.3f} mN")
        if a.json:
            Path(a.json).write_text(json.dumps(r, indent=1))
    return 0


if __name__ == "__main__":
    # the importable module's main, not this __main__ copy's: dask sends the stones' function to its workers by
    # reference, and this copy's (with its lock) could not be (`python -m planner.surrogate SCENE` failed at its
    # first stone until session 60)
    from planner.surrogate import main as _main
    sys.exit(_main())
