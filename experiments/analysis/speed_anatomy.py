"""Where on the course the speed error of Table I's Algorithm-2 runs comes from, beside the discounted LQR
with the true and the prior's noise mean, and what the course cost charges for it.

The precision issue's target "speed error <= 0.010 m/s on every seed" asks about the mean of ``|v_x - 12|``
over the whole course. For each run of a finished sweep directory this script drives the run's final
policy again on its own evaluation seeds (:func:`mixedrl.runs.eval_seeds`, with the trajectories; the
figures must equal the run's ``results.json``, or the script stops) and the two LQR references
(:func:`validation.nmpc.straight_lqr` at gamma = 0.99, the true and the prior's mean; no preview, exact
feed-forward of their mean) on the evaluation seeds of seed 0, and splits:

* the speed error into the contributions (summing to the course's mean) of three stretches of the road,
  by the car's ``X``: ``before`` the first lane change (``X < reference.x1``), the lane ``changes``
  (``x1 <= X < x2 + len2``) and ``after`` them;
* the course cost (eq. 54) into its speed part ``T q_v sum (v_x - 12)^2`` and the rest; ``target_buys``:
  for a run above 0.010 m/s, the share of its course cost the speed part would lose if its speed error
  were scaled down to 0.010 m/s (0 at or below).

It then reports per row the mean, std and worst of each figure, the share of the seed-to-seed variance of
the speed error that each stretch carries (covariance of the stretch's contribution with the total over the
total's variance; the three add to 1), and Pearson's correlation of the speed error with the course cost
over the seeds. Nothing is selected or trained.

Writes ``speed_anatomy.json`` and ``speed_anatomy.txt`` into ``--dest`` and prints the text.

Usage::

    python experiments/analysis/speed_anatomy.py runs/table1_seeds20_default --dest runs/speed_anatomy_default
"""

from __future__ import annotations

import argparse
import io
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from mixedrl.checkpoint import load_checkpoint
from mixedrl.envs.columns import stage_cost
from mixedrl.envs.evaluation import TrackingResult
from mixedrl.runs import RunDirectory, atomic_write_text, eval_seeds, make_trainer
from mixedrl.tasks import task_from_config
from seed_statistics import label, ordered
from validation.nmpc import drive, straight_lqr

STRETCHES = ("before", "changes", "after")
#: The speed-error target of the precision issue [m/s].
TARGET = 0.010
REFERENCES = {"LQR, gamma=0.99, true mean": "true", "LQR, gamma=0.99, prior mean": "prior"}


def anatomy(results: list[TrackingResult], cfg: Any) -> dict[str, float]:
    """The figures of one policy (module docstring), averaged over its courses ``results``."""
    ref = cfg.reference
    out: dict[str, list[float]] = {k: [] for k in ("speed_mae", *STRETCHES, "cost", "speed_cost")}
    for r in results:
        X = r.states[1:, 5]
        dv = r.speed_error[1:]  # the next states s_1 .. s_N, the convention of the Table I means
        n = dv.size
        parts = {"before": X < ref.x1, "changes": (X >= ref.x1) & (X < ref.x2 + ref.len2),
                 "after": X >= ref.x2 + ref.len2}
        for k, mask in parts.items():
            out[k].append(float(np.abs(dv[mask]).sum() / n))
        out["speed_mae"].append(float(np.abs(dv).mean()))
        out["cost"].append(float(r.total_cost))
        out["speed_cost"].append(float(np.sum(stage_cost(cfg, dv, 0.0, 0.0, 0.0))))  # eq. (54), speed term only
    rec = {k: float(np.mean(v)) for k, v in out.items()}
    rec["speed_share"] = rec["speed_cost"] / rec["cost"]
    s = rec["speed_mae"]
    rec["target_buys"] = rec["speed_cost"] * (1.0 - (TARGET / s) ** 2) / rec["cost"] if s > TARGET else 0.0
    return rec


def run_record(run_dir: Path) -> dict[str, Any]:
    """Drive one run's final policy on its evaluation seeds and measure it (module docstring)."""
    run = RunDirectory(run_dir)
    cfg = run.read_config()
    trainer = make_trainer(cfg)
    trainer.load_state_dict(load_checkpoint(run.path / "checkpoint.pt")["trainer"])
    ev = trainer.task.evaluate(trainer.policy, eval_seeds(cfg), keep_trajectory=True)
    stored = run.read_results()
    for k in ("speed_mae", "cost"):
        if not np.isclose(ev[k], stored[k], rtol=1e-9, atol=0.0):
            raise SystemExit(f"{run.path}: {k} driven again {ev[k]!r} differs from results.json's {stored[k]!r}")
    model_cfg = trainer.task.model.config
    return {"method": cfg.method, "seed": cfg.seed, **anatomy(ev["trajectories"], model_cfg)}


