"""Evaluations store their frames: one row per frame of the ground truth with the frame's detections and its share
of every matching, which the frame listings and frame views read instead of the kept predictions whole.

Evaluations stored before have no rows; their frames are answered from the kept predictions, as before.

Revision ID: 0004
Revises: 0003
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None


def upgrade() -> None:
    if sa.inspect(op.get_bind()).has_table("evaluation_frames"):
        return  # already made: a database without versions whose tables were made from the code's
    op.create_table(
        "evaluation_frames",
        sa.Column("evaluation_id", sa.String(length=32), nullable=False),
        sa.Column("frame_index", sa.Integer(), nullable=False),
        sa.Column("frame_id", sa.Text(), nullable=False),
        sa.Column("detections", sa.LargeBinary(), nullable=False),
        sa.Column("events", sa.LargeBinary(), nullable=False),
        sa.ForeignKeyConstraint(["evaluation_id"], ["evaluations.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("evaluation_id", "frame_index"),
    )
    op.create_index("ix_evaluation_frames_id", "evaluation_frames", ["evaluation_id", "frame_id"], unique=False)


def downgrade() -> None:
    op.drop_index("ix_evaluation_frames_id", table_name="evaluation_frames")
    op.drop_table("evaluation_frames")
