"""Version 3: events.cat_source_id as text, '' for none (was an integer, -1): socat's ids are
UUIDs since socat 0.1 (on SQLite, alembic's batch mode copies the table).

Revision ID: 0003
Revises: 0002
Create Date: 2026-12-06
"""
import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None

COMMENT = ("its id there (socat source_id, or sso_id of a solar-system object: a UUID in socat "
           "0.1, an integer in 0.0.2 or a file), '' if none")


def upgrade():
    conn = op.get_bind()
    if conn.dialect.name == "postgresql":
        op.alter_column("events", "cat_source_id", type_=sa.Text(),
                        postgresql_using="CASE WHEN cat_source_id = -1 THEN '' "
                                         "ELSE cat_source_id::text END",
                        comment=COMMENT)
    else:
        with op.batch_alter_table("events") as batch:
            batch.alter_column("cat_source_id", type_=sa.Text())
        op.execute("UPDATE events SET cat_source_id = '' "
                   "WHERE CAST(cat_source_id AS TEXT) = '-1'")
