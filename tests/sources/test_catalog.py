"""Known sources from a real socat database (built with socat's own DB client) and from
ECSV/CSV, and the flux-dependent cross-match against them. The socat installed decides the
API: 0.0.2 (the package index's) or 0.1 (socat's main branch: UUID ids, get_box_fixed,
datetimes); both are supported and these tests run on either."""
import uuid

import numpy as np
import pytest
from astropy import units as u
from astropy.coordinates import ICRS
from astropy.table import Table

from socat.client import db as socat_db

from so_transients.common.angles import ARCMIN, DEG
from so_transients.sources.catalog import (
    database_url, is_database_url, read_catalogue, read_ephemerides
)
from so_transients.sources.crossmatch import CrossmatchConfig, crossmatch, match_radius

from tests.conftest import add_socat_asteroid

T0 = 1_750_000_000
#: socat 0.1 (main) or 0.0.2
SOCAT_01 = hasattr(socat_db.Client, "get_box_fixed")


@pytest.fixture
def socat_file(tmp_path):
    """A socat SQLite catalogue: three fixed sources and one asteroid with an ephemeris of
    three hourly points moving 0.5 deg in RA per hour."""
    path = tmp_path / "socat.db"
    client = socat_db.Client(db_url=f"sqlite:///{path}")
    client.create_source(position=ICRS(ra=10 * u.deg, dec=-20 * u.deg), name="QSO A",
                         flux=100 * u.mJy)
    client.create_source(position=ICRS(ra=30 * u.deg, dec=-5 * u.deg), name="Blazar B",
                         flux=2.0 * u.Jy)
    client.create_source(position=ICRS(ra=50 * u.deg, dec=-40 * u.deg), name="no flux")
    add_socat_asteroid(client, "Vesta", 4, [
        (T0 + 3600 * k, ICRS(ra=(100 + 0.5 * k) * u.deg, dec=10 * u.deg)) for k in range(3)],
        flux=50 * u.mJy)
    return path


def test_socat_urls_and_files_are_told_apart(tmp_path):
    assert is_database_url("socat:///data/socat.db") and is_database_url("postgresql://h/db")
    assert is_database_url("sqlite:///x.db") and not is_database_url(tmp_path / "known.ecsv")
    assert database_url("socat:///data/socat.db") == "sqlite:////data/socat.db"
    assert database_url("postgresql+psycopg://u@h/db") == "postgresql+psycopg://u@h/db"
    with pytest.raises(ValueError, match="socat:"):
        database_url("socat:data.db")


def test_fixed_sources_read_from_socat(socat_file):
    for spec in (f"socat://{socat_file}", f"sqlite:///{socat_file}"):
        cat = read_catalogue(spec)
        order = np.argsort(cat.name)
        assert list(cat.name[order]) == ["Blazar B", "QSO A", "no flux"]
        assert np.allclose(cat.ra[order] / DEG, [30, 10, 50])
        assert np.allclose(cat.dec[order] / DEG, [-5, -20, -40])
        assert cat.flux_mjy[order][:2].tolist() == [2000.0, 100.0]
        assert np.isnan(cat.flux_mjy[order][2])
        ids = sorted(cat.source_id)        # strings: socat 0.1's UUIDs, 0.0.2's integers
        assert len(set(ids)) == 3 and all(isinstance(i, str) for i in ids)
        if SOCAT_01:
            assert all(uuid.UUID(i) for i in ids)
        else:
            assert ids == ["1", "2", "3"]
        assert cat.label == spec


def test_socat_from_its_own_settings(socat_file, monkeypatch):
    monkeypatch.setenv("socat_model_database_type", "sqlite")
    monkeypatch.setenv("socat_model_database_name", str(socat_file))
    assert len(read_catalogue("socat:")) == 3


def test_a_missing_socat_file_is_an_error_and_not_created(tmp_path):
    path = tmp_path / "absent.db"
    with pytest.raises(FileNotFoundError, match="absent.db"):
        read_catalogue(f"socat://{path}")
    assert not path.exists()


def test_ephemeris_read_around_the_times_asked(socat_file):
    eph = read_ephemerides(f"socat://{socat_file}", T0 + 1000, T0 + 2000)
    assert list(eph.time) == [T0, T0 + 3600, T0 + 7200] and set(eph.name) == {"Vesta"}
    assert np.allclose(eph.ra / DEG, [100, 100.5, 101])
    assert len(read_ephemerides(f"socat://{socat_file}", T0 + 10 * 86400, T0 + 10 * 86400)) == 0


