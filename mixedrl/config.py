"""One typed, documented configuration object per training run.

:class:`TrainConfig` holds every knob of a run of Algorithm 2 (``method`` = ``mixed``, ``model``,
``oracle``) or of the DDPG baseline (``method = "ddpg"``). It is saved as ``config.json`` beside the
run's results; loading a dictionary with a key that is not a field is an error (a misspelt option must
never be silently ignored).

The defaults are the settings used for the reproduction of Table I (``mixedrl reproduce``). Every method
gets the *same* networks, optimiser, learning rates, batch of states and iteration budget; the
``ddpg_*`` fields only configure what DDPG has and the model-based methods do not (replay buffer,
target networks, exploration noise; textbook values, not tuned). The shared settings (learning rates,
their decay, ``horizon``, ``value_output``, ``batch_size``, the budget) were chosen by a small search
on mixed-RL runs of the double lane change (seeds 0-2) and then applied unchanged to every method.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mixedrl._checks import check_unknown_keys

__all__ = ["TrainConfig", "METHODS", "TASKS"]

#: The four methods of the reproduction (mixed RL, model-driven RL, oracle, DDPG).
METHODS = ("mixed", "model", "oracle", "ddpg")
#: Tasks a run can be trained on: the double lane change (paper) and a small linear system.
TASKS = ("dlc", "linear")


@dataclass
class TrainConfig:
    """Configuration of one training run (Algorithm 2 or DDPG).

    Every field is documented below; ``to_dict`` / ``from_dict`` round-trip exactly through JSON.
    """

    method: str = "mixed"
    """Which algorithm: ``"mixed"`` (Algorithm 2, IBE posterior), ``"model"`` (Algorithm 2 on the prior
    model of eq. 55, IBE off), ``"oracle"`` (Algorithm 2 with the true noise) or ``"ddpg"``."""

    task: str = "dlc"
    """``"dlc"``: the double lane change of Section V; ``"linear"``: a 2-state linear system with a
    quadratic cost (known LQ optimum), used by the tests and the tutorial."""

    seed: int = 0
    """Seed of every generator of the run (network initialisation, initial states, noise, exploration,
    replay sampling). Same seed, same weights."""

    iterations: int = 1500
    """Budget: number of outer iterations ``k`` (one PEV + PIM step of Algorithm 2, or one DDPG update)."""

    batch_size: int = 512
    """Number of states per iteration: the parallel copies of the true environment whose current states
    form the PEV/PIM batch (Algorithm 2) or the replay minibatch size (DDPG)."""

    horizon: int = 60
    """Steps after which a training copy of the environment is reset to a fresh initial state."""

    train_half_widths: tuple[float, ...] = (0.3, 0.2, 1.0, 0.1, 1.0)
    """Double lane change only: half-widths of the uniform perturbation of ``[v_y, r, v_x - 12, e_phi,
    e_y]`` of the training start states (anywhere on the course), see
    :class:`mixedrl.envs.DoubleLaneChangeConfig`."""

    state_source: str = "true"
    """Where Algorithm 2's PEV/PIM states come from: ``"true"`` = the ``batch_size`` copies of the true
    environment, one true step per copy per iteration (the reproduction's setting); ``"model"`` = rollouts
    of the planning model ``f + xi_hat`` under the method's noise source
    (:class:`mixedrl.algorithms.model_data.ModelStateSampler`), the true environment only feeding the IBE
    (``true_envs``, ``true_steps``, ``true_every``)."""

    model_course_fraction: float = 0.75
    """``state_source="model"``: fraction of the batch's rollouts that drive the course from its start
    (the rest restart from the wide training distribution every ``horizon`` steps)."""

    model_course_start: int = 500
    """``state_source="model"``: iteration from which the course rollouts start from the course start;
    before it they restart from the wide distribution like the others (a schedule: the course is driven
    only by a policy that has first learnt to stay near the reference)."""

    model_course_horizon: int = 2000
    """``state_source="model"``: steps after which a course rollout (and a true-data copy) restarts at the
    course start (2000 = the whole double lane change)."""

    model_kick_prob: float = 0.01
    """``state_source="model"``: probability per step that a course rollout is kicked: a uniform random
    offset of ``model_kick_scale * obs_scale_i`` on each noise component is added to its state, and the
    policy has to recover (exploration in state space around the course)."""

    model_kick_scale: float = 1.0
    """``state_source="model"``: size of a kick, in units of the task's ``obs_scale``."""

    model_box: float = 3.0
    """``state_source="model"``: a rollout restarts when a component of its observation exceeds
    ``model_box`` times the task's ``obs_scale`` (``math.inf`` disables it)."""

    true_envs: int = 1
    """``state_source="model"``, mixed RL: true-environment copies driven at each collection."""

    true_steps: int = 20
    """``state_source="model"``, mixed RL: consecutive steps each true copy drives per collection."""

    true_every: int = 10
    """``state_source="model"``, mixed RL: iterations between collections (true transitions per iteration:
    ``true_envs * true_steps / true_every``; model-driven RL and the oracle collect none)."""

    hidden_sizes: tuple[int, ...] = (64, 64)
    """Hidden layer widths of the actor and the critic (the same for every method)."""

    activation: str = "elu"
    """Hidden activation of the MLPs: ``"elu"``, ``"tanh"`` or ``"relu"``."""

    value_output: str = "square"
    """Output head of the critic (and of DDPG's Q-critic): ``"softplus"``, ``"square"`` (sum of squares)
    or ``"linear"``; see :class:`mixedrl.networks.Critic`."""

    critic_lr: float = 3e-3
    """Adam learning rate alpha of the critic (eq. 50), also DDPG's Q-critic."""

    actor_lr: float = 3e-4
    """Adam learning rate beta of the actor (eq. 52), also DDPG's actor."""

    lr_decay_to: float = 0.01
    """Learning rates decay linearly from their value to ``lr_decay_to`` times it over the budget
    (1.0 = constant)."""

    grad_clip: float = 10.0
    """Clip of the global gradient norm of each update (``math.inf`` disables it)."""

    expectation: str = "sigma"
    """How the expectation over ``xi_hat ~ N(mu_hat, K_hat)`` in eqs. (49)-(52) is computed:
    ``"sigma"`` = deterministic spherical-cubature sigma points in the range of ``K_hat`` (2r points,
    exact for polynomials of degree <= 3 in ``xi``), ``"samples"`` = reparameterised Monte-Carlo samples."""

    noise_samples: int = 4
    """Number of reparameterised samples per state when ``expectation == "samples"``."""

    j_max: int = 5
    """Maximum number of extra PIM steps of the AGPI inner loop (Algorithm 2)."""

    mvc_check: str = "mean"
    """Where the MVC (eq. 38) is checked on the batch: ``"mean"`` (batch average of both sides) or
    ``"all"`` (every state)."""

    stop_epsilon: float = 0.0
    """Stopping test of Algorithm 2: stop when the mean absolute change of ``V`` and of ``pi`` on the
    batch both stay below ``stop_epsilon`` for ``stop_patience`` iterations; 0 disables it (the run
    uses its whole budget)."""

    stop_patience: int = 100
    """Consecutive iterations the stopping test must hold."""

    ibe_recursion: str = "exact"
    """Recursion of the Case-2 IBE (``"exact"`` = eq. 17 recursively, ``"paper"`` = eq. 18)."""

    eval_every: int = 100
    """Evaluate the policy on the full double lane change every ``eval_every`` iterations."""

    eval_seeds: int = 2
    """Number of noise realisations averaged by each evaluation."""

    checkpoint_every: int = 500
    """Write an atomic checkpoint every ``checkpoint_every`` iterations (and at the end)."""

    num_threads: int = 1
    """``torch.set_num_threads`` for the run (fixed, so results do not depend on the machine)."""

    ddpg_envs: int = 16
    """DDPG: parallel true-environment copies stepped once per iteration (transitions per iteration)."""

    ddpg_buffer_size: int = 200_000
    """DDPG: replay buffer capacity (transitions)."""

    ddpg_warmup: int = 2000
    """DDPG: transitions collected with exploration before the first update."""

    ddpg_tau: float = 0.005
    """DDPG: Polyak factor of the target networks."""

    ddpg_noise_std: float = 0.2
    """DDPG: standard deviation of the Gaussian exploration noise, as a fraction of each action bound."""

    def __post_init__(self) -> None:
        self.hidden_sizes = tuple(int(h) for h in self.hidden_sizes)
        self.train_half_widths = tuple(float(w) for w in self.train_half_widths)
        self.validate()

    def validate(self) -> None:
        """Check every field.

        Raises
        ------
        ValueError
            The message starts with the offending field's name.
        """
        if self.method not in METHODS:
            raise ValueError(f"method: expected one of {METHODS}, got {self.method!r}")
        if self.task not in TASKS:
            raise ValueError(f"task: expected one of {TASKS}, got {self.task!r}")
        if self.expectation not in ("sigma", "samples"):
            raise ValueError(f"expectation: expected 'sigma' or 'samples', got {self.expectation!r}")
        if self.mvc_check not in ("mean", "all"):
            raise ValueError(f"mvc_check: expected 'mean' or 'all', got {self.mvc_check!r}")
        if self.activation not in ("elu", "tanh", "relu"):
            raise ValueError(f"activation: expected 'elu', 'tanh' or 'relu', got {self.activation!r}")
        if self.value_output not in ("softplus", "square", "linear"):
            raise ValueError(f"value_output: expected 'softplus', 'square' or 'linear', got {self.value_output!r}")
        if self.state_source not in ("true", "model"):
            raise ValueError(f"state_source: expected 'true' or 'model', got {self.state_source!r}")
        if not 0.0 <= float(self.model_course_fraction) <= 1.0:
            raise ValueError(f"model_course_fraction: expected a number in [0, 1], got {self.model_course_fraction!r}")
        if isinstance(self.model_course_start, bool) or not isinstance(self.model_course_start, int) \
                or self.model_course_start < 0:
            raise ValueError(f"model_course_start: expected a non-negative integer, got {self.model_course_start!r}")
        if not 0.0 <= float(self.model_kick_prob) <= 1.0:
            raise ValueError(f"model_kick_prob: expected a number in [0, 1], got {self.model_kick_prob!r}")
        if not (float(self.model_kick_scale) >= 0 and math.isfinite(self.model_kick_scale)):
            raise ValueError(f"model_kick_scale: expected a finite number >= 0, got {self.model_kick_scale!r}")
        if not float(self.model_box) > 0:
            raise ValueError(f"model_box: expected a positive number, got {self.model_box!r}")
        if self.ibe_recursion not in ("exact", "paper"):
            raise ValueError(f"ibe_recursion: expected 'exact' or 'paper', got {self.ibe_recursion!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed: expected a non-negative integer, got {self.seed!r}")
        for name in ("iterations", "batch_size", "horizon", "noise_samples", "j_max", "stop_patience",
                     "eval_every", "eval_seeds", "checkpoint_every", "num_threads", "ddpg_envs",
                     "ddpg_buffer_size", "model_course_horizon", "true_envs", "true_steps", "true_every"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name}: expected a positive integer, got {value!r}")
        if isinstance(self.ddpg_warmup, bool) or not isinstance(self.ddpg_warmup, int) or self.ddpg_warmup < 0:
            raise ValueError(f"ddpg_warmup: expected a non-negative integer, got {self.ddpg_warmup!r}")
        if len(self.train_half_widths) != 5 or any(not (w >= 0 and math.isfinite(w)) for w in self.train_half_widths):
            raise ValueError(f"train_half_widths: expected 5 finite numbers >= 0, got {self.train_half_widths!r}")
        if not self.hidden_sizes or any(h < 1 for h in self.hidden_sizes):
            raise ValueError(f"hidden_sizes: expected positive widths, got {self.hidden_sizes!r}")
        for name in ("critic_lr", "actor_lr", "grad_clip", "ddpg_noise_std"):
            value = float(getattr(self, name))
            if not value > 0 or math.isnan(value):
                raise ValueError(f"{name}: expected a positive number, got {value!r}")
        for name in ("lr_decay_to", "ddpg_tau"):
            value = float(getattr(self, name))
            if not 0 < value <= 1:
                raise ValueError(f"{name}: expected a number in (0, 1], got {value!r}")
        if not (self.stop_epsilon >= 0 and math.isfinite(self.stop_epsilon)):
            raise ValueError(f"stop_epsilon: expected a finite number >= 0, got {self.stop_epsilon!r}")

    # ------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict[str, Any]:
        """Return the fields as a JSON-compatible dictionary (tuples become lists; ``inf`` a string)."""
        out = dataclasses.asdict(self)
        out["hidden_sizes"] = list(self.hidden_sizes)
        out["train_half_widths"] = list(self.train_half_widths)
        for name in ("grad_clip", "model_box"):
            if math.isinf(out[name]):
                out[name] = "inf"
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "TrainConfig":
        """Build a config from a dictionary.

        Raises
        ------
        ValueError
            ``data`` has a key that is not a field (message starts with ``config``), or a field is invalid.
        """
        if not isinstance(data, dict):
            raise ValueError(f"config: expected a dict, got {type(data).__name__}")
        check_unknown_keys(data, {f.name for f in dataclasses.fields(cls)}, "config")
        data = dict(data)
        for name in ("grad_clip", "model_box"):
            if data.get(name) == "inf":
                data[name] = math.inf
        return cls(**data)

    def replace(self, **changes: Any) -> "TrainConfig":
        """Return a copy with ``changes`` applied (unknown keys are an error)."""
        return TrainConfig.from_dict({**self.to_dict(), **changes})

    def save(self, path: str | Path) -> None:
        """Write the config as JSON to ``path``."""
        Path(path).write_text(json.dumps(self.to_dict(), indent=2, sort_keys=True) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> "TrainConfig":
        """Read a config written by :meth:`save`.

        Raises
        ------
        ValueError
            The file is not valid JSON or holds an unknown key.
        """
        try:
            data = json.loads(Path(path).read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"path: {path} is not valid JSON ({exc})") from None
        return cls.from_dict(data)

