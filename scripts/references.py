"""Regenerate the reference controllers' measurements for docs/references.rst ("How good is it").

Runs every row of :data:`validation.nmpc.REFERENCE_SETTINGS` (whole-course optimum; NMPC 2 s with the
true and the prior mean at gamma = 0.99 and 1; LQR at gamma = 0.99 and 1; the NMPC 2 s *without
preview* -- predicting on the reference's tangent at the car's X -- with the true and the prior mean at
gamma = 0.99 and 1; the LQR with the prior's mean at gamma = 0.99 and 1) on the reproduction's course
with noise seeds 0, 1, 2 and writes, into ``docs/_static/references/`` (or ``--out``):

* ``references.json`` -- every row (means over seeds, per-seed figures, settings), written after each
  row (atomically), so an interrupted run keeps the rows done;
* ``references.csv`` -- the table of the docs page;
* ``trajectories.npz`` -- seed 0's ``X``, ``e_y``, ``v_x - 12`` and inputs of every row (for the figures;
  key suffix = the row's index in ``REFERENCE_SETTINGS``);
* ``trajectory.png`` (path overlay and lateral error vs ``X``) and ``speed_error.png`` (speed error vs
  ``X``) of every row but the no-preview NMPC's; ``no_preview.png`` (lateral and speed error vs ``X``)
  of the no-preview NMPC rows beside the NMPC with preview and the LQRs at gamma = 0.99.

Needs the ``nmpc`` extra (CasADi). About 25 minutes in one process on the 2-core development machine
with other jobs running (NMPC re-solved every step; each run logs its wall time at the end). Rows
already in ``references.json`` are kept, not re-run (``--fresh`` re-runs everything); ``--only I ...``
runs the rows of those indices (e.g. rows added to ``REFERENCE_SETTINGS``, merged into the existing
files in the settings' order); ``--merge DIR`` adds the rows of another output directory (e.g. a second
process run with ``--only``); ``--figures-only`` redraws the figures and the CSV.

Usage: ``python scripts/references.py [--out DIR] [--seeds 0 1 2] [--period 1] [--only I ...] [--merge DIR]
[--fresh] [--figures-only]``
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import logging
import time
from pathlib import Path

import numpy as np

from mixedrl.envs import DoubleLaneChangeModel
from mixedrl.runs import atomic_write_bytes, atomic_write_text
from validation.nmpc import REFERENCE_SETTINGS, jsonable, reference_row

DEFAULT_OUT = Path(__file__).resolve().parents[1] / "docs" / "_static" / "references"
CSV_COLUMNS = ("method", "lateral_mae", "speed_mae", "cost", "solve_ms_mean", "solve_ms_max", "step_ms_mean", "period")
STYLE = {"whole-course optimum": ("k", "-"),
         "NMPC 2 s, gamma=1, true mean": ("tab:blue", "-"),
         "NMPC 2 s, gamma=1, prior mean": ("tab:blue", ":"),
         "NMPC 2 s, gamma=0.99, true mean": ("tab:green", "-"),
         "NMPC 2 s, gamma=0.99, prior mean": ("tab:green", ":"),
         "LQR, gamma=1, true mean": ("tab:red", "-"),
         "LQR, gamma=0.99, true mean": ("tab:orange", "-"),
         "LQR, gamma=1, prior mean": ("tab:red", ":"),
         "LQR, gamma=0.99, prior mean": ("tab:orange", ":"),
         "NMPC 2 s, gamma=1, true mean, no preview": ("tab:purple", "-"),
         "NMPC 2 s, gamma=1, prior mean, no preview": ("tab:purple", ":"),
         "NMPC 2 s, gamma=0.99, true mean, no preview": ("tab:brown", "-"),
         "NMPC 2 s, gamma=0.99, prior mean, no preview": ("tab:brown", ":")}
#: The rows of no_preview.png besides the no-preview NMPC rows.
NO_PREVIEW_COMPANIONS = ("NMPC 2 s, gamma=0.99, true mean", "LQR, gamma=0.99, true mean",
                         "LQR, gamma=0.99, prior mean")


def _no_preview(label: str) -> bool:
    return dict(REFERENCE_SETTINGS)[label].get("preview", True) is False


def write_csv(path: Path, rows: list[dict]) -> None:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=CSV_COLUMNS, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: (f"{v:.4g}" if isinstance(v, float) else ("" if v is None else v))
                         for k, v in row.items()})
    atomic_write_text(path, buf.getvalue())


def make_figures(out: Path) -> list[Path]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    data = np.load(out / "trajectories.npz")
    rows = json.loads((out / "references.json").read_text())
    index = {label: i for i, (label, _) in enumerate(REFERENCE_SETTINGS)}
    every = [(index[r["method"]], r["method"]) for r in rows]
    labels = [(i, label) for i, label in every if not _no_preview(label)]
    ref = DoubleLaneChangeModel().reference
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 6.5), sharex=True)
    X = np.linspace(0.0, 125.0, 1000)
    ax1.plot(X, ref.lateral(X), color="0.6", lw=4, alpha=0.5, label="reference")
    for i, label in labels:
        c, ls = STYLE.get(label, (None, "-"))
        Xi, ey = data[f"X_{i}"], data[f"ey_{i}"]
        ax1.plot(Xi, ref.lateral(Xi) + ey, color=c, ls=ls, lw=1.0, label=label)
        ax2.plot(Xi, ey, color=c, ls=ls, lw=1.0, label=label)
    ax1.set_ylabel("Y [m]")
    ax1.legend(fontsize=7, ncol=2)
    ax1.set_title("Double lane change, seed 0: reference controllers")
    ax2.set_ylabel("lateral error e_y [m]")
    ax2.set_xlabel("X [m]")
    ax2.axhline(0.0, color="0.6", lw=0.5)
    fig.tight_layout()
    paths = [out / "trajectory.png"]
    fig.savefig(paths[0], dpi=120)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(8, 3.8))
    for i, label in labels:
        c, ls = STYLE.get(label, (None, "-"))
        ax.plot(data[f"X_{i}"], data[f"ev_{i}"], color=c, ls=ls, lw=1.0, label=label)
    ax.axhline(0.0, color="0.6", lw=0.5)
    ax.set_xlabel("X [m]")
    ax.set_ylabel("speed error v_x - 12 [m/s]")
    ax.set_title("Speed error, seed 0")
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    paths.append(out / "speed_error.png")
    fig.savefig(paths[1], dpi=120)
    plt.close(fig)
    chosen = [(i, label) for i, label in every if _no_preview(label) or label in NO_PREVIEW_COMPANIONS]
    if any(_no_preview(label) for _, label in chosen):
        fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 6.5), sharex=True)
        for i, label in chosen:
            c, ls = STYLE.get(label, (None, "-"))
            ax1.plot(data[f"X_{i}"], data[f"ey_{i}"], color=c, ls=ls, lw=1.0, label=label)
            ax2.plot(data[f"X_{i}"], data[f"ev_{i}"], color=c, ls=ls, lw=1.0, label=label)
        for ax in (ax1, ax2):
            ax.axhline(0.0, color="0.6", lw=0.5)
        ax1.set_ylabel("lateral error e_y [m]")
        ax1.set_title("Without preview (tangent line at the car's X), seed 0")
        ax1.legend(fontsize=7, ncol=2)
        ax2.set_ylabel("speed error v_x - 12 [m/s]")
        ax2.set_xlabel("X [m]")
        fig.tight_layout()
        paths.append(out / "no_preview.png")
        fig.savefig(paths[2], dpi=120)
        plt.close(fig)
    return paths


def _load(out: Path) -> tuple[list[dict], dict[str, np.ndarray]]:
    if not (out / "references.json").exists():
        return [], {}
    rows = json.loads((out / "references.json").read_text())
    arrays = dict(np.load(out / "trajectories.npz")) if (out / "trajectories.npz").exists() else {}
    return rows, arrays


def _save(out: Path, rows: list[dict], arrays: dict[str, np.ndarray]) -> None:
    order = {label: i for i, (label, _) in enumerate(REFERENCE_SETTINGS)}
    rows = sorted(rows, key=lambda r: order[r["method"]])
    atomic_write_text(out / "references.json", json.dumps(rows, indent=2) + "\n")
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    atomic_write_bytes(out / "trajectories.npz", buf.getvalue())
    write_csv(out / "references.csv", rows)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--period", type=int, default=1, help="NMPC re-solve period [control steps]")
    parser.add_argument("--only", nargs="+", type=int, help="indices of REFERENCE_SETTINGS to run")
    parser.add_argument("--merge", type=Path, help="add the rows of another output directory")
    parser.add_argument("--fresh", action="store_true", help="re-run rows already in references.json")
    parser.add_argument("--figures-only", action="store_true")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    t0 = time.perf_counter()
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    rows, arrays = ([], {}) if args.fresh else _load(out)
    if args.merge is not None:
        more_rows, more_arrays = _load(args.merge)
        done = {r["method"] for r in more_rows}
        rows = [r for r in rows if r["method"] not in done] + more_rows
        arrays.update(more_arrays)
        _save(out, rows, arrays)
    if not args.figures_only:
        only = range(len(REFERENCE_SETTINGS)) if args.only is None else args.only
        for i in only:
            label = REFERENCE_SETTINGS[i][0]
            if any(r["method"] == label for r in rows):
                logging.info("%s: kept from %s", label, out / "references.json")
                continue
            row = reference_row(label, seeds=args.seeds, period=args.period, progress=True, keep_trajectory=True)
            first = row["trajectories"][0]
            arrays.update({f"X_{i}": first.states[:, 5], f"ey_{i}": first.lateral_error,
                           f"ev_{i}": first.speed_error, f"u_{i}": first.actions})
            rows.append(jsonable(row))
            _save(out, rows, arrays)
            logging.info("%s: lateral %.4f m, speed %.5f m/s, cost %.3f, solve %.1f ms (max %.1f)", label,
                         row["lateral_mae"], row["speed_mae"], row["cost"], row["solve_ms_mean"], row["solve_ms_max"])
    _save(out, rows, arrays)
    for path in make_figures(out):
        logging.info("wrote %s", path)
    logging.info("wall time %.1f min", (time.perf_counter() - t0) / 60.0)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
