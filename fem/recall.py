"""A scene's contact forces as fem computed them before: ``SurfaceModel.force_n`` and ``force_curve_n`` through a
``fem.memo`` per scene (kept on disk with the disk cache on).

For the questions a run asks again and again, run after run, of a model whose content it does not change: the
prior's force curves and design points (planner.tissue_response), the simulated truth's force grid (robot.simarm).
An answer is the model's own, bit for bit: the first time computed, then read back (tests check both).
"""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np

from . import diskcache
from .contact import surface_key, surface_model
from .memo import Memo, memo


@lru_cache(maxsize=1)
def solver_version() -> str:
    """The contact solver's code, which the surface model's key does not name (it names the operators' code), and
    numpy's version (its LAPACK solves the LCP's equations)."""
    return diskcache.files_digest([Path(__file__).resolve().parent / "lcp.py"], f"recall 1; numpy {np.__version__}")


@lru_cache(maxsize=64)
def _spec(scene) -> dict:
    return {"surface": surface_key(scene, {}), "solver": solver_version()}


def _memo(scene) -> Memo:
    return memo("forces", _spec(scene), n_key=2, width=1)


def known(scene) -> bool:
    """Whether the scene's model answered before (so it builds: its memo holds what it computed)."""
    return len(_memo(scene)) > 0


def remembered(m: Memo, key: tuple[float, ...], compute) -> float:
    """The number ``m`` holds under ``key``, else ``compute()`` (remembered; an exception is not)."""
    row = m.get(key)
    if row is None:
        f = compute()
        m.put(key, f)
        return f
    return float(row[0])


def force_n(scene, x_m: float, depth_m: float) -> float:
    """``surface_model(scene).force_n(x_m, depth_m)``, remembered."""
    return remembered(_memo(scene), (float(x_m), float(depth_m)), lambda: surface_model(scene).force_n(x_m, depth_m))


def force_curve_n(scene, x_m: float, depths_m) -> np.ndarray:
    """``surface_model(scene).force_curve_n(x_m, depths_m)``, remembered (solved whole when any depth is new)."""
    m = _memo(scene)
    keys = [(float(x_m), float(d)) for d in depths_m]
    rows = [m.get(k) for k in keys]
    if all(r is not None for r in rows):
        return np.array([r[0] for r in rows])
    f = surface_model(scene).force_curve_n(x_m, depths_m)
    for k, v in zip(keys, f.tolist()):
        m.put(k, v)
    return f
