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
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numba
import pytest

import kitti_eval
from kitti_eval.core import kernel_cache

PACKAGE = Path(kitti_eval.__file__).resolve().parent
_DISABLE_JIT = bool(numba.config.DISABLE_JIT)

# the error decomposition and the AP table of the bundled demo, and which kernels numba compiled
_RUN = """
import json, sys
from kitti_eval._jit import compilations

with compilations() as compiled:
    import kitti_eval
    from kitti_eval.analysis.decomposition import decompose, errors_document
    from kitti_eval.core.evaluation import evaluate
    from kitti_eval.io.loaders import load_pair
    from kitti_eval.demo import demo_paths

    gt_path, dt_path = demo_paths()
    gt, dt = load_pair(gt_path, dt_path)
    document = {"errors": errors_document(decompose(gt, dt)), "ap": evaluate(gt, dt).to_dict()}
print(json.dumps({"package": kitti_eval.__file__, "document": document, "compiled": compiled}))
"""

# one comparison of pass 1 of the matching (`frame_pass1`, inlined into matching's `_pass1` and into the
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


@pytest.mark.skipif(numba.config.DISABLE_JIT, reason="NUMBA_DISABLE_JIT: no dispatchers, no cache")
def test_the_package_kernels_are_located_by_the_kernel_locator_and_others_are_not() -> None:
    from numba.core.caching import FunctionCache

    from kitti_eval.core import matching

    ours = FunctionCache(matching.frame_pass1.py_func)
    assert isinstance(ours._impl.locator, kernel_cache.KernelLocator)
    assert ours._impl.locator.get_source_stamp() == kernel_cache.kernel_stamp(matching.__file__)

    def elsewhere(x: int) -> int:  # a user's own function, outside the package
        return x

    assert not isinstance(FunctionCache(elsewhere)._impl.locator, kernel_cache.KernelLocator)


# -- the kernels a platform wheel ships (kitti_eval/_kernels/, written by scripts/build_wheel.py) ----------------


class _Compiles:
    """The project's kernels numba compiles while the block runs (a load from a cache is not a compile). numba's
    own overloads a kernel uses (``np.zeros``'s, ...) compile with the first kernel of a process that uses them,
    so whether they show depends on what ran before in the process: they are not counted."""

    def __enter__(self) -> list[str]:
        from numba.core import event

        self.names: list[str] = []
        names = self.names

        class Listener(event.Listener):
            def on_start(self, ev: event.Event) -> None:
                func = ev.data["dispatcher"].py_func
                if func.__module__.startswith("kitti_eval"):
                    names.append(func.__qualname__)

            def on_end(self, ev: event.Event) -> None:
                pass

        self._scope = event.install_listener("numba:compile", Listener())
        self._scope.__enter__()
        return names

    def __exit__(self, *exc: object) -> None:
        self._scope.__exit__(*exc)


def _ship(root: Path, kernel: Any, *, stamp: tuple[str, str] | None = None) -> None:
    """Lay out ``root`` as a wheel's ``_kernels`` folder: a manifest for this numba and Python and the generic
    CPU, and ``kernel``'s code from numba's cache of this machine saved under the generic key (with ``stamp``
    instead of the sources' own, if given)."""
    from numba.core.caching import IndexDataCacheFile

    (sig,) = kernel.signatures
    cres, cache = kernel.overloads[sig], kernel._cache
    target = (cres.library.codegen.magic_tuple()[0], "generic", "")
    manifest = {"numba": numba.__version__, "python": kernel_cache.python_tag(), "target": target, "kernels": 1}
    root.mkdir(parents=True)
    (root / "manifest.json").write_text(json.dumps(manifest))
    shipped = kernel_cache.read_manifest(root)
    assert shipped is not None and shipped.target == target
    folder = shipped.folder(cache._impl.locator.py_file)
    assert folder == root / "core"  # folders named as the package's
    folder.mkdir()
    index = IndexDataCacheFile(
        cache_path=str(folder),
        filename_base=cache._impl.filename_base,
        source_stamp=stamp or cache._impl.locator.get_source_stamp(),
    )
    key = cache._index_key(sig, cres.library.codegen)
    data = cache._cache_file.load(key)  # as numba keeps it on disk (the session's warm-up saved or loaded it)
    assert data is not None
    index.save((key[0], target, *key[2:]), data)


