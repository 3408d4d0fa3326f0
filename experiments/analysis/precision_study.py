"""Precision study of issue 21 (Build item 2): does the learned actor resolve the feed-forward at the
equilibrium, and which training option makes it? Analysis only; prints and ships a table.

The runs are the sweep ``experiments/studies/precision_pendulum.toml`` (the pendulum of :mod:`mixedrl.envs.pendulum`,
``task.name = "pendulum"``, trained with the settings of docs/pendulum.rst, variant ``bellman1``: the
paper's Algorithm 2); this script only analyses them::

    mixedrl sweep experiments/studies/precision_pendulum.toml --out runs/precision_pendulum
    PYTHONPATH=. python experiments/analysis/precision_study.py ship runs/precision_pendulum [--dest DIR]

For each finished run (its ``config.json``, ``results.json`` and final ``checkpoint.pt``) it reports

* ``theta*``: the steady offset, ``mean_state_0`` of the run's final evaluation (``results.json``: the
  seeds of :func:`mixedrl.runs.eval_seeds`, as :func:`mixedrl.runs.train` uses them);
* ``u(0)``: the policy's action at the upright; ``u_lqr(0) = -l0``: the discounted LQR's on the
  linearisation for the noise mean the method plans with, and the steady offset that LQR holds;
* ``u_h(0)``: the minimiser over ``u`` of the critic's ``h(0, u, xi_hat)`` (eq. 37, on a grid of
  the action range), i.e. the action the trained critic asks for at the upright, and ``dh/du`` at the
  policy's action there (zero if the actor has reached the critic's minimiser);
* the same three actions at the policy's own steady state ``s*`` (the second-half mean of one
  noise-free rollout of the true mean from the upright), where the feed-forward acts.

``ship`` prints the table and writes ``rows.json`` (one object per run) and ``table.md`` to ``--dest``
(default ``experiments/results/precision``). (Before the move the script trained the runs itself and could print
``u(0)`` along training, ``--track``; a sweep keeps only the final checkpoint.)
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from mixedrl.algorithms.agpi import AGPI
from mixedrl.envs.pendulum import PendulumTask
from mixedrl.expectation import h_value
from mixedrl.config import FEEDFORWARDS
from mixedrl.precision import LQRPolicy
from mixedrl.runs import RunDirectory, atomic_write_text, eval_seeds, load_checkpoint, make_trainer
from mixedrl.tables import paired_interval
from mixedrl.tasks import task_from_config
from validation.lq import LQProblem, optimal_solution

ROOT = Path(__file__).resolve().parents[2]
SPEC = ROOT / "experiments" / "studies" / "precision_pendulum.toml"
OUT = ROOT / "experiments" / "results" / "precision"
HEADER = ("variant", "method", "seed", "cost", "theta*", "lqr_theta*", "u(0)", "u_lqr(0)", "u_h(0)", "dh/du(0)",
          "s*", "u(s*)", "u_lqr(s*)", "u_h(s*)", "tau_hat", "sec")


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


def analyse(run_dir: Path, variant: str = "", feedforward: str | None = None) -> dict[str, Any]:
    """The row of one finished pendulum run: its final evaluation (``results.json``) and the actions of its
    final checkpoint at the upright and at its own steady state, against the LQR on the linearisation.

    With ``feedforward`` the policy is the run's final actor with ``algorithm.feedforward = feedforward``
    (``"lq_ss"``: shifted near the LQR's steady state for the method's own noise mean), evaluated again
    on the run's evaluation seeds (:func:`mixedrl.runs.eval_seeds`, as :func:`mixedrl.runs.evaluate_run` does)."""
    run = RunDirectory(run_dir)
    config = run.read_config()
    res = run.read_results()
    if feedforward is not None:
        config = config.replace(**{"algorithm.feedforward": feedforward})
    agent = make_trainer(config)
    if not isinstance(agent, AGPI) or not isinstance(agent.task, PendulumTask):
        raise ValueError(f"run_dir: {run_dir} is not an Algorithm 2 run on the pendulum (task.name = "
                         f"{config.task.name!r}, method = {config.method!r})")
    agent.load_state_dict(load_checkpoint(run.path / "checkpoint.pt")["trainer"])
    task = agent.task
    ev = res["final"] if feedforward is None else agent.evaluate(eval_seeds(config))
    zero = torch.zeros(1, 2)
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
    return dict(variant=variant, feedforward=config.algorithm.feedforward, method=config.method, seed=config.seed,
                iterations=res["iterations"],
                cost=ev["cost"], theta=ev["mean_state_0"],
                terminated=ev["terminated_fraction"], u0=u0, u_lqr0=float(-l0[0]), u_h0=uh0, dhdu0=g0,
                lqr_theta=lqr_theta, tau_hat=float(task.torque_from_xi(mean[0])), s_star=float(ss[0, 0]),
                u_ss=uss, u_h_ss=uhs, dhdu_ss=gs, u_lqr_ss=ulqr_ss, seconds=res["train_seconds"],
                gain_error_rel=(res.get("policy_gap") or {}).get("gain_error_rel"))


