"""Shared fixtures: the kernels warmed once per session, and the service's test client; a marker a folder.

The tests are grouped by layer, a folder each, and each folder's tests carry its name as a marker:
``core`` (kernels, curves, the protocol's scenarios: a seconds-long loop), ``io``, ``analysis``, ``cli``,
``compat``, ``server`` (the service, its jobs and databases: processes), ``web`` (pages, some in Chromium),
``docs`` (the README's and the pages' examples), ``packaging`` (wheels, containers, CI). ``pytest tests/core``
or ``pytest -m core`` runs one; ``helpers/`` holds what they share (on the path by pyproject's ``pythonpath``).
Every test is also marked ``slow`` or not by the rules of ``helpers/slow_tests.py``: ``-m "not slow"`` is the
quick command, ``-m slow`` the rest."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Any

import pytest


@pytest.fixture(scope="session", autouse=True)
def _warm_kernels() -> None:
    """Compile (or load) every kernel before the first test, so no test's time includes compiling and a
    broken kernel fails here, once, rather than in whichever test happens to run first."""
    from kitti_eval._jit import warm_up

    warm_up()


@pytest.fixture(scope="session", autouse=True)
def _client_config_folder(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """The service client's folder (saved tokens, the keys of submissions not yet shown scored) is the test
    session's, never the user's: a test that names its own sets $KITTI_EVAL_CONFIG_DIR itself."""
    import os

    before = os.environ.get("KITTI_EVAL_CONFIG_DIR")
    os.environ["KITTI_EVAL_CONFIG_DIR"] = str(tmp_path_factory.mktemp("client-config"))
    yield
    if before is None:
        os.environ.pop("KITTI_EVAL_CONFIG_DIR", None)
    else:
        os.environ["KITTI_EVAL_CONFIG_DIR"] = before


@pytest.fixture(scope="module")
def service_client(tmp_path_factory: pytest.TempPathFactory) -> Callable[..., AbstractContextManager[Any]]:
    """A factory of TestClients on a fresh app in a folder of this module's (settings as keywords)."""
    from server_helpers import app_client

    def make(**settings: Any) -> AbstractContextManager[Any]:
        return app_client(tmp_path_factory.mktemp("service") / "data", **settings)

    return make


@pytest.fixture(scope="module")
def client(service_client: Callable[..., AbstractContextManager[Any]]) -> Iterator[Any]:
    """A TestClient on a fresh app with the default settings, shared by the tests of a module."""
    with service_client() as c:
        yield c


TESTS = Path(__file__).parent
FOLDERS = ("core", "io", "analysis", "cli", "compat", "server", "web", "docs", "packaging")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    from slow_tests import why_slow

    for item in items:
        folder = item.path.relative_to(TESTS).parts[0]  # tests/server/jobs/... is a test of tests/server
        if folder in FOLDERS:
            item.add_marker(getattr(pytest.mark, folder))
        if item.get_closest_marker("slow") is None and why_slow(item) is not None:
            item.add_marker(pytest.mark.slow)  # the rules of tests/helpers/slow_tests.py


#: a quick test that takes longer than this is named at the end of the quick command's run
QUICK_TEST_S = 10.0


def pytest_terminal_summary(terminalreporter: Any, exitstatus: int, config: pytest.Config) -> None:
    """After the quick command (-m "not slow"), name the tests that took long without being slow by the rules
    (a long computation in-process): mark them slow if they take as long on an idle machine."""
    if config.option.markexpr.replace(" ", "") != "notslow":
        return
    reports = [r for key in ("passed", "failed") for r in terminalreporter.stats.get(key, []) if r.when == "call"]
    long = sorted(((r.duration, r.nodeid) for r in reports if r.duration > QUICK_TEST_S), reverse=True)
    if long:
        terminalreporter.section(f"quick tests that took over {QUICK_TEST_S:.0f} s")
        for duration, nodeid in long:
            terminalreporter.write_line(f"{duration:6.1f} s  {nodeid}")


def pytest_configure(config: pytest.Config) -> None:
    for folder in FOLDERS:
        config.addinivalue_line("markers", f"{folder}: the tests of tests/{folder}/ (a marker a folder)")
    config.addinivalue_line(
        "markers",
        "slow: starts a process, sweeps, or computes long (tests/helpers/slow_tests.py marks them); "
        "-m 'not slow' is the quick command",
    )
