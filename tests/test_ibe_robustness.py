"""The IBE is never poisoned: bad input and overflowing updates are refused with the state kept.

Every estimator of :mod:`mixedrl.ibe` must refuse, with a ``ValueError`` naming the argument and its
``state_dict()`` unchanged, residuals (and states, actions) that are not real numbers, updates whose
posterior would not be finite and symmetric PSD (overflow included), zero-dimensional noise at
construction, and states with non-finite or non-PSD content. After a refused update the estimator
continues exactly as one that never saw it. No floating-point warning may escape (``error`` filter).
"""

import numpy as np
import pytest
import torch

from mixedrl.ibe import (
    KnownCovarianceIBE,
    LinearFeatureIBE,
    StateDependentIBE,
    UnknownCovarianceIBE,
    map_mean_cov,
    map_mean_known_cov,
    residuals,
)

pytestmark = pytest.mark.filterwarnings("error")

NOT_REAL = {
    "complex": lambda shape: np.ones(shape, dtype=complex),
    "bool": lambda shape: np.ones(shape, dtype=bool),
    "str": lambda shape: np.full(shape, "1.0"),
    "object": lambda shape: np.ones(shape).astype(object),
    "complex list": lambda shape: np.ones(shape, dtype=complex).tolist(),
    "bool tensor": lambda shape: torch.ones(shape, dtype=torch.bool),
    "complex tensor": lambda shape: torch.ones(shape, dtype=torch.complex128),
}


def assert_same_state(a: dict, b: dict) -> None:
    """Two ``state_dict()`` results are equal, bit for bit."""
    assert set(a) == set(b)
    for key in a:
        va, vb = a[key], b[key]
        if isinstance(va, list):
            assert len(va) == len(vb)
            for x, y in zip(va, vb):
                np.testing.assert_array_equal(x, y, strict=True)
        elif isinstance(va, np.ndarray):
            np.testing.assert_array_equal(va, vb, strict=True)
        else:
            assert va == vb, key


def known() -> KnownCovarianceIBE:
    return KnownCovarianceIBE(prior_mean=np.zeros(2), prior_cov=np.eye(2), noise_cov=np.diag([1.0, 0.5]))


def unknown(recursion: str = "exact") -> UnknownCovarianceIBE:
    return UnknownCovarianceIBE(prior_mean=np.zeros(2), prior_cov=np.eye(2), recursion=recursion)


