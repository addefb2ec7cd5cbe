"""The events database's migrations, run by alembic (:func:`so_transients.database.schema.migrate`).

``env.py`` runs them on the connection the package passes in; ``versions/`` holds one frozen
revision per structural change (``0001`` the tables as the first schema made them). A new
structural change is a new revision there, written with ``alembic revision`` against this
folder (``script_location``) or by hand; a column added to a declaration
(:data:`so_transients.events.schema.EVENTS`, the candidate schema, ...) needs none:
``so-transients db migrate`` adds declared columns after the revisions.
"""
