"""A generic disk cache: a content-addressed key -> a dict of numpy arrays, kept between runs.

Knows nothing about meshes or models: callers give a *kind* (the file prefix), a JSON-able *spec* (everything the
arrays depend on, code version included), a builder and the two halves of their serialisation. An entry is one
numpy ``.npz`` file (no pickle) named ``<kind>-<digest of spec>.npz``.

Location: ``$PALPATE_CACHE_DIR`` or ``~/.cache/palpate``; ``PALPATE_CACHE=0`` disables it. Writes are atomic
(temporary file + rename); an unreadable or inconsistent entry is ignored with a warning and rebuilt. A read-only
or full disk only warns. Its size is bounded (``$PALPATE_CACHE_MAX_BYTES``): reading or writing an entry marks it
used, and after a write the entries used least recently go (fem.cachesize).
"""
from __future__ import annotations

import hashlib
import json
import os
import tempfile
import warnings
import zipfile
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np

from fem import cachesize

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
        return
    if _in_cache(path):
        try:
            cachesize.after_write(path)
        except ValueError as e:            # a bad bound: the entry is kept, nothing is removed
            warnings.warn(f"palpate cache: not pruned: {e}", stacklevel=3)


def _in_cache(path: Path) -> bool:
    """Whether ``path`` is an entry of the cache directory (not, e.g., a table shipped with the source)."""
    return path.parent == cache_dir()


def _mapped(path: Path) -> Arrays:
    """The arrays of an uncompressed .npz (what ``write`` makes) as read-only memory maps: nothing is read until
    used, so a large operator of which a run touches a part costs only that part. Each member's bytes are contiguous
    in the file (stored, not deflated); its .npy header gives dtype, shape and order."""
    out = {}
    with zipfile.ZipFile(path) as zf, open(path, "rb") as f:
        for info in zf.infolist():
            if info.compress_type != zipfile.ZIP_STORED or not info.filename.endswith(".npy"):
                raise ValueError(f"member {info.filename} is not a stored .npy")
            f.seek(info.header_offset)
            local = f.read(30)
            name_len, extra_len = int.from_bytes(local[26:28], "little"), int.from_bytes(local[28:30], "little")
            f.seek(info.header_offset + 30 + name_len + extra_len)
            version = np.lib.format.read_magic(f)
            shape, fortran, dtype = (np.lib.format.read_array_header_1_0(f) if version == (1, 0) else
                                     np.lib.format.read_array_header_2_0(f))
            if dtype.hasobject:
                raise ValueError(f"member {info.filename} holds Python objects")
            key = info.filename[:-4]
            if int(np.prod(shape)) == 0:
                out[key] = np.zeros(shape, dtype)
            else:
                out[key] = np.memmap(path, dtype=dtype, mode="r", offset=f.tell(), shape=shape,
                                     order="F" if fortran else "C")
    return out


def read(path: Path, mmap: bool = False) -> Arrays | None:
    """The arrays of an entry (memory-mapped when ``mmap``); None when absent or unreadable (with a warning)."""
    if not path.exists():
        return None
    try:
        if mmap:
            arrays = _mapped(path)
        else:
            with np.load(path, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
    except FileNotFoundError:   # removed since (another process pruning the cache): a miss
        return None
    except Exception as e:  # noqa: BLE001 - any damage means: ignore the entry and rebuild
        stats["corrupt"] += 1
        warnings.warn(f"palpate cache: ignoring unreadable entry {path} ({type(e).__name__}: {e}); rebuilding",
                      stacklevel=3)
        return None
    if _in_cache(path):
        cachesize.mark_used(path)
    return arrays


def load_or_build(kind: str, spec: dict, build: Callable[[], T], to_arrays: Callable[[T], Arrays],
                  from_arrays: Callable[[Arrays], T], use: bool | None = None, mmap: bool = False) -> T:
    """``from_arrays`` of the stored entry, else ``build()`` (stored with ``to_arrays``). ``from_arrays`` raises
    KeyError or ValueError for an entry it cannot use; the entry is then ignored with a warning and rebuilt.
    ``mmap``: hand ``from_arrays`` read-only memory maps of the stored arrays (large operators read in part)."""
    if not enabled(use):
        return build()
    obj = load(kind, spec, from_arrays, use=use, mmap=mmap)
    if obj is not None:
        return obj
    stats[f"{kind}_miss"] += 1
    obj = build()
    write(entry_path(kind, spec), to_arrays(obj))
    return obj


def load(kind: str, spec: dict, from_arrays: Callable[[Arrays], T], use: bool | None = None,
         mmap: bool = False) -> T | None:
    """``from_arrays`` of the stored entry, or None when there is none (or it cannot be used: then with a
    warning, as in ``load_or_build``)."""
    if not enabled(use):
        return None
    path = entry_path(kind, spec)
    arrays = read(path, mmap=mmap)
    if arrays is None:
        return None
    try:
        obj = from_arrays(arrays)
    except (KeyError, ValueError) as e:
        stats["corrupt"] += 1
        warnings.warn(f"palpate cache: ignoring entry {path} ({type(e).__name__}: {e}); rebuilding", stacklevel=3)
        return None
    stats[f"{kind}_hit"] += 1
    return obj
