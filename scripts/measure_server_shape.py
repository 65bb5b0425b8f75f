"""The shape of the service's source: its largest classes and functions (lines, decorators and docstrings
included), and the imports that do not point down the folder map of ``tests/core/test_imports.py``.

``python scripts/measure_server_shape.py [--tree DIR] [--top 5]``: DIR is a checkout of the repository (the
default: this one), so an older commit is measured with ``git archive COMMIT | tar -x -C DIR`` first. The map
and the graph are this checkout's (its test module), read over DIR's files; a folder of DIR that is not on the
map is named. Prints the figures; exits 0.
"""

from __future__ import annotations

import argparse
import ast
import importlib.util
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]


def _import_checks() -> ModuleType:
    spec = importlib.util.spec_from_file_location("test_imports", ROOT / "tests" / "core" / "test_imports.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def sizes(server: Path) -> tuple[list[tuple[int, str]], list[tuple[int, str]]]:
    """(lines, "file:name") of every class and of every function (methods included) under ``server``."""
    classes: list[tuple[int, str]] = []
    functions: list[tuple[int, str]] = []
    for path in sorted(server.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        for node in ast.walk(tree):
            if not isinstance(node, ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
                continue
            start = min([node.lineno, *(d.lineno for d in node.decorator_list)])
            lines = (node.end_lineno or node.lineno) - start + 1
            where = f"{path.relative_to(server.parent)}:{node.name}"
            (classes if isinstance(node, ast.ClassDef) else functions).append((lines, where))
    return sorted(classes, reverse=True), sorted(functions, reverse=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tree", type=Path, default=ROOT)
    parser.add_argument("--top", type=int, default=5)
    args = parser.parse_args()
    tree = args.tree.resolve()
    classes, functions = sizes(tree / "server")
    for title, found in (("classes", classes), ("functions", functions)):
        print(f"largest {title} in server/ (lines):")
        for lines, where in found[: args.top]:
            print(f"  {lines:5d}  {where}")
    checks = _import_checks()
    graph = checks.import_graph({"kitti_eval": tree / "kitti_eval", "kitti_eval_server": tree / "server"})
    upward, unplaced = checks.upward_imports(graph, "kitti_eval_server", checks.SERVICE_MAP)
    print(f"imports that do not point down the folder map: {len(upward)}")
    for line in upward:
        print(f"  {line}")
    if unplaced:
        print(f"folders or modules not on the map: {', '.join(unplaced)}")


if __name__ == "__main__":
    main()
