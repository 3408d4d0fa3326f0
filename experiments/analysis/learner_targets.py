"""The final measurement of issue 42 near an equilibrium: the TARGET systems of
``experiments/studies/learner_targets.toml`` (the shipped pendulum, the linear test bed and the two
never-tuned systems of :mod:`experiments.target_systems`), seeds 0-9, no choice made here.

Each run is measured as :func:`tuning_baseline.one_run` measures a tuning run (the final evaluation's cost
against the discounted LQR with the true feed-forward on the same seeds, the steady offset against the
LQR's, ``policy_gap``, the noise mean), for every (system, setting, method, seed) of the spec, where a
setting is the library defaults (``default``) or a preset (``paper``). A run whose ``per_run`` JSON exists
is read, not trained again (the study resumes). The table gives per system and setting: cost / LQR(true)
(mean, worst, within 3% on how many seeds), offsets within the target on how many seeds, model-driven
RL's offset beside the prior's LQR's, and mixed against model-driven per seed (wins, the mean difference
with a paired bootstrap 95% interval).

Usage::

    PYTHONPATH=. python experiments/analysis/learner_targets.py [--spec ...] [--dest ...] [--only SYSTEM]
        [--settings default paper] [--jobs N]

``--jobs N`` trains the missing runs in ``N`` processes (one torch thread each) before the table is written;
``--settings`` trains and tables only those of the spec's settings (the table of all of them needs every run).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import sys
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
for p in (ROOT, ROOT / "experiments" / "analysis"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from experiments.target_systems import TARGET_SYSTEMS  # noqa: E402
from mixedrl.runs import atomic_write_text  # noqa: E402
from mixedrl.tables import paired_interval  # noqa: E402
from tuning_baseline import COST_REL, format_row, one_run  # noqa: E402

SPEC = ROOT / "experiments" / "studies" / "learner_targets.toml"
OUT = ROOT / "experiments" / "results" / "learner_targets"


def run_or_read(system: str, method: str, setting: str, seed: int, spec: dict[str, Any], dest: Path) -> dict[str, Any]:
    """The row of one run: read from its ``per_run`` JSON when the run exists, else trained and measured.

    A setting is ``"default"``, a preset's name, or a key of the spec's ``[overrides]`` table (``algorithm.*``
    settings over the library defaults; its per-run files end in ``_<setting>``)."""
    overrides = spec.get("overrides", {}).get(setting)
    preset = None if setting == "default" or overrides is not None else setting
    tag = "" if overrides is None else f"_{setting}"
    name = f"{system}_{method}_{seed}" if preset is None else f"{system}_{method}_{preset}_{seed}"
    path = dest / "per_run" / f"{name}{tag}.json"
    if path.exists():
        return json.loads(path.read_text())["row"]
    return one_run(system, method, seed, spec.get("iterations"), dest, systems=TARGET_SYSTEMS, preset=preset,
                   algorithm=overrides, tag=tag, setting=setting)


def setting_systems(spec: dict[str, Any], setting: str) -> list[str]:
    """The systems a setting is measured on: the spec's ``[setting_systems]`` entry, else every system."""
    return spec.get("setting_systems", {}).get(setting, spec["systems"])


