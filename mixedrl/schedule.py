"""The budget of a run on its task (:func:`resolve_budget`), one gradient step (:func:`descend`, one run or
many stacked) and the learning-rate schedule shared by Algorithm 2 and DDPG."""

from __future__ import annotations

import torch

from typing import Any, Callable, Hashable, Sequence

from mixedrl.config import TrainConfig, optimiser_section

__all__ = ["resolve_budget", "lr_factor", "set_learning_rates", "descend", "Descent"]


def resolve_budget(config: TrainConfig, task: Any) -> tuple[TrainConfig, int]:
    """The config an Algorithm-2 run on ``task`` trains with, and the factor its budget was scaled by.

    On a task that declares a state region (``task.declares_region()``) Algorithm 2 trains
    ``f = algorithm.region_budget`` times ``algorithm.iterations`` iterations, with ``sampler.true_every``
    and ``run.eval_every`` ``f`` times longer, so the true transitions stay those of ``iterations``. What
    runs over the budget (learning-rate decay, discount ramp) stretches with it; the checkpoint period and
    an explicit ``lr_decay_iterations`` do not. The resolved config has ``region_budget`` 1, so resolving
    it again changes nothing.

    Parameters
    ----------
    config : TrainConfig
        The run's config as given.
    task : Task
        Its task (any object; one without ``declares_region`` declares no region).

    Returns
    -------
    config : TrainConfig
        ``config`` itself where the rule does not apply (DDPG, no region, ``region_budget`` 1), else the
        scaled copy.
    factor : int
        ``region_budget`` where the rule applied, else 1.
    """
    factor = config.algorithm.region_budget
    declares = getattr(task, "declares_region", None)
    if factor == 1 or config.method == "ddpg" or declares is None or not declares():
        return config, 1
    changes: dict[str, Any] = {"algorithm.iterations": factor * config.algorithm.iterations,
                               "run.eval_every": factor * config.run.eval_every, "algorithm.region_budget": 1}
    if hasattr(config.sampler, "true_every"):
        changes["sampler.true_every"] = factor * config.sampler.true_every
    return config.replace(**changes), factor


def lr_factor(config: TrainConfig, k: int) -> float:
    """Return the factor of the learning rates at iteration ``k``: linear from 1 to ``lr_decay_to``.

    .. math:: \\alpha_k = \\alpha_0 \\Big(1 - (1 - \\rho) \\min\\big(1, \\tfrac{k}{L - 1}\\big)\\Big),
        \\qquad \\rho = \\texttt{lr\\_decay\\_to},\\
        L = \\min(\\texttt{lr\\_decay\\_iterations}, \\texttt{iterations})
        \\text{ (or } \\texttt{iterations} \\text{ if the former is 0)}

    Parameters
    ----------
    config : TrainConfig
        Supplies ``iterations``, ``lr_decay_iterations`` and ``lr_decay_to``.
    k : int
        Iteration index (``>= 0``).

    Returns
    -------
    float
        In ``[lr_decay_to, 1]`` (for ``lr_decay_to <= 1``).

    Notes
    -----
    A departure (eqs. 50 and 52 use fixed step sizes): the decay makes the last iterates settle. A budget
    ``K >= L`` is the ``L``-iteration run followed by ``K - L`` iterations at the final rates.
    """
    algo = config.algorithm
    length = min(algo.lr_decay_iterations, algo.iterations) if algo.lr_decay_iterations else algo.iterations
    frac = min(1.0, k / max(1, length - 1))
    return 1.0 - (1.0 - algo.lr_decay_to) * frac


def set_learning_rates(config: TrainConfig, k: int, critic_opt: torch.optim.Optimizer,
                       actor_opt: torch.optim.Optimizer) -> None:
    """Set the critic's and the actor's learning rates of iteration ``k``: ``lr * lr_factor(config, k)``.

    Parameters
    ----------
    config : TrainConfig
        Supplies the method's ``critic_lr`` and ``actor_lr`` (:func:`mixedrl.config.optimiser_section`)
        and the shared decay settings.
    k : int
        Iteration index.
    critic_opt, actor_opt : torch.optim.Optimizer
        Their parameter groups get the decayed rates.
    """
    factor, rates = lr_factor(config, k), optimiser_section(config)
    for opt, lr in ((critic_opt, rates.critic_lr), (actor_opt, rates.actor_lr)):
        for group in opt.param_groups:
            group["lr"] = lr * factor


