"""Sample-efficiency study: mixedrl's methods against SB3's TD3 and SAC in true transitions and wall time.

Four subcommands (run from the repository root with ``PYTHONPATH=.`` or the package installed)::

    # the peers (extra 'peers'): experiments/results/sample_efficiency/peers/<algo>_s<seed>.json
    python experiments/analysis/sample_efficiency.py peers --algos td3,sac --seeds 0-4 --transitions 100000 --jobs 2
    # mixedrl's methods: a sweep of experiments/studies/sample_efficiency.toml, recorded as
    # experiments/results/sample_efficiency/ours/<method>_s<seed>.json
    mixedrl sweep experiments/studies/sample_efficiency.toml --out runs/sample_efficiency
    python experiments/analysis/sample_efficiency.py from-sweep runs/sample_efficiency
    # or record the runs of a reproduction instead of training them again (mixed, model, oracle, and
    # DDPG's longer runs as 'ddpg'); the shipped study did this with runs/reproduce/runs (the layout of
    # reproductions before they trained through mixedrl sweep; today's: runs/reproduce)
    python experiments/analysis/sample_efficiency.py from-reproduction runs/reproduce
    # table (summary.csv, summary.json) and figures (curves_transitions.png, curves_wall.png)
    python experiments/analysis/sample_efficiency.py summary

Every peer run is one process of a ``multiprocessing`` pool (``--jobs``) with ``torch.set_num_threads(1)``.
A peer run whose JSON file exists is skipped, provided it was made with the same settings (otherwise the
script stops before training anything: remove the file or choose another ``--out``). mixedrl's own runs are
trained by ``mixedrl sweep`` (the one runner) and only recorded here. ``--out`` (default
``experiments/results/sample_efficiency``) is the root of everything. See ``docs/sample_efficiency.rst`` and
:mod:`experiments.analysis.sample_efficiency_lib`, :mod:`validation.peers`.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from multiprocessing import Pool
from pathlib import Path
from typing import Any

import torch

from mixedrl.runs import atomic_write_text
from mixedrl.runs import eval_seeds as run_eval_seeds
from mixedrl.config import TrainConfig
from validation.peers import ALGOS, train_peer
from experiments.analysis.sample_efficiency_lib import (
    choose_eval_every,
    load_runs,
    plot_curves,
    records_from_reproduction,
    records_from_sweep,
    summarize,
    write_summary,
)

OUT = Path("experiments/results/sample_efficiency")


def seeds_of(text: str) -> list[int]:
    """``"0-4"`` -> [0, 1, 2, 3, 4]; ``"0,2"`` -> [0, 2]."""
    if "-" in text:
        a, b = text.split("-")
        return list(range(int(a), int(b) + 1))
    return [int(x) for x in text.split(",") if x]


def names_of(text: str, allowed: tuple[str, ...], what: str) -> list[str]:
    names = [x for x in text.split(",") if x]
    bad = [x for x in names if x not in allowed]
    if bad or not names:
        raise SystemExit(f"--{what}: expected names from {allowed}, got {text!r}")
    return names


def _init_worker() -> None:
    torch.set_num_threads(1)
    logging.basicConfig(level=logging.WARNING, format="%(message)s")


def _peer_job(job: dict[str, Any]) -> str:
    res = train_peer(job["algo"], seed=job["seed"], transitions=job["transitions"], eval_every=job["eval_every"],
                     eval_seeds=job["eval_seeds"], out=job["path"], progress=job["progress"])
    last = res["rows"][-1]
    return (f"{job['algo']} s{job['seed']}: {res['true_transitions']} true transitions, {res['train_seconds']:.0f} s, "
            f"lateral {last['lateral_mae']:.4f} m, speed {last['speed_mae']:.4f} m/s, cost {last['cost']:.2f}")


def _run(jobs: list[dict[str, Any]], worker: Any, n_jobs: int) -> None:
    if not jobs:
        print("nothing to run (every file exists)")
        return
    with Pool(min(n_jobs, len(jobs)), initializer=_init_worker) as pool:
        for line in pool.imap_unordered(worker, jobs, chunksize=1):
            print(line, flush=True)


def _stale(path: Path, expected: dict[str, Any]) -> str | None:
    """None if ``path`` holds a run with the ``expected`` config entries, else what differs."""
    config = json.loads(path.read_text()).get("config", {})
    diff = sorted(k for k, v in expected.items() if config.get(k) != v)
    return None if not diff else f"{path} was made with other settings ({', '.join(diff)})"


def peers(args: argparse.Namespace) -> None:
    out = Path(args.out) / "peers"
    eval_every = args.eval_every or choose_eval_every(args.transitions)
    jobs, stale = [], []
    for algo in names_of(args.algos, ALGOS, "algos"):
        for seed in seeds_of(args.seeds):
            path = out / f"{algo}_s{seed}.json"
            if path.exists():
                expected = {"transitions": args.transitions, "eval_every": eval_every, "kwargs": {},
                            "eval_seeds": run_eval_seeds(TrainConfig(seed=seed, run={"eval_seeds": args.eval_seeds}))}
                problem = _stale(path, expected)
                if problem:
                    stale.append(problem)
                continue
            jobs.append({"algo": algo, "seed": seed, "transitions": args.transitions, "eval_every": eval_every,
                         "eval_seeds": args.eval_seeds, "path": str(path), "progress": args.jobs == 1})
    if stale:
        raise SystemExit("\n".join(stale) + "\nremove these files or choose another --out")
    _run(jobs, _peer_job, args.jobs)


def _write_records(records: list[dict[str, Any]], out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for record in records:
        path = out / f"{record['method']}_s{record['seed']}.json"
        atomic_write_text(path, json.dumps(record, indent=1) + "\n")
        print(f"wrote {path} ({len(record['rows'])} evaluations, {record['true_transitions']} true transitions)")


def from_sweep(args: argparse.Namespace) -> None:
    _write_records(records_from_sweep(args.sweep_dir), Path(args.out) / "ours")


def from_reproduction(args: argparse.Namespace) -> None:
    _write_records(records_from_reproduction(args.runs), Path(args.out) / "ours")


def summary(args: argparse.Namespace) -> None:
    root = Path(args.out)
    paths = sorted((root / "ours").glob("*.json")) + sorted((root / "peers").glob("*.json"))
    if not paths:
        raise SystemExit(f"no run files under {root}/ours or {root}/peers")
    runs = load_runs(paths)
    table = summarize(runs)
    csv_path, json_path = write_summary(table, root)
    plot_curves(runs, "true_transitions", root / "curves_transitions.png")
    plot_curves(runs, "wall_seconds", root / "curves_wall.png")
    for e in table:
        std = {k: ("" if e[f"{k}_std"] is None else f" ± {e[f'{k}_std']:.4f}") for k in ("lateral", "speed", "cost")}
        print(f"{e['method']:>6} seeds {e['seeds']}: lateral {e['lateral_mean']:.4f}{std['lateral']} m, "
              f"speed {e['speed_mean']:.4f}{std['speed']} m/s, cost {e['cost_mean']:.2f}{std['cost']}; "
              f"true transitions {e['true_transitions']}; threshold reached by {e['reached']}/{len(e['seeds'])} "
              f"at {e['accuracy_transitions']}; own final at {e['own_final_transitions']}, "
              f"settled at {e['settled_transitions']}")
    print(f"wrote {csv_path}, {json_path}, {root / 'curves_transitions.png'}, {root / 'curves_wall.png'}")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("peers", help="train SB3's TD3/SAC (extra 'peers')")
    p.add_argument("--algos", default="td3,sac")
    p.add_argument("--seeds", default="0-4")
    p.add_argument("--transitions", type=int, default=100_000)
    p.add_argument("--eval-every", type=int, default=None, help="default: about 12 evaluations per run")
    p.add_argument("--eval-seeds", type=int, default=2)
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--out", default=str(OUT))
    p = sub.add_parser("from-sweep", help="record the runs of a sweep of experiments/studies/sample_efficiency.toml")
    p.add_argument("sweep_dir", help="the sweep directory (mixedrl sweep ... --out DIR)")
    p.add_argument("--out", default=str(OUT))
    p = sub.add_parser("from-reproduction", help="record the runs of a reproduction (mixedrl reproduce) "
                                                 "instead of training them again")
    p.add_argument("runs", help="the reproduction's runs/ folder")
    p.add_argument("--out", default=str(OUT))
    p = sub.add_parser("summary", help="table and figures from the run files")
    p.add_argument("--out", default=str(OUT))
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if getattr(args, "jobs", 1) < 1:
        raise SystemExit("--jobs: expected a positive integer")
    {"peers": peers, "from-sweep": from_sweep, "summary": summary, "from-reproduction": from_reproduction}[args.cmd](args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
