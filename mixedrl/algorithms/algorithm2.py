"""Algorithm 2 of the paper as one loop: :func:`iteration`, read top to bottom beside the paper's box.

One outer iteration ``k`` of ``R >= 1`` runs (``R = 1``: a run alone, :meth:`mixedrl.algorithms.agpi.AGPI.iteration`;
``R > 1``: runs trained as one computation, :class:`mixedrl.algorithms.batched.BatchedAGPI`, which only stacks
their networks and batches) is

1. **data**: each run's sampler makes its batch ``x`` and the residuals ``xi^D`` (eq. 10) of its true
   transitions (the paper's: ``batch_size`` true copies stepped once under ``pi^k``);
2. **PEV** (eqs. 49-50, :func:`mixedrl.pev.critic_step`): one semi-gradient step of each critic under
   ``xi_hat_k``;
3. **PIM** (eqs. 51-52, :func:`mixedrl.pim.actor_step`): one gradient step of each actor under ``xi_hat_k``,
   gradients through the model ``f``, critics frozen;
4. **IBE** (eq. 20, :func:`ibe`): each noise source absorbs its residuals, ``xi_hat_k -> xi_hat_{k+1}``;
5. **MVC loop** (eqs. 37-39, :func:`mixedrl.pim.mvc_check`): while a run's maximum variation condition fails
   on its batch, one more PIM step under ``xi_hat_k`` (``j <- j + 1``), until it holds or ``j = j_max``;
   masked per run;
6. the **stopping test** ``|V^{k+1} - V^k| <= eps`` and ``|pi^{k+1} - pi^k| <= eps`` on the batch.

The noise source is the only difference between mixed RL (an IBE posterior), model-driven RL (the prior,
eq. 55) and the oracle (the true noise). Where the library departs from the paper the loop calls a named hook
of :mod:`mixedrl.departures`; with every departure off (``TrainConfig.preset("paper")``) the loop is the paper's.

Order: the paper's loop is IBE -> PEV -> PIM -> MVC. The MVC of eq. (38) needs ``xi_hat_{k+1}``, so the IBE
update sits between PIM and the MVC loop (a cyclic shift: PEV and PIM of iteration ``k`` use ``xi_hat_k``, the
MVC compares ``xi_hat_k`` with ``xi_hat_{k+1}``). The transitions feeding the IBE are collected under ``pi^k``
at the start of the iteration.

Everything a run draws at random comes from its own generator, in the order of a run alone
(:mod:`mixedrl.algorithms.batched` for ``R = 1`` against ``R >= 2``).
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np
import torch

from mixedrl.departures import anchor, critic_target, region, rollout, sampler, schedule, state_weights
from mixedrl.expectation import expectation_nodes, h_value
from mixedrl.pev import critic_step
from mixedrl.pim import MVCResult, actor_step, mvc_check

__all__ = ["iteration", "mvc_values", "ibe", "planning_moments", "nodes", "metrics_row"]


def iteration(engine: Any, active: Sequence[bool] | None = None) -> list[dict[str, float] | None]:
    """Implements Algorithm 2: one outer iteration ``k`` of every active run of ``engine``.

    Parameters
    ----------
    engine : BatchedAGPI
        The ``R`` runs (:attr:`members`, each an :class:`~mixedrl.algorithms.agpi.AGPI`), their stacked
        critics and actors (:attr:`critic`, :attr:`actor`, :attr:`critic_target`), their optimisers
        (:attr:`critic_descent`, :attr:`actor_descent`) and the rows of run ``r`` (:meth:`rows`).
    active : sequence of bool, optional
        Which runs iterate (default all). An inactive run draws nothing, takes no step and returns ``None``.

    Returns
    -------
    list
        Per run its metrics row (:func:`metrics_row`), or ``None`` if inactive.
    """
    flags, on = engine.active_runs(active)
    if not on:
        return [None] * engine.runs
    runs, task, R = engine.members, engine.task, engine.runs
    # the fields the runs share (batched.SHARED_FIELDS): the departure hooks of PEV and PIM
    rel = state_weights.offset(runs[0].config, getattr(task, "value_scale", 1.0))

    # ---- 1. data: the batch x and the residuals xi^D (eq. 10) of each active run, under pi^k
    batches: list[torch.Tensor] = []
    residuals: list[torch.Tensor | None] = []
    for r, m in enumerate(runs):
        if not flags[r]:  # an inactive run's rows hold its last batch; their results are unused
            batches.append(engine.placeholder(m))
            residuals.append(None)
            continue
        schedule.start(m)  # departure hook: the learning rates of iteration k
        s_r, xi_r = sampler.collect(m)  # hook: the paper's true copies, or model rollouts
        batches.append(s_r)
        residuals.append(xi_r)
    s = batches[0] if R == 1 else torch.cat(batches)
    obs = task.observe(s)
    with torch.no_grad():
        v_before = engine.critic(obs)
        u_old = engine.actor(obs)
    u_runs = [u_old[engine.rows(r)] for r in range(R)]

    def moments() -> list[tuple[np.ndarray, np.ndarray] | None]:
        """Each active run's moments of its current xi_hat on its rows (``None`` for an inactive run)."""
        return [planning_moments(m, batches[r], u_runs[r]) if flags[r] else None for r, m in enumerate(runs)]

    def quadrature(per_run_moments: list[tuple[np.ndarray, np.ndarray] | None]) -> tuple[torch.Tensor, torch.Tensor]:
        """Each active run's nodes of its moments on its rows (an inactive run: the first active's)."""
        per_run = [nodes(m, *mo) if mo is not None else None for m, mo in zip(runs, per_run_moments)]
        return engine.join([n if n is not None else per_run[on[0]] for n in per_run])

    # xi_hat_k: each run's current noise source (for mixed RL the IBE posterior; the prior before any data)
    moments_k = moments()
    nodes_k = quadrature(moments_k)

    if rollout.active(runs[0].config):
        # ---- 2-3. departure hook: PEV and PIM on H-step model rollouts under xi_hat_k (lambda-returns, SHAC)
        #      from the sampler's batch, or (departure hook: region starts) region draws and carried end states
        starts = region.starts(engine, s, on)
        critic_losses, actor_objs = rollout.update(engine, starts, moments_k, on, rel)

        def pim(which: list[int]) -> torch.Tensor:
            return rollout.improve(engine, starts, moments_k, which, rel)[0]
    else:
        # ---- 2. PEV (eqs. 49-50) under xi_hat_k: w^{k+1} = w^k - alpha dJ_critic/dw
        critic_losses = critic_step(task, engine.critic, engine.actor, engine.critic_descent, s, *nodes_k,
                                    relative_offset=rel, target_critic=engine.critic_target,
                                    runs=R, active=on)

        # ---- 3. PIM (eqs. 51-52) under xi_hat_k, critics frozen: theta^{k+1} = theta^k - beta dJ_actor/dtheta
        def pim(which: list[int]) -> torch.Tensor:
            return actor_step(task, engine.critic.frozen(), engine.actor, engine.actor_descent, s, *nodes_k,
                              relative_offset=rel, runs=R, active=which)

        actor_objs = pim(on)
        anchor.remember(engine, s, on)  # departure hook: the observations the actors were trained on

    # ---- 4. IBE (eq. 20): xi_hat_k -> xi_hat_{k+1}
    for r in on:
        ibe(runs[r].noise, residuals[r], runs[r].transitions)
    nodes_next = quadrature(moments())

    # ---- 5. MVC loop (eqs. 37-39), masked per run: more PIM steps under xi_hat_k until
    #         h(x, u^{k+1}, xi_hat_{k+1}) - h(x, u^{k+1}, xi_hat_k) <= e_k(x) = h(x, u^k, xi_hat_k) - h(x, u^{k+1}, xi_hat_k)
    critic = engine.critic.frozen()
    with torch.no_grad():
        h_old_cur = h_value(task, critic, s, u_old, *nodes_k)
    j = {r: 0 for r in on}
    pending = list(on)
    outcome: dict[int, tuple[MVCResult, int, torch.Tensor]] = {}
    while pending:
        # u^{k+1} and its h under xi_hat_k and xi_hat_{k+1} (no gradient; one compiled graph with algorithm.compile)
        u_new, h_new_cur, h_new_next = engine.mvc_values(s, obs, *nodes_k, *nodes_next)
        still: list[int] = []
        for r in pending:
            sl, cfg = engine.rows(r), runs[r].config.algorithm
            mvc = mvc_check(h_new_next[sl], h_new_cur[sl], h_old_cur[sl], cfg.mvc_check)
            if mvc.held or j[r] >= cfg.j_max:
                outcome[r] = (mvc, j[r], u_new[sl])
            else:
                still.append(r)
        if still:
            pim(still)
            for r in still:
                j[r] += 1
        pending = still
    with torch.no_grad():
        v_after = engine.critic(obs)

    # ---- 6. stopping test on the batch, then the end-of-iteration hooks and the metrics
    rows: list[dict[str, float] | None] = [None] * R
    critic_losses = [float(v) for v in critic_losses.reshape(-1)]
    actor_objs = [float(v) for v in actor_objs.reshape(-1)]
    for r in on:
        m, sl, cfg = runs[r], engine.rows(r), runs[r].config.algorithm
        mvc, j_r, u_new = outcome[r]
        with torch.no_grad():
            dv = float((v_after[sl] - v_before[sl]).abs().mean() / (v_before[sl].abs().mean() + 1e-12))
            dpi = float(((u_new - u_runs[r]) / m.actor_bound_tensor()).abs().mean())
        if cfg.stop_epsilon > 0 and dv <= cfg.stop_epsilon and dpi <= cfg.stop_epsilon:
            m.stop_count += 1
        else:
            m.stop_count = 0
        m.stopped = cfg.stop_epsilon > 0 and m.stop_count >= cfg.stop_patience
        critic_target.end(m)  # departure hook: w_bar <- beta w_bar + (1 - beta) w^{k+1}
        m.k += 1
        m.last_batch = batches[r]
        rows[r] = metrics_row(m, residuals[r], v_before[sl], critic_losses[r], actor_objs[r], dv, dpi, mvc, j_r)
    return rows


