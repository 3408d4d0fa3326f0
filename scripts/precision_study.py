"""Precision study of issue 21 (Build item 2): does the learned actor resolve the feed-forward at the
equilibrium, and which training option makes it? Analysis and measurement only; prints a table.

For each (method, seed) the pendulum of :mod:`mixedrl.envs.pendulum` is trained with the settings of
docs/pendulum.rst (plus the ``algorithm.*`` overrides given on the command line), and at the end it
reports

* ``theta*``: the steady offset, ``mean_state_0`` of the final evaluation (the seeds of
  :func:`mixedrl.runs.eval_seeds`, as :func:`mixedrl.runs.train` uses them);
* ``u(0)``: the policy's action at the upright; ``u_lqr(0) = -l0``: the discounted LQR's on the
  linearisation for the noise mean the method plans with, and the steady offset that LQR holds;
* ``u_h(0)``: the minimiser over ``u`` of the critic's ``h(0, u, xi_hat)`` (eq. 37, on a grid of
  the action range), i.e. the action the trained critic asks for at the upright, and ``dh/du`` at the
  policy's action there (zero if the actor has reached the critic's minimiser);
* the same three actions at the policy's own steady state ``s*`` (the second-half mean of one
  noise-free rollout of the true mean from the upright), where the feed-forward acts.

Every ``--track`` iterations ``u(0)`` and ``u_h(0)`` are printed, to see them converge (or not).

Usage::

    OMP_NUM_THREADS=1 PYTHONPATH=$PWD python scripts/precision_study.py --methods mixed model oracle \\
        --seeds 0 1 2 --iterations 1500 [--set algorithm.bellman_steps=10 ...]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from mixedrl.algorithms.agpi import AGPI
from mixedrl.config import TrainConfig
from mixedrl.envs.pendulum import PendulumTask
from mixedrl.expectation import h_value
from mixedrl.runs import eval_seeds
from validation.lq import LQProblem, optimal_solution


def lqr(task: PendulumTask, mean: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Gain ``L``, feed-forward ``l0`` (``u = -L s - l0``) of the discounted LQR for noise mean ``mean``
    (noise coordinates), and the steady angle it holds under the true mean on the linearisation."""
    lin = task.linearisation()
    A, B, E = lin["A"], lin["B"], lin["E"]
    problem = LQProblem(A=A, B=B, Q=lin["Q"], R=lin["R"], gamma=task.gamma, noise_mean=E @ task.true_mean,
                        noise_cov=E @ task.true_cov @ E.T, prior_mean=E @ task.prior_mean,
                        prior_cov=E @ task.prior_cov @ E.T)
    sol = optimal_solution(problem, noise_mean=E @ np.asarray(mean, dtype=float))
    steady = np.linalg.solve(np.eye(2) - (A - B @ sol.gain), E @ task.true_mean - B @ sol.offset)
    return sol.gain, sol.offset, float(steady[0])


def critic_argmin(agent: AGPI, s: torch.Tensor) -> tuple[float, float]:
    """Minimiser of ``h(s, u, xi_hat)`` over a grid of ``u`` in the action range, and ``dh/du`` at the
    policy's action (``s`` shape (1, 2))."""
    task = agent.task
    offsets, weights = agent.nodes(*agent.planning_moments(s, agent.policy(task.observe(s))))
    bound = float(task.action_bound[0])
    grid = torch.linspace(-bound, bound, 8001).reshape(-1, 1)
    with torch.no_grad():
        h = h_value(task, agent.critic, s.expand(grid.shape[0], -1), grid, offsets, weights)
    u_min = float(grid[int(torch.argmin(h)), 0])
    u = agent.policy(task.observe(s)).detach().clone().requires_grad_(True)
    hu = h_value(task, agent.critic, s, u, offsets, weights).sum()
    (grad,) = torch.autograd.grad(hu, u)
    return u_min, float(grad[0, 0])


def own_steady_state(agent: AGPI) -> torch.Tensor:
    """The policy's steady state on the true system with the noise at its mean (no randomness)."""
    task = agent.task
    s = torch.zeros(1, 2, dtype=torch.float64)
    xi = torch.as_tensor(task.true_mean, dtype=torch.float64) @ task.noise_matrix.double().T
    tail = []
    with torch.no_grad():
        for t in range(400):
            u = agent.policy(task.observe(s.float())).double()
            s = task.f(s, u) + xi
            if t >= 200:
                tail.append(s)
    return torch.cat(tail).mean(0, keepdim=True).float()


