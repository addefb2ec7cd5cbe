"""``so-transients run CONFIG``: the site pipeline, the catalogue and the groups' losses in one
command, whose exit status says whether every group was made."""
from pathlib import Path

import pytest
import yaml
from astropy.table import Table

from so_transients import cli
from so_transients.site.pipeline import PAPER, read_config, write_site_config

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def config(module_tmp, two_flare_dataset):
    root = module_tmp("run")
    return write_site_config(two_flare_dataset.context.parent, path=root / "preprocess.yaml",
                             results=root / "preprocess", template=PAPER)


def test_a_good_run_exits_0_with_the_catalogue_in_time_order(config, capsys):
    assert cli.main(["run", str(config)]) == 0
    out = capsys.readouterr().out
    table = Table.read(Path(config).parent / "preprocess" / "detections.ecsv")
    assert len(table) >= 2 and f"{len(table)} detections written" in out
    assert list(table["t_peak"]) == sorted(table["t_peak"])
    assert "Detectors per group:" in out and "detectors used" in out


def test_a_misspelt_key_fails_the_run_and_names_the_key(config, tmp_path, capsys):
    cfg = read_config(config)                     # its paths resolved: written elsewhere
    for step in cfg["process_pipe"]:
        if step["name"] == "transient_find":
            step["calc"]["snr_treshold"] = 3.0
    bad = tmp_path / "bad.yaml"
    cfg["archive"]["index"] = str(tmp_path / "out" / "process_archive.sqlite")
    cfg["archive"]["policy"]["filename"] = str(tmp_path / "out" / "preprocess_archive.h5")
    bad.write_text(yaml.safe_dump(cfg, sort_keys=False))
    assert cli.main(["run", str(bad)]) == 1
    err = capsys.readouterr().err
    assert "FAILED" in err and "snr_treshold" in err and "did you mean snr_threshold" in err
    assert cli.main(["run", str(bad), "--partial"]) == 0

