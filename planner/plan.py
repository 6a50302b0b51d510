"""The raster planner: one IPOPT NLP over all waypoints of a raster, seeded from the closed-form IK.

Decision variables: per waypoint k the approach configuration ``qa_k`` and the indent configuration ``qi_k`` (6 each).
Constraints (bounds carry the targets and margins, so one built solver serves every raster of the same size):

* TCP position of ``qa_k`` / ``qi_k`` equals the approach / indent target (base frame),
* tool axis alignment ``dot(z_tool, n_in) >= cos(tilt_tol)`` (no log-map, no NaN at zero error),
* approach and indent orientations alike: ``dot(x_tool(qa_k), x_tool(qi_k)) >= cos(tilt_tol)`` (the descent is a
  straight moveL along the tool axis),
* IK branch and singularity margins: ``sign_b * indicator_b(q) >= margin_b`` for b in shoulder / elbow / wrist
  (ur5e.branch_indicators): every configuration stays on the seed's branch, so no neighbour flips,
* joint limits as simple bounds.

Objective: joint travel ``sum_k 2|qi_k - qa_k|^2 + |qa_{k+1} - qa_k|^2`` (down-and-up plus moves between probes), a
small pull towards the seed (fixes the free rotation about the tool axis that travel alone leaves flat) and a tilt
penalty (W_TILT: the tolerance is a hard bound; tilt is used only where it buys joint travel).
The solver is built once per raster size and cached (``nlp_for(n)``); ``plan_raster`` builds it mapped per waypoint
(``RasterNLP(n, mapped=True)``: 0.02 s for the paper's 15-waypoint raster where the one-graph build takes 0.12 s;
the same iterates, the joints equal to ~1e-15 rad; the one-graph build stays as the reference the tests and
bench/bench_planner3d.py compare it with).

Entry points: ``plan_raster(scene, ...) -> planfile.Plan`` and, for adaptive refinement, ``replan(plan, x_positions_m)``
(same frames, limits, motion and options as an earlier plan, new waypoints).
"""
from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from core import ur5e
from core.contracts import SURFACE_FIT_FROM_FRACTION, Frames, Limits, Motion, Plan, PlanError, PlanOptions, Probe
from fem import recall
from fem.contact import surface_model
from fem.scene import STRAIN_MAX, from_dict, load
from planner import area
from planner import kinematics as kin
from planner.interrupt import interruptible
from planner.raster import (
    Targets,
    choose_depths,
    default_tissue_pose,
    force_exponents,
    raster_positions,
    targets,
)
from planner.timing import raster_timing

DEFAULT_GRID = (7, 7)    # a 3D block's raster when neither a grid nor a spacing is given
W_REG = 1e-3     # pull towards the seed [1/rad^2]
W_TILT = 100.0   # penalty on 1 - cos(tilt) ~ tilt^2/2: tilt is spent only where it buys real joint travel
POS_TOL_M = 1e-6
IPOPT_OPTIONS = {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes", "ipopt.tol": 1e-10,
                 "ipopt.constr_viol_tol": 1e-10, "ipopt.mu_init": 1e-4, "ipopt.max_iter": 200,
                 "ipopt.warm_start_init_point": "yes", "ipopt.warm_start_bound_push": 1e-9,
                 "ipopt.warm_start_mult_bound_push": 1e-9}


@dataclass
class Margins:
    """Singularity margins: shoulder [m] (wrist centre's reach in the arm plane), elbow |sin q3|, wrist |sin q5|."""
    shoulder_m: float = 0.05
    elbow: float = 0.15
    wrist: float = 0.15

    def as_array(self) -> np.ndarray:
        return np.array([self.shoulder_m, self.elbow, self.wrist])


def _waypoint_terms(fk, qa, qi, n_in, T_tcp) -> tuple[list, object]:
    """One waypoint's constraint pieces (TCP positions, tool-axis cosines, approach/indent x-axis cosine, branch
    indicators; in the bounds' order) and its cost (down-and-up travel and the tilt penalty), as SX."""
    Ta, pwa = fk(qa, T_tcp)
    Ti, pwi = fk(qi, T_tcp)
    ca_, ci = ca.dot(Ta[:3, 2], n_in), ca.dot(Ti[:3, 2], n_in)
    g = [Ta[:3, 3], Ti[:3, 3], ca_, ci, ca.dot(Ta[:3, 0], Ti[:3, 0]),
         kin.branch_indicators_sx(qa, pwa), kin.branch_indicators_sx(qi, pwi)]
    return g, 2 * ca.sumsqr(qi - qa) + W_TILT * (2 - ca_ - ci)


