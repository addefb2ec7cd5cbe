"""The candidate schema: every column a transient step produces, declared once.

A candidate is one crossing of one wafer-band group by a possible source. ``transient_find``
creates the rows, ``transient_cuts`` and ``transient_fit`` add columns; each column is declared
here with its dtype, unit, meaning and the step that fills it. The cores return plain dicts of
arrays keyed by these names, the preprocess steps store them unchanged (in ``aman`` on the
``transient_cand`` axis, in the archive on the detector axis, :mod:`so_transients.preprocess.slot_storage`),
and :mod:`so_transients.site.results` and the campaign read them back by the same names. The tables
people read take each column's unit and description from here.

To add a column: add one :class:`Column` below and fill it in the step's core function.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from astropy.table import Table
from sotodlib import core

CAND_AXIS = "transient_cand"
HIT_AXIS = "transient_hit"
STEPS = ("transient_find", "transient_cuts", "transient_significance", "transient_fit")


@dataclass(frozen=True)
class Column:
    name: str
    kind: str            # "int", "float", "bool" or "str" (strings have no fixed width)
    unit: str | None
    step: str            # the step that fills it
    description: str
    saved: bool = True   # stored in the preprocess archive and in the catalogue
    missing: object = None   # value where the step did not run or reach (None: by kind)

    @property
    def dtype(self):
        return {"int": np.int64, "float": np.float64, "bool": bool, "str": str}[self.kind]

    @property
    def fill(self):
        """Value of the column for a candidate the step did not reach."""
        if self.missing is not None:
            return self.missing
        return {"int": -1, "float": np.nan, "bool": False, "str": ""}[self.kind]


_F, _C, _S, _T = STEPS
SCHEMA = (
    Column("cand_id", "int", None, _F, "candidate number within its group (wafer x band)"),
    Column("bandpass", "str", None, _F, "band of the detectors (det_info bandpass)"),
    Column("wafer_slot", "str", None, _F, "wafer of the detector with the highest S/N"),
    Column("scan", "int", None, _F, "scan (sweep between turnarounds) within the observation"),
    Column("direction", "int", None, _F, "scan direction in azimuth: +1 or -1"),
    Column("cluster_ra", "float", "rad", _F, "mean RA of the clustered S/N >= threshold samples"),
    Column("cluster_dec", "float", "rad", _F, "mean Dec of the clustered samples"),
    Column("t_median", "float", "s", _F, "median ctime of the clustered samples"),
    Column("t_start", "float", "s", _F, "first ctime of the clustered samples"),
    Column("t_stop", "float", "s", _F, "last ctime of the clustered samples"),
    Column("t_peak", "float", "s", _F, "ctime of the clustered sample with the highest S/N"),
    Column("snr_max", "float", None, _F, "highest matched-filter S/N of the cluster"),
    Column("n_samples", "int", None, _F, "samples in the cluster"),
    Column("n_dets", "int", None, _F, "distinct detectors in the cluster"),
    Column("peak_det", "int", None, _F, "index (in the group) of the highest-S/N detector",
           saved=False),
    Column("map_z", "float", None, _F, "coherent mode: Z of the map maximum, in units of the "
                                       "scan's measured spread (NaN in paper mode)"),
    Column("n_crossings", "int", None, _F, "crossings whose coherent Z map_z sums: more than "
                                           "1 for a sweep stack (coherent mode), else 1"),
    Column("joint_z", "float", None, _F, "joint_bands: the joint-band statistic J of the map "
                                         "maximum (both bands of the wafer at the best "
                                         "spectral index; NaN without)"),
    Column("spectral_index", "float", None, _F, "joint_bands: the spectral index alpha (S "
                                                "proportional to nu^alpha) that maximises J"),
    Column("joint_id", "int", None, _F, "joint_bands: number shared by the two bands' "
                                        "candidates of one joint maximum (-1: none)"),
    Column("band_correlation", "float", None, _F, "joint_bands: correlation of the two bands' "
                                                  "maps in the candidate's scan (their shared "
                                                  "residual atmosphere)"),
    Column("pass_n_dets", "bool", None, _C, "enough detectors (min_dets)"),
    Column("pass_aspect_ratio", "bool", None, _C, "detectors form a line along the scan"),
    Column("pass_time_order", "bool", None, _C, "hit times follow a source drifting across"),
    Column("pass_sidelobe", "bool", None, _C, "no much stronger signal of opposite sign nearby"),
    Column("pass_known_source", "bool", None, _C, "not at a known source's position"),
    Column("aspect_ratio", "float", None, _C, "focal-plane extent along / across the scan"),
    Column("time_rms", "float", "s", _C, "robust rms of peak times about the drift model"),
    Column("instant_rms", "float", "s", _C, "robust rms of peak times about one instant"),
    Column("opposite_snr", "float", None, _C, "most negative S/N of the candidate's detectors "
                                              "within sidelobe_window"),
    Column("pol_fraction", "float", None, _C, "largest fraction of detectors sharing one "
                                              "polarization orientation"),
    Column("pol_flag", "bool", None, _C, "mostly one polarization orientation (not a cut)"),
    Column("cut_reason", "str", None, _C, "first cut failed, '' if none"),
    Column("passed", "bool", None, _C, "passed every cut"),
    Column("coherent_snr", "float", None, _S, "coherent statistic Z of the crossing at the "
                                               "candidate (optional step)"),
    Column("coherent_chi2", "float", None, _S, "chi-squared of that maximum's detector groups "
                                                "(bins - 1 degrees of freedom for a source "
                                                "crossing; NaN for a stack)"),
    Column("coherent_consistent", "bool", None, _S, "passes transient_find's chi-squared test "
                                                    "(far then ranks it among the background "
                                                    "maxima that pass it)", missing=True),
    Column("far", "float", "1 / h", _S, "false alarms per wafer-band-hour with Z at least "
                                        "this large: the higher of far_slides and "
                                        "far_inverted"),
    Column("far_slides", "float", "1 / h", _S, "far from the time slides' maxima"),
    Column("far_inverted", "float", "1 / h", _S, "far from the sign-inverted data's maxima "
                                                 "(counted, or beyond tail_from its tail "
                                                 "model where higher)"),
    Column("far_is_limit", "bool", None, _S, "far is an upper limit, not a count: no time "
                                             "slide reached this Z, so far is the slides' "
                                             "resolution (half a false alarm in their live "
                                             "time) and the sign-inverted data give no more"),
    Column("pass_far", "bool", None, _S, "far <= max_far (True without the step or max_far)",
           missing=True),
    Column("flux", "float", "mJy", _T, "fitted amplitude A0 of the beam model"),
    Column("flux_err", "float", "mJy", _T, "error of flux (measured error scale applied)"),
    Column("ra", "float", "rad", _T, "position: the fitted one where the fit converged, "
                                     "else the cluster mean"),
    Column("dec", "float", "rad", _T, "position (see ra)"),
    Column("ra_err", "float", "rad", _T, "error of the fitted RA, along RA on the sky"),
    Column("dec_err", "float", "rad", _T, "error of the fitted Dec"),
    Column("offset", "float", "mJy", _T, "fitted constant C of the beam model"),
    Column("offset_err", "float", "mJy", _T, "error of offset"),
    Column("snr_fit", "float", None, _T, "flux / flux_err"),
    Column("snr_joint", "float", None, _T, "joint_bands: both bands' fitted fluxes combined at "
                                           "spectral_index with their band_correlation, the "
                                           "S/N of the flux at the first band's frequency "
                                           "(NaN: not a joint pair, or a band's fit failed)"),
    Column("chi2_red", "float", None, _T, "reduced chi^2 of the fit"),
    Column("n_fit_samples", "int", None, _T, "samples fitted"),
    Column("n_fit_dets", "int", None, _T, "detectors fitted"),
    Column("fit_ok", "bool", None, _T, "the fit converged with finite errors"),
    Column("error_scale", "float", None, _T, "measured factor applied to the fit's errors"),
    Column("moving", "bool", None, _T, "its group's detections at this source move across "
                                        "scans (a planet, asteroid or satellite)"),
    Column("motion_rate", "float", "arcmin / min", _T, "rate of that motion (NaN: the fit "
                                                       "was not significant or stood alone)"),
    Column("pass_peak_ratio", "bool", None, _T, "snr_max <= max_peak_ratio x snr_fit (a "
                                                 "glitch residue's one detector is far brighter "
                                                 "than the fitted source could make it)"),
    Column("split_sigma", "float", None, _T, "the beam fits of two halves of the detectors "
                                             "(dealt alternately across the scan) differ by "
                                             "this many errors in position or flux, floors "
                                             "included (NaN: not significant or not measured)"),
    Column("pass_split", "bool", None, _T, "split_sigma <= max_split_sigma: the data support "
                                           "the fitted position and flux (a fit pulled by a "
                                           "few detectors does not pass)", missing=True),
    Column("duplicate_of", "int", None, _T, "cand_id of the detection of the same crossing "
                                            "(scan and band, fitted within a beam FWHM) with "
                                            "the higher S/N that this significant fit "
                                            "repeats; -1: none"),
    Column("real_score", "float", None, _T, "probability that the fitted candidate is a real "
                                            "source rather than an artefact, from the "
                                            "score_model (NaN: no model, or not fitted)"),
    Column("pass_score", "bool", None, _T, "real_score >= min_real_score (True without a cut)",
           missing=True),
    Column("detected", "bool", None, _T, "fit_ok, snr_fit (or, for the member of a joint "
                                          "pair with the higher snr_fit, snr_joint) >= min_snr, "
                                          "pass_peak_ratio, pass_split, "
                                          "pass_far, pass_score, not moving and not a "
                                          "duplicate"),
)
BY_NAME = {c.name: c for c in SCHEMA}

#: Samples of the clusters (``aman.transient_hits``), read by the cuts and the plots.
HIT_COLUMNS = {"cand": np.int64, "det": np.int64, "samp": np.int64, "snr": np.float32,
               "ra": np.float64, "dec": np.float64}


#: ``transient_find`` columns only the coherent mode's ``joint_bands`` fills: every other
#: search gives them their missing value (:func:`fill_missing`).
JOINT_FIND_COLUMNS = ("joint_z", "spectral_index", "joint_id", "band_correlation")


def fill_missing(values: dict, names, n) -> dict:
    """``values`` with each column of ``names`` it lacks at its missing value (``n`` rows)."""
    for name in names:
        if name not in values:
            column = BY_NAME[name]
            values[name] = np.full(n, column.fill, column.dtype)
    return values


def columns(step=None, saved=False):
    """The schema's columns filled by ``step`` (all steps by default), optionally only saved ones."""
    return [c for c in SCHEMA if (step is None or c.step == step) and (c.saved or not saved)]


