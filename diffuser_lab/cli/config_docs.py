"""docs/config.md's tables of keys, generated from the schema (:mod:`diffuser_lab.config`).

    python -m diffuser_lab.cli.config_docs            # rewrite the tables in docs/config.md
    python -m diffuser_lab.cli.config_docs --check    # exit 1 when docs/config.md is stale

One table per section of the schema (``graph``, ``scene.options``, ...): each key's type, its
default in the schema (a group's YAML file may set another), its range or choices (the declared
constraint of its field, the enum's values, or the names its registry has) and the comment
written beside it in config.py. Only the text between the two markers is generated; the prose
around them is the page's own.
"""
from __future__ import annotations

import ast
import dataclasses
import inspect
import io
import re
import sys
import tokenize
import typing
from enum import Enum
from pathlib import Path
from typing import Any, Optional, Sequence

from omegaconf import MISSING

from diffuser_lab import config
from diffuser_lab.data.capture import CaptureOptions
from diffuser_lab.data.sources import SOURCES
from diffuser_lab.runs.protocols import PROTOCOLS
from diffuser_lab.runs.resolve import names

BEGIN = ("<!-- keys: generated from diffuser_lab/config.py by `python -m diffuser_lab.cli.config_docs`; "
         "do not edit by hand -->")
END = "<!-- end of the generated keys -->"
DOC = Path(__file__).resolve().parents[2] / "docs" / "config.md"


def _comments(cls: type) -> dict[str, str]:
    """Each field of ``cls`` -> the comment written with it in the source: full-line comments
    right above it, then the comment at the end of its line(s)."""
    src = inspect.getsource(cls)
    lines = src.splitlines()
    by_line: dict[int, str] = {}
    for tok in tokenize.generate_tokens(io.StringIO(src).readline):
        if tok.type == tokenize.COMMENT:
            by_line[tok.start[0]] = tok.string.lstrip("#").strip()
    body = ast.parse(src).body[0]
    out = {}
    for node in body.body:
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        above = []
        ln = node.lineno - 1
        while ln >= 1 and lines[ln - 1].strip().startswith("#"):
            above.insert(0, by_line[ln])
            ln -= 1
        after = [by_line[i] for i in range(node.lineno, node.end_lineno + 1) if i in by_line]
        out[node.target.id] = " ".join(above + after)
    return out


def _section_type(hint: Any) -> Optional[type]:
    """The schema section (a :class:`~diffuser_lab.config.Section` dataclass) a field holds, or None."""
    for t in (hint, *typing.get_args(hint)):
        if isinstance(t, type) and dataclasses.is_dataclass(t):
            return t
    return None


def _type(hint: Any) -> str:
    args = typing.get_args(hint)
    origin = typing.get_origin(hint)
    if origin is typing.Union and type(None) in args:
        inner = [a for a in args if a is not type(None)]
        return f"{_type(inner[0])} or null"
    if origin in (list, typing.List):
        return f"list of {_type(args[0])}"
    if origin in (dict, typing.Dict):
        return "dict"
    if hint is Any:
        return "any"
    if isinstance(hint, type) and issubclass(hint, Enum):
        return "enum"
    return getattr(hint, "__name__", str(hint))


def _default(f: dataclasses.Field) -> str:
    if f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
        value = f.default_factory()  # type: ignore[misc]
    else:
        value = f.default
    if value is MISSING:
        return "required"
    if value is None:
        return "`null`"
    if isinstance(value, bool):
        return f"`{str(value).lower()}`"
    if isinstance(value, Enum):
        return f"`{value.name}`"
    return f"`{value}`"


def _choices(key: str, f: dataclasses.Field, hint: Any, registries: dict[str, list[str]]) -> str:
    if "registry" in f.metadata:
        return " / ".join(f"`{n}`" for n in registries.get(key, [])) + f" ({f.metadata['registry']})"
    check = f.metadata.get("check")
    if check is not None:
        return check.expected
    for t in (hint, *typing.get_args(hint)):
        if isinstance(t, type) and issubclass(t, Enum):
            return " / ".join(f"`{m.name}`" for m in t)
    return ""


