"""fem's internal architecture: no import cycles between its modules (top-level or inside functions), function-level
imports only of the optional heavy modules, and ``import fem`` does not load them."""
from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

FEM = Path(__file__).resolve().parent.parent / "fem"
LAZY_OK = ("gmsh", "meshio", "matplotlib", "scipy.sparse", "cvxopt", "pymetis",    # heavy imports that may stay
           "importlib.metadata", "tomllib",   # 10 and 4 ms of start-up: a gmsh without a stated version, TOML scenes
           ".condense", ".interior_factor")
# inside functions (scipy: a model from the disk cache predicts with numpy alone, issue 19; cvxopt: CHOLMOD;
# pymetis: the ordering CHOLMOD gets; fem.condense and fem.interior_factor, which load scipy.sparse and scipy.linalg:
# the 2D surface model's builds and fields, not its cached force queries)


def _is_lazy_ok(module: str) -> bool:
    return any(module == m or module.startswith(m + ".") for m in LAZY_OK)


def _imports(tree: ast.Module):
    """(node, inside_a_function_or_class) for every import statement of a module."""
    out = []

    def visit(node, nested):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                out.append((child, nested))
            visit(child, nested or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda,
                                                      ast.ClassDef)))
    visit(tree, False)
    return out


def _fem_targets(node, modules: set[str]) -> set[str]:
    """The fem modules an import statement of a fem module refers to."""
    if isinstance(node, ast.Import):
        names = [a.name for a in node.names]
        return {n.split(".")[1] for n in names if n.startswith("fem.") and n.split(".")[1] in modules}
    if node.level == 0 and node.module != "fem" and not (node.module or "").startswith("fem."):
        return set()
    base = (node.module or "").removeprefix("fem").lstrip(".") if node.level == 0 else (node.module or "")
    if base:
        head = base.split(".")[0]
        return {head} if head in modules else set()
    return {a.name for a in node.names if a.name in modules}   # from . import x / from fem import x


def import_graph(sources: dict[str, str]) -> dict[str, set[str]]:
    """module -> the fem modules it imports (at top level or inside functions), from {module name: source}."""
    modules = set(sources)
    return {name: set().union(*(_fem_targets(node, modules) for node, _ in _imports(ast.parse(src))))
            for name, src in sources.items()}


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """A cycle of the graph as a path [a, b, ..., a], or None."""
    state: dict[str, int] = {}          # 1: on the stack, 2: done
    stack: list[str] = []

    def dfs(u):
        state[u] = 1
        stack.append(u)
        for v in sorted(graph.get(u, ())):
            if state.get(v) == 1:
                return stack[stack.index(v):] + [v]
            if v not in state and (c := dfs(v)):
                return c
        stack.pop()
        state[u] = 2
        return None

    for u in sorted(graph):
        if u not in state and (c := dfs(u)):
            return c
    return None


def lazy_imports(sources: dict[str, str]) -> list[str]:
    """'module: imported' for every import inside a function or class body."""
    out = []
    for name, src in sources.items():
        for node, nested in _imports(ast.parse(src)):
            if nested:
                mods = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                    ["." * node.level + (node.module or "")]
                out += [f"{name}: {m}" for m in mods]
    return out


def fem_sources() -> dict[str, str]:
    return {p.stem: p.read_text() for p in sorted(FEM.glob("*.py"))}


def test_fem_has_no_import_cycle():
    graph = import_graph(fem_sources())
    assert graph["contact"] >= {"model", "diskcache"}       # the graph does see fem's imports
    assert find_cycle(graph) is None, f"import cycle in fem: {' -> '.join(find_cycle(graph))}"


def test_only_heavy_optional_modules_are_imported_inside_functions():
    bad = [s for s in lazy_imports(fem_sources()) if not _is_lazy_ok(s.split(": ")[1])]
    assert not bad, f"function-level imports in fem (move them to the top of the file): {bad}"


def test_the_disk_cache_imports_nothing_from_fem():
    """fem.diskcache (and fem.cachesize, its size bound) are generic: nothing of fem's models below them."""
    graph = import_graph(fem_sources())
    assert graph["diskcache"] == {"cachesize"} and graph["cachesize"] == set()


def test_the_checks_can_fail():
    """A cycle hidden in a function body, and a lazy import of a light module, are both found."""
    sources = {"a": "from .b import f\n", "b": "def f():\n    from . import c\n",
               "c": "import numpy\ndef g():\n    from fem.a import h\n    import scipy.sparse.linalg\n"}
    assert find_cycle(import_graph(sources)) == ["a", "b", "c", "a"]
    assert lazy_imports(sources) == ["b: .", "c: fem.a", "c: scipy.sparse.linalg"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_import_fem_does_not_load_heavy_modules():
    code = ("import sys, fem; print(sorted({m.split('.')[0] for m in sys.modules} & "
            f"{set(LAZY_OK)!r}))")
    out = subprocess.run([sys.executable, "-c", code], cwd=FEM.parent, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
