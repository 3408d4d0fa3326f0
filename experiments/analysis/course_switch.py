"""Where the outlying seeds of the double lane change come from: the critic's loss after the course sampler
switches its copies onto the course, against the run's course speed error.

The DLC experiment's sampler (``sampler.name = "dlc_course"``) restarts its course copies on the course from
iteration ``sampler.course_start`` on (500 in the experiment configuration); before it every copy restarts in
the wide training distribution. For each Algorithm-2 run of a finished sweep directory this script reads
``metrics.csv`` and ``config.json`` and measures, all from training-time logs and the run's periodic
evaluations:

* ``before``: the median critic loss over the ``--window`` iterations up to ``course_start``;
* ``rise``: the largest critic loss over the ``3 --window`` iterations after ``course_start``, over ``before``
  (and the iteration of that peak);
* ``speed_at_switch``: the evaluated course speed error at iteration ``course_start`` (the run must evaluate
  there: ``run.eval_every`` divides it), ``final``: at the last evaluation, and ``change = final -
  speed_at_switch``;

and reports Spearman's rank correlation (:func:`scipy.stats.spearmanr`) of ``rise`` with ``change`` and with
``final``, pooled over the runs and per method, and the runs of largest final speed error. Nothing is
selected: it describes runs that are already shipped.

Writes ``course_switch.json`` and ``course_switch.txt`` into ``--dest`` and prints the text.

Usage::

    python experiments/analysis/course_switch.py runs/table1_seeds20_default --dest runs/course_switch_default
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

from mixedrl.runs import atomic_write_text
from seed_statistics import label, ordered, row_key

#: Runs listed in the text, by largest final speed error.
WORST = 8


def run_record(run: Path, config: dict[str, Any], window: int) -> dict[str, Any]:
    """The measurements of one run directory, ``config`` its ``config.json`` (see the module docstring).

    Raises
    ------
    ValueError
        If the run has no course sampler, too few iterations after ``course_start``, or no evaluation at
        ``course_start``; the message names the run.
    """
    start = config.get("sampler", {}).get("course_start")
    if start is None:
        raise ValueError(f"{run}: sampler {config.get('sampler', {}).get('name')!r} has no course_start")
    start = int(start)
    loss: dict[int, float] = {}
    speed: dict[int, float] = {}
    with (run / "metrics.csv").open(newline="") as fh:
        for row in csv.DictReader(fh):
            k = int(row["iteration"])
            loss[k] = float(row["train/critic_loss"])
            if row.get("eval/speed_mae"):
                speed[k] = float(row["eval/speed_mae"])
    end = start + 3 * window
    after = [k for k in range(start + 1, end + 1) if k in loss]
    ahead = [loss[k] for k in range(start - window + 1, start + 1) if k in loss]
    if len(after) < end - start or len(ahead) < window:
        raise ValueError(f"{run}: the critic loss is not logged over iterations {start - window + 1}-{end}")
    if start not in speed:
        raise ValueError(f"{run}: no evaluation at the course start (iteration {start}); run.eval_every must divide it")
    before = float(np.median(ahead))
    peak_at = max(after, key=lambda k: loss[k])
    last = max(speed)
    variant = run.name.split("__")[0][len("variant="):] if run.name.startswith("variant=") else ""
    return {"method": config["method"], "seed": int(config["seed"]), "row": row_key(config["method"], variant),
            "course_start": start, "before": before,
            "peak": loss[peak_at], "peak_iteration": peak_at, "rise": loss[peak_at] / before,
            "speed_at_switch": speed[start], "final": speed[last], "final_iteration": last,
            "change": speed[last] - speed[start]}


def correlations(records: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """Spearman's rho and its p-value of ``rise`` against ``change`` and against ``final``."""
    rise = [r["rise"] for r in records]
    out = {}
    for key in ("change", "final"):
        res = stats.spearmanr(rise, [r[key] for r in records])
        out[key] = {"rho": float(res.statistic), "p": float(res.pvalue), "runs": len(records)}
    return out


