"""The documentation: every registered step, config key and candidate column is in the built
pages, and the README stays a user's page."""
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "docs" / "_ext"))
import step_docs  # noqa: E402


@pytest.fixture(scope="module")
def html(module_tmp):
    out = module_tmp("docs") / "html"
    run = subprocess.run([sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b",
                          "html", str(ROOT / "docs"), str(out)], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    return out


def test_every_step_and_config_key_is_documented(html):
    assert step_docs.missing_from_docs(html) == []


def test_every_candidate_column_is_documented(html):
    assert step_docs.missing_columns(html) == []


def test_the_checks_see_what_is_missing(tmp_path):
    """Pages without the steps' tables: every registered step and key is reported."""
    (tmp_path / "index.html").write_text("<html><body><p id='nothing'></p></body></html>")
    missing = step_docs.missing_from_docs(tmp_path)
    steps = set(step_docs.registered_steps())
    assert {s for s, key in missing if key is None} == steps
    assert ("transient_find", "coherent_threshold") in missing
    assert ("transient_find", "snr_threshold") in missing
    assert "flux" in step_docs.missing_columns(tmp_path)


def test_the_readme_is_a_short_page_for_users():
    text = (ROOT / "README.md").read_text()
    assert len(text.encode()) <= 12 * 1024
    assert "make demo" in text.split("\n## ")[0] and "make test" in text.split("\n## ")[0]


def test_each_setting_carries_its_unit_and_meaning_in_the_code():
    """Units and meanings live in the config dataclasses' field metadata (``setting``), not in
    comments: every key has a meaning, a key named for its unit carries that unit, and the
    time, angle and rate settings say theirs."""
    keys = {(k.step, k.name): k for step in step_docs.step_configs()
            for k in step_docs.config_keys(step)}
    assert all(k.meaning for k in keys.values())
    for (step, name), key in keys.items():
        for suffix, unit in (("_arcmin_per_min", "arcmin / min"), ("_arcsec", "arcsec"),
                             ("_deg", "deg"), ("_mjy", "mJy")):
            if name.endswith(suffix):
                assert key.unit == unit, (step, name)
    expect = {("transient_fit", "window"): "s", ("transient_fit", "local_window"): "s",
              ("transient_filter", "white_band"): "Hz", ("transient_filter", "highpass"): "Hz",
              ("transient_jumps", "window"): "s", ("transient_pca_mask", "block"): "s",
              ("transient_significance", "max_far"): "1 / h",
              ("transient_find", "coherent_threshold"): "Z"}
    assert {k: keys[k].unit for k in expect} == expect
