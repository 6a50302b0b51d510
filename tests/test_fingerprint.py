"""planner.fingerprint: a table's fingerprint computed once per version of fem and its libraries, then read."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

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


@pytest.mark.parametrize("changed", ["lcp.py", "condense.py", "peak.py", "surrogate.py", "surrogate3d.py"])
def test_a_change_to_the_code_behind_the_numbers_changes_the_version(changed, monkeypatch):
    """fem's solvers, core (which fem imports) and planner's fingerprint code: one changed byte, a new version."""
    before = fingerprint.numbers_version.__wrapped__()
    real = Path.read_bytes
    monkeypatch.setattr(Path, "read_bytes", lambda self: real(self) + (b"#" if self.name == changed else b""))
    assert fingerprint.numbers_version.__wrapped__() != before


def test_the_libraries_versions_are_in_the_version(monkeypatch):
    before = fingerprint.numbers_version.__wrapped__()
    monkeypatch.setattr(fingerprint, "_version", lambda d: "0.0" if d == "scipy" else fingerprint.metadata.version(d))
    assert fingerprint.numbers_version.__wrapped__() != before
    monkeypatch.setattr(fingerprint, "gmsh_version", lambda: "0.0")
    assert fingerprint.numbers_version.__wrapped__() != before
