"""Function approximators shared by every algorithm: the critic ``V(x; w)`` and actor ``pi(x; theta)``
of eq. (48), DDPG's Q-critic, and exact linear-quadratic representations for validation.

All networks are initialised from an explicit :class:`torch.Generator` (never torch's global random
state), so the same seed gives the same weights.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Sequence

import torch
from torch import nn

__all__ = ["MLP", "Critic", "Actor", "ClippedActor", "QCritic", "QuadraticCritic", "AffineActor", "init_uniform_",
           "stacked_actors"]

_ACTIVATIONS = {"elu": nn.ELU, "tanh": nn.Tanh, "relu": nn.ReLU}


def init_uniform_(module: nn.Module, generator: torch.Generator, last_scale: float = 1.0) -> nn.Module:
    """Initialise every :class:`torch.nn.Linear` of ``module`` from ``generator``.

    Weights and biases are drawn from ``U(-1/sqrt(fan_in), 1/sqrt(fan_in))`` (PyTorch's default
    ranges), the last linear layer's range multiplied by ``last_scale``.

    Parameters
    ----------
    module : torch.nn.Module
        Module whose linear layers are initialised in place.
    generator : torch.Generator
        Source of every draw.
    last_scale : float, optional
        Factor on the range of the output layer (small values start the actor near zero output).

    Returns
    -------
    torch.nn.Module
        ``module`` itself.

    Raises
    ------
    ValueError
        If ``generator`` is not a :class:`torch.Generator`.
    """
    if not isinstance(generator, torch.Generator):
        raise ValueError(f"generator: expected a torch.Generator, got {type(generator).__name__}")
    linears = [m for m in module.modules() if isinstance(m, nn.Linear)]
    with torch.no_grad():
        for i, lin in enumerate(linears):
            bound = 1.0 / math.sqrt(lin.in_features) * (last_scale if i == len(linears) - 1 else 1.0)
            nn.init.uniform_(lin.weight, -bound, bound, generator=generator)
            if lin.bias is not None:
                nn.init.uniform_(lin.bias, -bound, bound, generator=generator)
    return module


class MLP(nn.Module):
    """Multilayer perceptron ``in_dim -> hidden_sizes -> out_dim`` with a fixed input scaling.

    Parameters
    ----------
    in_dim, out_dim : int
        Input and output widths.
    hidden_sizes : sequence of int
        Hidden widths.
    activation : {"elu", "tanh", "relu"}
        Hidden activation.
    input_scale : torch.Tensor, shape (in_dim,), optional
        Inputs are divided by this (a fixed normalisation; default ones).
    generator : torch.Generator
        Initialisation source.
    last_scale : float, optional
        See :func:`init_uniform_`.
    """

    def __init__(self, in_dim: int, out_dim: int, hidden_sizes: Sequence[int], activation: str,
                 generator: torch.Generator, input_scale: torch.Tensor | None = None,
                 last_scale: float = 1.0) -> None:
        super().__init__()
        if activation not in _ACTIVATIONS:
            raise ValueError(f"activation: expected one of {sorted(_ACTIVATIONS)}, got {activation!r}")
        widths = [in_dim, *map(int, hidden_sizes)]
        hidden = [(nn.Linear(a, b), _ACTIVATIONS[activation]()) for a, b in zip(widths, widths[1:])]
        self.body = nn.Sequential(*[m for pair in hidden for m in pair], nn.Linear(widths[-1], out_dim))
        scale = torch.ones(in_dim) if input_scale is None else torch.as_tensor(input_scale, dtype=torch.float32)
        if scale.shape != (in_dim,) or not bool((scale > 0).all()):
            raise ValueError(f"input_scale: expected {in_dim} positive numbers, got {tuple(scale.shape)}")
        self.register_buffer("input_scale", scale.clone())
        init_uniform_(self, generator, last_scale)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Evaluate on ``x`` of shape ``(..., in_dim)``; returns ``(..., out_dim)``."""
        return self.body(x / self.input_scale)


#: Output heads of the value networks: the MLP's output width (see :class:`Critic`).
_OUT_WIDTH = {"linear": 1, "softplus": 1, "square": 8}


