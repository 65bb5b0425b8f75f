"""The documentation: the site builds with every warning an error (broken links and anchors included), the
README's links land on pages and headings that exist, and the pages that mirror the code name all of it."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import unicodedata
from pathlib import Path

import pytest
from doc_examples import ROOT

import kitti_eval

_FENCED = re.compile(r"^```.*?^```[ \t]*$", re.S | re.M)


def _slug(heading: str) -> str:
    """The anchor mkdocs gives a heading (Python-Markdown's toc: its text, ASCII, lower case, dashes)."""
    words = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading).replace("`", "")
    words = unicodedata.normalize("NFKD", words).encode("ascii", "ignore").decode("ascii")
    words = re.sub(r"[^\w\s-]", "", words).strip().lower()
    return re.sub(r"[-\s]+", "-", words)


def _anchors(page: Path) -> set[str]:
    prose = _FENCED.sub("", page.read_text(encoding="utf-8"))
    return {_slug(m.group(1)) for m in re.finditer(r"^#{1,6} (.+)$", prose, re.M)}


def test_the_site_builds_with_warnings_as_errors(tmp_path: Path) -> None:
    pytest.importorskip("mkdocs")
    pytest.importorskip("mkdocstrings")
    pytest.importorskip("material")
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    site = tmp_path / "site"
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "WARNING" not in proc.stderr, proc.stderr
    api = (site / "python" / "api" / "index.html").read_text(encoding="utf-8")
    assert "Evaluate detections against ground truth." in api  # the docstrings are in the reference
    assert 'class="doc doc-heading"' in api
    layers = (site / "architecture" / "index.html").read_text(encoding="utf-8")
    assert "../images/layers.svg" in layers and (site / "images" / "layers.svg").is_file()


def test_the_readmes_links_land_on_pages_and_headings() -> None:
    readme = _FENCED.sub("", (ROOT / "README.md").read_text(encoding="utf-8"))
    links = re.findall(r"\]\(([^)\s]+)\)", readme)
    local = [link for link in links if not re.match(r"[a-z]+:", link)]
    assert len(local) >= 20  # the README is mostly a way into docs/
    broken = []
    for link in local:
        path, _, anchor = link.partition("#")
        target = ROOT / path if path else ROOT / "README.md"
        if not target.exists() or (anchor and anchor not in _anchors(target)):
            broken.append(link)
    assert broken == []


def test_the_api_reference_has_every_public_name() -> None:
    page = (ROOT / "docs" / "python" / "api.md").read_text(encoding="utf-8")
    documented = {line.split()[-1].rsplit(".", 1)[-1] for line in page.splitlines() if line.startswith("::: ")}
    documented |= {
        name for line in page.splitlines() if line == "::: kitti_eval.errors" for name in kitti_eval.errors.__all__
    }
    assert set(kitti_eval.__all__) - {"__version__"} <= documented


def _module_map() -> list[str]:
    """The entries of the architecture page's module map: a path, then what it is (continuation lines joined)."""
    page = (ROOT / "docs" / "architecture" / "index.md").read_text(encoding="utf-8")
    block = re.search(r"^```\n(kitti_eval/.*?)^```", page, re.S | re.M)
    assert block, "docs/architecture/index.md lost its module map"
    entries: list[str] = []
    for line in block.group(1).splitlines():
        if line.startswith(" ") and entries:
            entries[-1] += " " + line.strip()
        else:
            entries.append(line)
    return entries


def test_the_module_map_names_every_module() -> None:
    entries = _module_map()
    unnamed = []
    for root in ("kitti_eval", "server", "scripts"):
        for path in sorted((ROOT / root).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            folder, name = rel.rsplit("/", 1)
            if name in ("__init__.py", "__main__.py"):
                continue
            for entry in entries:
                head = entry.split()[0].rstrip(",")
                if rel in entry or (head.rsplit("/", 1)[0] == folder and ("/*.py" in head or name in entry)):
                    break
            else:
                unnamed.append(rel)
    assert unnamed == [], "modules docs/architecture/index.md does not name"


def test_the_layers_picture_names_folders_that_exist() -> None:
    svg = (ROOT / "docs" / "images" / "layers.svg").read_text(encoding="utf-8")
    paths = re.findall(r">((?:kitti_eval|server)/[\w./]*)<", svg)
    assert len(paths) == 8 and all((ROOT / p).exists() for p in paths), paths
    assert {p.split("/")[1] for p in paths if p.startswith("kitti_eval/") and "." not in p} == {
        p.name for p in (ROOT / "kitti_eval").iterdir() if p.is_dir() and (p / "__init__.py").exists()
    }


def _names_of_sections(page: Path) -> set[str]:
    """A page's headings, and the bold words that open a paragraph (its sections without a heading)."""
    prose = _FENCED.sub("", page.read_text(encoding="utf-8"))
    names = {m.group(1).strip().lower() for m in re.finditer(r"^#{1,6} (.+)$", prose, re.M)}
    return names | {m.group(1).strip().lower() for m in re.finditer(r"^\*\*([^*]+?)\.?\*\*", prose, re.M)}


def test_pages_point_at_other_sections_by_links_not_by_name() -> None:
    """A page that sends the reader to a section by its name ('see the README's "Hosting a benchmark"') is not
    checked by anything, and pointed at sections the README no longer had; a link is checked by the strict build.
    So no page of docs/ names a section of the README (not a page of the site), or quotes a section's name
    outside a link."""
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    sections = set().union(*(_names_of_sections(p) for p in pages))
    assert {"hosting a benchmark", "who may do what"} <= sections
    by_name = []
    for page in pages[1:]:
        prose = _FENCED.sub("", page.read_text(encoding="utf-8"))
        prose = re.sub(r"\[[^\]]*\]\([^)]*\)", "", re.sub(r"`[^`]*`", "", prose))  # code and links aside
        for m in re.finditer(r"README's|\"([^\"\n]{3,80})\"", prose):
            if m.group(1) is None or m.group(1).lower() in sections:
                by_name.append(f"{page.relative_to(ROOT)}: {m.group(0)}")
    assert by_name == []
