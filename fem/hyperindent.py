"""Finite-strain indentation: a rigid cylindrical (or flat) tip pressed vertically into a neo-Hookean tissue
(fem.finite_strain), frictionless contact, Newton's method with the consistent tangent, load-stepped in depth.

Load case B as in fem.contact (bottom edge u_y = 0, sides and top free; the horizontal rigid mode removed by the
bottom's mean horizontal displacement, see ``supports``) but with the exact geometry: the tip is the circle of
radius R centred at (x0, H + R - depth) in the deformed configuration, and a top node's gap is its distance from
that circle, g = |x - c| - R, in its *current* position x = X + u (it may slide along the tip). The contact force
on a node acts along the circle's normal n = (x - c) / |x - c|.

One Newton step is a linear complementarity problem over the top nodes near the tip (fem.lcp, exact): with the
consistent tangent K~ = K_T - sum_a p_a t_a t_a^T / |x_a - c| (t_a the tangent: the contact normal's rotation,
rank one per node, applied by Woodbury's identity on a Cholesky factorization of the material tangent K_T),
z = -K~^-1 f_int and Y = K~^-1 G (G: the normals as columns),

    w = (g + G^T z) + (G^T Y) p,   p >= 0, w >= 0, p . w = 0,       du = z + Y p.

Near the solution the contact set no longer changes and this is Newton's step on the equality-constrained problem:
convergence is quadratic (tests print the residual history). Near a side at depth the consistent step's LCP can be
ill-posed (the tissue rolling around the frictionless tip nears an instability); that step uses K_T alone.
``sweep`` follows one tip position down through increasing depths (continuation: each step starts from the
previous solution extrapolated), halving a step that does not converge, and returns the force at every depth.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .condense import Cholesky, available
from .finite_strain import FiniteStrainModel
from .lcp import solve_lcp
from .model import Model, build_model
from .tip import tip_too_soft

MAX_NEWTON = 25
MIN_STEP_FRACTION = 1.0 / 64     # a load step is halved at most 6 times
RESIDUAL_TOL = 1e-7              # equilibrium: |f_int - G p| below this times the contact forces' norm...
FORCE_FLOOR = 1e-6               # ... or, before any contact, times this fraction of E R (N/m)
GAP_TOL_FACTOR = 1e-8            # |gap| of a contact node below this times R
CANDIDATE_GAP_FACTOR = 0.02      # nodes within this times R of the tip enter a step's LCP (others when they touch)


def supports(model: Model):
    """Load B's supports for the exact contact, as a map from the unknowns v to the reduced DOFs: a = T v.

    The bottom edge has u_y = 0 as in fem.contact; the horizontal rigid-body mode is removed by a zero *mean*
    horizontal displacement of the bottom edge (weights: each bottom node's share of its length), not by the
    linear model's pin at the bottom-left corner. In the linear model the pin carries no force (every contact force
    is vertical), so either choice gives the same answer there; the exact contact's forces follow the tip's normal
    and have a horizontal resultant under an asymmetric contact (beside a stone, near a side), which a point pin
    carries with a local, mesh-dependent deformation while the block slides on its frictionless bottom: pinned at
    the left corner, the paper section's finite-strain correction at 4 mm was 3 % larger at x = 45 mm than at its
    mirror image x = 25 mm and 4.4 % at 65 against 5 mm. The mean condition spreads that reaction over the bottom
    as a uniform shear; mirror images then agree (tests). Returns (T (n_red x n_v) sparse, the reduced DOFs that
    are unknowns in order, the dependent DOF)."""
    import scipy.sparse as sp
    mesh = model.mesh
    bot = mesh.bottom
    xb = mesh.nodes[bot, 0]
    w = np.gradient(xb) if len(xb) > 1 else np.ones(1)            # each node's share of the bottom's length
    k = int(np.argmin(np.abs(xb - 0.5 * mesh.width_m)))
    bx = model.reduced_index(2 * bot)
    fixed = model.reduced_index(2 * bot + 1)
    dep = int(bx[k])
    unknown = np.setdiff1d(np.arange(model.n_dofs), np.concatenate([fixed, [dep]]))
    pos = np.full(model.n_dofs, -1)
    pos[unknown] = np.arange(len(unknown))
    others = np.arange(len(bot)) != k
    rows = np.concatenate([unknown, np.full(int(others.sum()), dep)])
    cols = np.concatenate([np.arange(len(unknown)), pos[bx[others]]])
    vals = np.concatenate([np.ones(len(unknown)), -w[others] / w[k]])
    T = sp.csr_matrix((vals, (rows, cols)), shape=(model.n_dofs, len(unknown)))
    return T, unknown, dep


class NotConverged(RuntimeError):
    """Newton's method did not converge at a depth even with the smallest load step."""


