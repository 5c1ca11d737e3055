"""rescans: a run's re-scan policy and record, each patch's quality and tries

Revision ID: 0002
Revises: 0001
Create Date: 2026-12-02 08:45:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa

from alembic import op

revision: str = "0002"
down_revision: str | None = "0001"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("runs") as batch:
        batch.add_column(
            sa.Column("rescan_enabled", sa.Boolean(), nullable=False, server_default=sa.true())
        )
        batch.add_column(
            sa.Column("rescan_max_tries", sa.Integer(), nullable=False, server_default="2")
        )
        batch.add_column(sa.Column("rescans", sa.JSON(), nullable=False, server_default="[]"))
    with op.batch_alter_table("patches") as batch:
        batch.add_column(sa.Column("quality", sa.String(length=16), nullable=True))
        batch.add_column(sa.Column("quality_reason", sa.String(length=500), nullable=True))
        batch.add_column(sa.Column("tries", sa.Integer(), nullable=False, server_default="0"))


def downgrade() -> None:
    with op.batch_alter_table("patches") as batch:
        batch.drop_column("tries")
        batch.drop_column("quality_reason")
        batch.drop_column("quality")
    with op.batch_alter_table("runs") as batch:
        batch.drop_column("rescans")
        batch.drop_column("rescan_max_tries")
        batch.drop_column("rescan_enabled")
