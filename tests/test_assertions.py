"""Assertions that cannot fail, found in the tests themselves by their syntax (``ast``): a test that
asserts something true of every value proves nothing (issue 48). Reported, and none are left:

- a value compared with itself (``f(x) == f(x)``, ``a is a``);
- ``>= 0`` (or ``> -1``) on what is never negative: ``len()``, counts, sizes, sums of ``abs``, times,
  and the scores this project prints (mIoU, accuracy, coverage are percentages of counts);
- ``0 <= x <= 1`` on a share (a mean of booleans, a ratio of counts), ``0 <= x <= 100`` on a percentage;
- a range whose literal bounds are 1,000 or more apart (wide enough to hold any plausible value);
- ``is not None`` (or ``isinstance``) on a name the statement just before assigned from a constructor
  or a call that never returns None;
- ``assert <constant>`` (``assert True``, ``assert (x, "why")``: a tuple is true) and an ``or`` with a
  true constant (``assert x or True``);
- a chained range written downwards (``1 >= share >= 0``) is checked as the same range upwards, and
  one whose bounds are reversed (``5 <= x <= 1``) is reported: it holds for no value;
- ``np.testing.assert_*(a, a)`` (and ``a == pytest.approx(a)``): a value compared with itself;
- a bound that holds for every value of a metric's documented range (:data:`DOCUMENTED_RANGES`:
  ``0 <= ece <= 100``, ``brier <= 2``, ``peak_rss > 0``, ...).

Every ``*.py`` under tests/ is scanned: the test modules and their helpers (conftest.py, captures.py,
datasets.py, ...), whose assertions the tests run.
"""
from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent

NONNEG = re.compile(r"(^|_)(len|n|count|counts|size|sizes|num|n_\w+|miou|accuracy|acc|coverage|cover|time|times|"
                    r"wall|seconds|elapsed|bytes|frames|points|rows|iterations|its|steps|links|seen|labelled|"
                    r"share|frac|fraction|ratio)($|_)")
"""Names (a variable, an attribute, a subscript key) of what cannot be negative."""


INF = float("inf")
DOCUMENTED_RANGES = [
    (re.compile(r"(^|_)ece($|_)"), 0.0, 100.0, False),  # expected calibration error, percent
    (re.compile(r"(^|_)(miou|iou|accuracy|acc|coverage|cover)($|_)"), 0.0, 100.0, False),  # percentages
    (re.compile(r"(^|_)brier($|_)"), 0.0, 2.0, False),  # Brier score of a probability vector
    (re.compile(r"(^|_)nll($|_)"), 0.0, INF, False),  # negative log-likelihood
    (re.compile(r"(^|_)(share|frac|fraction)($|_)"), 0.0, 1.0, False),
    (re.compile(r"(^|_)(rss|peak_rss|peak_rss_gb|start_rss_gb|rss_gb|vm|vmsize)($|_)"), 0.0, INF, True),  # > 0 always
]
"""A metric's documented range as (name pattern, low, high, open at low): a bound on a value of that
name that every value in the range meets (``0 <= ece <= 100``, ``nll >= 0``, ``peak_rss_gb > 0``) is
reported. Open at low: the value is never the low end itself (a process's resident memory)."""


def _name(node: ast.AST) -> str:
    """The name an expression reads: ``x`` of ``x``, ``a.b``, ``a["b"]``, ``f(...)`` -> ``f``."""
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return node.attr
    if isinstance(node, ast.Subscript):
        key = node.slice
        if isinstance(key, ast.Constant) and isinstance(key.value, str):
            return key.value
        return _name(node.value)
    if isinstance(node, ast.Call):
        return _name(node.func)
    return ""


def _never_negative(node: ast.AST) -> bool:
    if isinstance(node, ast.Call):
        f = _name(node.func)
        if f in ("len", "abs", "count_nonzero", "sum", "mean") and isinstance(node.func, ast.Name) or f in (
                "len", "count_nonzero", "perf_counter", "time"):
            return True
        if f in ("sum", "mean", "max", "min") and isinstance(node.func, ast.Attribute):
            inner = node.func.value  # (a == b).mean(), np.abs(x).max()
            return isinstance(inner, ast.Compare) or (isinstance(inner, ast.Call) and _name(inner.func) in ("abs",))
        return False
    return bool(NONNEG.search(_name(node).lower()))