@dataclass
class HyperSweep:
    """A tip position's force against depth (the finite-strain truth's F(d) curve)."""
    x_m: float
    depth_m: np.ndarray             # increasing depths reached
    force_n_per_m: np.ndarray       # tip force per unit out-of-plane length at each
    force_n: np.ndarray             # times the tip's thickness
    newton_iterations: np.ndarray   # per depth
    residuals: list = field(default_factory=list)   # per depth: the relative residual after each Newton iteration
    stopped: str = ""               # why the sweep ended before its last depth ("" when it did not)
    time_s: float = 0.0


class HyperIndenter:
    """A scene's finite-strain contact problem, set up once (mesh, pattern, boundary conditions) for many sweeps."""

    def __init__(self, scene, model: Model | None = None, residual_tol: float = RESIDUAL_TOL):
        self._order_kept = None           # (the tangent's sparsity pattern, its fill-reducing order)
        self._chol: Cholesky | None = None  # the last tangent's factor (its symbolic analysis reused)
        if tip_too_soft(scene):
            raise ValueError("the finite-strain truth models a rigid tip; this scene's tip is soft "
                             f"(E_tip = {scene.indenter.youngs_pa:g} Pa)")
        self.scene = scene
        self.model = model or build_model(scene)
        self.fs = FiniteStrainModel(self.model)
        mesh = self.model.mesh
        self.T, self.free, _ = supports(self.model)
        self.TT = self.T.T.tocsr()
        pos = np.full(self.model.n_dofs, -1)
        pos[self.free] = np.arange(len(self.free))
        self.top = mesh.top
        self.X_top = mesh.nodes[self.top]
        red = self.model.reduced_index(np.stack([2 * self.top, 2 * self.top + 1], axis=1).ravel()).reshape(-1, 2)
        self.top_free = pos[red]                       # (n_top, 2) positions among the unknowns
        self.R = scene.indenter.radius_m
        self.H = mesh.height_m
        self.thickness_m = scene.indenter.thickness_m
        self.force_scale = scene.tissue.youngs_pa * self.R
        self.residual_tol = residual_tol
        self.tangent_fallbacks = 0     # Newton steps that used the material tangent alone (see _newton_step)

    def __getstate__(self):
        """Pickled (a study's worker) without the kept factor: a CHOLMOD factor does not pickle; it is made again."""
        return {**self.__dict__, "_chol": None}

    # -- geometry -------------------------------------------------------------------------------------------------
    def _tip(self, x0: float, depth: float, xy: np.ndarray):
        """(gap, outward normal, distance to the centre) of current positions ``xy`` (k, 2) against the tip."""
        if self.scene.indenter.shape == "cylinder":
            c = np.array([x0, self.H + self.R - depth])
            v = xy - c
            r = np.hypot(v[:, 0], v[:, 1])
            return r - self.R, v / r[:, None], r
        n = np.tile([0.0, -1.0], (len(xy), 1))           # a flat punch of half-width R: a plane at H - depth
        return (self.H - depth) - xy[:, 1], n, np.full(len(xy), np.inf)      # < 0: the tissue is penetrated

    def _candidates(self, x0: float, depth: float, a: np.ndarray, p: dict[int, float]):
        """Top nodes that may touch (under the tip's span now, or carrying force): indices, gaps, normals, radii."""
        u = a[self.model.reduced_index(2 * self.top)], a[self.model.reduced_index(2 * self.top + 1)]
        xy = self.X_top + np.stack(u, axis=1)
        near = np.abs(xy[:, 0] - x0) < self.R
        near[list(p)] = True
        idx = np.flatnonzero(near)
        g, n, r = self._tip(x0, depth, xy[idx])
        keep = (g < CANDIDATE_GAP_FACTOR * self.R) | np.isin(idx, list(p))
        return idx[keep], g[keep], n[keep], r[keep]

    # -- one depth ------------------------------------------------------------------------------------------------
    def solve(self, x0: float, depth: float, a: np.ndarray, p: dict[int, float]):
        """Newton from ``a`` (reduced displacements) and contact forces ``p`` (node -> N/m) to equilibrium at
        ``depth``: (a, p, force_n_per_m, relative residuals). NotConverged or FloatingPointError (an element folded
        over) when it does not get there in MAX_NEWTON iterations."""
        a = a.copy()
        history = []
        for _ in range(MAX_NEWTON + 1):
            f, K = self.fs.assemble(a)
            idx, g, n, r = self._candidates(x0, depth, a, p)
            pv = np.array([p.get(int(i), 0.0) for i in idx])
            cols = self.top_free[idx]                                   # (k, 2)
            f = self.TT @ f
            res = f.copy()
            np.add.at(res, cols[:, 0], -pv * n[:, 0])
            np.add.at(res, cols[:, 1], -pv * n[:, 1])
            rel = float(np.linalg.norm(res)) / max(float(np.linalg.norm(pv)), FORCE_FLOOR * self.force_scale)
            history.append(rel)
            gtol = GAP_TOL_FACTOR * self.R
            settled = np.all(np.abs(g[pv > 0]) < gtol) and np.all(g[pv == 0] > -gtol)
            if len(history) > 1 and rel < self.residual_tol and settled:
                return a, p, float(np.sum(pv * -n[:, 1])), history
            if len(history) > MAX_NEWTON:
                break
            a, p = self._newton_step(K, f, x0, idx, g, n, r, pv, a)
        raise NotConverged(f"finite-strain contact at x_m={x0:.5g}, depth_m={depth:.4g}: Newton did not converge "
                           f"(relative residuals {', '.join(f'{h:.1e}' for h in history[-4:])})")

    def _factorize(self, Kt):
        """solve(rhs) for the material tangent: CHOLMOD, its symbolic analysis kept between Newton steps while the
        tangent's sparsity pattern stays the same (it does: one mesh; the ordering was a quarter of a sweep's time when
        made every step, the rest of the analysis a tenth of it after that) and the columns solved in one sweep; SuperLU
        when the tangent is not positive definite or CHOLMOD is not installed."""
        import scipy.sparse.linalg as spla
        if available():
            try:
                if self._chol is None or not self._chol.refactor(Kt):
                    self._chol = None
                    self._chol = Cholesky(Kt, self._order_for(Kt), reusable=True)
                return self._chol.solve_columns
            except ArithmeticError:
                self._chol = None
        return spla.splu(Kt.tocsc()).solve

    def _order_for(self, Kt):
        """The fill-reducing order, kept for the tangent's sparsity pattern (made again only if that changes)."""
        pattern = (Kt.shape, Kt.indptr, Kt.indices)
        kept = self._order_kept
        if kept is None or kept[0][0] != pattern[0] or not (np.array_equal(kept[0][1], pattern[1])
                                                            and np.array_equal(kept[0][2], pattern[2])):
            kept = ((Kt.shape, Kt.indptr.copy(), Kt.indices.copy()), Cholesky.order_for(Kt))
            self._order_kept = kept
        return kept[1]

    def _newton_step(self, K, f, x0, idx, g, n, r, pv, a):
        """One Newton step: the LCP above with the consistent tangent K~ = K_T - U D U^T (U: the tangents t_a of
        the nodes in contact, D = p_a / |x_a - c|; the normal's rotation is rank one per node), applied through
        Woodbury's identity on one Cholesky factorization of the material tangent K_T. If that step's LCP is not
        well posed (the condensed matrix indefinite: the tissue rolling around the frictionless tip comes close to
        an instability near a side at depth), the step is made with K_T alone, which converges linearly."""
        Kt = (self.TT @ K @ self.T).tocsc()
        cols = self.top_free[idx]
        k = len(idx)
        on = np.flatnonzero(pv > 0) if self.scene.indenter.shape == "cylinder" else np.zeros(0, int)
        B = np.zeros((len(self.free), 1 + k + len(on)))
        B[:, 0] = -f
        B[cols[:, 0], 1 + np.arange(k)] = n[:, 0]
        B[cols[:, 1], 1 + np.arange(k)] = n[:, 1]
        B[cols[on, 0], 1 + k + np.arange(len(on))] = -n[on, 1]            # tangents t = (-n_y, n_x)
        B[cols[on, 1], 1 + k + np.arange(len(on))] = n[on, 0]
        X = self._factorize(Kt)(B)
        z, Y, V = X[:, 0], X[:, 1:1 + k], X[:, 1 + k:]
        G = B[:, 1:1 + k]
        if len(on):
            U = B[:, 1 + k:]
            S = np.diag(r[on] / pv[on]) - U.T @ V                         # D^-1 - U^T K_T^-1 U
            try:
                W = V @ np.linalg.solve(S, U.T @ np.column_stack([z, Y]))
                return self._lcp_step(z + W[:, 0], Y + W[:, 1:], G, g, x0, idx, a)
            except (NotConverged, np.linalg.LinAlgError):
                self.tangent_fallbacks += 1
        return self._lcp_step(z, Y, G, g, x0, idx, a)

    def _lcp_step(self, z, Y, G, g, x0, idx, a):
        """The step du = z + Y p with p from the LCP w = (g + G^T z) + (G^T Y) p."""
        M = G.T @ Y
        q = g + G.T @ z
        pnew = np.zeros(len(idx))
        if np.any(q < 0):
            try:
                pnew = solve_lcp(0.5 * (M + M.T), q, start=q < 0).z
            except RuntimeError as e:
                raise NotConverged(f"finite-strain contact at x_m={x0:.5g}: {e}") from None
        da = z + Y @ pnew
        if not np.all(np.isfinite(da)):
            raise NotConverged(f"finite-strain contact at x_m={x0:.5g}: a singular tangent")
        return a + self.T @ da, {int(i): float(v) for i, v in zip(idx, pnew) if v > 0}

    # -- a whole F(d) curve -----------------------------------------------------------------------------------------
    def sweep(self, x_m: float, depths_m) -> HyperSweep:
        """The tip at ``x_m`` pressed through the increasing ``depths_m`` (continuation from each to the next; a
        step that fails is halved, down to MIN_STEP_FRACTION of it). The sweep stops early (``stopped`` says why)
        where the tissue folds over or Newton fails even with the smallest step; the depths reached are returned."""
        t0 = time.perf_counter()
        depths = np.asarray(depths_m, float)
        min_step = MIN_STEP_FRACTION * float(np.diff(np.concatenate([[0.0], depths])).min())
        a = a_prev = np.zeros(self.model.n_dofs)
        d_done = d_prev = 0.0
        p: dict[int, float] = {}
        out_d, out_f, out_it, out_res = [], [], [], []
        stopped = ""
        for target in depths:
            step = target - d_done
            while not stopped and d_done < target:
                step = min(step, target - d_done)
                d = target if step >= target - d_done else d_done + step
                guess = a + (a - a_prev) * ((d - d_done) / (d_done - d_prev)) if d_done > d_prev else a
                try:
                    a_new, p_new, force, hist = self.solve(x_m, d, guess, p)
                except (NotConverged, FloatingPointError) as e:
                    step *= 0.5
                    if step < min_step:
                        stopped = f"{type(e).__name__}: {e}"
                    continue
                a_prev, d_prev, a, p, d_done = a, d_done, a_new, p_new, d
            if stopped:
                break
            out_d.append(d_done)
            out_f.append(force)
            out_it.append(len(hist) - 1)
            out_res.append(hist)
        f = np.array(out_f)
        return HyperSweep(x_m=float(x_m), depth_m=np.array(out_d), force_n_per_m=f, force_n=f * self.thickness_m,
                          newton_iterations=np.array(out_it), residuals=out_res, stopped=stopped,
                          time_s=time.perf_counter() - t0)

