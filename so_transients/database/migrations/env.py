"""alembic's environment: the revisions run on the connection that
:func:`so_transients.database.schema.migrate` passes in ``config.attributes``, inside its
transaction (which holds the writers' lock)."""
from alembic import context

from so_transients.database.schema import METADATA

connection = context.config.attributes["connection"]
context.configure(connection=connection, target_metadata=METADATA,
                  render_as_batch=connection.dialect.name == "sqlite")
with context.begin_transaction():
    context.run_migrations()
