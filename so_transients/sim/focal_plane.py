"""SO LAT focal-plane layout: tubes, hexagonal wafers and dual-polarization dichroic pixels.

Numbers come from sotodlib's nominal hardware model (``sim_hardware.sim_nominal()``): tube slots
and their wafer slots, tube position on the LAT hex layout (``toast_hex_pos``), ``tubespace``
(359.6 mm), ``waferspace`` (128.4 mm), ``pixsize`` (5.3 mm), ``npixel`` (432 sites) and
``platescale`` (0.00495 deg/mm). The layout follows the construction of sotodlib's TOAST focal
plane simulator without needing TOAST:

* a wafer is a hexagon of three 12x12 hex-packed rhombi (432 sites); two sites are left empty for
  mechanical reasons, leaving 430 optical pixels at a pitch of 5.3 mm x 0.00495 deg/mm = 1.574';
* every pixel is dichroic (MF: f090 + f150, UHF: f220 + f280) and has two orthogonally polarized
  detectors (``A`` and ``B``) per band: 860 detectors per band per wafer;
* three wafers per tube, rotated by the tube's ``wafer_slot_angle``; tubes on a hexagonal grid of
  pitch ``tubespace``. The whole plane is rotated so that rows of pixels run along xi, the
  direction a constant-elevation scan moves a source across the array.

Output is a dict of equal-length numpy arrays, the fields of SO's ``det_info`` and
``focal_plane`` (xi, eta, gamma in radians).
"""
from __future__ import annotations

import numpy as np

from so_transients.common.angles import DEG
from so_transients.common.bands import FLAVOR_BANDS, nominal_hardware

RHOMBUS_DIM = 12
#: Sites left empty in each wafer (rhombus, row, col), as in sotodlib's TOAST focal-plane sim.
EMPTY_SITES = ((1, 5, 6), (1, 6, 4))
#: Whole-plane rotation that puts pixel rows along xi.
PLANE_ROTATION = 90 * DEG


def _rotate(x, y, angle):
    c, s = np.cos(angle), np.sin(angle)
    return c * x - s * y, s * x + c * y


def _hex_grid_position(index: int):
    """(x, y) in units of the grid pitch of position ``index`` on a hexagonal grid, ring by ring.

    Position 0 is the centre, 1-6 the first ring, 7-18 the second (sotodlib's ``toast_hex_pos``).
    """
    if index == 0:
        return 0.0, 0.0
    ring, start = 1, 1
    while index >= start + 6 * ring:
        start += 6 * ring
        ring += 1
    k = index - start
    side, step = divmod(k, ring)
    corners = [np.array([np.cos(a), np.sin(a)]) * ring for a in np.arange(6) * 60 * DEG]
    a, b = corners[side], corners[(side + 1) % 6]
    x, y = a + (b - a) * step / ring
    return float(x), float(y)


def wafer_pixels(gap: float = 0.0):
    """Pixel sites of one wafer in its own frame, in units of the pixel pitch.

    Returns (x, y, pol_angle_A, rhombus) for the 430 optical pixels. Rhombus k spans directions
    30 + 120 k and 150 + 120 k degrees from the wafer centre and is pushed out along its
    bisector by ``gap`` (the hardware's ``rhombusgap`` over ``pixsize``); polarization of
    detector A alternates between 22.5 and 67.5 degrees from row to row and turns with the
    rhombus.
    """
    xs, ys, pols, rhombi = [], [], [], []
    for k in range(3):
        theta = (30 + 120 * k) * DEG
        e1 = np.array([np.cos(theta), np.sin(theta)])
        e2 = np.array([np.cos(theta + 120 * DEG), np.sin(theta + 120 * DEG)])
        shift = gap * np.array([np.cos(theta + 60 * DEG), np.sin(theta + 60 * DEG)])
        for row in range(RHOMBUS_DIM):
            for col in range(RHOMBUS_DIM):
                if (k, row, col) in EMPTY_SITES:
                    continue
                x, y = (col + 0.5) * e1 + (row + 0.5) * e2 + shift
                xs.append(x)
                ys.append(y)
                pols.append((22.5 if row % 2 == 0 else 67.5) * DEG + 120 * k * DEG)
                rhombi.append(k)
    return np.array(xs), np.array(ys), np.array(pols), np.array(rhombi)


def pixel_pitch(wafer_slot: str) -> float:
    """Pixel pitch of a wafer on the sky (radians): pixsize x platescale."""
    hw = nominal_hardware().data
    return hw["wafer_slots"][wafer_slot]["pixsize"] * hw["telescopes"]["LAT"]["platescale"] * DEG


def tube_center(tube_slot: str):
    """(xi, eta) of a LAT tube's centre in radians."""
    hw = nominal_hardware().data
    tele = hw["telescopes"]["LAT"]
    pitch = tele["tubespace"] * tele["platescale"] * DEG
    x, y = _hex_grid_position(hw["tube_slots"][tube_slot]["toast_hex_pos"])
    return _rotate(x * pitch, y * pitch, PLANE_ROTATION)


