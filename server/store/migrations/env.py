"""Alembic's environment: run the revisions on the connection :mod:`kitti_eval_server.store.schema` hands over
(in its transaction, under its lock); never a URL of its own. Imported outside Alembic (a walk over the
service's modules), it does nothing."""

from __future__ import annotations

from typing import Any

from alembic import context

import kitti_eval_server.store  # noqa: F401 - every area's tables on the metadata (team_store's too)
from kitti_eval_server.store.database import metadata


def run(connection: Any) -> None:
    context.configure(
        connection=connection,
        target_metadata=metadata,
        render_as_batch=connection.dialect.name == "sqlite",  # SQLite alters a table by copying it
        transaction_per_migration=False,
    )
    with context.begin_transaction():
        context.run_migrations()


_config = getattr(context, "config", None)  # set only while Alembic runs this file
if _config is not None:
    run(_config.attributes["connection"])