def mvc_values(task: Any, actor: Any, critic: Any, s: torch.Tensor, obs: torch.Tensor, offsets_k: torch.Tensor,
               weights_k: torch.Tensor, offsets_next: torch.Tensor, weights_next: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The left side of eq. (38) and the new term of eq. (39): ``u^{k+1} = pi^{k+1}(x)``,
    ``h(x, u^{k+1}, xi_hat_k)`` and ``h(x, u^{k+1}, xi_hat_{k+1})`` (eq. 37, :func:`mixedrl.expectation.h_value`).

    A pure function of tensors: the engine binds ``task``, its stacked actor and its frozen critic and
    evaluates it without gradient (``engine.mvc_values``, a :class:`mixedrl.compiled.Evaluation`).
    """
    u_new = actor(obs)
    return (u_new, h_value(task, critic, s, u_new, offsets_k, weights_k),
            h_value(task, critic, s, u_new, offsets_next, weights_next))


def ibe(noise: Any, residuals: torch.Tensor, transitions: tuple[torch.Tensor, torch.Tensor] | None = None) -> None:
    """Implements eq. (20): the IBE update ``[mu_k, K_k] = IBE(mu_{k-1}, K_{k-1}, xi^D_k)`` (eq. 13).

    Parameters
    ----------
    noise : NoiseSource or StateDependentNoiseSource
        The run's noise source (:mod:`mixedrl.noise`), updated in place.
    residuals : torch.Tensor, shape (M, noise_dim)
        The residuals of eq. (10) collected this iteration (float64).
    transitions : tuple of torch.Tensor, optional
        Their states and actions (float64), for a state-dependent source (Case 3, eq. 19).

    Notes
    -----
    A fixed source (model-driven RL, oracle: ``learns = False``) is left as it is, and so is any source when
    the iteration brought no finite residual.
    """
    if residuals.shape[0] == 0 or not noise.learns:
        return
    if noise.state_dependent:
        x, u = transitions
        noise.update(x.numpy(), u.numpy(), residuals.numpy())
    else:
        noise.update(residuals.numpy())


def planning_moments(run: Any, s: torch.Tensor, u: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """The moments of ``xi_hat_k`` that PEV and PIM plan with on the batch ``s`` (copies).

    Parameters
    ----------
    run : AGPI
        Its noise source.
    s : torch.Tensor, shape (B, state_dim)
        The batch.
    u : torch.Tensor, shape (B, action_dim)
        ``pi^k(s)``; used only by a state-dependent source.

    Returns
    -------
    mean : numpy.ndarray
        Shape (noise_dim,), or (B, noise_dim) for a state-dependent source: ``mu_hat_k``, or
        ``phi(x, pi^k(x); w_hat_k)`` per state (Case 3, held fixed during the iteration: PIM does not
        differentiate through ``phi``).
    cov : numpy.ndarray, shape (noise_dim, noise_dim)
        ``K_hat_k``.
    """
    if run.noise.state_dependent:
        mean = run.noise.mean_at(s.double(), u.double()).numpy()
    else:
        mean = run.noise.mean
    return np.array(mean, dtype=np.float64), np.array(run.noise.cov, dtype=np.float64)


def nodes(run: Any, mean: np.ndarray, cov: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """Quadrature of ``N(mean, cov)`` with the run's rule (:func:`mixedrl.expectation.expectation_nodes`:
    ``algorithm.expectation``, ``noise_samples``, the run's generator for sampled nodes).

    The nodes of a deterministic rule are computed only when ``(mean, cov)`` changed since the run's last call
    (``run.node_cache``, a :class:`~mixedrl.expectation.NodeCache`): the same tensors, bit for bit.

    Returns
    -------
    offsets : torch.Tensor
        Shape (P, state_dim), or (P, B, state_dim) per state.
    weights : torch.Tensor
        Shape (P,).
    """
    cache = getattr(run, "node_cache", None)
    compute = expectation_nodes if cache is None else cache
    return compute(mean, cov, run.task.noise_matrix, run.config.algorithm.expectation,
                   run.config.algorithm.noise_samples, run.generator)


def metrics_row(run: Any, residuals: torch.Tensor, v_before: torch.Tensor, critic_loss: float, actor_obj: float,
                dv: float, dpi: float, mvc: MVCResult, j: int) -> dict[str, float]:
    """The metrics row of iteration ``k`` of a run (namespaced keys, docs/metrics: ``train/*``, ``mvc/*``,
    ``data/*``, ``ibe/*``)."""
    metrics = {
        "train/critic_loss": critic_loss,
        "train/actor_objective": actor_obj,
        "train/value_mean": float(v_before.mean()),
        "train/value_change": dv,
        "train/policy_change": dpi,
        "mvc/held": float(mvc.held),
        "mvc/fraction_states": mvc.fraction,
        "mvc/lhs_mean": mvc.lhs_mean,
        "mvc/e_mean": mvc.e_mean,
        "mvc/e_nonnegative": mvc.e_nonnegative,
        "mvc/inner_steps": float(j),
        "data/true_transitions": float(run.true_transitions),
    }
    metrics.update(run.noise_metrics())
    if residuals.shape[0] > 0:
        batch_mean = residuals.mean(dim=0).numpy()
        for key in [k for k in metrics if k.startswith("ibe/mean_") and k[9:].isdigit()]:
            metrics[f"ibe/batch_mean_{key[9:]}"] = float(batch_mean[int(key[9:])])
    return metrics
