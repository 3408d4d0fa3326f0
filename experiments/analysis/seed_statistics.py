"""Per-seed statistics of Table I's Algorithm-2 rows: intervals, paired differences, win counts, the
precision yardstick, and the targets of the precision issue, from a finished sweep.

Reads one or more sources and writes into ``--dest``. A source is a sweep directory of ``mixedrl sweep``
(``sweep.json`` and each run's ``results.json``; for example ``experiments/studies/table1_seeds20.toml``) or the
``per_seed.csv`` of an earlier analysis by this script (its rows as they were measured). A row of the
tables is a method, or ``method[variant]`` for the runs of a spec's ``[variants.NAME]`` (for example
``ddpg[paper]`` and ``ddpg[ddpg_long]`` of ``experiments/studies/table1_seeds20_ddpg.toml``); two sources may not
give the same row.

* ``per_seed.csv``: one row per method and seed (lateral and speed errors, course cost, the action error
  at the equilibrium against the discounted LQ optimum for the method's own noise mean, ``policy_gap``);
* ``summary.json``: per row mean, sample std and 95% percentile-bootstrap interval of the mean of each
  figure (:func:`mixedrl.tables.bootstrap_interval`); per pair of methods (mixed - model-driven, mixed -
  oracle, and mixed RL against every further row such as DDPG's) the paired mean difference with its 95%
  interval (seeds resampled with both values, :func:`mixedrl.tables.paired_interval`), the ratio of means
  with its interval, and the seeds on which the first is better; the issue's targets, each with its measured figure and whether it is met;
* ``table.txt``: the same as text;
* ``per_seed.png``: every seed visible, mixed RL against model-driven RL and the oracle (needs matplotlib).

Usage::

    python experiments/analysis/seed_statistics.py runs/table1_seeds20 --dest experiments/results/table1_seeds20/seeds20
    python experiments/analysis/seed_statistics.py runs/table1_seeds20_default --feedforward lq_ss \
        --calibration 0 --dest experiments/results/table1_seeds20/default_lqss
    python experiments/analysis/seed_statistics.py experiments/results/table1_seeds20/seeds20/per_seed.csv runs/table1_seeds20_ddpg \
        --dest experiments/results/table1_seeds20/seeds20_ddpg

With ``--feedforward lq_ss`` every run's final checkpoint is evaluated again with ``algorithm.feedforward =
"lq_ss"`` (the same trained actor shifted, near the discounted LQ optimum's steady state for the method's own
noise mean, to the optimum's action there; docs page ``precision.rst``) on the run's own evaluation seeds: a
paired comparison of the two policies each run would deploy (sweep directories only); ``--calibration K`` sets
``algorithm.feedforward_calibration`` of that evaluation (0: the shift alone; default: the run's config, read at
today's default where it predates the setting). The rows evaluated with
the retired ``--feedforward lq`` (``feedforward``, ``default_feedforward``) are re-derived at commit c44231f.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
from pathlib import Path
from typing import Any

import numpy as np

from tqdm import tqdm

from mixedrl.config import FEEDFORWARDS
from mixedrl.runs import RunDirectory, atomic_write_bytes, atomic_write_text, evaluate_run
from mixedrl.tables import bootstrap_interval, csv_text, mean_std, paired_interval

METHODS = ("mixed", "model", "oracle")
LABELS = {"mixed": "Mixed RL", "model": "Model-driven RL", "oracle": "Oracle (true noise)"}
FIGURES = ("lateral_mae", "speed_mae", "cost", "ax_error", "delta_error")
UNITS = {"lateral_mae": "m", "speed_mae": "m/s", "cost": "", "ax_error": "m/s^2", "delta_error": "rad"}
#: The pairs compared seed by seed: (first, second); "better" = the first's figure is smaller. Mixed RL is
#: also compared with every further row (:func:`pairs`).
PAIRS = (("mixed", "model"), ("mixed", "oracle"), ("oracle", "model"))
#: Labels of the rows of other methods' variants (``method[variant]``); others are labelled by their key.
VARIANT_LABELS = {"ddpg[paper]": "DDPG, paper budget", "ddpg[ddpg_long]": "DDPG, 16x budget"}
#: The columns of ``per_seed.csv`` read back as numbers (:func:`load_csv_rows`); the others stay strings.
NUMERIC = ("lateral_mae", "speed_mae", "cost", "ax_error", "delta_error", "ax", "ax_optimum", "ax_error_learned",
           "gain_error_rel", "left_road")
INTEGER = ("seed", "iterations", "batch_size_runs")


def row_key(method: str, variant: str | None) -> str:
    """The table row of a run: its method, or ``method[variant]`` for a spec's variant."""
    return method if not variant else f"{method}[{variant}]"


