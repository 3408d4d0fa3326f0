"""The noise sources (mixedrl.noise): one factory for Algorithms 1 and 2, the protocol's ``learns`` flag,
and Case 3 (StateDependentIBE) planned with by Algorithm 2 through per-state nodes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mixedrl.algorithms.agpi import AGPI
from mixedrl.algorithms.policy_iteration import ibe_step
from mixedrl.config import TrainConfig
from mixedrl.ibe import KnownCovarianceIBE, StateDependentIBE, UnknownCovarianceIBE
from mixedrl.noise import GaussianNoise, make_noise_source
from mixedrl.tasks import LinearTask
from validation.lq import example_problem


@pytest.mark.parametrize("source", [LinearTask(), example_problem()])
def test_one_factory_for_both_algorithms(source) -> None:
    mixed = make_noise_source("mixed", source)
    assert isinstance(mixed, UnknownCovarianceIBE) and mixed.learns and not mixed.state_dependent
    assert np.array_equal(mixed.mean, source.prior_mean)
    assert make_noise_source("mixed", source, "paper").recursion == "paper"
    known = make_noise_source("mixed", source, covariance="known")
    assert isinstance(known, KnownCovarianceIBE) and np.array_equal(known.noise_cov, source.true_cov)
    model, oracle = make_noise_source("model", source), make_noise_source("oracle", source)
    assert isinstance(model, GaussianNoise) and not model.learns
    assert np.array_equal(model.mean, source.prior_mean) and np.array_equal(oracle.mean, source.true_mean)
    for kwargs, name in (({"method": "ddpg"}, "method"), ({"method": "mixed", "recursion": "x"}, "recursion"),
                         ({"method": "mixed", "covariance": "x"}, "covariance"),
                         ({"method": "mixed", "recursion": "paper", "covariance": "known"}, "recursion")):
        with pytest.raises(ValueError, match=f"^{name}"):
            make_noise_source(task=source, **kwargs)


def test_fixed_sources_do_not_learn_and_cannot_be_updated() -> None:
    prior = GaussianNoise([0.0], [[1.0]])
    assert not hasattr(prior, "update")  # no silent no-op
    with pytest.raises(ValueError, match="^noise"):
        ibe_step(prior, np.zeros((3, 1)))
    ibe_step(prior, None)  # a fixed source with no data: the IBE step is the identity
    assert np.array_equal(prior.mean, [0.0])


class Phi(torch.nn.Module):
    """phi(x, u) = x W + b: a state-dependent mean of the noise (Case 3)."""

    def __init__(self) -> None:
        super().__init__()
        self.lin = torch.nn.Linear(2, 2, dtype=torch.float64)
        with torch.no_grad():
            self.lin.weight.copy_(torch.tensor([[0.0, 0.0], [0.8, -0.4]]))
            self.lin.bias.zero_()

    def forward(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return self.lin(x)


def test_agpi_plans_with_a_state_dependent_ibe() -> None:
    """Algorithm 2 runs with Case 3 and plans, at each state of the batch, with nodes centred at
    phi(x, pi^k(x)) of the current fit; the fit moves with the data."""
    task = LinearTask()
    noise = StateDependentIBE(Phi(), task.true_cov + 1e-4 * np.eye(2), 2, 1, prior_std=1.0, max_iter=20)
    assert noise.learns and noise.state_dependent
    ag = AGPI(task, TrainConfig(method="mixed", task="linear", batch_size=16, iterations=5), noise_source=noise)
    seen: list[tuple[torch.Tensor, torch.Tensor]] = []
    original = ag.pev

    def spy(s, offsets, weights):  # noqa: ANN001
        with torch.no_grad():
            centre = noise.mean_at(s.double(), ag.actor(task.observe(s)).double())
        seen.append((torch.einsum("p,pbn->bn", weights.double(), offsets.double()), centre))
        return original(s, offsets, weights)

    ag.pev = spy
    w_before = noise.phi.lin.weight.detach().clone()
    rows = [ag.iteration() for _ in range(3)]
    assert all(np.isfinite(v) for r in rows for v in r.values())
    assert noise.count == 3 * 16 and rows[-1]["ibe/count"] == 48.0
    assert not torch.equal(w_before, noise.phi.lin.weight)  # the IBE learned
    for mean_used, centre in seen:
        assert mean_used.shape == (16, 2)
        torch.testing.assert_close(mean_used, centre @ task.noise_matrix.double().T, rtol=1e-6, atol=1e-6)
        assert float(centre[:, 1].std()) > 1e-3  # the nodes differ from state to state
