"""``so-transients run CONFIG``: the site pipeline, the catalogue and the groups' losses in one
command, whose exit status says whether every group was made."""
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
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


def test_a_misspelt_key_is_refused_before_anything_runs(config, tmp_path, capsys):
    cfg = read_config(config)                     # its paths resolved: written elsewhere
    for step in cfg["process_pipe"]:
        if step["name"] == "transient_find":
            step["calc"]["snr_treshold"] = 3.0
    bad = tmp_path / "bad.yaml"
    cfg["archive"]["index"] = str(tmp_path / "out" / "process_archive.sqlite")
    cfg["archive"]["policy"]["filename"] = str(tmp_path / "out" / "preprocess_archive.h5")
    bad.write_text(yaml.safe_dump(cfg, sort_keys=False))
    assert cli.main(["run", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "snr_treshold" in err and "did you mean snr_threshold" in err
    assert not (tmp_path / "out").exists()
    # pointed at the archive the good run made, the same config is refused as well: the
    # site pipeline would skip every group and never build it
    cfg["archive"] = read_config(config)["archive"]
    bad.write_text(yaml.safe_dump(cfg, sort_keys=False))
    assert cli.main(["run", str(bad)]) == 2
    assert "snr_treshold" in capsys.readouterr().err


def test_results_never_outlive_the_config_that_made_them(config, capsys):
    """Edit a step's key and rerun: the archive's groups were made with other steps, so the
    run is refused, naming them; --overwrite makes them again with the new steps."""
    test_a_good_run_exits_0_with_the_catalogue_in_time_order(config, capsys)  # the archive
    assert cli.main(["run", str(config)]) == 0             # the same steps: kept as they are
    edited = Path(config).with_name("edited.yaml")
    cfg = yaml.safe_load(Path(config).read_text())         # relative paths: the same archive
    for step in cfg["process_pipe"]:
        if step["name"] == "transient_fit":
            step["calc"]["min_snr"] = 30.0
    edited.write_text(yaml.safe_dump(cfg, sort_keys=False))
    capsys.readouterr()
    assert cli.main(["run", str(edited)]) == 2
    err = capsys.readouterr().err
    assert "made with other steps" in err and "w16/f090" in err and "--overwrite" in err
    assert cli.main(["run", str(edited), "--overwrite"]) == 0
    table = Table.read(Path(config).parent / "preprocess" / "detections.ecsv")
    assert len(table) and min(table["snr_fit"]) >= 30.0
    assert cli.main(["run", str(edited)]) == 0             # now its own
    assert cli.main(["run", str(config)]) == 2             # and no longer the first's
    assert cli.main(["run", str(config), "--overwrite"]) == 0


def test_a_known_source_list_without_sources_is_named_by_run(config, tmp_path, capsys, caplog):
    """A header-only known-source list: ``run`` says, before anything runs, that nothing will
    be masked (here it is then refused: the archive holds groups made with other steps)."""
    test_a_good_run_exits_0_with_the_catalogue_in_time_order(config, capsys)  # the archive
    header = tmp_path / "known.csv"
    header.write_text("ra,dec\n")
    cfg = read_config(config)
    for step in cfg["process_pipe"]:
        if step["name"] == "transient_cuts":
            step.setdefault("calc", {})["known_sources"] = str(header)
    edited = tmp_path / "known.yaml"
    edited.write_text(yaml.safe_dump(cfg, sort_keys=False))
    with caplog.at_level("WARNING"):
        assert cli.main(["run", str(edited)]) == 2
    assert f"{header}" in caplog.text and "lists no source" in caplog.text


def processes_running(text):
    """PIDs of the processes whose command line contains ``text``."""
    out = []
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            if text in cmdline.read_bytes().replace(b"\0", b" ").decode(errors="replace"):
                out.append(int(cmdline.parent.name))
        except OSError:
            pass
    return out


def test_a_stopped_run_stops_its_workers_and_the_next_run_continues(config, two_flare_dataset,
                                                                    tmp_path, capsys):
    """SIGTERM to `run` while the site pipeline works: it stops the pipeline and its
    workers (nothing left running, still writing), exits 143, and a rerun right after makes
    the same detections as an uninterrupted run."""
    # the uninterrupted run: the archive as this config makes it (remade if another
    # test's steps made it, which `run` refuses with 2)
    if cli.main(["run", str(config)]) != 0:
        assert cli.main(["run", str(config), "--overwrite"]) == 0
    reference = Table.read(Path(config).parent / "preprocess" / "detections.ecsv")
    stopped = write_site_config(two_flare_dataset.context.parent, path=tmp_path / "pp.yaml",
                                results=tmp_path / "preprocess", template=PAPER)
    proc = subprocess.Popen([sys.executable, "-m", "so_transients.cli", "run", str(stopped),
                             "--nproc", "2"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    t0 = time.monotonic()
    while not processes_running(f"so_transients.site.run {stopped}"):
        if proc.poll() is not None or time.monotonic() - t0 > 120:
            proc.terminate()          # it stops its pipeline; its output can be read once it ends
            pytest.fail(f"the site pipeline never started: {proc.communicate()}")
        time.sleep(0.2)
    time.sleep(5.0)                                       # the pool's workers are at work
    assert proc.poll() is None, "the run ended before it could be stopped"
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(60) == 143
    time.sleep(1.0)
    assert processes_running(str(stopped)) == []
    assert cli.main(["run", str(stopped)]) == 0
    again = Table.read(tmp_path / "preprocess" / "detections.ecsv")
    assert len(again) == len(reference)
    for name in ("t_peak", "flux", "snr_fit", "ra_deg", "dec_deg"):
        assert np.allclose(again[name], reference[name], rtol=1e-6), name
