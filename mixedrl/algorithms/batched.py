"""Many runs of Algorithm 2 as one computation: :class:`BatchedAGPI`.

``R`` runs (seeds x methods x config variants sharing :data:`SHARED_FIELDS`) are trained together. Each run
stays an :class:`~mixedrl.algorithms.agpi.AGPI` object with its own task, config, generator, noise source,
sampler, optimisers, schedule, counters, checkpoints and run directory; what is shared is the arithmetic:

* the critics and the actors of the ``R`` runs are stacked (:func:`torch.func.stack_module_state`) and
  evaluated as one batched function (:func:`torch.func.vmap`, :class:`StackedNetwork`); each run's modules
  keep working on their own, because their parameters are rebound to views of the stacked tensors;
* the ``R`` batches are concatenated (``R B`` states, run ``r`` in rows ``r B .. (r + 1) B - 1``) and PEV
  (eq. 49), PIM (eq. 51) and the three ``h`` of the MVC (eqs. 37-39) are evaluated once for all runs, each
  with its own quadrature of its own ``xi_hat_k`` (:func:`mixedrl.expectation.weighted_sum`);
* the losses are per run and each run takes its own clipped Adam step (:class:`mixedrl.schedule.Descent`);
  the MVC inner loop is masked per run.

The loop itself is :func:`mixedrl.algorithms.algorithm2.iteration` (:meth:`BatchedAGPI.iteration`). Everything
a run draws at random comes from its own generator, in the order of a run alone. ``R = 1`` calls the member's
own modules (no ``vmap``): :meth:`AGPI.iteration` is ``BatchedAGPI([run]).iteration()[0]``. For ``R >= 2`` a
run gets the same bits in any batch; alone and batched it agrees to float32 rounding only
(docs/algorithm2.rst, "Many runs as one computation").
"""

from __future__ import annotations

import copy
from functools import partial
from typing import Any, Callable, Sequence

import torch
from torch.func import functional_call, stack_module_state, vmap

from mixedrl.algorithms import algorithm2
from mixedrl.compiled import Evaluation
from mixedrl.config import optimiser_section
from mixedrl.schedule import Descent

__all__ = ["BatchedAGPI", "BatchedRuns", "StackedNetwork", "SHARED_FIELDS", "DDPG_SHARED_FIELDS", "batch_key"]

#: A member of a batch: an :class:`mixedrl.algorithms.agpi.AGPI` run (not imported: agpi imports this module).
AGPI = Any

#: The fields (dotted keys) the runs of one batch must share (network shapes, batch size, the form of
#: the losses and of the quadrature); every other field (method, seed, budget, learning rates, IBE,
#: sampler, MVC settings, ...) may differ between them.
SHARED_FIELDS = tuple(f"algorithm.{name}" for name in (
    "batch_size", "hidden_sizes", "activation", "value_output", "batch_weighting",
    "batch_weight_offset", "expectation", "noise_samples", "critic_target", "compile", "rollout_horizon",
    "rollout_lambda", "rollout_region", "actor_output"))

#: The fields (dotted keys) the DDPG runs of one batch (:class:`mixedrl.algorithms.batched_ddpg.BatchedDDPG`)
#: must share: the network shapes and DDPG's minibatch size; every other field may differ between them.
DDPG_SHARED_FIELDS = ("ddpg.batch_size", "algorithm.hidden_sizes", "ddpg.activation", "algorithm.value_output",
                      "algorithm.compile")


def _setting(config: Any, key: str) -> Any:
    """The value of the dotted ``section.field`` key of ``config``."""
    section, name = key.split(".")
    return getattr(getattr(config, section), name)


def batch_key(config: Any) -> tuple[Any, ...]:
    """What runs must share to be trained in one batch: the task and :data:`SHARED_FIELDS` (Algorithm 2) or
    :data:`DDPG_SHARED_FIELDS` (DDPG).

    Parameters
    ----------
    config : TrainConfig

    Returns
    -------
    tuple
        Equal keys can share a batch. Algorithm-2 and DDPG runs never have equal keys (the key of a DDPG
        run starts with ``"ddpg"``): they train in batches of their own kind.
    """
    if config.method == "ddpg":
        return ("ddpg", repr(config.task), config.run.num_threads) + tuple(
            repr(_setting(config, f)) for f in DDPG_SHARED_FIELDS)
    return (repr(config.task), config.run.num_threads) + tuple(repr(_setting(config, f)) for f in SHARED_FIELDS)