def label(key: str) -> str:
    """The printed name of a row."""
    return LABELS.get(key) or VARIANT_LABELS.get(key) or key


def ordered(keys: Any) -> list[str]:
    """Rows in print order: :data:`METHODS` first, then the others sorted."""
    keys = set(keys)
    return [m for m in METHODS if m in keys] + sorted(keys - set(METHODS))


def pairs(keys: Any) -> list[tuple[str, str]]:
    """The pairs compared seed by seed among the rows ``keys``: :data:`PAIRS`, then mixed RL against every
    further row."""
    keys = set(keys)
    extra = [("mixed", k) for k in ordered(keys) if k not in METHODS]
    return [(a, b) for a, b in [*PAIRS, *extra] if a in keys and b in keys]


#: What each evaluation-time ``algorithm.feedforward`` does to the trained actor (the table's heading).
SHIFTS = {"lq_ss": "shifted, near the LQ optimum's steady state for each method's own noise mean (within "
                   "algorithm.feedforward_width), to the optimum's action there: the library default 'auto' "
                   "on this task"}


def _evaluated(path: Path, feedforward: str, calibration: int | None = None) -> dict[str, Any]:
    """A run's final policy evaluated with ``algorithm.feedforward = feedforward`` (and
    ``algorithm.feedforward_calibration = calibration`` when given; :func:`evaluate_run`), in the keys of
    ``results.json`` that :func:`load_rows` reads."""
    out = evaluate_run(path, feedforward=feedforward, calibration=calibration)
    m = out["metrics"]
    return {"lateral_mae": float(m["lateral_mae"]), "speed_mae": float(m["speed_mae"]), "cost": float(m["cost"]),
            "final": {"terminated": m.get("terminated")}, "iterations": out["iteration"],
            "policy_gap": out["policy_gap"]}


def load_rows(sweep: Path, feedforward: str | None = None, partial: bool = False, calibration: int | None = None
              ) -> dict[str, list[dict[str, Any]]]:
    """Per row (:func:`row_key`), the sweep's finished runs sorted by seed: the figures of :data:`FIGURES`.

    A sweep with unfinished runs (no results yet) is refused unless ``partial``; with it, only the finished
    runs are read.

    With ``feedforward`` (``"lq_ss"``) each run's final checkpoint is evaluated again with
    ``algorithm.feedforward = feedforward`` (:func:`mixedrl.runs.evaluate_run`: the same trained actor,
    shifted near the LQ optimum's steady state for the method's own noise mean; the same evaluation seeds), and
    ``action_error_learned`` keeps the actor's own error from ``results.json``.
    """
    doc = json.loads((sweep / "sweep.json").read_text())
    rows: dict[str, list[dict[str, Any]]] = {}
    records = [r for r in doc["runs"] if r["error"] is None]
    unfinished = [r["name"] for r in records if r.get("results") is None]
    if unfinished and not partial:
        raise ValueError(f"{sweep}: {len(unfinished)} runs have no results yet ({', '.join(unfinished[:3])}, ...); "
                         f"finish the sweep (mixedrl sweep --resume) or pass --partial to read the finished ones")
    records = [r for r in records if r.get("results") is not None]
    for rec in tqdm(records, desc=f"evaluate (feedforward={feedforward})", disable=feedforward is None):
        res = RunDirectory(sweep / rec["run_dir"]).read_results()
        if "lateral_mae" not in res:
            raise ValueError(f"{sweep / rec['run_dir']}: task {res.get('task')!r} has no course errors; this "
                             f"analysis is for the double lane change (Table I)")
        learned_err = ((res.get("policy_gap") or {}).get("action_error") or [None, None])[1]
        if feedforward is not None:
            res = {**res, **_evaluated(sweep / rec["run_dir"], feedforward, calibration)}
        gap = res.get("policy_gap") or {}
        err = gap.get("action_error") or [None, None]
        variant = (rec.get("point") or {}).get("variant")
        rows.setdefault(row_key(rec["method"], variant), []).append({
            "method": rec["method"], **({"variant": variant} if variant else {}), "seed": rec["seed"],
            "lateral_mae": res["lateral_mae"],
            "speed_mae": res["speed_mae"], "cost": res["cost"],
            "ax_error": None if err[1] is None else abs(err[1]),
            "delta_error": None if err[0] is None else abs(err[0]),
            "ax": (gap.get("action") or [None, None])[1], "ax_optimum": (gap.get("optimum_action") or [None, None])[1],
            "ax_error_learned": None if learned_err is None else abs(learned_err),
            "gain_error_rel": gap.get("gain_error_rel"),
            "trained_feedforward": res.get("feedforward", "learned"),
            "left_road": res.get("final", {}).get("terminated"), "iterations": res["iterations"],
            "batch_size_runs": res.get("batch_size_runs", 1)})
    return {m: sorted(v, key=lambda r: r["seed"]) for m, v in rows.items()}


