"""The disk cache's size bound (fem.cachesize, used by fem.diskcache) and `palpate cache`: the entries used least
recently go first, what the writing process uses is kept, reads mark use (not of files outside the cache), partial
writes of dead writers go, the bound is read from the environment or refused with one line."""
from __future__ import annotations

import json
import os
import time
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from app.cli import main
from fem import cachesize, diskcache


@pytest.fixture
def cdir(tmp_path, monkeypatch):
    d = tmp_path / "cache"
    d.mkdir()
    monkeypatch.setenv("PALPATE_CACHE_DIR", str(d))
    monkeypatch.delenv("PALPATE_CACHE", raising=False)
    monkeypatch.delenv(cachesize.ENV, raising=False)
    monkeypatch.setattr(cachesize, "_in_use", set())
    monkeypatch.setattr(cachesize, "_warned", set())
    monkeypatch.setattr(cachesize, "_scanned", {})
    return d


def _entry(d, kind: str, key: int, size: int, age_s: float, now: float):
    """A fake entry file of ``size`` bytes last used ``age_s`` before ``now``."""
    p = d / f"{kind}-{key:020x}.npz"
    p.write_bytes(b"x" * size)
    os.utime(p, (now - age_s, now - age_s))
    return p


def test_prune_removes_least_recently_used_first_and_spares_what_is_kept(cdir):
    now = time.time()
    ps = [_entry(cdir, "mesh", i, 100, age_s=1000 - 10 * i, now=now) for i in range(10)]   # ps[0] the oldest
    r = cachesize.prune(cdir, 650, keep={ps[0]})
    # 1000 bytes, bound 650: four go, the oldest but ps[0] (kept)
    assert [e.path for e in r.removed] == ps[1:5]
    assert r.left_bytes == 600 and r.left_entries == 6 and r.in_use_bytes == 100
    assert sorted(p.name for p in cdir.iterdir()) == sorted(p.name for p in [ps[0], *ps[5:]])
    assert cachesize.prune(cdir, 650, keep=()).removed == ()                  # within the bound: nothing more


def test_the_bound_cannot_remove_what_is_kept(cdir):
    now = time.time()
    ps = [_entry(cdir, "surface3d", i, 500, age_s=100 - i, now=now) for i in range(3)]
    r = cachesize.prune(cdir, 0, keep=set(ps))
    assert r.removed == () and r.left_bytes == 1500 and r.in_use_bytes == 1500
    assert all(p.exists() for p in ps)


def test_a_write_prunes_the_others_and_warns_once_when_its_own_exceed_the_bound(cdir, monkeypatch):
    now = time.time()
    old = [_entry(cdir, "mesh", i, 4000, age_s=3600 + i, now=now) for i in range(3)]
    monkeypatch.setenv(cachesize.ENV, "6000")
    a = {"x": np.arange(100.0)}                                    # about 1 kB as .npz
    with warnings.catch_warnings():
        warnings.simplefilter("error")                              # within the bound: no warning
        diskcache.write(diskcache.entry_path("k1", {"a": 1}), a)
    # 12 kB + 1 kB over 6 kB: the two oldest go (the newest of the old, 4 kB, stays)
    assert [p.exists() for p in old] == [True, False, False]
    monkeypatch.setenv(cachesize.ENV, "100")
    with pytest.warns(UserWarning, match="above its bound.*in use by this process"):
        diskcache.write(diskcache.entry_path("k2", {"a": 2}), a)
    assert not old[0].exists()                                     # not in use: removed
    left = sorted(p.name.split("-")[0] for p in cdir.glob("*.npz"))
    assert left == ["k1", "k2"]                                    # this process's own are kept
    with warnings.catch_warnings():
        warnings.simplefilter("error")                              # warned once per directory
        diskcache.write(diskcache.entry_path("k3", {"a": 3}), a)


def test_reading_an_entry_marks_it_used_but_not_a_file_outside_the_cache(cdir, tmp_path):
    p = diskcache.entry_path("mesh", {"n": 1})
    diskcache.write(p, {"x": np.zeros(3)})
    os.utime(p, (1e9, 1e9))
    cachesize._in_use.clear()
    assert diskcache.read(p) is not None
    assert p.stat().st_mtime > time.time() - 60 and os.fspath(p) in cachesize._in_use
    os.utime(p, (1e9, 1e9))
    assert diskcache.read(p, mmap=True) is not None and p.stat().st_mtime > 1e9
    shipped = tmp_path / "data" / "surrogate-0123456789abcdef.npz"          # e.g. a table shipped with the source
    shipped.parent.mkdir()
    np.savez(shipped, x=np.zeros(2))
    os.utime(shipped, (1e9, 1e9))
    assert diskcache.read(shipped) is not None
    assert shipped.stat().st_mtime == 1e9 and os.fspath(shipped) not in cachesize._in_use


