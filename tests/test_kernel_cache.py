"""A warm numba cache never serves a kernel compiled from sources that have since changed.

numba judges a cached kernel by the file that defines it alone; the error decomposition's kernels compile
in the matching kernels of another module. :mod:`kitti_eval.core.kernel_cache` stamps every kernel with
the digest of its module and of all the package's modules it imports. The end-to-end test does what a
developer editing a kernel (or a user upgrading) does: copy the package, warm its cache, change the matching
rule in ``core/matching.py``, and run again on the warm cache and on an empty one.
"""

from __future__ import annotations

import ast
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import kitti_eval
from kitti_eval.core import kernel_cache

PACKAGE = Path(kitti_eval.__file__).resolve().parent

# the error decomposition and the AP table of the bundled demo, and which kernels numba compiled
_RUN = """
import json, sys
from numba.core import event

compiled = []

class Compiles(event.Listener):
    def on_start(self, ev):
        compiled.append(ev.data["dispatcher"].py_func.__qualname__)

    def on_end(self, ev):
        pass

with event.install_listener("numba:compile", Compiles()):
    import kitti_eval
    from kitti_eval.analysis.decomposition import decompose, errors_document
    from kitti_eval.core.evaluation import evaluate
    from kitti_eval.io.loaders import load_pair
    from kitti_eval.io.synth import demo_paths

    gt_path, dt_path = demo_paths()
    gt, dt = load_pair(gt_path, dt_path)
    document = {"errors": errors_document(decompose(gt, dt)), "ap": evaluate(gt, dt).to_dict()}
print(json.dumps({"package": kitti_eval.__file__, "document": document, "compiled": compiled}))
"""

# one comparison of pass 1 of the matching (`_frame_pass1`, inlined into matching's `_pass1` and into the
# decomposition's `_pass1_taken`)
_RULE = "c.sub[o0 + a * width + i] > min_overlap and c.d_score[d0 + a] > best"
_EDITED = "c.sub[o0 + a * width + i] > min_overlap + 0.2 and c.d_score[d0 + a] > best"


