"""The sensitivity-against-timescale figure draws every campaign's 90 % thresholds."""
import matplotlib.image as mpimg
import numpy as np
from astropy.table import Table

from so_transients.campaign.figures import plot_sensitivity_timescale


def _table(scale):
    t_rise = [0.5, 1.0, 5.0, 30.0]
    return Table({"band": ["f090"] * 4 + ["f150"] * 4, "t_rise": t_rise * 2,
                  "s90": scale * np.array([350, 290, 240, 215, 500, 390, 320, np.nan]),
                  "s90_err": np.full(8, 10.0)})


def test_one_panel_per_band_and_a_line_per_campaign(tmp_path):
    out = tmp_path / "sens.png"
    plot_sensitivity_timescale(out, {"coherent": _table(0.75), "paper": _table(1.0)},
                               note="far 0.083 per wafer-band-hour")
    image = mpimg.imread(out)
    assert image.shape[1] > 1.8 * image.shape[0]          # two panels side by side
    assert image[..., :3].std() > 0.05                     # something drawn
