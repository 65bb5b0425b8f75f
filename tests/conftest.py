"""Shared fixtures: the kernels warmed once per session, and the service's test client; a marker a folder.

The tests are grouped by layer, a folder each, and each folder's tests carry its name as a marker:
``core`` (kernels, curves, the protocol's scenarios: a seconds-long loop), ``io``, ``analysis``, ``cli``,
``compat``, ``server`` (the service, its jobs and databases: processes), ``web`` (pages, some in Chromium),
``docs`` (the README's and the pages' examples), ``packaging`` (wheels, containers, CI). ``pytest tests/core``
or ``pytest -m core`` runs one; ``helpers/`` holds what they share (on the path by pyproject's ``pythonpath``)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager
from typing import Any

import pytest


@pytest.fixture(scope="session", autouse=True)
def _warm_kernels() -> None:
    """Compile (or load) every kernel before the first test, so no test's time includes compiling and a
    broken kernel fails here, once, rather than in whichever test happens to run first."""
    from kitti_eval._jit import warm_up

    warm_up()


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


FOLDERS = ("core", "io", "analysis", "cli", "compat", "server", "web", "docs", "packaging")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        folder = item.path.parent.name
        if folder in FOLDERS:
            item.add_marker(getattr(pytest.mark, folder))


def pytest_configure(config: pytest.Config) -> None:
    for folder in FOLDERS:
        config.addinivalue_line("markers", f"{folder}: the tests of tests/{folder}/ (a marker a folder)")
    config.addinivalue_line(
        "markers", "slow: kills or starts server processes, or builds the wheel (seconds each); -m 'not slow' skips"
    )