def reference_records(config: Any) -> list[dict[str, Any]]:
    """The two LQR references driven on the evaluation seeds of seed 0 of ``config`` (a run's config)."""
    cfg = task_from_config(config.task).model.config
    seeds = eval_seeds(config.replace(seed=0))
    out = []
    for name, force in REFERENCES.items():
        results = [drive(straight_lqr(cfg, gamma=0.99, force=force), cfg, seed=s)[0] for s in seeds]
        out.append({"method": name, "seed": None, **anatomy(results, cfg)})
    return out


def _variance_shares(rows: list[dict[str, Any]]) -> dict[str, float]:
    total = np.array([r["speed_mae"] for r in rows])
    var = float(np.var(total))
    if var == 0.0:
        return {k: float("nan") for k in STRETCHES}
    return {k: float(np.cov([r[k] for r in rows], total, ddof=0)[0, 1] / var) for k in STRETCHES}


def summarise(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Per row: mean, std, worst of each figure; variance shares; the speed-cost correlation."""
    out: dict[str, Any] = {}
    for m in ordered({r["method"] for r in records if r["seed"] is not None}):
        rows = [r for r in records if r["method"] == m]
        figs = {}
        for k in ("speed_mae", *STRETCHES, "speed_share", "target_buys", "cost"):
            v = np.array([r[k] for r in rows])
            figs[k] = {"mean": float(v.mean()), "std": float(v.std(ddof=1)) if v.size > 1 else 0.0,
                       "worst": float(v.max())}
        speed, cost = np.array([r["speed_mae"] for r in rows]), np.array([r["cost"] for r in rows])
        out[m] = {"runs": len(rows), "above_target": int(np.sum(speed > TARGET)), **figs,
                  "variance_share": _variance_shares(rows),
                  "corr_speed_cost": float(np.corrcoef(speed, cost)[0, 1]) if len(rows) > 2 else float("nan")}
    return out


def text(source: str, records: list[dict[str, Any]], summary: dict[str, Any]) -> str:
    buf = io.StringIO()
    p = lambda *a: print(*a, file=buf)  # noqa: E731
    p(f"Where the course speed error comes from ({source}); speed errors are contributions to the course "
      "mean |v_x - 12| [m/s]")
    p("stretches by the car's X: before = X < x1 (first lane change), changes = x1 <= X < x2 + len2, after = the rest")
    p("speed share = T q_v sum (v_x - 12)^2 / course cost; target buys = the share of the course cost the speed "
      f"part would lose at {TARGET} m/s (runs above it)")
    p("")
    p(f"{'row':38s}{'speed':>9s}{'before':>9s}{'changes':>9s}{'after':>9s}{'speed share':>13s}{'target buys':>13s}"
      f"{'cost':>8s}")
    for m, s in summary.items():
        for i, stat in enumerate(("mean", "std", "worst")):
            p(f"{label(m) if i == 0 else '':38s}" + "".join(f"{s[k][stat]:9.4f}" for k in ("speed_mae", *STRETCHES))
              + f"{s['speed_share'][stat]:13.4f}{s['target_buys'][stat]:13.4f}{s['cost'][stat]:8.2f}   ({stat})")
    for r in records:
        if r["seed"] is None:
            p(f"{r['method']:38s}" + "".join(f"{r[k]:9.4f}" for k in ("speed_mae", *STRETCHES))
              + f"{r['speed_share']:13.4f}{r['target_buys']:13.4f}{r['cost']:8.2f}")
    p("")
    p("Over the seeds: the share of the speed error's variance each stretch carries; Pearson's r of speed error "
      "and course cost; runs above the target")
    for m, s in summary.items():
        v = s["variance_share"]
        p(f"  {label(m):36s}" + "   ".join(f"{k} {v[k]:+.2f}" for k in STRETCHES)
          + f"   r(speed, cost) {s['corr_speed_cost']:+.2f}   above {TARGET}: {s['above_target']} of {s['runs']}")
    return buf.getvalue()


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sweep", type=Path, help="a finished sweep directory of Algorithm-2 runs")
    ap.add_argument("--dest", type=Path, required=True, help="directory for speed_anatomy.json / .txt")
    args = ap.parse_args(argv)
    doc_path = args.sweep / "sweep.json"
    if not doc_path.is_file():
        raise SystemExit(f"sweep: {doc_path} does not exist (not a finished sweep directory)")
    doc = json.loads(doc_path.read_text())
    run_dirs = [args.sweep / r["run_dir"] for r in doc["runs"] if not r.get("error")
                and (args.sweep / r["run_dir"] / "checkpoint.pt").is_file()]
    if not run_dirs:
        raise SystemExit(f"sweep: no finished runs with a checkpoint under {args.sweep}")
    records = [run_record(d) for d in tqdm(run_dirs, desc="runs", file=sys.stderr)]
    records += reference_records(RunDirectory(run_dirs[0]).read_config())
    summary = summarise(records)
    out = text(str(args.sweep), records, summary)
    args.dest.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.dest / "speed_anatomy.json",
                      json.dumps({"source": str(args.sweep), "target": TARGET, "summary": summary,
                                  "records": records}, indent=1) + "\n")
    atomic_write_text(args.dest / "speed_anatomy.txt", out)
    sys.stdout.write(out)


if __name__ == "__main__":
    main()
