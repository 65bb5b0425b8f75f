"""Every import inside the project points down: no module imports, directly or through others, one that
imports it back.

The graph is read from the source with :mod:`ast`, not by importing anything. It holds every import
statement of ``kitti_eval`` and of the service (``server/`` in the repository, installed as
``kitti_eval_server``): absolute and relative ones, at module level, under ``if TYPE_CHECKING:``, and
inside functions. The lazy ones count too: a function's ``from .x import y`` runs as surely as a module's
(only later), and a circle that closes through one is still a circle in the design, one that a later move
of that import to the top of its module would turn into an ImportError. Importing ``a.b.c`` also runs the
packages ``a`` and ``a.b``; those implied edges are left out, as every module would otherwise be in a
circle with its package's ``__init__``. An edge to a package is kept only when the statement names the
package itself (``from .. import name`` where ``name`` is not a module).
"""

from __future__ import annotations

import ast
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
#: import name -> the folder it is installed from (pyproject.toml's package-dir mapping)
PACKAGES = {"kitti_eval": ROOT / "kitti_eval", "kitti_eval_server": ROOT / "server"}


def modules(packages: Mapping[str, Path]) -> dict[str, tuple[Path, bool]]:
    """Dotted module name -> (file, whether it is a package's ``__init__``)."""
    found: dict[str, tuple[Path, bool]] = {}
    for name, folder in packages.items():
        for path in sorted(folder.rglob("*.py")):
            parts = [name, *path.relative_to(folder).with_suffix("").parts]
            is_package = parts[-1] == "__init__"
            found[".".join(parts[:-1] if is_package else parts)] = (path, is_package)
    return found


def _absolute(module: str, is_package: bool, node: ast.ImportFrom) -> str:
    if node.level == 0:
        return node.module or ""
    base = module.split(".") if is_package else module.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join([*base, node.module] if node.module else base)


def import_graph(packages: Mapping[str, Path]) -> dict[str, set[str]]:
    """Module -> the project's modules it imports (each statement's innermost module of the project)."""
    known = modules(packages)
    graph: dict[str, set[str]] = {name: set() for name in known}
    for module, (path, is_package) in known.items():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = _absolute(module, is_package, node)
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in known else base for a in node.names]
            else:
                continue
            for target in targets:
                while target and target not in known:  # `import kitti_eval.core.x.y` of a name in x
                    target = target.rpartition(".")[0]
                if target and target != module:
                    graph[module].add(target)
    return graph


def cycles(graph: Mapping[str, Iterable[str]]) -> list[list[str]]:
    """One circle through each strongly connected group of modules, as ``[a, b, ..., a]`` (Tarjan's
    algorithm, iterative; then a shortest way back to the group's first module)."""
    edges = {v: sorted(ws) for v, ws in graph.items()}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    groups: list[list[str]] = []
    for start in sorted(edges):
        if start in index:
            continue
        work = [(start, 0)]
        while work:
            v, i = work.pop()
            if i == 0:
                index[v] = low[v] = len(index)
                stack.append(v)
                on_stack.add(v)
            if i < len(edges[v]):
                work.append((v, i + 1))
                w = edges[v][i]
                if w not in index:
                    work.append((w, 0))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            if work:
                parent = work[-1][0]
                low[parent] = min(low[parent], low[v])
            if low[v] == index[v]:
                group = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    group.append(w)
                    if w == v:
                        break
                if len(group) > 1 or v in edges[v]:
                    groups.append(sorted(group))
    found = []
    for group in groups:
        members, first = set(group), group[0]
        paths = {w: [first, w] for w in edges[first] if w in members}
        frontier = list(paths)
        while first not in paths:
            step = []
            for v in frontier:
                for w in edges[v]:
                    if w in members and w not in paths:
                        paths[w] = [*paths[v], w]
                        step.append(w)
            frontier = step
        found.append(paths[first])
    return sorted(found)


def report(circles: list[list[str]]) -> str:
    return "import circles:\n" + "\n".join(" -> ".join(c) for c in circles)


#: the service's map, top to bottom: each row's folders of ``server/`` and modules directly in it (``__init__``
#: the package itself). A module imports only modules of its own folder and of the rows below its own: not of
#: its row (the JSON routes and the web pages are side by side, and so are the benchmarks' wing and users'
#: evaluations: neither imports the other) nor above it.
SERVICE_MAP: tuple[frozenset[str], ...] = tuple(
    frozenset(row.split())
    for row in (
        "__init__",
        "commands",
        "main backup",
        "routes web shutdown middleware",
        "params",
        "service",
        "benchmarks evaluations",
        "ground_truths idempotency schemas",
        "jobs scoring",
        "access data_folder observability",
        "store settings",
        "errors",
    )
)


