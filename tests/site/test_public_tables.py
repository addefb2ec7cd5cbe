"""Every public table gives angles in degrees: beside the archive's radians in memory, alone in
a written file; a written catalogue reads back as written (empty ``cut_reason`` as '',
booleans as booleans) and with its radians restored by the package's reader. The archive's
own tables (both readers) are checked on a real run in tests/site/test_site_pipeline.py."""
import numpy as np
import pytest

from so_transients.common import candidates
from so_transients.common.angles import ARCSEC, DEG
from so_transients.common.tables import read_table
from so_transients.site.results import (read_catalogue, readable_columns,
                                        with_readable_columns, write_table)


def catalogue():
    """Two candidates as the archive gives them (radians, ctime), one cut, one detected."""
    rows = {"obs_id": np.array(["obs_1", "obs_1"]), "cand_id": np.array([0, 1]),
            "ra": np.array([1.0, -2.0]), "dec": np.array([-0.5, -0.4]),
            "ra_err": np.array([1e-5, 2e-5]), "dec_err": np.array([3e-5, 4e-5]),
            "cluster_ra": np.array([1.00001, -2.00002]), "cluster_dec": np.array([-0.5, -0.4]),
            "t_peak": np.array([1.7e9, 1.7e9 + 60]),
            "cut_reason": np.array(["", "time_order"]), "detected": np.array([True, False])}
    return candidates.table(rows, first=["obs_id"])


def angle_columns():
    return [c.name for c in candidates.columns(saved=True) if c.unit == "rad"]


def assert_angles_in_degrees(table):
    """Every angle column (rad) has its degree (error: arcsec) companion, right after it."""
    derived = {src: (name, unit, scale, period)
               for name, src, unit, scale, period, _ in readable_columns()}
    assert set(derived) == set(angle_columns()) >= {"ra", "dec", "cluster_ra", "ra_err"}
    for src, (name, unit, scale, period) in derived.items():
        assert table.colnames.index(name) == table.colnames.index(src) + 1
        assert str(table[name].unit) == unit and str(table[src].unit) == "rad"
        expected = np.asarray(table[src]) / scale
        assert np.allclose(table[name], np.mod(expected, period) if period else expected,
                           equal_nan=True)
    assert derived["ra"][1:] == ("deg", DEG, 360.0) and derived["dec"][3] is None
    assert derived["ra_err"][1:] == ("arcsec", ARCSEC, None)


def test_readable_columns_give_every_angle_in_degrees_once():
    once = with_readable_columns(catalogue())
    assert_angles_in_degrees(once)
    assert np.allclose(once["ra_deg"], [np.degrees(1.0), 360 - np.degrees(2.0)])
    assert np.allclose(once["dec_err_arcsec"], np.degrees([3e-5, 4e-5]) * 3600)
    assert str(once["t_peak_utc"][0]).startswith("2023-11-14T22:13:20")
    twice = with_readable_columns(once)
    assert twice.colnames == once.colnames
    for name in once.colnames:
        nan = once[name].dtype.kind == "f"
        assert np.array_equal(twice[name], once[name], equal_nan=nan), name


@pytest.mark.parametrize("suffix", [".ecsv", ".fits", ".csv"])
def test_a_written_catalogue_reads_back_as_written(tmp_path, suffix):
    path = write_table(catalogue(), tmp_path / f"detections{suffix}")
    back = read_table(path)
    assert list(back["cut_reason"]) == ["", "time_order"]
    assert back["cut_reason"].dtype.kind == "U" and not hasattr(back["cut_reason"], "mask")
    assert back["detected"].dtype == bool and list(back["detected"]) == [True, False]
    assert list(back["obs_id"]) == ["obs_1", "obs_1"]
    readable = with_readable_columns(catalogue())
    radians = angle_columns()
    assert back.colnames == [c for c in readable.colnames if c not in radians]
    assert np.allclose(back["ra_deg"], readable["ra_deg"])
    if suffix != ".csv":                 # CSV carries no units
        assert {str(back[c].unit) for c in back.colnames if c.endswith("_deg")} == {"deg"}
    again = read_catalogue(path)         # the package's own reader: radians restored
    assert_angles_in_degrees(again)
    for name in radians:
        expected = np.mod(catalogue()[name], 2 * np.pi) if name.endswith("ra") else catalogue()[name]
        assert np.allclose(again[name], expected, rtol=1e-14, atol=0), name
