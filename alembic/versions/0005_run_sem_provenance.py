"""run sem provenance: the SEM image a run was drawn on and the calibration that placed it

Revision ID: 0005
Revises: 0004
Create Date: 2026-12-06 12:40:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa

from alembic import op

revision: str = "0005"
down_revision: str | None = "0004"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("sem_images") as batch:
        # the SEM-to-stage calibration an acquired frame was placed through; null: none
        batch.add_column(sa.Column("calibration_id", sa.Integer(), nullable=True))
    with op.batch_alter_table("runs") as batch:
        # the SEM image the ROI was drawn on, and the calibration that placed that image
        batch.add_column(sa.Column("sem_id", sa.Integer(), nullable=True))
        batch.add_column(sa.Column("sem_calibration_id", sa.Integer(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("runs") as batch:
        batch.drop_column("sem_calibration_id")
        batch.drop_column("sem_id")
    with op.batch_alter_table("sem_images") as batch:
        batch.drop_column("calibration_id")