def _num(node: ast.AST):
    if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)) and not isinstance(node.value, bool):
        return float(node.value)
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
        v = _num(node.operand)
        return None if v is None else -v
    if isinstance(node, ast.BinOp) and isinstance(node.op, (ast.Mult, ast.Pow, ast.Div)):
        a, b = _num(node.left), _num(node.right)
        if a is None or b is None:
            return None
        return a * b if isinstance(node.op, ast.Mult) else a ** b if isinstance(node.op, ast.Pow) else (a / b if b else None)
    return None


def _share(node: ast.AST) -> bool:
    """A mean of booleans or a ratio of counts: in [0, 1] by construction."""
    if isinstance(node, ast.Call) and _name(node.func) == "mean":
        arg = node.args[0] if node.args else (node.func.value if isinstance(node.func, ast.Attribute) else None)
        return isinstance(arg, ast.Compare) or (isinstance(node.func, ast.Attribute) and isinstance(node.func.value, ast.Compare))
    return bool(re.search(r"(^|_)(share|frac|fraction)($|_)", _name(node).lower()))


def _truthy_constant(node: ast.AST) -> bool:
    """A literal that is true whatever the code does: a true constant, a non-empty tuple/list/set/dict,
    an f-string with text."""
    if isinstance(node, ast.Constant):
        return bool(node.value) and node.value is not Ellipsis
    if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
        return bool(node.elts)
    if isinstance(node, ast.Dict):
        return bool(node.keys)
    if isinstance(node, ast.JoinedStr):
        return any(isinstance(v, ast.Constant) and v.value for v in node.values)
    return False


_FLIP = {ast.Gt: ast.Lt, ast.GtE: ast.LtE, ast.Lt: ast.Gt, ast.LtE: ast.GtE}


def _upwards(t: ast.Compare) -> tuple[list, list]:
    """The chain's operands and operators with ``hi >= x >= lo`` turned into ``lo <= x <= hi``."""
    operands, ops = [t.left, *t.comparators], list(t.ops)
    if ops and all(isinstance(o, (ast.Gt, ast.GtE)) for o in ops):
        return operands[::-1], [_FLIP[type(o)]() for o in ops[::-1]]
    return operands, ops


def _bounds(operands: list, ops: list) -> list[tuple[ast.AST, tuple | None, tuple | None]]:
    """Each non-literal operand with its literal lower and upper bound in the chain, as (value,
    strict) pairs: ``0 <= x < 5`` -> [(x, (0, False), (5, True))]."""
    out = []
    for i, x in enumerate(operands):
        if _num(x) is not None:
            continue
        lo = hi = None
        if i > 0 and _num(operands[i - 1]) is not None:  # operands[i-1] OP x
            v, op = _num(operands[i - 1]), ops[i - 1]
            if isinstance(op, (ast.Lt, ast.LtE)):
                lo = (v, isinstance(op, ast.Lt))
            elif isinstance(op, (ast.Gt, ast.GtE)):
                hi = (v, isinstance(op, ast.Gt))
        if i + 1 < len(operands) and _num(operands[i + 1]) is not None:  # x OP operands[i+1]
            v, op = _num(operands[i + 1]), ops[i]
            if isinstance(op, (ast.Lt, ast.LtE)):
                hi = (v, isinstance(op, ast.Lt))
            elif isinstance(op, (ast.Gt, ast.GtE)):
                lo = (v, isinstance(op, ast.Gt))
        if lo or hi:
            out.append((x, lo, hi))
    return out


def _documented_range(x: ast.AST, lo, hi) -> str | None:
    """The range of :data:`DOCUMENTED_RANGES` a bound (lo, hi) on ``x`` holds for in full, said."""
    name = _name(x).lower()
    for pattern, a, b, open_low in DOCUMENTED_RANGES:
        if not pattern.search(name):
            continue
        low_ok = lo is None or lo[0] < a or lo[0] == a and (not lo[1] or open_low)
        high_ok = hi is None or hi[0] > b or hi[0] == b and not hi[1]
        if low_ok and high_ok:
            return f"{'(' if open_low else '['}{a:g}, {b:g}]"
    return None


def _self_compare_call(node: ast.Call) -> bool:
    """``np.testing.assert_*(a, a, ...)``, ``unittest``'s ``assertEqual(a, a)``: the first two arguments the same."""
    f = _name(node.func)
    return (f.startswith("assert_") or f.startswith("assert") and f[6:7].isupper()) and len(node.args) >= 2 \
        and ast.dump(node.args[0]) == ast.dump(node.args[1])


