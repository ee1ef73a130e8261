"""Vessel models shared by a deployment's nodes: the ``volume_models`` table.

A volume's model (``engine.model_key`` → the bytes of its ``<data_dir>/models`` file) kept in the job database, so
that an API replica and the workers of a scale-out deployment (no shared filesystem) read a volume once between
them (:mod:`service.storage.shared_models`). Empty until such a deployment keeps a model.

Revision ID: 0003
Revises: 0002
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    if sa.inspect(op.get_bind()).has_table("volume_models"):  # an unversioned database made with it (adopted at 0001)
        return
    op.create_table(
        "volume_models",
        sa.Column("model_key", sa.String(64), primary_key=True),
        sa.Column("size", sa.BigInteger, nullable=False),
        sa.Column("used_at", sa.Float, nullable=False),
        sa.Column("data", sa.LargeBinary, nullable=False),
    )


def downgrade() -> None:
    op.drop_table("volume_models")