def _run(where: Path, cache: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_")}
    env.update(NUMBA_CACHE_DIR=str(cache), PYTHONPATH=str(where), PYTHONDONTWRITEBYTECODE="1")
    done = subprocess.run(
        [sys.executable, "-c", _RUN], cwd=where, env=env, capture_output=True, text=True, timeout=600, check=False
    )
    assert done.returncode == 0, done.stderr[-3000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert Path(out["package"]).resolve().parent == (where / "kitti_eval").resolve()  # the copy, not the install
    return out


def _differences(a: object, b: object, path: str = "") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        keys = sorted(set(a) | set(b))
        return [d for k in keys for d in _differences(a.get(k), b.get(k), f"{path}/{k}")]
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in _differences(x, y, f"{path}[{i}]")]
    return [] if a == b else [path]


@pytest.mark.slow
def test_an_edit_of_a_called_kernel_in_another_module_is_not_served_stale(tmp_path: Path) -> None:
    copy = tmp_path / "src"
    shutil.copytree(PACKAGE, copy / "kitti_eval", ignore=shutil.ignore_patterns("__pycache__"))
    warm = tmp_path / "warm-cache"

    before = _run(copy, warm)
    assert {"_pass1", "_pass1_taken", "_group_maxima"} <= set(before["compiled"])  # really compiled
    assert _run(copy, warm)["compiled"] == []  # and then really cached

    matching = copy / "kitti_eval" / "core" / "matching.py"
    source = matching.read_text()
    assert source.count(_RULE) == 1, "the test's edit no longer finds pass 1's comparison in matching.py"
    matching.write_text(source.replace(_RULE, _EDITED))

    warm_after = _run(copy, warm)
    cold_after = _run(copy, tmp_path / "empty-cache")
    changed = _differences(before["document"], cold_after["document"])
    assert len(changed) > 50, "the edit must change the numbers, or the test proves nothing"
    stale = _differences(warm_after["document"], cold_after["document"])
    assert stale == [], f"{len(stale)} values differ between the warm and the cold cache, e.g. {stale[:5]}"
    # the decomposition's kernels were compiled again; the module that imports nothing changed was not
    assert {"_pass1", "_pass1_taken", "_group_maxima", "_tp_error_events"} <= set(warm_after["compiled"])
    assert "_frame_overlaps_kernel" not in warm_after["compiled"]


def _package(tmp_path: Path, files: dict[str, str]) -> Path:
    root = tmp_path / "pkg"
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return root


def test_a_stamp_covers_what_its_module_imports_and_nothing_else(tmp_path: Path) -> None:
    root = _package(
        tmp_path,
        {
            "__init__.py": "",
            "core/__init__.py": "",
            "core/consts.py": "LIMIT = 3\n",
            "core/low.py": "from .consts import LIMIT\n",
            "core/mid.py": "from . import low\nfrom ..util import helper\n",
            "top.py": "from .core.mid import low\n\ndef f():\n    from .late import x\n",
            "util.py": "helper = 1\n",
            "late.py": "x = 1\n",
            "cli.py": "from .top import f\n",
        },
    )
    names = {p.relative_to(root).as_posix() for p in kernel_cache.kernel_modules(root / "top.py", root)}
    # module-level imports, relative and of a package, transitively; a function's import is no global
    assert names == {"top.py", "core/mid.py", "core/low.py", "core/consts.py", "util.py", "core/__init__.py"}

    stamp = kernel_cache.kernel_stamp(root / "top.py", root)
    (root / "cli.py").write_text("from .top import f\nX = 2\n")
    (root / "late.py").write_text("x = 2\n")
    assert kernel_cache.kernel_stamp(root / "top.py", root) == stamp  # neither is compiled into top's kernels
    (root / "core" / "consts.py").write_text("LIMIT = 4\n")
    assert kernel_cache.kernel_stamp(root / "top.py", root) != stamp  # a constant two imports away is


def test_a_stamp_is_the_same_wherever_the_sources_are_installed(tmp_path: Path) -> None:
    """A reinstall (other place, new modification times) of the same sources keeps the cache valid."""
    first = _package(tmp_path / "a", {"__init__.py": "", "k.py": "from . import c\n", "c.py": "N = 1\n"})
    second = _package(tmp_path / "b", {"__init__.py": "", "k.py": "from . import c\n", "c.py": "N = 1\n"})
    os.utime(second / "c.py", (1, 1))
    assert kernel_cache.kernel_stamp(first / "k.py", first) == kernel_cache.kernel_stamp(second / "k.py", second)


def test_the_decomposition_is_stamped_with_the_matching_kernels_it_calls() -> None:
    closure = {
        p.relative_to(PACKAGE).as_posix()
        for p in kernel_cache.kernel_modules(PACKAGE / "analysis" / "decomposition.py")
    }
    assert {"analysis/decomposition.py", "core/matching.py", "core/protocol.py"} <= closure
    assert not any(name.startswith(("cli/", "compat/")) for name in closure)


def test_every_cached_kernel_goes_through_the_locator() -> None:
    """No module of the package takes ``njit`` from numba itself: a kernel decorated before the locator is
    in place would be stamped by its own file alone."""
    offenders = []
    for path in PACKAGE.rglob("*.py"):
        if path == Path(kernel_cache.__file__).resolve():
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "numba":
                if any(
                    alias.name in {"njit", "jit", "generated_jit", "vectorize", "guvectorize"} for alias in node.names
                ):
                    offenders.append(str(path.relative_to(PACKAGE)))
            if isinstance(node, ast.Attribute) and node.attr in {"njit", "jit"}:
                if isinstance(node.value, ast.Name) and node.value.id == "numba":
                    offenders.append(str(path.relative_to(PACKAGE)))
    assert offenders == []


def test_the_package_kernels_are_located_by_the_kernel_locator_and_others_are_not() -> None:
    from numba.core.caching import FunctionCache

    from kitti_eval.core import matching

    ours = FunctionCache(matching._frame_pass1.py_func)
    assert isinstance(ours._impl.locator, kernel_cache.KernelLocator)
    assert ours._impl.locator.get_source_stamp() == kernel_cache.kernel_stamp(matching.__file__)

    def elsewhere(x: int) -> int:  # a user's own function, outside the package
        return x

    assert not isinstance(FunctionCache(elsewhere)._impl.locator, kernel_cache.KernelLocator)