def _text(text: str) -> str:
    """Markdown for plain text: outside code spans ``*`` escaped and ``<name>`` kept visible."""
    parts = text.split("`")
    for i in range(0, len(parts), 2):  # the even parts are outside code spans
        parts[i] = re.sub(r"<(?=[A-Za-z/])", "&lt;", parts[i].replace("*", "\\*"))
    return "`".join(parts)


def _cell(text: str) -> str:
    """:func:`_text` for a table cell (``|`` escaped too)."""
    return _text(text).replace("|", "\\|")


def _prose(doc: str) -> str:
    """A docstring's first paragraph as markdown: Sphinx roles dropped, ````x```` -> ```x```."""
    text = doc.split("\n\n")[0].replace("\n", " ")
    text = re.sub(r":(?:mod|func|class|meth|data):`~?([^`]+)`", r"`\1`", text)
    return _text(text.replace("``", "`"))


def _tables(cls: type, prefix: str, registries: dict[str, list[str]], *, title: str = "",
            skip: frozenset = frozenset()) -> list[str]:
    hints = typing.get_type_hints(cls)
    comments = {}
    for base in reversed(cls.__mro__):  # a field's comment is where it is declared
        if dataclasses.is_dataclass(base) and base.__module__ != "builtins":
            comments.update(_comments(base) if "__dataclass_fields__" in vars(base) else {})
    rows, nested = [], []
    for f in dataclasses.fields(cls):
        if f.name in skip:
            continue
        key = f"{prefix}.{f.name}" if prefix else f.name
        sub = _section_type(hints[f.name])
        if sub is not None:
            nested.append((sub, key))
            continue
        rows.append(f"| `{key}` | {_type(hints[f.name])} | {_cell(_default(f))} | "
                    f"{_cell(_choices(key, f, hints[f.name], registries))} | {_cell(comments.get(f.name, ''))} |")
    out = []
    if rows:
        doc = _prose(inspect.getdoc(cls) or "") if cls is not config.Config else ""
        out += [title or (f"### `{prefix}`" if prefix else "### (top level)"), ""]
        if doc:
            out += [doc, ""]
        out += ["| key | type | default | range / choices | comment |", "| --- | --- | --- | --- | --- |", *rows, ""]
    for sub, key in nested:
        out += _tables(sub, key, registries)
    return out


def generated() -> str:
    """The generated part of docs/config.md (between and with the markers)."""
    registries = names(PROTOCOLS)
    lines = [BEGIN, "", *_tables(config.Config, "", registries)]
    common = frozenset(f.name for f in dataclasses.fields(CaptureOptions))
    lines += _tables(CaptureOptions, "scene.options", registries,
                     title="### `scene.options` of every capture format (`diffuser_lab/data/capture.py`)")
    for entry in SOURCES.values():  # the scene sources that declare their keys: their own ones
        if entry.options is not None:
            own = common if issubclass(entry.options, CaptureOptions) else frozenset()
            lines += _tables(entry.options, "scene.options", registries, skip=own,
                             title=f"### `scene.options` of `scene={entry.name}` ({entry.description})")
    return "\n".join([*lines, END])


def render(text: str) -> str:
    """``text`` (docs/config.md) with its generated part replaced (appended if it has none)."""
    if BEGIN in text and END in text:
        head, rest = text.split(BEGIN, 1)
        tail = rest.split(END, 1)[1]
        return head + generated() + tail
    return text.rstrip("\n") + "\n\n" + generated() + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    text = DOC.read_text()
    new = render(text)
    if "--check" in args:
        if new != text:
            print(f"{DOC} is stale: run python -m diffuser_lab.cli.config_docs", file=sys.stderr)
            return 1
        return 0
    if new != text:
        DOC.write_text(new)
        print(f"wrote {DOC}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
