"""The code version that enters a stored model's key: a digest of the source that defines the network, its
inputs and the training step, insensitive to comments, docstrings and formatting.

What is hashed, for a trainable method:

* ``denoisers/training/tasks.py`` without the builder functions of other methods (and the statements that
  register them), so a change to AFN's builder does not re-key the RAE;
* every module of this project imported, at module level or inside a function, by that builder, by
  ``denoisers.training.loop`` / ``data`` (the step, the data stream) and by ``trainer_config`` of
  ``denoisers.training.job`` (how a spec becomes the trainer's settings), transitively;
* the C++ sources of ``denoisers.native`` when it is among them (comments stripped).

The package ``denoisers.nets`` rebuilds networks by name and so imports every network (as ``denoisers.registry``
and ``denoisers.methods`` do with the methods); their own source is hashed but their imports are not followed, so
another family's network does not re-key a model.

:func:`method_code_digest` is the same digest for a hand-set method's tuning (``store/tuning``): its registry
module and ``denoisers.jobs.tuning``, transitively.

How a module is hashed: ``ast.dump`` of its parsed source with every docstring removed and without line
numbers. Comments are not in the tree, and formatting is not in the dump, so neither changes the digest;
any change to a statement, expression, name or constant does.
"""
from __future__ import annotations

import ast
import functools
import hashlib
import json
import os
import re
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
#: Top-level packages of this project whose modules are followed.
PROJECT_PACKAGES = ("denoisers", "scenegen")
TASKS_MODULE = "denoisers.training.tasks"
#: Modules whose source is hashed but whose imports are not followed (name-based dispatchers).
DISPATCH_MODULES = frozenset({"denoisers.nets", "denoisers.registry", "denoisers.methods"})
#: Roots of every trainable method besides its builder: the training step and the data stream.
STEP_MODULES = ("denoisers.training.loop", "denoisers.training.data")
#: Functions of other modules that turn a spec into training settings: (module, function).
SETTINGS_FUNCTIONS = (("denoisers.training.job", "trainer_config"),)
NATIVE_PACKAGE = "denoisers.native"
_CPP_COMMENTS = re.compile(r"//[^\n]*|/\*.*?\*/", re.DOTALL)


def module_path(name: str, root: Path = REPO_ROOT) -> Path | None:
    """The source file of project module ``name`` (a package's ``__init__.py``), or None."""
    base = root.joinpath(*name.split("."))
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _strip_docstrings(tree: ast.AST) -> ast.AST:
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
                    and isinstance(body[0].value.value, str):
                node.body = body[1:] or [ast.Pass()]
    return tree


def normalized_source(source: str) -> str:
    """``source`` as a canonical dump of its syntax tree: comments, docstrings and formatting left out."""
    return ast.dump(_strip_docstrings(ast.parse(source)), annotate_fields=False, include_attributes=False)


def _imported_modules(tree: ast.AST, module: str, is_package: bool, root: Path) -> set[str]:
    """Project modules imported anywhere in ``tree`` (``from x import y`` counts y when it is a module)."""
    package = module if is_package else module.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(tree):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                parent = ".".join(parts[:len(parts) - node.level + 1])
                base = f"{parent}.{base}" if base else parent
            names = [base] + [f"{base}.{alias.name}" for alias in node.names]
        for name in names:
            # "import a.b.c" also imports a and a.b
            parts = name.split(".")
            for end in range(1, len(parts) + 1):
                candidate = ".".join(parts[:end])
                if parts[0] in PROJECT_PACKAGES and module_path(candidate, root) is not None:
                    found.add(candidate)
    found.discard(module)
    return found


def _builder_names() -> dict[str, str]:
    """Trainable method -> name of its builder function in tasks.py (from the runtime registry)."""
    from denoisers.training import tasks

    return {method: builder.build.__name__ for method, builder in tasks._TASKS.items()}


def _names_in(node: ast.AST) -> set[str]:
    return {sub.id for sub in ast.walk(node) if isinstance(sub, ast.Name)}


def _tasks_tree(method: str, root: Path) -> ast.Module:
    """tasks.py without the builders of other methods' families and the statements that register them."""
    path = module_path(TASKS_MODULE, root)
    assert path is not None, TASKS_MODULE
    builders = _builder_names()
    if method not in builders:
        raise KeyError(f"method {method!r} cannot be trained; trainable methods: {', '.join(sorted(builders))}")
    kept = builders[method]
    others = set(builders.values()) - {kept}
    tree = ast.parse(path.read_text())
    body = []
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.name in others:
            continue
        registers = any(isinstance(sub, ast.Call) and getattr(sub.func, "id", None) == "register_task"
                        or isinstance(sub, ast.Call) and getattr(getattr(sub, "func", None), "func", None) is not None
                        and getattr(sub.func.func, "id", None) == "register_task" for sub in ast.walk(node))
        if registers and not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            names = _names_in(node)
            if names & others and kept not in names:
                continue
        body.append(node)
    tree.body = body
    return tree


def _function_tree(module: str, function: str, root: Path) -> ast.Module:
    path = module_path(module, root)
    assert path is not None, module
    tree = ast.parse(path.read_text())
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.name == function:
            return ast.Module(body=[node], type_ignores=[])
    raise KeyError(f"{module} has no function {function!r} (denoisers.store.code.SETTINGS_FUNCTIONS)")