def wafer_centers(tube_slot: str):
    """{wafer_slot: (xi, eta)} for the three wafers of a tube, in radians.

    The wafers sit at 2/sqrt(3) x half the wafer spacing from the tube centre, their flat
    edges facing each other, as in sotodlib's LAT layout.
    """
    hw = nominal_hardware().data
    tube = hw["tube_slots"][tube_slot]
    half = 0.5 * tube["waferspace"] * hw["telescopes"]["LAT"]["platescale"] * DEG
    local = [(-half, half / np.sqrt(3)), (half, half / np.sqrt(3)), (0.0, -2 * half / np.sqrt(3))]
    cx, cy = tube_center(tube_slot)
    centers = {}
    for wafer, (x, y) in zip(tube["wafer_slots"], local):
        dx, dy = _rotate(x, y, PLANE_ROTATION)
        centers[wafer] = (cx + dx, cy + dy)
    return centers


def lat_tubes(flavors=("LAT_MF", "LAT_UHF")):
    """Names of the LAT tube slots of the given flavours in sotodlib's nominal hardware."""
    hw = nominal_hardware().data
    return [name for name in hw["telescopes"]["LAT"]["tube_slots"]
            if hw["tube_slots"][name]["type"] in flavors]


def lat_layout() -> list:
    """``[(tube_slot, flavour, wafer_slots, bands)]`` of the LAT tubes the simulator knows
    (sotodlib's nominal hardware), what ``so-transients simulate --list`` prints."""
    hw = nominal_hardware().data
    return [(tube, hw["tube_slots"][tube]["type"], list(hw["tube_slots"][tube]["wafer_slots"]),
             list(FLAVOR_BANDS[hw["tube_slots"][tube]["type"]])) for tube in lat_tubes()]


def tube_flavor(tube_slot: str) -> str:
    """``LAT_MF`` or ``LAT_UHF`` (or another hardware type) for a tube slot."""
    hw = nominal_hardware().data
    if tube_slot not in hw["tube_slots"] or tube_slot[0] not in "cio":
        raise ValueError(f"unknown LAT tube slot {tube_slot!r}; known: {lat_tubes()}")
    return hw["tube_slots"][tube_slot]["type"]


def wafer_detectors(tube_slot: str, wafer_slot: str):
    """det_info and focal_plane fields of every detector of one wafer (both bands).

    Returns a dict of arrays: ``readout_id``, ``det_id``, ``tube_slot``, ``wafer_slot``,
    ``bandpass``, ``pol`` (``A``/``B``), ``pixel``, ``xi``, ``eta``, ``gamma`` (radians).
    Detectors are ordered band by band, then pixel by pixel, A before B.
    """
    hw = nominal_hardware().data
    tube = hw["tube_slots"][tube_slot]
    if wafer_slot not in tube["wafer_slots"]:
        raise ValueError(f"wafer slot {wafer_slot!r} is not in tube {tube_slot!r}: "
                         f"{tube['wafer_slots']}")
    wprops = hw["wafer_slots"][wafer_slot]
    pitch = pixel_pitch(wafer_slot)
    slot_angle = tube["wafer_slot_angle"][tube["wafer_slots"].index(wafer_slot)] * DEG
    x, y, pol_a, _ = wafer_pixels(gap=wprops["rhombusgap"] / wprops["pixsize"])
    x, y = _rotate(x * pitch, y * pitch, slot_angle + PLANE_ROTATION)
    cx, cy = wafer_centers(tube_slot)[wafer_slot]
    npix = len(x)
    rows = {k: [] for k in ("readout_id", "det_id", "tube_slot", "wafer_slot", "bandpass",
                            "pol", "pixel", "xi", "eta", "gamma")}
    for band in FLAVOR_BANDS[tube_flavor(tube_slot)]:
        for pix in range(npix):
            for pol, offset in (("A", 0.0), ("B", 90 * DEG)):
                rows["readout_id"].append(f"{wafer_slot}_{band}_{2 * pix + (pol == 'B'):04d}")
                rows["det_id"].append(f"{wafer_slot}_{band}_p{pix:03d}{pol}")
                rows["tube_slot"].append(tube_slot)
                rows["wafer_slot"].append(wafer_slot)
                rows["bandpass"].append(band)
                rows["pol"].append(pol)
                rows["pixel"].append(pix)
                rows["xi"].append(cx + x[pix])
                rows["eta"].append(cy + y[pix])
                gamma = pol_a[pix] + offset + slot_angle + PLANE_ROTATION
                rows["gamma"].append(np.mod(gamma, 2 * np.pi))
    out = {k: np.array(v) for k, v in rows.items()}
    return out


def tube_detectors(tube_slot: str, wafer_slots=None):
    """:func:`wafer_detectors` for several wafers of a tube (all three by default), concatenated."""
    hw = nominal_hardware().data
    wafers = hw["tube_slots"][tube_slot]["wafer_slots"] if wafer_slots is None else wafer_slots
    parts = [wafer_detectors(tube_slot, w) for w in wafers]
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