def _approx_of(node: ast.AST) -> ast.AST:
    """``x`` of ``pytest.approx(x, ...)``, else the node itself."""
    if isinstance(node, ast.Call) and _name(node.func) == "approx" and node.args:
        return node.args[0]
    return node


def findings_in(path: Path) -> list[str]:
    """Every assertion of ``path`` that cannot fail, as 'file:line: why'."""
    tree = ast.parse(path.read_text())
    out = []
    rel = path.relative_to(TESTS.parent) if path.is_relative_to(TESTS.parent) else path.name

    said = set()

    def say(node, why):
        if id(node) not in said:  # one reason per comparison
            said.add(id(node))
            out.append(f"{rel}:{node.lineno}: {why}: {ast.unparse(node)[:120]}")

    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and _self_compare_call(node):
            say(node, "a value compared with itself")
    bodies = [n.body for n in ast.walk(tree) if hasattr(n, "body") and isinstance(n.body, list)]
    for body in bodies:
        for prev, stmt in zip([None, *body[:-1]], body):
            if not isinstance(stmt, ast.Assert):
                continue
            if _truthy_constant(stmt.test):
                say(stmt, "'assert' on a true constant")
                continue
            if isinstance(stmt.test, ast.BoolOp) and isinstance(stmt.test.op, ast.Or) \
                    and any(_truthy_constant(v) for v in stmt.test.values):
                say(stmt.test, "an 'or' with a true constant")
                continue
            tests = stmt.test.values if isinstance(stmt.test, ast.BoolOp) and isinstance(stmt.test.op, ast.And) else [stmt.test]
            # all(x >= 0 for x in xs): the comparison inside
            tests = [t.args[0].elt if isinstance(t, ast.Call) and _name(t.func) == "all" and t.args
                     and isinstance(t.args[0], ast.GeneratorExp) else t for t in tests]
            for t in tests:
                if not isinstance(t, ast.Compare):
                    continue
                operands, ops = [t.left, *t.comparators], t.ops
                for (a, op, b) in zip(operands, ops, operands[1:]):
                    if isinstance(op, (ast.Eq, ast.Is, ast.GtE, ast.LtE)) and \
                            ast.dump(_approx_of(a)) == ast.dump(_approx_of(b)):
                        say(t, "a value compared with itself")
                    lo = _num(b)
                    if isinstance(op, ast.GtE) and lo is not None and lo <= 0 and _never_negative(a):
                        say(t, f"'>= {lo:g}' on what is never negative")
                    if isinstance(op, ast.Gt) and lo is not None and lo < 0 and _never_negative(a):
                        say(t, f"'> {lo:g}' on what is never negative")
                    base = a.value if isinstance(a, ast.Attribute) else a  # x, or x.attr
                    if isinstance(op, ast.IsNot) and isinstance(b, ast.Constant) and b.value is None \
                            and isinstance(base, ast.Name) and isinstance(prev, ast.Assign) \
                            and any(isinstance(x, ast.Name) and x.id == base.id for x in prev.targets) \
                            and isinstance(prev.value, ast.Call) and _name(prev.value.func)[:1].isupper():
                        say(t, "'is not None' on an object just constructed")
                operands, ops = _upwards(t)
                if len(operands) == 3 and all(isinstance(o, (ast.LtE, ast.Lt)) for o in ops):
                    lo, hi = _num(operands[0]), _num(operands[2])
                    if lo is not None and hi is not None:
                        if lo > hi:
                            say(t, f"a range whose bounds are reversed ({lo:g} > {hi:g}), true of no value")
                        elif lo <= 0 and hi >= 1 and _share(operands[1]) and hi <= 1:
                            say(t, "'0 <= x <= 1' on a share")
                        elif lo > 0 and hi / lo >= 1000:
                            say(t, f"a range {hi / lo:g} times wide")
                for x, lo, hi in _bounds(operands, ops):
                    whole = _documented_range(x, lo, hi)
                    if whole:
                        say(t, f"a bound every value of {_name(x)}'s documented range {whole} meets")
    return out


def findings(root: Path = TESTS) -> list[str]:
    """The scan of every module under ``root``: tests and their helpers."""
    return [f for p in sorted(root.rglob("*.py")) for f in findings_in(p)]


