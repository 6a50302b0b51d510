"""One process at a time in a run's output directory.

Two ``palpate run`` (or ``palpate-cell``) processes given the same ``--out`` both appended to probes.jsonl (the same
probe indices twice) and the last one's result.json won. ``holding(out, option)`` creates OUT and takes an exclusive
``flock`` on the directory itself (no file of its own in it: ``--fresh`` moves everything aside) for as long as the
block runs; a second process is refused with one line. The kernel drops the lock when the process ends, however it
ends. A file system without locks (some network mounts) gets a warning and no lock.
"""
from __future__ import annotations

import contextlib
import fcntl
import os
import sys
from pathlib import Path

from app.errors import UsageError


@contextlib.contextmanager
def holding(out: Path, option: str = "--out"):
    """OUT created and held (UsageError when another process holds it) while the block runs."""
    out.mkdir(parents=True, exist_ok=True)
    fd = os.open(out, os.O_RDONLY | os.O_DIRECTORY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise UsageError(f"{option} {out}: another palpate process is writing there now; wait for it to end "
                             f"(then the same command resumes) or choose another {option}") from None
        except OSError as e:
            print(f"palpate: warning: {option} {out}: cannot lock it ({e.strerror}): do not start a second run there",
                  file=sys.stderr)
        yield out
    finally:
        os.close(fd)
