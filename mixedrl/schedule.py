"""Learning-rate schedule shared by Algorithm 2 (:mod:`mixedrl.algorithms.agpi`) and DDPG."""

from __future__ import annotations

import torch

from mixedrl.config import TrainConfig

__all__ = ["lr_factor", "set_learning_rates"]


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
    Not in the paper (eqs. 50 and 52 use fixed step sizes); a decay makes the last iterates settle. With
    ``lr_decay_iterations = L`` a budget ``K >= L`` is the ``L``-iteration run followed by ``K - L``
    iterations at the final rates (its first ``L`` iterates are those of the ``L``-iteration run); a
    budget below ``L`` decays over the budget, so every run ends at the final rates.
    """
    algo = config.algorithm
    length = min(algo.lr_decay_iterations, algo.iterations) if algo.lr_decay_iterations else algo.iterations
    frac = min(1.0, k / max(1, length - 1))
    return 1.0 - (1.0 - config.algorithm.lr_decay_to) * frac


def set_learning_rates(config: TrainConfig, k: int, critic_opt: torch.optim.Optimizer,
                       actor_opt: torch.optim.Optimizer) -> None:
    """Set the critic's and the actor's learning rates of iteration ``k``: ``lr * lr_factor(config, k)``.

    Parameters
    ----------
    config : TrainConfig
        Supplies ``critic_lr``, ``actor_lr``, ``iterations`` and ``lr_decay_to``.
    k : int
        Iteration index.
    critic_opt, actor_opt : torch.optim.Optimizer
        Their parameter groups get the decayed rates.
    """
    factor = lr_factor(config, k)
    for group in critic_opt.param_groups:
        group["lr"] = config.algorithm.critic_lr * factor
    for group in actor_opt.param_groups:
        group["lr"] = config.algorithm.actor_lr * factor
