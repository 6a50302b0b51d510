"""Result types of the 3D load cases: a stress map over the top face and its peak."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .guards import check_finite


def quadratic_peak(x: np.ndarray, y: np.ndarray, v: np.ndarray) -> tuple[float, float, float]:
    """(x, y, value) of the maximum of scattered values: the largest node, refined by a least-squares quadratic
    through its nearest neighbours (at least 12 of them) when that quadratic has a maximum within half their reach
    and inside their bounding box (as ``core.peak.parabola_peak`` keeps its vertex within its samples: at a grid's
    edge a noisy quadratic could put it beyond the grid, where nothing was sampled)."""
    i = int(np.argmax(v))
    d = np.hypot(x - x[i], y - y[i])
    near = np.argsort(d)[:13]
    reach = d[near].max()
    dx, dy = x[near] - x[i], y[near] - y[i]
    A = np.stack([np.ones_like(dx), dx, dy, dx * dx, dx * dy, dy * dy], axis=1)
    if len(near) >= 6 and reach > 0:
        c, *_ = np.linalg.lstsq(A, v[near], rcond=None)
        H = np.array([[2 * c[3], c[4]], [c[4], 2 * c[5]]])
        if np.all(np.linalg.eigvalsh(H) < 0):
            s = np.linalg.solve(H, -c[1:3])
            xv, yv = x[i] + s[0], y[i] + s[1]
            inside = x[near].min() <= xv <= x[near].max() and y[near].min() <= yv <= y[near].max()
            if np.hypot(*s) <= 0.5 * reach and inside:
                val = c[0] + c[1] * s[0] + c[2] * s[1] + 0.5 * s @ H @ s
                return float(xv), float(yv), float(max(val, v[i]))
    return float(x[i]), float(y[i]), float(v[i])


@dataclass
class SurfaceMap:
    """Stresses at the top-face nodes (Pa)."""
    x_m: np.ndarray
    y_m: np.ndarray
    fields: dict[str, np.ndarray]

    def peak(self, key: str = "von_mises_pa") -> tuple[float, float, float]:
        """(x_m, y_m, value) of the maximum (quadratic_peak)."""
        return quadratic_peak(self.x_m, self.y_m, self.fields[key])

    def to_dict(self) -> dict:
        xp, yp, vp = self.peak()
        return check_finite({"surface": {"x_m": self.x_m.tolist(), "y_m": self.y_m.tolist(),
                                         **{k: v.tolist() for k, v in self.fields.items()}},
                             "peak": {"x_m": xp, "y_m": yp, "von_mises_pa": vp}}, "top-face stress map")


@dataclass
class UniformResult3D:
    model: object                       # fem.model3d.Model3D
    u: np.ndarray                       # full displacement (3N,)
    surface: SurfaceMap
    nodal: dict[str, np.ndarray] | None = None
    timings_s: dict = field(default_factory=dict)
    reaction_n: float = 0.0             # total vertical force on the top face (compression > 0), N
    residual: float = 0.0               # relative residual of the free equations
