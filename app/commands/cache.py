"""`palpate cache`: what the disk cache holds, and making room in it.

The disk cache keeps what fem and the planner derive once and reuse: meshes, factorized models and their operators,
surrogate tables, the forces a run asked before. Each entry can be rebuilt; removing one costs that rebuild (seconds
for a 2D model, a minute or two for a 3D one with stresses), never a result. It lives in $PALPATE_CACHE_DIR (default
~/.cache/palpate) and is bounded by $PALPATE_CACHE_MAX_BYTES (bytes; default 20e9): after each write the entries used
least recently go, except what the writing process uses and what any process used in the last 10 minutes.
"""
from __future__ import annotations

import argparse
import os
import shutil
import time
from collections import defaultdict
from pathlib import Path

from app.commands.output import json_alone, write_json
from app.errors import UsageError
from app.options import check_output_file, nonnegative_float
from fem import cachesize, diskcache

ACTIONS = ("list", "prune", "clear")


def add_parser(sub) -> None:
    p = sub.add_parser("cache", help="what the disk cache holds (by kind, size, last use); prune or clear it",
                       description=__doc__.split("\n\n", 1)[1].strip(),
                       epilog="actions:\n"
                              "  list    (default) the cache's directory, bound and entries by kind\n"
                              "  prune   remove the entries used least recently until the rest fit the bound\n"
                              "          (--max-bytes, else $PALPATE_CACHE_MAX_BYTES), and partial writes over an "
                              "hour old\n"
                              "  clear   remove every entry, lock file no process holds, partial write and "
                              "resumable\n"
                              "          table build (*.parts); with --kind only the entries of those kinds (and "
                              "their\n"
                              "          free lock files). A command running meanwhile rebuilds what it loses\n"
                              "examples:\n"
                              "  palpate cache\n"
                              "  palpate cache list --entries --json cache.json\n"
                              "  palpate cache prune --max-bytes 5e9\n"
                              "  palpate cache clear --kind factor3d --kind band3d",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("action", nargs="?", default="list", choices=ACTIONS, help="list (default), prune or clear")
    p.add_argument("--max-bytes", type=nonnegative_float, metavar="N",
                   help="prune: the size to prune to, in bytes (e.g. 5e9); default $PALPATE_CACHE_MAX_BYTES or 20e9. "
                        "Unlike the pruning after a write it spares nothing: a command running meanwhile rebuilds "
                        "what it loses")
    p.add_argument("--kind", action="append", metavar="KIND",
                   help="clear: only entries of this kind (repeatable; `palpate cache` lists the kinds present)")
    p.add_argument("--entries", action="store_true", help="list: every entry, not only the kinds")
    p.add_argument("--json", metavar="PATH", help="also write the listing or what was removed as JSON ('-': "
                                                  "standard output)")
    p.set_defaults(func=run)


def _utc(t: float) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(t))


def _bound() -> tuple[float, str]:
    try:
        v = cachesize.max_bytes()
    except ValueError as e:
        raise UsageError(str(e)) from None
    return v, (f"${cachesize.ENV}" if os.environ.get(cachesize.ENV, "").strip() else "the default")


def _listing(root: Path, ents: list[cachesize.Entry], with_entries: bool) -> dict:
    kinds: dict[str, list[cachesize.Entry]] = defaultdict(list)
    for e in ents:
        kinds[e.kind].append(e)
    limit, source = _bound()
    out = {"dir": str(root), "enabled": diskcache.enabled(), "max_bytes": limit, "max_bytes_from": source,
           "total_bytes": sum(e.size_bytes for e in ents), "entries": len(ents),
           "kinds": {k: {"entries": len(v), "size_bytes": sum(e.size_bytes for e in v),
                         "last_used_utc": _utc(max(e.used_s for e in v)),
                         "first_used_utc": _utc(min(e.used_s for e in v))} for k, v in sorted(kinds.items())},
           "lock_files": len(list(root.glob("*.lock"))) if root.is_dir() else 0,
           "partial_writes": [str(p) for p in cachesize.partial_writes(root, older_than_s=0.0)],
           "resumable_builds": sorted(str(p) for p in root.glob("*.parts")) if root.is_dir() else []}
    out["resumable_builds_bytes"] = sum(f.stat().st_size for b in out["resumable_builds"] for f in Path(b).rglob("*")
                                        if f.is_file())
    if with_entries:
        out["entry_list"] = [{"path": str(e.path), "kind": e.kind, "size_bytes": e.size_bytes,
                              "last_used_utc": _utc(e.used_s)} for e in ents]
    return out