class RasterNLP:
    """The IPOPT solver for rasters of ``n`` waypoints (parametric: targets in the bounds, normal/TCP/seed in p).

    ``mapped=False``: the whole problem as one SX graph (the reference; its build grows with n: ~1.4 s for 100
    waypoints, ~6 s for 400). ``mapped=True``: the same problem with one waypoint's constraints, cost and their
    derivatives as SX Functions ``map``-ped over the n waypoints inside an MX graph: the build is nearly independent
    of n (~0.05 s for 400), a solve as fast, the solution the same to ~1e-15 rad (same iterates:
    bench/bench_planner3d.py compares both). ``plan_raster`` uses it (2D and 3D)."""

    def __init__(self, n: int, mapped: bool = False):
        t0 = time.perf_counter()
        self.n, self.mapped = n, mapped
        if mapped:
            self._build_mapped(n)
            self.build_s = time.perf_counter() - t0
            return
        fk = kin.fk_function()
        w = ca.SX.sym("w", 12 * n)               # [qa_0, qi_0, qa_1, qi_1, ...]
        n_in = ca.SX.sym("n_in", 3)
        T_tcp = ca.reshape(ca.SX.sym("T_tcp", 16), 4, 4)
        q_ref = ca.SX.sym("q_ref", 12 * n)
        p = ca.vertcat(n_in, ca.vec(T_tcp), q_ref)
        J = W_REG * ca.sumsqr(w - q_ref)
        g = []
        for k in range(n):
            qa, qi = w[12 * k:12 * k + 6], w[12 * k + 6:12 * k + 12]
            gk, jk = _waypoint_terms(fk, qa, qi, n_in, T_tcp)
            g += gk
            J += jk
            if k + 1 < n:
                J += ca.sumsqr(w[12 * (k + 1):12 * (k + 1) + 6] - qa)
        self.solver = ca.nlpsol(f"raster{n}", "ipopt", {"x": w, "p": p, "f": J, "g": ca.vertcat(*g)}, IPOPT_OPTIONS)
        self.build_s = time.perf_counter() - t0

    def _build_mapped(self, n: int) -> None:
        """The same variables, parameters, constraints (in the same order) and objective, built from one waypoint's
        SX Functions mapped over all n: its constraints and cost, their 15 x 12 Jacobian and the 12 x 12 Hessian of
        its Lagrangian, handed to IPOPT as block-diagonal matrices (``jac_g``, ``hess_lag``: CasADi's own derivative
        of a map is several times slower to evaluate), plus the objective's constant quadratic part (the pull to the
        seed and the moves between neighbours)."""
        qa, qi = ca.SX.sym("qa", 6), ca.SX.sym("qi", 6)
        n_in, t_tcp = ca.SX.sym("n_in", 3), ca.SX.sym("T_tcp", 16)
        gk, jk = _waypoint_terms(kin.fk_function(), qa, qi, n_in, ca.reshape(t_tcp, 4, 4))
        g = ca.vertcat(*gk)
        qq, ng = ca.vertcat(qa, qi), g.numel()
        sigma, lam = ca.SX.sym("sigma"), ca.SX.sym("lam", ng)
        one = ca.Function("waypoint", [qa, qi, n_in, t_tcp], [g, jk])
        one_jac = ca.Function("waypoint_jac", [qa, qi, n_in, t_tcp], [ca.jacobian(g, qq)])
        one_hess = ca.Function("waypoint_hess", [qa, qi, n_in, t_tcp, sigma, lam],
                               [ca.hessian(sigma * jk + ca.dot(lam, g), qq)[0]])

        w = ca.MX.sym("w", 12 * n)
        n_in_m, t_tcp_m, q_ref = ca.MX.sym("n_in", 3), ca.MX.sym("T_tcp", 16), ca.MX.sym("q_ref", 12 * n)
        lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", ng * n)
        W = ca.reshape(w, 12, n)                  # column k = [qa_k, qi_k]
        args = (W[:6, :], W[6:, :], n_in_m, t_tcp_m)
        G, Jk = one.map(n, "serial")(*args)
        J = W_REG * ca.sumsqr(w - q_ref) + ca.sum2(Jk)
        if n > 1:
            J += ca.sumsqr(W[:6, 1:] - W[:6, :-1])
        p = ca.vertcat(n_in_m, t_tcp_m, q_ref)
        jac = ca.diagcat(*ca.horzsplit(one_jac.map(n, "serial")(*args), 12))
        hess = ca.diagcat(*ca.horzsplit(one_hess.map(n, "serial")(*args, lam_f, ca.reshape(lam_g, ng, n)), 12))
        # Hessian of the constant quadratic part: 2 W_REG I + 2 D'D, D the differences qa_{k+1} - qa_k
        diag = np.full(12 * n, 2 * W_REG)
        qa_idx = (12 * np.arange(n)[:, None] + np.arange(6)[None, :])          # (n, 6) entries of the qa_k
        diag[qa_idx] += 2.0 * ((np.arange(n) > 0).astype(float) + (np.arange(n) + 1 < n))[:, None]
        a = qa_idx[:-1].ravel()
        rows = np.concatenate([np.arange(12 * n), a, a + 12]).tolist()       # each entry once (no duplicates)
        cols = np.concatenate([np.arange(12 * n), a + 12, a]).tolist()
        vals = np.concatenate([diag, np.full(2 * len(a), -2.0)])
        quad = ca.DM.triplet(rows, cols, ca.DM(vals), 12 * n, 12 * n)
        opts = dict(IPOPT_OPTIONS)
        opts["jac_g"] = ca.Function("nlp_jac_g", [w, p], [ca.vec(G), jac], ["x", "p"], ["g", "jac_g_x"])
        opts["hess_lag"] = ca.Function("nlp_hess_l", [w, p, lam_f, lam_g], [ca.triu(lam_f * quad + hess)],
                                       ["x", "p", "lam_f", "lam_g"], ["triu_hess_gamma_x_x"])
        self.solver = ca.nlpsol(f"raster{n}m", "ipopt", {"x": w, "p": p, "f": J, "g": ca.vec(G)}, opts)

    def solve(self, q_seed: np.ndarray, tg: Targets, tcp_offset, branch, margins: Margins,
              tilt_tol_rad: float) -> tuple[np.ndarray, dict]:
        """q_seed: (n, 2, 6) [approach, indent]. Returns the optimal (n, 2, 6) and solver statistics."""
        n = self.n
        x0 = np.asarray(q_seed, dtype=float).reshape(-1)
        p = np.concatenate([tg.normal_in, ur5e.pose_to_T(tcp_offset).reshape(-1, order="F"), x0])
        lo, hi = [], []
        c = math.cos(tilt_tol_rad * (1 - 1e-4))  # a hair inside: the cosine is flat near 0, IPOPT's 1e-10 is ~1e-8 rad
        s = np.asarray(branch, dtype=float)
        m = margins.as_array()
        b_lo = np.where(s > 0, m, -np.inf)
        b_hi = np.where(s > 0, np.inf, -m)
        for k in range(n):
            lo += [*tg.approach_m[k], *tg.indent_m[k], c, c, c, *b_lo, *b_lo]
            hi += [*tg.approach_m[k], *tg.indent_m[k], np.inf, np.inf, np.inf, *b_hi, *b_hi]
        lbx = np.tile(ur5e.JOINT_LOWER_RAD, 2 * n)
        ubx = np.tile(ur5e.JOINT_UPPER_RAD, 2 * n)
        t0 = time.perf_counter()
        r = interruptible(lambda: self.solver(x0=x0, p=p, lbx=lbx, ubx=ubx, lbg=np.array(lo), ubg=np.array(hi)))
        dt = time.perf_counter() - t0
        st = self.solver.stats()
        info = {"status": st.get("return_status"), "success": bool(st.get("success")),
                "iterations": int(st.get("iter_count", -1)), "solve_s": dt, "objective": float(r["f"])}
        return np.array(r["x"]).reshape(n, 2, 6), info


