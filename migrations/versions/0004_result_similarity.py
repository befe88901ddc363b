"""keep the similarity D a job computed

Revision ID: 0004
Revises: 0003
Create Date: 2026-12-01

``results.similarity_npy``: the (n, n) similarity matrix D of a succeeded job as ``.npy``
bytes (``GET /v1/jobs/{id}/similarity``); null for results stored before.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0004"
down_revision: str | None = "0003"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("results") as batch:
        batch.add_column(sa.Column("similarity_npy", sa.LargeBinary(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("results") as batch:
        batch.drop_column("similarity_npy")