def descend(loss: torch.Tensor, leaves: Sequence[torch.Tensor], run_params: Sequence[Sequence[torch.Tensor]],
            optimizers: Sequence[torch.optim.Optimizer], grad_clips: Sequence[float],
            active: Sequence[int] | None = None) -> None:
    """One gradient step per run: the gradient of ``J_r`` clipped, then run ``r``'s own optimiser's step.

    Parameters
    ----------
    loss : torch.Tensor
        Shape () for one run (``leaves`` are then its parameters), or (R,) for ``R`` stacked runs
        (``leaves`` are the stacked parameters, shape ``(R, ...)`` each, and run ``r``'s loss depends on
        slice ``r`` only).
    leaves : sequence of torch.Tensor
        The tensors the gradient is taken with respect to.
    run_params : sequence of sequences of torch.Tensor
        Per run, its parameters in the order of ``leaves`` (for stacked runs views of slice ``r``).
    optimizers : sequence of torch.optim.Optimizer
        Per run, the optimiser over ``run_params[r]`` (its learning rate, state and step count).
    grad_clips : sequence of float
        Per run, the largest gradient norm (:func:`torch.nn.utils.clip_grad_norm_`).
    active : sequence of int, optional
        The runs that step (default all); the others keep their parameters and optimiser state.

    Raises
    ------
    ValueError
        ``loss`` has neither shape () nor (R,) with ``R = len(optimizers)``.
    """
    runs = len(optimizers)
    if not (loss.ndim == 0 and runs == 1) and tuple(loss.shape) != (runs,):
        raise ValueError(f"loss: expected shape () for one run or ({runs},), got {tuple(loss.shape)}")
    grads = torch.autograd.grad(loss if loss.ndim == 0 else loss.sum(), list(leaves))
    for r in range(runs) if active is None else active:
        params = run_params[r]
        for p, g in zip(params, grads):
            p.grad = g if loss.ndim == 0 else g[r]
        torch.nn.utils.clip_grad_norm_(params, grad_clips[r])
        optimizers[r].step()
        for p in params:
            p.grad = None


class Descent:
    """The gradient steps of one network of ``R`` runs: :func:`descend` bound to the tensors, the runs'
    optimisers and their gradient clips.

    Parameters
    ----------
    leaves, run_params, optimizers, grad_clips
        As for :func:`descend` (stacked runs: :class:`mixedrl.algorithms.batched.StackedNetwork`).
    mode : {"off", "on", "functional"}, optional
        ``algorithm.compile`` (:mod:`mixedrl.compiled`): how :meth:`minimise` steps (``"off"``: :func:`descend`).
    """

    def __init__(self, leaves: Sequence[torch.Tensor], run_params: Sequence[Sequence[torch.Tensor]],
                 optimizers: Sequence[torch.optim.Optimizer], grad_clips: Sequence[float], mode: str = "off") -> None:
        from mixedrl.compiled import check_mode

        self.leaves, self.run_params = list(leaves), [list(p) for p in run_params]
        self.optimizers, self.grad_clips = list(optimizers), list(grad_clips)
        self.mode = check_mode(mode, "mode")
        #: The compiled steps of :meth:`minimise`, one per loss (key): :class:`mixedrl.compiled.Update`.
        self.updates: dict[Hashable, Any] = {}

    @classmethod
    def single(cls, module: torch.nn.Module, optimizer: torch.optim.Optimizer, grad_clip: float) -> "Descent":
        """One run's network, its optimiser and its gradient clip."""
        params = list(module.parameters())
        return cls(params, [params], [optimizer], [grad_clip])

    def __call__(self, loss: torch.Tensor, active: Sequence[int] | None = None) -> None:
        """Each (active) run's clipped step on its loss (shape () for one run, (R,) for ``R``): :func:`descend`."""
        descend(loss, self.leaves, self.run_params, self.optimizers, self.grad_clips, active)

    def minimise(self, loss: Callable[..., torch.Tensor], tensors: Sequence[torch.Tensor],
                 active: Sequence[int] | None = None, key: Hashable = None) -> Any:
        """Each (active) run's clipped step on a pure loss ``loss(params, *tensors)``: eagerly when
        :attr:`mode` is ``"off"``, else by a :class:`mixedrl.compiled.Update` kept per ``key`` (default:
        ``loss``). Returns the loss before the step, detached, or ``(value, aux)`` when the loss returns
        ``(value, aux)`` (:mod:`mixedrl.compiled`)."""
        from mixedrl.compiled import minimise

        return minimise(self, loss, tensors, active, key)
