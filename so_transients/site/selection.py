"""Which observations of an ObsDb a command works on: sotodlib's own selection options
(``--query``, ``--obs-id``, ``--min-ctime``, ``--max-ctime``, as ``preprocess_tod`` takes
them), so that a site can run one night of a large ObsDb, and "missing" means missing among
the observations selected."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ObsSelection:
    query: str | None = None          # an ObsDb query, or a file listing obs_ids
    obs_id: str | None = None
    min_ctime: float | None = None    # observations starting at or after this ctime ...
    max_ctime: float | None = None    # ... and at or before this one

    @property
    def everything(self) -> bool:
        return all(v is None for v in vars(self).values())

    def preprocess_args(self) -> list:
        """The same selection as ``preprocess_tod``'s options."""
        out = []
        for key, value in vars(self).items():
            if value is not None:
                out += [f"--{key.replace('_', '-')}", str(value)]
        return out

    def obs_ids(self, context) -> set:
        """obs_ids of the context's ObsDb that the selection takes (sotodlib's
        ``get_obslist``, as the site pipeline selects them)."""
        from sotodlib.site_pipeline.utils.obsdb import get_obslist

        return {o["obs_id"] for o in get_obslist(context, query=self.query, obs_id=self.obs_id,
                                                 min_ctime=self.min_ctime,
                                                 max_ctime=self.max_ctime)}

    @classmethod
    def from_args(cls, args) -> "ObsSelection":
        return cls(*(getattr(args, k, None) for k in ("query", "obs_id", "min_ctime",
                                                        "max_ctime")))


def add_selection_arguments(parser):
    """``--query``, ``--obs-id``, ``--min-ctime``, ``--max-ctime`` on ``parser``."""
    parser.add_argument("--query", default=None,
                        help="ObsDb query (or a file of obs_ids) selecting the observations")
    parser.add_argument("--obs-id", default=None, help="one observation")
    parser.add_argument("--min-ctime", type=float, default=None,
                        help="observations starting at or after this ctime (s)")
    parser.add_argument("--max-ctime", type=float, default=None,
                        help="observations starting at or before this ctime (s)")
