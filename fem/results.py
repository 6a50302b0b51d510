"""Result types shared by the load A solvers (fem.uniform: displacement formulation, fem.mixed: u-p)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from core.peak import parabola_peak

from .guards import check_finite
from .model import Model


@dataclass
class Profile:
    """Stresses along the top surface (Pa), nodes sorted by x."""
    x_m: np.ndarray
    fields: dict[str, np.ndarray]

    def peak(self, key: str = "von_mises_pa") -> tuple[float, float]:
        """(x_m, value) of the maximum, refined by a parabola through the largest node and its neighbours."""
        v = self.fields[key]
        i = int(np.argmax(v))
        return parabola_peak(self.x_m, v, max(i - 1, 0), min(i + 1, len(v) - 1))

    def to_dict(self) -> dict:
        """The profile and its peak as JSON-ready values; NonFiniteResultError (fem.guards) if any is not finite."""
        xp, vp = self.peak()
        return check_finite({"surface": {"x_m": self.x_m.tolist(), **{k: v.tolist() for k, v in self.fields.items()}},
                "peak": {"x_m": xp, "von_mises_pa": vp}}, "surface stress profile")


@dataclass
class UniformResult:
    model: Model
    u: np.ndarray                      # full displacement (2N,)
    surface: Profile
    nodal: dict[str, np.ndarray] | None = None    # full-field stresses and strains at nodes (None: surface only)
    timings_s: dict = field(default_factory=dict)
    reaction_n_per_m: float = 0.0      # total vertical force on the top edge per unit thickness (compression > 0)
    residual: float = 0.0              # relative residual of the free equations, ||(K u)_free|| / ||K_fp u_p||
