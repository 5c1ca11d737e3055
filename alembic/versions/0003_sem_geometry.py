"""sem geometry: an SEM image's full pixel-to-stage map, and where its SEM stage stood

Revision ID: 0003
Revises: 0002
Create Date: 2026-12-06 11:30:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa

from alembic import op

revision: str = "0003"
down_revision: str | None = "0002"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("sem_images") as batch:
        # the 2 x 2 pixel-to-stage map; null: diag(pixel_x, pixel_y), as images were placed
        batch.add_column(sa.Column("matrix", sa.JSON(), nullable=True))
        batch.add_column(sa.Column("rotation", sa.Float(), nullable=False, server_default="0"))
        batch.add_column(sa.Column("sem_stage", sa.JSON(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("sem_images") as batch:
        batch.drop_column("sem_stage")
        batch.drop_column("rotation")
        batch.drop_column("matrix")