@pytest.fixture
def shipped_root(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """A ``_kernels`` folder of this test's, and numba's own cache in an empty folder (so it holds nothing)."""
    import numba

    root = tmp_path / "_kernels"
    monkeypatch.setattr(kernel_cache, "SHIPPED_ROOT", root)
    monkeypatch.setattr(numba.config, "CACHE_DIR", str(tmp_path / "numba-cache"))
    kernel_cache.shipped_kernels.cache_clear()
    yield root
    kernel_cache.shipped_kernels.cache_clear()


def _fresh(kernel: Any) -> Any:
    """A new dispatcher of ``kernel``'s function, as a new process's import makes it."""
    return kernel_cache.njit(cache=True, nogil=True)(kernel.py_func)


@pytest.mark.skipif(_DISABLE_JIT, reason="NUMBA_DISABLE_JIT: nothing is compiled")
def test_a_kernel_missing_from_numbas_cache_loads_the_shipped_one(shipped_root: Path) -> None:
    import numpy as np

    from kitti_eval.core import geometry

    kernel = geometry._iou_2d_kernel
    _ship(shipped_root, kernel)
    fresh = _fresh(kernel)
    assert isinstance(fresh._cache, kernel_cache.KernelCache)
    assert fresh._cache.cache_path.startswith(str(shipped_root.parent / "numba-cache"))  # numba's place for saving
    (sig,) = kernel.signatures
    with _Compiles() as compiled:
        fresh.compile(sig)
    assert compiled == [] and fresh.stats.cache_hits[sig] == 1
    a = np.array([[0.0, 0.0, 10.0, 10.0], [5.0, 5.0, 20.0, 20.0]])
    assert np.array_equal(fresh(a, a, True), kernel(a, a, True))
    assert not any(Path(fresh._cache.cache_path).glob("*.nbi"))  # nothing written: the shipped code is only read


@pytest.mark.skipif(_DISABLE_JIT, reason="NUMBA_DISABLE_JIT: nothing is compiled")
def test_a_shipped_kernel_of_other_sources_is_not_loaded(shipped_root: Path) -> None:
    """The shipped index carries the content stamp: an installation whose sources differ compiles."""
    from kitti_eval.core import geometry

    kernel = geometry._iou_2d_kernel
    _ship(shipped_root, kernel, stamp=("kitti-eval-kernel-closure-1", "0" * 64))
    fresh = _fresh(kernel)
    with _Compiles() as compiled:
        fresh.compile(kernel.signatures[0])
    assert "_iou_2d_kernel" in compiled
    assert any(Path(fresh._cache.cache_path).glob("geometry._iou_2d_kernel-*.nbi"))  # saved where numba saves


def test_shipped_kernels_are_used_only_for_their_numba_python_and_a_portable_target(shipped_root: Path) -> None:
    assert kernel_cache.shipped_kernels() is None  # no manifest: an editable or source install
    shipped_root.mkdir()
    here = (numba.__version__, kernel_cache.python_tag())
    for (numba_version, python), usable in [(here, True), (("0.1.0", here[1]), False), ((here[0], "py27"), False)]:
        manifest = {"numba": numba_version, "python": python, "target": ["x86_64-unknown-linux-gnu", "generic", ""]}
        (shipped_root / "manifest.json").write_text(json.dumps({**manifest, "kernels": 3}))
        kernel_cache.shipped_kernels.cache_clear()
        assert (kernel_cache.shipped_kernels() is not None) == usable
    x86 = kernel_cache.ShippedKernels(shipped_root, "", "", ("x86_64-unknown-linux-gnu", "generic", ""), 1)
    assert x86.usable_on(("x86_64-unknown-linux-gnu", "skylake-avx512", "+avx512f"))
    assert not x86.usable_on(("aarch64-unknown-linux-gnu", "neoverse-n1", ""))
    host_specific = kernel_cache.ShippedKernels(shipped_root, "", "", ("x86_64-unknown-linux-gnu", "znver4", ""), 1)
    assert not host_specific.usable_on(("x86_64-unknown-linux-gnu", "skylake", ""))


# -- nowhere writable: another uid, a read-only installation, no home (tests/packaging/test_any_uid.py runs it) --


@pytest.fixture
def nowhere_writable(shipped_root: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """numba finds no writable place (its locators all refuse); the read-only place is an empty folder of this
    test's. Returns that folder."""
    read_only = shipped_root.parent / "read-only"
    read_only.mkdir()
    monkeypatch.setattr(kernel_cache._impl_class(), "_locator_classes", [kernel_cache.KernelLocator])
    monkeypatch.setattr(kernel_cache.ReadOnlyLocator, "get_cache_path", lambda self: str(read_only))
    monkeypatch.setattr(kernel_cache, "_warned", False)
    return read_only


@pytest.mark.skipif(_DISABLE_JIT, reason="NUMBA_DISABLE_JIT: nothing is compiled")
def test_with_nowhere_writable_a_kernel_loads_the_shipped_one_or_compiles_in_memory(
    nowhere_writable: Path, shipped_root: Path
) -> None:
    import warnings

    import numpy as np

    from kitti_eval.core import geometry

    shipped, other = geometry._iou_2d_kernel, geometry._frame_overlaps_kernel
    _ship(shipped_root, shipped)
    assert kernel_cache.writable_cache() is None
    fresh = _fresh(shipped)
    assert fresh._cache._impl.locator.read_only
    with warnings.catch_warnings(record=True) as caught, _Compiles() as compiled:
        warnings.simplefilter("always")
        fresh.compile(shipped.signatures[0])
    assert compiled == [] and caught == []  # the shipped code: nothing compiled, nothing to say
    a = np.array([[0.0, 0.0, 10.0, 10.0], [5.0, 5.0, 20.0, 20.0]])
    assert np.array_equal(fresh(a, a, True), shipped(a, a, True))
    with warnings.catch_warnings(record=True) as caught, _Compiles() as compiled:
        warnings.simplefilter("always")
        for _ in range(2):  # a second dispatcher of it, as a second kernel: compiled again, said once
            _fresh(other).compile(other.signatures[0])
    assert compiled == ["_frame_overlaps_kernel", "_frame_overlaps_kernel"]
    assert [w.category for w in caught] == [kernel_cache.KernelCacheWarning]
    assert "NUMBA_CACHE_DIR" in str(caught[0].message) and "compiled in memory" in str(caught[0].message)
    assert list(nowhere_writable.iterdir()) == [] and not (shipped_root.parent / "numba-cache").exists()


def test_kernel_cache_warnings_go_where_the_application_says(monkeypatch: pytest.MonkeyPatch) -> None:
    import warnings

    passed_on: list[type[Warning]] = []
    monkeypatch.setattr(warnings, "showwarning", lambda message, category, *rest, **kw: passed_on.append(category))
    said: list[str] = []
    kernel_cache.route_warnings(said.append)
    kernel_cache.route_warnings(said.append)  # routed again (the CLI's command and the service in one process)
    warnings.showwarning("in memory", kernel_cache.KernelCacheWarning, "x.py", 1)
    warnings.showwarning("other", UserWarning, "x.py", 1)
    assert said == ["in memory"] and passed_on == [UserWarning]
