"""What each transient step reads of an AxisManager, declared once.

``REQUIRED[step]``: fields the step cannot run without (it refuses the group, naming the
missing ones); ``OPTIONAL[step]``: fields it uses when present. Dotted paths name fields of
sub-AxisManagers. The steps check their input with :func:`require`, and the injection
campaign keeps exactly these fields (:func:`kept_fields`) when it cuts windows out of a group.
Standard SO fields only, besides what an earlier transient step wrote.
"""
from __future__ import annotations

from so_transients.common.pointing import BORE_Q

_POINTING = ("timestamps", "boresight.az", "boresight.el", "focal_plane.xi", "focal_plane.eta")
_POINTING_OPTIONAL = ("boresight.roll", BORE_Q, "obs_info.obs_id")

REQUIRED = {
    "transient_jumps": ("signal", "timestamps"),
    "transient_pca_mask": ("timestamps",),
    "transient_pca_filter": (),
    "transient_fourier_filter": ("timestamps",),
    "transient_glitches": ("timestamps",),
    "transient_filter": ("signal", "timestamps", "boresight.az", "boresight.el", "det_info"),
    "transient_find": ("transient_snr", "transient_filter.bandpass",
                       "transient_filter.beam_sigma") + _POINTING,
    "transient_cuts": ("transient_candidates", "transient_hits", "transient_snr",
                       "focal_plane.gamma", "transient_filter.beam_sigma") + _POINTING,
    "transient_significance": ("transient_candidates", "transient_snr", "transient_scan",
                               "transient_filter.sigma_amp", "transient_filter.dead",
                               "transient_filter.beam_sigma",
                               "transient_filter.bandpass") + _POINTING,
    "transient_fit": ("transient_candidates", "transient_snr", "transient_filter.bandpass",
                      "transient_filter.sigma_amp", "transient_filter.dead",
                      "transient_filter.beam_sigma", "transient_filter.fit_inflation",
                      "transient_filter.lag", "transient_filter.response") + _POINTING,
}
OPTIONAL = {
    "transient_filter": ("obs_info.obs_id", "flags"),
    "transient_find": ("det_info.wafer_slot",) + _POINTING_OPTIONAL,
    "transient_cuts": _POINTING_OPTIONAL,
    "transient_significance": _POINTING_OPTIONAL,
    "transient_fit": ("transient_hits",) + _POINTING_OPTIONAL,
}


class GroupName:
    """'obs_id (wafer, band)' of an AxisManager for messages; worked out only when shown."""

    def __init__(self, aman):
        self.aman = aman

    def __str__(self):
        aman = self.aman
        obs_id = aman.obs_info.obs_id if "obs_info" in aman else "unknown observation"
        parts = []
        if "det_info" in aman:
            for key in ("wafer_slot", "bandpass"):
                if key in aman.det_info._fields:
                    parts.append(",".join(sorted(set(map(str, aman.det_info[key])))))
        return f"{obs_id} ({', '.join(parts) or 'all detectors'})"


def has_field(aman, path):
    """Whether ``aman`` holds the field at the dotted ``path``."""
    node = aman
    for part in path.split("."):
        if not hasattr(node, "_fields") or part not in node._fields:
            return False
        node = node[part]
    return True


def require(aman, step, extra=()):
    """Raise a ValueError naming the step, the observation and group, and every missing
    field of ``REQUIRED[step]`` (and ``extra``)."""
    missing = [p for p in REQUIRED[step] + tuple(extra) if not has_field(aman, p)]
    if missing:
        raise ValueError(f"{step}: {GroupName(aman)} lacks {', '.join(missing)}")


def kept_fields(steps, sub_of=("flags", "transient_filter", "obs_info", "det_info",
                               "boresight", "focal_plane")) -> dict:
    """{sub-AxisManager: fields of it that ``steps`` read} for the sub-AxisManagers
    ``sub_of``; a bare name (e.g. ``det_info``) keeps all of that sub-AxisManager."""
    out = {}
    for step in steps:
        for path in REQUIRED[step] + OPTIONAL[step]:
            head, _, rest = path.partition(".")
            if head in sub_of:
                out.setdefault(head, set()).add(rest or "*")
    return out
