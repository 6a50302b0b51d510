"""Tissue force for the simulated arm: a lazy grid cache over an expensive force model, and a cheap stand-in.

``CachedForce``: ``force_model`` is evaluated lazily on a grid (x snapped to ``x_grid_m``, depth nodes every
``depth_grid_m``) and interpolated linearly in depth. For F ~ k d^1.5 the interpolation error is
h^2/8 * F'' = 0.09 k h^2 d^-0.5: below 0.3 % of F for d >= 1 mm with h = 0.1 mm (tests measure it).

``standin_force_model``: a Hertz-like k d^1.5, stiffened above shallow stones, for tests and a fast simulator
(no fem).
"""
from __future__ import annotations

import math

import numpy as np


class CachedForce:
    """Lazy grid cache of an expensive ``force_model(x_m, depth_m)`` (a 2D section) or, with ``three_d``,
    ``force_model(x_m, y_m, depth_m)`` (a 3D block: y snapped like x); linear interpolation in depth."""

    def __init__(self, force_model, x_grid_m: float = 1e-5, depth_grid_m: float = 1e-4, three_d: bool = False):
        self.f, self.hx, self.hd, self.three_d = force_model, x_grid_m, depth_grid_m, three_d
        self.nodes: dict[tuple[int, int, int], float] = {}
        self.extrapolated = 0        # nodes the model refused (out of its range), linearly extrapolated
        # calls whose depth lies at or beyond the first node the model refused at that x (not one grid step of
        # extrapolation towards the range's edge, but a force the model cannot give): reported, never silent
        self.beyond_range = 0
        self.deepest_beyond_range_m = 0.0
        self.first_refusal = ""              # why fem refused its first depth (the range report says it)
        self._refused_from: dict[tuple[int, int], int] = {}   # (ix, iy) -> first depth node the model refused

    def _eval(self, ix: int, iy: int, depth_m: float) -> float:
        if self.three_d:
            return float(self.f(ix * self.hx, iy * self.hx, depth_m))
        return float(self.f(ix * self.hx, depth_m))

    def _node(self, ix: int, iy: int, idp: int) -> float:
        v = self.nodes.get((ix, iy, idp))
        if v is None:
            try:
                v = 0.0 if idp <= 0 else self._eval(ix, iy, idp * self.hd)
            except ValueError as e:   # beyond the model's range (fem refused the depth): continue linearly
                self.first_refusal = self.first_refusal or " ".join(str(e).split())
                self._refused_from[(ix, iy)] = min(idp, self._refused_from.get((ix, iy), idp))
                v = 2 * self._node(ix, iy, idp - 1) - self._node(ix, iy, idp - 2) if idp >= 2 else 0.0
                self.extrapolated += 1
            self.nodes[(ix, iy, idp)] = v
        return v

    def __call__(self, x_m: float, depth_m: float, y_m: float = 0.0) -> float:
        f, beyond = self.look(x_m, depth_m, y_m)
        if beyond:
            self.count_beyond(depth_m)
        return f

    def look(self, x_m: float, depth_m: float, y_m: float = 0.0) -> tuple[float, bool]:
        """(the force, whether it lies at or beyond the model's range) without counting it in the range report."""
        if depth_m <= 0:
            return 0.0, False
        ix, iy = int(round(x_m / self.hx)), (int(round(y_m / self.hx)) if self.three_d else 0)
        u = depth_m / self.hd
        i = int(math.floor(u))
        w = u - i
        f = (1 - w) * self._node(ix, iy, i) + w * self._node(ix, iy, i + 1)
        return f, (ix, iy) in self._refused_from and u >= self._refused_from[(ix, iy)]

    def look_many(self, x_m: np.ndarray, depth_m: np.ndarray, y_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``look`` at many points in turn (depths > 0): the forces and whether each lies at or beyond the model's
        range. Element by element the same operations (round half to even, floor, the same interpolation), the
        nodes evaluated in the order the points first need them, and each point's range flag read as ``look`` reads
        it at its turn: after the nodes of the points before it (the same flags for a model whose refusals are not
        monotone in depth)."""
        ix = np.rint(x_m / self.hx).astype(np.int64)
        iy = np.rint(y_m / self.hx).astype(np.int64) if self.three_d else np.zeros(len(ix), np.int64)
        u = depth_m / self.hd
        i = np.floor(u).astype(np.int64)
        w = u - i
        keys, first, inv = np.unique(np.stack([ix, iy, i], axis=1), axis=0, return_index=True, return_inverse=True)
        inv = inv.reshape(-1)
        n0, n1, refused = np.empty(len(keys)), np.empty(len(keys)), np.empty(len(keys))
        order = np.argsort(first, kind="stable")
        rows = keys.tolist()
        for r in order.tolist():
            a, b, c = rows[r]
            n0[r], n1[r] = self._node(a, b, c), self._node(a, b, c + 1)
            refused[r] = self._refused_from.get((a, b), np.inf)     # this column's range after this key's nodes
        f = (1 - w) * n0[inv] + w * n1[inv]
        beyond = np.zeros(len(u), bool)
        for a, b in {(r[0], r[1]) for r in rows}:       # per column: the last of its keys needed by each point
            kk = order[(keys[order, 0] == a) & (keys[order, 1] == b)]
            at = np.flatnonzero((ix == a) & (iy == b))
            last = kk[np.searchsorted(first[kk], at, side="right") - 1]
            beyond[at] = u[at] >= refused[last]
        return f, beyond

    def count_beyond(self, depth_m: float) -> None:
        """Count one force beyond the model's range at ``depth_m`` (the range report)."""
        self.beyond_range += 1
        self.deepest_beyond_range_m = max(self.deepest_beyond_range_m, depth_m)

    def range_report(self) -> dict | None:
        """None if every force came from the model's range; else what was extrapolated (for run.json)."""
        if not self.beyond_range:
            return None
        return {"samples_beyond_model_range": self.beyond_range,
                "deepest_m": self.deepest_beyond_range_m,
                "note": "the simulated force was extrapolated linearly beyond the force model's range (fem "
                        f"refused: {self.first_refusal or 'a depth beyond its range'}); those forces are not the "
                        "model's"}


def standin_force_model(width_m=0.07, k_n_per_m15=1500.0, stones=((0.035, 0.025, 0.015),), contrast=0.6):
    """A Hertz-like stand-in for fem: k d^1.5, stiffened near shallow stones ((x_m, depth_m, diameter_m) each)."""
    def f(x_m, depth_m):
        if depth_m <= 0 or not (0.0 <= x_m <= width_m):
            return 0.0
        g = 1.0
        for sx, sd, sdia in stones:
            g += contrast * (sdia / (2 * sd)) * math.exp(-((x_m - sx) / (0.6 * sd)) ** 2)
        return k_n_per_m15 * g * depth_m ** 1.5
    return f
