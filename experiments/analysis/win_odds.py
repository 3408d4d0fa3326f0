"""What the seed-to-seed spread of the learned policies allows: the odds of issue 21's per-seed targets.

For each ``per_seed.csv`` of ``experiments/analysis/seed_statistics.py`` given, with the paired speed-error difference
``d_s = model_s - mixed_s`` over the seeds ``s`` modelled as normal with the measured mean and sample std
(a model, stated as such; the seeds are independent runs):

* the chance that mixed RL is better on one seed, ``p = Phi(mean(d) / std(d))``, and the chance of at least
  18 wins in 20 seeds, ``P(Binomial(20, p) >= 18)``; the same with the median and the normal-consistent
  median absolute deviation (:func:`scipy.stats.median_abs_deviation`, ``scale="normal"``) in place of
  mean and std, which a few outlying seeds do not dominate (the normal model is poor where they do:
  compare ``p`` with the observed share of wins);
* the std of ``d`` at which, with the measured mean difference, 18 of 20 would come with probability 0.9;
* mixed RL's speed error: mean, std, and the mean + 1.87 std that the worst of 20 normal seeds reaches on
  average (the expected maximum of 20 standard normals is 1.8675), against the target 0.010 m/s on every
  seed.

Writes ``--out`` (text) and prints it.

Usage::

    python experiments/analysis/win_odds.py experiments/results/table1_seeds20/default/per_seed.csv ... --out experiments/results/table1_seeds20/win_odds.txt
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy import optimize, stats

from mixedrl.runs import atomic_write_text
from seed_statistics import load_csv_rows

#: The expected maximum of 20 independent standard normal draws.
EXPECTED_MAX_OF_20 = 1.8675
WINS, SEEDS, CONFIDENCE = 18, 20, 0.9


def odds(path: Path) -> dict[str, float]:
    """The figures of the module docstring for one ``per_seed.csv``.

    Raises
    ------
    ValueError
        If the file lacks mixed or model-driven RL, or they share fewer than 3 seeds.
    """
    rows = load_csv_rows(path)
    if "mixed" not in rows or "model" not in rows:
        raise ValueError(f"{path}: needs the rows of mixed and model-driven RL")
    model = {r["seed"]: r["speed_mae"] for r in rows["model"]}
    mixed = {r["seed"]: r["speed_mae"] for r in rows["mixed"]}
    seeds = sorted(set(model) & set(mixed))
    if len(seeds) < 3:
        raise ValueError(f"{path}: mixed and model-driven RL share {len(seeds)} seeds; need at least 3")
    d = np.array([model[s] - mixed[s] for s in seeds])
    m = np.array([mixed[s] for s in seeds])
    p = float(stats.norm.cdf(d.mean() / d.std(ddof=1)))
    p_robust = float(stats.norm.cdf(np.median(d) / stats.median_abs_deviation(d, scale="normal")))
    p_needed = optimize.brentq(lambda q: stats.binom.sf(WINS - 1, SEEDS, q) - CONFIDENCE, 0.5, 1.0 - 1e-12)
    return {"n": len(seeds), "wins": int((d > 0).sum()), "diff_mean": float(d.mean()), "diff_std": float(d.std(ddof=1)),
            "p_win": p, "p_18_of_20": float(stats.binom.sf(WINS - 1, SEEDS, p)), "p_win_robust": p_robust,
            "p_18_of_20_robust": float(stats.binom.sf(WINS - 1, SEEDS, p_robust)),
            "diff_std_for_0.9": float(d.mean() / stats.norm.ppf(p_needed)) if d.mean() > 0 else float("nan"),
            "mixed_mean": float(m.mean()), "mixed_std": float(m.std(ddof=1)), "mixed_max": float(m.max()),
            "mixed_expected_max": float(m.mean() + EXPECTED_MAX_OF_20 * m.std(ddof=1))}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("csvs", type=Path, nargs="+", help="per_seed.csv files of seed_statistics.py")
    parser.add_argument("--out", type=Path, required=True, help="the text file to write")
    args = parser.parse_args(argv)
    lines = ["Speed error, mixed vs model-driven RL: d = model - mixed per seed, modelled as normal",
             f"p = Phi(mean/std): the chance of a win on one seed; P18 = P(Binomial(20, p) >= 18); std for 0.9: the "
             f"std of d at which P18 = 0.9 with the same mean; robust: median / normal-consistent MAD in place "
             f"of mean / std",
             "mixed: mean, std, worst seed, and mean + 1.87 std (the worst of 20 normal seeds on average) [m/s]", ""]
    for path in args.csvs:
        try:
            o = odds(path)
        except (ValueError, OSError) as exc:
            parser.error(str(exc))
        lines += [f"{path.parent.name}:",
                  f"  d {o['diff_mean']:+.4f} ± {o['diff_std']:.4f}   wins {o['wins']} of {o['n']}   "
                  f"p {o['p_win']:.3f}   "
                  f"P18 {o['p_18_of_20']:.2f}   std for 0.9: {o['diff_std_for_0.9']:.4f}   robust: p "
                  f"{o['p_win_robust']:.3f}, P18 {o['p_18_of_20_robust']:.2f}",
                  f"  mixed {o['mixed_mean']:.4f} ± {o['mixed_std']:.4f}   worst {o['mixed_max']:.4f}   "
                  f"expected worst of 20 {o['mixed_expected_max']:.4f}"]
    text = "\n".join(lines)
    atomic_write_text(args.out, text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
