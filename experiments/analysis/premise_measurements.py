"""The measured numbers of docs/theory.rst, "Eq. (27) measured" and "Premises".

* eq. (27): :func:`theory.gamma_condition` per iteration of Algorithm 1 on the LQ example (methods
  ``mixed`` and ``oracle``, seed 0, 12 iterations, the run's 256 check states), beside the eq. (28)
  fraction (``extra["lyapunov_margin"]``), ``gamma_required``, the largest failing ``||x||`` and the
  largest slack of eq. (25); then at the exact optimum with the true noise and with the noise removed.
* Lemma 2: :func:`theory.prior_full_rank` on the vehicle's prior (from the paper's numbers and from
  ``DoubleLaneChangeTask().prior_cov``) and on the LQ example's prior.

Usage: ``python experiments/analysis/premise_measurements.py`` (a few seconds; prints to stdout).
"""

from __future__ import annotations

import sys

import numpy as np

from mixedrl.noise import GaussianNoise
from mixedrl.quadratic import AffinePolicy
from mixedrl.tasks import DoubleLaneChangeTask
from theory import gamma_condition, prior_full_rank
from validation.lq import check_states, example_problem, optimal_solution, run_algorithm1


def _row(label: str, rep, states: np.ndarray) -> str:
    lyap = rep.extra["lyapunov_margin"]
    scale = np.abs(rep.extra["expected_value"]) + np.abs(rep.extra["expected_utility"])
    lyap_held = float(np.mean(lyap >= -1e-9 * scale))
    norms = np.linalg.norm(states, axis=1)
    failed = norms[~rep.held_mask]
    return (f"{label:>12}  eq27 held {rep.held_fraction:6.1%}  eq28 held {lyap_held:6.1%}  "
            f"gamma_required {rep.extra['gamma_required']:.4f}  "
            f"largest failing |x| {failed.max() if failed.size else 0.0:.3g}  "
            f"max slack(25) {np.max(rep.extra['bellman_slack']):.3g}")


def main() -> int:
    """Print the measurements; returns the exit code."""
    out = sys.stdout
    prob = example_problem()
    states = check_states(prob.n, 256, (1e-3, 1e2), np.random.default_rng([0, 1]))  # run_algorithm1's states
    out.write(f"eq. (27) on the LQ example, gamma = {prob.gamma}\n")
    for method in ("mixed", "oracle"):
        res = run_algorithm1(prob, method, iterations=12, seed=0, theory_checks=False)
        for it in res.history[:-1]:
            noise = GaussianNoise(it.ibe_mean, it.ibe_cov)
            rep = gamma_condition(it.value, AffinePolicy(it.gain, it.offset), prob.dynamics, prob.cost,
                                  prob.gamma, noise, states)
            out.write(_row(f"{method} k={it.k}", rep, states) + "\n")
    other = check_states(prob.n, 256, (1e-3, 1e2), np.random.default_rng(0))
    opt = optimal_solution(prob)
    rep = gamma_condition(opt.value, opt.policy, prob.dynamics, prob.cost, prob.gamma,
                          GaussianNoise(prob.noise_mean, prob.noise_cov), other)
    out.write(_row("optimum", rep, other) + "\n")
    zero_mean, zero_cov = np.zeros(prob.n), np.zeros((prob.n, prob.n))
    opt0 = optimal_solution(prob, noise_mean=zero_mean, noise_cov=zero_cov)
    rep = gamma_condition(opt0.value, opt0.policy, prob.dynamics, prob.cost, prob.gamma,
                          GaussianNoise(zero_mean, zero_cov), other)
    out.write(_row("noise-free", rep, other) + "\n\n")

    task = DoubleLaneChangeTask()
    T, m = 1.0 / 200.0, 1500.0
    paper = np.diag([1e-20, 1e-20, (4.0 * T / m) ** 2, 1e-20, 1e-20])
    for label, cov, noise_cov in (("vehicle prior (paper)", paper, task.true_cov),
                                  ("vehicle prior (task)", task.prior_cov, task.true_cov),
                                  ("LQ example prior", prob.prior_cov, prob.noise_cov)):
        rep = prior_full_rank(cov, noise_cov=noise_cov)
        out.write(f"{label}: rank {rep.rank}/{rep.dim} at rtol {rep.rtol:.3g} (at 1e-6: {rep.rank_at(1e-6)}, "
                  f"at 1e-13: {rep.rank_at(1e-13)}), condition number {rep.condition_number:.3g}, "
                  f"full rank {rep.full_rank}, samples the prior is worth {np.round(rep.equivalent_samples, 3).tolist()}\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