def summarise(rows: list[dict[str, Any]], systems: list[str], settings: list[str]) -> list[str]:
    """The summary lines per system and setting (module docstring)."""
    lines = []
    for system in systems:
        for setting in settings:
            sel = {m: sorted((r for r in rows if r["system"] == system and r["setting"] == setting
                              and r["method"] == m), key=lambda r: r["seed"]) for m in ("mixed", "model", "oracle")}
            for m, rs in sel.items():
                if not rs:
                    continue
                ratio = np.array([r["cost_ratio"] for r in rs])
                lines.append(f"- {system} {setting} {m}: cost/LQR(true) mean {ratio.mean():.3f} (worst {ratio.max():.3f});"
                             f" within {COST_REL:.0%} on {sum(r['cost_within_target'] for r in rs)}/{len(rs)}; offset"
                             f" within target on {sum(r['offset_within_target'] for r in rs)}/{len(rs)}; offset mean"
                             f" {np.mean([r['offset'] for r in rs]):+.4f} (LQR true {rs[0]['lqr_true_offset']:+.4f},"
                             f" prior {rs[0]['lqr_prior_offset']:+.4f}); wall {np.mean([r['wall_seconds'] for r in rs]):.0f} s/run")
            mixed, model = sel["mixed"], sel["model"]
            common = sorted({r["seed"] for r in mixed} & {r["seed"] for r in model})
            if common:
                cm = {r["seed"]: r["cost"] for r in mixed}
                cd = {r["seed"]: r["cost"] for r in model}
                diff = np.array([cd[s] - cm[s] for s in common])
                mean, lo, hi = paired_interval([cd[s] for s in common], [cm[s] for s in common])
                ci = "" if lo is None else f" [{lo:+.4g}, {hi:+.4g}]"
                lines.append(f"  - {system} {setting}: mixed cheaper than model-driven on {int((diff > 0).sum())}/"
                             f"{len(common)} seeds; cost(model) - cost(mixed) mean {mean:+.4g}{ci} (paired bootstrap 95%)")
    return lines


def _job(job: tuple[str, str, str, int, dict[str, Any], Path]) -> dict[str, Any]:
    """One run of the pool (one torch thread per process)."""
    torch.set_num_threads(1)
    return run_or_read(*job)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--spec", type=Path, default=SPEC)
    ap.add_argument("--dest", type=Path, default=OUT)
    ap.add_argument("--only", default=None, help="only this system")
    ap.add_argument("--settings", nargs="+", default=None, help="only these of the spec's settings")
    ap.add_argument("--jobs", type=int, default=1, help="processes for the runs not yet measured")
    args = ap.parse_args(argv)
    spec = tomllib.loads(args.spec.read_text())
    if args.jobs < 1:
        raise SystemExit(f"--jobs: expected at least 1, got {args.jobs}")
    settings = spec["settings"] if args.settings is None else args.settings
    unknown = sorted(set(settings) - set(spec["settings"]))
    if unknown:
        raise SystemExit(f"--settings: {unknown} are not settings of {args.spec.name} ({spec['settings']})")
    torch.set_num_threads(1)
    systems = [s for s in spec["systems"] if args.only in (None, s)]
    keys = [(system, method, setting, seed) for system in systems for setting in settings
            if system in setting_systems(spec, setting) for method in spec["methods"] for seed in spec["seeds"]]
    if args.jobs > 1:  # the missing runs first, in parallel; each writes its own per_run JSON
        with multiprocessing.get_context("fork").Pool(args.jobs) as pool:
            for i, row in enumerate(pool.imap_unordered(_job, [(*k, spec, args.dest) for k in keys]), 1):
                print(f"[{i}/{len(keys)}] [{row['setting']}] " + format_row(row), file=sys.stderr, flush=True)
    rows = []
    for key in keys:
        row = run_or_read(*key, spec, args.dest)
        print(f"[{key[2]}] " + format_row(row), file=sys.stderr, flush=True)
        rows.append(row)
    spec = {**spec, "settings": settings}
    lines = [f"Issue 42 targets near an equilibrium: {', '.join(systems)}; settings {spec['settings']}; seeds "
             f"{spec['seeds']}; written by experiments/analysis/learner_targets.py from {args.spec.name}.", "",
             "Columns as experiments/results/tuning_baseline/table.md.", "",
             "| setting | system | method | seed | cost | LQR(true) | cost/LQR | LQR(prior) | offset | LQR off (true) "
             "| LQR off (prior) | offset ok | du(eq) own | du(eq) true | gain err | mean est / true | wall s |",
             "|" + "---|" * 17]
    lines += [f"| {r['setting']} " + format_row(r) for r in rows]
    lines += ["", "Summary:", ""] + summarise(rows, systems, spec["settings"])
    args.dest.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.dest / "table.md", "\n".join(lines) + "\n")
    atomic_write_text(args.dest / "rows.json", json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
