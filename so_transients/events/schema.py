"""The columns of the event tables, declared once (name, dtype, unit, meaning).

* ``events``: one row per event (detections of one source joined in position and time);
* ``lightcurves``: one row per crossing and band of an event's position, in lightcurvedb's
  ``FluxMeasurement`` fields (source, time, position and uncertainties, flux, frequency,
  module) plus the TOD's own (observation, wafer, scan, detection flag, upper limit);
* ``lightcurve_fits``: one row per event and band, the paper's eq. 1 fitted;
* ``cutouts``: one row per event and band, the sky cutout of its best crossing made from the
  TOD (a FITS file with its WCS) and the detector time streams there.

Catalogue units: degrees for positions, arcsec for their errors, ctime seconds and ISO UTC
for times, mJy for fluxes. To add a column: add one :class:`Column` here and fill it where
the table is built (:mod:`so_transients.events.tables`); tables are made with
:func:`so_transients.common.candidates.typed_table`.
"""
from __future__ import annotations

from so_transients.common.candidates import Column
from so_transients.events.lightcurve_fit import FLARE_PARAMS

_E, _L, _F, _C = "events", "lightcurves", "lightcurve_fits", "cutouts"

EVENTS = (
    Column("event_id", "int", None, _E, "event number in this run, in order of first detection"),
    Column("source_id", "int", None, _E, "events at one position within source_gap_hours share "
                                         "it (lightcurvedb's source)"),
    Column("event_uuid", "str", None, _E, "the event's UUID, the same in every run that finds "
                                          "it (from its first detection) and in alerts and "
                                          "the database"),
    Column("source_uuid", "str", None, _E, "its source's UUID (from the source's first event); "
                                           "the database resolves it to its persistent source"),
    Column("name", "str", None, _E, "SOTR Jhhmmss.s+ddmmss: from the event's position"),
    Column("ra", "float", "deg", _E, "inverse-variance weighted RA of its detections"),
    Column("dec", "float", "deg", _E, "weighted Dec of its detections"),
    Column("pos_err", "float", "arcsec", _E, "one-axis statistical error of the weighted "
                                             "position (no pointing systematic)"),
    Column("t_first", "float", "s", _E, "ctime of the first detection's peak sample"),
    Column("t_last", "float", "s", _E, "ctime of the last detection's peak sample"),
    Column("t_first_utc", "str", None, _E, "t_first as ISO UTC"),
    Column("t_last_utc", "str", None, _E, "t_last as ISO UTC"),
    Column("n_detections", "int", None, _E, "detections joined (crossings x wafers x bands)"),
    Column("obs_ids", "str", None, _E, "observations with a detection (comma-separated)"),
    Column("wafers", "str", None, _E, "wafers with a detection"),
    Column("bands", "str", None, _E, "bands with a detection"),
    Column("peak_flux", "float", "mJy", _E, "brightest detection's fitted flux"),
    Column("peak_flux_err", "float", "mJy", _E, "its error"),
    Column("peak_band", "str", None, _E, "its band"),
    Column("single_band", "bool", None, _E, "detected in one band only although another band "
                                            "of the same wafers was measured"),
    Column("joint_snr", "float", None, _E, "highest S/N of a detected crossing combined with "
                                           "the other band's forced S/N at that crossing, "
                                           "(snr_a + snr_b) / sqrt(2)"),
    Column("alpha_mf", "float", None, _E, "spectral index S ~ nu^alpha, f090/f150, from "
                                          "simultaneous crossings"),
    Column("alpha_mf_err", "float", None, _E, "its error"),
    Column("alpha_uhf", "float", None, _E, "spectral index f220/f280"),
    Column("alpha_uhf_err", "float", None, _E, "its error"),
    Column("n_crossings", "int", None, _E, "light-curve points (crossings x bands measured)"),
    Column("n_upper_limits", "int", None, _E, "of which upper limits"),
    Column("note", "str", None, _E, "what could not be measured, '' if nothing"),
    Column("far", "float", "1 / h", _E, "lowest false-alarm rate of its detections, per "
                                        "wafer-band-hour (transient_significance; NaN without)"),
    Column("far_is_limit", "bool", None, _E, "that far is an upper limit (the time slides' "
                                             "resolution), not a count"),
    Column("catalogue", "str", None, _E, "catalogue of the cross-matched source (the events "
                                         "config's `catalogue`), '' if none matched"),
    Column("cat_source_id", "str", None, _E, "its id there (socat source_id, or sso_id of a "
                                             "solar-system object: a UUID in socat 0.1, an "
                                             "integer in 0.0.2 or a file), '' if none"),
    Column("cat_source_name", "str", None, _E, "its name there"),
    Column("cat_ra", "float", "deg", _E, "its RA (a solar-system object's at the event)"),
    Column("cat_dec", "float", "deg", _E, "its Dec"),
    Column("cat_separation", "float", "arcmin", _E, "distance from the event's position"),
    Column("cat_flux_ratio", "float", None, _E, "peak_flux / the catalogued flux (NaN when the "
                                                "catalogue has none)"),
    Column("cat_class", "str", None, _E, "catalogued_flare, catalogued, solar_system or new "
                                         "(so_transients.sources.crossmatch); '' when no "
                                         "catalogue was searched"),
)