class StackedNetwork:
    """``R`` modules of one architecture as one function of ``R`` runs' inputs.

    Parameters
    ----------
    modules : sequence of torch.nn.Module
        The runs' networks (identical structure).
    batch : int
        States per run, ``B``: an input of ``N = K R B`` rows holds ``K`` blocks of ``R B`` rows, run
        ``r``'s rows ``r B .. (r + 1) B - 1`` of each block (the layout of :func:`mixedrl.expectation.expect`,
        whose points are ordered node-major).

    Notes
    -----
    For ``R = 1`` the call is the module itself. For ``R > 1`` the stacked parameters are leaves of shape
    ``(R, ...)`` (:attr:`leaves`) and each module's parameters are rebound to their views, so a step on
    the stacked tensors is a step of every module and the modules stay usable on their own. The buffers
    are stacked too (:attr:`buffers`) and each module's buffers rebound to their views, so a change of a
    module's buffer in place reaches the stacked call.
    """

    def __init__(self, modules: Sequence[torch.nn.Module], batch: int) -> None:
        self.modules = list(modules)
        self.runs = len(self.modules)
        self.batch = int(batch)
        if self.runs == 1:
            self.names = [name for name, _ in self.modules[0].named_parameters()]
            self.leaves = list(self.modules[0].parameters())
            return
        params, self.buffers = stack_module_state(self.modules)
        self.params = dict(params)
        for r, module in enumerate(self.modules):
            for name, p in module.named_parameters():
                p.data = self.params[name].data[r]
            for name, b in module.named_buffers():
                b.data = self.buffers[name].data[r]
        self.names = list(self.params)
        self.leaves = list(self.params.values())
        base = copy.deepcopy(self.modules[0]).to("meta")

        def call(params: dict[str, torch.Tensor], buffers: dict[str, torch.Tensor], *x: torch.Tensor) -> torch.Tensor:
            return functional_call(base, (params, buffers), x)

        self._call = vmap(call)
        self._frozen = lambda *x: self(*x, frozen=True)

    def run_params(self) -> list[list[torch.Tensor]]:
        """Per run, its parameters in the order of :attr:`leaves`."""
        if self.runs == 1:
            return [self.leaves]
        named = [dict(m.named_parameters()) for m in self.modules]
        return [[params[name] for name in self.params] for params in named]

    def __call__(self, *x: torch.Tensor, frozen: bool = False) -> torch.Tensor:
        """Evaluate on the inputs ``x`` (one or more, as the module's ``forward`` takes them: an observation,
        or an observation and an action for :class:`mixedrl.networks.QCritic`), each of shape ``(K R B, d)``;
        ``frozen``: no gradient to the parameters."""
        if self.runs == 1:
            return self.modules[0](*x)
        return self._apply({name: p.detach() for name, p in self.params.items()} if frozen else self.params, x)

    def at(self, params: Sequence[torch.Tensor]) -> Callable[..., torch.Tensor]:
        """The same function at the parameters ``params`` (in the order of :attr:`leaves`, stacked for
        ``R > 1``): the network inside a pure loss of :mod:`mixedrl.compiled`."""
        named = dict(zip(self.names, params))
        if self.runs == 1:
            module = self.modules[0]
            return lambda *x: functional_call(module, named, x)
        return lambda *x: self._apply(named, x)

    def _apply(self, params: dict[str, torch.Tensor], x: Sequence[torch.Tensor]) -> torch.Tensor:
        """The ``R > 1`` call at ``params``: each run's rows to its network (vmap), the rows back in order."""
        n = x[0].shape[0]
        k = n // (self.runs * self.batch)
        if k * self.runs * self.batch != n or any(t.shape[0] != n for t in x):
            raise ValueError(f"x: {[t.shape[0] for t in x]} rows, expected one multiple of runs x batch = "
                             f"{self.runs} x {self.batch}")
        xs = [t.reshape(k, self.runs, self.batch, *t.shape[1:]).transpose(0, 1).reshape(
            self.runs, k * self.batch, *t.shape[1:]) for t in x]
        out = self._call(params, self.buffers, *xs)
        tail = out.shape[2:]
        return out.reshape(self.runs, k, self.batch, *tail).transpose(0, 1).reshape(n, *tail)

    def frozen(self) -> Any:
        """The same function without gradient to the parameters (the critic inside PIM)."""
        return self.modules[0] if self.runs == 1 else self._frozen


