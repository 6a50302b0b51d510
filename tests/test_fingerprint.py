"""planner.fingerprint: a table's fingerprint computed once per version of fem and its libraries, then read."""
from __future__ import annotations

from pathlib import Path

import numpy as np

import fem
import planner.surrogate as su
from fem.scene import load
from planner import fingerprint
from planner.surrogate import Grid


def test_the_2d_fingerprint_is_read_back_and_recomputed_for_a_changed_fem(tmp_path, monkeypatch):
    monkeypatch.setenv("PALPATE_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv("PALPATE_CACHE", raising=False)
    prior = load("paper").prior()
    own = su.table_scene(prior, prior.tissue.youngs_pa)
    fresh = su.fingerprint(own, Grid())
    calls = []
    real = su.fingerprint
    monkeypatch.setattr(su, "fingerprint", lambda *a: calls.append(1) or real(*a))
    first = su._fingerprint_now(own, Grid())
    second = su._fingerprint_now(own, Grid())
    assert len(calls) == 1                                  # the second read it from the disk cache
    np.testing.assert_array_equal(first, fresh)
    np.testing.assert_array_equal(second, fresh)
    su._MEM.clear()
    sur = su.load_surrogate(prior, build=False)             # the shipped table, checked without fem
    assert len(calls) == 1 and sur.T.size
    monkeypatch.setattr(fingerprint, "numbers_version", lambda: "fem changed")
    su._fingerprint_now(own, Grid())
    assert len(calls) == 2
    su._MEM.clear()


def test_numbers_version_covers_every_fem_source_and_the_libraries(monkeypatch):
    seen = {}
    monkeypatch.setattr(fingerprint.diskcache, "files_digest",
                        lambda paths, extra="": seen.update(paths=[Path(p).name for p in paths], extra=extra) or "x")
    fingerprint.numbers_version.__wrapped__()
    assert sorted(seen["paths"]) == sorted(p.name for p in Path(fem.__file__).resolve().parent.glob("*.py"))
    assert "lcp.py" in seen["paths"] and "condense.py" in seen["paths"]       # not only the mesh caches' list
    assert f"numpy {np.__version__}" in seen["extra"] and "scipy " in seen["extra"] and "gmsh " in seen["extra"]
