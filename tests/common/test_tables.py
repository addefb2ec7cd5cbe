"""Tables read back as written in ECSV, FITS and CSV: empty strings stay '' (astropy reads
them as masked), NaN stays NaN, booleans stay booleans."""
import numpy as np
import pytest
from astropy.table import Column, MaskedColumn, Table

from so_transients.common.tables import FORMATS, for_writing, read_table


def example():
    return Table({"cut_reason": np.array(["", "time_order", ""]),
                  "obs_id": np.array(["obs_a", "obs_b", "obs_c"]),
                  "flux": np.array([1.5, np.nan, 3.0]),
                  "passed": np.array([True, False, True]),
                  "cand_id": np.array([0, 1, 2])})


def write(table, path):
    fmt = FORMATS[path.suffix]
    out, options = for_writing(table, fmt)
    out.write(path, format=fmt, **options)


@pytest.mark.parametrize("suffix", sorted(set(FORMATS)))
def test_a_table_reads_back_as_written(tmp_path, suffix):
    path = tmp_path / f"t{suffix}"
    write(example(), path)
    back = read_table(path)
    assert back.colnames == example().colnames
    for name in ("cut_reason", "obs_id"):
        assert type(back[name]) is Column and back[name].dtype.kind == "U"
        assert list(back[name]) == list(example()[name])
    assert type(back["flux"]) is Column
    assert np.array_equal(back["flux"], example()["flux"], equal_nan=True)
    assert back["passed"].dtype == bool and list(back["passed"]) == [True, False, True]
    assert list(back["cand_id"]) == [0, 1, 2]


@pytest.mark.parametrize("suffix", sorted(set(FORMATS)))
def test_astropy_alone_masks_empty_strings_where_read_table_does_not(tmp_path, suffix):
    """What the helpers are for: astropy's reader masks the '' the plain writer wrote."""
    path = tmp_path / f"t{suffix}"
    example().write(path, format=FORMATS[suffix])
    kwargs = {"comment": "#"} if suffix == ".csv" else {}
    plain = Table.read(path, format=FORMATS[suffix], **kwargs)
    assert isinstance(plain["cut_reason"], MaskedColumn)
    assert list(plain["cut_reason"].mask) == [True, False, True]
    assert list(read_table(path)["cut_reason"]) == ["", "time_order", ""]


def test_an_ecsv_written_for_reading_gives_empty_strings_to_astropy_alone(tmp_path):
    path = tmp_path / "t.ecsv"
    write(example(), path)
    back = Table.read(path)
    assert not np.any(getattr(back["cut_reason"], "mask", False))
    assert list(back["cut_reason"] == "") == [True, False, True]


def test_masked_strings_are_written_empty(tmp_path):
    table = example()
    table["cut_reason"] = MaskedColumn(["x", "time_order", "y"], mask=[True, False, True])
    path = tmp_path / "t.ecsv"
    write(table, path)
    assert list(read_table(path)["cut_reason"]) == ["", "time_order", ""]


def test_a_masked_int_stays_masked_and_a_bad_file_is_named(tmp_path):
    path = tmp_path / "t.csv"
    path.write_text("a,b\n1,x\n,y\n")
    back = read_table(path)
    assert isinstance(back["a"], MaskedColumn) and list(back["a"].mask) == [False, True]
    empty = tmp_path / "empty.ecsv"
    empty.write_text("")
    with pytest.raises(ValueError, match="empty.ecsv"):
        read_table(empty)