def load_csv_rows(path: Path) -> dict[str, list[dict[str, Any]]]:
    """Per row, the rows of a ``per_seed.csv`` written by this script (empty cells are ``None``).

    Raises
    ------
    ValueError
        If the file lacks a column :func:`load_rows` writes or a cell of a numeric column is not a number.
    """
    with open(path, newline="") as fh:
        records = list(csv.DictReader(fh))
    missing = [c for c in ("method", "seed", *FIGURES) if records and c not in records[0]]
    if not records or missing:
        raise ValueError(f"{path}: not a per_seed.csv of this script ("
                         + (f"missing columns {missing})" if records else "no rows)"))
    rows: dict[str, list[dict[str, Any]]] = {}
    for i, rec in enumerate(records, start=2):
        row: dict[str, Any] = {}
        for key, cell in rec.items():
            try:
                row[key] = (None if cell == "" else int(cell) if key in INTEGER
                            else float(cell) if key in NUMERIC else cell)
            except ValueError:
                raise ValueError(f"{path}, line {i}: column {key!r} is {cell!r}, not a number") from None
        rows.setdefault(row_key(row["method"], row.get("variant")), []).append(row)
    return {m: sorted(v, key=lambda r: r["seed"]) for m, v in rows.items()}


def load_sources(sources: list[Path], feedforward: str | None = None, partial: bool = False,
                 calibration: int | None = None) -> tuple[dict[str, list[dict[str, Any]]], dict[str, list[str]]]:
    """The rows of every source (a sweep directory or a ``per_seed.csv``), merged, and per source the rows
    it gave (``partial``: a sweep's finished runs only, :func:`load_rows`).

    Raises
    ------
    ValueError
        If two sources give the same row, ``feedforward`` is asked of a ``per_seed.csv``, or a source is
        neither a sweep directory nor a file.
    """
    rows: dict[str, list[dict[str, Any]]] = {}
    given: dict[str, list[str]] = {}
    for src in sources:
        if src.is_dir():
            got = load_rows(src, feedforward, partial, calibration)
        elif src.is_file():
            if feedforward is not None:
                raise ValueError(f"{src}: --feedforward evaluates checkpoints again; it needs sweep directories, "
                                 f"not a per_seed.csv")
            got = load_csv_rows(src)
        else:
            raise ValueError(f"{src}: no such sweep directory or per_seed.csv")
        twice = sorted(set(got) & set(rows))
        if twice:
            raise ValueError(f"{src}: rows {twice} also come from an earlier source")
        rows.update(got)
        given[str(src)] = ordered(got)
    return rows, given


