"""Campaign flare placement: at a detector's pointing at the peak time, or anywhere scanned."""
from types import SimpleNamespace

import numpy as np
import pytest

from tests.conftest import load_group
from so_transients.campaign.config import Cell, Injection
from so_transients.campaign.flare_injection import draw_cell_flares
from so_transients.common.pointing import boresight_q, source_in_focal_plane
from so_transients.common.scan_geometry import detector_pitch


@pytest.fixture(scope="module")
def group_state(bright_source_dataset):
    """The fields of a prepared group that drawing flares reads, from one simulated wafer."""
    aman = load_group(bright_source_dataset)
    return SimpleNamespace(aman=aman, timestamps=np.asarray(aman.timestamps),
                           bore_q=boresight_q(aman), xi=np.asarray(aman.focal_plane.xi),
                           eta=np.asarray(aman.focal_plane.eta))


def _offset_at_peak(state, flares):
    """Angle (radians) from each flare to the nearest detector at the flare's peak sample."""
    out = []
    for f in flares:
        k = int(np.argmin(np.abs(state.timestamps - f["t_peak"])))
        xi, eta = source_in_focal_plane(state.bore_q[k:k + 1], f["ra"], f["dec"])
        out.append(np.hypot(state.xi - xi[0], state.eta - eta[0]).min())
    return np.array(out)


def test_scan_area_placement_rarely_puts_a_detector_on_the_peak(group_state):
    cell = Cell("f090", 0.5, 500.0)
    pitch = detector_pitch(group_state.xi, group_state.eta)
    at_peak = draw_cell_flares(cell, 40, [group_state], np.random.default_rng(3))
    anywhere = draw_cell_flares(cell, 40, [group_state], np.random.default_rng(3), "scan_area")
    # the default: a detector within half a pitch at the peak (1e-3 pitch: flat-sky slack)
    assert np.all(_offset_at_peak(group_state, at_peak) <= 0.501 * pitch)
    # scan_area: the same peak times, but most peaks fall far from every detector
    assert np.array_equal(at_peak["t_peak"][:1], anywhere["t_peak"][:1])
    assert np.mean(_offset_at_peak(group_state, anywhere) > 2 * pitch) > 0.8


def test_unknown_placement_is_refused():
    with pytest.raises(ValueError, match="placement"):
        Injection(placement="at_random")


def _offset_at(state, flare, t):
    k = int(np.argmin(np.abs(state.timestamps - t)))
    xi, eta = source_in_focal_plane(state.bore_q[k:k + 1], flare["ra"], flare["dec"])
    return np.hypot(state.xi - xi[0], state.eta - eta[0]).min()


def test_active_window_placement_meets_the_flare_within_its_light_curve(group_state):
    """A detector points at each flare at some moment of its active window (within half a
    pitch), and for most flares not at the peak itself."""
    cell = Cell("f090", 2.0, 500.0)
    pitch = detector_pitch(group_state.xi, group_state.eta)
    flares = draw_cell_flares(cell, 30, [group_state], np.random.default_rng(4),
                              "active_window")
    t = group_state.timestamps
    for f in flares:
        inside = t[(t >= f["t_peak"] - f["t_rise"]) & (t <= f["t_peak"] + f["t_decay"])]
        assert min(_offset_at(group_state, f, s) for s in inside) <= 0.6 * pitch
    assert np.mean(_offset_at_peak(group_state, flares) > 2 * pitch) > 0.5


def test_flare_eta_shapes_the_injected_light_curves(group_state):
    from so_transients.common.flare_model import flare_flux

    cell = Cell("f090", 0.5, 500.0)
    linear = draw_cell_flares(cell, 5, [group_state], np.random.default_rng(4))
    peaked = draw_cell_flares(cell, 5, [group_state], np.random.default_rng(4), flare_eta=3.0)
    assert np.all(linear["eta_rise"] == 1.0) and np.all(peaked["eta_decay"] == 3.0)
    f = peaked[0]
    half = f["t_peak"] - 0.25          # half-way up the rise: 1/2 linear, 1/8 with eta = 3
    ratio = flare_flux(np.array([half]), f["t_peak"], 500.0, 0.5, 0.5, 3.0, 3.0)[0] / 500.0
    assert ratio == pytest.approx(0.125)
    with pytest.raises(ValueError, match="flare_eta"):
        Injection(flare_eta=0.0)


def test_the_default_injection_keeps_a_configs_digest(tmp_path):
    from so_transients.campaign.config import CampaignConfig

    grid = {"f090": {"t_rise": [0.5], "s_peak_mjy": [500]}}
    base = CampaignConfig(grid=grid)
    assert CampaignConfig(grid=grid, injection=Injection(flare_eta=1.0)).digest() == base.digest()
    assert CampaignConfig(grid=grid, injection=Injection(flare_eta=2.0)).digest() != base.digest()
