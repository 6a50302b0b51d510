"""Independent pieces of work (table stones, study trials) run serially or on dask.distributed, resumably.

``run_pieces(fn, shared, pieces, names, store, runner)`` returns ``[fn(shared, piece) for piece in pieces]``, in
order, whatever runs them:

* ``Runner(workers=1)``: in this process, one after the other;
* ``Runner(workers=N)``: a dask ``LocalCluster`` of N single-threaded worker processes on this machine;
* ``Runner(scheduler="tcp://host:8786")``: the workers of an existing dask scheduler (any number of machines; each
  needs palpate importable, e.g. ``pip install -e .`` on a shared checkout).

Results equal a serial run's: each piece carries its own seed and the pieces do not talk to each other; ``shared``
(a surrogate table, say) is sent to every worker once (``Client.scatter(broadcast=True)``). With a ``store``
directory every finished piece is written there as soon as it arrives (``<name>.json``, or ``<name>.npy`` for an
array; atomically, never overwritten) and a re-run reads it back instead of computing it again: an interrupted
study or table resumes. A progress bar (tqdm, on standard error) shows pieces done and the ETA.
"""
from __future__ import annotations

import json
import logging
import os
import signal
import sys
import tempfile
from collections.abc import Callable, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.textfile import InputFileError


@dataclass(frozen=True)
class Runner:
    """Where pieces run: ``workers`` processes on this machine (1: serially in this process) or, with
    ``scheduler``, an existing dask cluster (its address, e.g. tcp://10.0.0.5:8786)."""
    workers: int = 1
    scheduler: str | None = None
    progress: bool = True

    def describe(self) -> str:
        if self.scheduler:
            return f"dask scheduler {self.scheduler}"
        return "serial (this process)" if self.workers <= 1 else f"dask LocalCluster, {self.workers} workers"


def _json_default(v):
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.floating):
        return float(v)
    if isinstance(v, np.bool_):
        return bool(v)
    if isinstance(v, np.ndarray):
        return v.tolist()
    raise TypeError(f"not JSON-able: {type(v).__name__}")


def _write_once(path: Path, write) -> None:
    """Write a file atomically and only if it does not exist yet (a finished piece is never overwritten)."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name + ".", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
        try:
            os.link(tmp, path)                 # fails if the piece is already there
        except FileExistsError:
            pass
        except OSError:                        # a file system without hard links: rename, unless it is there
            if not path.exists():
                os.replace(tmp, path)
    finally:
        Path(tmp).unlink(missing_ok=True)


def save_piece(store: Path, name: str, result) -> None:
    store.mkdir(parents=True, exist_ok=True)          # created with the first finished piece, not before
    if isinstance(result, np.ndarray):
        _write_once(store / f"{name}.npy", lambda f: np.save(f, result, allow_pickle=False))
    else:
        text = json.dumps(result, default=_json_default).encode()
        _write_once(store / f"{name}.json", lambda f: f.write(text))


def rows_with(*keys: str) -> Callable[[object], None]:
    """A piece's shape: a list of rows (JSON objects), each holding ``keys`` (what every row its work writes has)."""
    def check(piece) -> None:
        if not isinstance(piece, list) or not all(isinstance(r, dict) and all(k in r for k in keys) for r in piece):
            raise ValueError(f"not a list of rows each with {', '.join(repr(k) for k in keys)}")
    return check


def record_with(*keys: str) -> Callable[[object], None]:
    """A piece's shape: one JSON object holding ``keys``."""
    def check(piece) -> None:
        missing = [k for k in keys if not isinstance(piece, dict) or k not in piece]
        if missing:
            raise ValueError(f"not a record with {', '.join(repr(k) for k in missing)}")
    return check


def array_of(shape: tuple[int, ...]) -> Callable[[object], None]:
    """A piece's shape: an array of real numbers of ``shape`` (NaN allowed: a table marks what it did not sample)."""
    def check(piece) -> None:
        a = np.asarray(piece)
        if a.shape != tuple(shape) or a.dtype.kind not in "fiu":
            raise ValueError(f"not an array of numbers of shape {tuple(shape)} (it is {a.dtype} {a.shape})")
    return check