def names(step=None, saved=False):
    return [c.name for c in columns(step, saved)]


def empty(step=None) -> dict:
    """Zero-length columns of ``step`` (every step by default)."""
    return {c.name: np.zeros(0, c.dtype) for c in columns(step)}


def empty_hits() -> dict:
    return {name: np.zeros(0, dtype) for name, dtype in HIT_COLUMNS.items()}


def check(values: dict, step):
    """Raise unless ``values`` holds exactly the columns of ``step``, each one-dimensional."""
    expected = set(names(step))
    if set(values) != expected:
        raise ValueError(f"{step} produced columns {sorted(set(values) ^ expected)} not "
                         f"matching the candidate schema")
    lengths = {len(np.asarray(v)) for v in values.values()}
    if len(lengths) > 1:
        raise ValueError(f"{step}: columns of different lengths {sorted(lengths)}")
    return values


def by_band(cands: dict, hits: dict, evaluate, step):
    """Columns of ``step`` for every candidate: ``evaluate(band, sel, cands, hits)`` is called
    with each band's candidate indices ``sel``, its candidates and their hits (renumbered
    within the band), and the parts are reassembled."""
    n = len(cands["bandpass"])
    parts = []
    for band in np.unique(cands["bandpass"]):
        sel = np.flatnonzero(cands["bandpass"] == band)
        mine = np.isin(hits["cand"], sel)
        sub_hits = {k: v[mine] for k, v in hits.items()}
        sub_hits["cand"] = np.searchsorted(sel, sub_hits["cand"])
        parts.append((sel, evaluate(band, sel, {k: v[sel] for k, v in cands.items()}, sub_hits)))
    if not parts:
        return empty(step)
    out = {}
    for name in parts[0][1]:
        dtype = np.result_type(*[np.asarray(p[name]).dtype for _, p in parts])
        out[name] = np.zeros(n, dtype)
        for sel, part in parts:
            out[name][sel] = part[name]
    return out


