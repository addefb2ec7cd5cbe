"""The distributed path, as a cluster runs it: sotodlib's site pipeline and ``so-transients
events`` under ``mpiexec -n 2`` (rank 0 dispatching groups to the other rank through
sotodlib's ``get_exec_env``) give exactly what the serial runs give. The campaign's MPI test
is in tests/campaign/test_campaign.py."""
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from astropy.table import Table

from so_transients.site.pipeline import PAPER, failed_groups, run_site_pipeline, write_site_config
from so_transients.site.results import archive_table

pytestmark = [pytest.mark.slow, pytest.mark.skipif(
    not shutil.which("mpiexec", path=str(Path(sys.executable).parent)),
    reason="needs mpiexec beside the interpreter (pip install '.[test]' brings mpich)")]

MPIEXEC = shutil.which("mpiexec", path=str(Path(sys.executable).parent))
ENV = dict(os.environ, OMP_NUM_THREADS="1", OMP_WAIT_POLICY="passive")


def mpi(*args, cwd):
    run = subprocess.run([MPIEXEC, "-n", "2", sys.executable, *args], env=ENV, cwd=cwd,
                         capture_output=True, text=True, timeout=1200)
    assert run.returncode == 0, run.stderr[-3000:]
    return run


def same(a: Table, b: Table):
    """Equal tables (rows in the same order of obs, group and candidate)."""
    keys = [k for k in ("obs_id", "bandpass", "cand_id", "event_id", "t") if k in a.colnames]
    a, b = a.copy(), b.copy()
    if keys:
        a.sort(keys)
        b.sort(keys)
    assert a.pformat(max_lines=-1, max_width=-1) == b.pformat(max_lines=-1, max_width=-1)


@pytest.fixture(scope="module")
def serial_and_mpi(module_tmp, noisy_dataset):
    """The shipped site config on five minutes of one wafer in two bands (two groups),
    once serially and once under mpiexec -n 2."""
    root = module_tmp("mpi")
    configs = {}
    for name in ("serial", "mpi"):
        configs[name] = write_site_config(noisy_dataset.context.parent,
                                          path=root / f"{name}.yaml", results=root / name,
                                          template=PAPER)
    run_site_pipeline(configs["serial"])
    mpi("-m", "sotodlib.site_pipeline.preprocess_tod", str(configs["mpi"]), "--nproc", "2",
        cwd=root)
    return root, configs


def test_the_site_pipeline_under_mpi_gives_the_serial_archive(serial_and_mpi):
    _, configs = serial_and_mpi
    assert failed_groups(configs["mpi"]) == "" and failed_groups(configs["serial"]) == ""
    serial = archive_table(configs["serial"], detected_only=False)
    assert len(serial) > 0
    same(archive_table(configs["mpi"], detected_only=False), serial)


def test_events_under_mpi_give_the_serial_events(serial_and_mpi):
    root, configs = serial_and_mpi
    outs = {name: root / f"events_{name}" for name in configs}
    subprocess.run([sys.executable, "-m", "so_transients.cli", "events", str(configs["serial"]),
                    "-o", str(outs["serial"]), "--nproc", "2", "-q"], env=ENV, check=True,
                   capture_output=True)
    mpi("-m", "so_transients.cli", "events", str(configs["serial"]), "-o", str(outs["mpi"]),
        "--nproc", "2", "-q", cwd=root)
    tables = sorted(p.name for p in outs["serial"].glob("*.ecsv"))
    assert tables
    assert tables == sorted(p.name for p in outs["mpi"].glob("*.ecsv"))
    for name in tables:
        same(Table.read(outs["mpi"] / name), Table.read(outs["serial"] / name))
    assert len(Table.read(outs["serial"] / "events.ecsv")) > 0
