"""``make demo``'s promise, as the README states it: 12 detections of its 6 flares, none
that matches no flare, and the 6 events they make."""
import re

import pytest

from so_transients import cli

pytestmark = pytest.mark.slow    # simulates the demo's 10 minutes and runs the site pipeline


def test_the_demo_reports_what_the_readme_promises(tmp_path, capsys):
    assert cli.main(["demo", "--out", str(tmp_path / "demo"), "--nproc", "2", "-q"]) == 0
    out = capsys.readouterr().out
    assert "12 detections, 0 not matching any injected flare." in out
    assert re.search(r"^6 event\(s\) from 12 detection\(s\)", out, re.M), out[-2000:]
    readme = (cli.DEMO_CONFIG.parents[2] / "README.md").read_text()
    assert "`12 detections, 0 not matching any injected flare.`" in readme
    assert "the 6 events of its 6 flares" in readme
