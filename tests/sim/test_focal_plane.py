"""Focal-plane geometry against sotodlib's nominal LAT hardware numbers."""
import numpy as np
import pytest
from scipy.spatial import cKDTree

from so_transients.sim import focal_plane as fp

ARCMIN = np.pi / 180 / 60
PITCH = 5.3 * 0.00495 * 60 * ARCMIN          # 1.574'
TUBE_PITCH = np.radians(359.6 * 0.00495)      # 1.780 deg


@pytest.fixture(scope="module")
def wafer():
    return fp.wafer_detectors("i1", "w16")


def test_pixel_and_detector_counts(wafer):
    for band in ("f090", "f150"):
        in_band = wafer["bandpass"] == band
        assert in_band.sum() == 860
        assert len(np.unique(wafer["pixel"][in_band])) == 430
    assert set(wafer["bandpass"]) == {"f090", "f150"}


def test_two_orthogonal_polarizations_per_pixel_per_band(wafer):
    for band in ("f090", "f150"):
        for pix in (0, 123, 429):
            sel = (wafer["bandpass"] == band) & (wafer["pixel"] == pix)
            assert sorted(wafer["pol"][sel]) == ["A", "B"]
            g = wafer["gamma"][sel]
            assert np.isclose(np.mod(g[1] - g[0], np.pi), np.pi / 2)
            assert np.ptp(wafer["xi"][sel]) == 0 and np.ptp(wafer["eta"][sel]) == 0


def test_nearest_neighbour_pitch(wafer):
    sel = (wafer["bandpass"] == "f090") & (wafer["pol"] == "A")
    xy = np.c_[wafer["xi"][sel], wafer["eta"][sel]]
    dist, _ = cKDTree(xy).query(xy, k=2)
    assert abs(np.median(dist[:, 1]) / PITCH - 1) < 0.01
    assert dist[:, 1].min() > 0.99 * PITCH   # rhombus gaps never bring pixels closer


def test_uhf_wafer_bands_and_names():
    dets = fp.wafer_detectors("c1", "w00")
    assert set(dets["bandpass"]) == {"f220", "f280"}
    assert len(set(dets["readout_id"])) == len(dets["readout_id"]) == 1720


def test_tube_and_wafer_placement():
    centers = {t: np.array(fp.tube_center(t)) for t in ("c1", "i1", "i3", "i4", "i5", "i6")}
    assert np.allclose(centers["c1"], 0)
    for tube in ("i1", "i3", "i4", "i5", "i6"):   # the inner ring, one tube pitch from c1
        assert np.isclose(np.hypot(*centers[tube]), TUBE_PITCH)
    for tube in ("i1", "c1"):
        wafer_centers = np.array(list(fp.wafer_centers(tube).values()))
        sep = np.hypot(*(wafer_centers[:, None] - wafer_centers[None]).transpose(2, 0, 1))
        assert np.allclose(sep[~np.eye(3, dtype=bool)], np.radians(128.4 * 0.00495))
        dets = fp.tube_detectors(tube)
        radius = np.hypot(dets["xi"] - centers[tube][0], dets["eta"] - centers[tube][1])
        assert 0.6 < np.degrees(2 * radius.max()) < 1.4      # tube field of view ~1.3 deg


def test_rows_of_pixels_run_along_xi(wafer):
    """A constant-elevation scan moves sources along xi; pixel rows must follow it."""
    sel = (wafer["bandpass"] == "f090") & (wafer["pol"] == "A")
    xy = np.c_[wafer["xi"][sel], wafer["eta"][sel]]
    dist, idx = cKDTree(xy).query(xy, k=7)
    d = xy[idx[:, 1:]] - xy[:, None]
    near = np.abs(dist[:, 1:] - PITCH) < 0.01 * PITCH
    angles = np.degrees(np.arctan2(d[..., 1], d[..., 0]))[near] % 180
    assert np.mean(np.minimum(angles, 180 - angles) < 1) > 0.3


def test_bad_names_are_refused():
    with pytest.raises(ValueError, match="unknown LAT tube"):
        fp.tube_flavor("x9")
    with pytest.raises(ValueError, match="not in tube"):
        fp.wafer_detectors("i1", "w00")


def test_documented_default_config_matches_code():
    from pathlib import Path

    from so_transients.sim.config import SimConfig, load_config

    documented = load_config(Path(__file__).parents[2] / "configs" / "sim_default.yaml")
    assert documented.to_dict() == SimConfig().to_dict()