_CACHE: dict[tuple[int, bool], RasterNLP] = {}


def nlp_for(n: int, mapped: bool = False) -> RasterNLP:
    """The solver for ``n`` waypoints, built on first use (see ``build_s``) and cached for the process."""
    if (n, mapped) not in _CACHE:
        _CACHE[n, mapped] = RasterNLP(n, mapped)
    return _CACHE[n, mapped]


# ---------------------------------------------------------------------------------------------------------------
# seeding from the closed form

def tool_rotation(normal_in, tissue_x, yaw_rad: float) -> np.ndarray:
    """Tool orientation with z along the inward normal and x at ``yaw`` from the raster direction."""
    z = np.asarray(normal_in, dtype=float)
    x0 = np.asarray(tissue_x, dtype=float)
    x0 = x0 - z * np.dot(x0, z)
    x0 /= np.linalg.norm(x0)
    y0 = np.cross(z, x0)
    x = math.cos(yaw_rad) * x0 + math.sin(yaw_rad) * y0
    return np.column_stack([x, np.cross(z, x), z])


def _describe_branch_failure(k: int, which: str, point, branch, tcp_offset, normal_in) -> str:
    p = np.round(np.asarray(point), 4).tolist()
    T = np.eye(4)
    T[:3, 3] = point
    n_any = 0
    helper = [1.0, 0, 0] if abs(normal_in[0]) < 0.9 else [0, 1.0, 0]
    for yaw in np.linspace(0, 2 * math.pi, 12, endpoint=False):
        T[:3, :3] = tool_rotation(normal_in, helper, yaw)
        n_any += len(ur5e.ik_all(T, tcp_offset))
    dist = float(np.linalg.norm(np.asarray(point)[:2]))
    if n_any == 0:
        far = float(np.linalg.norm(np.asarray(point) - [0.0, 0.0, ur5e.D1])) > 0.45
        fix = ("move the tissue closer to the base (--tissue-pose), shorten the TCP offset (--tcp-offset), or narrow "
               "the raster (--margin-m / --x-min-m / --x-max-m)") if far else (
               "move the tissue farther from the base (--tissue-pose)")
        why = f"too far; reach about {ur5e.REACH_M:g} m" if far else "too close to the base"
        return (f"waypoint {k} ({which} tip at {p} m in the base frame, {dist:.3f} m from the base axis) is out of "
                f"reach of the UR5e ({why}) with the tool along the surface normal: {fix}")
    return (f"waypoint {k} ({which} tip at {p} m) has no inverse-kinematics solution on the branch "
            f"(shoulder, elbow, wrist) = {tuple(branch)} with the tool along the surface normal: change --branch or "
            f"move the tissue (--tissue-pose)")


