"""One night of a two-night ObsDb: `run`, `catalog` and `events` take sotodlib's own
selection options (--query, --obs-id, --min-ctime, --max-ctime); the site pipeline makes the
selected observations only, and "missing" means missing among them."""
import pytest
from astropy.table import Table

from so_transients import cli
from so_transients.site.pipeline import PAPER, write_site_config
from tests.conftest import run_sim

pytestmark = pytest.mark.slow

START, DAY = 1_700_000_000.0, 86400.0


@pytest.fixture(scope="module")
def two_nights(module_tmp):
    root = module_tmp("two_nights")
    sim = run_sim(root / "data", seed=7, observation={"start": START, "duration": 200.0,
                                                      "n_obs": 2, "gap": DAY},
                  instrument={"bands": ["f090"]}, cmb={"enabled": False},
                  flares={"n": 1, "s_peak_mjy": 3000.0, "t_rise": 10.0})
    config = write_site_config(sim.context.parent, path=root / "pp.yaml",
                               results=root / "preprocess", template=PAPER)
    return sim, config


def test_the_second_night_alone(two_nights, capsys):
    sim, config = two_nights
    first, second = sorted(sim.obs_ids)
    night = ["--min-ctime", str(START + DAY / 2)]
    assert cli.main(["run", str(config), *night]) == 0
    out = capsys.readouterr().out
    assert "groups expected 1, in the archive 1, failed 0" in out
    table = Table.read(config.parent / "preprocess" / "detections.ecsv")
    assert set(table["obs_id"]) <= {second}
    # the whole ObsDb: the first night was never made, and is named as missing
    assert cli.main(["catalog", str(config), "-o", str(config.parent / "all.ecsv")]) == 1
    assert f"FAILED {first} w16/f090: missing" in capsys.readouterr().err
    assert cli.main(["catalog", str(config), "-o", str(config.parent / "one.ecsv"),
                     "--obs-id", second]) == 0
    assert cli.main(["events", str(config), "-o", str(config.parent / "events"), "-q",
                     *night]) == 0
    assert cli.main(["events", str(config), "-o", str(config.parent / "events_all"),
                     "-q"]) == 1


def test_a_missing_file_fails_only_its_group(two_nights, tmp_path, capsys):
    """The first night's only TOD file gone (it holds the ObsDb's first detector): `run`
    still makes the second night, and exits 1 naming the first's group and file."""
    sim, _ = two_nights
    first, second = sorted(sim.obs_ids)
    config = write_site_config(sim.context.parent, path=tmp_path / "pp.yaml",
                               results=tmp_path / "preprocess", template=PAPER)
    tod = next((sim.context.parent / "tod" / first).glob("*.h5"))
    tod.rename(tmp_path / tod.name)
    try:
        assert cli.main(["run", str(config)]) == 1
    finally:
        (tmp_path / tod.name).rename(tod)
    err = capsys.readouterr().err
    assert f"FAILED {first} w16/f090" in err and f"FAILED {second}" not in err
    table = Table.read(tmp_path / "preprocess" / "detections.ecsv")
    assert set(table["obs_id"]) <= {second}