def features(x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    return torch.cat([torch.ones((x.shape[0], 1), dtype=torch.float64), x, u], dim=1)


def linear() -> LinearFeatureIBE:
    return LinearFeatureIBE(features, np.zeros((4, 2)), np.array([[1.0, 0.2], [0.2, 0.5]]), 2, 1, prior_std=0.7)


class Phi(torch.nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.lin = torch.nn.Linear(3, 2)

    def forward(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return self.lin(torch.cat([x, u], dim=1))


def state_dependent() -> StateDependentIBE:
    torch.manual_seed(0)
    return StateDependentIBE(Phi(), np.array([[1.0, 0.2], [0.2, 0.5]]), 2, 1, prior_std=1.0, max_iter=20)


def normal_residuals(n: int = 1000) -> np.ndarray:
    return np.random.default_rng(7).normal(0.3, 1.0, size=(n, 2))


# ----------------------------------------------------------------------------------------------------
# the probes of issue 22 item 4
# ----------------------------------------------------------------------------------------------------
def refuse_then_continue(est, clean, bad) -> None:
    """``est.update(bad)`` is refused with the state kept; 1000 normal residuals then give, bit for bit,
    the state of ``clean`` (same history without ``bad``)."""
    before = est.state_dict()
    with pytest.raises(ValueError, match=r"^xi: update rejected.*not be finite"):
        est.update(bad)
    assert_same_state(est.state_dict(), before)
    assert np.all(np.isfinite(est.mean)) and np.all(np.isfinite(est.cov))
    for xi in normal_residuals():
        est.update(xi)
        clean.update(xi)
    assert_same_state(est.state_dict(), clean.state_dict())
    np.testing.assert_array_equal(est.mean, clean.mean)
    np.testing.assert_array_equal(est.cov, clean.cov)
    np.testing.assert_array_equal(est.mean_cov, clean.mean_cov)


@pytest.mark.parametrize("recursion", ["exact", "paper"])
def test_case2_huge_residual_refused_and_later_data_unaffected(recursion: str) -> None:
    est, clean = unknown(recursion), unknown(recursion)
    est.update(normal_residuals(5))
    clean.update(normal_residuals(5))
    refuse_then_continue(est, clean, [[1e160, 0.0], [0.0, 0.0]])


def test_case2_fresh_estimator_refuses_the_probe() -> None:
    est = UnknownCovarianceIBE(prior_mean=np.zeros(2), prior_cov=np.eye(2))
    refuse_then_continue(est, unknown(), [[1e160, 0], [0, 0]])


def test_case1_overflowing_sum_refused_and_later_data_unaffected() -> None:
    refuse_then_continue(known(), known(), np.full((3, 2), 1e308))


def test_case1_overflow_across_updates_refused() -> None:
    """Each update is finite, their running sum ``m_k`` is not."""
    est = known()
    est.update([1e308, 0.0])
    before = est.state_dict()
    with pytest.raises(ValueError, match=r"^xi: update rejected"):
        est.update([1e308, 0.0])
    assert_same_state(est.state_dict(), before)


@pytest.mark.parametrize("kind", sorted(NOT_REAL))
@pytest.mark.parametrize("make", [known, unknown, lambda: unknown("paper")], ids=["case1", "case2", "case2-paper"])
def test_case12_residuals_must_be_real(make, kind: str) -> None:
    est = make()
    est.update(normal_residuals(3))
    before = est.state_dict()
    with pytest.raises(ValueError, match=r"^xi: "):
        est.update(NOT_REAL[kind]((3, 2)))
    assert_same_state(est.state_dict(), before)


@pytest.mark.parametrize("kind", sorted(NOT_REAL))
@pytest.mark.parametrize("make", [linear, state_dependent], ids=["linear", "state-dependent"])
@pytest.mark.parametrize("arg", ["x", "u", "xi"])
def test_case3_inputs_must_be_real(make, kind: str, arg: str) -> None:
    est = make()
    rng = np.random.default_rng(1)
    good = {"x": rng.normal(size=(3, 2)), "u": rng.normal(size=(3, 1)), "xi": rng.normal(size=(3, 2))}
    est.update(**good)
    before = est.state_dict()
    bad = dict(good, **{arg: NOT_REAL[kind](good[arg].shape)})
    with pytest.raises(ValueError, match=rf"^{arg}: "):
        est.update(**bad)
    assert_same_state(est.state_dict(), before)


@pytest.mark.parametrize("kind", ["complex", "bool", "str"])
def test_batch_references_and_residuals_refuse_non_real(kind: str) -> None:
    bad = NOT_REAL[kind]((3, 2))
    with pytest.raises(ValueError, match=r"^xi: "):
        map_mean_known_cov(np.zeros(2), np.eye(2), np.eye(2), bad)
    with pytest.raises(ValueError, match=r"^xi: "):
        map_mean_cov(np.zeros(2), np.eye(2), bad)
    with pytest.raises(ValueError, match=r"^prior_mean: "):
        KnownCovarianceIBE(NOT_REAL[kind]((2,)), np.eye(2), np.eye(2))
    with pytest.raises(ValueError, match=r"^prior_cov: "):
        UnknownCovarianceIBE(np.zeros(2), NOT_REAL[kind]((2, 2)))
    with pytest.raises(ValueError, match=r"^x: "):
        residuals(lambda x, u: x, bad, np.zeros((3, 1)), np.zeros((3, 2)))


def test_batch_references_refuse_overflow() -> None:
    with pytest.raises(ValueError, match=r"^xi: .*not be finite"):
        map_mean_known_cov(np.zeros(2), np.eye(2), np.eye(2), np.full((3, 2), 1e308))
    with pytest.raises(ValueError, match=r"^xi: .*not be finite"):
        map_mean_cov(np.zeros(2), np.eye(2), [[1e160, 0.0], [0.0, 0.0]])


# ----------------------------------------------------------------------------------------------------
# zero dimensions
# ----------------------------------------------------------------------------------------------------
def test_zero_dimension_refused_at_construction() -> None:
    z, zz = np.zeros(0), np.zeros((0, 0))
    with pytest.raises(ValueError, match=r"^prior_mean: .*at least one dimension"):
        KnownCovarianceIBE(z, zz, zz)
    with pytest.raises(ValueError, match=r"^prior_mean: .*at least one dimension"):
        UnknownCovarianceIBE(z, zz)
    with pytest.raises(ValueError, match=r"^prior_mean: .*at least one dimension"):
        map_mean_known_cov(z, zz, zz, np.zeros((3, 0)))
    with pytest.raises(ValueError, match=r"^prior_mean: .*at least one dimension"):
        map_mean_cov(z, zz, np.zeros((3, 0)))
    with pytest.raises(ValueError, match=r"^noise_cov: .*at least one dimension"):
        StateDependentIBE(Phi(), zz, 2, 1)
    with pytest.raises(ValueError, match=r"^prior_weights .*at least one dimension"):
        LinearFeatureIBE(features, np.zeros((4, 0)), zz, 2, 1)
    with pytest.raises(ValueError, match=r"^prior_weights .*at least one dimension"):
        LinearFeatureIBE(lambda x, u: x[:, :0], np.zeros((0, 2)), np.eye(2), 2, 1)


# ----------------------------------------------------------------------------------------------------
# Case 3 overflow
# ----------------------------------------------------------------------------------------------------
def test_linear_feature_overflow_refused_and_later_data_unaffected() -> None:
    est, clean = linear(), linear()
    rng = np.random.default_rng(2)
    before = est.state_dict()
    with pytest.raises(ValueError, match=r"^x: update rejected"):
        est.update(np.full((3, 2), 1e200), np.zeros((3, 1)), np.zeros((3, 2)))  # G = sum g g^T overflows
    assert_same_state(est.state_dict(), before)
    with pytest.raises(ValueError, match=r"^xi: update rejected"):
        est.update(np.full((3, 2), 10.0), np.zeros((3, 1)), np.full((3, 2), 1e308))  # S = sum g xi^T overflows
    assert_same_state(est.state_dict(), before)
    for _ in range(50):
        x, u, xi = rng.normal(size=(20, 2)), rng.normal(size=(20, 1)), rng.normal(size=(20, 2))
        est.update(x, u, xi)
        clean.update(x, u, xi)
    assert_same_state(est.state_dict(), clean.state_dict())
    np.testing.assert_array_equal(est.weights, clean.weights)


def test_state_dependent_overflow_refused_and_later_data_unaffected() -> None:
    est, clean = state_dependent(), state_dependent()
    rng = np.random.default_rng(3)
    before = est.state_dict()
    with pytest.raises(ValueError, match=r"^xi: update rejected"):
        est.update(np.zeros((3, 2)), np.zeros((3, 1)), np.full((3, 2), 1e200))  # eq. (19) overflows
    assert_same_state(est.state_dict(), before)
    x, u, xi = rng.normal(size=(1000, 2)), rng.normal(size=(1000, 1)), rng.normal(size=(1000, 2))
    est.update(x, u, xi)
    clean.update(x, u, xi)
    assert_same_state(est.state_dict(), clean.state_dict())


# ----------------------------------------------------------------------------------------------------
# load_state_dict
# ----------------------------------------------------------------------------------------------------
def _poison(state: dict, key: str, value) -> dict:
    out = dict(state)
    out[key] = value
    return out


@pytest.mark.parametrize(
    ("make", "key", "value", "match"),
    [
        (known, "total", np.array([np.nan, 0.0]), "NaN or inf"),
        (known, "total", np.array([1.0, 2.0], dtype=complex), "real numbers"),
        (known, "prior_cov", np.array([[1.0, 0.0], [0.0, -1.0]]), "positive semi-definite"),
        (known, "noise_cov", np.eye(2, dtype=bool), "real numbers"),
        (unknown, "scatter", np.array([[1.0, 2.0], [2.0, 1.0]]), "positive semi-definite"),
        (unknown, "data_mean", np.array([np.inf, 0.0]), "NaN or inf"),
        (unknown, "data_mean", np.array([1e200, 0.0]), "not be finite"),
        (lambda: unknown("paper"), "psi", np.array([[1.0, 0.0], [0.0, -1.0]]), "positive semi-definite"),
        (lambda: unknown("paper"), "cov", np.array([[1.0, 2.0], [2.0, 1.0]]), "positive semi-definite"),
        (lambda: unknown("paper"), "mean", np.array([np.nan, 0.0]), "NaN or inf"),
        (linear, "gram", -np.eye(4), "positive semi-definite"),
        (linear, "cross", np.full((4, 2), np.inf), "NaN or inf"),
        (state_dependent, "xi", np.full((3, 2), np.nan), "NaN or inf"),
        (state_dependent, "noise_cov", np.array([[1.0, 2.0], [2.0, 1.0]]), "positive semi-definite"),
    ],
)
def test_load_state_dict_refuses_bad_content(make, key: str, value, match: str) -> None:
    est = make()
    if isinstance(est, (KnownCovarianceIBE, UnknownCovarianceIBE)):
        est.update(normal_residuals(3))
    else:
        rng = np.random.default_rng(4)
        est.update(rng.normal(size=(3, 2)), rng.normal(size=(3, 1)), rng.normal(size=(3, 2)))
    state = est.state_dict()
    bad = _poison(state, key, value)
    if key == "data_mean" and match == "not be finite":
        bad["scatter"] = np.diag([1e300, 0.0])  # finite statistics, K_hat = C + d d^T overflows
    with pytest.raises(ValueError, match=rf"^state_dict: .*{match}"):
        est.load_state_dict(bad)
    assert_same_state(est.state_dict(), state)
    assert_same_state(est.state_dict(), make().load_state_dict(est.state_dict()).state_dict())


def test_load_state_dict_refuses_overflowing_case1_posterior() -> None:
    """Finite statistics whose posterior mean overflows (``G^{-1} m_k`` for a correlated prior)."""
    est = KnownCovarianceIBE(np.zeros(2), np.array([[1.0, 0.999], [0.999, 1.0]]), np.eye(2))
    state = est.state_dict()
    bad = dict(state, count=1, total=np.array([1.7e308, -1.7e308]))
    with pytest.raises(ValueError, match=r"^state_dict: update rejected"):
        est.load_state_dict(bad)
    assert_same_state(est.state_dict(), state)
