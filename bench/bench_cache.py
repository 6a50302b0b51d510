"""What the disk cache's bound costs (fem.cachesize): a pruning pass against the number of entries in the directory,
and a write's share of it within the bound (the directory listed at most once every RESCAN_S per process).

    python bench/bench_cache.py --out bench-out/cache [--sizes 200,2000,20000]

For each size: that many small fake entries (``mesh-<20 hex>.npz``, 100 bytes, their last use spread over a day) in
a fresh directory; the median of 5 pruning passes within the bound (they list and stat every entry, remove
nothing), and the median cost of ``fem.diskcache.write`` of a 1 kB entry, the first write of a process (which
lists the directory) and the next ones (which do not). Writes OUT/cache.json and OUT/cache.md.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from fem import cachesize, diskcache  # noqa: E402


def one_size(n: int) -> dict:
    with tempfile.TemporaryDirectory(prefix="bench-cache-") as d:
        root = Path(d)
        now = time.time()
        for i in range(n):
            p = root / f"mesh-{i:020x}.npz"
            p.write_bytes(b"x" * 100)
            os.utime(p, (now - 86400 * i / n, now - 86400 * i / n))
        passes = []
        for _ in range(5):
            t = time.perf_counter()
            r = cachesize.prune(root, 1e15, keep=())
            passes.append(time.perf_counter() - t)
        assert not r.removed and r.left_entries == n
        os.environ["PALPATE_CACHE_DIR"] = str(root)
        cachesize._scanned.clear()
        writes = []
        for i in range(6):
            t = time.perf_counter()
            diskcache.write(diskcache.entry_path("bench", {"i": i}), {"x": np.zeros(100)})
            writes.append(time.perf_counter() - t)
    return {"entries": n, "prune_pass_s": statistics.median(passes), "prune_pass_per_entry_s":
            statistics.median(passes) / n, "first_write_s": writes[0], "later_write_s": statistics.median(writes[1:])}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="output directory (cache.json, cache.md)")
    ap.add_argument("--sizes", default="200,2000,20000", help="entry counts, comma-separated")
    a = ap.parse_args()
    try:
        sizes = [int(v) for v in a.sizes.split(",")]
    except ValueError:
        print(f"bench_cache: --sizes {a.sizes!r}: give entry counts such as 200,2000", file=sys.stderr)
        return 2
    if not sizes or min(sizes) < 1:
        print(f"bench_cache: --sizes {a.sizes!r}: each count must be at least 1", file=sys.stderr)
        return 2
    saved = os.environ.get("PALPATE_CACHE_DIR")
    rows = []
    try:
        for n in sizes:
            row = one_size(n)
            rows.append(row)
            print(f"{n:>7} entries: pruning pass {row['prune_pass_s'] * 1e3:8.2f} ms "
                  f"({row['prune_pass_per_entry_s'] * 1e6:.1f} us an entry); a process's first write "
                  f"{row['first_write_s'] * 1e3:.2f} ms, later writes {row['later_write_s'] * 1e3:.2f} ms", flush=True)
    finally:
        if saved is None:
            os.environ.pop("PALPATE_CACHE_DIR", None)
        else:
            os.environ["PALPATE_CACHE_DIR"] = saved
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "cache.json").write_text(json.dumps({"rows": rows, "rescan_s": cachesize.RESCAN_S}, indent=1) + "\n")
    lines = ["| entries | pruning pass | per entry | first write of a process | later writes |", "|---:|---:|---:|---:|---:|"]
    lines += [f"| {r['entries']:,} | {r['prune_pass_s'] * 1e3:.2f} ms | {r['prune_pass_per_entry_s'] * 1e6:.1f} us | "
              f"{r['first_write_s'] * 1e3:.2f} ms | {r['later_write_s'] * 1e3:.2f} ms |" for r in rows]
    (out / "cache.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out / 'cache.json'} and {out / 'cache.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
