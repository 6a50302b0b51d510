"""The disk cache (fem.diskcache, used by fem.scene_mesh and fem.contact): restored surface models are bitwise the fresh ones, keys follow the scene's content,
damaged entries are ignored with a warning, PALPATE_CACHE=0 writes nothing."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fem import contact, contact3d, diskcache, scene_mesh
from fem import scene as S


@pytest.fixture
def cdir(tmp_path, monkeypatch):
    monkeypatch.setenv("PALPATE_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("PALPATE_CACHE", raising=False)
    monkeypatch.setattr(contact, "_CACHE", {})
    return tmp_path / "cache"


def _scene(name="paper"):
    return S.load(name).with_analysis(mesh_size_m=0.004)


def test_restored_surface_model_is_bitwise_the_fresh_one(cdir):
    sc = _scene()
    fresh = contact.surface_model(sc)
    assert sorted(p.name.split("-")[0] for p in cdir.glob("*.npz")) == ["mesh", "surface"]
    contact._CACHE.clear()
    hits = diskcache.stats["surface_hit"]
    restored = contact.surface_model(sc)
    assert diskcache.stats["surface_hit"] == hits + 1 and restored is not fresh
    assert restored._fac is None                       # force queries need no factorization
    assert np.array_equal(restored.C, fresh.C)
    assert np.array_equal(restored.model.mesh.nodes, fresh.model.mesh.nodes)
    xs = np.linspace(0.01, 0.06, 7)
    assert [restored.force_n(x, 0.004) for x in xs] == [fresh.force_n(x, 0.004) for x in xs]
    a, b = restored.indent(0.03, 0.004), fresh.indent(0.03, 0.004)   # fields: factorized on first use
    assert a.max_von_mises_pa == b.max_von_mises_pa and np.array_equal(a.pressure_pa, b.pressure_pa)
    assert not list(cdir.glob("*.tmp"))


def test_elastic_tip_is_cached_too(cdir):
    sc = _scene("healthy")
    fresh = contact.surface_model(sc, rigid_tip=False)
    contact._CACHE.clear()
    restored = contact.surface_model(sc, rigid_tip=False)
    assert not restored.rigid_tip and np.array_equal(restored.tip.C, fresh.tip.C)
    assert restored.force_n(0.035, 0.004) == fresh.force_n(0.035, 0.004)


def test_keys_follow_content_not_name():
    a = _scene()
    b = dataclasses.replace(a, name="other")
    stiffer = a.with_stones([dataclasses.replace(a.stones[0], youngs_pa=1e10)])
    assert contact.surface_key(a, {}) == contact.surface_key(b, {})
    assert contact.surface_key(a, {}) != contact.surface_key(stiffer, {})
    assert contact.surface_key(a, {}) != contact.surface_key(a, {"rigid_stones": False})
    assert scene_mesh.mesh_key(a) == scene_mesh.mesh_key(stiffer)          # moduli do not change the mesh
    assert scene_mesh.mesh_key(a) != scene_mesh.mesh_key(a.with_analysis(order=1))


@pytest.mark.parametrize("damage", [b"", b"not an npz file", None])
def test_damaged_entries_are_ignored_with_a_warning(cdir, damage):
    sc = _scene()
    fresh = contact.surface_model(sc)
    contact._CACHE.clear()
    path = next(cdir.glob("surface-*.npz"))
    if damage is None:      # a valid file holding the wrong array
        np.savez(path, C=np.zeros((3, 3)))
    else:
        path.write_bytes(damage)
    with pytest.warns(UserWarning, match="palpate cache: ignoring"):
        again = contact.surface_model(sc)
    assert np.array_equal(again.C, fresh.C)
    contact._CACHE.clear()
    assert np.array_equal(contact.surface_model(sc).C, fresh.C)   # the rebuilt entry was written back


def test_damaged_mesh_entry(cdir):
    sc = _scene("healthy")
    m1 = scene_mesh.mesh_for(sc)
    next(cdir.glob("mesh-*.npz")).write_bytes(b"\x00" * 100)
    with pytest.warns(UserWarning, match="ignoring"):
        m2 = scene_mesh.mesh_for(sc)
    assert np.array_equal(m1.nodes, m2.nodes) and np.array_equal(m1.tris, m2.tris)


def test_disabled_writes_nothing(cdir, monkeypatch):
    monkeypatch.setenv("PALPATE_CACHE", "0")
    sm = contact.surface_model(_scene("healthy"))
    assert sm.force_n(0.035, 0.004) > 0
    assert not cdir.exists() or not any(cdir.iterdir())
    monkeypatch.delenv("PALPATE_CACHE")
    contact._CACHE.clear()
    contact.surface_model(_scene("healthy"), cache=False)          # per call
    assert not cdir.exists() or not any(cdir.iterdir())


def test_unwritable_directory_only_warns(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    monkeypatch.setenv("PALPATE_CACHE_DIR", str(blocker / "sub"))    # cannot mkdir under a file
    monkeypatch.setattr(contact, "_CACHE", {})
    with pytest.warns(UserWarning, match="could not write"):
        sm = contact.surface_model(_scene("healthy"))
    assert sm.force_n(0.035, 0.004) > 0


def test_a_restored_3d_compliance_is_memory_mapped_and_gives_the_fresh_forces(cdir):
    """The 3D compliance (dense, 0.5 GB on block3d) is read memory-mapped: a run reads the rows of the windows it
    probes. The forces are the fresh model's bit for bit; a damaged entry is rebuilt; a non-finite number in an entry
    never leaves fem (the force that reads it raises)."""
    small = S.Scene(name="t", tissue=S.Tissue(width_m=0.03, length_m=0.03, height_m=0.015, youngs_pa=2500.0,
                                              poisson=0.4),
                    indenter=S.Indenter(shape="sphere", radius_m=0.004),
                    analysis=S.Analysis(order=2, mesh_size_m=0.006, surface_refine=4.0, patch_m=0.02,
                                        top_displacement_m=0.001))
    fresh = contact3d.load_or_build_surface3d(small, {})
    restored = contact3d.load_or_build_surface3d(small, {})
    assert isinstance(restored.C.base, np.memmap) and not restored.C.flags.writeable
    pts = [(0.015, 0.015, 0.001), (0.011, 0.017, 0.0015), (0.019, 0.012, 0.0005)]
    assert [restored.force_n(*p) for p in pts] == [fresh.force_n(*p) for p in pts]
    path = next(cdir.glob("surface3d-*.npz"))
    path.write_bytes(path.read_bytes()[:1000])                     # truncated
    with pytest.warns(UserWarning, match="palpate cache: ignoring"):
        again = contact3d.load_or_build_surface3d(small, {})
    assert [again.force_n(*p) for p in pts] == [fresh.force_n(*p) for p in pts]
    C = np.array(fresh.C)
    C[:] = np.nan
    diskcache.write(path, {"C": C})
    poisoned = contact3d.load_or_build_surface3d(small, {})
    with pytest.raises(FloatingPointError):
        poisoned.force_n(*pts[0])


def _loads(sm, n: int = 3) -> np.ndarray:
    """Downward nodal forces on the top: n columns, a few nodes each under different x."""
    F = np.zeros((len(sm.top), n))
    for k, x in enumerate(np.linspace(0.02, 0.05, n)):
        near = np.argsort(np.abs(sm.x - x))[:5]
        F[near, k] = np.linspace(1.0, 2.0, 5) * 1e-3
    return F


def test_2d_fields_come_from_the_stored_factor_without_assembly(cdir):
    """The 2D fields' factor (kind ``factor``): equal to the SuperLU solve to round-off; a later process (the
    in-memory cache cleared) reads it and neither assembles nor factorizes, with bitwise the same fields."""
    sc = _scene()
    fresh = contact.surface_model(sc)
    F = _loads(fresh)
    U = fresh.displacements(F)
    ref = contact.condensed_displacements(fresh.model, fresh.fac, F)        # SuperLU, the full solve's path
    assert np.max(np.abs(U - ref)) <= 1e-9 * np.max(np.abs(ref))
    assert len(list(cdir.glob("factor-*.npz"))) == 1
    contact._CACHE.clear()
    restored = contact.surface_model(sc)
    U2 = restored.displacements(F)
    assert np.array_equal(U2, U)
    assert "K" not in vars(restored.model) and restored._fac is None       # no assembly, no factorization
    u = restored.full_field(0.035, 0.004)
    assert np.array_equal(u, fresh.full_field(0.035, 0.004))


def _damage(arrays: dict) -> None:
    arrays["x"][len(arrays["x"]) // 2] = np.nan


@pytest.mark.parametrize("damage, why", [
    (lambda a: a.update(p=a["p"][::-1].copy()), "does not fit"),      # another order: the top not last
    (_damage, "not finite"),
])
def test_a_2d_factor_entry_that_does_not_fit_or_is_not_finite_is_rebuilt(cdir, damage, why):
    sc = _scene()
    F = _loads(contact.surface_model(sc))
    U = contact.surface_model(sc).displacements(F)
    path = next(cdir.glob("factor-*.npz"))
    with np.load(path) as z:
        a = {k: z[k] for k in z.files}
    damage(a)
    np.savez(path, **a)
    contact._CACHE.clear()
    with pytest.warns(UserWarning, match=f"palpate cache: ignoring.*{why}"):
        again = contact.surface_model(sc).displacements(F)
    assert np.array_equal(again, U)


def test_without_cholmod_the_2d_fields_come_from_superlu(cdir, monkeypatch):
    from fem import condense
    calls = []
    monkeypatch.setattr(condense, "interior_factor", lambda *a, **k: calls.append(1))   # returns None
    sm = contact.surface_model(_scene())
    F = _loads(sm, 2)
    U = sm.displacements(F)
    assert np.array_equal(U, contact.condensed_displacements(sm.model, sm.fac, F))
    sm.displacements(F)
    assert calls == [1] and not list(cdir.glob("factor-*.npz"))             # tried once, nothing stored


def test_models_differing_only_in_what_the_factor_does_not_see_share_it(cdir):
    """The tip, the stress band and the influence operators' use do not change K: one factor entry serves all."""
    sc = _scene()
    F = _loads(contact.surface_model(sc))
    U = contact.surface_model(sc).displacements(F)
    other = contact.surface_model(S.load("paper").with_analysis(mesh_size_m=0.004), stress_band_m=0.006,
                                  use_influence=False)
    assert other is not contact.surface_model(sc)
    assert np.array_equal(other.displacements(F), U) and len(list(cdir.glob("factor-*.npz"))) == 1
    stiffer = dataclasses.replace(sc, tissue=dataclasses.replace(sc.tissue, youngs_pa=2 * sc.tissue.youngs_pa))
    contact.surface_model(stiffer).displacements(F)
    assert len(list(cdir.glob("factor-*.npz"))) == 2                            # K changed: another entry
