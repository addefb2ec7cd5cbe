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
    assert not deconvolves_time_constants(pipe(PAPER))
    as_sotodlib = [dict(s, name=s["name"].replace("transient_fourier_filter", "fourier_filter"))
                   for s in production]
    assert deconvolves_time_constants(as_sotodlib)
    without = [s for s in production
               if (s.get("process") or {}).get("filt_function") != "timeconst_filter"]
    assert not deconvolves_time_constants(without)