def check_shared(members: Sequence[Any], fields: Sequence[str]) -> None:
    """Refuse runs that cannot share a batch: another task or architecture than run 0, a field of
    ``fields`` that differs from run 0's, or the same run twice.

    Parameters
    ----------
    members : sequence of AGPI or DDPG
        The runs, at least one, all of one kind.
    fields : sequence of str
        The fields (dotted keys) they must share (:data:`SHARED_FIELDS` or :data:`DDPG_SHARED_FIELDS`).

    Raises
    ------
    ValueError
        ``members: ...`` naming the run and the field.
    """
    first = members[0]
    for i, m in enumerate(members[1:], start=1):
        if getattr(m, "architecture", None) != getattr(first, "architecture", None) or \
                type(m.task) is not type(first.task) or m.config.task != first.config.task:
            raise ValueError(f"members: run {i} ({m.config.method}, seed {m.config.seed}) has another task or "
                             f"architecture than run 0; a batch shares one task")
        for f in fields:
            if _setting(m.config, f) != _setting(first.config, f):
                raise ValueError(f"members: run {i} has {f} = {_setting(m.config, f)!r}, run 0 "
                                 f"{_setting(first.config, f)!r}; the runs of a batch share {', '.join(fields)}")
    if len({id(m) for m in members}) != len(members):
        raise ValueError("members: the same run appears twice")


class BatchedRuns:
    """What the engines of many runs share (:class:`BatchedAGPI`, :class:`mixedrl.algorithms.batched_ddpg.BatchedDDPG`):
    the checked members, ``R`` (:attr:`runs`), the minibatch size ``B`` (:attr:`batch`), the task, and the
    runs' critics and actors as :class:`StackedNetwork`.

    Parameters
    ----------
    members : sequence
        The runs; :meth:`check_members` (of the subclass) refuses those that cannot share a batch.
    """

    #: The subclass's kind of run, the attributes that tell a member of that kind, the fields its runs share.
    kind, interface, shared = "", (), ()

    @classmethod
    def check_members(cls, members: Sequence[Any], name: str = "members") -> None:
        """Refuse members that cannot share a batch (the constructor's ``ValueError``, its message starting with
        ``name``): none, a run of another kind, or runs that differ in the task or a shared field
        (:func:`check_shared`)."""
        if len(members) == 0:
            raise ValueError(f"{name}: expected at least one {cls.kind} run, got none")
        for i, m in enumerate(members):
            if not all(hasattr(m, a) for a in cls.interface):
                method = getattr(getattr(m, "config", None), "method", "?")
                raise ValueError(f"{name}: entry {i} is {type(m).__name__} ({method}), not "
                                 f"{'an' if cls.kind == 'AGPI' else 'a'} {cls.kind} run; Algorithm-2 and DDPG runs "
                                 f"train in batches of their own kind")
        check_shared(members, cls.shared)

    def __init__(self, members: Sequence[Any]) -> None:
        self.check_members(members)
        self.members = list(members)
        self.runs = len(self.members)
        self.batch = optimiser_section(self.members[0].config).batch_size
        self.task = self.members[0].task
        self.critic = StackedNetwork([m.critic for m in self.members], self.batch)
        self.actor = StackedNetwork([m.actor for m in self.members], self.batch)
        self._critic_params = self.critic.run_params()
        self._actor_params = self.actor.run_params()
        mode = self.members[0].config.algorithm.compile
        #: Each run's clipped Adam step of its critic / its actor (:class:`mixedrl.schedule.Descent`), eager,
        #: compiled or functional by ``algorithm.compile`` (:mod:`mixedrl.compiled`).
        self.critic_descent = Descent(self.critic.leaves, self._critic_params, [m.critic_opt for m in self.members],
                                      self.grad_clips(), mode)
        self.actor_descent = Descent(self.actor.leaves, self._actor_params, [m.actor_opt for m in self.members],
                                     self.grad_clips(), mode)

    def active_runs(self, active: Sequence[bool] | None) -> tuple[list[bool], list[int]]:
        """The ``active`` flags of an iteration (default: all runs) and the indices of the active runs.

        Raises
        ------
        ValueError
            ``active`` does not hold one flag per run.
        """
        flags = [True] * self.runs if active is None else [bool(a) for a in active]
        if len(flags) != self.runs:
            raise ValueError(f"active: expected {self.runs} flags, got {len(flags)}")
        return flags, [r for r in range(self.runs) if flags[r]]

    def grad_clips(self) -> list[float]:
        """Per run, its gradient clip (``algorithm.grad_clip``, or ``ddpg.grad_clip`` for DDPG)."""
        return [optimiser_section(m.config).grad_clip for m in self.members]