def statistics(rows: dict[str, list[dict[str, Any]]]) -> dict[str, Any]:
    """The content of ``summary.json`` (see the module docstring)."""
    out: dict[str, Any] = {"methods": {}, "pairs": {}}
    for m, runs in rows.items():
        entry: dict[str, Any] = {"seeds": [r["seed"] for r in runs]}
        for f in FIGURES:
            vals = [r[f] for r in runs if r[f] is not None]
            mean, std = mean_std(vals)
            low, high = bootstrap_interval(vals)
            entry[f] = {"mean": mean, "std": std, "ci_low": low, "ci_high": high,
                        "min": float(np.min(vals)) if vals else None, "max": float(np.max(vals)) if vals else None}
        out["methods"][m] = entry
    for a, b in pairs(rows):
        common = sorted(set(r["seed"] for r in rows[a]) & set(r["seed"] for r in rows[b]))
        ra = {r["seed"]: r for r in rows[a]}
        rb = {r["seed"]: r for r in rows[b]}
        pair: dict[str, Any] = {"seeds": common}
        for f in FIGURES:
            xa = [ra[s][f] for s in common]
            xb = [rb[s][f] for s in common]
            if any(v is None for v in xa + xb):
                continue
            diff, dl, dh = paired_interval(xa, xb)
            ratio, rl, rh = paired_interval(xb, xa, statistic="ratio")
            pair[f] = {"difference": diff, "difference_ci": [dl, dh], f"{b}_over_{a}": ratio,
                       "ratio_ci": [rl, rh], "wins": int(sum(x < y for x, y in zip(xa, xb))), "n": len(common)}
        out["pairs"][f"{a}-{b}"] = pair
    out["targets"] = targets(rows, out)
    return out


def targets(rows: dict[str, list[dict[str, Any]]], stats: dict[str, Any]) -> dict[str, Any]:
    """The precision issue's targets (its numbers), each ``{"measured": ..., "met": bool}``."""
    t: dict[str, Any] = {}
    mixed = rows.get("mixed", [])
    if mixed:
        worst_ax = max(r["ax_error"] for r in rows["mixed"])
        t["mixed_action_at_origin_le_0.01_every_seed"] = {"measured": worst_ax, "met": worst_ax <= 0.01}
        worst_v = max(r["speed_mae"] for r in mixed)
        worst_y = max(r["lateral_mae"] for r in mixed)
        t["mixed_speed_le_0.010_every_seed"] = {"measured": worst_v, "met": worst_v <= 0.010}
        t["mixed_speed_le_0.0072_every_seed (stretch)"] = {"measured": worst_v, "met": worst_v <= 0.0072}
        t["mixed_lateral_le_0.151_every_seed"] = {"measured": worst_y, "met": worst_y <= 0.151}
    for m in ("model", "oracle"):
        if m in rows:
            worst = max(r["ax_error"] for r in rows[m])
            t[f"{m}_action_at_origin_le_0.01_every_seed"] = {"measured": worst, "met": worst <= 0.01}
    pair = stats["pairs"].get("mixed-model", {}).get("speed_mae")
    if pair:
        t["model_over_mixed_speed_ge_1.5"] = {"measured": pair["model_over_mixed"], "met": pair["model_over_mixed"] >= 1.5}
        lo, hi = pair["difference_ci"]
        t["paired_speed_difference_ci_excludes_0"] = {"measured": [lo, hi], "met": hi is not None and hi < 0.0}
        t["mixed_better_on_speed_on_ge_90pct_of_seeds"] = {"measured": f"{pair['wins']} of {pair['n']}",
                                                           "met": pair["wins"] >= 0.9 * pair["n"]}
    cost = stats["pairs"].get("mixed-oracle", {}).get("cost")
    if cost:
        ratio = 1.0 / cost["oracle_over_mixed"]
        # mixed / oracle: invert the interval of oracle / mixed
        lo, hi = cost["ratio_ci"]
        t["mixed_cost_within_5pct_of_oracle"] = {"measured": {"mixed_over_oracle": ratio,
                                                              "ci": [1.0 / hi, 1.0 / lo] if lo and hi else None},
                                                 "met": hi is not None and lo is not None and 1.0 / lo <= 1.05}
    return t