def test_an_entry_removed_before_it_is_opened_is_a_quiet_miss(cdir, monkeypatch):
    p = diskcache.entry_path("mesh", {"n": 2})
    diskcache.write(p, {"x": np.zeros(3)})

    def gone(path):
        raise FileNotFoundError(path)
    monkeypatch.setattr(diskcache, "_mapped", gone)
    corrupt = diskcache.stats["corrupt"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert diskcache.read(p, mmap=True) is None
    assert diskcache.stats["corrupt"] == corrupt


def test_partial_writes_of_dead_writers_go_and_nothing_else(cdir):
    now = time.time()
    key = f"{7:020x}"
    dead, live = cdir / f"factor3d-{key}.x1ab_9.tmp", cdir / f"factor3d-{key}.x2cd.tmp"
    foreign = [cdir / "firefox-download.tmp", cdir / f"mesh-{key}.tmp", cdir / "notes-0123456789abcdef0123.tmp"]
    for p, age in [(dead, cachesize.STALE_TMP_S + 60), (live, 5)] + [(f, 10 * cachesize.STALE_TMP_S) for f in foreign]:
        p.write_bytes(b"y" * 10)
        os.utime(p, (now - age, now - age))
    (cdir / f"surface-{key}.zz.tmp").mkdir()                       # a directory of that name: not ours to remove
    os.utime(cdir / f"surface-{key}.zz.tmp", (now - 1e5, now - 1e5))
    r = cachesize.prune(cdir, 0, keep=())
    assert r.stale_tmp == (dead,) and not dead.exists() and live.exists()
    assert all(f.exists() for f in foreign) and (cdir / f"surface-{key}.zz.tmp").is_dir()


def test_only_entry_files_count(cdir):
    now = time.time()
    e = _entry(cdir, "forces", 7, 50, 10, now)
    cal = cdir / "surrogate3d-0123456789abcdef-cal-0.004-1.5.npz"     # the 3D table's mesh calibration
    cal.write_bytes(b"c" * 30)
    (cdir / (e.name + ".lock")).write_bytes(b"")
    (cdir / f"mesh-{1:020x}.npz").mkdir()                            # a directory named like an entry
    user = ["scan-202401011200.npz", "run-20240101-123456789012.npz", "Mesh-0123456789abcdef.npz", "notes.txt",
            "x-0123456789abcdef0.npz"]
    for name in user:
        (cdir / name).write_text("mine")
    assert sorted((x.kind, x.size_bytes) for x in cachesize.entries(cdir)) == [("forces", 50), ("surrogate3d-cal", 30)]
    cachesize.prune(cdir, 0, keep=())
    assert not e.exists() and not cal.exists() and (cdir / (e.name + ".lock")).exists()
    assert all((cdir / name).exists() for name in user) and (cdir / f"mesh-{1:020x}.npz").is_dir()


def test_entries_used_recently_by_any_process_are_spared_after_a_write(cdir, monkeypatch):
    now = time.time()
    recent = _entry(cdir, "surface", 1, 5000, cachesize.RECENT_S / 2, now)       # another command's, just used
    old = _entry(cdir, "surface", 2, 5000, 2 * cachesize.RECENT_S, now)
    monkeypatch.setenv(cachesize.ENV, "3000")
    with pytest.warns(UserWarning, match="used within the last"):
        diskcache.write(diskcache.entry_path("k", {"a": 1}), {"x": np.zeros(10)})
    assert recent.exists() and not old.exists()


def test_a_directory_within_its_bound_is_listed_once_per_rescan_interval(cdir, monkeypatch):
    calls = []
    real = cachesize.entries
    monkeypatch.setattr(cachesize, "entries", lambda root: calls.append(root) or real(root))
    for i in range(20):
        diskcache.write(diskcache.entry_path("k", {"i": i}), {"x": np.zeros(10)})
    assert len(calls) == 1                                          # 20 writes, one listing
    monkeypatch.setenv(cachesize.ENV, "1")                          # over the bound: every write lists and prunes
    with pytest.warns(UserWarning, match="above its bound"):
        diskcache.write(diskcache.entry_path("k", {"i": 20}), {"x": np.zeros(10)})
    diskcache.write(diskcache.entry_path("k", {"i": 21}), {"x": np.zeros(10)})
    assert len(calls) == 3
    monkeypatch.setenv(cachesize.ENV, "1e12")
    monkeypatch.setattr(cachesize, "_scanned", {str(cdir): (time.time() - cachesize.RESCAN_S - 1, 0)})
    diskcache.write(diskcache.entry_path("k", {"i": 22}), {"x": np.zeros(10)})
    assert len(calls) == 4                                          # the interval passed: listed again


def test_remove_lock_spares_a_held_lock(cdir):
    import fcntl
    lock = cdir / f"forces-{3:020x}.npz.lock"
    lock.write_bytes(b"")
    with open(lock, "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        assert not cachesize.remove_lock(lock) and lock.exists()
    assert cachesize.remove_lock(lock) and not lock.exists()


@pytest.mark.parametrize("text", ["abc", "-1", "nan", "inf", "1e9 bytes"])
def test_a_bad_bound_is_refused_naming_the_variable(monkeypatch, text):
    monkeypatch.setenv(cachesize.ENV, text)
    with pytest.raises(ValueError, match=f"{cachesize.ENV}=.*bytes"):
        cachesize.max_bytes()


@pytest.mark.parametrize("text, value", [("5e9", 5e9), ("0", 0.0), ("  ", cachesize.DEFAULT_MAX_BYTES),
                                         ("123456", 123456.0)])
def test_the_bound_from_the_environment(monkeypatch, text, value):
    monkeypatch.setenv(cachesize.ENV, text)
    assert cachesize.max_bytes() == value


@settings(max_examples=200, deadline=None)
@given(sizes=st.lists(st.integers(0, 1000), min_size=0, max_size=12), limit=st.integers(0, 8000),
       data=st.data())
def test_prune_property(tmp_path_factory, sizes, limit, data):
    """Whatever the sizes, ages and kept set: nothing kept goes; the rest fits the bound unless only kept entries
    are left to remove; what goes is never more recently used than an unkept entry that stays; pruning stops as soon
    as the bound is met."""
    d = tmp_path_factory.mktemp("c")
    now = time.time()
    ages = data.draw(st.lists(st.integers(1, 10 ** 6), min_size=len(sizes), max_size=len(sizes), unique=True))
    ps = [_entry(d, "k", i, s, a, now) for i, (s, a) in enumerate(zip(sizes, ages))]
    keep = set(data.draw(st.lists(st.sampled_from(ps), unique=True)) if ps else [])
    r = cachesize.prune(d, limit, keep=keep)
    gone = {e.path for e in r.removed}
    assert not gone & keep and all(not p.exists() for p in gone)
    left = [p for p in ps if p not in gone]
    assert r.left_bytes == sum(p.stat().st_size for p in left)
    assert r.left_bytes <= limit or all(p in keep for p in left)
    used = {p: now - a for p, a in zip(ps, ages)}
    stay = [used[p] for p in left if p not in keep]
    assert all(used[p] < min(stay) for p in gone) if stay and gone else True
    if r.removed:           # before the last removal the rest did not fit
        assert r.left_bytes + r.removed[-1].size_bytes > limit


def test_cli_lists_prunes_and_clears(cdir, capsys, tmp_path):
    now = time.time()
    m = [_entry(cdir, "mesh", i, 1000, 100 + i, now) for i in range(3)]
    f = [_entry(cdir, "factor3d", i, 5000, 10 + i, now) for i in range(2)]
    (cdir / (f[0].name + ".lock")).write_bytes(b"")
    out = tmp_path / "list.json"
    assert main(["cache", "--json", str(out), "--entries"]) == 0
    d = json.loads(out.read_text())
    assert d["entries"] == 5 and d["total_bytes"] == 13000
    assert d["kinds"]["mesh"] == {**d["kinds"]["mesh"], "entries": 3, "size_bytes": 3000}
    assert d["kinds"]["factor3d"]["size_bytes"] == 10000 and len(d["entry_list"]) == 5
    assert "factor3d" in capsys.readouterr().out
    # prune to 11 kB: the three meshes (the least recently used) go first, two of them suffice
    assert main(["cache", "prune", "--max-bytes", "11000", "--json", str(out)]) == 0
    d = json.loads(out.read_text())
    assert [os.path.basename(e["path"]) for e in d["removed"]] == [m[2].name, m[1].name]
    assert d["left_bytes"] == 11000 and m[0].exists()
    assert main(["cache", "clear", "--kind", "factor3d"]) == 0
    assert not any(p.exists() for p in f) and not (cdir / (f[0].name + ".lock")).exists() and m[0].exists()
    capsys.readouterr()
    assert main(["cache", "clear", "--kind", "factor3d"]) == 0                  # again: nothing left, not an error
    assert "no entries of kind factor3d (present: mesh)" in capsys.readouterr().out
    import fcntl
    held, orphan = cdir / (m[0].name + ".lock"), cdir / f"forces-{9:020x}.npz.lock"
    held.write_bytes(b"")
    orphan.write_bytes(b"")
    parts = cdir / f"surrogate-{5:016x}.parts"
    parts.mkdir()
    (parts / "stone_001.npz").write_bytes(b"p" * 100)
    mine = cdir / "notes.parts"                                               # not a table build's name
    mine.mkdir()
    with open(held, "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)                                        # a memo merge running
        assert main(["cache", "clear", "--json", str(out)]) == 0
    d = json.loads(out.read_text())
    assert not list(cdir.glob("*.npz")) and not parts.exists() and not orphan.exists() and mine.is_dir()
    assert held.exists() and d["lock_files_held"] == [str(held)] and d["resumable_builds_removed"] == [str(parts)]


@pytest.mark.parametrize("argv, env, needle", [
    (["cache", "clear", "--kind", "Factor3D"], {}, "--kind 'Factor3D': a kind is a lower-case name"),
    (["cache", "prune", "--max-bytes", "-5"], {}, "--max-bytes"),
    (["cache", "--kind", "mesh"], {}, "--kind mesh: only for `palpate cache clear`"),
    (["cache", "clear", "--max-bytes", "5"], {}, "--max-bytes 5: only for `palpate cache prune`"),
    (["cache"], {cachesize.ENV: "lots"}, f"{cachesize.ENV}='lots'"),
    (["cache"], {"PALPATE_CACHE": "of"}, "PALPATE_CACHE='of'"),
    (["plan", "paper", "--out", "PLAN"], {cachesize.ENV: "lots"}, f"{cachesize.ENV}='lots'"),   # any command
    (["plan", "paper", "--out", "PLAN"], {"PALPATE_CACHE_DIR": "FILE"}, "PALPATE_CACHE_DIR="),
])
def test_cli_bad_input_is_one_line_and_exit_2(cdir, capsys, monkeypatch, tmp_path, argv, env, needle):
    _entry(cdir, "mesh", 1, 10, 10, time.time())
    (tmp_path / "FILE").write_text("not a directory")
    argv = [str(tmp_path / "plan.json") if a == "PLAN" else a for a in argv]
    for k, v in env.items():
        monkeypatch.setenv(k, str(tmp_path / v) if v == "FILE" else v)
    assert main(argv) == 2
    assert not (tmp_path / "plan.json").exists()
    err = capsys.readouterr().err.strip()
    assert needle in err and len(err.splitlines()) == 1 and "Traceback" not in err


def test_a_memo_lock_removed_while_waited_for_is_taken_again(cdir):
    """A merge waiting on a lock file that `palpate cache clear` removed must not lock the removed file (a second
    merge would lock the new one and both would run): it locks the file now at the path."""
    import fcntl
    import threading

    from fem import memo
    entry = cdir / f"forces-{4:020x}.npz"
    lock = cdir / (entry.name + ".lock")
    holder = open(lock, "a")
    fcntl.flock(holder, fcntl.LOCK_EX)                  # a first merge holds the lock
    inside = threading.Event()

    def waiter():
        with memo._locked(entry):
            inside.set()
            time.sleep(0.3)
    t = threading.Thread(target=waiter)
    t.start()
    time.sleep(0.2)                                     # the waiter is blocked on the first file
    lock.unlink()                                       # removed meanwhile (as a clear racing the merge would)
    fcntl.flock(holder, fcntl.LOCK_UN)
    holder.close()
    assert inside.wait(5)
    probe = open(lock, "a")                             # the file now at the path: held by the waiter
    with pytest.raises(OSError):
        fcntl.flock(probe, fcntl.LOCK_EX | fcntl.LOCK_NB)
    t.join()
    fcntl.flock(probe, fcntl.LOCK_EX | fcntl.LOCK_NB)   # released after
    probe.close()


def test_clear_leaves_lock_files_that_are_not_palpates(cdir):
    (cdir / "mydata.npz").write_bytes(b"d")
    (cdir / "mydata.npz.lock").write_bytes(b"")
    (cdir / f"forces-{5:020x}.npz.lock").write_bytes(b"")
    assert main(["cache", "clear"]) == 0
    assert sorted(p.name for p in cdir.iterdir()) == ["mydata.npz", "mydata.npz.lock"]