def format_row(r: dict[str, Any]) -> str:
    """One line of the table (the columns of :data:`HEADER`)."""
    return " | ".join(f"{x}" for x in (
        r["variant"], r["method"], r["seed"], f"{r['cost']:.3f}", f"{r['theta']:+.4f}", f"{r['lqr_theta']:+.4f}",
        f"{r['u0']:+.3f}", f"{r['u_lqr0']:+.3f}", f"{r['u_h0']:+.3f}", f"{r['dhdu0']:+.2e}",
        f"{r['s_star']:+.4f}", f"{r['u_ss']:+.3f}", f"{r['u_lqr_ss']:+.3f}", f"{r['u_h_ss']:+.3f}",
        f"{r['tau_hat']:.3f}", f"{r['seconds']:.0f}"))


#: The generality target of issue 21: mixed RL's steady offset within ``REL`` of the LQR-with-feed-forward's
#: (true mean) plus ``ABS`` rad.
TARGET_REL, TARGET_ABS = 0.1, 1e-3


def summarize_rows(rows: list[dict[str, Any]], task: PendulumTask | None = None) -> dict[str, Any]:
    """Per method: the steady offsets ``theta*`` over seeds (mean, std, min, max), their distance to the
    LQR with the true mean's feed-forward, and the seeds within the target ``TARGET_REL |theta_lqr| +
    TARGET_ABS``; the same for the cost; per seed the paired cost difference mixed - model-driven."""
    task = PendulumTask() if task is None else task
    _, l0_true, theta_true = lqr(task, task.true_mean)
    _, _, theta_prior = lqr(task, task.prior_mean)
    tol = TARGET_REL * abs(theta_true) + TARGET_ABS
    out: dict[str, Any] = {"lqr_theta_true_mean": theta_true, "lqr_theta_prior_mean": theta_prior,
                           "lqr_u0_true_mean": float(-l0_true[0]), "tolerance": tol, "methods": {}}
    by_method: dict[str, dict[int, dict[str, Any]]] = {}
    for r in rows:
        by_method.setdefault(r["method"], {})[r["seed"]] = r
    for m, runs in by_method.items():
        theta = np.array([runs[k]["theta"] for k in sorted(runs)])
        cost = np.array([runs[k]["cost"] for k in sorted(runs)])
        dist = np.abs(theta - theta_true)
        out["methods"][m] = {"seeds": sorted(runs), "theta_mean": float(theta.mean()),
                             "theta_std": float(theta.std(ddof=1)) if len(theta) > 1 else 0.0,
                             "theta_min": float(theta.min()), "theta_max": float(theta.max()),
                             "distance_to_lqr_mean": float(dist.mean()), "distance_to_lqr_max": float(dist.max()),
                             "within_target": int((dist <= tol).sum()), "n": len(theta),
                             "cost_mean": float(cost.mean()), "cost_max": float(cost.max())}
        gains = [runs[k].get("gain_error_rel") for k in sorted(runs)]
        if all(g is not None for g in gains):  # runs written before policy_gap reported the gain have none
            out["methods"][m]["gain_error_rel_mean"] = float(np.mean(gains))
            out["methods"][m]["gain_error_rel_max"] = float(np.max(gains))
    if "mixed" in by_method and "model" in by_method:
        common = sorted(set(by_method["mixed"]) & set(by_method["model"]))
        a = [by_method["mixed"][k]["cost"] for k in common]
        b = [by_method["model"][k]["cost"] for k in common]
        diff, lo, hi = paired_interval(a, b)
        da = [abs(by_method["mixed"][k]["theta"] - theta_true) for k in common]
        db = [abs(by_method["model"][k]["theta"] - theta_true) for k in common]
        out["mixed_minus_model"] = {"cost_difference": diff, "cost_difference_ci": [lo, hi],
                                    "cost_wins": int(sum(x < y for x, y in zip(a, b))),
                                    "offset_wins": int(sum(x < y for x, y in zip(da, db))), "n": len(common)}
    return out