def run(method: str, seed: int, iterations: int, overrides: dict, track: int) -> dict:
    task = PendulumTask()
    flat = dict(method=method, task="linear", seed=seed, iterations=iterations, batch_size=256, horizon=100,
                model_course_fraction=0.0, model_course_horizon=100, model_kick_prob=0.0,
                model_box=3.0, batch_weighting="relative", lr_decay_iterations=iterations, eval_every=300)
    for key, value in overrides.items():  # "section.field" keys (e.g. algorithm.bellman_steps) or old flat keys
        if "." in key:
            section, name = key.split(".", 1)
            flat.setdefault(section, {})[name] = value
        else:
            flat[key] = value
    config = TrainConfig(**flat)
    agent = AGPI(task, config)
    zero = torch.zeros(1, 2)
    t0 = time.time()
    for k in range(iterations):
        agent.iteration()
        if track and (k + 1) % track == 0:
            with torch.no_grad():
                u0 = float(agent.policy(task.observe(zero))[0, 0])
            uh, g = critic_argmin(agent, zero)
            print(f"  [{method} s{seed}] k={k + 1:5d} u(0)={u0:+.3f} u_h(0)={uh:+.3f} dh/du={g:+.2e}", flush=True)
    elapsed = time.time() - t0
    ev = task.evaluate(agent.policy, eval_seeds(config))
    mean, _ = agent.noise_moments()
    L, l0, lqr_theta = lqr(task, mean)
    with torch.no_grad():
        u0 = float(agent.policy(task.observe(zero))[0, 0])
    uh0, g0 = critic_argmin(agent, zero)
    ss = own_steady_state(agent)
    with torch.no_grad():
        uss = float(agent.policy(task.observe(ss))[0, 0])
    uhs, gs = critic_argmin(agent, ss)
    ulqr_ss = float((-(L @ ss.double().numpy()[0]) - l0)[0])
    return dict(method=method, seed=seed, iterations=iterations, overrides=overrides, cost=ev["cost"],
                theta=ev["mean_state_0"], terminated=ev["terminated_fraction"], u0=u0, u_lqr0=float(-l0[0]),
                u_h0=uh0, dhdu0=g0, lqr_theta=lqr_theta, tau_hat=float(task.torque_from_xi(mean[0])),
                s_star=float(ss[0, 0]), u_ss=uss, u_h_ss=uhs, dhdu_ss=gs, u_lqr_ss=ulqr_ss, seconds=elapsed)


def parse_value(text: str):
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--methods", nargs="+", default=["mixed", "model", "oracle"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--iterations", type=int, default=1500)
    parser.add_argument("--track", type=int, default=0, help="print u(0) every this many iterations")
    parser.add_argument("--set", nargs="*", default=[], help="key=value overrides: section.field (algorithm.bellman_steps=10) or an old flat key")
    parser.add_argument("--json", default="", help="append the rows to this JSON-lines file")
    args = parser.parse_args()
    overrides = {kv.split("=", 1)[0]: parse_value(kv.split("=", 1)[1]) for kv in args.set}
    torch.set_num_threads(1)
    header = ("method", "seed", "cost", "theta*", "lqr_theta*", "u(0)", "u_lqr(0)", "u_h(0)", "dh/du(0)",
              "s*", "u(s*)", "u_lqr(s*)", "u_h(s*)", "tau_hat", "sec")
    rows = []
    for method in args.methods:
        for seed in args.seeds:
            r = run(method, seed, args.iterations, overrides, args.track)
            rows.append(r)
            print(" | ".join(f"{x}" for x in (
                r["method"], r["seed"], f"{r['cost']:.3f}", f"{r['theta']:+.4f}", f"{r['lqr_theta']:+.4f}",
                f"{r['u0']:+.3f}", f"{r['u_lqr0']:+.3f}", f"{r['u_h0']:+.3f}", f"{r['dhdu0']:+.2e}",
                f"{r['s_star']:+.4f}", f"{r['u_ss']:+.3f}", f"{r['u_lqr_ss']:+.3f}", f"{r['u_h_ss']:+.3f}",
                f"{r['tau_hat']:.3f}", f"{r['seconds']:.0f}")), flush=True)
            if args.json:
                with open(args.json, "a") as fh:
                    fh.write(json.dumps(r) + "\n")
    print("overrides:", overrides, "iterations:", args.iterations)
    print(" | ".join(header))
    for r in rows:
        print(" | ".join(f"{x}" for x in (
            r["method"], r["seed"], f"{r['cost']:.3f}", f"{r['theta']:+.4f}", f"{r['lqr_theta']:+.4f}",
            f"{r['u0']:+.3f}", f"{r['u_lqr0']:+.3f}", f"{r['u_h0']:+.3f}", f"{r['dhdu0']:+.2e}",
            f"{r['s_star']:+.4f}", f"{r['u_ss']:+.3f}", f"{r['u_lqr_ss']:+.3f}", f"{r['u_h_ss']:+.3f}",
            f"{r['tau_hat']:.3f}", f"{r['seconds']:.0f}")))


if __name__ == "__main__":
    main()