def seed_configurations(tg: Targets, tissue_x, tcp_offset, branch=ur5e.DEFAULT_BRANCH,
                        yaws=np.linspace(-math.pi, math.pi, 24, endpoint=False)) -> tuple[np.ndarray, float]:
    """Closed-form IK (vectorized) for every target with the tool exactly along the normal, all on ``branch``, each
    unwrapped next to its neighbour (continued outwards from the middle waypoint). The yaw about the tool axis is the
    one (from ``yaws``) whose middle-waypoint solution is nearest the UR home pose. Returns ((n, 2, 6), yaw)."""
    n = len(tg.approach_m)
    mid = n // 2
    Tinv = ur5e.rigid_inv(ur5e.pose_to_T(tcp_offset))
    T = np.zeros((len(yaws), 4, 4))
    T[:, 3, 3] = 1.0
    T[:, :3, :3] = [tool_rotation(tg.normal_in, tissue_x, y) for y in yaws]
    T[:, :3, 3] = tg.approach_m[mid]
    Qy = ur5e.ik_branch_batch(T @ Tinv, branch)
    cost = [np.sum((ur5e.unwrap_near(q, ur5e.Q_HOME)[1:] - ur5e.Q_HOME[1:]) ** 2) if np.all(np.isfinite(q))
            else np.inf for q in Qy]
    b = int(np.argmin(cost))
    if not np.isfinite(cost[b]):
        raise PlanError(_describe_branch_failure(mid, "approach", tg.approach_m[mid], branch, tcp_offset,
                                                     tg.normal_in))
    yaw = float(yaws[b])
    T = np.zeros((n, 2, 4, 4))
    T[..., 3, 3] = 1.0
    T[..., :3, :3] = tool_rotation(tg.normal_in, tissue_x, yaw)
    T[:, 0, :3, 3], T[:, 1, :3, 3] = tg.approach_m, tg.indent_m
    Q = ur5e.ik_branch_batch((T @ Tinv).reshape(-1, 4, 4), branch).reshape(n, 2, 6)
    for k in range(n):
        for j, which in enumerate(("approach", "indent")):
            if not np.all(np.isfinite(Q[k, j])):
                pts = tg.approach_m if j == 0 else tg.indent_m
                raise PlanError(_describe_branch_failure(k, which, pts[k], branch, tcp_offset, tg.normal_in))
    Q[mid, 0] = ur5e.unwrap_near(Q[mid, 0], ur5e.unwrap_near(Qy[b], ur5e.Q_HOME))
    for k in list(range(mid + 1, n)) + list(range(mid - 1, -1, -1)):
        Q[k, 0] = ur5e.unwrap_near(Q[k, 0], Q[k - 1, 0] if k > mid else Q[k + 1, 0])
    for k in range(n):
        Q[k, 1] = ur5e.unwrap_near(Q[k, 1], Q[k, 0])
    return Q, yaw


# ---------------------------------------------------------------------------------------------------------------
# checks

@dataclass
class Check:
    pos_err_m: float
    tilt_rad: float
    branch_ok: bool
    margins_ok: bool
    limits_ok: bool
    worst_margin: dict = field(default_factory=dict)

    def ok(self, tilt_tol_rad: float) -> bool:
        return (self.pos_err_m <= POS_TOL_M and self.tilt_rad <= tilt_tol_rad + 1e-9 and self.branch_ok
                and self.margins_ok and self.limits_ok)


