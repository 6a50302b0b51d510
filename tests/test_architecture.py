"""The import contract (docs/architecture.md): packages depend one way, and no module imports in a cycle.

    core  <-  fem  <-  planner  <-  app
              fem  <-  robot    <-  app

core imports no other palpate package; fem imports core; planner imports fem and core; robot imports core and, for
the simulated arm only, fem; app may import everything. planner and robot never import each other. Both top-level
imports and imports inside functions count.
"""
from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("core", "fem", "planner", "robot", "app")
ALLOWED = {
    "core": set(),
    "fem": {"core"},
    "planner": {"core", "fem"},
    "robot": {"core", "fem"},
    "app": {"core", "fem", "planner", "robot"},
}
# robot modules that may ask fem for forces: the simulated truth (the driver never does)
ROBOT_FEM_USERS = {"robot.simarm"}
# imports allowed inside functions: optional heavy libraries that keep CLI start-up fast
LAZY_OK = ("matplotlib", "gmsh", "meshio", "rtde_control", "rtde_receive", "dashboard_client", "fem.plots",
           "fem.export", "fem.export3d", "fem.plots3d", "cvxopt", "pymetis", "planner.plots_plan", "planner.plots_run",
           "planner.plots_accuracy", "importlib.metadata", "distributed", "dask",
           "scipy.sparse", "app.commands.sim3d", "app.commands.run3d", "planner.plots_run3d", "tomllib",
           "fem.condense", "fem.interior_factor", "urllib.request", "tqdm",
           "fem.contact3d", "fem.recall3d", "fem.mesh3d", "planner.depth3d", "fem.scene_mesh3d")
# scipy.sparse: a cached model predicts with numpy alone (issue 19); app.commands.sim3d and run3d: the 3D path
# (scipy.linalg, CHOLMOD) loaded for a 3D scene only; tomllib: TOML scenes only (4 ms of a cached predict's start-up);
# fem.condense, fem.interior_factor (scipy.sparse, scipy.linalg, CHOLMOD): a 2D surface model's fields only;
# fem.contact3d, fem.recall3d, fem.mesh3d, planner.depth3d, fem.scene_mesh3d: fem's 3D code (25 ms) where a scene
# is a block;
# urllib.request (http, ssl, email: 15 ms): a real Net F/T box's calibration only; tqdm: where a study's pieces run


def modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for f in sorted((ROOT / pkg).rglob("*.py")):
            rel = f.relative_to(ROOT).with_suffix("")
            parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
            out[".".join(parts)] = f
    return out


