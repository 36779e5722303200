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


# ---------------------------------------------------------------------------------------------
# private names stay in their module, runs/ functions stay short, no code written twice (issue 59)


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def _private_uses(parsed: dict[str, tuple[Path, ast.Module]]):
    """(module, what) for every private name one module of the package takes from another: ``from
    .x import _y``, ``from diffuser_lab.x import _y``, ``x._y`` on a module ``x`` imported, and a
    private module (``_x``) imported from outside the package that holds it (``from . import
    _unrolled`` inside ``backends/numba/`` is its own)."""
    def own(m: str, private_module: str) -> bool:  # m lives in the package that holds private_module
        parent = private_module.rsplit(".", 1)[0]
        return m == private_module or m.startswith(parent + ".") or m == parent

    mods = {m: f for m, (f, _) in parsed.items()}
    for m, (f, tree) in parsed.items():
        pkg = m.split(".") if f.name == "__init__.py" else m.split(".")[:-1]
        bound = {}  # local name -> module of the package
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                base = pkg[: len(pkg) - node.level + 1] if node.level else []
                root = ".".join(base + ([node.module] if node.module else []))
                if root != "diffuser_lab" and not root.startswith("diffuser_lab."):
                    continue
                parts = root.split(".")
                for i in range(1, len(parts)):
                    if _private(parts[i]) and not own(m, ".".join(parts[: i + 1])):
                        yield m, ".".join(parts[: i + 1])
                for a in node.names:
                    full = f"{root}.{a.name}"
                    if full in mods:
                        bound[a.asname or a.name] = full
                        if _private(a.name) and not own(m, full):
                            yield m, full
                    elif _private(a.name) and root != m:
                        yield m, full
            elif isinstance(node, ast.Import):
                for a in node.names:
                    if a.asname and a.name in mods:
                        bound[a.asname] = a.name
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and _private(node.attr) and isinstance(node.value, ast.Name) \
                    and node.value.id in bound:
                target = bound[node.value.id]
                full = f"{target}.{node.attr}"
                if target != m and not (full in mods and own(m, full)):
                    yield m, full


PRIVATE_USES_ALLOWED: set[tuple[str, str]] = set()
"""Private names a module may still take from another: none since issue 59's runs/ refactor (runs/work.py,
method/space.py made them public). This set only shrinks: a fixed entry fails
test_allowed_private_uses_still_exist until it is removed here."""


@functools.lru_cache(maxsize=1)
def _package_private_uses() -> frozenset:
    return frozenset(_private_uses(_parsed()))


def test_no_private_name_used_across_modules():
    """A name with a leading underscore is its module's own: another module that needs it gets it
    made public (or moved to where both can import it)."""
    bad = sorted(_package_private_uses() - PRIVATE_USES_ALLOWED)
    assert not bad, "private names used across modules:\n" + "\n".join(f"{m} uses {t}" for m, t in bad)


def test_allowed_private_uses_still_exist():
    """Every entry of :data:`PRIVATE_USES_ALLOWED` is still a use (the allowlist only shrinks)."""
    gone = sorted(PRIVATE_USES_ALLOWED - _package_private_uses())
    assert not gone, "fixed: remove from PRIVATE_USES_ALLOWED:\n" + "\n".join(f"{m} uses {t}" for m, t in gone)


def test_the_private_use_scan_sees_each_form(tmp_path):
    """The scan catches ``from .x import _y``, ``from diffuser_lab.x import _y``, ``x._y`` and a private
    module imported from outside its package, and lets a package's own private modules be."""
    pkg = tmp_path / "diffuser_lab"
    (pkg / "a" / "deep").mkdir(parents=True)
    (pkg / "b").mkdir()
    files = {"__init__.py": "", "a/__init__.py": "", "a/x.py": "def _y(): pass\ndef z(): pass\n",
             "a/_hidden.py": "def k(): pass\n", "a/deep/__init__.py": "", "a/deep/own.py": "from .. import _hidden\n",
             "a/own.py": "from . import _hidden\nfrom ._hidden import k\n",
             "b/__init__.py": "", "b/rel.py": "from ..a.x import _y\n", "b/abs.py": "from diffuser_lab.a.x import _y, z\n",
             "b/attr.py": "from diffuser_lab.a import x\nx.z()\nx._y()\n", "b/mod.py": "from diffuser_lab.a._hidden import k\n"}
    for name, text in files.items():
        (pkg / name).write_text(text)
    mods = {}
    for f in pkg.rglob("*.py"):
        name = ".".join(f.relative_to(tmp_path).with_suffix("").parts)
        mods[name[: -len(".__init__")] if name.endswith(".__init__") else name] = (f, ast.parse(f.read_text()))
    assert sorted(set(_private_uses(mods))) == [
        ("diffuser_lab.b.abs", "diffuser_lab.a.x._y"), ("diffuser_lab.b.attr", "diffuser_lab.a.x._y"),
        ("diffuser_lab.b.mod", "diffuser_lab.a._hidden"), ("diffuser_lab.b.rel", "diffuser_lab.a.x._y")]


