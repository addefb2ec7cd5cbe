"""The 90 % detection threshold against the flare's duration, as the map-domain surveys quote
their sensitivity: one line per campaign, one panel per band.

    C=data/campaign_coherent_far P=data/campaign_paper_far_scored r=results
    python studies/sensitivity_timescale.py \\
      "coherent mode=$C/$r/thresholds_far.ecsv,${C}_slow/$r/thresholds_far.ecsv" \\
      "paper mode=$P/$r/thresholds_far_score.ecsv,${P}_slow/$r/thresholds_far_score.ecsv" \\
      "paper, score >= 0.5=$P/$r/thresholds_far_score0.5.ecsv,${P}_slow/$r/thresholds_far_score0.5.ecsv" \\
      --joint data/joint_bands/thresholds.ecsv --far 0.083 -o docs/results/sensitivity_timescale.png

Each argument is ``LABEL=TABLE``: a campaign's threshold table (``thresholds.ecsv``,
``thresholds_far.ecsv`` or ``thresholds_equal_rate.ecsv`` of its results folder, or
``thresholds_far_score*.ecsv`` of ``studies/score_thresholds.py``; tables of
several campaigns of one label, e.g. a grid and its slow rows, are joined when given as
``LABEL=TABLE1,TABLE2``). ``--far``: the false-alarm rate the thresholds hold, per
wafer-band-hour; the figure states it per LAT-day too (36 MF and UHF wafer-bands, 24 hours).
``--joint``: the thresholds of ``studies/joint_bands.py`` (both bands of one wafer searched
jointly, against each band alone at the same rate per wafer-hour), one panel per spectral
index beside the campaigns' bands.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from astropy.table import Table, vstack

from so_transients.campaign.figures import plot_sensitivity_timescale

LAT_WAFER_BANDS = 36      # 6 MF and UHF tubes x 3 wafers x 2 bands
JOINT_SEARCHES = {"single": "each band alone (either finds it)",
                  "joint": "both bands jointly (J)"}


def joint_curves(table: Table) -> dict:
    """The joint-band study's thresholds (``t_rise``, ``spectral_index``, ``search``,
    ``s90``, ``s90_err``) as curves of :func:`plot_sensitivity_timescale`: one per search,
    each spectral index a panel of its own ("band")."""
    curves = {}
    for search, label in JOINT_SEARCHES.items():
        rows = table[table["search"] == search]
        rows["band"] = [f"f090 & f150, index {a:+g} ($S_p$ at 93 GHz)"
                        for a in rows["spectral_index"]]
        curves[label] = rows
    return curves


def joint_rate(thresholds: Path) -> str:
    """The joint-band study's rate, from the ``backgrounds.ecsv`` beside its thresholds."""
    backgrounds = Table.read(thresholds.parent / "backgrounds.ecsv")
    single = backgrounds[backgrounds["search"] == "single"]
    rate = float(single["rate"][0])
    return (f"{rate:.3g} per wafer-band-hour = {rate * LAT_WAFER_BANDS * 24:.0f} per LAT-day, "
            f"one hour of {single['wafer'][0]}, flares injected into its S/N")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("curves", nargs="+", metavar="LABEL=TABLE[,TABLE]")
    p.add_argument("--joint", type=Path, help="thresholds.ecsv of studies/joint_bands.py")
    p.add_argument("--far", type=float, required=True,
                   help="false-alarm rate of the thresholds, per wafer-band-hour")
    p.add_argument("-o", "--out", type=Path, default=Path("sensitivity_timescale.png"))
    args = p.parse_args(argv)
    curves = {}
    for item in args.curves:
        label, _, paths = item.rpartition("=")   # a label may hold "="
        if not label or not paths:
            p.error(f"{item!r}: expected LABEL=TABLE")
        curves[label] = vstack([Table.read(path) for path in paths.split(",")],
                               metadata_conflicts="silent")   # each table its own digest
    per_day = args.far * LAT_WAFER_BANDS * 24
    note = (f"false-alarm rate {args.far:.3g} per wafer-band-hour = {per_day:.0f} per LAT-day "
            f"({LAT_WAFER_BANDS} MF and UHF wafer-bands)")
    if args.joint:
        curves.update(joint_curves(Table.read(args.joint)))
        note += f"\nthe index panels: {joint_rate(args.joint)}"
    plot_sensitivity_timescale(args.out, curves, note)
    for label, table in curves.items():
        print(label)
        table["band", "t_rise", "s90", "s90_err"].pprint(max_lines=-1)
    print(f"{note}\nwritten {args.out}")


if __name__ == "__main__":
    main()