def _print_listing(d: dict) -> None:
    state = "" if d["enabled"] else " (off: PALPATE_CACHE=0, commands neither read nor write it)"
    print(f"disk cache {d['dir']}{state}")
    print(f"  bound {cachesize.size_text(d['max_bytes'])} ({d['max_bytes_from']}; ${cachesize.ENV} sets it): after each write the "
          f"entries used least recently go")
    if not d["entries"]:
        print("  no entries")
    else:
        print(f"  {'kind':<14}{'entries':>8}{'size':>12}  last used (UTC)")
        for k, v in d["kinds"].items():
            print(f"  {k:<14}{v['entries']:>8}{cachesize.size_text(v['size_bytes']):>12}  {v['last_used_utc']}")
        print(f"  {'total':<14}{d['entries']:>8}{cachesize.size_text(d['total_bytes']):>12}"
              + ("  (above the bound: the next write prunes it)" if d["total_bytes"] > d["max_bytes"] else ""))
    for e in d.get("entry_list", []):
        print(f"    {e['last_used_utc']}  {cachesize.size_text(e['size_bytes']):>10}  {e['path']}")
    extra = [f"{d['lock_files']} lock files"] if d["lock_files"] else []
    if d["partial_writes"]:
        extra.append(f"{len(d['partial_writes'])} partial writes (a writer's, or left by one that was killed)")
    if d["resumable_builds"]:
        extra.append(f"{len(d['resumable_builds'])} resumable table builds (*.parts, "
                     f"{cachesize.size_text(d['resumable_builds_bytes'])}: outside the bound; `palpate cache clear` "
                     f"removes them)")
    if extra:
        print("  also: " + "; ".join(extra))


def run(args) -> int:
    root = diskcache.cache_dir()
    if args.json is not None and args.json != "-":     # ('' too: refused there, as by every command)
        check_output_file(args.json, "--json")
    if args.max_bytes is not None and args.action != "prune":
        raise UsageError(f"--max-bytes {args.max_bytes:g}: only for `palpate cache prune`")
    if args.kind and args.action != "clear":
        raise UsageError(f"--kind {args.kind[0]}: only for `palpate cache clear`")
    if args.entries and args.action != "list":
        raise UsageError("--entries: only for `palpate cache list`")
    with json_alone(args.json):
        if args.action == "list":
            d = _listing(root, cachesize.entries(root), args.entries)
            _print_listing(d)
        elif args.action == "prune":
            limit = args.max_bytes if args.max_bytes is not None else _bound()[0]
            r = cachesize.prune(root, limit, keep=())
            d = _removed(root, r.removed, r.stale_tmp, limit)
        else:
            ents = cachesize.entries(root)
            if args.kind:
                bad = [k for k in args.kind if not cachesize.KIND_NAME.match(k)]
                if bad:
                    raise UsageError(f"--kind {bad[0]!r}: a kind is a lower-case name such as mesh or factor3d "
                                     f"(`palpate cache` lists those present)")
                present = sorted({e.kind for e in ents})
                unknown = [k for k in args.kind if k not in cachesize.KINDS and k not in present]
                if unknown:
                    raise UsageError(f"--kind {unknown[0]!r}: not a kind palpate's cache holds; one of "
                                     f"{', '.join(sorted(cachesize.KINDS))}")
                for k in args.kind:
                    if k not in present:
                        print(f"disk cache {root}: no entries of kind {k} (present: {', '.join(present) or 'none'})")
                ents = [e for e in ents if e.kind in args.kind]
            gone = [e for e in ents if cachesize.remove(e.path)]
            locks = [Path(os.fspath(e.path) + ".lock") for e in gone]
            parts = []
            if not args.kind:               # everything: orphan lock files, partial writes, resumable builds too
                locks = sorted(p for p in root.glob("*.npz.lock") if cachesize.kind_of(p.with_suffix(""))) \
                    if root.is_dir() else []
                parts = sorted(p for p in root.glob("*.parts") if p.is_dir() and not p.is_symlink()
                               and cachesize.kind_of(p.with_suffix(".npz")))
            held = [str(p) for p in locks if p.exists() and not cachesize.remove_lock(p)]
            for p in parts:
                shutil.rmtree(p, ignore_errors=True)
            stale = [] if args.kind else [p for p in cachesize.partial_writes(root, older_than_s=0.0)
                                          if cachesize.remove(p)]
            d = _removed(root, gone, stale, None)
            d.update({"resumable_builds_removed": [str(p) for p in parts], "lock_files_held": held})
            if parts:
                print(f"  and {len(parts)} resumable table builds (*.parts)")
            if held:
                print(f"  {len(held)} lock files kept: a palpate process holds them")
    write_json(args.json, d)
    return 0


def _removed(root: Path, removed, stale, limit: float | None) -> dict:
    left = cachesize.entries(root)
    d = {"dir": str(root), "removed": [{"path": str(e.path), "kind": e.kind, "size_bytes": e.size_bytes,
                                       "last_used_utc": _utc(e.used_s)} for e in removed],
         "removed_bytes": sum(e.size_bytes for e in removed), "partial_writes_removed": [str(p) for p in stale],
         "left_entries": len(left), "left_bytes": sum(e.size_bytes for e in left), "max_bytes": limit}
    bound = f" (bound {cachesize.size_text(limit)})" if limit is not None else ""
    print(f"disk cache {root}: removed {len(removed)} entries ({cachesize.size_text(d['removed_bytes'])}"
          + (", the least recently used" if limit is not None and removed else "") + ")"
          + (f" and {len(stale)} partial writes" if stale else "")
          + f"; {len(left)} entries left, {cachesize.size_text(d['left_bytes'])}{bound}")
    return d