MAX_RUNS_FUNCTION = 80
"""The most lines a function of ``runs/`` may take, its docstring not counted."""

LONG_RUNS_FUNCTIONS: dict[str, int] = {}
"""Functions of runs/ allowed over MAX_RUNS_FUNCTION, each with its length as a ceiling: none since issue
59's refactor (pipeline._run 186, single_frame 174, online 121, tiled 97 before). This only shrinks: one at
or under MAX_RUNS_FUNCTION fails test_allowed_long_functions_are_still_long until it is removed here, one
that grows past its figure fails test_runs_functions_are_short."""


def _function_lengths(folder: Path, root: Path = PKG) -> dict[str, int]:
    """'path::qualified.name' (path relative to ``root``): lines of the body, its docstring not counted,
    for every function (methods and nested functions too) of the Python files below ``folder``."""
    out = {}

    def visit(node, prefix, rel):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                name = f"{prefix}{child.name}"
                if not isinstance(child, ast.ClassDef):
                    body = child.body
                    if isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
                            and isinstance(body[0].value.value, str) and len(body) > 1:
                        body = body[1:]
                    out[f"{rel}::{name}"] = child.end_lineno - body[0].lineno + 1
                visit(child, name + ".", rel)
            else:
                visit(child, prefix, rel)

    for f in sorted(folder.rglob("*.py")):
        tree = _parsed()[_name_of(f)][1] if root == PKG else ast.parse(f.read_text())  # the package's: parsed once
        visit(tree, "", f.relative_to(root).as_posix())
    return out


def _too_long(lengths: dict[str, int], allowed: dict[str, int] = LONG_RUNS_FUNCTIONS) -> dict[str, int]:
    """The functions of ``lengths`` over :data:`MAX_RUNS_FUNCTION` lines, or over their figure in ``allowed``."""
    return {k: n for k, n in lengths.items() if n > allowed.get(k, MAX_RUNS_FUNCTION)}


def test_runs_functions_are_short():
    """A run's code reads as steps: no function of ``runs/`` over :data:`MAX_RUNS_FUNCTION` lines
    (:data:`LONG_RUNS_FUNCTIONS`: today's, none longer than it is)."""
    long = _too_long(_function_lengths(PKG / "runs"))
    assert not long, f"functions of runs/ over {MAX_RUNS_FUNCTION} lines (or longer than allowed): {long}"


def test_allowed_long_functions_are_still_long():
    lengths = _function_lengths(PKG / "runs")
    done = sorted(k for k in LONG_RUNS_FUNCTIONS if lengths.get(k, 0) <= MAX_RUNS_FUNCTION)
    assert not done, f"short now (or gone): remove from LONG_RUNS_FUNCTIONS: {done}"


def test_function_length_counts_the_body_without_its_docstring(tmp_path):
    d = tmp_path / "runs"
    d.mkdir()
    (d / "m.py").write_text('def f():\n    """doc\n    more"""\n    a = 1\n\n    return a\n\n\n'
                            'class C:\n    def g(self):\n        def h():\n            pass\n        return h\n')
    assert _function_lengths(d, tmp_path) == {"runs/m.py::f": 3, "runs/m.py::C.g": 3, "runs/m.py::C.g.h": 1}


def test_the_length_guard_catches_a_planted_long_function(tmp_path):
    """A planted function one line over the limit fails the guard, one at the limit passes, and an
    allowed one fails once it grows past its figure."""
    d = tmp_path / "runs"
    d.mkdir()
    body = lambda n: "".join(f"    x{i} = {i}\n" for i in range(n))  # noqa: E731
    (d / "m.py").write_text(f'def ok():\n    """doc"""\n{body(MAX_RUNS_FUNCTION)}\n\n'
                            f"def over():\n{body(MAX_RUNS_FUNCTION + 1)}\n\n"
                            f"def allowed():\n{body(MAX_RUNS_FUNCTION + 20)}\n")
    lengths = _function_lengths(d, tmp_path)
    assert _too_long(lengths, {}) == {"runs/m.py::over": 81, "runs/m.py::allowed": 100}
    assert _too_long(lengths, {"runs/m.py::over": 81, "runs/m.py::allowed": 100}) == {}
    assert _too_long(lengths, {"runs/m.py::over": 81, "runs/m.py::allowed": 99}) == {"runs/m.py::allowed": 100}


DUPLICATES_ALLOWED = {
    # pairs of places that `duplicates` lists, outside generated code, judged not worth one shared piece;
    # this only shrinks (a pair no longer listed fails test_allowed_duplicates_still_exist)
    ("backends/numba/sparse.py", "backends/numba/sparse.py"):
        "two compiled row kernels' accumulators set to zero (7 lines of initial values)",
    ("data/simulate.py", "data/sources/demo.py"):
        "two signatures' keyword defaults (shape alone); data/ is not this guard's to change",
}


