"""The command line's user options: listings, the two site configs and their overrides."""
import logging

import pytest
import yaml

from so_transients import cli
from so_transients.sim.config import load_config
from so_transients.sim.focal_plane import lat_layout


@pytest.fixture(autouse=True)
def sotodlib_logger_restored():
    """cli.main stops sotodlib's logger propagating: undo it for the tests that follow."""
    yield
    logging.getLogger("sotodlib").propagate = True


@pytest.fixture
def dataset(tmp_path):
    """A folder that passes for a dataset (site-config reads nothing but its context.yaml's
    path)."""
    (tmp_path / "context.yaml").write_text("imports: [so_transients]\n")
    return tmp_path


def steps(path):
    return {s["name"]: s for s in yaml.safe_load(path.read_text())["process_pipe"]}


def test_simulate_list_prints_every_tube_with_its_wafers_and_bands(capsys):
    assert cli.main(["simulate", "--list"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 1 + len(lat_layout())
    c1 = next(line.split() for line in out if line.startswith("c1"))
    assert c1 == ["c1", "LAT_UHF", "w00", "w01", "w02", "f220", "f280"]


def test_simulate_options_update_sections_key_by_key():
    cfg = load_config(None, {"observation": {"duration": 120.0, "start": None},
                             "instrument": {"tubes": ["c1"], "wafers": ["w01"],
                                            "bands": None}})
    default = load_config(None)
    assert cfg.observation.duration == 120.0
    assert cfg.observation.start == default.observation.start
    assert cfg.instrument.tubes == ["c1"] and cfg.instrument.wafers == ["w01"]
    assert cfg.instrument.bands is None


def test_site_config_writes_the_production_search_by_default(dataset):
    assert cli.main(["site-config", str(dataset)]) == 0
    pipe = steps(dataset / "preprocess.yaml")
    assert pipe["transient_find"]["calc"]["mode"] == "coherent"
    assert pipe["transient_significance"]["calc"]["max_far"] == 0.005
    assert {"transient_fourier_filter", "transient_glitches", "noise",
            "transient_pca_filter"} <= set(pipe)


def test_site_config_paper_mode_and_overrides(dataset, tmp_path):
    known = tmp_path / "known.csv"
    known.write_text("ra,dec\n10.0,-30.0\n")
    assert cli.main(["site-config", str(dataset), "--mode", "paper", "--known-sources",
                     str(known), "-o", str(tmp_path / "paper.yaml")]) == 0
    pipe = steps(tmp_path / "paper.yaml")
    assert pipe["transient_find"]["calc"]["mode"] == "paper"
    assert "transient_significance" not in pipe
    assert pipe["transient_cuts"]["calc"]["known_sources"] == str(known.resolve())
    assert cli.main(["site-config", str(dataset), "--max-far", "0.02"]) == 0
    assert steps(dataset / "preprocess.yaml")["transient_significance"]["calc"]["max_far"] \
        == 0.02


def test_paper_mode_gets_its_own_config_and_archive(dataset):
    assert cli.main(["site-config", str(dataset)]) == 0
    assert cli.main(["site-config", str(dataset), "--mode", "paper"]) == 0
    production = yaml.safe_load((dataset / "preprocess.yaml").read_text())
    paper = yaml.safe_load((dataset / "preprocess_paper.yaml").read_text())
    assert paper["archive"]["index"] == "preprocess_paper/process_archive.sqlite"
    assert production["archive"]["index"] == "preprocess/process_archive.sqlite"


@pytest.mark.parametrize("max_far", ["0", "-1"])
def test_a_max_far_that_is_not_positive_is_refused_at_once(dataset, capsys, max_far):
    assert cli.main(["site-config", str(dataset), "--max-far", max_far]) == 2
    assert "max_far must be positive" in capsys.readouterr().err
    assert not (dataset / "preprocess.yaml").exists()


def test_a_known_source_list_is_read_when_the_config_is_written(dataset, tmp_path, capsys,
                                                                caplog):
    empty = tmp_path / "empty.csv"
    empty.write_text("")
    assert cli.main(["site-config", str(dataset), "--known-sources", str(empty)]) == 2
    assert "--known-sources" in capsys.readouterr().err
    header = tmp_path / "header.csv"
    header.write_text("ra,dec\n")
    with caplog.at_level("WARNING"):
        assert cli.main(["site-config", str(dataset), "--known-sources", str(header)]) == 0
    assert "lists no source" in caplog.text


def test_max_far_in_paper_mode_is_refused(dataset, capsys):
    assert cli.main(["site-config", str(dataset), "--mode", "paper", "--max-far", "0.01"]) == 2
    assert "--max-far" in capsys.readouterr().err


def test_study_commands_sit_apart_from_the_user_commands(capsys):
    with pytest.raises(SystemExit):
        cli.main(["campaign", "x.yaml"])
    with pytest.raises(SystemExit) as done:
        cli.main(["study", "--help"])
    assert done.value.code == 0
    out = capsys.readouterr().out
    assert "campaign" in out and "events-check" in out and "combine" in out


def test_simulate_start_names_the_observation(tmp_path):
    """``--start`` (ISO UTC or ctime) sets the first observation's start and so its obs_id: a
    second simulated dataset does not reuse the first one's."""
    from astropy.time import Time

    from so_transients.sim.dataset import obs_id_for

    args = ["simulate", "--duration", "10", "--tubes", "i1", "--wafers", "w16", "--bands",
            "f090", "-q"]
    assert cli.main([*args, "-o", str(tmp_path / "a"), "--start", "2024-03-01T00:00:00"]) == 0
    assert cli.main([*args, "-o", str(tmp_path / "b"), "--start", "1709251200"]) == 0
    start = Time("2024-03-01T00:00:00", scale="utc").unix
    assert start == 1709251200
    expected = obs_id_for(start, "i1")
    for name in ("a", "b"):
        assert [p.name for p in (tmp_path / name / "tod").iterdir()] == [expected]
    assert expected != obs_id_for(load_config(None).observation.start, "i1")


def test_help_does_not_import_the_pipeline_and_steps_register_when_it_is(tmp_path):
    """``so-transients --help`` (and ``import so_transients``) leave sotodlib's preprocess
    module unimported; importing it afterwards registers every step, as does importing
    sotodlib's preprocess first."""
    import ast
    import subprocess
    import sys

    help_only = ("import sys\nfrom so_transients import cli\n"
                 "try:\n    cli.main(['--help'])\nexcept SystemExit:\n    pass\n"
                 "print('IMPORTED', 'sotodlib.preprocess' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", help_only], capture_output=True, text=True,
                         check=True).stdout
    assert "IMPORTED False" in out
    steps = ("from sotodlib.preprocess import Pipeline\n"
             "print('STEPS', sorted(k for k in Pipeline.PIPELINE if k.startswith('transient_')))\n")
    for first in ("import so_transients\n", "import sotodlib.preprocess, so_transients\n"):
        out = subprocess.run([sys.executable, "-c", first + steps], capture_output=True,
                             text=True, check=True).stdout
        registered = ast.literal_eval(out.split("STEPS", 1)[1].strip())
        assert {"transient_filter", "transient_find", "transient_fit", "transient_jumps",
                "transient_pca_filter"} <= set(registered), first


@pytest.mark.parametrize("module, extra, argv", [
    ("sqlalchemy", "db", ["db", "query"]), ("jsonschema", "alerts", ["alerts", ".", "-o", "x"])])
def test_a_command_whose_extra_is_missing_names_it(module, extra, argv):
    """The database and the alerts are optional extras: without them the command says
    which to install (exit 2), in a process where the module cannot be imported."""
    import subprocess
    import sys

    code = (f"import sys; sys.modules[{module!r}] = None\n"
            f"from so_transients import cli; sys.exit(cli.main({argv!r}))")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert run.returncode == 2, run.stderr[-2000:]
    assert f"pip install 'so_transients[{extra}]'" in run.stderr
