"""What each group lost on the way: detectors the site pipeline's steps removed, detectors
``transient_filter`` could not use and why, and samples it could not search.

Read from the archive alone: every saved step stores a ``valid`` range per detector, so the
detectors a step saw are those valid in its output, and the steps between two saved ones
removed the difference (sotodlib's ``select`` of ``noise``, for example).
``transient_filter`` stores why it left each detector out (``excluded``,
:data:`so_transients.detect.matched_filter.EXCLUDED`) and the fraction of each detector's
samples that were not finite or masked (``masked_fraction``).
"""
from __future__ import annotations

import logging

import numpy as np
from astropy.table import Table
from sotodlib import core

from so_transients.detect.health import health_warnings, weight_health
from so_transients.detect.matched_filter import EXCLUDED, EXCLUDED_NAMES
from so_transients.site.results import archive_entries
from so_transients.site.pipeline import archive_index

log = logging.getLogger(__name__)

FILTER = "transient_filter"


def _seen(field, ndet):
    """Detectors valid in a saved step's output (all of them when it has no ``valid``)."""
    if "valid" not in field._fields:
        return np.ones(ndet, bool)
    valid = field.valid
    mask = valid.mask() if hasattr(valid, "mask") else np.asarray(valid, bool)
    return np.asarray(mask).any(axis=1)


def proc_losses(proc) -> dict:
    """One group's losses from its archived ``proc`` AxisManager."""
    ndet = proc.dets.count
    steps = [name for name in proc._fields
             if isinstance(proc[name], core.AxisManager) and "dets" in proc[name]._axes]
    removed, before, previous = [], np.ones(ndet, bool), "the start"
    for name in steps:
        seen = _seen(proc[name], ndet) & before
        if np.sum(before & ~seen):
            removed.append(f"{int(np.sum(before & ~seen))} between {previous} and {name}")
        before, previous = seen, name
        if name == FILTER:
            break
    out = {"n_dets": ndet, "removed_upstream": int(ndet - before.sum()) if FILTER in steps
           else 0, "upstream_steps": "; ".join(removed)}
    if FILTER in steps:
        f = proc[FILTER]
        reached = _seen(f, ndet)
        code = (np.asarray(f.excluded) if "excluded" in f._fields
                else np.where(np.asarray(f.dead, bool), 1, 0))[reached]
        for k, name in EXCLUDED_NAMES.items():
            out[f"excluded_{name}"] = int(np.sum(code == k))
        used = reached.copy()
        used[reached] = code == 0
        out["used"] = int(used.sum())
        out["jumps_removed"] = int(np.sum(np.asarray(f.n_jumps)[used])) \
            if "n_jumps" in f._fields else 0
        if "transient_jumps" in steps and "n_jumps" in proc["transient_jumps"]._fields:
            out["jumps_removed"] += int(np.sum(np.asarray(proc["transient_jumps"].n_jumps)[used]))
        health = weight_health(np.asarray(f.sigma_amp), used)
        out.update(n_eff=health["n_eff"], eff_fraction=health["eff_fraction"],
                   max_weight_share=health["max_weight_share"],
                   health="; ".join(health_warnings(health)))
        masked = (np.asarray(f.masked_fraction) if "masked_fraction" in f._fields
                  else np.zeros(ndet))
        out["masked_sample_fraction"] = float(np.mean(masked[used])) if used.any() else 1.0
    else:
        out["used"] = 0
        out["masked_sample_fraction"] = np.nan
    out["lost_fraction"] = 1.0 - out["used"] / ndet if ndet else 1.0
    return out


def group_losses(archive_or_config, max_lost=0.3, obs_ids=None) -> Table:
    """One row per archived group (obs_id, its tags, :func:`proc_losses`); a warning naming
    the observation, the group and the reasons for each that lost more than ``max_lost`` of
    its detectors (of ``obs_ids`` only, when given)."""
    rows = []
    for obs_id, tags, filename, dataset in archive_entries(archive_index(archive_or_config)):
        if obs_ids is not None and obs_id not in obs_ids:
            continue
        proc = core.AxisManager.load(filename, dataset)
        row = {"obs_id": obs_id, "group": "/".join(str(v) for v in tags.values()),
               **proc_losses(proc)}
        if row.get("health"):
            log.warning("%s %s: %s: fluxes and positions may be wrong", obs_id, row["group"],
                        row["health"])
        if row["lost_fraction"] > max_lost:
            log.warning("%s %s: %d of %d detectors not used (%.0f %%): %s", obs_id, row["group"],
                        row["n_dets"] - row["used"], row["n_dets"], 100 * row["lost_fraction"],
                        describe(row))
        rows.append(row)
    names = list(dict.fromkeys(k for r in rows for k in r))
    table = Table(rows=[[r.get(k, 0) for k in names] for r in rows] or None, names=names)
    table.meta["comments"] = [
        "removed_upstream: detectors the standard steps removed before transient_filter",
        "excluded_*: detectors transient_filter did not use, by reason (EXCLUDED)",
        "masked_sample_fraction: mean over used detectors of the samples not searched",
        "jumps_removed: readout jumps transient_jumps and transient_filter removed from the "
        "used detectors",
        "n_eff: effective number of detectors, (sum w)^2 / sum w^2 with w = 1 / sigma_amp^2; "
        "eff_fraction: n_eff / used; max_weight_share: the heaviest detector's share",
        "health: what is out of range (so_transients.detect.health), '' when healthy",
        "lost_fraction: detectors not used, of the group's"]
    return table


def describe(row) -> str:
    """The reasons of a :func:`group_losses` row, in words."""
    parts = [f"{row['removed_upstream']} removed by the standard steps"
             + (f" ({row['upstream_steps']})" if row.get("upstream_steps") else "")]
    parts += [f"{row['excluded_' + name]} {EXCLUDED[k]}" for k, name in EXCLUDED_NAMES.items()
              if row.get("excluded_" + name)]
    return ", ".join(parts)


def report(table: Table) -> str:
    """One line per group: detectors used, what removed the others, samples not searched."""
    lines = []
    for row in table:
        row = dict(zip(table.colnames, row))
        lines.append(f"  {row['obs_id']} {row['group']}: {row['used']} of {row['n_dets']} "
                     f"detectors used ({describe(row)}); "
                     f"{100 * row['masked_sample_fraction']:.2g} % of their samples masked, "
                     f"{row.get('jumps_removed', 0)} readout jumps removed; effective "
                     f"number of detectors {row.get('n_eff', np.nan):.0f}"
                     + (f" -- {row['health']}" if row.get("health") else ""))
    return "\n".join(lines)
