"""The prior block's force at each probe position (x, y) as a function of the probe's TRUE indentation: what the 3D
localizer needs to fit the surface height, its tilt and the stiffness scale as nuisance parameters.

Tabulated with 3D fem (fem.contact3d: one exact contact LCP per node) per probe position on a geometric grid of
indentations and interpolated linearly in (log depth, log force): exact for a power law (Hertz: d^1.5). fem's force
is not smooth in depth, though (a ring of top nodes enters the contact at a time: small kinks), so between nodes the
interpolation is off by up to 0.6 % (16 nodes; 0.2 % with 24 or 32: the kinks, not the node count, set it), as large
as a probe's noise on a 70 mN force. Each probe's row is therefore anchored at its own measured indentation: shifted
so that it gives fem's exact force there (one more LCP per probe); the interpolation then only carries the force's
change with a surface offset, a fraction of a millimetre (within 0.4 % of fem 0.3 mm either side of the
anchor on the test block; tests/test_loop3d.py measures both). Beyond the grid (fem
refuses indentations at the tip radius) the same line is extrapolated. A position's row is computed once per process
(rounds re-use the positions of earlier ones).

The tissue's thickness is a nuisance as in the 2D section (planner.tissue_response): the rows are tabulated for
the prior and for the prior with its height scaled by ``1 -+ THICKNESS_STEP`` (two more 3D fem models of the block,
built once and kept in the disk cache), each anchored at the probe's indentation on its own model, and interpolated
quadratically in the relative thickness change ``eta``. A localizer that holds the thickness fixed asks for the
prior's height alone (``thickness=False``).
"""
from __future__ import annotations

import numpy as np

from fem import recall3d
from fem.contact3d import surface3d_cached, surface_model3d
from fem.scene import STRAIN_MAX
from planner.tissue_response import (
    THICKNESS_STEP,
    loglog_depth,
    loglog_force,
    scene_with_height,
    thickness_reference,
)

N_NODES = 16
MIN_FRAC, MAX_FRAC = 0.06, 0.96

_ROWS: dict = {}          # (scene key, deepest node, round(x, 7), round(y, 7)) -> log force row


