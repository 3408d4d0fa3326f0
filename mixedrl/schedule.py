"""Learning-rate schedule shared by Algorithm 2 (:mod:`mixedrl.algorithms.agpi`) and DDPG."""

from __future__ import annotations

import torch

from mixedrl.config import TrainConfig

__all__ = ["lr_factor", "set_learning_rates"]


def lr_factor(config: TrainConfig, k: int) -> float:
    """Return the factor of the learning rates at iteration ``k``: linear from 1 to ``lr_decay_to``.

    .. math:: \\alpha_k = \\alpha_0 \\Big(1 - (1 - \\rho) \\min\\big(1, \\tfrac{k}{K - 1}\\big)\\Big),
        \\qquad \\rho = \\texttt{lr\\_decay\\_to},\\ K = \\texttt{iterations}

    Parameters
    ----------
    config : TrainConfig
        Supplies ``iterations`` and ``lr_decay_to``.
    k : int
        Iteration index (``>= 0``).

    Returns
    -------
    float
        In ``[lr_decay_to, 1]`` (for ``lr_decay_to <= 1``).

    Notes
    -----
    Not in the paper (eqs. 50 and 52 use fixed step sizes); a decay makes the last iterates settle.
    """
    frac = min(1.0, k / max(1, config.iterations - 1))
    return 1.0 - (1.0 - config.lr_decay_to) * frac


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
        group["lr"] = config.critic_lr * factor
    for group in actor_opt.param_groups:
        group["lr"] = config.actor_lr * factor
