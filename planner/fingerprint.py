"""A surrogate table's fingerprint, computed once per version of what decides fem's numbers.

A table (planner.surrogate, planner.surrogate3d) stores what fem computed for a small case when it was built, and is
used only while fem computes the same now: a behavioural check, so that refactoring fem without changing its numbers
keeps the table. Computing "now" costs a mesh and a factorization (0.4-0.9 s in 2D, 0.6 s in 3D, with the machine's
load) in every process that loads a table. The same code on the same numeric libraries gives the same numbers, so the
result is kept in fem's disk cache under the version of both (``numbers_version``: every source file of fem and of
core, which fem imports, the planner modules that compute a fingerprint (FINGERPRINT_CODE), and gmsh's, numpy's,
scipy's and cvxopt's versions) and read back by the next process; any change to them computes it again.
"""
from __future__ import annotations

import functools
import importlib.metadata as metadata
from collections.abc import Callable
from pathlib import Path

import numpy as np

import fem
from fem import diskcache
from fem.scene_mesh import gmsh_version

LIBRARIES = ("numpy", "scipy", "cvxopt")
FINGERPRINT_CODE = ("fingerprint.py", "surrogate.py", "surrogate3d.py")    # planner's part: the probes, the scenes


def _version(dist: str) -> str:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return "?"


@functools.lru_cache(maxsize=1)
def numbers_version() -> str:
    """A digest of every source file of fem and core, planner's FINGERPRINT_CODE, gmsh's version and the numeric
    libraries' (LIBRARIES)."""
    libs = "; ".join(f"{d} {_version(d)}" for d in LIBRARIES)
    return diskcache.files_digest(sources(), f"gmsh {gmsh_version()}; {libs}")


def sources() -> list[Path]:
    """The source files whose code decides a fingerprint's numbers."""
    fem_dir = Path(fem.__file__).resolve().parent
    here = Path(__file__).resolve().parent
    return (sorted(fem_dir.glob("*.py")) + sorted((fem_dir.parent / "core").glob("*.py"))
            + [here / name for name in FINGERPRINT_CODE])


def cached_fingerprint(kind: str, spec: dict, compute: Callable[[], np.ndarray]) -> np.ndarray:
    """``compute()`` (what fem computes now for the table of ``spec``), from fem's disk cache when this
    ``numbers_version`` computed it before; computed (and stored) otherwise, or always when the cache is off."""
    return diskcache.load_or_build(kind, {**spec, "numbers": numbers_version()}, build=compute,
                                   to_arrays=lambda fp: {"fingerprint": np.asarray(fp, float)},
                                   from_arrays=lambda d: np.array(d["fingerprint"], float))