def check_configurations(Q: np.ndarray, tg: Targets, tcp_offset, branch, margins: Margins) -> Check:
    """Independent (numpy) verification of a solution."""
    q = Q.reshape(-1, 6)
    T, pw = kin.fk_batch(q, tcp_offset)
    target = np.stack([tg.approach_m, tg.indent_m], axis=1).reshape(-1, 3)
    pos_err = float(np.max(np.linalg.norm(T[:, :3, 3] - target, axis=1)))
    tilt = float(np.max(np.arccos(np.clip(T[:, :3, 2] @ tg.normal_in, -1.0, 1.0))))
    ind = np.column_stack([-(pw[:, 0] * np.cos(q[:, 0]) + pw[:, 1] * np.sin(q[:, 0])), np.sin(q[:, 2]),
                           np.sin(q[:, 4])]) * np.asarray(branch, dtype=float)
    worst = ind.min(axis=0)
    b_ok = bool(np.all(ind > 0))
    m_ok = bool(np.all(ind >= margins.as_array() - 1e-9))
    lim = bool(np.all(Q >= ur5e.JOINT_LOWER_RAD - 1e-9) and np.all(Q <= ur5e.JOINT_UPPER_RAD + 1e-9))
    return Check(pos_err, tilt, b_ok, m_ok, lim, dict(zip(("shoulder_m", "elbow", "wrist"), worst.tolist())))


def margin_failure_message(chk: Check, margins: Margins) -> str:
    parts = []
    w = chk.worst_margin
    if w["shoulder_m"] < margins.shoulder_m:
        parts.append(f"the wrist passes within {w['shoulder_m']:.3f} m of the shoulder singularity (margin "
                     f"{margins.shoulder_m} m): move the tissue farther from the base axis")
    if w["elbow"] < margins.elbow:
        parts.append(f"the elbow is nearly stretched or folded (|sin q3| = {w['elbow']:.3f} < {margins.elbow}): "
                     f"move the tissue closer to (stretched) or farther from (folded) the base, or change its height")
    if w["wrist"] < margins.wrist:
        parts.append(f"the wrist is near its singularity (|sin q5| = {w['wrist']:.3f} < {margins.wrist}): "
                     f"change the tissue pose's orientation (--tissue-pose)")
    return "; ".join(parts) or "constraints violated"


def solve_raster(tg: Targets, tissue_x, tcp_offset, *, branch=ur5e.DEFAULT_BRANCH, margins: Margins | None = None,
                 tilt_tol_rad: float = math.radians(0.5), mapped: bool = False) -> tuple[np.ndarray, dict]:
    """Seed from the closed form, then solve the NLP (``mapped``: see RasterNLP). Returns ((n, 2, 6) joints, info).
    Raises PlanError."""
    margins = margins or Margins()
    t0 = time.perf_counter()
    Q0, yaw = seed_configurations(tg, tissue_x, tcp_offset, branch)
    seed_s = time.perf_counter() - t0
    chk0 = check_configurations(Q0, tg, tcp_offset, branch, margins)
    if not chk0.margins_ok:
        raise PlanError("the raster cannot keep the singularity margins: " + margin_failure_message(chk0, margins))
    t0 = time.perf_counter()
    cached = (len(Q0), mapped) in _CACHE
    nlp = nlp_for(len(Q0), mapped)
    get_s = time.perf_counter() - t0
    Q, info = nlp.solve(Q0, tg, tcp_offset, branch, margins, tilt_tol_rad)
    chk = check_configurations(Q, tg, tcp_offset, branch, margins)
    info.update(seed_s=seed_s, build_s=nlp.build_s, seed_yaw_rad=yaw, used="nlp")
    if mapped:
        info.update(nlp="mapped", built_now=not cached, build_now_s=get_s)
    if not chk.ok(tilt_tol_rad):
        # the seed is feasible by construction (exact alignment, margins checked): never hand out a broken plan
        info["used"] = "seed"
        info["nlp_check"] = chk.__dict__
        Q, chk = Q0, chk0
    info["check"] = chk.__dict__
    info["travel_rad"] = float(np.sum(np.abs(np.diff(Q[:, 0], axis=0))) + 2 * np.sum(np.abs(Q[:, 1] - Q[:, 0])))
    info["travel_seed_rad"] = float(np.sum(np.abs(np.diff(Q0[:, 0], axis=0))) + 2 * np.sum(np.abs(Q0[:, 1] - Q0[:, 0])))
    return Q, info


# ---------------------------------------------------------------------------------------------------------------
# the whole plan

def _prior(scene):
    scene = load(scene)
    return scene if (not scene.stones and scene.name.endswith("-prior")) else scene.prior()


