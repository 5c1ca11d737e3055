"""sem calibrations: the SEM-to-stage maps measured, per instrument and field of view

Revision ID: 0004
Revises: 0003
Create Date: 2026-12-06 11:50:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa

from alembic import op

revision: str = "0004"
down_revision: str | None = "0003"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "sem_calibrations",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column("created_at", sa.DateTime(), nullable=False),
        sa.Column("instrument", sa.String(length=512), nullable=False),
        sa.Column("field", sa.Float(), nullable=False),
        sa.Column("pixels", sa.Integer(), nullable=False),
        sa.Column("scan_rotation", sa.Float(), nullable=False),
        sa.Column("matrix", sa.JSON(), nullable=False),
        sa.Column("offset", sa.JSON(), nullable=False),
        sa.Column("stage", sa.JSON(), nullable=False),
        sa.Column("residual_px", sa.Float(), nullable=False),
        sa.Column("sigma", sa.JSON(), nullable=False),
        sa.Column("moves", sa.JSON(), nullable=False),
        sa.Column("actor", sa.String(length=100), nullable=False),
    )
    op.create_index("ix_sem_calibrations_instrument", "sem_calibrations", ["instrument"])


def downgrade() -> None:
    op.drop_index("ix_sem_calibrations_instrument", table_name="sem_calibrations")
    op.drop_table("sem_calibrations")
