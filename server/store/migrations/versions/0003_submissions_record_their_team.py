"""A submission records the team it counted for when it was accepted (``submissions.team``), so that the board
keeps naming it after a member leaves the team.

The rows already there get the team the board named until now: their participant's team in the benchmark, if
they had joined it by the time the submission was accepted (no one could leave a team before this revision).
A phase's row is ``NAME`` or ``NAME~PHASE``; teams are the benchmark's (``NAME``).

Revision ID: 0003
Revises: 0002
"""

from __future__ import annotations

from datetime import datetime, timezone

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None

_submissions = sa.table(
    "submissions",
    sa.column("id", sa.String(32)),
    sa.column("benchmark", sa.String(64)),
    sa.column("participant", sa.String(64)),
    sa.column("created_at", sa.DateTime(timezone=True)),
    sa.column("team", sa.String(64)),
)
_members = sa.table(
    "team_members",
    sa.column("benchmark", sa.String(64)),
    sa.column("participant", sa.String(64)),
    sa.column("team", sa.String(64)),
    sa.column("joined_at", sa.DateTime(timezone=True)),
)


def _utc(value: datetime) -> datetime:
    return value.replace(tzinfo=timezone.utc) if value.tzinfo is None else value.astimezone(timezone.utc)


def upgrade() -> None:
    conn = op.get_bind()
    # a database whose tables were made by a later release's code and whose version was then taken away (as the
    # tests imitate an unversioned release) has the column: the base revision made no table it had
    if "team" not in {c["name"] for c in sa.inspect(conn).get_columns("submissions")}:
        op.add_column("submissions", sa.Column("team", sa.String(64), nullable=True))
    joined = {
        (r.benchmark, r.participant): (r.team, _utc(r.joined_at))
        for r in conn.execute(
            sa.select(_members.c.benchmark, _members.c.participant, _members.c.team, _members.c.joined_at)
        )
    }
    if not joined:
        return
    c = _submissions.c
    rows = conn.execute(sa.select(c.id, c.benchmark, c.participant, c.created_at).where(c.team.is_(None))).all()
    for row in rows:
        team = joined.get((row.benchmark.split("~", 1)[0], row.participant))
        if team is not None and team[1] <= _utc(row.created_at):
            conn.execute(sa.update(_submissions).where(_submissions.c.id == row.id).values(team=team[0]))


def downgrade() -> None:
    with op.batch_alter_table("submissions") as batch:
        batch.drop_column("team")
