"""job outcome, retry time and callbacks

Revision ID: 0003
Revises: 0002
Create Date: 2026-12-01

``jobs`` gains ``outcome`` (how it ended: succeeded, failed, cancelled while queued, aborted
while running), ``next_attempt_at`` (when a job queued for a retry may be claimed) and
``callback_url``; ``callback_deliveries`` and ``callback_attempts`` hold the pending
callbacks and every try at delivering them. Jobs that ended before this revision get their
outcome from their status; a cancelled one that had started counts as aborted.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0003"
down_revision: str | None = "0002"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

Id = sa.BigInteger().with_variant(sa.Integer(), "sqlite")


def upgrade() -> None:
    with op.batch_alter_table("jobs", schema=None) as batch_op:
        batch_op.add_column(sa.Column("outcome", sa.String(length=20), nullable=True))
        batch_op.add_column(sa.Column("next_attempt_at", sa.DateTime(), nullable=True))
        batch_op.add_column(sa.Column("callback_url", sa.Text(), nullable=True))
    op.execute(
        "UPDATE jobs SET outcome = CASE "
        "WHEN status = 'succeeded' THEN 'succeeded' "
        "WHEN status = 'failed' THEN 'failed' "
        "WHEN status = 'cancelled' AND started_at IS NULL THEN 'cancelled' "
        "WHEN status = 'cancelled' THEN 'aborted' END "
        "WHERE status IN ('succeeded', 'failed', 'cancelled')"
    )
    op.create_table(
        "callback_deliveries",
        sa.Column("job_id", Id, nullable=False),
        sa.Column("url", sa.Text(), nullable=False),
        sa.Column("body", sa.Text(), nullable=False),
        sa.Column("state", sa.String(length=20), nullable=False),
        sa.Column("attempts", sa.Integer(), nullable=False),
        sa.Column("max_attempts", sa.Integer(), nullable=False),
        sa.Column("next_attempt_at", sa.DateTime(), nullable=False),
        sa.Column("lease_owner", sa.String(length=200), nullable=True),
        sa.Column("lease_expires_at", sa.DateTime(), nullable=True),
        sa.Column("created_at", sa.DateTime(), nullable=False),
        sa.Column("finished_at", sa.DateTime(), nullable=True),
        sa.ForeignKeyConstraint(["job_id"], ["jobs.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("job_id"),
    )
    with op.batch_alter_table("callback_deliveries", schema=None) as batch_op:
        batch_op.create_index(
            "ix_callback_deliveries_state_next", ["state", "next_attempt_at"], unique=False
        )
    op.create_table(
        "callback_attempts",
        sa.Column("id", Id, nullable=False),
        sa.Column("job_id", Id, nullable=False),
        sa.Column("attempt", sa.Integer(), nullable=False),
        sa.Column("started_at", sa.DateTime(), nullable=False),
        sa.Column("duration_ms", sa.Integer(), nullable=False),
        sa.Column("status_code", sa.Integer(), nullable=True),
        sa.Column("error", sa.Text(), nullable=True),
        sa.ForeignKeyConstraint(
            ["job_id"], ["callback_deliveries.job_id"], ondelete="CASCADE"
        ),
        sa.PrimaryKeyConstraint("id"),
        sqlite_autoincrement=True,
    )
    with op.batch_alter_table("callback_attempts", schema=None) as batch_op:
        batch_op.create_index(
            "ix_callback_attempts_job_id", ["job_id", "attempt"], unique=False
        )


def downgrade() -> None:
    with op.batch_alter_table("callback_attempts", schema=None) as batch_op:
        batch_op.drop_index("ix_callback_attempts_job_id")
    op.drop_table("callback_attempts")
    with op.batch_alter_table("callback_deliveries", schema=None) as batch_op:
        batch_op.drop_index("ix_callback_deliveries_state_next")
    op.drop_table("callback_deliveries")
    with op.batch_alter_table("jobs", schema=None) as batch_op:
        batch_op.drop_column("callback_url")
        batch_op.drop_column("next_attempt_at")
        batch_op.drop_column("outcome")
