"""Known-source lists of ``transient_cuts``: a missing, empty or malformed file is refused when
the pipeline is built, with one line naming the step, the key and the file; a list without
sources is read with a warning that nothing will be masked."""
import logging

import numpy as np
import pytest

import so_transients  # noqa: F401  registers the transient steps with sotodlib's Pipeline
from so_transients.common.step_config import ConfigError
from so_transients.sources.catalog import read_known_sources

ECSV_HEADER = """# %ECSV 1.0
# ---
# datatype:
# - {name: ra, unit: rad, datatype: float64}
# - {name: dec, unit: rad, datatype: float64}
# schema: astropy-2.0
ra dec
"""


def write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    return path


def refused(path, unit="deg"):
    """The one-line message of the error ``read_known_sources`` raises on ``path``."""
    with pytest.raises(ConfigError) as err:
        read_known_sources(path, unit)
    message = str(err.value)
    assert "\n" not in message
    return message


def names_everything(message, path):
    return (message.startswith("transient_cuts: known_sources: ") and str(path) in message)


def test_a_csv_in_degrees_and_an_ecsv_in_radians_give_the_same_sources(tmp_path):
    csv = write(tmp_path, "known.csv", "name,ra,dec\nA,10.5,-30.25\nB,359.0,89.0\nC,-20.0,0\n")
    ra, dec = read_known_sources(csv)
    np.testing.assert_allclose(np.degrees(ra), [10.5, 359.0, -20.0])
    np.testing.assert_allclose(np.degrees(dec), [-30.25, 89.0, 0.0])
    ecsv = write(tmp_path, "known.ecsv",
                 ECSV_HEADER + "".join(f"{r} {d}\n" for r, d in zip(ra, dec)))
    ra2, dec2 = read_known_sources(ecsv, unit="arcmin")     # the columns' own unit wins
    np.testing.assert_allclose(ra2, ra)
    np.testing.assert_allclose(dec2, dec)
    arcmin = write(tmp_path, "arcmin.csv", "ra,dec\n60,-120\n")
    np.testing.assert_allclose(np.degrees(read_known_sources(arcmin, unit="arcmin")),
                               [[1.0], [-2.0]])


def test_a_missing_file_is_refused_naming_it(tmp_path):
    path = tmp_path / "nowhere.ecsv"
    message = refused(path)
    assert names_everything(message, path) and "no such file" in message
    assert "not a file" in refused(tmp_path)                # a folder


@pytest.mark.parametrize("name", ["empty.ecsv", "empty.csv"])
def test_a_zero_byte_file_is_refused_as_empty(tmp_path, name):
    path = write(tmp_path, name, "")
    message = refused(path)
    assert names_everything(message, path) and "empty (0 bytes)" in message
    assert "ECSV header line" not in message


@pytest.mark.parametrize("name, text, why", [
    ("garbage.ecsv", "ra dec\n1 2\n", "cannot be read as ascii.ecsv"),
    ("ragged.csv", "ra,dec\n1,2,3\n4,5\n", "cannot be read"),
    ("columns.csv", "x,y\n1,2\n", "lacks column(s) ra, dec (has: x, y)"),
    ("onlyra.csv", "ra\n1\n", "lacks column(s) dec"),
    ("text.csv", "ra,dec\nabc,def\n", "column ra is not numeric"),
    ("blank.csv", "ra,dec\n1,2\n3,\n", "column dec has 1 missing or non-finite value(s), "
                                       "the first in data row 2"),
    ("nan.csv", "ra,dec\nnan,2\n", "column ra has 1 missing or non-finite"),
    ("dec.csv", "ra,dec\n10,95\n", "column dec must lie in [-90, 90] deg; data row 1 has 95"),
    ("ra.csv", "ra,dec\n10,0\n400,0\n", "column ra must lie in [-180, 360] deg; data row 2"),
    ("flux.ecsv", ECSV_HEADER.replace("{name: dec, unit: rad", "{name: dec, unit: mJy")
     + "1.0 1.0\n", "column dec has unit mJy, not an angle"),
])
def test_a_malformed_file_is_refused_naming_it_and_what_is_wrong(tmp_path, name, text, why):
    path = write(tmp_path, name, text)
    message = refused(path)
    assert names_everything(message, path)
    assert why in message


def test_degrees_read_as_radians_are_out_of_range(tmp_path):
    path = write(tmp_path, "deg.csv", "ra,dec\n150.0,2.2\n")
    message = refused(path, unit="rad")
    assert names_everything(message, path) and "known_sources_unit" in message


@pytest.mark.parametrize("unit", ["degg", "m"])
def test_a_unit_that_is_not_an_angle_is_refused_naming_its_key(tmp_path, unit):
    path = write(tmp_path, "known.csv", "ra,dec\n1,2\n")
    assert refused(path, unit).startswith("transient_cuts: known_sources_unit: ")


@pytest.mark.parametrize("name, text", [("header.csv", "ra,dec\n"),
                                        ("header.ecsv", ECSV_HEADER)])
def test_a_list_without_sources_warns_that_nothing_is_masked(tmp_path, caplog, name, text):
    path = write(tmp_path, name, text)
    with caplog.at_level(logging.WARNING, logger="so_transients.sources.catalog"):
        ra, dec = read_known_sources(path)
    assert len(ra) == len(dec) == 0
    assert any(str(path) in r.getMessage() and "transient_cuts" in r.getMessage()
               and "nothing will be masked" in r.getMessage() for r in caplog.records)


def test_one_source_reads_without_a_warning(tmp_path, caplog):
    path = write(tmp_path, "one.csv", "ra,dec\n1,2\n")
    with caplog.at_level(logging.WARNING, logger="so_transients.sources.catalog"):
        assert len(read_known_sources(path)[0]) == 1
    assert not caplog.records


def pipeline(known_sources):
    from sotodlib.preprocess import Pipeline

    return Pipeline([{"name": "transient_cuts", "calc": {"known_sources": known_sources},
                      "save": True}])


def test_building_the_pipeline_with_an_empty_file_is_refused(tmp_path):
    """sotodlib's Pipeline reads the file when it builds ``transient_cuts``, before any data."""
    path = write(tmp_path, "empty.ecsv", "")
    with pytest.raises(ValueError, match="transient_cuts: known_sources: .*empty.ecsv.*0 bytes"):
        pipeline(str(path))
    with pytest.raises(ValueError, match="transient_cuts: known_sources: : not a file"):
        pipeline("")                                     # an empty path is not "no list"
    good = write(tmp_path, "good.csv", "ra,dec\n10,20\n")
    np.testing.assert_allclose(np.degrees(pipeline(str(good))[0].known), [[10.0], [20.0]])
    assert len(pipeline(None)[0].known[0]) == 0
