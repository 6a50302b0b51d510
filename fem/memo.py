"""What fem computed before for the same question, kept between runs: a memo of float keys -> float rows on disk.

A run asks fem the same things as the run before it: the prior tissue's force curve at each probe position (the
localizer's tables), its force at each candidate of the refinement's design, the simulated truth's force on its
depth grid; 3,000 to 4,000 contact solves (0.6 s) in ``palpate run paper --sim``. A ``Memo`` keeps each answer
exactly as computed (the same float64 bits) under its exact key (floats: a position, a depth), in memory and, with
the disk cache on, in one file per question and model (``fem.diskcache``: ``<kind>-<digest of spec>.npz``, the
spec naming the model's content and the code that computes the answer). An entry is a function of its spec and key
on one machine's libraries, so reading it back is the same as computing it again (as for the disk cache's operators,
whose keys do not name scipy's or the BLAS's build either: a cache directory shared between machines, or kept across
a library upgrade, may hold either build's round-off).

Files are written when the process ends (and when a memo leaves the in-memory registry): merged with what another
process wrote meanwhile, under an exclusive lock on ``<file>.lock`` (POSIX ``flock``; where there is none, two
processes ending at the same moment may each write over the other's merge), atomically, the newest ``MAX_ROWS``
kept. A process that ends without running its exit handlers (a forked child's ``os._exit``, a kill) writes
nothing. Either loses entries, never correctness: they are computed again. A damaged
or inconsistent file (not finite, wrong shapes) is ignored with a warning and replaced at the next write;
``PALPATE_CACHE=0`` keeps memos in memory only.

Used by the callers that ask the same questions run after run (fem.recall, fem.recall3d), not by fem's own queries:
``SurfaceModel.force_n`` always solves (``palpate predict`` and the benchmarks time the solver).
"""
from __future__ import annotations

import atexit
import contextlib
import math
import os
import warnings
from collections import OrderedDict
from pathlib import Path

import numpy as np

from . import diskcache

try:
    import fcntl
except ImportError:                 # not POSIX: merges unlocked (see the module)
    fcntl = None

MAX_ROWS = 20_000           # per file: a paper run adds about 1,500 to each of its prior's memos the first time
MAX_OPEN = 16               # memos kept in memory (a study's truths each have their own)

Key = tuple[float, ...]
Row = tuple[float, ...]


class Memo:
    """Rows of ``width`` floats under keys of ``n_key`` floats, for one ``kind`` and ``spec`` (see the module)."""

    def __init__(self, kind: str, spec: dict, n_key: int, width: int):
        self.kind, self.spec, self.n_key, self.width = kind, spec, n_key, width
        self.path = diskcache.entry_path(kind, spec) if diskcache.enabled() else None
        self.digest = diskcache.digest(spec)    # written into the file and checked on reading (its name's digest)
        self._said_ignored = False               # a file ignored is said once (not again at the merge of save())
        self._rows: dict[Key, Row] | None = None
        self._new: dict[Key, Row] = {}
        self._used: set[Key] = set()         # keys read back here: kept before the others when a file is trimmed

    def _load(self) -> dict[Key, Row]:
        if self._rows is None:
            self._rows = self._read()
        return self._rows

    def _read(self) -> dict[Key, Row]:
        arrays = diskcache.read(self.path) if self.path is not None else None
        if arrays is None:
            self._said_ignored |= self.path is not None and self.path.exists()   # unreadable: diskcache said so
            return {}
        try:
            keys, rows = arrays["keys"], arrays["rows"]
            if str(arrays["digest"]) != self.digest:     # another entry's rows under this name (copied, swapped)
                raise ValueError(f"it holds the rows of entry {str(arrays['digest'])!r}, not of {self.digest!r}")
            if (keys.ndim != 2 or rows.ndim != 2 or keys.shape != (len(rows), self.n_key)
                    or rows.shape[1] != self.width or keys.dtype != np.float64 or rows.dtype != np.float64):
                raise ValueError(f"keys {keys.shape} {keys.dtype}, rows {rows.shape} {rows.dtype}: expected "
                                 f"(n, {self.n_key}) and (n, {self.width}) float64")
            if not (np.isfinite(keys).all() and np.isfinite(rows).all()):
                raise ValueError("an entry is not finite")
        except (KeyError, ValueError) as e:
            diskcache.stats["corrupt"] += 1
            if not self._said_ignored:
                warnings.warn(f"palpate cache: ignoring memo {self.path} ({type(e).__name__}: {e})", stacklevel=4)
            self._said_ignored = True
            return {}
        diskcache.stats[f"{self.kind}_read"] += 1
        return dict(zip(map(tuple, keys.tolist()), map(tuple, rows.tolist())))

    def __len__(self) -> int:
        return len(self._load())

    def get(self, key: Key) -> Row | None:
        """The row stored under ``key`` (None when absent)."""
        row = self._load().get(key)
        if row is not None:
            self._used.add(key)
        return row

    def put(self, key: Key, row) -> None:
        """Store ``row`` (``width`` finite floats) under ``key``."""
        row = tuple(float(v) for v in np.ravel(row))
        if len(row) != self.width or not all(map(math.isfinite, row)):
            raise ValueError(f"memo {self.kind}: a row must be {self.width} finite floats, got {row}")
        rows = self._load()
        rows[key] = row
        self._new[key] = row
        _DIRTY.add(self)
        if len(rows) > 2 * MAX_ROWS:         # a long process (a serial study): written, then the newest kept
            self.save()
            for k in list(rows)[:len(rows) - MAX_ROWS]:
                del rows[k]
            self._used &= rows.keys()

    def save(self) -> None:
        """Write the entries this process added, merged with the file as it is now; beyond MAX_ROWS the oldest go
        first of those neither added nor read back here, then of those only added, then of those read back."""
        _DIRTY.discard(self)
        if self.path is None or not self._new:
            return
        with _locked(self.path), warnings.catch_warnings():
            if self._said_ignored:                   # the file this process found unusable: said once, on reading
                warnings.simplefilter("ignore")
            merged = self._read()
            merged.update(self._new)
            keys = list(merged)
            if len(keys) > MAX_ROWS:
                rank = {k: 1 for k in self._new} | {k: 2 for k in self._used}
                keys = sorted(keys, key=lambda k: rank.get(k, 0))[-MAX_ROWS:]     # (stable: the oldest first)
            diskcache.write(self.path, {"digest": np.array(self.digest),
                                        "keys": np.array(keys, dtype=np.float64).reshape(len(keys), self.n_key),
                                        "rows": np.array([merged[k] for k in keys], dtype=np.float64)
                                        .reshape(len(keys), self.width)})
        self._new = {}