def default_force_model(prior):
    """fem's condensed surface model of the prior scene (built once per scene by fem, ~1 s; its answers remembered
    between runs: fem.recall). Built (or restored) here, so its errors come before any depth is asked."""
    surface_model(prior)
    return functools.partial(recall.force_n, prior)


MIN_NORMAL_UP = 0.5     # the tissue's outward normal within 60 deg of the base's +z: tissue lying on a table


def plan_raster(scene, *, n_waypoints: int | None = None, spacing_m: float | None = None,
                margin_m: float | None = None, x_positions_m=None, depth_m=None, force_n=None, limits=None,
                motion=None, frames=None, options: PlanOptions | None = None, margins: Margins | None = None,
                joint_limits=None, positions_m=None, grid: tuple[int, int] | None = None, region=None, polygon=None):
    """Plan a probing raster over the top surface of ``scene``'s prior (its stones are dropped before anything else).

    2D section: waypoints ``x_positions_m`` (tissue-frame x, e.g. a finer set over an interval for adaptive
    refinement: see ``raster.interval_positions``), else ``n_waypoints`` or ``spacing_m`` with ``margin_m`` (default
    0.005 m) from the edges (default 15 waypoints).
    3D block (``tissue.length_m`` set): waypoints ``positions_m`` ((N, 2) tissue-frame (x, y), probed in that order),
    else a grid (``grid`` = (nx, ny), default 7 x 7, or ``spacing_m``) over ``region`` ((x0, y0, x1, y1)) or
    ``polygon`` ((K, 2) vertices) or, by default, fem's probed patch minus ``margin_m`` (default: the tip radius), in
    serpentine order (planner.area). Every position's tip footprint must lie on fem's probed patch.
    Depths: ``depth_m`` (a number or one per waypoint) if given, else chosen per waypoint from ``force_n(x_m,
    depth_m)`` (3D: ``force_n(x_m, y_m, depth_m)``; default: fem's surface model of the prior, in 3D solved exactly
    and fast by planner.depth3d) as the deepest probe whose predicted force stays within ``force_fraction *
    limits.force_limit_n`` and ``limits.depth_limit_m``.
    ``options`` (core.contracts.PlanOptions): IK branch, tilt tolerance, force fraction, minimum depth.
    Frames default to the tissue lying on the arm's table 0.40 m in front of the base (raster.default_tissue_pose,
    area.default_block_pose: the block's middle there). Returns a core.contracts.Plan; raises PlanError with a
    message naming what to change."""

    t_all = time.perf_counter()
    prior = _prior(scene)
    tis = prior.tissue
    limits = limits or Limits()
    motion = motion or Motion()
    options = options or PlanOptions()
    branch, tilt_tol_rad = tuple(options.branch), options.tilt_tol_rad
    force_fraction, min_depth_m = options.force_fraction, options.min_depth_m
    if prior.is_3d:
        default_pose = area.default_block_pose(tis.width_m, tis.length_m, tis.height_m)
    else:
        default_pose = default_tissue_pose(tis.width_m, tis.height_m)
    frames = frames or Frames(tissue_pose_base=default_pose)
    normal = ur5e.pose_to_T(frames.tissue_pose_base)[:3, 2]
    if normal[2] < MIN_NORMAL_UP:
        raise PlanError(f"--tissue-pose {list(frames.tissue_pose_base)}: the tissue's surface normal points "
                        f"{np.round(normal, 3).tolist()} in the base frame; it must face up (its base z component "
                        f">= {MIN_NORMAL_UP:g}, i.e. tilted at most {np.degrees(np.arccos(MIN_NORMAL_UP)):.0f} deg): "
                        f"check the rotation part of the pose")
    for name, v in (("approach_speed_m_s", motion.approach_speed_m_s), ("probe_speed_m_s", motion.probe_speed_m_s)):
        if not (0 < v <= limits.max_tool_speed_m_s):
            raise PlanError(f"motion.{name} = {v} m/s must lie in (0, limits.max_tool_speed_m_s = "
                                f"{limits.max_tool_speed_m_s}]")
    raster_notes = None
    if prior.is_3d:
        for name, v in (("x_positions_m", x_positions_m), ("n_waypoints (--waypoints)", n_waypoints)):
            if v is not None:
                raise PlanError(f"{name} is for a 2D section; scene {prior.name!r} is a 3D block: give positions_m "
                                f"((N, 2) x, y), a grid (--grid NXxNY) or a spacing (--spacing-m)")
        if positions_m is not None:
            if grid is not None or spacing_m is not None or region is not None or polygon is not None:
                raise PlanError("give either positions_m or a grid/spacing over a region, not both")
            P = area.check_positions(prior, positions_m, option="positions_m")
        else:
            if region is not None and polygon is not None:
                raise PlanError("give either --region or --polygon, not both")
            reg = (area.Region.rectangle(*region) if region is not None else
                   area.Region.polygon(polygon) if polygon is not None else None)
            if grid is None and spacing_m is None:
                grid = DEFAULT_GRID
            ar = area.area_raster(prior, region=reg, grid=grid, spacing_m=spacing_m, margin_m=margin_m)
            P, raster_notes = ar.positions_m, ar.to_dict()
        x, y = P[:, 0].copy(), P[:, 1].copy()
        where = P
    else:
        for name, v in (("positions_m", positions_m), ("grid (--grid)", grid), ("region (--region)", region),
                        ("polygon (--polygon)", polygon)):
            if v is not None:
                raise PlanError(f"{name} is for a 3D block; scene {prior.name!r} is a 2D section (no "
                                f"tissue.length_m): give x positions, --waypoints or --spacing-m")
        if x_positions_m is not None:
            x = np.asarray(x_positions_m, dtype=float).reshape(-1)
            if x.size == 0 or np.any(x < 0) or np.any(x > tis.width_m):
                raise PlanError(f"x positions must be non-empty and lie on the surface [0, {tis.width_m}] m")
        else:
            if n_waypoints is None and spacing_m is None:
                n_waypoints = 15
            x = raster_positions(tis.width_m, n=n_waypoints, spacing_m=spacing_m,
                                 margin_m=0.005 if margin_m is None else margin_m)
        y, where = None, x

    tissue_x = ur5e.pose_to_T(frames.tissue_pose_base)[:3, 0]
    depth_for = None
    if force_n is None:
        deepest = STRAIN_MAX * prior.tissue.height_m
        if depth_m is None and limits.depth_limit_m > deepest:      # fem would refuse the depths the search tries
            raise PlanError(f"--depth-limit-m {limits.depth_limit_m:g} is {limits.depth_limit_m / prior.tissue.height_m:.0%} "
                            f"of the tissue's height {prior.tissue.height_m:g} m: fem's linear model covers "
                            f"indentations up to {STRAIN_MAX:.0%} of it; give --depth-limit-m <= "
                            f"{math.floor(deepest * 1e6) / 1e6:g} m")
        # fail fast, before fem builds its model (~1-5 s): every waypoint reachable down to the depth limit
        seed_configurations(targets(x, np.full(x.shape, limits.depth_limit_m), frames.tissue_pose_base,
                                    motion.approach_height_m, y_m=y), tissue_x, frames.tcp_offset, branch)
        if prior.is_3d:             # the 3D model's code (fem.contact3d: 25 ms of imports) for a block only
            from fem.contact3d import surface_model3d
            from planner.depth3d import ContactDepths3D
            solver = ContactDepths3D(surface_model3d(prior))
            force_n, depth_for = solver.force_n, solver.depth_for
        else:
            force_n = default_force_model(prior)

    t0 = time.perf_counter()
    if depth_m is not None:
        d = np.broadcast_to(np.asarray(depth_m, dtype=float), x.shape).copy()
        if np.any(d <= 0) or np.any(d > limits.depth_limit_m):
            raise PlanError(f"depths must lie in (0, --depth-limit-m = {limits.depth_limit_m}] m")
        if y is None:
            f = np.array([force_n(float(a), float(b)) for a, b in zip(x, d)])
        else:
            f = np.array([force_n(float(a), float(c), float(b)) for a, c, b in zip(x, y, d)])
        if f.max() > limits.force_limit_n:
            raise PlanError(f"the fixed depth gives a predicted force of {f.max():.3g} N, above the force "
                                f"limit {limits.force_limit_n} N: lower --depth-m or raise --force-limit-n")
        limited_by, target_n = ["fixed"] * len(x), None
    else:
        dc = choose_depths(force_n, where, force_limit_n=limits.force_limit_n, depth_limit_m=limits.depth_limit_m,
                           force_fraction=force_fraction, min_depth_m=min_depth_m, depth_for=depth_for)
        d, f, limited_by, target_n = dc.depth_m, dc.force_n, dc.limited_by, dc.target_force_n

    # over the chord the driver's surface fit sees: from SURFACE_FIT_FROM_FRACTION of the threshold on
    expo = force_exponents(force_n, where, d, f, SURFACE_FIT_FROM_FRACTION * motion.contact_threshold_n, depth_for)
    depth_s = time.perf_counter() - t0

    tg = targets(x, d, frames.tissue_pose_base, motion.approach_height_m, y_m=y)
    lo, hi = np.asarray(limits.workspace_min_m), np.asarray(limits.workspace_max_m)
    for k, pts in enumerate(zip(tg.approach_m, tg.indent_m)):
        for p in pts:
            if np.any(p < lo) or np.any(p > hi):
                raise PlanError(f"waypoint {k} (tip at {np.round(p, 4).tolist()} m) leaves the workspace box "
                                    f"{lo.tolist()}..{hi.tolist()} m (limits.workspace_min_m/max_m): move the tissue "
                                    f"(--tissue-pose)")
    Q, info = solve_raster(tg, tissue_x, frames.tcp_offset, branch=branch, margins=margins,
                           tilt_tol_rad=tilt_tol_rad, mapped=True)     # (the one-graph NLP: a reference)
    t_timing = time.perf_counter()
    tm = raster_timing(tg.approach_m, tg.indent_m, Q[:, 0], Q[:, 1], motion, joint_limits,
                       tool_speed_m_s=limits.max_tool_speed_m_s)
    probes, prev = [], None
    T_all = kin.fk_batch(Q.reshape(-1, 6), frames.tcp_offset)[0].reshape(len(x), 2, 4, 4)
    for k in range(len(x)):
        pa = ur5e.T_to_pose(T_all[k, 0], near=prev)
        pi = ur5e.T_to_pose(T_all[k, 1], near=pa)
        prev = pa
        extra = {} if y is None else {"y_m": float(y[k])}
        probes.append(Probe(index=k, x_m=float(x[k]), depth_m=float(d[k]), predicted_force_n=float(f[k]),
                            force_exponent=expo[k], approach_pose=pa, indent_pose=pi,
                            q_approach_rad=Q[k, 0].tolist(), q_indent_rad=Q[k, 1].tolist(),
                            t_start_s=tm.t_start_s[k], duration_s=tm.duration_s[k], **extra))
    notes = {"planner": "casadi-ipopt raster v1", "target_force_n": target_n, "depth_limited_by": limited_by, "solver": info, "timing": tm.to_dict(),
             "times_s": {"depth_choice": depth_s, "seed": info["seed_s"], "solve": info["solve_s"],
                         "build_once": info["build_s"], "total": time.perf_counter() - t_all}}
    if prior.is_3d:
        notes["times_s"].update(nlp_build_now=info["build_now_s"], timing_poses=time.perf_counter() - t_timing)
        notes["raster"] = raster_notes or {"positions": "given (positions_m)", "n": len(x),
                                           "travel_m": area.travel_m(where)}
        if depth_for is not None:
            notes["depth_method"] = {"method": "parametric LCP on fem's condensed patch compliance (exact forces)",
                                     "lcp_solves": solver.n_lcp}
    plan = Plan(scene=prior.to_dict(), frames=frames, limits=limits, motion=motion, options=options, probes=probes,
                total_time_s=tm.total_s, notes=notes)
    plan.check()
    if prior.is_3d:
        notes["times_s"]["total"] = time.perf_counter() - t_all
    return plan