def place(module: str, package: str) -> str | None:
    """The folder of ``package`` (or its module directly in it) that ``module`` belongs to; None outside it."""
    if module == package:
        return "__init__"
    if not module.startswith(package + "."):
        return None
    return module[len(package) + 1 :].partition(".")[0]


def upward_imports(
    graph: Mapping[str, Iterable[str]], package: str, layers: Sequence[frozenset[str]]
) -> tuple[list[str], list[str]]:
    """The imports of ``package``'s modules that do not point down its map (``layers``, top row first), each as
    ``"module -> module"``, and the folders or modules of the package that are not on the map."""
    row = {name: i for i, names in enumerate(layers) for name in names}
    upward, unplaced = [], set()
    for module, targets in graph.items():
        here = place(module, package)
        if here is None:
            continue
        if here not in row:
            unplaced.add(here)
            continue
        for target in sorted(targets):
            there = place(target, package)
            if there is None or there == here:
                continue
            if there not in row:
                unplaced.add(there)
            elif row[there] <= row[here]:
                upward.append(f"{module} -> {target}")
    return sorted(upward), sorted(unplaced)


def test_no_import_circle() -> None:
    circles = cycles(import_graph(PACKAGES))
    assert circles == [], report(circles)


def test_the_graph_holds_every_kind_of_import() -> None:
    graph = import_graph(PACKAGES)
    assert {m.partition(".")[0] for m in graph} == {"kitti_eval", "kitti_eval_server"}
    assert {"kitti_eval.core", "kitti_eval.core.matching", "kitti_eval_server.routes.health"} < graph.keys()
    assert "kitti_eval.core.arrays" in graph["kitti_eval.core.geometry"]  # relative, module level
    assert "kitti_eval.core.evaluation" in graph["kitti_eval._jit"]  # inside warm_up()
    assert "kitti_eval._jit" in graph["kitti_eval_server.service"]  # absolute, from the service
    assert graph["kitti_eval.core.arrays"] == set()


def test_the_bottom_of_the_house_imports_nothing_above_it() -> None:
    """``core`` is the bottom: it imports only itself, the error tree and numpy/numba; the numba cache's
    warm-up is the top: only the CLI and the service import it."""
    graph = import_graph(PACKAGES)
    for module, targets in graph.items():
        if module.startswith("kitti_eval.core."):
            above = {t for t in targets if not t.startswith("kitti_eval.core") and t != "kitti_eval.errors"}
            assert above == set(), module
    importers = {m for m, targets in graph.items() if "kitti_eval._jit" in targets}
    assert importers and all(m.startswith(("kitti_eval.cli", "kitti_eval_server.")) for m in importers), importers


def test_the_service_s_folders_import_downwards_only() -> None:
    """Not only no circle of modules: no circle of folders either, nor an import between the two doors (the
    JSON routes and the web pages) or the two wings (benchmarks and evaluations: both score with the scoring
    folder below them). Every folder of ``server/`` and module directly in it is on
    :data:`SERVICE_MAP`, and each imports only rows below its own."""
    graph = import_graph(PACKAGES)
    upward, unplaced = upward_imports(graph, "kitti_eval_server", SERVICE_MAP)
    assert unplaced == [], f"not on SERVICE_MAP (add each to the row it belongs to): {unplaced}"
    assert upward == [], "imports that do not point down the service's map:\n" + "\n".join(upward)
    on_disk = {p.stem if p.is_file() else p.name for p in (ROOT / "server").iterdir()}
    on_disk = {n for n in on_disk if (ROOT / "server" / n).is_dir() or (ROOT / "server" / f"{n}.py").is_file()}
    names = set().union(*SERVICE_MAP)
    assert names - on_disk - {"__init__"} == set(), "on SERVICE_MAP but not in server/"


