"""The service's layout stays findable: a folder a subsystem, few modules beside them, and parts composed of
parts rather than classes built from the project's own classes or grown past a size a reader takes in."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SERVER = ROOT / "server"
#: a class this long (its first line to its last) is split by what it does
MAX_CLASS_LINES = 300
#: modules directly in server/, beside its subsystems' folders
MAX_TOP_MODULES = 12


def _classes(root: Path) -> list[tuple[Path, ast.ClassDef]]:
    return [
        (path, node)
        for path in sorted(root.rglob("*.py"))
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8")))
        if isinstance(node, ast.ClassDef)
    ]


def _name(base: ast.expr) -> str:
    return base.attr if isinstance(base, ast.Attribute) else base.id if isinstance(base, ast.Name) else ""


def test_no_class_of_the_service_is_300_lines_or_more() -> None:
    sizes = {f"{p.relative_to(ROOT)}::{c.name}": c.end_lineno - c.lineno + 1 for p, c in _classes(SERVER)}  # type: ignore[operator]
    assert len(sizes) > 50  # the walk found the service's classes, or it proves nothing
    assert {k: n for k, n in sizes.items() if n >= MAX_CLASS_LINES} == {}


def test_no_class_is_built_from_two_of_the_projects_own_classes() -> None:
    own = {c.name for root in (SERVER, ROOT / "kitti_eval") for _, c in _classes(root)}
    mixed = {
        f"{p.relative_to(ROOT)}::{c.name}": names
        for p, c in _classes(SERVER)
        if len(names := [_name(b) for b in c.bases if _name(b) in own]) >= 2
    }
    assert {"Area", "ApiError", "BenchmarkCatalog"} <= own  # the project's classes were found
    assert mixed == {}


def test_the_service_is_a_folder_a_subsystem() -> None:
    top = sorted(p.name for p in SERVER.glob("*.py") if p.name != "__init__.py")
    folders = {p.name for p in SERVER.iterdir() if (p / "__init__.py").exists()}
    assert len(top) <= MAX_TOP_MODULES, top
    assert {"access", "jobs", "evaluations", "ground_truths", "benchmarks", "store", "routes", "web"} <= folders