class PriorResponse3D:
    """log F(x_i, y_i, d, eta) of the prior (stone-free) block at fixed probe positions, anchored at ``depth_m`` (one
    per probe: fem's exact force there on each thickness's model; None: not anchored). ``thickness``: tabulate the
    thinner and thicker blocks too (eta free); False: the prior's height only (eta must be 0)."""

    def __init__(self, prior, x_m, y_m, depth_m=None, thickness: bool = True):
        R = prior.indenter.radius_m
        # up to the tip's radius, or on a thin block to the deepest indentation fem allows on its thinnest node
        thinnest = 1.0 - THICKNESS_STEP if thickness else 1.0
        top = min(MAX_FRAC * R, 0.99 * STRAIN_MAX * thinnest * prior.tissue.height_m)
        self.logd = np.linspace(np.log(MIN_FRAC * R), np.log(top), N_NODES)
        self.thickness = bool(thickness)
        x, y = np.asarray(x_m, float), np.asarray(y_m, float)
        ref = thickness_reference(prior) if thickness else None

        def rows_of(sc):
            rows = []
            for xi, yi in zip(x, y):
                key = (sc.key(), float(top), round(float(xi), 7), round(float(yi), 7))
                row = _ROWS.get(key)
                if row is None:
                    row = np.log(np.maximum([recall3d.force_n(sc, float(xi), float(yi), float(d))
                                             for d in np.exp(self.logd)], 1e-12))
                    _ROWS[key] = row
                rows.append(row)
            rows = np.array(rows).reshape(-1, N_NODES)
            if depth_m is not None:
                surface_model3d(sc)   # built (or restored) first: _exact takes a ValueError for a refused depth only
                d = np.asarray(depth_m, float)
                exact = np.array([_exact(sc, float(xi), float(yi), float(di)) for xi, yi, di in zip(x, y, d)])
                ok = exact > 0
                shift = np.zeros(len(d))
                shift[ok] = np.log(exact[ok]) - np.log(loglog_force(rows[ok], self.logd, d[ok]))
                rows = rows + shift[:, None]
            return rows
        tabs = [rows_of(prior if k == 0 else scene_with_height(prior, 1.0 + k * THICKNESS_STEP))
                for k in ((-1, 0, 1) if thickness else (0,))]
        if ref is not None:              # the outer nodes relative to the prior on their own mesh
            r = rows_of(ref)
            tabs[0], tabs[2] = tabs[1] + tabs[0] - r, tabs[1] + tabs[2] - r
        self.T = np.stack(tabs)          # (thickness nodes, n, depth nodes)
        self._last: tuple[float, np.ndarray] | None = None

    @property
    def rows(self) -> np.ndarray:
        """The prior's own rows (eta = 0)."""
        return self.T[len(self.T) // 2]

    def _rows(self, eta: float) -> np.ndarray:
        """log F rows at the relative thickness change ``eta`` (quadratic through the three nodes; the last eta's
        kept: a fit asks for the same one several times per evaluation)."""
        eta = float(eta)
        if eta == 0.0:
            return self.rows
        if not self.thickness:
            raise ValueError("PriorResponse3D(thickness=False) has the prior's height only: eta must be 0")
        if self._last is None or self._last[0] != eta:
            u = eta / THICKNESS_STEP
            w = np.array([0.5 * u * (u - 1), 1 - u * u, 0.5 * u * (u + 1)])
            self._last = (eta, np.tensordot(w, self.T, axes=1))
        return self._last[1]

    def force_n(self, depth_m, idx=None, eta: float = 0.0) -> np.ndarray:
        """The prior's force at each probe's (or probe ``idx``'s) true indentation ``depth_m`` (0 out of contact), the
        block's thickness changed by the relative ``eta``."""
        rows = self._rows(eta)
        return loglog_force(rows if idx is None else rows[idx], self.logd, depth_m)

    def depth_at_force_m(self, force_n, idx=None, eta: float = 0.0) -> np.ndarray:
        """The indentation at which each probe's (or probe ``idx``'s) prior force reaches ``force_n``."""
        rows = self._rows(eta)
        return loglog_depth(rows if idx is None else rows[idx], self.logd, force_n)


_EXACT: dict = {}


def _exact(scene, x: float, y: float, d: float) -> float:
    """fem's force at (x, y, d), 0 where fem refuses the indentation (at the tip radius): no anchor there."""
    key = (scene.key(), round(x, 7), round(y, 7), round(d, 9))
    if key not in _EXACT:
        try:
            _EXACT[key] = recall3d.force_n(scene, x, y, d) if d > 0 else 0.0
        except ValueError:
            _EXACT[key] = 0.0
    return _EXACT[key]


def prior_and_thickness_slope3d(prior, x_m, y_m, depth_m) -> tuple[np.ndarray, np.ndarray]:
    """The prior block's force at each (x, y) pressed ``depth_m`` deep (one, or one per position) and its derivative
    with respect to the relative thickness change (central difference over the ``THICKNESS_STEP`` nodes, fem on
    each): the nuisance columns of a 3D detectability analysis (planner.detect3d), as in 2D."""
    x, y = np.asarray(x_m, float), np.asarray(y_m, float)
    d = np.broadcast_to(np.asarray(depth_m, float), x.shape)
    F = {}
    ref = thickness_reference(prior)
    for k in (-1, 0, 1):
        sc = prior if k == 0 else scene_with_height(prior, 1.0 + k * THICKNESS_STEP)
        F[k] = np.array([_refused_nan(sc, float(xi), float(yi), float(di)) if k < 0 else
                         recall3d.force_n(sc, float(xi), float(yi), float(di)) for xi, yi, di in zip(x, y, d)])
    if ref is not None:                  # the outer nodes relative to the prior on their own mesh
        Fr = np.array([recall3d.force_n(ref, float(xi), float(yi), float(di)) for xi, yi, di in zip(x, y, d)])
        F[-1], F[1] = F[0] * F[-1] / Fr, F[0] * F[1] / Fr
    # (a depth the thinner block refuses, past STRAIN_MAX of its height: the one-sided difference)
    slope = np.where(np.isfinite(F[-1]), (F[1] - F[-1]) / (2 * THICKNESS_STEP), (F[1] - F[0]) / THICKNESS_STEP)
    return F[0], slope


def _refused_nan(scene, x: float, y: float, d: float) -> float:
    try:
        return recall3d.force_n(scene, x, y, d)
    except ValueError:
        return float("nan")


def thickness_models_to_build(prior) -> list[float]:
    """The height factors (of ``1 -+ THICKNESS_STEP``) whose 3D fem model of the prior block is not in the disk
    cache yet: built on first use (38-44 s each for block3d here, measured), then kept."""
    capped = thickness_reference(prior) is not None     # (then the prior's height on the capped mesh: a reference)
    return [f for f in ((1.0 - THICKNESS_STEP, 1.0, 1.0 + THICKNESS_STEP) if capped else
                        (1.0 - THICKNESS_STEP, 1.0 + THICKNESS_STEP))
            if not surface3d_cached(scene_with_height(prior, f))]
