"""sem registrations: a merged mosaic registered onto an SEM image

Revision ID: 0006
Revises: 0005
Create Date: 2026-12-06 13:50:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa

from alembic import op

revision: str = "0006"
down_revision: str | None = "0005"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "sem_registrations",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column("created_at", sa.DateTime(), nullable=False),
        sa.Column("merge_id", sa.Integer(), nullable=False),
        sa.Column("sem_id", sa.Integer(), nullable=False),
        # T_sem_mosaic: p' = scale R(rotation) p + offset, stage metres
        sa.Column("rotation_deg", sa.Float(), nullable=False),
        sa.Column("scale", sa.Float(), nullable=False),
        sa.Column("offset", sa.JSON(), nullable=False),
        sa.Column("affine", sa.JSON(), nullable=True),
        sa.Column("sigma", sa.JSON(), nullable=False),
        sa.Column("score", sa.Float(), nullable=False),
        sa.Column("rival", sa.Float(), nullable=False),
        sa.Column("overlap", sa.Float(), nullable=False),
        sa.Column("accepted", sa.Boolean(), nullable=False),
        sa.Column("reason", sa.String(length=500), nullable=True),
        sa.Column("weights", sa.JSON(), nullable=False),
        sa.Column("calibration_id", sa.Integer(), nullable=True),
        sa.Column("actor", sa.String(length=100), nullable=False),
    )
    op.create_index("ix_sem_registrations_merge_id", "sem_registrations", ["merge_id"])


def downgrade() -> None:
    op.drop_index("ix_sem_registrations_merge_id", table_name="sem_registrations")
    op.drop_table("sem_registrations")
