"""Version 4: alembic records the schema's revision (``alembic_version``); the table the
package's own migration runner kept, ``schema_version``, is dropped.

Revision ID: 0004
Revises: 0003
Create Date: 2026-12-06
"""
import sqlalchemy as sa
from alembic import op

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None


def upgrade():
    if sa.inspect(op.get_bind()).has_table("schema_version"):
        op.drop_table("schema_version")
