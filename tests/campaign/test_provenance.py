"""Where a study's table says it came from."""
from pathlib import Path

from so_transients.campaign.provenance import ROOT, repository_path


def test_a_path_in_the_repository_is_named_from_its_root_and_one_outside_by_its_tail(tmp_path):
    assert repository_path(ROOT / "configs" / "preprocess_paper.yaml") == \
        "configs/preprocess_paper.yaml"
    outside = tmp_path / "campaign_paper_mf" / "results"
    assert repository_path(outside) == "results"
    assert repository_path(outside, 2) == str(Path("campaign_paper_mf", "results"))
    assert str(tmp_path) not in repository_path(outside, 2)
