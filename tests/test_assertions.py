"""Assertions that cannot fail, found in the tests themselves by their syntax (``ast``): a test that
asserts something true of every value proves nothing (issue 48). Reported, and none are left:

- a value compared with itself (``f(x) == f(x)``, ``a is a``);
- ``>= 0`` (or ``> -1``) on what is never negative: ``len()``, counts, sizes, sums of ``abs``, times,
  and the scores this project prints (mIoU, accuracy, coverage are percentages of counts);
- ``0 <= x <= 1`` on a share (a mean of booleans, a ratio of counts), ``0 <= x <= 100`` on a percentage;
- a range whose literal bounds are 1,000 or more apart (wide enough to hold any plausible value);
- ``is not None`` (or ``isinstance``) on a name the statement just before assigned from a constructor
  or a call that never returns None.
"""
from __future__ import annotations

import ast
import re
from pathlib import Path

TESTS = Path(__file__).resolve().parent

NONNEG = re.compile(r"(^|_)(len|n|count|counts|size|sizes|num|n_\w+|miou|accuracy|acc|coverage|cover|time|times|"
                    r"wall|seconds|elapsed|bytes|frames|points|rows|iterations|its|steps|links|seen|labelled|"
                    r"share|frac|fraction|ratio)($|_)")
"""Names (a variable, an attribute, a subscript key) of what cannot be negative."""


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


def findings_in(path: Path) -> list[str]:
    """Every assertion of ``path`` that cannot fail, as 'file:line: why'."""
    tree = ast.parse(path.read_text())
    out = []
    rel = path.relative_to(TESTS.parent) if path.is_relative_to(TESTS.parent) else path.name

    def say(node, why):
        out.append(f"{rel}:{node.lineno}: {why}: {ast.unparse(node)[:120]}")

    bodies = [n.body for n in ast.walk(tree) if hasattr(n, "body") and isinstance(n.body, list)]
    for body in bodies:
        for prev, stmt in zip([None, *body[:-1]], body):
            if not isinstance(stmt, ast.Assert):
                continue
            tests = stmt.test.values if isinstance(stmt.test, ast.BoolOp) and isinstance(stmt.test.op, ast.And) else [stmt.test]
            # all(x >= 0 for x in xs): the comparison inside
            tests = [t.args[0].elt if isinstance(t, ast.Call) and _name(t.func) == "all" and t.args
                     and isinstance(t.args[0], ast.GeneratorExp) else t for t in tests]
            for t in tests:
                if not isinstance(t, ast.Compare):
                    continue
                operands = [t.left, *t.comparators]
                for (a, op, b) in zip(operands, t.ops, operands[1:]):
                    if isinstance(op, (ast.Eq, ast.Is, ast.GtE, ast.LtE)) and ast.dump(a) == ast.dump(b):
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
                if len(operands) == 3 and all(isinstance(o, (ast.LtE, ast.Lt)) for o in t.ops):
                    lo, hi = _num(operands[0]), _num(operands[2])
                    if lo is not None and hi is not None:
                        if lo <= 0 and hi >= 1 and _share(operands[1]) and hi <= 1:
                            say(t, "'0 <= x <= 1' on a share")
                        elif lo > 0 and hi / lo >= 1000:
                            say(t, f"a range {hi / lo:g} times wide")
    return out


def findings(root: Path = TESTS) -> list[str]:
    return [f for p in sorted(root.rglob("test_*.py")) for f in findings_in(p)]


def test_the_scan_finds_each_kind_of_assertion_that_cannot_fail(tmp_path):
    bad = tmp_path / "test_bad.py"
    bad.write_text(
        "def test_x(run):\n"
        "    assert f(a) == f(a)\n"
        "    assert len(rows) >= 0\n"
        "    assert run.metrics['miou'] >= 0 and 0 <= np.mean(a == b) <= 1\n"
        "    assert 0.1e9 < roof < 10e12\n"
        "    g = Graph(pts)\n"
        "    assert g is not None\n"
        "    assert all(f['diffuser_miou'] >= 0 for f in frames)\n"
        "    assert run.metrics['miou'] >= 50 and 0.2 < share_equal < 0.9 and x >= 0\n")
    text = [ln.split(": ", 1)[1] for ln in findings_in(bad)]
    assert [t.split(":")[0] for t in text] == ["a value compared with itself", "'>= 0' on what is never negative",
                                                "'>= 0' on what is never negative", "'0 <= x <= 1' on a share",
                                                "a range 100000 times wide", "'is not None' on an object just constructed",
                                                "'>= 0' on what is never negative"]


def test_no_assertion_in_the_suite_cannot_fail():
    found = findings()
    assert not found, "assertions that cannot fail:\n" + "\n".join(found)
