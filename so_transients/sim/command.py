"""``so-transients simulate [CONFIG]``: SO LAT observations simulated into a sotodlib dataset
(``--list``: the tubes, wafers and bands it knows). Built like a sotodlib site-pipeline
element (:func:`get_parser`, :func:`main`)."""
from __future__ import annotations

import argparse
import sys
import time


def get_parser(parser=None):
    if parser is None:
        parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", nargs="?", help="simulation YAML (default: built-in defaults)")
    parser.add_argument("-o", "--out", help="output folder (default: the config's `output`)")
    parser.add_argument("--seed", type=int, help="override the config's seed")
    parser.add_argument("--duration", type=float, help="seconds per observation")
    parser.add_argument("--start", help="first observation's start, ctime or ISO UTC (it names "
                                        "the obs_id; default: the config's)")
    parser.add_argument("--tubes", nargs="+", metavar="TUBE", help="LAT tube slots (see --list)")
    parser.add_argument("--wafers", nargs="+", metavar="WAFER",
                        help="wafer slots of those tubes (default: the config's)")
    parser.add_argument("--bands", nargs="+", metavar="BAND",
                        help="bands (default: both bands of each tube)")
    parser.add_argument("--list", action="store_true",
                        help="list the tubes, wafers and bands that can be simulated, and stop")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing dataset")
    parser.add_argument("--workers", type=int, default=1,
                        help="threads generating detector chunks (same result for any number)")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    return parser


def print_layout():
    """The tubes, wafers and bands that can be simulated."""
    from so_transients.sim.focal_plane import lat_layout

    print(f"{'tube':5} {'flavour':8} {'wafers':16} bands")
    for tube, flavour, wafers, bands in lat_layout():
        print(f"{tube:5} {flavour:8} {' '.join(wafers):16} {' '.join(bands)}")


def run_simulation(args):
    """Simulate the dataset of ``args`` (this parser's options; those it lacks take the
    config's values) and return the simulation result."""
    from so_transients.common.times import parse_time
    from so_transients.sim.config import load_config
    from so_transients.sim.simulate import simulate

    start = getattr(args, "start", None)
    config = load_config(args.config, {
        "seed": args.seed, "output": args.out,
        "observation": {"duration": getattr(args, "duration", None),
                        "start": None if start is None else parse_time(start)},
        "instrument": {"tubes": getattr(args, "tubes", None),
                       "wafers": getattr(args, "wafers", None),
                       "bands": getattr(args, "bands", None)}})
    t0 = time.time()
    result = simulate(config, overwrite=args.overwrite, progress=not args.quiet,
                      workers=getattr(args, "workers", 1))
    print(f"Simulated {len(result.obs_ids)} observation(s) in {time.time() - t0:.0f} s; "
          f"context: {result.context}")
    return result


def main(args) -> int:
    if args.list:
        print_layout()
    else:
        run_simulation(args)
    return 0


if __name__ == "__main__":
    sys.exit(main(get_parser().parse_args()))