class BatchedAGPI(BatchedRuns):
    """``R`` runs of Algorithm 2 stacked as one computation; :meth:`iteration` is
    :func:`mixedrl.algorithms.algorithm2.iteration` (the paper's loop) on them.

    Parameters
    ----------
    members : sequence of AGPI
        The runs (built, possibly restored from checkpoints). They must share the task and
        :data:`SHARED_FIELDS`; the batch rebinds their network parameters to views of stacked tensors.

    Raises
    ------
    ValueError
        No runs, a run that is not an :class:`AGPI`, or runs that differ in a shared field.
    """

    kind, interface, shared = "AGPI", ("critic_opt", "actor_opt", "collect", "noise", "critic_target"), SHARED_FIELDS

    def __init__(self, members: Sequence[AGPI]) -> None:
        super().__init__(members)
        algo = self.members[0].config.algorithm
        self._filler: torch.Tensor | None = None
        #: The runs' target critics ``V(x; w_bar)`` stacked (:mod:`mixedrl.departures.critic_target`), else
        #: ``None``; the stacked views follow each run's in-place update.
        self.critic_target = (StackedNetwork([m.critic_target.module for m in self.members], self.batch)
                              if algo.critic_target > 0 else None)
        #: The MVC loop's values of ``h`` (:func:`mixedrl.algorithms.algorithm2.mvc_values`), without gradient.
        self.mvc_values = Evaluation(partial(algorithm2.mvc_values, self.task, self.actor, self.critic.frozen()),
                                     algo.compile)

    def iteration(self, active: Sequence[bool] | None = None) -> list[dict[str, float] | None]:
        """Implements Algorithm 2, one outer iteration of every active run:
        :func:`mixedrl.algorithms.algorithm2.iteration` (see there; ``active``: which runs iterate)."""
        return algorithm2.iteration(self, active)

    # -------------------------------------------------------------------------------------- stacking
    def placeholder(self, m: AGPI) -> torch.Tensor:
        """A batch for a run that does not iterate (its last batch): it fills its rows, its results are unused."""
        if m.last_batch is not None:
            return m.last_batch
        if self._filler is None:
            self._filler = self.task.sample_initial(self.batch, torch.Generator().manual_seed(0)).float()
        return self._filler

    def join(self, nodes: list[tuple[torch.Tensor, torch.Tensor]]) -> tuple[torch.Tensor, torch.Tensor]:
        """The runs' quadratures as one, per state: offsets (P, R B, n) and weights (P, R B), run ``r``'s
        nodes on its rows; a run with fewer nodes than ``P`` repeats its first node with weight 0."""
        if self.runs == 1:
            return nodes[0]
        size = max(off.shape[0] for off, _ in nodes)
        offsets, weights = [], []
        for off, w in nodes:
            off = off if off.ndim == 3 else off[:, None, :].expand(off.shape[0], self.batch, off.shape[-1])
            pad = size - off.shape[0]
            if pad:
                off = torch.cat([off, off[:1].expand(pad, *off.shape[1:])])
                w = torch.cat([w, w.new_zeros(pad)])
            offsets.append(off)
            weights.append(w[:, None].expand(size, self.batch))
        return torch.cat(offsets, dim=1), torch.cat(weights, dim=1)

    def rows(self, r: int) -> slice:
        """The rows of run ``r`` in the stacked batch: ``r B .. (r + 1) B - 1``."""
        return slice(r * self.batch, (r + 1) * self.batch)