def test_an_import_up_or_across_the_map_is_found() -> None:
    """The check can fail: an import from a row to the row above, one across a row, and a folder off the map."""
    graph = {
        "pkg": {"pkg.top.a"},
        "pkg.top.a": {"pkg.top.b", "pkg.low", "numpy"},
        "pkg.top.b": set(),
        "pkg.side": {"pkg.top.a"},
        "pkg.low": {"pkg.top.b", "pkg.side.x"},
        "pkg.stray": {"pkg.low"},
    }
    layers = (frozenset({"__init__"}), frozenset({"top", "side"}), frozenset({"low"}))
    assert upward_imports(graph, "pkg", layers) == (
        ["pkg.low -> pkg.side.x", "pkg.low -> pkg.top.b", "pkg.side -> pkg.top.a"],
        ["stray"],
    )


def test_the_library_imports_nothing_of_the_service() -> None:
    """``kitti_eval`` imports nothing of ``kitti_eval_server``, in no statement (inside functions and under
    ``if TYPE_CHECKING:`` too) and by no name in its code (``importlib.import_module("kitti_eval_server...")``):
    the service's commands reach the command line through an entry point (kitti_eval/cli/installed.py)."""
    graph = import_graph(PACKAGES)
    upward = {m: sorted(t for t in targets if t.startswith("kitti_eval_server")) for m, targets in graph.items()}
    assert {m: t for m, t in upward.items() if m.startswith("kitti_eval.") and t} == {}
    named = []
    for path in sorted((ROOT / "kitti_eval").rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        docstrings = {
            id(node.body[0].value)
            for node in ast.walk(tree)
            if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
            and node.body
            and isinstance(node.body[0], ast.Expr)
        }
        for node in ast.walk(tree):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings:
                if "kitti_eval_server" in node.value:
                    named.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert named == []
    # the other way is read: the service's commands (the command line's before) import the library
    assert "kitti_eval.errors" in graph["kitti_eval_server.commands.admin"]


def _write(folder: Path, files: Mapping[str, str]) -> None:
    for name, text in files.items():
        path = folder / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


def test_a_circle_is_found_and_named(tmp_path: Path) -> None:
    """The check can fail: a circle closed by a lazy relative import is found and named (a module that
    names itself is no edge, and a package's ``__init__`` importing a module of the circle is not in it)."""
    _write(
        tmp_path / "pkg",
        {
            "__init__.py": "from .top import run\n",
            "low/__init__.py": "",
            "low/kernels.py": "def k():\n    from ..top import run\n    return run\n",
            "mid.py": "from .low import kernels\n",
            "top.py": "import pkg.mid\n\ndef run():\n    pass\n",
            "alone.py": "from . import alone\n",
            "clean.py": "from .low.kernels import k\nimport numpy\n",
        },
    )
    graph = import_graph({"pkg": tmp_path / "pkg"})
    assert graph["pkg.mid"] == {"pkg.low.kernels"}
    assert graph["pkg.clean"] == {"pkg.low.kernels"}
    assert graph["pkg"] == {"pkg.top"}
    assert graph["pkg.alone"] == set()  # a module importing itself by name is no edge of the graph
    assert cycles(graph) == [["pkg.low.kernels", "pkg.top", "pkg.mid", "pkg.low.kernels"]]
    assert report(cycles(graph)) == "import circles:\npkg.low.kernels -> pkg.top -> pkg.mid -> pkg.low.kernels"


def test_each_circle_is_named_once_by_a_shortest_way_round() -> None:
    """The shape of the circle this test was written against (the kernels' array convention and the
    warm-up in one module, below the kernels and above the analyses at once), beside a separate one."""
    graph = {
        "kitti_eval._jit": {"kitti_eval.core.evaluation", "kitti_eval.analysis.bootstrap"},
        "kitti_eval.core.evaluation": {"kitti_eval.core.matching"},
        "kitti_eval.core.matching": {"kitti_eval._jit"},
        "kitti_eval.analysis.bootstrap": {"kitti_eval._jit", "kitti_eval.core.evaluation"},
        "x": {"y"},
        "y": {"x", "kitti_eval.core.matching"},
    }
    assert cycles(graph) == [
        ["kitti_eval._jit", "kitti_eval.analysis.bootstrap", "kitti_eval._jit"],
        ["x", "y", "x"],
    ]
    graph["kitti_eval.core.matching"] = set()  # the kernels no longer import the warm-up
    assert cycles(graph) == [["kitti_eval._jit", "kitti_eval.analysis.bootstrap", "kitti_eval._jit"], ["x", "y", "x"]]
    graph["kitti_eval.analysis.bootstrap"] = {"kitti_eval.core.evaluation"}
    assert cycles(graph) == [["x", "y", "x"]]