def analyse(sweep: Path, window: int) -> dict[str, Any]:
    """Every Algorithm-2 run of the sweep directory, with the correlations pooled and per method."""
    runs = sorted(p for p in (sweep / "runs").iterdir() if (p / "metrics.csv").is_file()) \
        if (sweep / "runs").is_dir() else []
    configs = {p: json.loads((p / "config.json").read_text()) for p in runs}
    records = [run_record(p, c, window) for p, c in configs.items() if c["method"] != "ddpg"]
    if len(records) < 3:
        raise ValueError(f"sweep: {sweep} holds {len(records)} Algorithm-2 runs with metrics; need 3 or more")
    present = {r["row"] for r in records}
    variants = sorted({r["row"].partition("[")[2].rstrip("]") for r in records})
    methods = ordered({r["method"] for r in records})
    rows = [row_key(m, v) for v in variants for m in methods if row_key(m, v) in present]
    per = {m: [r for r in records if r["row"] == m] for m in rows}
    return {"source": str(sweep), "window": window, "runs": records, "pooled": correlations(records),
            "methods": {m: {"median_rise": float(np.median([r["rise"] for r in rs])),
                            "max_rise": float(np.max([r["rise"] for r in rs])),
                            "correlation": correlations(rs) if len(rs) >= 3 else None}
                        for m, rs in per.items()}}


def _rho(c: dict[str, Any] | None, key: str) -> str:
    if c is None or math.isnan(c[key]["rho"]):
        return "n/a"
    return f"{c[key]['rho']:+.2f} (p {c[key]['p']:.2g}, {c[key]['runs']} runs)"


def render(doc: dict[str, Any]) -> str:
    w = doc["window"]
    lines = [f"The critic's loss after the course switch against the course speed error ({doc['source']})",
             f"rise = largest critic loss over the {3 * w} iterations after sampler.course_start "
             f"/ median over the {w} before; change = final speed error - speed error at course_start [m/s]", "",
             "Spearman's rank correlation of the rise with the change and with the final speed error:",
             f"  {'all runs':<22} change {_rho(doc['pooled'], 'change')}   final {_rho(doc['pooled'], 'final')}"]
    for m, d in doc["methods"].items():
        lines.append(f"  {label(m):<22} change {_rho(d['correlation'], 'change')}   "
                     f"final {_rho(d['correlation'], 'final')}   median rise {d['median_rise']:.1f}, "
                     f"largest {d['max_rise']:.1f}")
    records = doc["runs"]
    rank = {id(r): i + 1 for i, r in enumerate(sorted(records, key=lambda r: -r["rise"]))}
    lines += ["", f"The {WORST} runs of largest final speed error (rise rank among {len(records)}, 1 = largest):",
              f"  {'run':<26}{'speed at switch':>16}{'final':>9}{'change':>9}{'rise':>7}{'rank':>6}{'peak at':>9}"]
    for r in sorted(records, key=lambda r: -r["final"])[:WORST]:
        lines.append(f"  {label(r['row']) + ' seed ' + str(r['seed']):<26}{r['speed_at_switch']:>16.4f}"
                     f"{r['final']:>9.4f}{r['change']:>+9.4f}{r['rise']:>7.1f}{rank[id(r)]:>6}{r['peak_iteration']:>9}")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sweep", type=Path, help="a finished sweep directory of mixedrl sweep (DLC course sampler)")
    parser.add_argument("--dest", type=Path, required=True, help="directory for course_switch.json and .txt")
    parser.add_argument("--window", type=int, default=100, help="iterations of the 'before' window (default 100)")
    args = parser.parse_args(argv)
    if args.window < 1:
        parser.error(f"--window: must be >= 1, got {args.window}")
    try:
        doc = analyse(args.sweep, args.window)
    except (ValueError, OSError, KeyError) as exc:
        parser.error(str(exc))
    text = render(doc)
    args.dest.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.dest / "course_switch.json", json.dumps(doc, indent=1) + "\n")
    atomic_write_text(args.dest / "course_switch.txt", text)
    sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