@contextlib.contextmanager
def _locked(path: Path):
    """An exclusive lock on ``path``'s lock file while a merge reads and writes it (none where flock is missing or
    the lock file cannot be made: a read-only cache only warns when written, as diskcache does)."""
    if fcntl is None:
        yield
        return
    lock = path.with_name(path.name + ".lock")
    for _ in range(100):
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            f = open(lock, "a")
        except OSError:
            yield
            return
        with f:
            try:
                fcntl.flock(f, fcntl.LOCK_EX)
            except OSError as e:            # a file system without locks (some NFS mounts): merged unlocked
                warnings.warn(f"palpate cache: could not lock {f.name} ({e}); merging without the lock",
                              stacklevel=4)
                yield
                return
            if _same_file(f, lock):         # not removed (``palpate cache clear``) while this process waited
                yield
                return
    raise RuntimeError(f"palpate cache: {lock} kept being replaced; cannot lock it")


def _same_file(f, path: Path) -> bool:
    """Whether the open file ``f`` is still the file at ``path`` (a lock taken on a removed file locks nothing)."""
    try:
        a, b = os.fstat(f.fileno()), os.stat(path)
    except OSError:
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


_OPEN: OrderedDict[tuple, Memo] = OrderedDict()
_DIRTY: set[Memo] = set()


def memo(kind: str, spec: dict, n_key: int, width: int) -> Memo:
    """The memo of ``kind`` and ``spec`` (a flat dict of strings and numbers) in the disk cache as configured now:
    one object per process while among the MAX_OPEN most recently asked for (one leaving is written first)."""
    name = (kind, tuple(sorted(spec.items())), n_key, width, diskcache.enabled(), os.environ.get("PALPATE_CACHE_DIR"))
    m = _OPEN.get(name)
    if m is None:
        m = _OPEN[name] = Memo(kind, spec, n_key, width)
        while len(_OPEN) > MAX_OPEN:
            _OPEN.popitem(last=False)[1].save()
    else:
        _OPEN.move_to_end(name)
    return m


def save_all() -> None:
    """Write every memo with new entries (at the process's end; a test or a long study may call it earlier)."""
    for m in list(_DIRTY):
        m.save()


def forget() -> None:
    """Drop the memos from memory (written first): the next question reads the files again."""
    save_all()
    _OPEN.clear()


def _save_at_exit() -> None:
    """``save_all`` at the process's end; a Ctrl-C there (a second one: the first ended the command) leaves what is
    not yet written unwritten -- a cache, remade on demand, each file written whole or not at all (diskcache) --
    instead of a traceback after the command's one line (session 56's review)."""
    try:
        save_all()
    except KeyboardInterrupt:
        pass


atexit.register(_save_at_exit)