def _closure(trees: dict[str, ast.AST], root: Path) -> dict[str, ast.AST]:
    """``trees`` plus every project module they import, transitively (dispatch modules not followed)."""
    result = dict(trees)
    todo = [(name, tree) for name, tree in trees.items()]
    while todo:
        name, tree = todo.pop()
        if name in DISPATCH_MODULES:
            continue
        path = module_path(name.split(":")[0], root)
        is_package = path is not None and path.name == "__init__.py"
        for imported in sorted(_imported_modules(tree, name.split(":")[0], is_package, root)):
            if imported in result:
                continue
            imported_path = module_path(imported, root)
            assert imported_path is not None
            result[imported] = ast.parse(imported_path.read_text())
            todo.append((imported, result[imported]))
    return result


def code_files(method: str, root: Path = REPO_ROOT) -> dict[str, str]:
    """Name -> normalised source of every piece of code that determines ``method``'s trained weights."""
    trees: dict[str, ast.AST] = {TASKS_MODULE: _tasks_tree(method, root)}
    for module in STEP_MODULES:
        path = module_path(module, root)
        assert path is not None, module
        trees[module] = ast.parse(path.read_text())
    for module, function in SETTINGS_FUNCTIONS:
        trees[f"{module}:{function}"] = _function_tree(module, function, root)
    closure = _closure(trees, root)
    files = {name: ast.dump(_strip_docstrings(tree), annotate_fields=False, include_attributes=False)
             for name, tree in closure.items()}
    if NATIVE_PACKAGE in closure:
        native_dir = root.joinpath(*NATIVE_PACKAGE.split("."))
        for source in sorted(native_dir.glob("*.cpp")):
            text = _CPP_COMMENTS.sub("", source.read_text())
            files[f"{NATIVE_PACKAGE}/{source.name}"] = " ".join(text.split())
    return dict(sorted(files.items()))


#: How many source fingerprints the on-disk digest cache keeps (one per code version seen lately).
CACHE_VERSIONS = 8


def source_fingerprint(root: Path = REPO_ROOT) -> str:
    """SHA-256 of the raw bytes of every file a code digest can read: the project packages' ``.py`` files and the
    native ``.cpp`` sources below ``root``. Equal fingerprints give equal code digests."""
    digest = hashlib.sha256()
    for package in PROJECT_PACKAGES:
        for path in sorted((root / package).rglob("*")):
            if path.suffix in (".py", ".cpp") and "__pycache__" not in path.parts and "_build" not in path.parts:
                digest.update(path.relative_to(root).as_posix().encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()


def digest_cache_file() -> Path:
    """The on-disk cache of code digests across processes (a Snakefile parse keys every model: seconds of AST
    work per process otherwise): ``$XDG_CACHE_HOME/mcdenoise-harness/code_digests.json``."""
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "mcdenoise-harness" / "code_digests.json"


def _read_cache() -> dict[str, dict[str, str]]:
    try:
        cache = json.loads(digest_cache_file().read_text())
        return cache if isinstance(cache, dict) else {}
    except (OSError, ValueError):
        return {}


def _write_cache(fingerprint: str, method: str, value: str) -> None:
    cache = _read_cache()
    entry = cache.pop(fingerprint, {})
    cache[fingerprint] = {**entry, method: value}            # most recently written last
    while len(cache) > CACHE_VERSIONS:
        cache.pop(next(iter(cache)))
    path = digest_cache_file()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        temporary.write_text(json.dumps(cache))
        os.replace(temporary, path)
    except OSError:
        pass                                                  # a read-only home: compute again next time


@functools.lru_cache(maxsize=64)
def _cached_digest(method: str, root: str) -> str:
    fingerprint = source_fingerprint(Path(root))          # covers this module, so the digest rules too
    cached = _read_cache().get(fingerprint, {}).get(method)
    if cached:
        return cached
    files = code_files(method, Path(root))
    digest = hashlib.sha256()
    for name, text in files.items():
        digest.update(name.encode() + b"\0" + hashlib.sha256(text.encode()).hexdigest().encode() + b"\n")
    _write_cache(fingerprint, method, digest.hexdigest())
    return digest.hexdigest()


def code_digest(method: str, root: Path = REPO_ROOT) -> str:
    """SHA-256 over :func:`code_files` of trainable method ``method`` (cached per process, and across processes
    under :func:`source_fingerprint` in :func:`digest_cache_file`)."""
    return _cached_digest(method, str(root))


def method_module(method: str, root: Path = REPO_ROOT) -> str:
    """The module of ``denoisers/methods/`` whose ``@register("<method>", ...)`` defines registry method ``method``
    (found in the source, without importing the methods)."""
    for path in sorted((root / "denoisers" / "methods").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "register" and node.args \
                    and isinstance(node.args[0], ast.Constant) and node.args[0].value == method:
                return f"denoisers.methods.{path.stem}"
    raise KeyError(f"no module of denoisers/methods registers method {method!r}")


@functools.lru_cache(maxsize=64)
def _cached_method_digest(method: str, root: str) -> str:
    base = Path(root)
    roots = {name: ast.parse(module_path(name, base).read_text())  # type: ignore[union-attr]
             for name in (method_module(method, base), "denoisers.jobs.tuning")}
    digest = hashlib.sha256()
    for name, tree in sorted(_closure(roots, base).items()):
        text = ast.dump(_strip_docstrings(tree), annotate_fields=False, include_attributes=False)
        digest.update(name.encode() + b"\0" + hashlib.sha256(text.encode()).hexdigest().encode() + b"\n")
    return digest.hexdigest()


def method_code_digest(method: str, root: Path = REPO_ROOT) -> str:
    """Digest of the code a hand-set method's tuning result depends on (its module and the grid search)."""
    return _cached_method_digest(method, str(root))
