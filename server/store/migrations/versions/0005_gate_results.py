"""A gate may have an evaluation made without keeping it (a read-only token's gate): its result is a row of
``gate_results``, read once by its owner or deleted a few minutes after it was made, never an evaluation.

Revision ID: 0005
Revises: 0004
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects.postgresql import JSONB

revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None


def upgrade() -> None:
    if sa.inspect(op.get_bind()).has_table("gate_results"):
        return  # already made: a database without versions whose tables were made from the code's
    op.create_table(
        "gate_results",
        sa.Column("id", sa.String(length=32), nullable=False),
        sa.Column("owner", sa.String(length=64), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("document", sa.JSON().with_variant(JSONB(), "postgresql"), nullable=False),
        sa.PrimaryKeyConstraint("id"),
    )
    op.create_index("ix_gate_results_created", "gate_results", ["created_at"], unique=False)


def downgrade() -> None:
    op.drop_index("ix_gate_results_created", table_name="gate_results")
    op.drop_table("gate_results")