def test_ecsv_and_csv_catalogues(tmp_path):
    table = Table({"ra": [10.0, 30.0] * u.deg, "dec": [-20.0, -5.0] * u.deg,
                   "name": ["QSO A", "Blazar B"], "flux": [0.1, 2.0] * u.Jy})
    table.write(tmp_path / "known.ecsv")
    cat = read_catalogue(tmp_path / "known.ecsv")
    assert np.allclose(cat.ra, np.radians([10, 30])) and cat.flux_mjy.tolist() == [100, 2000]
    assert list(cat.source_id) == ["", ""]
    (tmp_path / "known.csv").write_text("ra,dec\n0.5,-0.1\n")
    cat = read_catalogue(tmp_path / "known.csv", unit="rad")
    assert cat.ra.tolist() == [0.5] and np.isnan(cat.flux_mjy[0]) and cat.name.tolist() == [""]
    (tmp_path / "bad.csv").write_text("ra,de\n0.5,-0.1\n")
    with pytest.raises(ValueError, match=r"bad.csv: lacks column\(s\) dec"):
        read_catalogue(tmp_path / "bad.csv")


def test_match_radius_grows_with_flux_as_sotrplib_sifter():
    cfg = CrossmatchConfig()
    radius = match_radius([0.0, 10.0, 1000.0, 2000.0, 10_000.0, np.nan], cfg) / ARCMIN
    assert np.allclose(radius, [1.5, 1.5, 30.0, 60.0, 120.0, 1.5])


def test_crossmatch_classes(socat_file):
    spec = f"socat://{socat_file}"
    t_mid = T0 + 1800
    # (ra, dec) deg, flux mJy, time
    events = [
        (10.0, -20.0 + 1.0 / 60, 120.0, t_mid),      # QSO A at its flux, 1' off
        (10.0, -20.0 + 1.0 / 60, 800.0, t_mid),      # QSO A eight times brighter: a flare
        (30.0, -5.0 + 40.0 / 60, 2000.0, t_mid),     # 40' from a 2 Jy source, 2 Jy: 60' radius
        (30.0, -5.0 + 40.0 / 60, 20.0, t_mid),       # the same offset at 20 mJy: 1.5' radius
        (100.25, 10.0, 60.0, t_mid),                  # Vesta half-way along its ephemeris
        (100.25, 10.0, 60.0, T0 + 20 * 86400),        # the same place 20 days later
        (50.0, -40.0, 30.0, t_mid),                   # a source without a catalogue flux
    ]
    ra, dec, flux, t = (np.array(c, float) for c in zip(*events))
    got = crossmatch(ra * DEG, dec * DEG, flux, t, read_catalogue(spec),
                     read_ephemerides(spec, t.min(), t.max()), CrossmatchConfig())
    assert list(got["cat_class"]) == ["catalogued", "catalogued_flare", "catalogued", "new",
                                      "solar_system", "new", "catalogued"]
    assert list(got["cat_source_name"]) == ["QSO A", "QSO A", "Blazar B", "", "Vesta", "",
                                            "no flux"]
    assert got["cat_separation"][0] == pytest.approx(1.0, rel=1e-6)
    assert got["cat_separation"][2] == pytest.approx(40.0, rel=1e-6)
    assert got["cat_separation"][4] < 0.01       # interpolated to the event's time
    assert got["cat_flux_ratio"][:3] == pytest.approx([1.2, 8.0, 1.0])
    assert got["cat_flux_ratio"][4] == pytest.approx(60.0 / 50.0)
    assert np.isnan(got["cat_flux_ratio"][6]) and np.isnan(got["cat_separation"][3])
    assert list(got["catalogue"]) == [spec] * 3 + [""] + [spec] + [""] + [spec]
    vesta = read_ephemerides(spec, t.min(), t.max()).sso_id[0]
    assert got["cat_source_id"][3] == "" and got["cat_source_id"][4] == vesta
    assert vesta == ("1" if not SOCAT_01 else str(uuid.UUID(vesta)))


def test_flare_ratio_threshold_is_configurable(socat_file):
    cat = read_catalogue(f"socat://{socat_file}")
    got = crossmatch([10 * DEG], [-20 * DEG], [300.0], [T0], cat, None,
                     CrossmatchConfig(flare_ratio=2.0))
    assert got["cat_class"][0] == "catalogued_flare"
