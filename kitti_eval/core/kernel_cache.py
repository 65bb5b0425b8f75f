"""numba's on-disk cache for this package's kernels, made to depend on everything a kernel compiles in.

numba decides whether a cached kernel is still valid by the source file that defines it, and only that file.
A kernel that calls a kernel of another module, or reads a constant of another module, has the other's
machine code and values compiled into its own; numba does not notice when that other module changes, and
loads the old code. That is what happened to the error decomposition, whose kernels call the matching
kernels of :mod:`kitti_eval.core.matching`: an edit of the matching rule (or an upgrade that changed
matching.py but not decomposition.py) left the decomposition running the old rule.

Here every cached kernel of the package is stamped with a digest of its own module *and of every module of
the package that module imports, directly or through others* (module-level imports, read from the source
with :mod:`ast`; a kernel can only reach what its module's globals hold). A change to any of them changes the
stamp, numba finds the cached kernel stale and compiles it again. The digest is over the files' content, not
their modification times, so a reinstall of the same sources keeps the cache valid.

The stamp is given to numba through a cache locator: :class:`KernelLocator` sits first in numba's list of
locators, answers only for functions defined in this package (a user's own numba code is cached as numba
always does), finds the folder through numba's own locators (``NUMBA_CACHE_DIR``, the package's
``__pycache__``, the user-wide cache) and changes only the stamp. Kernel modules import :func:`njit` from
here, so the locator is in place before their first kernel is decorated (``tests/test_kernel_cache.py``
checks that no module takes ``njit`` from numba directly).
"""

from __future__ import annotations

import ast
import hashlib
import os
from collections.abc import Iterator
from functools import cache
from pathlib import Path
from typing import Any

from numba import njit
from numba.core import caching

__all__ = ["KernelLocator", "kernel_modules", "kernel_stamp", "njit"]

#: the folder of this package (``kitti_eval/``): the locator answers for the files below it
PACKAGE_ROOT = Path(__file__).resolve().parents[1]
_PACKAGE_NAME = PACKAGE_ROOT.name
#: marks a stamp as this package's (numba compares stamps for equality; any picklable value will do)
_STAMP_TAG = "kitti-eval-kernel-closure-1"


def _module_file(root: Path, dotted: str) -> Path | None:
    """The file of module ``dotted`` (``kitti_eval.core.matching``) below ``root``, or None."""
    parts = dotted.split(".")
    if parts[0] != root.name:
        return None
    base = root.joinpath(*parts[1:])
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _module_name(root: Path, path: Path) -> str:
    parts = [root.name, *path.relative_to(root).with_suffix("").parts]
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _module_level(body: list[ast.stmt]) -> Iterator[ast.stmt]:
    """The statements that run when the module is imported: descends into if/try/with, not into functions
    or classes (a kernel sees only the module's globals)."""
    for node in body:
        yield node
        if isinstance(node, (ast.If, ast.For, ast.While)):
            yield from _module_level(node.body)
            yield from _module_level(node.orelse)
        elif isinstance(node, ast.With):
            yield from _module_level(node.body)
        elif isinstance(node, ast.Try):
            yield from _module_level(node.body)
            for handler in node.handlers:
                yield from _module_level(handler.body)
            yield from _module_level(node.orelse)
            yield from _module_level(node.finalbody)


def _imported(root: Path, path: Path) -> frozenset[Path]:
    """The files of this package that module ``path`` imports at module level."""
    st = path.stat()
    return _imported_memo(root, path, st.st_mtime_ns, st.st_size)


@cache
def _imported_memo(root: Path, path: Path, mtime_ns: int, size: int) -> frozenset[Path]:
    del mtime_ns, size  # part of the memo key only: an edited file is parsed again
    module = _module_name(root, path)
    is_package = path.name == "__init__.py"
    tree = ast.parse(path.read_bytes(), filename=str(path))
    found: set[Path] = set()

    def add(dotted: str) -> None:
        target = _module_file(root, dotted)
        if target is not None:
            found.add(target)

    for node in _module_level(tree.body):
        if isinstance(node, ast.Import):
            for alias in node.names:
                add(alias.name)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base_parts = module.split(".") if is_package else module.split(".")[:-1]
                base_parts = base_parts[: len(base_parts) - (node.level - 1)]
                base = ".".join([*base_parts, node.module] if node.module else base_parts)
            else:
                base = node.module or ""
            add(base)
            for alias in node.names:
                add(f"{base}.{alias.name}")  # `from . import matching` names a module
    found.discard(path)
    return frozenset(found)


def kernel_modules(path: Path, root: Path = PACKAGE_ROOT) -> list[Path]:
    """``path`` and every file of the package it imports at module level, directly or through others: all
    that the kernels defined in ``path`` may have compiled into themselves. Sorted."""
    seen = {path.resolve()}
    todo = [path.resolve()]
    while todo:
        for target in _imported(root, todo.pop()):
            if target not in seen:
                seen.add(target)
                todo.append(target)
    return sorted(seen)


@cache
def _stamp(path: Path, root: Path, signature: tuple[tuple[str, int, int], ...]) -> tuple[str, str]:
    del signature  # part of the memo key only: an edited file is read again
    digest = hashlib.sha256()
    for source in kernel_modules(path, root):
        digest.update(source.relative_to(root).as_posix().encode() + b"\0" + source.read_bytes() + b"\0")
    return _STAMP_TAG, digest.hexdigest()


def kernel_stamp(path: str | os.PathLike[str], root: Path = PACKAGE_ROOT) -> tuple[str, str]:
    """The stamp numba keeps with the cached kernels of module ``path``: a digest of the content of
    :func:`kernel_modules` (names relative to the package, so the stamp does not depend on where it is
    installed; numba's cache folders already do)."""
    resolved = Path(path).resolve()
    closure = kernel_modules(resolved, root)
    signature = tuple((str(p), p.stat().st_mtime_ns, p.stat().st_size) for p in closure)
    return _stamp(resolved, root, signature)


def _is_ours(py_file: str) -> bool:
    try:
        return Path(py_file).resolve().is_relative_to(PACKAGE_ROOT) and py_file.endswith(".py")
    except (OSError, ValueError):
        return False


def _impl_class() -> Any:
    """numba's cache implementation class holding the list of locators (renamed in numba 0.68)."""
    return getattr(caching, "CacheImpl", None) or getattr(caching, "_CacheImpl")  # noqa: B009


class KernelLocator(caching._CacheLocator):
    """numba's own locator for a kernel of this package, with the stamp of :func:`kernel_stamp`."""

    def __init__(self, inner: Any, py_file: str) -> None:
        self._inner = inner
        self._py_file = py_file

    def ensure_cache_path(self) -> None:
        self._inner.ensure_cache_path()

    def get_cache_path(self) -> str:
        return str(self._inner.get_cache_path())

    def get_source_stamp(self) -> tuple[str, str]:
        return kernel_stamp(self._py_file)

    def get_disambiguator(self) -> str:
        return str(self._inner.get_disambiguator())

    @classmethod
    def from_function(cls, py_func: Any, py_file: str) -> KernelLocator | None:
        if not _is_ours(py_file):
            return None
        for other in _impl_class()._locator_classes:
            if other is cls:
                continue
            inner = other.from_function(py_func, py_file)
            if inner is not None:
                try:
                    kernel_stamp(py_file)
                except (OSError, SyntaxError, ValueError):
                    return None  # sources not readable as files: numba's own stamp
                return cls(inner, py_file)
        return None


def _install() -> None:
    locators = _impl_class()._locator_classes
    if KernelLocator not in locators:
        locators.insert(0, KernelLocator)


_install()
