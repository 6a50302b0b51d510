"""How large the disk cache may grow, and what leaves it when it is full: the entries used least recently.

Every entry is derived (a mesh, a factor, remembered forces, a table): removing one costs its rebuild, never a
result. A 3D model with stresses keeps about 2 GB on disk and every change of fem's code makes new keys, so without a
bound the cache grows until the disk is full.

- **Use** is an entry's modification time: ``fem.diskcache`` sets it when it writes an entry and when it reads one
  (``mark_used``), so the oldest time is the entry used least recently.
- **The bound** is ``$PALPATE_CACHE_MAX_BYTES`` (bytes, e.g. ``20e9``; default ``DEFAULT_MAX_BYTES``). After each write
  (``after_write``) the entries used least recently are removed until the cache's entries fit, except what this
  process has read or written (``in_use``): a run never loses what it is working with, so the bound is soft; when
  those alone exceed it a warning says so once.
  Entries used within the last ``RECENT_S`` are spared too (another command or a study's worker is likely using
  them). The directory is listed at most every ``RESCAN_S`` while this process's own estimate of the total (the last
  listing plus what it wrote since) stays within the bound: a study writing thousands of small entries does not list
  a large directory after each.
- **Partial writes** of palpate's own (``<kind>-<key>.<random>.tmp``) older than ``STALE_TMP_S`` are removed by the
  same pass; no other file is touched: only names of the entries' exact form count (``kind_of``), so a cache
  directory shared with other files loses none of them.
- Lock files (fem.memo's ``*.npz.lock``, empty) and resumable builds (``*.parts`` directories) are never removed
  here; ``palpate cache clear`` removes both (a lock file only when no process holds it).

Another process may hold an entry that this one removes: on POSIX an open or memory-mapped file stays readable until
closed (its space is freed only then); one it reads later is a miss, rebuilt. Two processes pruning at once only
remove a little more.
"""
from __future__ import annotations

import math
import os
import re
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

try:
    import fcntl
except ImportError:                   # not POSIX: lock files are never removed
    fcntl = None

ENV = "PALPATE_CACHE_MAX_BYTES"
DEFAULT_MAX_BYTES = 20e9          # about ten 3D models with their stresses (2 GB each), the 2D ones beside them
STALE_TMP_S = 3600.0              # a partial write older than this belongs to a writer that is gone
RECENT_S = 600.0                  # entries used this recently are spared (other processes may be using them)
RESCAN_S = 60.0                   # after a write, the directory is listed again at most this often (within bound)
# <kind>-<16 or 20 hex digits>[-cal-<mesh size>-<grade>].npz (fem.diskcache.entry_path; the surrogate tables and
# the 3D table's mesh calibrations), and their partial writes <entry stem>.<random>.tmp (tempfile.mkstemp)
_ENTRY = re.compile(r"^(?P<kind>[a-z][a-z0-9]*)-(?:[0-9a-f]{20}|[0-9a-f]{16})(?P<cal>-cal-[0-9.e+-]+-[0-9.e+-]+)?"
                    r"\.npz$")
_PARTIAL = re.compile(r"^(?P<stem>[a-z][a-z0-9]*-(?:[0-9a-f]{20}|[0-9a-f]{16})(?:-cal-[0-9.e+-]+-[0-9.e+-]+)?)"
                      r"\.[A-Za-z0-9_]+\.tmp$")
KIND_NAME = re.compile(r"^[a-z][a-z0-9]*(?:-cal)?$")
# Every kind palpate's code writes (tests/test_review_s49.py finds each in the code): `palpate cache clear --kind`
# refuses any other name rather than clear nothing and succeed (a typo such as factor3 would look done)
KINDS = frozenset({"band3d", "factor", "factor3d", "fingerprint", "fingerprint3d", "forces", "forces3d", "hyper",
                   "hypershape", "influence", "mesh", "mesh3d", "surface", "surface3d", "surrogate",
                   "surrogate3d", "surrogate3d-cal", "tip3d"})

_in_use: set[str] = set()         # entries this process read or wrote (never removed by its own pruning)
_warned: set[str] = set()
_scanned: dict[str, tuple[float, int]] = {}   # directory -> (when listed, bytes of entries then + written since)


@dataclass(frozen=True)
class Entry:
    """One cache entry: its file, kind (the name before the key), size and last use (modification time, s since the
    epoch)."""
    path: Path
    kind: str
    size_bytes: int
    used_s: float


@dataclass(frozen=True)
class PruneReport:
    removed: tuple[Entry, ...]     # entries removed, least recently used first
    stale_tmp: tuple[Path, ...]    # partial writes removed
    left_bytes: int                # what the entries take after pruning
    left_entries: int
    in_use_bytes: int              # of that, what the pruning process holds (kept whatever the bound)


def max_bytes() -> float:
    """The bound from $PALPATE_CACHE_MAX_BYTES (a number of bytes, >= 0), else DEFAULT_MAX_BYTES; ValueError naming
    the variable for anything else."""
    text = os.environ.get(ENV)
    if text is None or not text.strip():
        return DEFAULT_MAX_BYTES
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not (math.isfinite(v) and v >= 0):
        raise ValueError(f"{ENV}={text!r}: give the disk cache's size bound in bytes, a finite number >= 0 "
                         "(e.g. 20e9 for 20 GB; unset: 20e9)")
    return v


