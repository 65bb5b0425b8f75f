"""Which tests are slow: the rules ``tests/conftest.py`` marks ``slow`` by, so that the quick command
(``python -m pytest -q -m "not slow"``) leaves them out and a new test is classified without anyone remembering to.

A test is slow when

* it is marked ``slow`` by hand (a long computation: a statistical check, a large set; or processes the
  library starts itself, which the rules do not follow: a local Dask cluster);
* its module is a sweep (``test_*_sweep.py``: every route against every caller, hundreds of cases); or
* it starts a process: its code, or any code of the suite it reaches by name (the fixtures it asks for, the
  helpers and classes they call, transitively), uses ``subprocess``, ``multiprocessing``, a process pool, a
  browser driver, Dask's cluster, or names PostgreSQL's, Chromium's, docker's or uvicorn's programs. A live
  service, worker processes, a throwaway PostgreSQL cluster, Chromium, a CLI run in a new interpreter, a
  container: each costs seconds, and these are what made the whole suite take a quarter of an hour.

Only the suite's own code is followed (files under ``tests/``); the library's and the service's are not, so a
test of the service that runs in-process stays quick even where the service could start processes.
"""

from __future__ import annotations

import inspect
import sys
import types
from collections.abc import Callable, Iterable
from functools import cache
from pathlib import Path
from typing import Any

TESTS = Path(__file__).resolve().parent.parent

#: names whose use means a new process (modules, classes, functions; matched against the names code uses)
PROCESS_NAMES = frozenset(
    {
        "subprocess",
        "Popen",
        "multiprocessing",
        "ProcessPoolExecutor",
        "fork",
        "spawnv",
        "execv",
        "webdriver",
        "LocalCluster",
    }
)
#: programs whose name, as a string of its own or a command line's first word, means a new process
PROCESS_PROGRAMS = frozenset({"pg_ctl", "initdb", "postgres", "chromium", "chromedriver", "docker", "uvicorn"})
#: a module of sweeps: every route against every caller or input
SWEEP_FILE = "_sweep.py"


def _in_suite(obj: Any) -> bool:
    try:
        path = inspect.getsourcefile(obj)
    except TypeError:
        return False
    return path is not None and Path(path).resolve().is_relative_to(TESTS)


def _codes(code: types.CodeType) -> Iterable[types.CodeType]:
    yield code
    for const in code.co_consts:
        if isinstance(const, types.CodeType):
            yield from _codes(const)


def _functions_of(obj: Any) -> list[Callable[..., Any]]:
    """The functions a name of the suite stands for: itself, a class's methods, a fixture's function."""
    obj = getattr(obj, "__wrapped__", obj)  # a fixture: pytest keeps the function under __wrapped__
    get = getattr(obj, "_get_wrapped_function", None)
    if callable(get):
        obj = get()
    if isinstance(obj, types.FunctionType):
        return [obj]
    if isinstance(obj, type):
        out: list[Callable[..., Any]] = []
        for value in vars(obj).values():
            value = value.fget if isinstance(value, property) else getattr(value, "__func__", value)
            if isinstance(value, types.FunctionType):
                out.append(value)
        return out
    return []


@cache
def starts_a_process(fn: Callable[..., Any]) -> bool:
    """Whether ``fn`` (a function of the suite) starts a process, or calls code of the suite that does."""
    return _starts(fn, set())


def _starts(fn: Callable[..., Any], seen: set[Any]) -> bool:
    if fn in seen or not isinstance(fn, types.FunctionType) or not _in_suite(fn):
        return False
    seen.add(fn)
    names: set[str] = set()
    for code in _codes(fn.__code__):
        names.update(code.co_names)
        names.update(code.co_freevars)
        for const in code.co_consts:
            if isinstance(const, str) and _names_a_program(const):
                return True
    if names & PROCESS_NAMES or any(n.split(".")[-1] in PROCESS_NAMES for n in names):
        return True
    scope = dict(fn.__globals__)
    if fn.__closure__:
        scope.update(zip(fn.__code__.co_freevars, (c.cell_contents for c in fn.__closure__ if _filled(c))))
    imported = [sys.modules.get(n) for n in names]  # modules imported inside the function
    modules = [m for m in [*scope.values(), *imported] if isinstance(m, types.ModuleType) and _in_suite(m)]
    for name in names:
        candidates = [scope[name]] if name in scope else []
        candidates += [getattr(m, name) for m in modules if hasattr(m, name)]
        for obj in candidates:
            if any(_starts(f, seen) for f in _functions_of(obj)):
                return True
    return False


def _names_a_program(text: str) -> bool:
    words = text.split(maxsplit=1)
    return bool(words) and "\n" not in text and words[0].rsplit("/", 1)[-1] in PROCESS_PROGRAMS


def _filled(cell: types.CellType) -> bool:
    try:
        cell.cell_contents  # noqa: B018 - an empty cell raises
    except ValueError:
        return False
    return True


def why_slow(item: Any) -> str | None:
    """Why the collected test ``item`` is slow (a rule of the module docstring), None when it is quick."""
    if item.get_closest_marker("slow") is not None:
        return "marked slow"
    if item.path.name.endswith(SWEEP_FILE):
        return "a sweep"
    fn = getattr(item, "function", None)
    if fn is not None and starts_a_process(fn):
        return "starts a process"
    info = getattr(item, "_fixtureinfo", None)
    for name, defs in info.name2fixturedefs.items() if info is not None else ():
        for fixture in defs:
            if any(starts_a_process(f) for f in _functions_of(fixture.func)):
                return f"starts a process (fixture {name})"
    return None
