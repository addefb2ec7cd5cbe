"""The campaign reads the shipped configs' standard steps by what they run, sotodlib's steps or
their chunked equivalents alike."""
import yaml

from so_transients.campaign.noise import deconvolves_time_constants
from so_transients.site.pipeline import PAPER, PRODUCTION


def pipe(path):
    return yaml.safe_load(path.read_text())["process_pipe"]


def test_the_time_constant_deconvolution_is_recognised_under_either_name():
    production = pipe(PRODUCTION)
    assert deconvolves_time_constants(production)
    assert deconvolves_time_constants(pipe(PAPER))   # the same steps for real detectors
    as_sotodlib = [dict(s, name=s["name"].replace("transient_fourier_filter", "fourier_filter"))
                   for s in production]
    assert deconvolves_time_constants(as_sotodlib)
    without = [s for s in production
               if (s.get("process") or {}).get("filt_function") != "timeconst_filter"]
    assert not deconvolves_time_constants(without)


def test_both_shipped_configs_run_the_standard_steps_for_real_detectors():
    """The paper config runs the production config's standard steps, in the same order and
    with the same settings, before its own search: without readout-jump removal and the
    time-constant deconvolution it made 1.3 false detections per wafer-band-hour on drawn
    real wafers and put crossings up to 0.3' along the scan (docs/results/drawn_wafers.md)."""
    def standard(path):
        steps = pipe(path)
        return steps[:[s["name"] for s in steps].index("transient_filter")]
    assert standard(PAPER) == standard(PRODUCTION)