CANNOT_FAIL = {
    "self": ("assert f(a) == f(a)", "a value compared with itself"),
    "len >= 0": ("assert len(rows) >= 0", "'>= 0' on what is never negative"),
    "metric >= 0, and-ed": ("assert run.metrics['miou'] >= 0 and x > 1", "'>= 0' on what is never negative"),
    "inside all()": ("assert all(f['diffuser_miou'] >= 0 for f in frames)", "'>= 0' on what is never negative"),
    "share in [0, 1]": ("assert 0 <= np.mean(a == b) <= 1", "'0 <= x <= 1' on a share"),
    "1,000x wide": ("assert 0.1e9 < roof < 10e12", "a range 100000 times wide"),
    "constructed": ("g = Graph(pts)\n    assert g is not None", "'is not None' on an object just constructed"),
    "a constant": ("assert 1", "'assert' on a true constant"),
    "a tuple": ("assert (x == 1, 'x is one')", "'assert' on a true constant"),
    "or True": ("assert x > 3 or True", "an 'or' with a true constant"),
    "downwards": ("assert 1 >= np.mean(a == b) >= 0", "'0 <= x <= 1' on a share"),
    "reversed": ("assert 5 <= x <= 1", "a range whose bounds are reversed (5 > 1), true of no value"),
    "np.testing self": ("np.testing.assert_allclose(z.sum(1), z.sum(1), atol=1e-6)", "a value compared with itself"),
    "approx self": ("assert r.miou == pytest.approx(r.miou)", "a value compared with itself"),
    "ece in percent": ("assert 0 <= c['ece'] <= 100", "a bound every value of ece's documented range [0, 100] meets"),
    "ece downwards": ("assert 100 >= c['ece'] >= 0", "a bound every value of ece's documented range [0, 100] meets"),
    "brier": ("assert c['brier'] <= 2", "a bound every value of brier's documented range [0, 2] meets"),
    "nll": ("assert c['nll'] >= 0", "a bound every value of nll's documented range [0, inf] meets"),
    "peak memory": ("assert s['peak_rss_gb'] > 0", "a bound every value of peak_rss_gb's documented range (0, inf] meets"),
}
"""One snippet per kind of assertion that cannot fail, and the reason the scan gives."""

CAN_FAIL = ["assert False, 'unreachable'", "assert 0 < c['ece'] < 5", "assert 0.2 < share_equal < 0.9",
            "assert c['brier'] < 0.4", "assert c['nll'] > 0.1", "assert s['peak_rss_gb'] >= s['start_rss_gb'] + 0.05",
            "np.testing.assert_allclose(a, b)", "assert x > 3 or y", "assert 3 <= kept <= 3", "assert r.miou == pytest.approx(61.9)",
            "assert run.metrics['miou'] >= 50"]
"""Snippets the scan leaves alone: each can fail."""


def _scan(tmp_path, line: str) -> list[str]:
    bad = tmp_path / "test_bad.py"
    bad.write_text(f"def test_x(run):\n    {line}\n")
    return [f.split(": ", 1)[1] for f in findings_in(bad)]


@pytest.mark.parametrize("case", list(CANNOT_FAIL))
def test_the_scan_finds_each_kind_of_assertion_that_cannot_fail(case, tmp_path):
    line, why = CANNOT_FAIL[case]
    assert [f.split(": ", 1)[0] for f in _scan(tmp_path, line)] == [why]


@pytest.mark.parametrize("line", CAN_FAIL)
def test_the_scan_passes_assertions_that_can_fail(line, tmp_path):
    assert _scan(tmp_path, line) == []


def test_the_scan_reads_the_tests_helper_modules(tmp_path):
    """conftest.py, captures.py, ...: their assertions run inside the tests."""
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "helpers.py").write_text("def check(run):\n    assert 0 <= run['ece'] <= 100\n")
    (tmp_path / "conftest.py").write_text("def check(x):\n    np.testing.assert_array_equal(x, x)\n")
    found = findings(tmp_path)
    assert [f.split(":")[0] for f in found] == ["conftest.py", "helpers.py"]
    assert {p.name for p in TESTS.glob("*.py")} >= {"conftest.py", "captures.py", "datasets.py", "bounded.py"}  # scanned


def test_no_assertion_in_the_suite_cannot_fail():
    found = findings()
    assert not found, "assertions that cannot fail:\n" + "\n".join(found)
