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

The thickness is not a nuisance in 3D (unlike the 2D section, planner.tissue_response): the block's thickness is
known to the planner as the prior's, and the 3D fit does without it (docs/loop3d.md says what that costs).
"""
from __future__ import annotations

import numpy as np

from fem import recall3d
from fem.contact3d import surface_model3d
from fem.scene import STRAIN_MAX
from planner.tissue_response import loglog_depth, loglog_force

N_NODES = 16
MIN_FRAC, MAX_FRAC = 0.06, 0.96

_ROWS: dict = {}          # (prior key, round(x, 7), round(y, 7)) -> log force row


class PriorResponse3D:
    """log F(x_i, y_i, d) of the prior (stone-free) block at fixed probe positions, anchored at ``depth_m`` (one per
    probe: fem's exact force there; None: not anchored)."""

    def __init__(self, prior, x_m, y_m, depth_m=None):
        R = prior.indenter.radius_m
        top = min(MAX_FRAC * R, 0.99 * STRAIN_MAX * prior.tissue.height_m)    # (a thin block: fem's deepest)
        self.logd = np.linspace(np.log(MIN_FRAC * R), np.log(top), N_NODES)
        rows = []
        for xi, yi in zip(np.asarray(x_m, float), np.asarray(y_m, float)):
            key = (prior.key(), round(float(xi), 7), round(float(yi), 7))
            row = _ROWS.get(key)
            if row is None:
                row = np.log(np.maximum([recall3d.force_n(prior, float(xi), float(yi), float(d))
                                         for d in np.exp(self.logd)], 1e-12))
                _ROWS[key] = row
            rows.append(row)
        self.rows = np.array(rows).reshape(-1, N_NODES)
        if depth_m is not None:
            surface_model3d(prior)     # built (or restored) first: _exact takes a ValueError for a refused depth only
            d = np.asarray(depth_m, float)
            exact = np.array([_exact(prior, float(x), float(y), float(di))
                              for x, y, di in zip(np.asarray(x_m, float), np.asarray(y_m, float), d)])
            ok = exact > 0
            shift = np.zeros(len(d))
            shift[ok] = np.log(exact[ok]) - np.log(loglog_force(self.rows[ok], self.logd, d[ok]))
            self.rows = self.rows + shift[:, None]

    def force_n(self, depth_m, idx=None) -> np.ndarray:
        """The prior's force at each probe's (or probe ``idx``'s) true indentation ``depth_m`` (0 out of contact)."""
        return loglog_force(self.rows if idx is None else self.rows[idx], self.logd, depth_m)

    def depth_at_force_m(self, force_n, idx=None) -> np.ndarray:
        """The indentation at which each probe's (or probe ``idx``'s) prior force reaches ``force_n``."""
        return loglog_depth(self.rows if idx is None else self.rows[idx], self.logd, force_n)


_EXACT: dict = {}


def _exact(prior, x: float, y: float, d: float) -> float:
    """fem's force at (x, y, d), 0 where fem refuses the indentation (at the tip radius): no anchor there."""
    key = (prior.key(), round(x, 7), round(y, 7), round(d, 9))
    if key not in _EXACT:
        try:
            _EXACT[key] = recall3d.force_n(prior, x, y, d) if d > 0 else 0.0
        except ValueError:
            _EXACT[key] = 0.0
    return _EXACT[key]
