"""One crossing, one detection: the paper's clustering splits a crossing between two rows of
detector tracks farther apart than its scale, and ``transient_fit`` keeps one detection of it
(on arrays, then end to end on a UHF wafer in paper mode)."""
import numpy as np
import pytest
from astropy.table import vstack

from so_transients.campaign.matching import compare_with_truth
from so_transients.common.angles import ARCMIN, ARCSEC, sky_separation
from so_transients.common.bands import get_band, sigma_fwhm_by_band
from so_transients.detect.find import FindConfig, find_candidates
from so_transients.detect.fit import FitConfig
from so_transients.detect.fit_candidates import detection_decision
from so_transients.detect.matched_filter import FilterConfig
from so_transients.site.results import proc_table

from tests.conftest import load_group, run_sim, run_steps

FS = 220.0
STEP = np.radians(1.0) / FS                 # 1 deg/s on the sky
FWHM = {b: get_band(b).fwhm for b in ("f220", "f280")}


def test_a_crossing_between_two_rows_of_tracks_makes_two_clusters():
    """The cause: two rows of detector tracks 0.9' apart across the scan, a 1' FWHM source
    midway between them. Each detector's S/N >= 3 samples lie along its track; the rows are
    farther apart than DBSCAN's scale sigma_FWHM (0.60' at f220), so they are two clusters."""
    ndet, nsamp = 12, 2000
    row = np.where(np.arange(ndet) < 6, -0.45, 0.45) * ARCMIN     # across the scan
    lead = (np.arange(ndet) % 6) * 1.574 * ARCMIN                 # along the scan
    sigma = get_band("f220").sigma
    ra = np.arange(nsamp)[None, :] * STEP - lead[:, None]        # detector d at sample s
    source = 1000 * STEP - 4 * ARCMIN
    snr = (12.0 * np.exp(-0.5 * ((ra - source) ** 2 + row[:, None] ** 2) / sigma**2)
           ).astype(np.float32)
    eps = sigma_fwhm_by_band([sigma], ["f220"])["f220"]
    cands, hits = find_candidates(snr, np.arange(nsamp) / FS, np.zeros(nsamp, int),
                                  np.array([1]), lambda d, s: (ra[d, s], row[d]), eps,
                                  FindConfig())
    assert len(cands["scan"]) == 2
    for c in range(2):
        assert len(np.unique(np.sign(row[hits["det"][hits["cand"] == c]]))) == 1


def _candidates(bands, scans, snr_max=None, n_crossings=None):
    n = len(bands)
    return {"bandpass": np.asarray(bands), "scan": np.asarray(scans),
            "cand_id": np.arange(n) + 100, "t_peak": np.asarray(scans) * 90.0,
            "snr_max": np.full(n, 8.0) if snr_max is None else np.asarray(snr_max, float),
            "n_crossings": np.ones(n, int) if n_crossings is None else np.asarray(n_crossings)}


def _fits(snr_fit, ra, dec, err=1 * ARCSEC):
    n = len(snr_fit)
    return {"fit_ok": np.ones(n, bool), "snr_fit": np.asarray(snr_fit, float),
            "ra": np.asarray(ra, float), "dec": np.asarray(dec, float),
            "ra_err": np.full(n, err), "dec_err": np.full(n, err)}


def test_two_fits_of_one_crossing_give_one_detection_and_distinct_crossings_stay():
    """Candidates 0 and 1 are the two halves of one f220 crossing (fitted 0.02" apart, as in
    the report); 2 is the same source on the next scan, 3 a second source 2 FWHM away on the
    same scan, 4 the crossing in f280, 5 a fit below min_snr at the same place."""
    ra0, dec0 = 1.0, -0.7
    d = 0.02 * ARCSEC
    cands = _candidates(["f220", "f220", "f220", "f220", "f280", "f220"], [1, 1, 2, 1, 1, 1])
    fits = _fits([40.5, 40.6, 38.0, 20.0, 19.0, 4.0],
                 [ra0, ra0, ra0, ra0, ra0, ra0],
                 [dec0, dec0 + d, dec0, dec0 + 2 * FWHM["f220"], dec0, dec0])
    out = detection_decision(cands, fits, FitConfig(), FWHM)
    assert list(out["detected"]) == [False, True, True, True, True, False]
    assert list(out["duplicate_of"]) == [101, -1, -1, -1, -1, -1]


def test_the_detection_kept_is_one_that_passes_the_other_tests():
    """The higher-S/N fit of a crossing fails the peak-ratio test: the other is kept."""
    cands = _candidates(["f280", "f280"], [3, 3], snr_max=[200.0, 20.0])
    fits = _fits([30.0, 29.0], [2.0, 2.0], [0.1, 0.1 + 5 * ARCSEC])
    out = detection_decision(cands, fits, FitConfig(max_peak_ratio=3.0), FWHM)
    assert list(out["detected"]) == [False, True]
    assert list(out["duplicate_of"]) == [101, -1]


