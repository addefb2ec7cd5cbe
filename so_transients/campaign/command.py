"""``so-transients study ...``: the validation studies.

* ``campaign CONFIG``: injection-recovery (efficiency, thresholds, flux and pointing recovery,
  false positives);
* ``combine RESULTS... -o OUT``: several campaigns' results as one;
* ``events-check CONFIG``: flares and noise through the site pipeline and the events command,
  compared with the truth;
* ``train-score CONFIG``: the real-or-artefact score trained on simulated real wafers (and a
  person's labels from vetting pages).

Built like a sotodlib site-pipeline element (:func:`get_parser`, :func:`main`).
"""
from __future__ import annotations

import argparse
import sys
import time

STUDIES = ("campaign", "combine", "events-check", "train-score")


def get_parser(parser=None, parents=()):
    """The studies as sub-commands of ``parser`` (``parents``: options each of them takes)."""
    if parser is None:
        parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    study = parser.add_subparsers(dest="study", required=True,
                                  metavar="{" + ",".join(STUDIES) + "}")

    def add(name, help_text):
        return study.add_parser(name, parents=list(parents), help=help_text)

    p = add("campaign", "injection-recovery campaign: efficiency, detection thresholds, "
                        "flux/pointing recovery, false positives")
    p.add_argument("config", help="campaign YAML (e.g. studies/configs/campaign_quick.yaml)")
    p.add_argument("-o", "--out", help="output folder (default: the config's `output`)")
    p.add_argument("--nproc", type=int, help="worker processes (default: the config's)")
    p.add_argument("--restart", action="store_true",
                   help="discard units of a different config in the output folder")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")

    p = add("combine", "one set of result tables and figures from several campaigns' "
                       "results (e.g. an MF and a UHF campaign)")
    p.add_argument("results", nargs="+", help="campaign results folders (<output>/results)")
    p.add_argument("-o", "--out", required=True, help="output folder")

    p = add("events-check", "flares and noise through the site pipeline and the events "
                            "command, compared with the truth")
    p.add_argument("config", help="events-check YAML (e.g. studies/configs/events_check.yaml)")
    p.add_argument("-o", "--out", help="output folder (default: the config's `output`)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")

    p = add("train-score", "the real-or-artefact score: labelled candidates of simulated real "
                           "wafers, the model trained and measured on held-out seeds and "
                           "another scan pattern")
    p.add_argument("config", help="training YAML (e.g. studies/configs/score_training.yaml)")
    p.add_argument("-o", "--out", help="output folder (default: the config's `output`)")
    p.add_argument("--model", help="model file to write (default: OUT/real_score.json)")
    p.add_argument("--labels", nargs="+", default=[], metavar="CSV",
                   help="labels a person exported from `so-transients report` pages, trained "
                        "on beside the simulated ones")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    return parser


def campaign(args) -> int:
    from so_transients.campaign.config import load_campaign
    from so_transients.campaign.run import run_campaign
    from so_transients.common.parallel import executor, is_worker_rank

    cfg = load_campaign(args.config, {"output": args.out, "nproc": args.nproc})
    pool, as_completed = executor(cfg.nproc)
    if is_worker_rank(pool, cfg.nproc):
        return 0        # an MPI worker rank: it served units until rank 0 finished
    t0 = time.time()
    try:
        folder = run_campaign(cfg, restart=args.restart, progress=not args.quiet, pool=pool,
                              as_completed=as_completed,
                              command=f"so-transients study campaign {args.config}")
    finally:
        if pool is not None:
            pool.shutdown()
    print((folder / "thresholds.md").read_text())
    print(f"Campaign done in {time.time() - t0:.0f} s; results in {folder}")
    return 0


def combine(args) -> int:
    from so_transients.campaign.combine import combine_results

    folder = combine_results(args.results, args.out)
    print((folder / "summary.md").read_text())
    print(f"Combined results in {folder}")
    return 0


def events_check(args) -> int:
    from so_transients.campaign.events_check import EventsCheckConfig, run_events_check

    cfg = EventsCheckConfig.read(args.config, args.out)
    t0 = time.time()
    folder = run_events_check(cfg, progress=not args.quiet,
                              command=f"so-transients study events-check {args.config}")
    print((folder / "summary.md").read_text())
    print(f"Events check done in {time.time() - t0:.0f} s; results in {folder}")
    return 0


def train_score(args) -> int:
    from so_transients.campaign.score_training import (
        ScoreTrainingConfig, markdown, run_score_training
    )

    cfg = ScoreTrainingConfig.read(args.config, args.out, args.labels)
    t0 = time.time()
    path, figures = run_score_training(cfg, progress=not args.quiet, model_out=args.model)
    print(markdown(figures))
    print(f"Score model trained in {time.time() - t0:.0f} s: {path}")
    return 0


def main(args) -> int:
    return {"campaign": campaign, "combine": combine, "events-check": events_check,
            "train-score": train_score}[args.study](args)


if __name__ == "__main__":
    sys.exit(main(get_parser().parse_args()))