def _generated_by(path: Path) -> str | None:
    """The module that generates ``path`` (its first line: 'Generated by ``python -m MODULE``'), else None."""
    first = path.read_text().split("\n", 1)[0]
    if "Generated by" not in first or "python -m " not in first:
        return None
    return first.split("python -m ", 1)[1].split("`", 1)[0].strip()


def _duplicates_of(repo: Path) -> list[tuple[str, str, str]]:
    """(file, file, flags) for every pair that ``duplicates`` lists below ``repo`` (paths relative to it)."""
    import re
    import shutil
    import subprocess

    import pytest

    exe = shutil.which("duplicates")
    if exe is None:
        pytest.skip("the duplicates command is not on PATH here (it is a developer tool, not a dependency)")
    out = subprocess.run([exe, "--repo", str(repo), "--most", "200", "--seconds", "120"], capture_output=True,
                         text=True, timeout=300).stdout
    assert "incomplete:" not in out, out  # the rows would speak only of what was read
    rows = re.findall(r"^D\d+ (\S+):\d+-\d+ ~ (\S+):\d+-\d+(.*)$", out, flags=re.M)
    assert rows or out.startswith("no duplicates"), out
    return [(a, b, rest) for a, b, rest in rows]


@functools.lru_cache(maxsize=1)
def _duplicate_pairs() -> list[tuple[str, str, str]]:
    """:func:`_duplicates_of` the package."""
    return _duplicates_of(PKG)


def _generated_pair(a: str, b: str, root: Path = PKG) -> bool:
    """Both sides generated, or one generated and the other the module that generates it (its template)."""
    ga, gb = _generated_by(root / a), _generated_by(root / b)
    as_module = lambda p: f"{root.name}." + p[:-3].replace("/", ".")  # noqa: E731
    return (ga is not None and gb is not None) or (ga is not None and ga == as_module(b)) or \
        (gb is not None and gb == as_module(a))


def _written_twice(pairs, root: Path = PKG, allowed=DUPLICATES_ALLOWED) -> list[tuple[str, str, str]]:
    """The pairs of ``pairs`` that are neither generated, nor marked ``boilerplate``, nor ``allowed``."""
    return [(a, b, flags.strip()) for a, b, flags in pairs
            if "boilerplate" not in flags and not _generated_pair(a, b, root) and tuple(sorted((a, b))) not in allowed]


def test_code_is_written_once():
    """``duplicates`` on the package lists only generated code (the Jacobi kernels of ``_unrolled.py``, and
    their template in ``jacobi.py``), rows it marks ``boilerplate`` (most of what they share is thin:
    runs of ``@property`` getters, keyword lists) and :data:`DUPLICATES_ALLOWED`."""
    bad = _written_twice(_duplicate_pairs())
    assert not bad, "code written twice (duplicates --repo diffuser_lab):\n" + "\n".join(f"{a} ~ {b} {f}" for a, b, f in bad)


def test_allowed_duplicates_still_exist():
    listed = {tuple(sorted((a, b))) for a, b, _ in _duplicate_pairs()}
    gone = sorted(set(DUPLICATES_ALLOWED) - listed)
    assert not gone, f"no longer listed: remove from DUPLICATES_ALLOWED: {gone}"


def test_the_duplicates_guard_catches_a_planted_copy(tmp_path):
    """A function copied by hand into a second module fails the guard; a generated module's copies of its
    template, and an allowed pair, do not."""
    pkg = tmp_path / "diffuser_lab"
    pkg.mkdir()
    fn = "def {name}(a, b):\n" + "".join(f"    a = a * {i} + b - {i + 1}\n    b = (b - a) // {i + 2}\n" for i in range(5)) \
        + "    return a, b\n"
    (pkg / "one.py").write_text(fn.format(name="mix") + "\n\ndef other():\n    return 1\n")
    (pkg / "two.py").write_text("X = 3\n\n\n" + fn.format(name="mix"))
    kernel = "def {name}(z, out):\n    for i in range(len(z)):\n" + "".join(
        f"        if z[i] > {i}:\n            out[i] += z[i] * {i}\n" for i in range(5))  # another shape
    (pkg / "gen.py").write_text('TEMPLATE = """\n' + kernel.format(name="kernel_W") + '"""\n')
    (pkg / "_made.py").write_text("# Generated by ``python -m diffuser_lab.gen``: do not edit.\n\n"
                                  + kernel.format(name="kernel_16") + "\n\n" + kernel.format(name="kernel_32"))
    pairs = _duplicates_of(pkg)
    bad = {tuple(sorted((a, b))) for a, b, _ in _written_twice(pairs, pkg, {})}
    assert bad == {("one.py", "two.py")}, pairs
    assert {tuple(sorted((a, b))) for a, b, _ in pairs} >= {("_made.py", "_made.py"), ("_made.py", "gen.py")}, pairs  # generated, or the generated module and its template
    assert not _written_twice(pairs, pkg, {p: "planted" for p in bad})
