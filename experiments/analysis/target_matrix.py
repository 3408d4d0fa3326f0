"""The precision issue's targets, every shipped 20-seed row at once: which row meets which target.

Reads the ``summary.json`` (the targets as :mod:`seed_statistics` measured them) and ``per_seed.csv`` of
each directory given (a ``--dest`` of ``experiments/analysis/seed_statistics.py``) and writes one line per directory:
each target's measured figure and whether it is met (upper case ``NO`` when missed). The speed target
also counts the seeds within 0.010 m/s from ``per_seed.csv``. Nothing is measured again.

Usage::

    python experiments/analysis/target_matrix.py experiments/results/table1_seeds20/seeds20 \
        experiments/results/table1_seeds20/feedforward --out experiments/results/table1_seeds20/targets.txt
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import sys
from pathlib import Path
from typing import Any

from mixedrl.runs import atomic_write_text

#: (column head, key in summary.json's "targets") in print order.
COLUMNS = (("action", "mixed_action_at_origin_le_0.01_every_seed"),
           ("speed<=0.010", "mixed_speed_le_0.010_every_seed"),
           ("lateral<=0.151", "mixed_lateral_le_0.151_every_seed"),
           ("ratio>=1.5", "model_over_mixed_speed_ge_1.5"),
           ("CI excl. 0", "paired_speed_difference_ci_excludes_0"),
           (">=18 of 20", "mixed_better_on_speed_on_ge_90pct_of_seeds"),
           ("cost/oracle<=1.05", "mixed_cost_within_5pct_of_oracle"))
SPEED_TARGET = 0.010


def _cell(key: str, target: dict[str, Any] | None, within: str) -> str:
    if target is None:
        return "-"
    m, ok = target["measured"], "met" if target["met"] else "NO"
    if key == "mixed_speed_le_0.010_every_seed":
        return f"{ok} {within}, worst {m:.4f}"
    if key == "paired_speed_difference_ci_excludes_0":
        return f"{ok} [{m[0]:+.4f}, {m[1]:+.4f}]"
    if key == "mixed_better_on_speed_on_ge_90pct_of_seeds":
        return f"{ok} {m}"
    if key == "mixed_cost_within_5pct_of_oracle":
        return f"{ok} {m['mixed_over_oracle']:.3f} [{m['ci'][0]:.3f}, {m['ci'][1]:.3f}]"
    if key == "mixed_action_at_origin_le_0.01_every_seed":
        return f"{ok} {m:.1e}"
    return f"{ok} {m:.3f}" if key.startswith("model_over") else f"{ok} {m:.4f}"


def row(directory: Path) -> list[str]:
    """The cells of one directory (module docstring)."""
    summary_path, csv_path = directory / "summary.json", directory / "per_seed.csv"
    for p in (summary_path, csv_path):
        if not p.is_file():
            raise SystemExit(f"source: {p} does not exist (not an output directory of seed_statistics.py)")
    targets = json.loads(summary_path.read_text()).get("targets", {})
    speeds = [float(r["speed_mae"]) for r in csv.DictReader(csv_path.open()) if r["method"] == "mixed"]
    if not speeds:
        raise SystemExit(f"source: {csv_path} has no mixed RL rows")
    within = f"{sum(s <= SPEED_TARGET for s in speeds)} of {len(speeds)}"
    return [directory.name] + [_cell(k, targets.get(k), within) for _, k in COLUMNS]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sources", type=Path, nargs="+", help="output directories of seed_statistics.py")
    ap.add_argument("--out", type=Path, required=True, help="the text file to write")
    args = ap.parse_args(argv)
    rows = [row(d) for d in args.sources]
    heads = ["row"] + [h for h, _ in COLUMNS]
    widths = [max(len(r[i]) for r in [heads, *rows]) for i in range(len(heads))]
    buf = io.StringIO()
    buf.write("The precision issue's targets for mixed RL, per shipped 20-seed row (met / NO; measured figure)\n")
    buf.write("action: worst |a_x - a_x*| [m/s^2]; speed, lateral: worst seed [m/s, m]; ratio: model / mixed speed; "
              "CI: paired 95% interval of mixed - model speed; cost: mixed / oracle with its paired interval\n\n")
    for r in [heads, *rows]:
        buf.write("  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() + "\n")
    atomic_write_text(args.out, buf.getvalue())
    sys.stdout.write(buf.getvalue())


if __name__ == "__main__":
    main()