class Critic(nn.Module):
    """State-value critic ``V(x; w)`` of eq. (48): an :class:`MLP` with one output, times ``value_scale``.

    ``forward(obs)`` maps observations ``(..., obs_dim)`` to values ``(...)``. The utility of eq. (2) is
    ``>= 0``, so every value is ``>= 0``; the default heads respect that (a critic that cannot go
    negative cannot be exploited by the actor where it has not been trained): ``output="softplus"``,
    ``value_scale * softplus(MLP(obs))``, or ``output="square"``, ``value_scale * |MLP(obs)|^2 / 2`` with
    an 8-dimensional MLP output (a sum of squares: near-quadratic around its minimum, like the LQ value);
    ``"linear"`` is the plain MLP.
    """

    def __init__(self, obs_dim: int, hidden_sizes: Sequence[int], activation: str, generator: torch.Generator,
                 obs_scale: torch.Tensor | None = None, value_scale: float = 1.0, output: str = "softplus") -> None:
        super().__init__()
        if output not in _OUT_WIDTH:
            raise ValueError(f"output: expected one of {sorted(_OUT_WIDTH)}, got {output!r}")
        self.net = MLP(obs_dim, _OUT_WIDTH[output], hidden_sizes, activation, generator, obs_scale)
        self.value_scale = float(value_scale)
        self.output = output

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        z = self.net(obs)
        if self.output == "square":
            return 0.5 * z.pow(2).sum(-1) * self.value_scale
        z = z.squeeze(-1)
        return (z if self.output == "linear" else nn.functional.softplus(z)) * self.value_scale


class Actor(nn.Module):
    """Deterministic actor ``u = pi(x; theta)`` of eq. (48), bounded by ``action_bound``.

    ``u = action_bound * tanh(MLP(obs))``; the output layer starts small so the first policy is near 0.
    """

    def __init__(self, obs_dim: int, action_dim: int, hidden_sizes: Sequence[int], activation: str,
                 generator: torch.Generator, action_bound: torch.Tensor, obs_scale: torch.Tensor | None = None
                 ) -> None:
        super().__init__()
        self.net = MLP(obs_dim, action_dim, hidden_sizes, activation, generator, obs_scale, last_scale=0.1)
        bound = torch.as_tensor(action_bound, dtype=torch.float32)
        if bound.shape != (action_dim,) or not bool((bound > 0).all()):
            raise ValueError(f"action_bound: expected {action_dim} positive numbers, got {tuple(bound.shape)}")
        self.register_buffer("action_bound", bound.clone())

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.action_bound * torch.tanh(self.net(obs))


class ClippedActor(Actor):
    """An :class:`Actor` whose output is clipped instead of ``tanh``-squashed
    (``algorithm.actor_output = "clip_inward"``, :mod:`mixedrl.departures.actor_output`), the clip's gradient
    passed straight through for the parameters only, and only inward.

    .. math:: u(o) = \\bar u \\operatorname{clip}\\big(z(o; \\theta), -1, 1\\big), \\qquad z = \\mathrm{MLP}(o; \\theta)

    with the gradients ``du/dtheta = u_bar dz/dtheta`` where ``|z| <= 1`` and, where ``z`` is clipped, where a
    descent step moves ``z`` back inside (``dJ/dz * z > 0``: straight through, so a saturated actor still
    receives the gradient that pulls it back, and cannot wind up), and ``du/do = u_bar clip'(z) dz/do`` (the
    true one: zero where clipped). The value is exactly ``u_bar clip(z, -1, 1)``: the straight-through term
    ``z_p - detach(z_p)``, ``z_p = MLP(detach(o))``, adds 0. With gradients enabled the MLP is evaluated twice
    (``o`` and ``detach(o)``). Same parameters, initialisation and draws as the :class:`Actor`.
    """

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        z = self.net(obs)
        out = z.clamp(-1.0, 1.0)
        if torch.is_grad_enabled():
            z_params = self.net(obs.detach())  # the parameters' path only
            outside = (z < -1.0) | (z > 1.0)
            through = _Inward.apply(z_params - z_params.detach(), z.detach())
            out = out + torch.where(outside, through, torch.zeros_like(z_params))
        return self.action_bound * out


class _Inward(torch.autograd.Function):
    """``x`` unchanged; backward: the gradient ``g`` kept where a descent step moves ``z`` back inside
    (``g z > 0``), zero where it would push ``z`` further out (no wind-up of a saturated output)."""

    generate_vmap_rule = True

    @staticmethod
    def forward(x: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        return x.clone()

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[torch.Tensor, torch.Tensor], output: torch.Tensor) -> None:
        ctx.save_for_backward(inputs[1])

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor, None]:
        (z,) = ctx.saved_tensors
        return grad * (grad * z > 0).to(grad.dtype), None


