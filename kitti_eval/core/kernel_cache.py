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
here, so the locator is in place before their first kernel is decorated (``tests/packaging/test_kernel_cache.py``
checks that no module takes ``njit`` from numba directly).

A platform wheel (``scripts/build_wheel.py``) also carries the kernels, compiled for the generic CPU of its
platform (``NUMBA_CPU_NAME=generic`` in the build's process only), in ``kitti_eval/_kernels/``: a folder of
numba cache files laid out like the package, with a manifest naming the numba and Python versions and the
target they were compiled for. numba keys a cached kernel by the CPU it was compiled for, so a process
compiling for its own CPU (the default, which this module leaves alone) would never look at them. The
:func:`njit` of this module therefore gives every cached kernel a :class:`KernelCache`: numba's own cache
(same folders, same keys, new compilations saved where numba saves them) that, when it holds nothing for
the kernel, reads the shipped index under the generic target's key. Generic code runs on every CPU of its
target (x86-64 code without AVX runs on any x86-64), and it is numba's own loader that links it in. The
shipped index carries the same content stamp as any other, so an edited installation never loads them, and
it is only read: a read-only site-packages or a ``NUMBA_CACHE_DIR`` elsewhere changes nothing.

Where numba finds no writable place at all (no ``NUMBA_CACHE_DIR``, a read-only installation, no writable
home: another uid in a container, a read-only root filesystem, a shared installation on a cluster), numba
itself refuses to decorate a ``cache=True`` function (``RuntimeError: cannot cache function ...: no locator
available``). A kernel of this package then gets a read-only place instead (:class:`ReadOnlyLocator`: the
module's ``__pycache__``, as numba's in-tree cache, read but never written): it loads what is there or what
the wheel ships, and what it has to compile stays in memory for the process, with one
:class:`KernelCacheWarning` saying how to keep it (``NUMBA_CACHE_DIR``).
"""

from __future__ import annotations

import ast
import hashlib
import inspect
import json
import os
import sys
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

import numba
from numba.core import caching
from numba.core.dispatcher import Dispatcher

__all__ = [
    "SHIPPED_ROOT",
    "KernelCache",
    "KernelCacheWarning",
    "KernelLocator",
    "ReadOnlyLocator",
    "ShippedKernels",
    "kernel_modules",
    "kernel_stamp",
    "njit",
    "python_tag",
    "read_manifest",
    "route_warnings",
    "shipped_kernels",
    "writable_cache",
]

#: the folder of this package (``kitti_eval/``): the locator answers for the files below it
PACKAGE_ROOT = Path(__file__).resolve().parents[1]
_PACKAGE_NAME = PACKAGE_ROOT.name
#: marks a stamp as this package's (numba compares stamps for equality; any picklable value will do)
_STAMP_TAG = "kitti-eval-kernel-closure-1"
#: where a platform wheel keeps its kernels: numba's cache files, in folders named as the package's
SHIPPED_ROOT = PACKAGE_ROOT / "_kernels"
#: what the build writes beside them: numba and Python versions, the target compiled for, the kernels
MANIFEST = "manifest.json"
#: CPU names whose code runs on every CPU of their target triple (numba's magic tuple: triple, name, features)
PORTABLE_CPUS = frozenset({"generic"})


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


class KernelCacheWarning(RuntimeWarning):
    """The kernels are compiled in memory only: no place for numba's cache is writable."""


def _no_place_message() -> str:
    custom = os.environ.get("NUMBA_CACHE_DIR")
    tried = f"NUMBA_CACHE_DIR={custom}" if custom else "NUMBA_CACHE_DIR is unset"
    return (
        f"numba's cache has no writable place ({tried}; {PACKAGE_ROOT}'s __pycache__ and the user's cache folder "
        "are not writable): the kernels are compiled in memory by every process that uses them, "
        "on every run; set NUMBA_CACHE_DIR to a writable folder to keep them"
    )


_warned = False


def _warn_in_memory() -> None:
    """One :class:`KernelCacheWarning` a process, on the first kernel compiled with nowhere to keep it."""
    global _warned
    if not _warned:
        _warned = True
        warnings.warn(_no_place_message(), KernelCacheWarning, stacklevel=2)


def route_warnings(show: Callable[[str], None]) -> None:
    """Have :class:`KernelCacheWarning` said by ``show`` (the CLI's stderr line, the service's log) instead of
    Python's ``file:line: Warning`` print; every other warning is shown as before."""
    previous = warnings.showwarning
    if getattr(previous, "_kitti_eval_route", None) is not None:
        previous = previous._kitti_eval_route  # type: ignore[attr-defined]

    def showwarning(message: Any, category: type[Warning], *args: Any, **kwargs: Any) -> None:
        if issubclass(category, KernelCacheWarning):
            show(str(message))
        else:
            previous(message, category, *args, **kwargs)

    showwarning._kitti_eval_route = previous  # type: ignore[attr-defined]
    warnings.showwarning = showwarning


class ReadOnlyLocator(caching._CacheLocator):
    """numba's in-tree place (the module's ``__pycache__``), read and never written: the place of a kernel of
    this package when numba finds no writable one. Cache files there (an installation warmed before it was
    made read-only) load; a compiled kernel is not saved (:meth:`KernelCache._save_overload`)."""

    def __init__(self, py_func: Any, py_file: str) -> None:
        self._py_file = py_file
        self._lineno = py_func.__code__.co_firstlineno  # numba's disambiguator: the same cache file names
        self._cache_path = os.path.join(os.path.dirname(py_file), "__pycache__")

    def ensure_cache_path(self) -> None:
        raise OSError(f"{self._cache_path}: numba's cache is only read here")

    def get_cache_path(self) -> str:
        return self._cache_path

    def get_source_stamp(self) -> tuple[str, str]:
        return kernel_stamp(self._py_file)

    def get_disambiguator(self) -> str:
        return str(self._lineno)

    @classmethod
    def from_function(cls, py_func: Any, py_file: str) -> ReadOnlyLocator:
        return cls(py_func, py_file)


def writable_cache(py_file: str | os.PathLike[str] | None = None) -> str | None:
    """The folder numba saves this package's kernels (those of ``py_file``, default the matching kernels' module)
    in, or None when no place is writable and they are compiled in memory only."""
    py_file = str(py_file or PACKAGE_ROOT / "core" / "matching.py")
    locator = KernelLocator.from_function(writable_cache, py_file)
    return None if locator is None or locator.read_only else locator.get_cache_path()


class KernelLocator(caching._CacheLocator):
    """numba's own locator for a kernel of this package, with the stamp of :func:`kernel_stamp`; where numba's
    locators find no writable place, a :class:`ReadOnlyLocator`."""

    def __init__(self, inner: Any, py_file: str) -> None:
        self._inner = inner
        self._py_file = py_file

    @property
    def py_file(self) -> str:
        return self._py_file

    @property
    def read_only(self) -> bool:
        """True when nothing compiled is saved (no writable place)."""
        return isinstance(self._inner, ReadOnlyLocator)

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
        try:
            kernel_stamp(py_file)
        except (OSError, SyntaxError, ValueError):
            return None  # sources not readable as files: numba's own stamp
        for other in _impl_class()._locator_classes:
            if other is cls:
                continue
            inner = other.from_function(py_func, py_file)
            # numba's user-wide place is relative (``~/.cache``) where no home is found: never the working folder
            if inner is not None and os.path.isabs(str(inner.get_cache_path())):
                return cls(inner, py_file)
        return cls(ReadOnlyLocator.from_function(py_func, py_file), py_file)


def python_tag() -> str:
    """The Python part of numba's cache file names (``py311``): a cache is for one Python version."""
    return f"py{sys.version_info[0]}{sys.version_info[1]}{getattr(sys, 'abiflags', '')}"


@dataclass(frozen=True)
class ShippedKernels:
    """The kernels a platform wheel carries, as its manifest describes them."""

    root: Path
    numba: str
    python: str
    #: numba's magic tuple of the build's codegen: (target triple, CPU name, CPU features)
    target: tuple[str, str, str]
    kernels: int

    def usable_on(self, magic: tuple[str, str, str]) -> bool:
        """True when code compiled for :attr:`target` runs under a codegen of ``magic`` (same triple)."""
        return self.target[0] == magic[0] and self.target[1] in PORTABLE_CPUS

    def folder(self, py_file: str) -> Path:
        """Where the cache files of the kernels of ``py_file`` (a module of the package) are."""
        return self.root.joinpath(*Path(py_file).resolve().relative_to(PACKAGE_ROOT).parent.parts)


def read_manifest(root: Path | None = None) -> ShippedKernels | None:
    """The manifest of ``root`` (:data:`SHIPPED_ROOT`), or None when there is none (an editable or source
    install) or it is unreadable."""
    root = SHIPPED_ROOT if root is None else root
    try:
        doc = json.loads((root / MANIFEST).read_text(encoding="utf-8"))
        triple, cpu, features = (str(part) for part in doc["target"])
        return ShippedKernels(root, str(doc["numba"]), str(doc["python"]), (triple, cpu, features), int(doc["kernels"]))
    except (OSError, ValueError, KeyError, TypeError):
        return None


@cache
def shipped_kernels() -> ShippedKernels | None:
    """The kernels this installation carries, if they were built for the running numba and Python."""
    shipped = read_manifest()
    if shipped is None or shipped.numba != numba.__version__ or shipped.python != python_tag():
        return None
    return shipped


class KernelCache(caching.FunctionCache):
    """numba's cache of one kernel of the package, which also reads the kernels a platform wheel ships.

    Loading looks in numba's own place first, under numba's own key (the kernels compiled on this machine,
    for its CPU); when that holds nothing, in the shipped index under the key of the target the wheel was
    built for, if code for that target runs here. Saving is numba's: a kernel compiled here is kept in
    numba's place, for this CPU; the shipped files are never written."""

    def __init__(self, py_func: Any) -> None:
        super().__init__(py_func)
        self._shipped: tuple[ShippedKernels, caching.IndexDataCacheFile] | None = None
        shipped = shipped_kernels()
        if shipped is not None and isinstance(self._impl.locator, KernelLocator):
            index = caching.IndexDataCacheFile(
                cache_path=str(shipped.folder(self._impl.locator.py_file)),
                filename_base=self._impl.filename_base,
                source_stamp=self._impl.locator.get_source_stamp(),
            )
            self._shipped = shipped, index

    def _load_overload(self, sig: Any, target_context: Any) -> Any:
        data = super()._load_overload(sig, target_context)
        if data is not None or self._shipped is None or not self._enabled:
            return data
        shipped, index = self._shipped
        codegen = target_context.codegen()
        if not shipped.usable_on(codegen.magic_tuple()):
            return None
        own_key = self._index_key(sig, codegen)
        found = index.load((own_key[0], shipped.target, *own_key[2:]))
        return None if found is None else self._impl.rebuild(target_context, found)

    def _save_overload(self, sig: Any, data: Any) -> None:
        locator = self._impl.locator
        if isinstance(locator, KernelLocator) and locator.read_only:
            if self._enabled and self._impl.check_cachable(data):
                _warn_in_memory()
            return
        super()._save_overload(sig, data)


def njit(*args: Any, **options: Any) -> Any:
    """numba's ``njit``, whose kernels with ``cache=True`` have a :class:`KernelCache`.

    As a decorator, bare or with options. Given signatures (``njit("f8(f8)", ...)``), numba compiles at once,
    before a cache could be swapped in: that form is numba's own, with numba's cache."""
    if len(args) == 1 and inspect.isfunction(args[0]):
        return _kernel(args[0], options)
    if args:
        return numba.njit(*args, **options)
    return lambda func: _kernel(func, options)


def _kernel(func: Callable[..., Any], options: dict[str, Any]) -> Any:
    options = dict(options)
    cached = bool(options.pop("cache", False))
    dispatcher = numba.njit(**options)(func)
    if cached and isinstance(dispatcher, Dispatcher):  # under NUMBA_DISABLE_JIT numba returns the function
        dispatcher._cache = KernelCache(dispatcher.py_func)  # type: ignore[attr-defined]
    return dispatcher


def _install() -> None:
    locators = _impl_class()._locator_classes
    if KernelLocator not in locators:
        locators.insert(0, KernelLocator)


_install()