def format_summary(summary: dict[str, Any]) -> list[str]:
    """Text lines of :func:`summarize_rows`."""
    lines = [f"LQR with the true mean's feed-forward holds theta* = {summary['lqr_theta_true_mean']:+.4f} rad "
             f"(u(0) = {summary['lqr_u0_true_mean']:+.3f} N m); with the prior's {summary['lqr_theta_prior_mean']:+.4f}. "
             f"Target: |theta* - {summary['lqr_theta_true_mean']:+.4f}| <= {summary['tolerance']:.4f} rad.", ""]
    for m, e in summary["methods"].items():
        lines.append(f"  {m:<7} theta* {e['theta_mean']:+.4f} ± {e['theta_std']:.4f} [{e['theta_min']:+.4f}, "
                     f"{e['theta_max']:+.4f}] rad; |theta* - LQR| mean {e['distance_to_lqr_mean']:.4f}, worst "
                     f"{e['distance_to_lqr_max']:.4f}; within target on {e['within_target']} of {e['n']}; cost mean "
                     f"{e['cost_mean']:.3f}, worst {e['cost_max']:.3f}"
                     + (f"; gain ||du/dx + L|| / ||L|| mean {e['gain_error_rel_mean']:.3f}, worst "
                        f"{e['gain_error_rel_max']:.3f}" if "gain_error_rel_mean" in e else ""))
    pair = summary.get("mixed_minus_model")
    if pair:
        lo, hi = pair["cost_difference_ci"]
        ci = "n/a" if lo is None or hi is None else f"{lo:+.3f}, {hi:+.3f}"
        lines.append(f"  mixed - model cost {pair['cost_difference']:+.3f} [{ci}]; mixed better on cost "
                     f"on {pair['cost_wins']} of {pair['n']}, closer to the LQR's offset on {pair['offset_wins']}")
    return lines


def lqr_yardstick(run_dir: Path) -> dict[str, Any]:
    """The LQR with the true mean and with the prior's (:class:`LQRPolicy`) evaluated like the run
    (its task and evaluation seeds, which depend on the run's seed): cost and steady offset ``theta*`` by
    the same evaluator."""
    config = RunDirectory(run_dir).read_config()
    task = task_from_config(config.task)
    out = {}
    for name, mean in (("true_mean", task.true_mean), ("prior_mean", task.prior_mean)):
        ev = task.evaluate(LQRPolicy(task, np.asarray(mean, dtype=np.float64)), eval_seeds(config))
        out[name] = {"cost": ev["cost"], "theta": ev["mean_state_0"], "terminated": ev["terminated_fraction"]}
    return out