def load_piece(store: Path, name: str, shape: Callable[[object], None] | None = None):
    """A finished piece from ``store``, or None. A piece that cannot be read back (emptied, cut short, edited), or is
    not of the ``shape`` its work writes (``rows_with``, ``record_with``, ``array_of``: a check that raises
    ValueError), is an InputFileError naming it: it is not computed again over it (nothing on disk is overwritten),
    the user moves it aside."""
    npy, js = store / f"{name}.npy", store / f"{name}.json"
    try:
        if npy.exists():
            piece = np.load(npy, allow_pickle=False)
        elif js.exists():
            piece = json.loads(js.read_text())
        else:
            return None
        if shape is not None:
            shape(piece)
        return piece
    except (ValueError, EOFError) as e:         # (json's JSONDecodeError and numpy's bad files are ValueErrors)
        bad = npy if npy.exists() else js
        raise InputFileError("a finished piece of this work", bad,
                             f"cannot be read back ({e}): move it aside, and the same command computes it again "
                             f"(nothing on disk is overwritten)") from None


@contextmanager
def dask_client(runner: Runner):
    """A dask.distributed Client for ``runner`` (a LocalCluster it starts and stops, or the scheduler's)."""
    import dask
    from distributed import Client, LocalCluster
    if runner.scheduler:
        client = Client(runner.scheduler, timeout="20s")
        try:
            yield client
        finally:
            client.close()
        return
    # no dashboard; the scheduler's own HTTP server (health routes) on a free port of this host only, not on dask's
    # 8787 (taken by another cluster: dask warned "Port 8787 is already in use"); each worker runs dask_setup below,
    # then the user's own preloads (dask's distributed.worker.preload setting, which an explicit preload replaces)
    preload = dask.config.get("distributed.worker.preload", None) or []
    preload = [__name__, *([preload] if isinstance(preload, str) else preload)]
    with LocalCluster(n_workers=runner.workers, threads_per_worker=1, processes=True, dashboard_address=None,
                      scheduler_kwargs={"dashboard_address": "127.0.0.1:0"}, preload=preload,
                      silence_logs=logging.ERROR) as cluster, Client(cluster) as client:
        yield client


def dask_setup(worker) -> None:
    """dask's preload hook, run in each LocalCluster worker process as it starts (``preload`` above): a Ctrl-C at
    the terminal reaches the whole process group, workers included, and each printed a KeyboardInterrupt traceback
    under the run's "interrupted". The workers leave it to this process, which stops them as it ends."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _bar(runner: Runner, total: int, done: int, desc: str):
    from tqdm import tqdm  # only where pieces run (a run that reads its tables never does)
    return tqdm(total=total, initial=done, desc=desc, unit="piece", file=sys.stderr, disable=not runner.progress,
                smoothing=0.1, dynamic_ncols=True)


def run_pieces(fn: Callable, shared, pieces: Sequence, names: Sequence[str], runner: Runner = Runner(),
               store: Path | None = None, desc: str = "pieces", on_result: Callable | None = None,
               shape: Callable[[object], None] | None = None) -> list:
    """``[fn(shared, p) for p in pieces]`` on ``runner`` (module doc); ``names`` (unique, file-name safe) name the
    pieces in ``store``. ``on_result(i, result)`` is called in this process as each piece finishes (or is read
    back). ``fn`` must be importable by its module path on the workers (a module-level function). ``shape`` checks
    a piece read back from ``store`` (``load_piece``)."""
    if len(names) != len(pieces) or len(set(names)) != len(names):
        raise ValueError("run_pieces: one unique name per piece")
    results: list = [None] * len(pieces)
    todo = []
    for i, name in enumerate(names):
        r = load_piece(store, name, shape) if store is not None else None
        if r is None:
            todo.append(i)
        else:
            results[i] = r
            if on_result:
                on_result(i, r)

    def finish(i, r):
        if store is not None:
            save_piece(store, names[i], r)
            r = load_piece(store, names[i], shape)     # what a resumed run would read: the same values either way
        results[i] = r
        if on_result:
            on_result(i, r)

    with _bar(runner, len(pieces), len(pieces) - len(todo), desc) as bar:
        if not todo:
            return results
        if runner.scheduler is None and runner.workers <= 1:
            for i in todo:
                finish(i, fn(shared, pieces[i]))
                bar.update(1)
            return results
        from distributed import as_completed
        with dask_client(runner) as client:
            # a list of one: scatter would split a dict or a tuple into separate pieces
            shared_f = client.scatter([shared], broadcast=True)[0] if shared is not None else None
            futures = {client.submit(fn, shared_f, pieces[i], pure=False): i for i in todo}
            for fut in as_completed(futures):
                finish(futures[fut], fut.result())
                bar.update(1)
    return results
