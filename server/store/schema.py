"""The schema's version: Alembic's revisions (``migrations/versions``), run by the service on its own connection.

A database records the revision its schema is at (Alembic's ``alembic_version`` table). At start the service
(:meth:`Database.create_schema <kitti_eval_server.store.database.Database.create_schema>`):

* creates an empty database at the newest revision (the head);
* opens one at the head as it is;
* refuses one at an older revision, or made by a release before the schema had versions (its tables and no
  version), with one sentence naming ``kitti-eval admin db upgrade``, unless told to upgrade at start
  (``KITTI_EVAL_DB_UPGRADE``, ``kitti-eval serve --upgrade``): the upgrade then runs in one transaction under a
  lock (PostgreSQL's advisory lock, SQLite's write lock), so that replicas started together upgrade it once;
* refuses one at a revision this release does not know (a newer release upgraded it).

A database of an unversioned release is brought to the base revision by the base revision's own upgrade
(the tables and the columns it lacks, as that release's start added them), then to the head.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from pathlib import Path

from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import inspect
from sqlalchemy.engine import Connection

__all__ = ["MIGRATIONS", "SchemaState", "alembic_config", "head", "state_of", "upgrade"]

MIGRATIONS = Path(__file__).resolve().parent / "migrations"
#: a table every release's schema has had: a database holding it and no version is an unversioned release's
_ALWAYS = "evaluations"


def alembic_config(conn: Connection | None = None) -> Config:
    """Alembic's configuration for this package's revisions, on ``conn`` (``env.py`` runs on it)."""
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS))
    config.set_main_option("path_separator", "os")
    if conn is not None:
        config.attributes["connection"] = conn
    return config


@cache
def _script() -> ScriptDirectory:
    return ScriptDirectory.from_config(alembic_config())


def head() -> str:
    """The newest revision this release knows."""
    found = _script().get_current_head()
    assert found is not None
    return found


def known(revision: str) -> bool:
    try:
        return _script().get_revision(revision) is not None
    except Exception:  # noqa: BLE001 - alembic's "no such revision" has several classes
        return False


@dataclass(frozen=True)
class SchemaState:
    """Where a database's schema is: its revision (None: none recorded) and whether it holds the tables."""

    revision: str | None
    has_tables: bool

    @property
    def empty(self) -> bool:
        return self.revision is None and not self.has_tables

    @property
    def current(self) -> bool:
        return self.revision == head()

    @property
    def newer(self) -> bool:
        """At a revision this release does not know: a newer one upgraded it."""
        return self.revision is not None and not known(self.revision)

    def describe(self) -> str:
        if self.empty:
            return "empty (no kitti-eval tables)"
        if self.revision is None:
            return "unversioned (made by a release before the schema had versions: no revision recorded)"
        if self.newer:
            return f"at revision {self.revision}, which this release does not know (a newer release upgraded it)"
        return f"at revision {self.revision}" + (" (the newest)" if self.current else "")


def state_of(conn: Connection) -> SchemaState:
    revision = MigrationContext.configure(conn).get_current_revision()
    return SchemaState(revision, inspect(conn).has_table(_ALWAYS))


def upgrade(conn: Connection, revision: str = "head") -> None:
    """Run the revisions from the database's to ``revision`` on ``conn`` (in its transaction)."""
    command.upgrade(alembic_config(conn), revision)
