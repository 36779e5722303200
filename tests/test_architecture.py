"""The package's import graph, drawn from the code with ``ast``: no import cycle, ``config.py`` at
the bottom importing nothing of the package, imports pointing down the layers (backends -> data ->
method -> runs -> recording -> cli), the package's own imports at the top of files, and one
diffusion core: no numba/numpy choice outside ``backends/``."""
from __future__ import annotations

import ast
import functools
from pathlib import Path

PKG = Path(__file__).resolve().parent.parent / "diffuser_lab"
LAYERS = ["config", "seeding", "progress", "hooks", "registry", "backends", "data", "method", "runs", "recording", "cli"]
"""Bottom to top: a module imports only its own layer and those below (the package face, the
package's ``__init__``, may import anything)."""


@functools.cache
def _parsed() -> dict[str, tuple[Path, ast.Module]]:
    """Every module of the package by its dotted name: (file, syntax tree), parsed once per process."""
    out = {}
    for f in PKG.rglob("*.py"):
        out[_name_of(f)] = (f, ast.parse(f.read_text()))
    return out


def _name_of(f: Path) -> str:
    name = ".".join(f.relative_to(PKG.parent).with_suffix("").parts)
    return name[: -len(".__init__")] if name.endswith(".__init__") else name


def _modules() -> dict[str, Path]:
    return {m: f for m, (f, _) in _parsed().items()}


def _import_nodes(tree: ast.AST):
    """(import node, inside a function?) for every import of ``tree``: one walk."""
    stack = [(tree, False)]
    while stack:
        node, inner = stack.pop()
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node, inner
        inner = inner or isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
        stack.extend((child, inner) for child in ast.iter_child_nodes(node))


@functools.cache
def _all_imports() -> tuple[tuple[str, str, bool], ...]:
    """(module, imported module, inside a function?) for every import of the package's own modules."""
    mods, out = _modules(), []
    for m, (f, tree) in _parsed().items():
        for node, inner in _import_nodes(tree):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                base = m.split(".") if f.name == "__init__.py" else m.split(".")[:-1]
                base = base[: len(base) - node.level + 1] if node.level else []
                root = ".".join(base + ([node.module] if node.module else []))
                targets = [root] + [f"{root}.{a.name}" for a in node.names]
            out += [(m, t, inner) for t in targets if t in mods and t != m and not m.startswith(t + ".")]
    return tuple(out)


def _imports(mods: dict[str, Path]):
    """(module, imported module, inside a function?) of the modules ``mods`` (the package's, parsed once)."""
    return [e for e in _all_imports() if e[0] in mods]


def _layer(module: str) -> int:
    part = module.split(".")[1] if "." in module else ""
    return LAYERS.index(part) if part in LAYERS else -1


def test_no_import_cycle():
    mods = _modules()
    faces = {m for m, f in mods.items() if f.name == "__init__.py" and m.count(".") <= 1}  # package faces
    edges: dict[str, set] = {m: set() for m in mods}
    for a, b, _ in _imports(mods):
        edges[a].add(b)
    cycles, color = [], {}

    def dfs(u, stack):
        color[u] = 1
        stack.append(u)
        for v in edges[u]:
            if v in faces and v.count(".") == 0:
                continue
            if color.get(v) == 1:
                cycles.append(stack[stack.index(v):] + [v])
            elif not color.get(v):
                dfs(v, stack)
        stack.pop()
        color[u] = 2

    for m in mods:
        if not color.get(m):
            dfs(m, [])
    assert not cycles, "import cycles:\n" + "\n".join(" -> ".join(c) for c in cycles)


def test_config_imports_nothing_of_the_package():
    mods = _modules()
    assert not [t for a, t, _ in _imports(mods) if a == "diffuser_lab.config"]


def test_imports_point_down_the_layers():
    mods = _modules()
    up = [(a, t) for a, t, _ in _imports(mods) if a != "diffuser_lab" and _layer(a) >= 0 and _layer(t) > _layer(a)]
    assert not up, "upward imports:\n" + "\n".join(f"{a} -> {t}" for a, t in up)


def test_package_imports_at_the_top_of_files():
    """Inside a function only to break what would be a cycle or defer a heavy optional dependency:
    at most 25 in all (the issue's bound)."""
    local = [(a, t) for a, t, inner in _imports(_modules()) if inner]
    assert len(local) <= 25, local


def test_no_compiled_or_numpy_choice_outside_backends():
    """Only backends/ imports numba or the compiled kernels (and the command line, which decides
    whether they compile now): everything else calls one function per operation."""
    asks = []
    for f in PKG.rglob("*.py"):
        rel = f.relative_to(PKG).as_posix()
        if rel.startswith(("backends/", "cli/")):
            continue
        for node, _ in _import_nodes(_parsed()[_name_of(f)][1]):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith(("numba", "diffuser_lab.backends.numba")):
                asks.append(rel)
            elif isinstance(node, ast.ImportFrom) and node.module == "diffuser_lab.backends" and \
                    any(a.name == "numba" for a in node.names):
                asks.append(rel)
            elif isinstance(node, ast.Import) and any(a.name.split(".")[0] == "numba" for a in node.names):
                asks.append(rel)
    assert not asks, asks


def test_tests_mirror_the_package():
    """A test is found where its code is: tests/<folder>/ for diffuser_lab/<folder>/ (and analysis/,
    benchmarks/); a folder without Python files is test data (tests/data/fuzz_corpus); no test module
    name twice (pytest imports them by their file names)."""
    tests = Path(__file__).resolve().parent
    folders = {p.relative_to(PKG).as_posix() for p in PKG.rglob("*") if p.is_dir() and not p.name.startswith("__")}
    for d in (p for p in tests.rglob("*") if p.is_dir() and not p.name.startswith("__")):
        rel = d.relative_to(tests).as_posix()
        assert rel in folders or rel.split("/")[0] in ("analysis", "benchmarks") or not any(d.rglob("*.py")), rel
    names = [p.name for p in tests.rglob("test_*.py")]
    assert len(names) == len(set(names)), sorted(n for n in names if names.count(n) > 1)


def test_scene_sources_import_shared_layers_only():
    """A scene source module (data/sources/<name>.py) imports the shared data layers, never another
    source: the registry (data/sources/__init__.py) is the one module that knows them all."""
    mods = _modules()
    src = {m for m, f in mods.items() if m.startswith("diffuser_lab.data.sources.")}
    bad = sorted({(a, b) for a, b, _ in _imports(mods) if a in src and b in src})
    assert not bad, bad
