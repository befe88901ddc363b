"""a grouping job has no model shape

Revision ID: 0006
Revises: 0005
Create Date: 2026-12-01

``jobs.model_shape_id`` becomes nullable: a grouping job (issue 11) groups a collection's
shapes and has no model, so it stores NULL instead of recording the collection's first shape.
Grouping jobs stored before keep the shape they recorded. Downgrading gives a job without a
model that shape again (the smallest shape id of its collection, else the first of its
shapes), so the column can be NOT NULL once more.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0006"
down_revision: str | None = "0005"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def _id_type() -> sa.types.TypeEngine:
    # 0002: BIGINT on PostgreSQL, SQLite's INTEGER elsewhere
    return sa.BigInteger() if op.get_bind().dialect.name == "postgresql" else sa.Integer()


def upgrade() -> None:
    with op.batch_alter_table("jobs") as batch:
        batch.alter_column("model_shape_id", existing_type=_id_type(), nullable=True)


def downgrade() -> None:
    jobs = sa.table(
        "jobs",
        sa.column("id", sa.Integer()),
        sa.column("collection_id", sa.Integer()),
        sa.column("model_shape_id", sa.Integer()),
        sa.column("shape_ids", sa.JSON()),
    )
    shapes = sa.table("shapes", sa.column("id", sa.Integer()),
                      sa.column("collection_id", sa.Integer()))
    bind = op.get_bind()
    orphans = bind.execute(
        sa.select(jobs.c.id, jobs.c.collection_id, jobs.c.shape_ids)
        .where(jobs.c.model_shape_id.is_(None))
    ).all()
    for job_id, collection_id, shape_ids in orphans:
        first = bind.scalar(
            sa.select(sa.func.min(shapes.c.id)).where(shapes.c.collection_id == collection_id)
        )
        if first is None:  # the collection's shapes are gone: the job's first one
            first = min(shape_ids) if shape_ids else 0
        bind.execute(sa.update(jobs).where(jobs.c.id == job_id).values(model_shape_id=first))
    with op.batch_alter_table("jobs") as batch:
        batch.alter_column("model_shape_id", existing_type=_id_type(), nullable=False)
