"""The prior tissue's force at each probe as a function of the probe's TRUE indentation and of the tissue's
thickness: what the localizer needs to fit the surface height and the thickness as nuisance parameters.

A registration error moves the true surface against the nominal one, so a probe planned ``d`` deep is really
``d + h(x)`` deep; a tissue thicker or thinner than the prior changes the force profile's *shape* (about 1.5 mN of
0.1 N between the middle and the ends for 10 %, after the best stiffness scale: a broad bump a stone could be
blamed for), where the Poisson ratio (0.35-0.49) changes it only by a scale (residual below 0.02 mN: measured with
fem on the paper tissue, 15 positions at 4 mm). So the response is tabulated with fem per probe position on a
geometric grid of indentations, for the prior and for the prior with its height scaled by ``1 -+ THICKNESS_STEP``,
and interpolated: linearly in (log depth, log force) (exact for a power law; extrapolated the same way beyond the
grid, where fem refuses: indentations at the tip radius), quadratically in the relative thickness change ``eta``.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from core.arrays import clip
from fem import recall
from fem.scene import STRAIN_MAX

THICKNESS_STEP = 0.10          # the thickness nodes: prior height x (1 - step, 1, 1 + step)
N_NODES = 32                   # indentation nodes, geometric from MIN_FRAC to MAX_FRAC of the tip radius
MIN_FRAC, MAX_FRAC = 0.06, 0.96

_ROWS: dict = {}               # (prior key, thickness node, round(x, 7)) -> log force row


def fem_deepest_m(prior, height_factor: float = 1.0) -> float:
    """The deepest indentation fem takes on ``prior`` with its height scaled by ``height_factor``: below the tip's
    radius and at most STRAIN_MAX of the height (fem.contact.check_depth)."""
    return min(prior.indenter.radius_m, STRAIN_MAX * height_factor * prior.tissue.height_m)


def thickness_mesh_m(prior) -> float:
    """The mesh size of the thickness nodes of ``prior`` (its tissue 1 -+ THICKNESS_STEP times as tall): the prior's
    own, capped at half the thinnest node's height (fem's rule: at least two elements through the tissue). A 40 x 40
    x 20 mm block takes the 3D default mesh size of 9.6 mm, its 18 mm node would not: fem refused it only after the
    run had built its 3D table for 9.7 min (session 51's review)."""
    return min(prior.analysis.mesh_size_m, (1.0 - THICKNESS_STEP) * prior.tissue.height_m / 2)


def scene_with_height(prior, factor: float):
    """``prior`` with its tissue ``factor`` times as tall, meshed at ``thickness_mesh_m(prior)``: the prior itself at
    factor 1 unless that caps its mesh."""
    mesh = thickness_mesh_m(prior)
    if factor == 1.0 and mesh == prior.analysis.mesh_size_m:
        return prior
    return dataclasses.replace(prior, tissue=dataclasses.replace(prior.tissue, height_m=prior.tissue.height_m * factor),
                               analysis=dataclasses.replace(prior.analysis, mesh_size_m=mesh))


def thickness_reference(prior):
    """None, or where ``thickness_mesh_m`` caps the mesh, the prior at its own height on the capped mesh: the
    thinner and thicker nodes' forces are then taken relative to it, F_k = F_prior F_k / F_reference (a ratio of two
    forces on one mesh), so the prior's own force stays the prior's (the truth a simulated run presses is meshed as
    the scene says) and the thickness slope holds no mesh change. Session 52: capping the thinner node's mesh alone
    moved its force by as much as the 10 % height change (a review: the thinner block came out softer than the
    prior, the slope 2.4 times too small); the three nodes on the capped mesh instead put the mesh change into the
    prior's own force, 1.4 % off the truth's, where a stone's contrast was 1 %: a run's stone came out 2.4-3.2
    sigma off."""
    ref = scene_with_height(prior, 1.0)
    return None if ref is prior else ref


class PriorResponse:
    """log F(x_i, d, eta) of the prior (stone-free) tissue at fixed probe positions ``x_m``."""

    def __init__(self, prior, x_m):
        R = prior.indenter.radius_m
        # up to the tip's radius, or on a thin tissue to the deepest indentation fem allows on its thinnest node
        top = min(MAX_FRAC * R, 0.99 * STRAIN_MAX * (1.0 - THICKNESS_STEP) * prior.tissue.height_m)
        self.logd = np.linspace(np.log(MIN_FRAC * R), np.log(top), N_NODES)
        W = prior.tissue.width_m
        x = np.clip(np.asarray(x_m, float), 0.0, W)
        ref = thickness_reference(prior)

        def rows_of(sc, k):
            rows = []
            for xi in x:
                key = (prior.key(), k, round(float(xi), 7))
                row = _ROWS.get(key)
                if row is None:
                    row = np.log(np.maximum(recall.force_curve_n(sc, float(xi), np.exp(self.logd)), 1e-12))
                    _ROWS[key] = row
                rows.append(row)
            return np.array(rows).reshape(len(x), N_NODES)
        tabs = [rows_of(prior if k == 0 else scene_with_height(prior, 1.0 + k * THICKNESS_STEP), k) for k in (-1, 0, 1)]
        if ref is not None:               # the outer nodes relative to the prior on their own mesh
            r = rows_of(ref, "reference")
            tabs[0], tabs[2] = tabs[1] + tabs[0] - r, tabs[1] + tabs[2] - r
        self.T = np.stack(tabs)           # (3, n, nodes)
        self._last: tuple[float, np.ndarray] | None = None
        self._last_slopes: tuple[float, np.ndarray] | None = None

    def _rows(self, eta: float) -> np.ndarray:
        """log F rows (n, nodes) at the relative thickness change ``eta`` (quadratic through the three nodes; the
        last eta's kept: a fit asks for the same one several times per evaluation)."""
        eta = float(eta)
        if self._last is None or self._last[0] != eta:
            u = eta / THICKNESS_STEP
            w = np.array([0.5 * u * (u - 1), 1 - u * u, 0.5 * u * (u + 1)])
            self._last = (eta, np.tensordot(w, self.T, axes=1))
        return self._last[1]

    def _row_slopes(self, eta: float) -> np.ndarray:
        """d/d eta of ``_rows(eta)`` (the last eta's kept)."""
        eta = float(eta)
        if self._last_slopes is None or self._last_slopes[0] != eta:
            u = eta / THICKNESS_STEP
            dw = np.array([u - 0.5, -2.0 * u, u + 0.5]) / THICKNESS_STEP
            self._last_slopes = (eta, np.tensordot(dw, self.T, axes=1))
        return self._last_slopes[1]

    def force_slopes(self, depth_m, eta: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """d/d depth and d/d eta of ``force_n`` at each probe (exact for the interpolant; 0 out of contact)."""
        d = np.asarray(depth_m, float)
        i, w = _loglog_segment(self.logd, d)
        n = np.arange(len(d))
        rows, drows = self._rows(eta), self._row_slopes(eta)
        F = np.exp((1 - w) * rows[n, i] + w * rows[n, i + 1])
        step = self.logd[1] - self.logd[0]
        dF_dd = np.where(d > 1e-7, F * (rows[n, i + 1] - rows[n, i]) / (step * np.maximum(d, 1e-7)), 0.0)
        dF_deta = np.where(d > 0, F * ((1 - w) * drows[n, i] + w * drows[n, i + 1]), 0.0)
        return dF_dd, dF_deta

    def depth_at_force_slopes(self, force_n, eta: float = 0.0, idx=None) -> tuple[np.ndarray, np.ndarray]:
        """d/d log(force) and d/d eta of ``depth_at_force_m`` at each probe (or probe ``idx``)."""
        rows, drows = self._rows(eta), self._row_slopes(eta)
        if idx is not None:
            rows, drows = rows[idx], drows[idx]
        F = np.asarray(force_n, float)
        lf = np.log(np.maximum(F, 1e-12))
        k = clip(np.sum(rows < lf[:, None], axis=1) - 1, 0, len(self.logd) - 2)
        n = np.arange(len(lf))
        gap = rows[n, k + 1] - rows[n, k]
        t = (lf - rows[n, k]) / gap
        step = self.logd[1] - self.logd[0]
        d = np.exp(self.logd[k] + t * step)
        dd_dlf = np.where(F > 1e-12, d * step / gap, 0.0)
        dd_deta = d * step * (-drows[n, k] - t * (drows[n, k + 1] - drows[n, k])) / gap
        return dd_dlf, dd_deta

    def force_n(self, depth_m, eta: float = 0.0) -> np.ndarray:
        """The prior's force at each probe's true indentation ``depth_m`` (0 where it is not in contact)."""
        return loglog_force(self._rows(eta), self.logd, depth_m)

    def depth_at_force_m(self, force_n, eta: float = 0.0, idx=None) -> np.ndarray:
        """The indentation at which each probe's (or probe ``idx``'s) prior force reaches ``force_n`` (the inverse
        of ``force_n``)."""
        rows = self._rows(eta)
        return loglog_depth(rows if idx is None else rows[idx], self.logd, force_n)


def loglog_force(rows: np.ndarray, logd: np.ndarray, depth_m) -> np.ndarray:
    """Force at ``depth_m`` (one per row) from rows of log force on the even log-depth nodes ``logd``: linear in
    (log depth, log force), extrapolated the same way beyond the nodes; 0 where the depth is not positive."""
    d = np.asarray(depth_m, float)
    i, w = _loglog_segment(logd, d)
    n = np.arange(len(d))
    lf = (1 - w) * rows[n, i] + w * rows[n, i + 1]
    return np.where(d > 0, np.exp(lf), 0.0)


def _loglog_segment(logd: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The log-depth segment of each depth and the weight of its upper node (outside [0, 1] at the ends: linear
    extrapolation)."""
    u = (np.log(np.maximum(d, 1e-7)) - logd[0]) / (logd[1] - logd[0])
    i = clip(np.floor(u).astype(int), 0, len(logd) - 2)
    return i, u - i


def loglog_depth(rows: np.ndarray, logd: np.ndarray, force_n) -> np.ndarray:
    """The inverse of ``loglog_force``: the depth at which each row's force reaches ``force_n`` (rows rise)."""
    lf = np.log(np.maximum(np.asarray(force_n, float), 1e-12))
    k = clip(np.sum(rows < lf[:, None], axis=1) - 1, 0, len(logd) - 2)
    n = np.arange(len(lf))
    t = (lf - rows[n, k]) / (rows[n, k + 1] - rows[n, k])
    return np.exp(logd[k] + t * (logd[1] - logd[0]))


def prior_and_thickness_slope(prior, x_m, depth_m) -> tuple[np.ndarray, np.ndarray]:
    """The prior's force at ``x_m`` (indentation ``depth_m``: one, or one per position) and its derivative with respect to the relative thickness
    change (central difference over the ``THICKNESS_STEP`` nodes): the nuisance columns of a design's Fisher
    information (planner.refine)."""
    W = prior.tissue.width_m
    x = np.clip(np.asarray(x_m, float), 0.0, W)
    d = np.broadcast_to(np.asarray(depth_m, float), x.shape)
    F = {}
    ref = thickness_reference(prior)
    for k in (-1, 0, 1, "reference") if ref is not None else (-1, 0, 1):
        # (remembered: a run's refinement design asks for the same candidate grid every round)
        sc = ref if k == "reference" else prior if k == 0 else scene_with_height(prior, 1.0 + k * THICKNESS_STEP)
        F[k] = np.array([recall.force_n(sc, float(xi), float(di)) for xi, di in zip(x, d)])
    if ref is not None:                    # the outer nodes relative to the prior on their own mesh
        F[-1], F[1] = F[0] * F[-1] / F["reference"], F[0] * F[1] / F["reference"]
    return F[0], (F[1] - F[-1]) / (2 * THICKNESS_STEP)
