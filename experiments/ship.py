"""Ship a study: run the commands at the top of its spec, which train its runs and write its result folder.

Every spec of ``experiments/studies`` starts with a comment holding the commands that produce its shipped
results (``mixedrl sweep`` of the spec into ``runs/``, then the analysis scripts of ``experiments/analysis``
writing into ``experiments/results``). This script is the one command that runs them, from the repository
root with the repository on the path::

    python experiments/ship.py table1_seeds20_default              # train and write the results
    python experiments/ship.py table1_seeds20_default --dry-run    # print the commands only
    python experiments/ship.py table1_seeds20_default --analysis   # the runs exist: only the analysis

A command line of a spec's header is a comment line ``#   mixedrl ...``, ``#   python ...`` or
``#   PYTHONPATH=. python ...``; a trailing backslash continues it on the next comment line. The header ends at
the first line that is not a comment.
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STUDIES = ROOT / "experiments" / "studies"
_COMMAND = re.compile(r"^#   (?:PYTHONPATH=\. )?(?:mixedrl|python) ")


def commands(spec: Path) -> list[list[str]]:
    """The commands of a spec's header, each as its argv (``PYTHONPATH=.`` dropped: :func:`run` sets it)."""
    out: list[list[str]] = []
    current: str | None = None
    for line in spec.read_text().splitlines():
        if not line.startswith("#"):
            break
        if current is None and not _COMMAND.match(line):
            continue
        current = line[1:].strip() if current is None else f"{current} {line[1:].strip()}"
        if current.endswith("\\"):
            current = current[:-1].rstrip()
            continue
        argv = shlex.split(current)
        out.append(argv[1:] if argv[0] == "PYTHONPATH=." else argv)
        current = None
    return out


def executable(argv: list[str]) -> list[str]:
    """``argv`` with ``mixedrl`` and ``python`` replaced by this interpreter."""
    if argv[0] == "mixedrl":
        return [sys.executable, "-c", "import sys; from mixedrl.cli import main; sys.exit(main())", *argv[1:]]
    if argv[0] == "python":
        return [sys.executable, *argv[1:]]
    raise ValueError(f"not a command of a spec's header: {shlex.join(argv)}")


def run(spec: Path, analysis_only: bool = False, dry_run: bool = False) -> int:
    """Run the commands of ``spec`` from the repository root (with ``analysis_only``, all but the sweeps)."""
    todo = [c for c in commands(spec) if not (analysis_only and c[:2] == ["mixedrl", "sweep"])]
    if not todo:
        print(f"{spec}: no commands in its header", file=sys.stderr)
        return 2
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    for argv in todo:
        print("+", shlex.join(argv), flush=True)
        if not dry_run:
            done = subprocess.run(executable(argv), cwd=ROOT, env=env)
            if done.returncode:
                return done.returncode
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("study", help="a spec of experiments/studies, by name (table1_seeds20) or path")
    parser.add_argument("--analysis", action="store_true", help="skip the sweeps (their runs/ directories exist)")
    parser.add_argument("--dry-run", action="store_true", help="print the commands, run nothing")
    args = parser.parse_args(argv)
    spec = Path(args.study) if args.study.endswith(".toml") else STUDIES / f"{args.study}.toml"
    if not spec.is_file():
        parser.error(f"{spec} does not exist")
    return run(spec, args.analysis, args.dry_run)


if __name__ == "__main__":
    raise SystemExit(main())
