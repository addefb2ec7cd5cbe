"""Eq. 1 of the reference paper at chosen times."""
import numpy as np
import pytest

from so_transients.common.flare_model import active_window, flare_flux


def test_linear_flare_values():
    t = np.array([-10.0, 100 - 4, 100 - 2, 100 - 1, 100, 100 + 1, 100 + 2, 100 + 4, 1e9])
    got = flare_flux(t, t_peak=100.0, s_peak=800.0, t_rise=4.0)
    assert np.allclose(got, [0, 0, 400, 600, 800, 600, 400, 0, 0])


def test_power_law_indices_and_asymmetric_decay():
    # rise: S_p ((t + t_r - t_p) / t_r)^2 ; decay: S_p ((t_p + t_d - t) / t_d)^0.5
    got = flare_flux([9.0, 11.0, 14.0], t_peak=10.0, s_peak=100.0, t_rise=2.0, t_decay=8.0,
                     eta_rise=2.0, eta_decay=0.5)
    assert np.allclose(got, [100 * 0.5**2, 100 * (7 / 8) ** 0.5, 100 * (4 / 8) ** 0.5])


def test_window_and_bad_input():
    assert active_window(10.0, 2.0, 5.0) == (8.0, 15.0)
    assert active_window(10.0, 2.0) == (8.0, 12.0)
    with pytest.raises(ValueError):
        flare_flux([0.0], 0.0, 1.0, t_rise=0.0)