def to_aman(values: dict, axis_name, n) -> core.AxisManager:
    """An AxisManager holding 1-d ``values`` (each of length ``n``) on a new IndexAxis.

    Equivalent to wrapping the columns one by one, in one step: each ``wrap`` merges, and a
    merge restricts every field already present, so a catalogue of k columns would cost k^2
    field restrictions (a third of a campaign's search time). The columns are assigned exactly
    as ``AxisManager.wrap`` fills the helper it then merges.
    """
    out = core.AxisManager(core.IndexAxis(axis_name, n))
    for name, value in values.items():
        value = np.asarray(value)
        if value.ndim != 1 or len(value) != n:
            raise ValueError(f"column {name!r} has shape {value.shape}, expected ({n},)")
        out._fields[name] = value
        out._assignments[name] = [axis_name]
    return out


def add_to_aman(sub: core.AxisManager, values: dict, axis_name):
    """Add (or replace) ``values`` on axis ``axis_name`` of ``sub`` in one merge (a wrap per
    column would restrict every field of ``sub`` once per column)."""
    for name in [k for k in values if k in sub._fields]:
        sub.move(name, None)
    sub.merge(to_aman(values, axis_name, sub[axis_name].count), restrict_in_place=True)


def from_aman(sub: core.AxisManager, axis_name) -> dict:
    """The columns of ``sub`` on ``axis_name``, as a dict of arrays."""
    return {k: np.asarray(sub[k]) for k in sub._fields if sub._assignments[k] == [axis_name]}


