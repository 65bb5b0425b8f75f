"""A database of a release before the schema had versions, imitated from one this release made: the tables later
revisions added dropped (that release never had them), then the recorded version. The columns a test's release
lacked are the test's to drop."""

from __future__ import annotations

import importlib
from collections.abc import Callable

import kitti_eval_server.store  # noqa: F401 - every area's tables on the metadata
from kitti_eval_server.store.database import metadata

__all__ = ["later_tables", "as_unversioned"]


def later_tables() -> list[str]:
    """The code's tables the base revision does not make, those that refer to others first."""
    base = importlib.import_module("kitti_eval_server.store.migrations.versions.0001_base").metadata
    return [t.name for t in reversed(metadata.sorted_tables) if t.name not in base.tables]


def as_unversioned(execute: Callable[[str], object]) -> None:
    """Through ``execute`` (``sqlite3.Connection.execute``, or a function that runs SQLAlchemy's ``text``): drop
    the later revisions' tables and the version."""
    for table in later_tables():
        execute(f"DROP TABLE {table}")
    execute("DROP TABLE alembic_version")
