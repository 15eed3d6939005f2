"""The project's modules import each other without cycles.

The import graph is built statically with ``ast`` over every .py file of the project packages:
every ``import`` / ``from ... import`` statement counts, wherever it is (module level, inside a
function, under ``if TYPE_CHECKING:``), because a lazy import that imports back is still a cycle.
Edges go to project modules only: relative imports are resolved, ``from pkg import name`` is an edge
to the submodule ``pkg.name`` when that is a module (so ``from denoisers import registry`` inside
``denoisers/__init__.py`` is an edge to ``denoisers.registry``) and to ``pkg`` otherwise, and
``import a.b.c`` is an edge to the longest prefix that is a project module. Importing ``pkg.sub``
does not add an edge to ``pkg`` (the package ``__init__`` runs first, but that is not the importer
depending on it). Dynamic imports (``importlib.import_module``) are not followed.
"""
from __future__ import annotations

import ast
from collections import deque
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: Top-level directories whose .py files form the graph (missing ones are skipped).
SOURCE_DIRS = ("scenegen", "denoisers", "benchmarks", "scripts")


Graph = dict[str, dict[str, list[str]]]  # importer -> imported -> ["path:line", ...]


def module_files(root: Path, dirs: tuple[str, ...] = SOURCE_DIRS) -> dict[str, Path]:
    """Dotted module name -> file, for every .py file under ``root/<dir>`` (``pkg/__init__.py`` is ``pkg``)."""
    modules = {}
    for top in dirs:
        if not (root / top).is_dir():
            continue
        for path in sorted((root / top).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            if any(part == "__pycache__" or part.startswith(".") for part in parts):
                continue
            if parts[-1] == "__init__":
                parts = parts[:-1]
            modules[".".join(parts)] = path
    return modules


def _longest_module_prefix(name: str, modules: dict[str, Path]) -> str | None:
    parts = name.split(".")
    for end in range(len(parts), 0, -1):
        candidate = ".".join(parts[:end])
        if candidate in modules:
            return candidate
    return None


def _targets(node: ast.Import | ast.ImportFrom, module: str, path: Path, modules: dict[str, Path]) -> list[str]:
    """Project modules one import statement of ``module`` (file ``path``) imports."""
    is_package = path.name == "__init__.py"
    package = module if is_package else module.rpartition(".")[0]
    # A directory without __init__.py holds scripts (benchmarks/): they import siblings by bare name.
    script_dir = package if not (path.parent / "__init__.py").exists() else None

    def resolve(name: str) -> str | None:
        found = _longest_module_prefix(name, modules)
        if found is None and script_dir:
            found = _longest_module_prefix(f"{script_dir}.{name}", modules)
        return found

    if isinstance(node, ast.Import):
        return [target for alias in node.names if (target := resolve(alias.name))]
    if node.level:
        base_parts = package.split(".") if package else []
        if node.level - 1 > len(base_parts):
            raise AssertionError(f"{path}:{node.lineno}: relative import beyond the top-level package")
        base_parts = base_parts[:len(base_parts) - (node.level - 1)]
        base = ".".join(base_parts + ([node.module] if node.module else []))
    else:
        base = node.module or ""
    targets = []
    for alias in node.names:
        submodule = f"{base}.{alias.name}" if base else alias.name
        if alias.name != "*" and submodule in modules:
            targets.append(submodule)
        elif base and (target := resolve(base)):
            targets.append(target)
    return targets


def import_graph(root: Path = ROOT, dirs: tuple[str, ...] = SOURCE_DIRS) -> Graph:
    """Edges between project modules from every import statement (module and function level)."""
    modules = module_files(root, dirs)
    graph: Graph = {module: {} for module in modules}
    for module, path in modules.items():
        where = path.relative_to(root)
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                for target in dict.fromkeys(_targets(node, module, path, modules)):
                    if target != module:
                        graph[module].setdefault(target, []).append(f"{where}:{node.lineno}")
    return graph


def strongly_connected_components(graph: Graph) -> list[set[str]]:
    """Tarjan's algorithm (iterative); components in no particular order."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    components: list[set[str]] = []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, successors = work[-1]
            for succ in successors:
                if succ not in index:
                    index[succ] = low[succ] = len(index)
                    stack.append(succ)
                    on_stack.add(succ)
                    work.append((succ, iter(sorted(graph[succ]))))
                    break
                if succ in on_stack:
                    low[node] = min(low[node], index[succ])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = set()
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.add(member)
                        if member == node:
                            break
                    components.append(component)
    return components


def import_cycles(graph: Graph) -> list[set[str]]:
    """Sets of modules that import each other (strongly connected components of more than one module)."""
    return sorted((c for c in strongly_connected_components(graph) if len(c) > 1), key=lambda c: sorted(c))


def shortest_cycle(graph: Graph, component: set[str]) -> list[str]:
    """A shortest cycle through the alphabetically first module of ``component``: [a, b, ..., a]."""
    start = min(component)
    parent: dict[str, str] = {}
    queue = deque([start])
    while queue:
        node = queue.popleft()
        for succ in sorted(graph[node]):
            if succ not in component:
                continue
            if succ == start:
                path = [node]  # node, its BFS parent, ..., start
                while path[-1] != start:
                    path.append(parent[path[-1]])
                return [*reversed(path), start]
            if succ not in parent:
                parent[succ] = node
                queue.append(succ)
    raise AssertionError(f"{sorted(component)} is not a cycle")


def describe_cycle(graph: Graph, component: set[str]) -> str:
    cycle = shortest_cycle(graph, component)
    lines = [f"import cycle among {len(component)} modules {sorted(component)}:", "  " + " -> ".join(cycle)]
    for src, dst in zip(cycle, cycle[1:]):
        lines.append(f"    {src} -> {dst}: {', '.join(graph[src][dst])}")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------- the project
def test_project_has_no_import_cycles():
    graph = import_graph()
    cycles = import_cycles(graph)
    report = "\n\n".join(describe_cycle(graph, c) for c in cycles)
    if report:
        print(report)
    assert not cycles, report


def test_graph_sees_the_project_imports():
    """Module-level, function-level and package imports of the real tree all become edges."""
    graph = import_graph()
    assert "denoisers.training.models" in graph["denoisers.training.job"]        # module level
    assert "scenegen.custom.scene" in graph["scenegen.render"]                    # inside a function
    assert "denoisers.registry" in graph["benchmarks.denoiser_speed"]             # from denoisers import registry
    assert "denoisers.native" in graph["benchmarks.denoiser_speed"]
    assert "denoisers.nets.rae" in graph["denoisers.nets"]                        # package __init__ -> submodule


# ------------------------------------------------------------------------------- the checker itself
def _write(root: Path, files: dict[str, str]) -> None:
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


def test_checker_resolves_imports(tmp_path):
    _write(tmp_path, {
        "pkg/__init__.py": "from pkg import registry\nfrom . import helpers as h\n",
        "pkg/registry.py": "import os\nimport pkg.sub.deep\n",
        "pkg/helpers.py": "from .registry import thing, other\nfrom pkg import CONSTANT\n",
        "pkg/sub/__init__.py": "",
        "pkg/sub/deep.py": "def f():\n    from .. import helpers\n    from ..sub import deep\n",
        "tools/run.py": "import sibling\nfrom pkg.registry import x\n",
        "tools/sibling.py": "",
    })
    graph = import_graph(tmp_path, ("pkg", "tools"))
    assert graph == {
        "pkg": {"pkg.registry": ["pkg/__init__.py:1"], "pkg.helpers": ["pkg/__init__.py:2"]},
        "pkg.registry": {"pkg.sub.deep": ["pkg/registry.py:2"]},
        "pkg.helpers": {"pkg.registry": ["pkg/helpers.py:1"], "pkg": ["pkg/helpers.py:2"]},
        "pkg.sub": {},
        "pkg.sub.deep": {"pkg.helpers": ["pkg/sub/deep.py:2"]},  # ``from ..sub import deep``: itself
        "tools.run": {"tools.sibling": ["tools/run.py:1"], "pkg.registry": ["tools/run.py:2"]},
        "tools.sibling": {},
    }
    cycles = import_cycles(graph)
    assert cycles == [{"pkg", "pkg.helpers", "pkg.registry", "pkg.sub.deep"}]
    message = describe_cycle(graph, cycles[0])
    assert "pkg -> pkg.helpers -> pkg" in message and "pkg/helpers.py:2" in message


def test_checker_finds_a_function_level_cycle(tmp_path):
    _write(tmp_path, {
        "app/__init__.py": "",
        "app/a.py": "from app.b import g\n\ndef f():\n    return g()\n",
        "app/b.py": "def g():\n    from app import a\n    return a\n",
        "app/c.py": "from app import a, b\n",
    })
    graph = import_graph(tmp_path, ("app",))
    assert import_cycles(graph) == [{"app.a", "app.b"}]
    assert shortest_cycle(graph, {"app.a", "app.b"}) == ["app.a", "app.b", "app.a"]


def test_scoring_jobs_do_not_import_torch() -> None:
    """The evaluate / score-scenario commands (several hundred short jobs per run) check their config and load
    their modules without torch, whose import costs about 1.7 s each; a training command's check does import it."""
    import os
    import subprocess
    import sys

    probe = ("import sys\n"
             "from denoisers.cli import TORCH_FREE_COMMANDS, load_evaluation_config\n"
             "import denoisers.jobs.scoring, denoisers.jobs.stability, denoisers.stability_metrics, denoisers.metrics\n"
             "assert {'evaluate', 'score-scenario'} <= TORCH_FREE_COMMANDS\n"
             "load_evaluation_config('config/config.yaml', build_models=False)\n"
             "print('torch' in sys.modules)\n"
             "load_evaluation_config('config/config.yaml')\n"
             "print('torch' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, check=True,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert out.stdout.split() == ["False", "True"], out.stdout + out.stderr
