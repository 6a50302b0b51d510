"""Test-session settings: a private, empty disk cache (tests compute from scratch and never read a developer's
~/.cache/palpate), single-threaded BLAS (2 shared cores), and a non-interactive matplotlib backend."""
import os
import tempfile

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MPLBACKEND", "Agg")
_CACHE_DIR = tempfile.mkdtemp(prefix="palpate-test-cache-")
os.environ["PALPATE_CACHE_DIR"] = _CACHE_DIR
