"""Alerts for followers: one machine-readable record per new or updated event (GCN unified
JSON core fields, optionally VOEvent 2.0 XML), validated against the JSON Schema kept here.

- ``alert.schema.json``: the record's JSON Schema (after nasa-gcn/gcn-schema's core blocks)
- :mod:`.records`: records built from an events table: initial, update, retraction
- :mod:`.tense`: current, test or injection, from what the dataset says it is
- :mod:`.voevent`: the same record as VOEvent 2.0 XML
- :mod:`.command`: ``so-transients alerts``
"""