def stacked_actors(actors: Sequence[nn.Module]) -> Callable[[torch.Tensor], torch.Tensor] | None:
    """``P`` plain :class:`Actor` modules of one architecture as one batched function (a batched matrix
    product per layer), or ``None`` when they are not (another class, other shapes or activations).

    .. math:: u_p = \\bar u_p \\tanh\\big(\\mathrm{MLP}_p(o_p / s_p)\\big), \\qquad p = 1 \\dots P

    The returned function maps observations ``(P, S, obs_dim)`` to actions ``(P, S, action_dim)``; the
    weights are copied when it is built (later changes of the modules are not seen). Used by the course
    evaluation of many runs (:func:`mixedrl.envs.evaluate_courses` with ``exact=False``). Its float32 outputs
    agree with each module's own to rounding, not bit for bit (a batched product sums in another order).
    """
    if len(actors) == 0 or any(type(a) is not Actor for a in actors):
        return None
    layers = list(actors[0].net.body)
    kinds = [type(layer) for layer in layers]
    if any(k is not nn.Linear and k not in _ACTIVATIONS.values() for k in kinds):
        return None
    shapes = [tuple(v.shape) for v in actors[0].state_dict().values()]
    if any([type(x) for x in a.net.body] != kinds or [tuple(v.shape) for v in a.state_dict().values()] != shapes
           for a in actors):
        return None
    with torch.no_grad():
        scale = torch.stack([a.net.input_scale for a in actors])[:, None, :]
        bound = torch.stack([a.action_bound for a in actors])[:, None, :]
        # per layer: the stacked (P, in, out) weights and (P, 1, out) biases, or the activation module
        steps = [(torch.stack([a.net.body[i].weight.detach() for a in actors]).transpose(1, 2).contiguous(),
                  torch.stack([a.net.body[i].bias.detach() for a in actors])[:, None, :])
                 if isinstance(layer, nn.Linear) else layer for i, layer in enumerate(layers)]

    def call(obs: torch.Tensor) -> torch.Tensor:
        h = obs / scale
        for step in steps:
            # h W^T + b for every run at once; the activations are elementwise
            h = torch.baddbmm(step[1], h, step[0]) if isinstance(step, tuple) else step(h)
        return bound * torch.tanh(h)

    return call


class QCritic(Critic):
    """Action-value critic ``Q(x, u; w)`` for DDPG: the same MLP on ``[obs / obs_scale, u / bound]``, with the
    same non-negative output as :class:`Critic`."""

    def __init__(self, obs_dim: int, action_dim: int, hidden_sizes: Sequence[int], activation: str,
                 generator: torch.Generator, action_bound: torch.Tensor, obs_scale: torch.Tensor | None = None,
                 value_scale: float = 1.0, output: str = "softplus") -> None:
        obs_scale = torch.ones(obs_dim) if obs_scale is None else torch.as_tensor(obs_scale, dtype=torch.float32)
        scale = torch.cat([obs_scale, torch.as_tensor(action_bound, dtype=torch.float32)])
        super().__init__(obs_dim + action_dim, hidden_sizes, activation, generator, scale, value_scale, output)

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return super().forward(torch.cat([obs, action], dim=-1))


class QuadraticCritic(nn.Module):
    """Exact value class of the LQ case: ``V(x) = x^T P x + 2 p^T x + c`` with ``P = M M^T`` free (to check
    Algorithm 2 against the DARE solution)."""

    def __init__(self, obs_dim: int, generator: torch.Generator) -> None:
        super().__init__()
        self.M = nn.Parameter(0.1 * torch.randn(obs_dim, obs_dim, generator=generator))
        self.p = nn.Parameter(torch.zeros(obs_dim))
        self.c = nn.Parameter(torch.zeros(()))

    @property
    def P(self) -> torch.Tensor:
        """The quadratic term ``M M^T``, shape (n, n)."""
        return self.M @ self.M.T

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        quad = torch.einsum("...i,ij,...j->...", obs, self.P, obs)
        return quad + 2.0 * obs @ self.p + self.c


class AffineActor(nn.Module):
    """Exact policy class of the LQ case: ``u = -L x - l0`` (unbounded)."""

    def __init__(self, obs_dim: int, action_dim: int, generator: torch.Generator) -> None:
        super().__init__()
        self.L = nn.Parameter(torch.zeros(action_dim, obs_dim))
        self.l0 = nn.Parameter(torch.zeros(action_dim))
        _ = generator  # deterministic zero start; the argument keeps the constructors uniform

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return -(obs @ self.L.T) - self.l0