def test_a_duplicate_shares_the_motion_of_its_crossing():
    """A source moving 1'/min, detected on three scans, twice on the second: the motion test
    sees three detections, and the duplicate is moving too."""
    scans = [0, 1, 1, 2]
    cands = _candidates(["f220"] * 4, scans)
    dec = -0.5 + np.asarray(cands["t_peak"]) / 60.0 * ARCMIN
    fits = _fits([30.0, 31.0, 30.0, 29.0], np.full(4, 3.0), dec)
    out = detection_decision(cands, fits, FitConfig(), FWHM)
    assert out["moving"].all() and not out["detected"].any()
    assert list(out["duplicate_of"]) == [-1, -1, 101, -1]
    assert np.allclose(out["motion_rate"], 1.0, rtol=0.01)


def test_a_sweep_stack_is_not_joined_with_a_crossing():
    cands = _candidates(["f220", "f220"], [1, 1], n_crossings=[1, 3])
    fits = _fits([20.0, 25.0], [1.0, 1.0], [0.2, 0.2])
    out = detection_decision(cands, fits, FitConfig(), FWHM)
    assert out["detected"].all() and (out["duplicate_of"] == -1).all()


# ----------------------------------------------------------------------------- end to end

STEPS = [{"name": "transient_filter", "process": {}, "calc": True, "save": True},
         {"name": "transient_find", "calc": {"mode": "paper"}, "save": True},
         {"name": "transient_cuts", "calc": {}, "save": True},
         {"name": "transient_fit", "calc": {}, "save": True}]


START, DURATION = 1_700_000_000.0, 180.0


@pytest.fixture(scope="module")
def uhf_paper(module_tmp):
    """3 minutes of UHF wafer w01 (tube c1) at elevation 60, white noise, six 3-8 Jy flares
    and two 3-6 Jy steady sources, searched in paper mode in both bands: (dataset, every
    candidate). Without joining, five crossings of this sky give two detections each (three
    in f220, one in f280, one of a steady source)."""
    sim = run_sim(module_tmp("uhf_crossings"), seed=1,
                  observation={"start": START, "duration": DURATION},
                  instrument={"tubes": ["c1"], "wafers": ["w01"]}, scan={"el": 60.0},
                  atmosphere={"enabled": False}, cmb={"enabled": False},
                  flares={"n": 6, "s_peak_mjy": [3000, 8000], "t_rise": [10, 30]},
                  point_sources={"n": 2, "flux_mjy": [3000, 6000]})
    tables = [proc_table(run_steps(load_group(sim, wafer="w01", band=band), STEPS),
                         sim.obs_ids[0]) for band in ("f220", "f280")]
    return sim, vstack(tables)


def _near(table, source, radius=0.5 * ARCMIN):
    """Rows of ``table`` in ``source``'s band within ``radius`` of it."""
    close = sky_separation(np.asarray(table["ra"], float), np.asarray(table["dec"], float),
                           source["ra"], source["dec"]) < radius
    return table[close & (table["bandpass"] == source["band"])]


@pytest.mark.slow
def test_each_uhf_crossing_is_detected_once_in_paper_mode(uhf_paper):
    sim, table = uhf_paper
    found = table[np.asarray(table["detected"], bool)]
    matched, _, crossings = compare_with_truth(sim.context.parent, found)
    counts = {}
    for (source, _, _, band), times in crossings.items():
        mine = np.asarray(matched["t_peak"][(matched["source_id"] == source)
                                            & (matched["bandpass"] == band)])
        for when in times:
            counts[(source, band, round(float(when) - START, 2))] = int(
                np.sum(np.abs(mine - when) < 0.5))
    assert len(counts) >= 10 and max(counts.values()) == 1, counts
    # crossings are missed only where nothing is searched: the filter's edge buffers
    edge = FilterConfig().edge_buffer
    assert all(not edge <= k[2] <= DURATION - edge for k, v in counts.items() if not v), counts
    # the other detections are the steady sources', each found at most once per scan
    steady = matched[matched["source_id"] < 0]
    per_source = [_near(steady, source) for source in sim.point_sources]
    assert sum(len(rows) for rows in per_source) == len(steady)
    for rows in per_source:
        assert len(rows) >= 1 and len(set(rows["scan"])) == len(rows)
    # the repeats are recorded, each naming the detection of its group and scan
    repeats = table[np.asarray(table["duplicate_of"]) >= 0]
    assert len(repeats) >= 5
    for r in repeats:
        kept = table[(table["bandpass"] == r["bandpass"])
                     & (table["cand_id"] == r["duplicate_of"])]
        assert len(kept) == 1 and kept["detected"][0] and kept["scan"][0] == r["scan"]