LIGHTCURVES = (
    Column("event_id", "int", None, _L, "the event measured"),
    Column("source_id", "int", None, _L, "its source (lightcurvedb source_id)"),
    Column("time", "str", None, _L, "ISO UTC of the crossing's centre (lightcurvedb time)"),
    Column("ctime", "float", "s", _L, "the same as ctime"),
    Column("ra", "float", "deg", _L, "position measured at (held: the event's)"),
    Column("dec", "float", "deg", _L, "position measured at"),
    Column("ra_uncertainty", "float", "deg", _L, "the event position's one-axis error"),
    Column("dec_uncertainty", "float", "deg", _L, "the same"),
    Column("flux", "float", "mJy", _L, "beam-fit amplitude with the position held"),
    Column("flux_err", "float", "mJy", _L, "its error (the group's measured error scale)"),
    Column("frequency", "int", "GHz", _L, "band as lightcurvedb's integer frequency"),
    Column("module", "str", None, _L, "optics tube (det_info tube_slot)"),
    Column("obs_id", "str", None, _L, "observation"),
    Column("wafer_slot", "str", None, _L, "wafer"),
    Column("bandpass", "str", None, _L, "band (det_info bandpass)"),
    Column("scan", "int", None, _L, "scan within the observation (as transient_find counts)"),
    Column("detected", "bool", None, _L, "a detection of the event is at this crossing"),
    Column("snr", "float", None, _L, "flux / flux_err"),
    Column("upper_limit", "float", "mJy", _L, "max(flux, 0) + k flux_err where snr < "
                                              "detect_snr, else NaN"),
    Column("offset", "float", "mJy", _L, "fitted constant C"),
    Column("n_fit_dets", "int", None, _L, "detectors fitted"),
    Column("chi2_red", "float", None, _L, "reduced chi^2 of the forced fit"),
)

_PARAM_UNITS = {"s_peak": "mJy", "t_peak": "s", "t_rise": "s", "t_decay": "s",
                "eta_rise": None, "eta_decay": None}
LIGHTCURVE_FITS = (
    Column("event_id", "int", None, _F, "the event"),
    Column("bandpass", "str", None, _F, "band fitted"),
    *[c for name in FLARE_PARAMS for c in (
        Column(name, "float", _PARAM_UNITS[name], _F, f"eq. 1 {name}"),
        Column(f"{name}_err", "float", _PARAM_UNITS[name], _F, f"error of {name} (NaN: held)"))],
    Column("chi2_red", "float", None, _F, "reduced chi^2"),
    Column("n_points", "int", None, _F, "light-curve points fitted"),
    Column("fit_ok", "bool", None, _F, "the fit converged with finite errors"),
)

CUTOUTS = (
    Column("event_id", "int", None, _C, "the event"),
    Column("event_uuid", "str", None, _C, "its UUID (as in events, alerts and the database)"),
    Column("source_uuid", "str", None, _C, "its source's UUID"),
    Column("bandpass", "str", None, _C, "band"),
    Column("obs_id", "str", None, _C, "observation of the crossing"),
    Column("wafer_slot", "str", None, _C, "wafer of the crossing"),
    Column("ctime", "float", "s", _C, "the crossing's centre: the event's highest forced S/N "
                                      "in this band"),
    Column("time", "str", None, _C, "the same as ISO UTC (lightcurvedb Cutout time)"),
    Column("frequency", "int", "GHz", _C, "band as lightcurvedb's integer frequency"),
    Column("flux", "float", "mJy", _C, "forced flux at that crossing"),
    Column("snr", "float", None, _C, "its S/N"),
    Column("beam_fwhm", "float", "arcmin", _C, "the band's beam FWHM (the detectors' median)"),
    Column("peak_ra", "float", "deg", _C, "RA of the cutout's brightest pixel"),
    Column("peak_dec", "float", "deg", _C, "Dec of the cutout's brightest pixel"),
    Column("peak_offset", "float", "arcmin", _C, "that pixel's distance from the event's "
                                                 "position"),
    Column("file", "str", None, _C, "FITS file of the cutout, relative to the events folder: "
                                    "the binned filtered amplitude (mJy) with its WCS, and "
                                    "its weights (1/mJy^2) in HDU WEIGHT"),
    Column("streams", "str", None, _C, "NPZ file of the detector time streams of its "
                                       "crossings at the detection S/N (at least this one): "
                                       "so_transients.events.cutouts.crossings_of"),
)
