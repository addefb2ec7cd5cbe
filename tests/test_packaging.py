"""The wheel carries what its commands read: a non-editable install, away from the checkout,
finds the shipped configs (the demo's simulation, the site and events configs), the vetting
pages' templates and the database's migrations in the package."""
import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

CHECK = """
import sys
from pathlib import Path
import so_transients
from so_transients import cli
from so_transients.site.pipeline import PAPER, PRODUCTION
installed = Path(so_transients.__file__).parent
assert installed.is_relative_to(Path(sys.argv[1])), installed
from so_transients.report.pages import ASSETS, TEMPLATES
templates = [TEMPLATES / name for name in ("index.html.j2", "event.html.j2", *ASSETS)]
for path in (cli.DEMO_CONFIG, PRODUCTION, PAPER, *templates):
    assert path.is_file() and path.is_relative_to(installed), path
dataset = Path(sys.argv[2])
assert cli.main(["site-config", str(dataset)]) == 0
assert cli.main(["site-config", str(dataset), "--mode", "paper"]) == 0
from so_transients.database import schema
from so_transients.database.engine import open_database
assert schema.MIGRATIONS.is_relative_to(installed)
with open_database(dataset / "events.db").connect() as conn:   # made by the installed revisions
    assert schema.stored_revision(conn) == schema.HEAD
print("OK", sorted(p.name for p in dataset.glob("*.yaml")))
"""


def source_copy(folder) -> Path:
    """What the wheel is built from, copied: pip builds in the source tree (``build/``,
    ``*.egg-info``), where a checkout's leftovers (files since removed, another
    interpreter's build running at the same time) would go into the wheel."""
    folder.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, folder / name)
    shutil.copytree(REPO / "so_transients", folder / "so_transients",
                    ignore=shutil.ignore_patterns("__pycache__"))
    return folder


def test_a_wheel_installed_elsewhere_finds_its_configs(tmp_path):
    wheels, target, dataset = tmp_path / "wheels", tmp_path / "site", tmp_path / "dataset"
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    source = source_copy(tmp_path / "source")
    subprocess.run([*pip, "wheel", "--no-deps", "-w", str(wheels), str(source)], check=True)
    (wheel,) = wheels.glob("so_transients-*.whl")
    subprocess.run([*pip, "install", "--no-deps", "--target", str(target), str(wheel)],
                   check=True)
    dataset.mkdir()
    (dataset / "context.yaml").write_text("imports: [so_transients]\n")
    run = subprocess.run([sys.executable, "-c", CHECK, str(target), str(dataset)],
                         cwd=tmp_path, env={"PYTHONPATH": str(target), "PATH": "/usr/bin:/bin"},
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "OK ['context.yaml', 'preprocess.yaml', 'preprocess_paper.yaml']" in run.stdout
