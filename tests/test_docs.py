"""The documentation site (mkdocs.yml, docs/) and its pictures (docs/images/, scripts/make_pictures.py).

``mkdocs build --strict`` fails on a broken link, a missing page or image, a page left out of the
nav, or a docstring mkdocstrings cannot read; the README's links and images are checked here (it
is not part of the site)."""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
IMAGES = DOCS / "images"
IMAGES_BUDGET = 4 * 1024 * 1024  # bytes, all committed pictures together
IMAGE = re.compile(r"!\[[^\]]*\]\(([^)\s]+)")
LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s#]+)(?:#[^)]*)?\)")


def _pages() -> list[Path]:
    return [ROOT / "README.md", *sorted(DOCS.rglob("*.md"))]


def _named_images() -> dict[Path, list[Path]]:
    """{image file: the pages naming it}, relative links resolved from each page."""
    out: dict[Path, list[Path]] = {}
    for page in _pages():
        for target in IMAGE.findall(page.read_text()):
            if not re.match(r"https?:", target):
                out.setdefault((page.parent / target).resolve(), []).append(page)
    return out


def test_every_named_image_exists_and_all_are_small():
    named = _named_images()
    missing = {str(p.relative_to(ROOT)): [str(q.relative_to(ROOT)) for q in pages]
               for p, pages in named.items() if not p.is_file()}
    assert not missing, f"images named but not there (python scripts/make_pictures.py): {missing}"
    assert (ROOT / "docs" / "images" / "overview.png").resolve() in named, "the README/site's opening picture"
    files = [p for p in IMAGES.rglob("*") if p.is_file()]
    unused = sorted(str(p.relative_to(ROOT)) for p in files if p.resolve() not in named)
    assert not unused, f"pictures no page names (delete them or show them): {unused}"
    total = sum(p.stat().st_size for p in files)
    assert total <= IMAGES_BUDGET, f"docs/images/ holds {total / 2**20:.2f} MiB, expected <= 4 MiB"


def test_readme_links_and_images_resolve():
    text = (ROOT / "README.md").read_text()
    targets = [t for t in LINK.findall(text) + IMAGE.findall(text) if not re.match(r"https?:|mailto:", t)]
    assert any(t.startswith("docs/images/") for t in IMAGE.findall(text)), "the README opens with a picture"
    broken = [t for t in targets if not (ROOT / t).exists()]
    assert not broken, f"README.md links to files that are not there: {broken}"


@pytest.mark.slow  # ~3.5 s: the whole site, the API pages from the docstrings
def test_mkdocs_build_strict(tmp_path):
    """The site builds with no warning (strict): every page in the nav, every link and image found,
    the API reference's docstrings parsed."""
    pytest.importorskip("mkdocs", reason="the docs extra (pip install -e '.[docs]') is not installed")
    pytest.importorskip("mkdocstrings", reason="the docs extra (pip install -e '.[docs]') is not installed")
    p = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
                       cwd=ROOT, capture_output=True, text=True, env=dict(os.environ, NO_MKDOCS_2_WARNING="1"))
    warnings = [line for line in p.stderr.splitlines() if "WARNING" in line or "ERROR" in line]
    assert p.returncode == 0, "mkdocs build --strict failed:\n" + "\n".join(warnings or p.stderr.splitlines()[-20:])
    assert (tmp_path / "site" / "reference" / "api" / "index.html").is_file()
    api = (tmp_path / "site" / "reference" / "api" / "index.html").read_text()
    assert "RunResult" in api and "Frame" in api, "the API page has no docstrings (mkdocstrings)"
    for page in ("results/index.html", "config/index.html", "index.html"):
        assert (tmp_path / "site" / page).is_file(), page


def _make_pictures():
    import importlib.util

    spec = importlib.util.spec_from_file_location("make_pictures", ROOT / "scripts" / "make_pictures.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_pictures_splat_keeps_the_nearest_point():
    """The pictures' 3D views (scripts/make_pictures.py): a point hides the ones behind it in its
    pixel, whatever their order; each covers a (2 radius + 1)^2 square; points behind the camera
    are not drawn."""
    import numpy as np

    mp = _make_pictures()
    K = np.array([[4.0, 0, 4], [0, 4.0, 3], [0, 0, 1]])
    T = np.eye(4)
    points = np.array([[0, 0, 2.0], [0, 0, 1.0], [0.5, 0, 1.0], [0, 0, -1.0]])  # far, near, right, behind
    colors = np.array([[0, 0, 255], [255, 0, 0], [0, 255, 0], [9, 9, 9]], np.uint8)
    for order in ([0, 1, 2, 3], [3, 2, 1, 0]):
        img = mp.splat(points[order], colors[order], K, T, (7, 9), radius=0)
        assert img[3, 4].tolist() == [255, 0, 0]  # the near point, not the far one behind it
        assert img[3, 6].tolist() == [0, 255, 0]
        assert (img != 255).any(2).sum() == 2  # the far point is hidden, the one behind the camera absent
    img = mp.splat(points[1:2], colors[1:2], K, T, (7, 9), radius=1)
    assert (img[2:5, 3:6] == [255, 0, 0]).all() and (img != 255).any(2).sum() == 9