def typed_table(cols, rows: dict) -> Table:
    """An astropy Table with every column of ``cols`` (missing ones filled with the column's
    fill value), each with its dtype, unit and description."""
    n = len(next(iter(rows.values()))) if rows else 0
    out = Table()
    for col in cols:
        values = np.asarray(rows[col.name]) if col.name in rows else np.full(n, col.fill)
        out[col.name] = values.astype(col.dtype) if col.kind != "str" else values.astype(str)
        out[col.name].unit = col.unit
        out[col.name].description = col.description
    return out


def table(rows: dict, first=()) -> Table:
    """An astropy Table of candidate ``rows``, every schema column present (missing ones
    filled), each with its unit and description; ``first``: extra columns (e.g. ``obs_id``)
    put before the schema's, with their values in ``rows``."""
    out = typed_table(columns(saved=True), rows)
    for k, name in enumerate(first):
        out.add_column(rows[name], name=name, index=k)
    for name in [k for k in rows if k not in out.colnames and k not in BY_NAME]:
        out[name] = rows[name]
    return out


def markdown() -> str:
    """The schema as a Markdown table (``so-transients schema``); the documentation's table is
    generated from the same schema by the ``candidate-columns`` directive of
    ``docs/_ext/step_docs.py``."""
    lines = ["| column | step | unit | meaning |", "| --- | --- | --- | --- |"]
    for col in columns(saved=True):
        lines.append(f"| `{col.name}` | `{col.step}` | {col.unit or ''} | {col.description} |")
    return "\n".join(lines)