def plan_prior(plan: Plan):
    """The prior scene a plan was made on (fem.scene.Scene), parsed from the plan's plain-data copy."""
    return from_dict(plan.scene, default_name=plan.scene.get("name", "prior"))


def replan(plan, x_positions_m, *, force_n=None, **overrides):
    """A new plan over new positions with everything else taken from ``plan``: its prior scene, frames, limits,
    motion and options. A 2D plan takes (N,) tissue-frame x (e.g. ``raster.interval_positions(lo, hi, n=11)`` around a
    suspected stone); a 3D plan (N, 2) tissue-frame (x, y), probed in the order given (what adaptive refinement
    over an area calls). ``overrides`` go to ``plan_raster``."""
    prior = plan_prior(plan)
    kw = dict(frames=plan.frames, limits=plan.limits, motion=plan.motion, options=plan.options)
    kw.update(overrides)
    if prior.is_3d:
        P = np.asarray(x_positions_m, dtype=float)
        if P.ndim != 2 or P.shape[1:] != (2,):
            raise PlanError(f"a 3D plan (scene {prior.name!r}) is re-planned over (N, 2) tissue-frame (x, y) "
                            f"positions, got an array of shape {P.shape}")
        return plan_raster(prior, positions_m=P, force_n=force_n, **kw)
    if np.ndim(x_positions_m) > 1 and np.shape(x_positions_m)[1:] != (1,):
        raise PlanError(f"a 2D plan (scene {prior.name!r}) is re-planned over (N,) tissue-frame x positions, got an "
                        f"array of shape {np.shape(x_positions_m)}")
    return plan_raster(prior, x_positions_m=x_positions_m, force_n=force_n, **kw)
