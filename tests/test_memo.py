"""fem.memo and fem.recall: what fem computed before, read back bit for bit, from memory and from disk."""
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

from fem import contact, diskcache, memo, recall
from fem import scene as S

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def cache(tmp_path, monkeypatch):
    """A private disk cache, and no memo left in memory from before (or after)."""
    memo.forget()
    monkeypatch.setenv("PALPATE_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv("PALPATE_CACHE", raising=False)
    yield tmp_path
    memo.forget()


def replace_height(sc, h):
    return S.Scene(name=sc.name, tissue=S.Tissue(width_m=sc.tissue.width_m, length_m=sc.tissue.length_m, height_m=h,
                                                 youngs_pa=sc.tissue.youngs_pa, poisson=sc.tissue.poisson),
                   indenter=sc.indenter, analysis=sc.analysis)


@pytest.fixture(scope="module")
def coarse():
    return S.load("paper").prior().with_analysis(mesh_size_m=0.004)


def test_rows_come_back_bit_for_bit_and_merge_across_writers(cache):
    spec = {"what": "test", "v": 1}
    rng = np.random.default_rng(3)
    keys = [tuple(v) for v in rng.normal(size=(50, 2)).tolist()]
    rows = rng.normal(size=(50, 3)) * 1e-7
    a = memo.Memo("t", spec, 2, 3)
    for k, r in zip(keys[:30], rows[:30]):
        a.put(k, r)
    b = memo.Memo("t", spec, 2, 3)          # another writer: saw nothing of a yet
    for k, r in zip(keys[30:], rows[30:]):
        b.put(k, r)
    a.save()
    b.save()                                 # merged with a's file, not over it
    c = memo.Memo("t", spec, 2, 3)
    assert len(c) == 50
    for k, r in zip(keys, rows):
        assert [v.hex() for v in c.get(k)] == [v.hex() for v in r.tolist()]
    assert c.get((0.5, 0.25)) is None
    assert memo.Memo("t", {"what": "test", "v": 2}, 2, 3).get(keys[0]) is None      # another spec: another file
    with pytest.raises(ValueError, match="finite"):
        c.put((0.5, 0.25), [1.0, float("nan"), 2.0])      # never stored: a file holds finite rows only
    with pytest.raises(ValueError, match="3 finite"):
        c.put((0.5, 0.25), [1.0, 2.0])


def test_a_memo_leaving_the_registry_is_written(cache, monkeypatch):
    monkeypatch.setattr(memo, "MAX_OPEN", 2)
    first = memo.memo("t", {"n": 0}, 1, 1)
    first.put((1.0,), 5.0)
    assert memo.memo("t", {"n": 0}, 1, 1) is first                      # one object per memo while open
    assert not first.path.exists()
    memo.memo("t", {"n": 1}, 1, 1), memo.memo("t", {"n": 2}, 1, 1)     # the first leaves: written
    assert first.path.exists() and memo.Memo("t", {"n": 0}, 1, 1).get((1.0,)) == (5.0,)
    assert memo.memo("t", {"n": 0}, 1, 1) is not first                  # asked again: read from its file


def test_a_full_file_keeps_the_newest(cache, monkeypatch):
    monkeypatch.setattr(memo, "MAX_ROWS", 10)
    m = memo.Memo("t", {"cap": 1}, 1, 1)
    for i in range(25):
        m.put((float(i),), i)
    m.save()
    back = memo.Memo("t", {"cap": 1}, 1, 1)
    assert len(back) == 10 and back.get((24.0,)) == (24.0,) and back.get((15.0,)) == (15.0,)
    assert back.get((14.0,)) is None


def test_a_long_process_trims_its_memo_in_memory(cache, monkeypatch):
    """Past twice the cap in memory (a serial study's prior): written, then the newest MAX_ROWS kept in memory; the
    file holds the newest too, those read back here before the rest."""
    monkeypatch.setattr(memo, "MAX_ROWS", 10)
    m = memo.Memo("t", {"long": 1}, 1, 1)
    for i in range(5):
        m.put((float(i),), i)
    assert m.get((0.0,)) == (0.0,)                       # read back: kept when the file is trimmed
    for i in range(5, 21):
        m.put((float(i),), i)
    assert len(m) == 10 and m.get((20.0,)) == (20.0,) and m.get((10.0,)) is None
    on_disk = memo.Memo("t", {"long": 1}, 1, 1)
    assert len(on_disk) == 10 and on_disk.get((0.0,)) == (0.0,) and on_disk.get((20.0,)) == (20.0,)
    assert on_disk.get((11.0,)) is None and on_disk.get((12.0,)) == (12.0,)


@pytest.mark.parametrize("damage", ["garbage", "shape", "nan-key", "nan-row", "swapped", "no digest"])
def test_a_damaged_file_is_ignored_with_a_warning_and_replaced(cache, damage):
    """Among the damages: another entry's valid file under this entry's name (a session-60 review rotated the
    forces files among their names, and a run used them without a word), or a file without its digest."""
    spec = {"damaged": damage}
    path = diskcache.entry_path("t", spec)
    if damage == "garbage":
        path.write_bytes(b"not a zip file")
    elif damage == "swapped":
        other = memo.Memo("t", {"another": 1}, 2, 1)
        other.put((0.1, 0.2), 3.0)
        other.save()
        path.write_bytes(other.path.read_bytes())
    else:
        keys = {"nan-key": np.array([[0.1, np.nan]]), "shape": np.zeros((1, 3))}.get(damage, np.zeros((1, 2)))
        rows = np.array([[np.nan]]) if damage == "nan-row" else np.zeros((1, 1))
        digest = {} if damage == "no digest" else {"digest": np.array(diskcache.digest(spec))}
        diskcache.write(path, {**digest, "keys": keys, "rows": rows})
    m = memo.Memo("t", spec, 2, 1)
    with pytest.warns(UserWarning, match="palpate cache: ignoring"):
        assert len(m) == 0
    m.put((0.1, 0.2), 7.0)
    with warnings.catch_warnings():                  # read again at the merge: still ignored, and said once only
        warnings.simplefilter("error")               # (a session-60 review: a second raw warning at the exit)
        m.save()
    again = memo.Memo("t", spec, 2, 1)
    assert again.get((0.1, 0.2)) == (7.0,) and len(again) == 1          # replaced: the damaged rows not merged


def test_with_the_disk_cache_off_nothing_is_written(cache, monkeypatch):
    monkeypatch.setenv("PALPATE_CACHE", "0")
    m = memo.memo("t", {"off": 1}, 1, 1)
    assert m.path is None
    m.put((1.0,), 2.0)
    memo.save_all()
    assert m.get((1.0,)) == (2.0,) and not list(cache.iterdir())


def test_recalled_forces_are_the_models_own(cache, coarse, monkeypatch):
    """Remembered forces and force curves equal a fresh model's bit for bit; after the memo is written and
    forgotten, they come from disk without the model."""
    x, depths = [0.012, 0.035, 0.0551], [0.001, 0.0025, 0.004]
    assert not recall.known(coarse)
    F = [[recall.force_n(coarse, xi, d) for d in depths] for xi in x]
    curve = recall.force_curve_n(coarse, 0.02, np.array(depths))
    memo.forget()
    contact.forget_except(set())              # a fresh model (from the disk cache), not the one that answered
    model = contact.surface_model(coarse)
    assert F == [[model.force_n(xi, d) for d in depths] for xi in x]
    assert curve.tobytes() == model.force_curve_n(0.02, np.array(depths)).tobytes()

    def no_model(*a, **k):
        raise AssertionError("the model was asked")
    monkeypatch.setattr(recall, "surface_model", no_model)
    assert recall.known(coarse)
    assert [[recall.force_n(coarse, xi, d) for d in depths] for xi in x] == F
    assert recall.force_curve_n(coarse, 0.02, depths).tobytes() == curve.tobytes()
    with pytest.raises(AssertionError, match="asked"):        # a new depth on the curve: solved whole
        recall.force_curve_n(coarse, 0.02, depths + [0.005])


def test_the_memo_outlives_the_process(cache, coarse):
    """Written at the process's end (atexit): a second process reads what the first computed."""
    code = ("import sys; from fem import recall, scene as S; sc = S.load('paper').prior().with_analysis("
            "mesh_size_m=0.004); print(recall.known(sc), repr(recall.force_n(sc, 0.03, 0.003)))")
    env = {"PALPATE_CACHE_DIR": str(cache), "PYTHONPATH": str(ROOT), "OPENBLAS_NUM_THREADS": "1"}
    out = [subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
           for _ in range(2)]
    first, second = (o.split() for o in out)
    assert first[0] == "False" and second[0] == "True" and first[1] == second[1]
    assert float(second[1]) == contact.surface_model(coarse).force_n(0.03, 0.003)


def test_recalled_3d_forces_are_the_models_own(cache, monkeypatch):
    """The 3D half (fem.recall3d): the model's forces bit for bit, then from disk without the model; a refused
    indentation raises every time (not remembered)."""
    from fem import contact3d, recall3d
    from fem.contact3d import surface_model3d
    sc = S.Scene(name="t3d", tissue=S.Tissue(width_m=0.03, length_m=0.024, height_m=0.015, youngs_pa=2500.0,
                                             poisson=0.4),
                 indenter=S.Indenter(shape="sphere", radius_m=0.004),
                 analysis=S.Analysis(order=1, mesh_size_m=0.006, surface_refine=2.0, patch_m=0.02,
                                     top_displacement_m=0.001))
    pts = [(0.015, 0.012, 0.0005), (0.017, 0.014, 0.0012)]
    F = [recall3d.force_n(sc, *p) for p in pts]
    memo.forget()
    contact3d._CACHE.clear()                  # a fresh model (from the disk cache), not the one that answered
    model = surface_model3d(sc)
    assert F == [model.force_n(*p) for p in pts] and min(F) > 0
    monkeypatch.setattr(recall3d, "surface_model3d", lambda *a, **k: pytest.fail("the model was asked"))
    assert recall3d.known(sc) and [recall3d.force_n(sc, *p) for p in pts] == F
    assert not recall3d.known(replace_height(sc, 0.016))                          # another scene: nothing known
    monkeypatch.setattr(recall3d, "surface_model3d", lambda *a, **k: model)
    for _ in range(2):
        with pytest.raises(ValueError):
            recall3d.force_n(sc, 0.015, 0.012, 0.004)                         # at the tip radius: refused


def test_a_remembered_truth_still_builds_its_model_first(cache, coarse, monkeypatch):
    """The simulated truth's model is built (or restored) before the run even when its forces are remembered: a
    model that cannot be built now (here: over a lowered DOF budget) stops the run at the start with fem's own error,
    not as a force model that fails mid-run (the simulated arm takes a ValueError there as beyond the model's
    range)."""
    from fem.scene import SceneError
    from robot.simarm import truth_force
    f, _ = truth_force(coarse)
    assert f(0.03, 0.003) == contact.surface_model(coarse).force_n(0.03, 0.003)
    memo.forget()
    contact.forget_except(set())
    assert recall.known(coarse)
    monkeypatch.setenv("PALPATE_MAX_DOFS", "1000")
    with pytest.raises(SceneError, match="DOF"):
        truth_force(coarse)


def test_writers_ending_together_keep_each_others_rows(cache):
    """Two processes write the same memo, the second while the first is between reading the file and writing its
    merge (its write held up 1 s): under the lock the second waits and merges the first's rows; unlocked (checked by
    hand with ``memo.fcntl = None``) the first's write drops the second's rows every time."""
    code = ("import sys, time; from fem import diskcache, memo; k, t0 = int(sys.argv[1]), float(sys.argv[2]); "
            "m = memo.Memo('t', {'race': 1}, 1, 1); [m.put((float(k * 100000 + i),), i) for i in range(5000)]; "
            "w = diskcache.write; diskcache.write = (lambda p, a: (time.sleep(1.0), w(p, a))) if k == 0 else w; "
            "time.sleep(max(0.0, t0 + 0.3 * k - time.time())); m.save()")
    env = {"PALPATE_CACHE_DIR": str(cache), "PYTHONPATH": str(ROOT), "OPENBLAS_NUM_THREADS": "1"}
    t0 = time.time() + 1.5
    ps = [subprocess.Popen([sys.executable, "-c", code, str(k), str(t0)], env=env) for k in (0, 1)]
    assert all(p.wait() == 0 for p in ps)
    memo.forget()
    assert len(memo.Memo("t", {"race": 1}, 1, 1)) == 10000
