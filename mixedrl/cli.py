"""The ``mixedrl`` command line.

::

    mixedrl train --method {mixed,model,ddpg,oracle} --seed S --out DIR [--iterations N]
                  [--config FILE.json] [--set key=value ...] [--resume] [--no-progress] [--tensorboard]
    mixedrl evaluate RUN_DIR [--seeds N]
    mixedrl sweep SPEC.toml --out DIR [--workers N] [--batch N] [--force] [--address ADDR] [--resume] ...
    mixedrl reproduce [--seeds 5] [--out DIR] [--quick] [--resume] [--workers W] [--no-progress]

``train`` writes a run directory (:mod:`mixedrl.runs`); ``--config FILE.json`` reads a (partial, nested)
:class:`~mixedrl.config.TrainConfig` dict like a run's ``config.json``, and ``--set KEY=VALUE ...`` then
overrides fields by dotted keys (values are JSON, else strings; :func:`mixedrl.config.apply_overrides`).
``train`` and ``evaluate`` print one JSON object on stdout and one line about the ``policy_gap`` on stderr.

**Command plug-ins.** Commands beyond ``train``, ``evaluate`` and ``sweep`` (e.g. ``reproduce``) are entry
points of the group :data:`COMMAND_GROUP`, e.g. in ``pyproject.toml``::

    [project.entry-points."mixedrl.commands"]
    reproduce = "validation.reproduce:register"

naming a function ``register(subparsers) -> handler``: it adds *one* sub-parser named like the entry
point and returns the handler, which takes the parsed ``argparse.Namespace`` and returns the exit status.
A ``ValueError`` it raises is reported in one line with exit status 2. A plug-in that fails to load is
skipped with a warning.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from collections.abc import Callable
from importlib.metadata import EntryPoint, entry_points
from pathlib import Path
from typing import Any, Sequence

from mixedrl.config import CONFIG_PRESETS, FEEDFORWARDS, METHODS, TrainConfig, apply_overrides
from mixedrl.precision import format_policy_gap, gap_summary
from mixedrl.runs import RunDirectory, evaluate_run, make_trainer, train
from mixedrl.sweep import SEED_MAX, add_parser as add_sweep_parser, flatten_table, format_summary, load_spec, run_sweep

__all__ = ["main", "build_parser", "parse_overrides", "command_plugins", "COMMAND_GROUP", "Handler"]

logger = logging.getLogger(__name__)

#: Entry-point group of the command plug-ins (see the module docstring).
COMMAND_GROUP = "mixedrl.commands"
#: A command's handler: parsed arguments -> exit status.
Handler = Callable[[argparse.Namespace], int]


def parse_overrides(items: Sequence[str]) -> dict[str, Any]:
    """Turn ``["key=value", ...]`` into a dict; values are parsed as JSON when possible (else strings),
    keys are kept as given (dotted).

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


