"""The sensitivity-against-timescale figure draws every campaign's 90 % thresholds, each band
and each campaign alike on every panel."""
import matplotlib.image as mpimg
import numpy as np
from astropy.table import Table

from so_transients.campaign.figures import plot_sensitivity_timescale, sensitivity_timescale_figure


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


def test_panels_in_the_curves_order_on_one_scale_each_curve_one_colour():
    joint = Table({"band": ["f090 & f150, index -1"] * 2 + ["f090 & f150, index +2"] * 2,
                   "t_rise": [1.0, 150.0] * 2, "s90": [380.0, 240.0, 210.0, 130.0],
                   "s90_err": [20.0, 8.0, 10.0, 5.0]})
    fig = sensitivity_timescale_figure({"coherent": _table(0.75), "paper": _table(1.0),
                                        "joint": joint}, note="a\nb")
    axes = fig.axes
    assert [ax.get_title() for ax in axes] == ["f090", "f150", "f090 & f150, index -1",
                                               "f090 & f150, index +2"]
    assert {ax.get_ylim() for ax in axes} == {(0.0, 1.05 * 510.0)}    # the highest s90 + err
    assert len({ax.get_xlim() for ax in axes}) == 1
    colour = {}
    for ax in axes:
        for curve in ax.containers:              # one error-bar container per curve
            colour.setdefault(curve.get_label(), set()).add(curve.lines[0].get_color())
    assert set(colour) == {"coherent", "paper", "joint"}
    assert all(len(c) == 1 for c in colour.values())
    assert len({c.pop() for c in colour.values()}) == 3