def format_table(rows: dict[str, list[dict[str, Any]]], stats: dict[str, Any], feedforward: str | None = None,
                 sources: dict[str, list[str]] | None = None, calibration: int | None = None) -> str:
    """``table.txt`` (with ``sources``, from more than one, a line naming each source's rows)."""
    n = max((len(v) for v in rows.values()), default=0)
    what = "Algorithm-2 rows" if set(rows) <= set(METHODS) else "rows"
    lines = [f"Table I, {what} over {n} seeds: mean ± sample std [95% bootstrap interval of the mean]"]
    if sources and len(sources) > 1:
        lines += [f"Rows from {src}: {', '.join(keys)}" for src, keys in sources.items()]
    if feedforward is not None:
        lines.append(f"Policies evaluated with algorithm.feedforward = {feedforward!r} (the same trained actors, "
                     f"{SHIFTS.get(feedforward, 'shifted')})"
                     + ("" if calibration is None else f"; algorithm.feedforward_calibration = {calibration}"))
    trained = sorted({r.get("trained_feedforward") or "learned" for runs in rows.values() for r in runs} - {"learned"})
    if trained:
        lines.append(f"Runs with algorithm.feedforward = {', '.join(map(repr, trained))}")
    lines.append("")
    head = f"{'method':<22}" + "".join(f"{f + (' [' + UNITS[f] + ']' if UNITS[f] else ''):>36}" for f in FIGURES[:3])
    lines += [head, "-" * len(head)]
    for m in ordered(stats["methods"]):
        e = stats["methods"][m]
        cells = "".join(f"{e[f]['mean']:>12.4g} ± {e[f]['std']:<7.2g}[{e[f]['ci_low']:.4g}, {e[f]['ci_high']:.4g}]"
                        .rjust(36) for f in FIGURES[:3])
        lines.append(f"{label(m):<22}{cells}")
    lines += ["", "Action at the equilibrium against the discounted LQ optimum for the method's own noise mean "
              "(|a - a*|, policy_gap): mean ± std [interval], worst seed"]
    for m in ordered(stats["methods"]):
        e = stats["methods"][m]
        lines.append(f"  {label(m):<22} a_x {e['ax_error']['mean']:.4f} ± {e['ax_error']['std']:.4f} "
                     f"[{e['ax_error']['ci_low']:.4f}, {e['ax_error']['ci_high']:.4f}], worst "
                     f"{e['ax_error']['max']:.4f} m/s^2;  delta {e['delta_error']['mean']:.5f}, worst "
                     f"{e['delta_error']['max']:.5f} rad")
        if feedforward is not None:
            own = [r["ax_error_learned"] for r in rows[m] if r["ax_error_learned"] is not None]
            lines.append(f"  {'':<22} (the learned actor's own a_x error: {np.mean(own):.4f}, worst "
                         f"{np.max(own):.4f} m/s^2)")
    gains = {m: [r.get("gain_error_rel") for r in rows[m]] for m in ordered(rows)}
    if gains and all(v is not None for vals in gains.values() for v in vals):
        lines += ["", "Gain at the equilibrium against the LQ optimum's (||du/dx + L|| / ||L||, policy_gap): "
                  "mean, worst seed"]
        lines += [f"  {label(m):<22} {np.mean(v):.4f}, worst {np.max(v):.4f}" for m, v in gains.items()]
    lines += ["", "Paired over the same seeds (first - second; wins: seeds where the first is smaller):"]
    for key, pair in stats["pairs"].items():
        a, b = key.split("-", 1)
        for f in ("lateral_mae", "speed_mae", "cost", "ax_error"):
            if f not in pair:
                continue
            p = pair[f]
            lo, hi = p["difference_ci"]
            rlo, rhi = p["ratio_ci"]
            lines.append(f"  {a} - {b:<7} {f:<12} diff {p['difference']:+.4g} [{lo:+.4g}, {hi:+.4g}]   "
                         f"{b}/{a} {p[f'{b}_over_{a}']:.3f} [{rlo:.3f}, {rhi:.3f}]   {a} better on "
                         f"{p['wins']} of {p['n']}")
    lines += ["", "Targets of the precision issue:"]
    for name, tgt in stats["targets"].items():
        lines.append(f"  {name}: {'met' if tgt['met'] else 'MISSED'} (measured {_fmt(tgt['measured'])})")
    return "\n".join(lines)


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, list):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    if isinstance(v, dict):
        return ", ".join(f"{k} {_fmt(x)}" for k, x in v.items())
    return str(v)


