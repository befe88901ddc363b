"""a running job's overall share done

Revision ID: 0005
Revises: 0004
Create Date: 2026-12-01

``jobs.progress_fraction``: the worker's estimate of the share of the whole job done (0-1,
never going back; :class:`service.progress.FractionTracker`), written with its progress;
null for jobs that ran before, and while no stage is known.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0005"
down_revision: str | None = "0004"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("jobs") as batch:
        batch.add_column(sa.Column("progress_fraction", sa.Float(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("jobs") as batch:
        batch.drop_column("progress_fraction")
