"""The ``mixedrl`` command line.

::

    mixedrl train --method {mixed,model,ddpg,oracle} --seed S --out DIR [--iterations N]
                  [--config FILE.json] [--set key=value ...] [--resume] [--no-progress]
    mixedrl evaluate RUN_DIR [--seeds N]
    mixedrl reproduce [--seeds 5] [--out DIR] [--quick] [--resume] [--workers W] [--no-progress]

``train`` writes a run directory (:mod:`mixedrl.runs`); ``--resume`` continues an interrupted run from
its last checkpoint and ends with exactly the result of an uninterrupted run. ``evaluate`` drives the
double lane change with a run's final policy. ``reproduce`` runs the four methods over several seeds and
prints Table I with the paper's numbers beside ours (the reproduction script is
:mod:`validation.reproduce`). This module is the only place of the package that prints.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Any, Sequence

from mixedrl.config import METHODS, TrainConfig

__all__ = ["main", "build_parser", "parse_overrides"]


def parse_overrides(items: Sequence[str]) -> dict[str, Any]:
    """Turn ``["key=value", ...]`` into a dict; values are parsed as JSON when possible (else strings).

    Raises
    ------
    ValueError
        An item without ``=``.
    """
    out: dict[str, Any] = {}
    for item in items:
        if "=" not in item:
            raise ValueError(f"--set: expected key=value, got {item!r}")
        key, value = item.split("=", 1)
        try:
            out[key.strip()] = json.loads(value)
        except json.JSONDecodeError:
            out[key.strip()] = value
    return out


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``mixedrl``."""
    parser = argparse.ArgumentParser(prog="mixedrl", description="Mixed RL with additive stochastic uncertainty.")
    parser.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("train", help="train one method with one seed into a run directory")
    p.add_argument("--method", choices=METHODS, required=True)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, required=True, help="run directory")
    p.add_argument("--iterations", type=int, default=None, help="budget (default: the config's)")
    p.add_argument("--config", type=Path, default=None, help="JSON file with TrainConfig fields")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="override config fields")
    p.add_argument("--resume", action="store_true", help="continue from the run's checkpoint")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")

    p = sub.add_parser("evaluate", help="evaluate a run's final policy on the double lane change")
    p.add_argument("run_dir", type=Path)
    p.add_argument("--seeds", type=int, default=None, help="number of noise seeds (default: the run's)")

    p = sub.add_parser("reproduce", help="reproduce Table I and the figures of the paper")
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--out", type=Path, default=Path("runs/reproduce"))
    p.add_argument("--quick", action="store_true", help="reduced budget (<= 3 minutes), for the test suite")
    p.add_argument("--resume", action="store_true", help="reuse finished runs and resume interrupted ones")
    p.add_argument("--workers", type=int, default=None, help="parallel training processes (default: 2)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    return parser


def _train(args: argparse.Namespace) -> int:
    from mixedrl.runs import RunDirectory, make_trainer, train

    run = RunDirectory(args.out)
    if args.resume and run.config_path.is_file():
        config = run.read_config()
    else:
        base: dict[str, Any] = {}
        if args.config is not None:
            base = TrainConfig.load(args.config).to_dict()
        base.update(parse_overrides(args.set))
        base.update({"method": args.method, "seed": args.seed})
        if args.iterations is not None:
            base["iterations"] = args.iterations
        config = TrainConfig.from_dict(base)
    trainer = make_trainer(config)
    results = train(trainer, run, resume=args.resume, progress=not args.no_progress)
    print(json.dumps({k: results[k] for k in ("method", "seed", "iterations", "lateral_mae", "speed_mae", "cost",
                                              "iterations_to_converge", "train_seconds") if k in results},
                     indent=2))
    return 0


def _evaluate(args: argparse.Namespace) -> int:
    from mixedrl.runs import RunDirectory, eval_seeds, load_checkpoint, make_trainer

    run = RunDirectory(args.run_dir)
    config = run.read_config()
    if args.seeds is not None:
        config = config.replace(eval_seeds=args.seeds)
    trainer = make_trainer(config)
    trainer.load_state_dict(load_checkpoint(run.checkpoint_path)["trainer"])
    metrics = trainer.evaluate(eval_seeds(config))
    print(json.dumps({"run": str(run.path), "method": config.method, "seed": config.seed, "iteration": trainer.k,
                      **{k: v for k, v in metrics.items() if isinstance(v, (int, float))}}, indent=2))
    return 0


def _reproduce(args: argparse.Namespace) -> int:
    # the reproduction is the readable script validation/reproduce.py; the command is its entry point
    from validation.reproduce import format_table, reproduce

    results = reproduce(args.out, seeds=args.seeds, quick=args.quick, resume=args.resume, workers=args.workers,
                        progress=not args.no_progress)
    print(format_table(results))
    print(f"\nresults: {Path(args.out) / 'results.json'}   figures: {Path(args.out) / 'figures'}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``mixedrl`` command; returns the exit status.

    Errors in the user's input (``ValueError``) are reported in one line with exit status 2.
    """
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(message)s")
    handlers = {"train": _train, "evaluate": _evaluate, "reproduce": _reproduce}
    try:
        return handlers[args.command](args)
    except ValueError as exc:
        print(f"mixedrl {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
