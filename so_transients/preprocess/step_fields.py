"""What each transient step declares about itself, in one place: its process class's ``spec``.

A :class:`StepSpec` names the step's config dataclasses (the keys of its YAML block), the
AxisManager fields it cannot run without (``requires``: it refuses the group, naming the
missing ones) and those it uses when present (``optional``). Dotted paths name fields of
sub-AxisManagers. :func:`step_specs` reads them from sotodlib's registry, so that a new step is
its module and its registration. The steps check their input with :func:`require`, and the
injection campaign keeps exactly these fields (:func:`kept_fields`) when it cuts windows out
of a group. Standard SO fields only, besides what an earlier transient step wrote.
"""
from __future__ import annotations

from dataclasses import dataclass

from so_transients.common.pointing import BORE_Q

#: the pointing every search step reads, and what it uses of it when present
POINTING = ("timestamps", "boresight.az", "boresight.el", "focal_plane.xi", "focal_plane.eta")
POINTING_OPTIONAL = ("boresight.roll", BORE_Q, "obs_info.obs_id")


@dataclass(frozen=True)
class StepSpec:
    """A step's config dataclasses and the AxisManager fields it reads (see the module)."""

    configs: tuple = ()
    requires: tuple = ()
    optional: tuple = ()


def step_specs() -> dict:
    """``{name: StepSpec}`` of every registered step that declares one, in registration
    order (importing :mod:`so_transients.preprocess` registers them)."""
    import so_transients.preprocess  # noqa: F401
    from sotodlib.preprocess import Pipeline

    return {name: cls.spec for name, cls in Pipeline.PIPELINE.items()
            if isinstance(getattr(cls, "spec", None), StepSpec)}


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
    field the step requires (and ``extra``)."""
    missing = [p for p in step_specs()[step].requires + tuple(extra) if not has_field(aman, p)]
    if missing:
        raise ValueError(f"{step}: {GroupName(aman)} lacks {', '.join(missing)}")


def kept_fields(steps, sub_of=("flags", "transient_filter", "obs_info", "det_info",
                               "boresight", "focal_plane")) -> dict:
    """{sub-AxisManager: fields of it that ``steps`` read} for the sub-AxisManagers
    ``sub_of``; a bare name (e.g. ``det_info``) keeps all of that sub-AxisManager."""
    out, specs = {}, step_specs()
    for step in steps:
        for path in specs[step].requires + specs[step].optional:
            head, _, rest = path.partition(".")
            if head in sub_of:
                out.setdefault(head, set()).add(rest or "*")
    return out
