"""An alert record as a VOEvent 2.0 packet (IVOA Recommendation, 2011).

``role`` is ``observation`` for an alert of SO data (tense ``current``) and ``test`` for a
simulation (``test`` and ``injection``). Who: the author's IVORN and the alert's creation
time; What: the record's numeric and text fields as Params (units and UCDs where they have
them); WhereWhen: the position (ICRS, degrees, error radius) at the trigger time; Why: the
cross-match class as the inference; Citations: the alert this one follows (``followup`` for a
subsequent alert, ``supersedes`` for an update, ``retraction``).
"""
from __future__ import annotations

import xml.etree.ElementTree as ET

NS = "http://www.ivoa.net/xml/VOEvent/v2.0"
XSI = "http://www.w3.org/2001/XMLSchema-instance"
AUTHOR = "ivo://org.simonsobs/so_transients"
ROLE = {"current": "observation", "test": "test", "injection": "test"}
CITE = {"subsequent": "followup", "update": "supersedes", "retraction": "retraction"}
#: record field -> (unit, UCD) of its Param
PARAMS = {
    "alert_tense": (None, None), "alert_type": (None, None), "record_number": (None, None),
    "event_name": (None, "meta.id"), "snr": (None, "stat.snr"), "far": ("Hz", None),
    "far_is_upper_limit": (None, None),
    "flux_density_mjy": ("mJy", "phot.flux.density"),
    "flux_density_error_mjy": ("mJy", "stat.error;phot.flux.density"),
    "flux_density": ("erg/cm2/s/Hz", "phot.flux.density"),
    "flux_density_spectral_point": ("MHz", "em.freq"), "peak_band": (None, "instr.bandpass"),
    "spectral_index": (None, "spect.index"), "spectral_index_error": (None, "stat.error"),
    "spectral_index_bands": (None, None), "duration": ("s", "time.duration"),
    "duration_error": ("s", "stat.error;time.duration"),
    "detection_span": ("s", "time.interval"), "last_detection_time": (None, "time.end"),
    "obs_ids": (None, "obs.id"), "wafers": (None, "instr.det"), "bands": (None, None),
    "crossmatch_class": (None, "src.class"), "known_source": (None, "meta.id.cross"),
    "known_source_separation": ("arcmin", "pos.angDistance"), "flux_ratio": (None, None),
    "update_message": (None, "meta.note"),
}


def ivorn(record) -> str:
    return f"{AUTHOR}#{record['id']}-{record['record_number']:02d}"


def _value(value) -> str:
    return ",".join(map(str, value)) if isinstance(value, list) else str(value)


def to_voevent(record: dict) -> str:
    """The VOEvent 2.0 XML of an alert record."""
    ET.register_namespace("voe", NS)
    root = ET.Element(f"{{{NS}}}VOEvent", {
        "version": "2.0", "role": ROLE[record["alert_tense"]], "ivorn": ivorn(record),
        f"{{{XSI}}}schemaLocation": f"{NS} http://www.ivoa.net/xml/VOEvent/VOEvent-v2.0.xsd"})
    who = ET.SubElement(root, "Who")
    ET.SubElement(who, "AuthorIVORN").text = AUTHOR
    ET.SubElement(who, "Date").text = record["alert_datetime"].rstrip("Z")
    author = ET.SubElement(who, "Author")
    ET.SubElement(author, "shortName").text = f"{record['mission']} {record['instrument']}"
    what = ET.SubElement(root, "What")
    for name, (unit, ucd) in PARAMS.items():
        if name in record:
            attrs = {"name": name, "value": _value(record[name])}
            attrs.update({k: v for k, v in (("unit", unit), ("ucd", ucd)) if v})
            ET.SubElement(what, "Param", attrs)
    if "ra" in record:
        _where_when(root, record)
        why = ET.SubElement(root, "Why")
        inference = ET.SubElement(why, "Inference")
        ET.SubElement(inference, "Name").text = record.get("known_source", record["event_name"])
        ET.SubElement(inference, "Concept").text = \
            f"millimetre transient: {record['crossmatch_class'] or 'not cross-matched'}"
    if record.get("supersedes"):
        citations = ET.SubElement(root, "Citations")
        previous = dict(id=record["id"], record_number=record["record_number"] - 1)
        ET.SubElement(citations, "EventIVORN", {"cite": CITE[record["alert_type"]]}).text = \
            ivorn(previous)
        ET.SubElement(citations, "Description").text = record["update_message"]
    ET.indent(root)
    return ET.tostring(root, encoding="unicode", xml_declaration=True)


def _where_when(root, record):
    location = ET.SubElement(ET.SubElement(root, "WhereWhen"), "ObsDataLocation")
    ET.SubElement(location, "ObservatoryLocation", {"id": "GEOLUN"})
    observation = ET.SubElement(location, "ObservationLocation")
    ET.SubElement(observation, "AstroCoordSystem", {"id": "UTC-ICRS-GEO"})
    coords = ET.SubElement(observation, "AstroCoords", {"coord_system_id": "UTC-ICRS-GEO"})
    instant = ET.SubElement(ET.SubElement(coords, "Time", {"unit": "s"}), "TimeInstant")
    ET.SubElement(instant, "ISOTime").text = record["trigger_time"].rstrip("Z")
    position = ET.SubElement(coords, "Position2D", {"unit": "deg"})
    ET.SubElement(position, "Name1").text = "RA"
    ET.SubElement(position, "Name2").text = "Dec"
    value = ET.SubElement(position, "Value2")
    ET.SubElement(value, "C1").text = repr(record["ra"])
    ET.SubElement(value, "C2").text = repr(record["dec"])
    ET.SubElement(position, "Error2Radius").text = repr(record["ra_dec_error"])
