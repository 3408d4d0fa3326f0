"""Eq. (18) (the paper's Case 2 recursion) against the exact recursive eq. (17), as a function of N.

Writes ``experiments/results/ibe_paper_vs_exact/ibe_paper_vs_exact.csv`` (included by ``docs/ibe.rst``) and
``experiments/results/ibe_paper_vs_exact/ibe_paper_vs_exact.png``. Two cases:

* ``vehicle``: the paper's vehicle task (n = 5, T = 1/200, m = 1500), prior mu_M = 150 T/m and
  K_M = (4T/m)^2 on v_x (1e-20 elsewhere), true noise N(261 T/m, 32 (T/m)^2) on v_x only (rank 1).
* ``well-posed``: n = 2, true mean (1, -1), full-rank K, prior mean one prior-sd away, K_M = I.

Residuals are fed one at a time to ``UnknownCovarianceIBE(recursion="paper")`` and
``UnknownCovarianceIBE(recursion="exact")``; errors are relative (mean: max-norm over the noisy
components divided by the true mean's max-norm; covariance: Frobenius). Median over ``--seeds`` seeds.

Usage: ``python experiments/analysis/ibe_paper_vs_exact.py [--seeds 10] [--nmax 10000]``
"""

from __future__ import annotations

import argparse
import csv
import pathlib

import numpy as np
from tqdm import tqdm

from mixedrl.ibe import UnknownCovarianceIBE

OUT = pathlib.Path(__file__).resolve().parents[2] / "experiments" / "results" / "ibe_paper_vs_exact"
GRID = [1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000, 10000]


def vehicle_case():
    s = 1.0 / 200.0 / 1500.0
    mu_m = np.array([0.0, 0.0, 150 * s, 0.0, 0.0])
    k_m = np.diag([1e-20, 1e-20, (4 * s) ** 2, 1e-20, 1e-20])
    mu = np.array([0.0, 0.0, 261 * s, 0.0, 0.0])
    k = np.zeros((5, 5))
    k[2, 2] = 32 * s**2
    return mu_m, k_m, mu, k


def well_posed_case():
    mu = np.array([1.0, -1.0])
    k = np.array([[1.0, 0.3], [0.3, 0.5]])
    return mu + np.array([1.0, 0.0]), np.eye(2), mu, k


def draw(mu, k, n, rng):
    lam, vec = np.linalg.eigh(k)
    factor = vec * np.sqrt(np.clip(lam, 0, None))
    return mu + rng.standard_normal((n, mu.shape[0])) @ factor.T


def run(case, seeds, nmax):
    mu_m, k_m, mu, k = case()
    grid = [n for n in GRID if n <= nmax]
    res = {key: np.zeros((seeds, len(grid))) for key in ("mean18", "mean17", "cov18", "cov17")}
    for seed in tqdm(range(seeds), desc=case.__name__):
        rng = np.random.default_rng([2024, seed])
        xi = draw(mu, k, grid[-1], rng)
        paper = UnknownCovarianceIBE(mu_m, k_m, recursion="paper")
        exact = UnknownCovarianceIBE(mu_m, k_m)
        j = 0
        for i, row in enumerate(xi, start=1):
            paper.update(row)
            exact.update(row)
            if i == grid[j]:
                for tag, est in (("18", paper), ("17", exact)):
                    res["mean" + tag][seed, j] = np.max(np.abs(est.mean - mu)) / np.max(np.abs(mu))
                    res["cov" + tag][seed, j] = np.linalg.norm(est.cov - k) / np.linalg.norm(k)
                j += 1
    return grid, {key: np.median(val, axis=0) for key, val in res.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--nmax", type=int, default=10000)
    args = parser.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    rows = []
    curves = {}
    for case in (vehicle_case, well_posed_case):
        grid, med = run(case, args.seeds, args.nmax)
        name = "vehicle" if case is vehicle_case else "well-posed"
        curves[name] = (grid, med)
        for j, n in enumerate(grid):
            rows.append([name, n] + [f"{med[key][j]:.3g}" for key in ("mean18", "mean17", "cov18", "cov17")])
    with open(OUT / "ibe_paper_vs_exact.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["case", "N", "mean rel. error eq. (18)", "mean rel. error eq. (17)", "cov rel. error eq. (18)", "cov rel. error eq. (17)"])
        w.writerows(rows)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for ax, (name, (grid, med)) in zip(axes, curves.items()):
        ax.loglog(grid, med["mean18"], "o-", color="C3", label="mean, eq. (18) (paper)")
        ax.loglog(grid, med["mean17"], "o-", color="C0", label="mean, exact eq. (17)")
        ax.loglog(grid, med["cov18"], "s--", color="C3", alpha=0.6, label="cov, eq. (18)")
        ax.loglog(grid, med["cov17"], "s--", color="C0", alpha=0.6, label="cov, exact eq. (17)")
        ax.set_xlabel("number of residuals N")
        ax.set_title(f"{name} case (median of {args.seeds} seeds)")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("relative error")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(OUT / "ibe_paper_vs_exact.png", dpi=110)


if __name__ == "__main__":
    main()