def command_plugins() -> list[EntryPoint]:
    """The installed command plug-ins: entry points of the group :data:`COMMAND_GROUP`, sorted by name."""
    return sorted(entry_points(group=COMMAND_GROUP), key=lambda ep: ep.name)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``mixedrl`` (built-in commands and plug-ins; each sets the default ``handler``)."""
    parser = argparse.ArgumentParser(prog="mixedrl", description="Mixed RL with additive stochastic uncertainty.")
    parser.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("train", help="train one method with one seed into a run directory",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       epilog="examples:\n"
                              "  mixedrl train --method mixed --out runs/p300 --set task.prior_force_mean=300\n"
                              "  mixedrl train --method mixed --out runs/x --config experiment.json "
                              "--set task.gamma=0.98\n"
                              "dotted keys address the nested task configuration (see mixedrl.config).")
    p.add_argument("--method", choices=METHODS, required=True)
    p.add_argument("--seed", type=int, default=None, help="seed (default 0; with --resume: the run's)")
    p.add_argument("--out", type=Path, required=True, help="run directory")
    p.add_argument("--iterations", type=int, default=None,
                   help="budget (default: the config's; with --resume a larger one extends the run)")
    p.add_argument("--config", type=Path, default=None,
                   help="JSON file with TrainConfig fields, nested like a run's config.json")
    p.add_argument("--set", nargs="*", action="extend", default=[], metavar="KEY=VALUE",
                   help="override config fields; dotted keys for nested ones (task.prior_force_mean=300, "
                        "task.disturbance.mean=261); values are JSON, else strings; repeated --set flags add up")
    p.add_argument("--preset", choices=tuple(CONFIG_PRESETS), default=None,
                   help="'paper': the paper's literal Algorithm 2 (TrainConfig.preset); --set applies on top")
    p.add_argument("--resume", action="store_true",
                   help="continue from the run's checkpoint (without it, --out must be new or empty)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--tensorboard", action="store_true",
                   help="also write the metrics as TensorBoard scalars into OUT/tb (extra 'tensorboard')")
    p.set_defaults(handler=_train)

    p = sub.add_parser("evaluate", help="evaluate a run's final policy on its task")
    p.add_argument("run_dir", type=Path)
    p.add_argument("--seeds", type=int, default=None, help="number of noise seeds (default: the run's)")
    # not argparse's choices: a retired value is refused by the config, naming the commit that still runs it
    p.add_argument("--feedforward", default=None, metavar="{" + ",".join(FEEDFORWARDS) + "}",
                   help="evaluate with this algorithm.feedforward instead of the run's ('lq_ss': the actor shifted "
                        "near the LQ optimum's steady state to the optimum's action there, for the method's own "
                        "noise mean)")
    p.add_argument("--calibration", type=int, default=None, metavar="K",
                   help="evaluate with this algorithm.feedforward_calibration instead of the run's (0: the shift "
                        "alone, no Newton step on the model's mean state)")
    p.set_defaults(handler=_evaluate)

    add_sweep_parser(sub)  # Ray is imported only when a sweep runs on it
    sub.choices["sweep"].set_defaults(handler=_sweep)

    for ep in command_plugins():  # the plug-ins (module docstring)
        if ep.name in sub.choices:
            logger.warning("command plug-in %r (%s) ignored: the command exists", ep.name, ep.value)
            continue
        try:
            handler = ep.load()(sub)
        except Exception as exc:  # noqa: BLE001 - a broken plug-in must not break the other commands
            logger.warning("command plug-in %r (%s) failed to load: %s: %s", ep.name, ep.value,
                           type(exc).__name__, exc)
            continue
        if ep.name not in sub.choices or not callable(handler):
            logger.warning("command plug-in %r (%s) ignored: register() must add the sub-parser %r and return "
                           "its handler", ep.name, ep.value, ep.name)
            continue
        sub.choices[ep.name].set_defaults(handler=handler)
    return parser


def _sweep(args: argparse.Namespace) -> int:
    """``mixedrl sweep``: 0 if every run finished, 1 if some failed, 2 for invalid input or a missing Ray."""
    doc = run_sweep(load_spec(args.spec, force=args.force), args.out, address=args.address, num_cpus=args.num_cpus,
                    resume=args.resume, progress=not args.no_progress, workers=args.workers, batch=args.batch,
                    batch_ddpg=args.batch_ddpg)
    print(format_summary(doc, args.out))
    if doc["failed"]:
        print(f"mixedrl sweep: {doc['failed']} run(s) failed; see 'error' in sweep.json", file=sys.stderr)
        return 1
    return 0


#: Fields with their own ``train`` flag, refused in ``--set``.
_OWN_FLAGS = {"method": "--method", "seed": "--seed"}


def _requested_config(args: argparse.Namespace, run: RunDirectory) -> TrainConfig:
    """The config ``mixedrl train`` asks for: from the flags, or with ``--resume`` the saved config with the
    explicit flags on top (so a contradicting flag shows up as a difference)."""
    overrides = parse_overrides(args.set)
    for key, flag in _OWN_FLAGS.items():
        if key in overrides:
            raise ValueError(f"--set: {key} has its own flag; use {flag} instead of --set {key}=...")
    given = {"method": args.method, "seed": args.seed, "algorithm.iterations": args.iterations}
    file_data, path = None, args.config
    if path is not None:
        if not path.is_file():
            raise ValueError(f"--config: {path} {'is not a file' if path.exists() else 'does not exist'}")
        try:
            file_data = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ValueError(f"--config: cannot read {path} as JSON ({exc})") from None
        if not isinstance(file_data, dict):
            raise ValueError(f"--config: {path} holds a JSON {type(file_data).__name__}, expected an object of "
                             f"config fields")
    if args.resume and run.config_path.is_file():
        base = run.read_config().to_dict()
        if file_data is not None:
            base = apply_overrides(base, flatten_table(file_data))
    else:
        base = TrainConfig.from_dict(file_data).to_dict() if file_data is not None else {}
        if args.preset:
            base = TrainConfig.from_dict({"method": args.method, "seed": 0, **base}).with_preset(args.preset).to_dict()
        given["seed"] = 0 if args.seed is None else args.seed
    base = apply_overrides(base, {**overrides, **{k: v for k, v in given.items() if v is not None}})
    return TrainConfig.from_dict(base)


def _train(args: argparse.Namespace) -> int:
    if args.seed is not None and not 0 <= args.seed <= SEED_MAX:
        raise ValueError(f"--seed: {args.seed} is out of range; expected an integer in [0, 2**64 - 1]")
    run = RunDirectory(args.out)
    if args.resume and not run.holds_run():
        names = run.entries()  # what is there instead (a .lock listed here is not the package's)
        found = f"; it holds {', '.join(names[:3])}, which mixedrl did not write" if names else ""
        raise ValueError(f"--resume: {run.path} holds no run to resume (no config.json, checkpoint.pt or lock "
                         f"of a started run{found})")
    trainer = make_trainer(_requested_config(args, run))
    results = train(trainer, run, resume=args.resume, progress=not args.no_progress, tensorboard=args.tensorboard)
    shown = {k: results[k] for k in ("method", "seed", "iterations", "lateral_mae", "speed_mae", "cost",
                                      "iterations_to_converge", "train_seconds", "true_transitions") if k in results}
    if "policy_gap" in results:
        shown["policy_gap"] = gap_summary(results["policy_gap"])
    reference = (results.get("references") or {}).get("lqr_true_mean")
    if reference is not None and "cost" in results:
        shown["lqr_true_mean_cost"] = reference["cost"]
        shown["cost_over_lqr"] = results["cost"] / reference["cost"] if reference["cost"] > 0 else None
    print(json.dumps(shown, indent=2))
    if "policy_gap" in results:  # the one human-readable line (stdout stays one JSON object)
        print(format_policy_gap(results["policy_gap"], results.get("policy_gap_reason")), file=sys.stderr)
    return 0


def _evaluate(args: argparse.Namespace) -> int:
    out = evaluate_run(args.run_dir, seeds=args.seeds, feedforward=args.feedforward, calibration=args.calibration)
    config, metrics, gap = out["config"], out["metrics"], out["policy_gap"]
    print(json.dumps({"run": str(args.run_dir), "method": config.method, "seed": config.seed,
                      "iteration": out["iteration"], "feedforward": config.algorithm.feedforward,
                      "feedforward_calibration": config.algorithm.feedforward_calibration,
                      **{k: v for k, v in metrics.items() if isinstance(v, (int, float))},
                      "policy_gap": gap_summary(gap)}, indent=2))
    print(format_policy_gap(gap, out["policy_gap_reason"]), file=sys.stderr)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``mixedrl`` command; returns the exit status (2, with one line on stderr, for a
    ``ValueError``, ``OSError`` or ``ImportError`` of a missing extra)."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(message)s")
    try:
        return int(args.handler(args))
    except (ValueError, OSError, ImportError) as exc:
        text = " ".join(str(exc).split()) or type(exc).__name__
        print(f"mixedrl {args.command}: error: {text}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
