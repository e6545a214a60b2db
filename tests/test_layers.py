"""Layers that only look down and no import cycles.

The contracts are in pyproject.toml ([tool.importlinter]): the layers (cli, demos, benchmarks,
tuning, selftest > sim > trackers > tracking, scheduler > ops > backends > models > registry >
profiler > device and the small modules below everything), trackers never import sim, ops never import
benchmarks, backends never import ops, and no cycles between sibling packages or modules. Layers
that another change adds later are optional in the contract (in parentheses), so the contract
holds before they exist and checks them once they do.

Beside import-linter's checks, :func:`cycles` looks for cycles in the module graph itself (every
import statement, also those inside functions): a module importing the package that contains
it (``from . import backend_module``, the package re-exporting its modules) is the one import
not counted, and no module imports the package root ``gputrack`` (whose ``__init__`` re-exports
from every layer).
"""

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]


def lint(root: Path) -> subprocess.CompletedProcess:
    """Run import-linter with the repository's contracts on the ``gputrack`` package under ``root``."""
    code = (
        "import sys; from importlinter.cli import lint_imports; "
        f"sys.exit(lint_imports(config_filename={str(ROOT / 'pyproject.toml')!r}, no_cache=True, no_logo=True))"
    )
    return subprocess.run([sys.executable, "-c", code], cwd=root, env={**os.environ, "PYTHONPATH": str(root)},
                          capture_output=True, text=True, timeout=300)  # fmt: skip


def ignored_imports() -> set[tuple[str, str]]:
    """The (importer, imported) pairs the contracts ignore (their ``ignore_imports``), wildcards resolved
    against the graph when checked."""
    doc = tomllib.loads((ROOT / "pyproject.toml").read_text())
    found = set()
    for contract in doc["tool"]["importlinter"]["contracts"]:
        for expr in contract.get("ignore_imports", []):
            a, b = (s.strip() for s in expr.split("->"))
            found.add((a, b))
    return found


def _matches(name: str, pattern: str) -> bool:
    if pattern.endswith(".**"):
        return name.startswith(pattern[:-3] + ".")
    return name == pattern


def module_graph(root: Path) -> dict[str, set[str]]:
    """{module: modules it imports} inside the ``gputrack`` package under ``root`` (grimp, in a
    subprocess with ``root`` on the path), less the contracts' ignored imports."""
    code = (
        "import json, grimp; g = grimp.build_graph('gputrack', cache_dir=None); "
        "print(json.dumps({m: sorted(g.find_modules_directly_imported_by(m)) for m in g.modules}))"
    )
    proc = subprocess.run([sys.executable, "-c", code], cwd=root, env={**os.environ, "PYTHONPATH": str(root)},
                          capture_output=True, text=True, timeout=300, check=True)  # fmt: skip
    ignored = ignored_imports()
    return {
        m: {t for t in targets if not any(_matches(m, a) and _matches(t, b) for a, b in ignored)}
        for m, targets in json.loads(proc.stdout).items()
    }


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components (> 1 module) of the import graph, an import of a module's own
    ancestor package not counted (Tarjan's algorithm, iterative)."""

    def counted(a, b):
        return not a.startswith(b + ".")

    index, low, on_stack, stack, out = {}, {}, set(), [], []
    counter = 0
    for start in sorted(edges):
        if start in index:
            continue
        work = [(start, iter(sorted(t for t in edges[start] if counted(start, t))))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(t for t in edges.get(w, ()) if counted(w, t)))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def test_the_contracts_hold():
    proc = lint(ROOT)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "BROKEN" not in proc.stdout and "KEPT" in proc.stdout


def test_no_import_cycles_between_modules():
    edges = module_graph(ROOT)
    assert cycles(edges) == []


def test_no_module_imports_the_package_root():
    edges = module_graph(ROOT)
    offenders = sorted(m for m, targets in edges.items() if "gputrack" in targets and m != "gputrack")
    assert offenders == [], f"import the module you need (e.g. gputrack.device), not gputrack itself: {offenders}"


# -- the checks catch what they are meant to catch: the package copied, one import added ---------
@pytest.fixture(scope="module")
def package_copy(tmp_path_factory):
    root = tmp_path_factory.mktemp("layers")
    shutil.copytree(ROOT / "gputrack", root / "gputrack", ignore=shutil.ignore_patterns("__pycache__"))
    return root


def _with_import(root: Path, module: str, statement: str):
    """Append a function that makes ``statement`` to ``module`` (a path under gputrack/); return
    (the path, its original text)."""
    path = root / "gputrack" / module
    original = path.read_text()
    path.write_text(original + "\n\n" + textwrap.dedent(f"""
        def _added_for_the_test():
            {statement}
    """))
    return path, original


@pytest.mark.parametrize(
    "module, statement, broken",
    [
        ("ops/particles.py", "from ..benchmarks import harness", "Ops never import a benchmark"),
        ("backends/reference/particles.py", "from ...ops.particles import BestK", "Backends never import an op"),
        ("trackers/body/tracker.py", "from ...sim import sequence", "Trackers never import the simulator"),
        ("models/chain.py", "from ..scheduler import Scheduler", "Layers only look down"),
        ("sim/problems.py", "from ..demos import body", "Layers only look down"),
    ],
)
def test_a_new_upward_import_breaks_a_contract(package_copy, module, statement, broken):
    path, original = _with_import(package_copy, module, statement)
    try:
        proc = lint(package_copy)
    finally:
        path.write_text(original)
    assert proc.returncode != 0
    assert f"{broken} BROKEN" in proc.stdout, proc.stdout + proc.stderr


def test_a_cycle_is_found(package_copy):
    path, original = _with_import(package_copy, "ops/_args.py", "from .pf import pf_stage")
    try:
        found = cycles(module_graph(package_copy))
        proc = lint(package_copy)
    finally:
        path.write_text(original)
    assert any({"gputrack.ops._args", "gputrack.ops.pf"} <= set(c) for c in found), found
    assert "No import cycles between sibling packages and modules BROKEN" in proc.stdout, proc.stdout


def test_an_import_of_the_root_is_found(package_copy):
    path, original = _with_import(package_copy, "sim/problems.py", "import gputrack")
    try:
        edges = module_graph(package_copy)
    finally:
        path.write_text(original)
    assert "gputrack" in edges["gputrack.sim.problems"]
