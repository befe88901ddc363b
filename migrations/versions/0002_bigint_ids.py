"""64-bit ids on server databases

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-23

The API accepts ids up to 2**63 - 1. SQLite's INTEGER already holds them (and its columns
stay as they are); on PostgreSQL the id columns, the columns referring to ids, and the
id sequences become BIGINT.
"""

from collections.abc import Sequence

from alembic import op

revision: str = "0002"
down_revision: str | None = "0001"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

COLUMNS = {
    "collections": ["id"],
    "shapes": ["id", "collection_id"],
    "jobs": ["id", "collection_id", "model_shape_id"],
    "results": ["job_id"],
    "result_subjects": ["job_id", "shape_id", "parent_shape_id"],
    "idempotency_keys": ["id"],
}
SEQUENCES = ["collections_id_seq", "shapes_id_seq", "jobs_id_seq", "idempotency_keys_id_seq"]


def _retype(sql_type: str) -> None:
    if op.get_bind().dialect.name != "postgresql":
        return
    for table, columns in COLUMNS.items():
        for column in columns:
            op.execute(f"ALTER TABLE {table} ALTER COLUMN {column} TYPE {sql_type}")
    for sequence in SEQUENCES:
        op.execute(f"ALTER SEQUENCE IF EXISTS {sequence} AS {sql_type}")


def upgrade() -> None:
    _retype("BIGINT")


def downgrade() -> None:
    _retype("INTEGER")
