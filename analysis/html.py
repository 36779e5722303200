"""A report's Markdown as one self-contained HTML page (``analysis.report --html``).

The Markdown :mod:`analysis.report` writes uses headings, paragraphs, ``- `` lists, pipe tables,
images on a line of their own and inline ``code`` / ``**bold**``; those are rendered, everything
else is escaped text. Images are inlined as base64 ``data:`` URIs: the page is one file that can be
mailed or attached to a review without the PNGs beside it.
"""
from __future__ import annotations

import base64
import html
import mimetypes
import re
from pathlib import Path

STYLE = """
body { font: 15px/1.45 system-ui, -apple-system, "Segoe UI", sans-serif; color: #1d1d1f; margin: 2em auto;
       max-width: 1400px; padding: 0 1.5em; }
h1 { font-size: 1.6em; margin-bottom: .3em; } h2 { font-size: 1.25em; margin-top: 1.8em;
     border-bottom: 1px solid #ddd; padding-bottom: .2em; }
code { background: #f2f2f4; padding: 0 .25em; border-radius: 3px; font-size: .92em; }
.table { overflow-x: auto; margin: .8em 0; }
table { border-collapse: collapse; font-size: 13px; font-variant-numeric: tabular-nums; }
th, td { border: 1px solid #d6d6d9; padding: .25em .55em; text-align: right; white-space: nowrap; }
th { background: #f4f5f7; position: sticky; top: 0; }
td:first-child, th:first-child { text-align: left; }
tr:nth-child(even) td { background: #fafafb; }
td.ns { color: #8a8a8e; }
td.diff small { color: #6e6e73; } td.diff strong { color: #1f4e8c; }
img { max-width: 100%; height: auto; display: block; margin: .8em 0; border: 1px solid #eee; }
"""
_IMAGE = re.compile(r"^!\[([^\]]*)\]\(([^)]+)\)$")


def _inline(text: str) -> str:
    text = html.escape(text, quote=False)
    text = re.sub(r"`([^`]+)`", r"<code>\1</code>", text)
    return re.sub(r"\*\*([^*]+)\*\*", r"<strong>\1</strong>", text)


def _image(alt: str, src: str, folder: Path) -> str:
    path = folder / src
    if not path.is_file():
        raise FileNotFoundError(f"{path}: the report names this image but it is not there")
    mime = mimetypes.guess_type(path.name)[0] or "application/octet-stream"
    data = base64.b64encode(path.read_bytes()).decode("ascii")
    return f'<img alt="{html.escape(alt)}" src="data:{mime};base64,{data}">'


_DIFF = re.compile(r"^([+-][\d.]+)( \[[^\]]+\])?( p \S+)( n\.s\.)?$")  # a paired difference's cell


def _cell(text: str) -> str:
    """A table cell; a paired difference (``+4.7 [+2.1, +7.3] p 0.031 n.s.``) on two lines (the mean,
    bold when significant; the interval and p), the whole cell grey when not significant."""
    m = _DIFF.match(text)
    if not m:
        return f"<td>{_inline(text)}</td>"
    mean, interval, p, ns = m.groups()
    mean = mean if ns else f"<strong>{mean}</strong>"
    return (f'<td class="{"diff ns" if ns else "diff"}">{mean}<br>'
            f"<small>{html.escape((interval or '').strip())} {html.escape(p.strip())}{' n.s.' if ns else ''}</small></td>")


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def _table(rows: list[str]) -> str:
    head, body = _cells(rows[0]), [_cells(r) for r in rows[2:]]
    out = ['<div class="table"><table>', "<thead><tr>" + "".join(f"<th>{_inline(c)}</th>" for c in head) + "</tr></thead>",
           "<tbody>"]
    for cells in body:
        out.append("<tr>" + "".join(_cell(c) for c in cells) + "</tr>")
    return "\n".join(out + ["</tbody></table></div>"])


def to_html(markdown: str, folder: Path, title: str = "report") -> str:
    """The page of ``markdown`` (the report's subset, module docstring); images read from ``folder``."""
    body, para, lines = [], [], markdown.splitlines()

    def flush():
        if para:
            body.append("<p>" + _inline(" ".join(para)) + "</p>")
            para.clear()

    i = 0
    while i < len(lines):
        line = lines[i].rstrip()
        m = re.match(r"^(#{1,4}) (.*)$", line)
        if m:
            flush()
            body.append(f"<h{len(m.group(1))}>{_inline(m.group(2))}</h{len(m.group(1))}>")
        elif line.startswith("|"):
            flush()
            j = i
            while j < len(lines) and lines[j].startswith("|"):
                j += 1
            body.append(_table(lines[i:j]))
            i = j
            continue
        elif _IMAGE.match(line):
            flush()
            body.append(_image(*_IMAGE.match(line).groups(), folder))
        elif line.startswith("- "):
            flush()
            j = i
            while j < len(lines) and lines[j].startswith("- "):
                j += 1
            body.append("<ul>" + "".join(f"<li>{_inline(x[2:])}</li>" for x in lines[i:j]) + "</ul>")
            i = j
            continue
        elif not line.strip():
            flush()
        else:
            para.append(line.strip())
        i += 1
    flush()
    return (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">\n<title>{html.escape(title)}</title>\n'
            f"<style>{STYLE}</style></head>\n<body>\n" + "\n".join(body) + "\n</body></html>\n")


def write_html(markdown_path: Path, out: Path, title: str | None = None) -> Path:
    """Render ``markdown_path`` (images relative to its folder) to ``out``; the title: the first heading."""
    md = Path(markdown_path).read_text()
    first = next((ln[2:] for ln in md.splitlines() if ln.startswith("# ")), "report")
    out = Path(out)
    out.write_text(to_html(md, Path(markdown_path).parent, title or first))
    return out
