"""The rules that split the suite into the quick command and the slow one (tests/helpers/slow_tests.py): a test
that starts a process is slow however deep in the suite's helpers the process starts, and one that does not
stays quick. New tests are classified by these rules alone, so they are what keeps the quick command quick."""

from __future__ import annotations

import inspect
import subprocess

import server_helpers
import server_postgres
from slow_tests import PROCESS_NAMES, starts_a_process


class _Daemon:
    """A helper class of the kind the suite has (a live server, a database cluster): the process is in a method."""

    def start(self) -> None:
        subprocess.Popen(["sleep", "1"])  # never run: the rules read code, they do not call it


def _helper_that_starts_one() -> None:
    _Daemon().start()


def _test_through_two_helpers() -> None:
    _helper_that_starts_one()


def _test_naming_a_program() -> None:
    command = ["pg_ctl", "start"]
    print(command)  # noqa: T201 - code for the rules to read, never run


def _test_in_process() -> None:
    assert sum([1, 2]) == 3


def _test_importing_a_helper_inside() -> None:
    from server_helpers import LiveServer

    LiveServer  # noqa: B018 - code for the rules to read, never run


#: the samples by name: a test that named them directly would reach their processes itself and be slow
SAMPLES = {
    "helper": _helper_that_starts_one,
    "two helpers": _test_through_two_helpers,
    "program": _test_naming_a_program,
    "in process": _test_in_process,
    "imported inside": _test_importing_a_helper_inside,
}
HELPERS = {
    "live server": getattr(server_helpers, "LiveServer").start,  # noqa: B009 - not a name, for the same reason
    "database": getattr(server_postgres, "PostgresCluster").start,  # noqa: B009
    "in-process service": getattr(server_helpers, "app_client").__wrapped__,  # noqa: B009 - the function itself
}


def test_a_process_started_in_a_helper_of_a_helper_makes_the_test_slow() -> None:
    assert starts_a_process(SAMPLES["helper"])
    assert starts_a_process(SAMPLES["two helpers"])
    assert starts_a_process(SAMPLES["imported inside"])  # a module imported inside the function


def test_a_program_named_in_a_command_makes_the_test_slow() -> None:
    assert starts_a_process(SAMPLES["program"])


def test_code_that_starts_nothing_stays_quick() -> None:
    assert not starts_a_process(SAMPLES["in process"])
    assert not starts_a_process(HELPERS["in-process service"])  # the service in-process, as most server tests use
    assert not starts_a_process(print)  # not the suite's code: not followed
    assert inspect.getsourcefile(HELPERS["in-process service"]) == server_helpers.__file__  # followed, not contextlib


def test_the_suites_process_helpers_are_recognised() -> None:
    """The helpers that start the slow things of the suite: uvicorn, PostgreSQL."""
    assert starts_a_process(HELPERS["live server"])
    assert starts_a_process(HELPERS["database"])
    assert {"subprocess", "multiprocessing", "webdriver", "LocalCluster"} <= PROCESS_NAMES
