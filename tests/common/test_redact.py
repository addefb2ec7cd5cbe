"""Credentials never leave the process."""
import pytest

from so_transients.common.redact import redacted
from so_transients.sources.catalog import read_catalogue


@pytest.mark.parametrize("url, shown", [
    ("postgresql://user:s3cret@db.example:5432/socat", "postgresql://user:***@db.example:5432/socat"),
    ("postgresql+psycopg://u:p%40ss@h/db", "postgresql+psycopg://u:***@h/db"),
    ("postgresql://user@host/db", "postgresql://user@host/db"),
    ("socat:///data/socat.db", "socat:///data/socat.db"),
    ("known_sources.ecsv", "known_sources.ecsv"),
])
def test_a_urls_password_is_hidden(url, shown):
    assert redacted(url) == shown


def test_a_catalogue_that_cannot_be_read_is_named_without_its_password():
    with pytest.raises(Exception) as err:
        read_catalogue("postgresql://user:s3cret@127.0.0.1:1/socat")   # nothing listens
    assert "s3cret" not in str(err.value)