def make_figure(rows: dict[str, list[dict[str, Any]]], path: Path, feedforward: str | None = None) -> Path | None:
    """``per_seed.png``: per figure, every seed's value for each method, seeds on the x axis (with
    ``feedforward`` the last panel is the learned actor's own action error, the evaluated one's being 0)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # pragma: no cover - optional extra
        return None
    fig, axes = plt.subplots(1, 4, figsize=(15, 3.4))
    colors = {"mixed": "C0", "model": "C1", "oracle": "k"}
    extra = iter(("C2", "C3", "C4", "C5", "C6", "C8", "C9"))
    colors.update({m: next(extra, "C7") for m in ordered(rows) if m not in colors})
    last = "ax_error" if feedforward is None else "ax_error_learned"
    for ax, f in zip(axes, ("speed_mae", "lateral_mae", "cost", last)):
        for m in ordered(rows):
            ax.plot([r["seed"] for r in rows[m]], [r[f] for r in rows[m]], "o", ms=4, color=colors[m],
                    label=label(m), alpha=0.8)
        ax.set_xlabel("seed")
        unit = UNITS.get(f, UNITS["ax_error"])
        ax.set_title(("learned actor's ax_error" if f == "ax_error_learned" else f) + (f" [{unit}]" if unit else ""))
        ax.set_yscale("log" if f in ("cost", last) else "linear")
    if feedforward is not None:
        fig.suptitle(f"algorithm.feedforward = {feedforward!r} (the same trained actors)", fontsize=9)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    plt.close(fig)
    atomic_write_bytes(path, buffer.getvalue())
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("sources", type=Path, nargs="+",
                        help="finished sweep directories (sweep.json) or per_seed.csv files of this script")
    parser.add_argument("--dest", type=Path, required=True, help="where to write the tables and the figure")
    parser.add_argument("--feedforward", choices=FEEDFORWARDS, default=None,
                        help="evaluate each run's final checkpoint again with this algorithm.feedforward "
                             "('lq_ss': the actor shifted near the LQ optimum's steady state to the optimum's "
                             "action there, locally)")
    parser.add_argument("--calibration", type=int, default=None, metavar="K",
                        help="with --feedforward: algorithm.feedforward_calibration of that evaluation (0: the shift "
                             "alone; default: the run's config)")
    parser.add_argument("--partial", action="store_true",
                        help="read only the finished runs of an unfinished sweep (default: refuse it)")
    args = parser.parse_args(argv)
    try:
        if args.calibration is not None and args.feedforward is None:
            raise ValueError("--calibration: it sets the calibration of --feedforward's evaluation; give --feedforward")
        rows, sources = load_sources(args.sources, args.feedforward, args.partial, args.calibration)
    except ValueError as exc:
        parser.error(str(exc))
    if not rows:
        parser.error(f"{', '.join(map(str, args.sources))}: no finished run")
    stats = statistics(rows)
    args.dest.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.dest / "per_seed.csv", csv_text([r for m in ordered(rows) for r in rows[m]]))
    atomic_write_text(args.dest / "summary.json", json.dumps(stats, indent=2) + "\n")
    table = format_table(rows, stats, args.feedforward, sources, args.calibration)
    atomic_write_text(args.dest / "table.txt", table + "\n")
    make_figure(rows, args.dest / "per_seed.png", args.feedforward)
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
