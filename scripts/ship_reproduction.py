"""Regenerate the shipped reproduction artifacts in ``docs/_static/reproduction`` from the code.

Runs (or, with ``--resume``, reuses) ``mixedrl reproduce`` into ``--out``, then writes into ``--dest``:
``results.json`` and the figures (copied from the run), and ``table.txt`` = Table I
(:func:`validation.reproduce.format_table`) followed by the block "references, not learned"
(:func:`validation.reproduce.format_references`) read from the measured references that
``scripts/references.py`` ships in ``docs/_static/references/references.json``. Figures of an older
numbering that the reproduction no longer writes are removed from ``--dest``.

Usage::

    PYTHONPATH=. python scripts/ship_reproduction.py [--seeds 5] [--out runs/reproduce] [--resume]

About 10 minutes on this 2-core machine for 5 seeds (624 s measured quiet, 2026-12-07; see
``docs/reproduction.rst``): the Algorithm-2 runs train in batches; those batches and the five long DDPG runs
(not batched) are most of it.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from mixedrl.runs import atomic_write_bytes, atomic_write_text
from validation.reproduce import format_references, format_table, make_figures, reproduce


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path("runs/reproduce"))
    parser.add_argument("--dest", type=Path, default=Path("docs/_static/reproduction"))
    parser.add_argument("--references", type=Path, default=Path("docs/_static/references/references.json"))
    parser.add_argument("--resume", action="store_true", help="reuse finished runs of --out")
    parser.add_argument("--workers", type=int, default=None)
    parser.add_argument("--figures-only", action="store_true",
                        help="redraw the figures of the finished reproduction in --out (its results.json) and ship "
                             "them with its table; trains nothing")
    args = parser.parse_args(argv)

    ref_dir = args.references.parent if args.references.is_file() else None
    if args.figures_only:
        results = json.loads((args.out / "results.json").read_text())
        make_figures(args.out, results, references=ref_dir)
    else:
        results = reproduce(args.out, seeds=args.seeds, resume=args.resume, workers=args.workers, progress=True,
                            references=ref_dir)
    table = format_table(results)
    if args.references.is_file():
        table += "\n\n" + format_references(json.loads(args.references.read_text()))
        table += f"\n(references measured by scripts/references.py, {args.references.name})"
    args.dest.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.dest / "table.txt", table + "\n")
    atomic_write_bytes(args.dest / "results.json", (args.out / "results.json").read_bytes())
    written = {p.name for p in (args.out / "figures").glob("*.png")}
    for name in written:
        atomic_write_bytes(args.dest / name, (args.out / "figures" / name).read_bytes())
    for old in args.dest.glob("fig*.png"):
        if old.name not in written:
            old.unlink()
    print(table)
    print(f"\nshipped to {args.dest}: table.txt, results.json, {len(written)} figures")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