def imports_of(name: str, path: Path) -> list[tuple[tuple[str, ...], bool]]:
    """(what one import statement may import, inside a function?) for every import statement of a module:
    ``from pkg import x`` may import ``pkg`` and ``pkg.x`` (x may be a module)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    base = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    found = []

    def walk(node, inside: bool):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.Import):
                found.extend(((a.name,), inside) for a in child.names)
            elif isinstance(child, ast.ImportFrom):
                mod = child.module or ""
                if child.level:
                    mod = ".".join(base[:len(base) - child.level + 1] + ([mod] if mod else []))
                found.append(((mod, *(f"{mod}.{a.name}" for a in child.names)), inside))
            walk(child, inside or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)))
    walk(tree, False)
    return found


def build_graph():
    mods = modules()
    edges, nested = {}, {}
    for name, path in mods.items():
        imps = imports_of(name, path)
        edges[name] = {m for targets, _ in imps for m in targets if m in mods and m != name}
        nested[name] = [targets for targets, inside in imps if inside]
    return mods, edges, nested


@pytest.fixture(scope="module")
def graph():
    return build_graph()


def forbidden_edges(edges) -> list[str]:
    bad = []
    for src, targets in edges.items():
        src_pkg = src.split(".")[0]
        for t in targets:
            t_pkg = t.split(".")[0]
            if t_pkg == src_pkg:
                continue
            if t_pkg not in ALLOWED[src_pkg]:
                bad.append(f"{src} -> {t}")
            elif src_pkg == "robot" and t_pkg == "fem" and src not in ROBOT_FEM_USERS:
                bad.append(f"{src} -> {t} (only {sorted(ROBOT_FEM_USERS)} may ask fem)")
    return sorted(bad)


def cycles_of(edges) -> list[list[str]]:
    # a package's __init__ re-exporting its own modules is not a cycle of the modules themselves
    deps = {m: {t for t in ts if not t.startswith(m + ".")} for m, ts in edges.items()}
    state, stack, cycles = {}, [], []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for t in sorted(deps.get(m, ())):
            if state.get(t) == 1:
                cycles.append(stack[stack.index(t):] + [t])
            elif t not in state:
                visit(t)
        stack.pop()
        state[m] = 2
    for m in sorted(deps):
        if m not in state:
            visit(m)
    return cycles


def test_packages_depend_one_way(graph):
    bad = forbidden_edges(graph[1])
    assert not bad, "forbidden imports:\n  " + "\n  ".join(bad)


def test_no_import_cycles(graph):
    cycles = cycles_of(graph[1])
    assert not cycles, "import cycles:\n  " + "\n  ".join(" -> ".join(c) for c in cycles)


def test_imports_inside_functions_only_for_heavy_optional_modules(graph):
    def lazy_ok(targets):
        return any(t == h or t.startswith(h + ".") for t in targets for h in LAZY_OK)
    bad = [f"{m}: {targets[-1]}" for m, imps in graph[2].items() for targets in imps if not lazy_ok(targets)]
    assert not bad, "imports inside functions (move them to the top):\n  " + "\n  ".join(sorted(set(bad)))


def test_the_checks_can_fail(graph):
    """The checkers themselves: a planner module importing robot, and a two-module cycle, are caught."""
    edges = {k: set(v) for k, v in graph[1].items()}
    edges["planner.localize"].add("robot.driver")
    assert "planner.localize -> robot.driver" in forbidden_edges(edges)
    edges["fem.scene"].add("fem.contact")
    edges["fem.contact"].add("fem.scene")
    assert any("fem.scene" in c and "fem.contact" in c for c in cycles_of(edges))


def test_a_subcommand_that_fails_to_import_is_an_error_not_a_silent_omission(monkeypatch):
    """The CLI once skipped a subcommand whose module failed to import: `palpate` then just lacked it."""
    from app import cli
    monkeypatch.setitem(cli.COMMANDS, "nosuch", "a subcommand whose module does not exist")
    with pytest.raises(ModuleNotFoundError):
        cli.build_parser("nosuch")
    for name in cli.COMMANDS:
        if name != "nosuch":
            assert cli.build_parser(name)._subparsers is not None      # every real subcommand imports


def test_predict_and_simulate_start_without_scipy():
    """Start-up (issue 19): the 2D commands' modules load neither scipy nor the 3D path at import; fem imports
    scipy when a model is assembled or factorized (a cached scene predicts with numpy alone: test_influence)."""
    code = ("import sys, app.commands.predict, app.commands.simulate; "
            "print(sorted({k.split('.')[0] for k in sys.modules} & {'scipy', 'cvxopt', 'matplotlib', 'casadi'}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.strip() == "[]"


def test_a_2d_run_starts_without_the_3d_path_and_the_network_libraries():
    """Start-up (issue 19): ``palpate run`` on a 2D section loads fem's 3D code only for a block, urllib (http, ssl,
    email) only to ask a real Net F/T box for its calibration, tqdm only where a study's pieces run; 40 ms of a
    simulated run's start in all. A 3D scene's run still finds the 3D code (the modules load it where needed)."""
    code = ("import sys, app.cli, app.commands.run; "
            "print(sorted(k for k in sys.modules if k in ('urllib.request', 'tqdm', 'http.client', 'ssl') "
            "or (k.startswith('fem.') and '3d' in k)))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.strip() == "[]"