def lqr_summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Over the runs' evaluation seeds: the two LQRs' mean cost and ``theta*``, and per method the paired
    cost difference method - LQR (true mean, then prior mean) with its interval and the seeds where the
    method is cheaper."""
    seeds = sorted({r["seed"] for r in rows})
    first = {r["seed"]: r["lqr_evaluated"] for r in rows}
    out: dict[str, Any] = {k: {"cost_mean": float(np.mean([first[s][k]["cost"] for s in seeds])),
                               "theta_mean": float(np.mean([first[s][k]["theta"] for s in seeds])),
                               "terminated_max": float(np.max([first[s][k]["terminated"] for s in seeds]))}
                           for k in ("true_mean", "prior_mean")}
    out["methods"] = {}
    for m in sorted({r["method"] for r in rows}):
        runs = sorted((r for r in rows if r["method"] == m), key=lambda r: r["seed"])
        entry = {}
        for k in ("true_mean", "prior_mean"):
            a = [r["cost"] for r in runs]
            b = [r["lqr_evaluated"][k]["cost"] for r in runs]
            diff, lo, hi = paired_interval(a, b)
            entry[k] = {"cost_difference": diff, "cost_difference_ci": [lo, hi],
                        "cheaper": int(sum(x < y for x, y in zip(a, b))), "n": len(a)}
        out["methods"][m] = entry
    return out


def format_lqr_summary(yard: dict[str, Any]) -> list[str]:
    """Text lines of :func:`lqr_summary`."""
    lines = [f"  LQR evaluated like the runs (each run's evaluation seeds), {k.replace('_', ' ')}: cost "
             f"{yard[k]['cost_mean']:.3f}, theta* {yard[k]['theta_mean']:+.4f} rad, fell at most "
             f"{yard[k]['terminated_max']:.2f}" for k in ("true_mean", "prior_mean")]
    for m, e in yard["methods"].items():
        lines.append(f"  {m:<7} cost - LQR(true mean) " + ", ".join(
            f"{'' if k == 'true_mean' else 'LQR(prior mean) '}{e[k]['cost_difference']:+.3f} "
            f"[{e[k]['cost_difference_ci'][0]:+.3f}, {e[k]['cost_difference_ci'][1]:+.3f}], cheaper on "
            f"{e[k]['cheaper']} of {e[k]['n']}" for k in ("true_mean", "prior_mean")))
    return lines


def ship(args: argparse.Namespace) -> None:
    """Analyse every finished run of the sweep ``args.sweep_dir``; print the table, write ``rows.json`` and
    ``table.md`` to ``args.dest``."""
    doc_path = args.sweep_dir / "sweep.json"
    if not doc_path.is_file():
        raise SystemExit(f"ship: {doc_path} does not exist; run: mixedrl sweep {SPEC.relative_to(ROOT)} "
                         f"--out {args.sweep_dir}")
    torch.set_num_threads(1)
    finished = [r for r in json.loads(doc_path.read_text())["runs"] if r["error"] is None and r["results"] is not None]
    rows = [analyse(args.sweep_dir / r["run_dir"], r["point"].get("variant", ""), args.feedforward)
            for r in tqdm(finished, desc="analyse", disable=None)]
    lines = [" | ".join(HEADER), " | ".join("---" for _ in HEADER)] + [format_row(r) for r in rows]
    variants = sorted({r["variant"] for r in rows})
    summaries = {v: summarize_rows([r for r in rows if r["variant"] == v]) for v in variants}
    if args.lqr:  # per run: the LQRs on that run's evaluation seeds (they depend on the run's seed)
        for rec, row in zip(finished, rows):
            row["lqr_evaluated"] = lqr_yardstick(args.sweep_dir / rec["run_dir"])
    for v in variants:
        lines += ["", f"Summary{' of variant ' + v if v else ''}"
                      f"{' (feedforward = ' + args.feedforward + ')' if args.feedforward else ''}:"]
        lines += format_summary(summaries[v])
        if args.lqr:
            summaries[v]["lqr_evaluated"] = yard = lqr_summary([r for r in rows if r["variant"] == v])
            lines += format_lqr_summary(yard)
    print("\n".join(lines))
    args.dest.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.dest / "rows.json", json.dumps(rows, indent=1) + "\n")
    atomic_write_text(args.dest / "summary.json", json.dumps(summaries, indent=1) + "\n")
    atomic_write_text(args.dest / "table.md", "\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("ship", help="analyse the runs of a sweep of experiments/studies/precision_pendulum.toml")
    p.add_argument("sweep_dir", type=Path)
    p.add_argument("--dest", type=Path, default=OUT)
    p.add_argument("--feedforward", choices=FEEDFORWARDS, default=None,
                   help="analyse each final actor with this algorithm.feedforward (evaluated again)")
    p.add_argument("--lqr", action="store_true",
                   help="also evaluate the LQR with the true and the prior mean like the runs (summary "
                        "'lqr_evaluated')")
    p.set_defaults(func=ship)
    args = parser.parse_args(argv)
    args.func(args)


if __name__ == "__main__":
    main()