def size_text(n: float) -> str:
    """A size in bytes as a person reads it (GB from 10 MB, else MB; decimal units)."""
    n = n + 0.0                  # (-0, a bound given as "-0", reads 0.00 MB)
    return f"{n / 1e9:.2f} GB" if n >= 1e7 else f"{n / 1e6:.2f} MB"


def kind_of(path: Path) -> str | None:
    """The kind of an entry's file name (``<kind>-<hex key>.npz``), None for any other file."""
    m = _ENTRY.match(path.name)
    return None if m is None else m.group("kind") + ("-cal" if m.group("cal") else "")


def entries(root: Path) -> list[Entry]:
    """The entries in ``root``, least recently used first (none when it does not exist)."""
    out = []
    try:
        items = list(os.scandir(root))
    except FileNotFoundError:
        return []
    for d in items:
        kind = kind_of(Path(d.name))
        if kind is None:
            continue
        try:
            if not d.is_file(follow_symlinks=False):
                continue
            st = d.stat(follow_symlinks=False)
        except FileNotFoundError:          # removed meanwhile by another process
            continue
        out.append(Entry(Path(d.path), kind, int(st.st_size), float(st.st_mtime)))
    out.sort(key=lambda e: (e.used_s, e.path.name))
    return out


def partial_writes(root: Path, older_than_s: float = STALE_TMP_S, now: float | None = None) -> list[Path]:
    """palpate's partial writes (``<entry stem>.<random>.tmp`` files) in ``root`` last touched more than
    ``older_than_s`` ago."""
    now = time.time() if now is None else now
    out = []
    for p in root.glob("*.tmp") if root.is_dir() else ():
        try:
            if _PARTIAL.match(p.name) and p.is_file() and not p.is_symlink() and now - p.stat().st_mtime > older_than_s:
                out.append(p)
        except FileNotFoundError:
            continue
    return sorted(out)


def mark_used(path: Path) -> None:
    """``path`` (an entry just read or written) is in use by this process and now its most recently used entry. A
    cache on a read-only file system keeps its old times."""
    _in_use.add(os.fspath(path))
    try:
        os.utime(path)
    except OSError:
        pass


def remove_lock(path: Path) -> bool:
    """Remove a lock file (fem.memo's) unless a process holds it (taken without waiting first; where there is no
    flock, kept). Whether it is gone."""
    if fcntl is None:
        return False
    try:
        with open(path, "a") as f:
            try:
                fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                return False                # held: a memo merge is running
            return remove(path)
    except FileNotFoundError:
        return True
    except OSError:
        return False


def remove(path: Path) -> bool:
    """Whether ``path`` is gone (removed now, or by another process first)."""
    try:
        path.unlink()
    except FileNotFoundError:
        pass
    except OSError as e:                   # read-only, or held open where that forbids it
        warnings.warn(f"palpate cache: could not remove {path}: {e}", stacklevel=3)
        return False
    return True


def prune(root: Path, limit_bytes: float, keep=None, now: float | None = None,
          recent_s: float = 0.0) -> PruneReport:
    """Remove the entries of ``root`` used least recently until the rest take at most ``limit_bytes``, sparing
    ``keep`` (paths; default: what this process has in use) and entries used within ``recent_s``; and partial writes
    older than STALE_TMP_S."""
    keep = _in_use if keep is None else {os.fspath(p) for p in keep}
    now = time.time() if now is None else now
    stale = tuple(p for p in partial_writes(root, now=now) if remove(p))
    ents = entries(root)
    total = sum(e.size_bytes for e in ents)
    removed, left = [], []
    for e in ents:
        spared = os.fspath(e.path) in keep or now - e.used_s < recent_s
        if total > limit_bytes and not spared and remove(e.path):
            removed.append(e)
            total -= e.size_bytes
        else:
            left.append(e)
    return PruneReport(tuple(removed), stale, total, len(left),
                       sum(e.size_bytes for e in left if os.fspath(e.path) in keep))


def after_write(path: Path) -> PruneReport | None:
    """After ``path`` was written to the cache: mark it used, and prune the cache to its bound (sparing what this
    process uses and what was used within RECENT_S) unless it was listed less than RESCAN_S ago and this process's
    estimate of its size (that listing plus what it wrote since) is within the bound (None then); warn once per
    cache directory when the spared entries alone exceed the bound."""
    mark_used(path)
    limit = max_bytes()
    d = os.fspath(path.parent)
    try:
        size = path.stat().st_size
    except OSError:
        size = 0
    when, total = _scanned.get(d, (-math.inf, 0))
    now = time.time()
    if total + size <= limit and now - when < RESCAN_S:
        _scanned[d] = (when, total + size)
        return None
    report = prune(path.parent, limit, now=now, recent_s=RECENT_S)
    _scanned[d] = (now, report.left_bytes)
    if report.left_bytes > limit and d not in _warned:
        _warned.add(d)
        warnings.warn(f"palpate cache: {path.parent} holds {size_text(report.left_bytes)}, above its bound of "
                      f"{size_text(limit)} ({ENV}); {size_text(report.in_use_bytes)} of it in use by this process "
                      f"and the rest used within the last {RECENT_S / 60:g} minutes (kept): raise the bound or expect "
                      f"rebuilds", stacklevel=3)
    return report
