"""``so-transients run`` with a known-source file that cannot be used: every group stops when
sotodlib builds its pipeline, before its data are read, and the run exits non-zero naming the
file, the key and the step."""
import time

import pytest

from so_transients import cli
from so_transients.site.pipeline import write_site_config

pytestmark = pytest.mark.slow


def test_an_empty_known_source_file_fails_the_run_naming_it(two_flare_dataset, tmp_path,
                                                            capsys):
    empty = tmp_path / "known_sources.ecsv"
    empty.write_text("")
    config = write_site_config(two_flare_dataset.context.parent, path=tmp_path / "pp.yaml",
                               results=tmp_path / "preprocess",
                               overrides={"transient_cuts": {"calc": {"known_sources":
                                                                      str(empty)}}})
    t0 = time.monotonic()
    code = cli.main(["run", str(config)])
    elapsed = time.monotonic() - t0
    err = capsys.readouterr().err
    assert code != 0
    assert f"transient_cuts: known_sources: {empty}: the file is empty (0 bytes)" in err
    assert "ECSV header line" not in err
    assert elapsed < 60, f"the run took {elapsed:.0f} s to fail"
