"""``python -m validation.theory_lq``: the ``theory`` checks per iteration on the shipped LQ example.

Prints, for each method (``--method``, default all three), one row per iteration ``k -> k+1`` with
the Lyapunov decrease (eqs. 28/41), value decrease (eqs. 29/42), MVC (eqs. 38-39) and IBE shift
(eq. 45) reports, then the MVC / value-decrease cross-tabulation of the run.

(This driver was ``python -m theory lq``; it lives in ``validation`` so that ``theory`` imports only
:mod:`mixedrl`, and ``validation`` imports both.)
"""

from __future__ import annotations

import argparse
import sys

from validation.lq import METHODS, example_problem, mvc_value_crosstab, run_algorithm1, theory_table

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    parser = argparse.ArgumentParser(prog="python -m validation.theory_lq", description=__doc__.split("\n")[0])
    parser.add_argument("--method", choices=[*METHODS, "all"], default="all")
    parser.add_argument("--iterations", type=int, default=30)
    parser.add_argument("--samples", type=int, default=100, help="samples per iteration (mixed)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    prob = example_problem()
    methods = METHODS if args.method == "all" else (args.method,)
    for method in methods:
        res = run_algorithm1(prob, method, args.iterations, args.samples, seed=args.seed)
        sys.stdout.write(theory_table(res, prob) + "\n")
        ct = mvc_value_crosstab(res)
        sys.stdout.write(
            "MVC held at every state in {iterations_mvc_all}/{iterations} iterations, value decrease at every "
            "state in {iterations_vdec_all}/{iterations}; per (iteration, state): MVC held {mvc_held}/{pairs}, "
            "P(value decrease | MVC) = {vdec_given_mvc:.3f}, P(value decrease | no MVC) = {vdec_given_not_mvc:.3f}\n\n".format(**ct)
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
