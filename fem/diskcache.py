"""A generic disk cache: a content-addressed key -> a dict of numpy arrays, kept between runs.

Knows nothing about meshes or models: callers give a *kind* (the file prefix), a JSON-able *spec* (everything the
arrays depend on, code version included), a builder and the two halves of their serialisation. An entry is one
numpy ``.npz`` file (no pickle) named ``<kind>-<digest of spec>.npz``.

Location: ``$PALPATE_CACHE_DIR`` or ``~/.cache/palpate``; ``PALPATE_CACHE=0`` disables it. Writes are atomic
(temporary file + rename); an unreadable or inconsistent entry is ignored with a warning and rebuilt. A read-only
or full disk only warns.
"""
from __future__ import annotations

import hashlib
import json
import os
import tempfile
import warnings
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np

T = TypeVar("T")
Arrays = dict[str, np.ndarray]

stats: Counter[str] = Counter()   # "<kind>_hit", "<kind>_miss", "corrupt"


def enabled(use: bool | None = None) -> bool:
    """``use`` when given, else $PALPATE_CACHE (on unless 0/false/no/off)."""
    if use is not None:
        return bool(use)
    return os.environ.get("PALPATE_CACHE", "1").strip().lower() not in ("0", "false", "no", "off")


def cache_dir() -> Path:
    d = os.environ.get("PALPATE_CACHE_DIR")
    return Path(d) if d else Path.home() / ".cache" / "palpate"


def digest(spec: dict) -> str:
    """Content-addressed key of a JSON-able dict (key order does not matter)."""
    return hashlib.sha256(json.dumps(spec, sort_keys=True, default=str).encode()).hexdigest()[:20]


def files_digest(paths, extra: str = "") -> str:
    """A hash of some files' bytes (and a string): a code version that changes when the code does."""
    h = hashlib.sha256(extra.encode())
    for p in paths:
        h.update(Path(p).read_bytes())
    return h.hexdigest()[:12]


def entry_path(kind: str, spec: dict) -> Path:
    return cache_dir() / f"{kind}-{digest(spec)}.npz"


def write(path: Path, arrays: Arrays) -> None:
    """Atomic write: a temporary file in the same directory, renamed over the entry."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.stem + ".", suffix=".tmp")
        try:
            with os.fdopen(fd, "wb") as f:
                np.savez(f, **arrays)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    except OSError as e:   # a read-only or full disk must not stop an analysis
        warnings.warn(f"palpate cache: could not write {path}: {e}", stacklevel=3)


def read(path: Path) -> Arrays | None:
    """The arrays of an entry; None when absent or unreadable (with a warning)."""
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except Exception as e:  # noqa: BLE001 - any damage means: ignore the entry and rebuild
        stats["corrupt"] += 1
        warnings.warn(f"palpate cache: ignoring unreadable entry {path} ({type(e).__name__}: {e}); rebuilding",
                      stacklevel=3)
        return None


def load_or_build(kind: str, spec: dict, build: Callable[[], T], to_arrays: Callable[[T], Arrays],
                  from_arrays: Callable[[Arrays], T], use: bool | None = None) -> T:
    """``from_arrays`` of the stored entry, else ``build()`` (stored with ``to_arrays``). ``from_arrays`` raises
    KeyError or ValueError for an entry it cannot use; the entry is then ignored with a warning and rebuilt."""
    if not enabled(use):
        return build()
    path = entry_path(kind, spec)
    arrays = read(path)
    if arrays is not None:
        try:
            obj = from_arrays(arrays)
        except (KeyError, ValueError) as e:
            stats["corrupt"] += 1
            warnings.warn(f"palpate cache: ignoring entry {path} ({type(e).__name__}: {e}); rebuilding",
                          stacklevel=2)
        else:
            stats[f"{kind}_hit"] += 1
            return obj
    stats[f"{kind}_miss"] += 1
    obj = build()
    write(path, to_arrays(obj))
    return obj
