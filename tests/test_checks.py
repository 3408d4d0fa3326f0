"""Tests of the shared input validation (mixedrl.checks)."""

import numpy as np
import pytest
import torch

from mixedrl import checks


def test_as_vector_rejects_wrong_shape_and_names_argument():
    with pytest.raises(ValueError, match=r"^prior_mean: expected shape \(3,\)"):
        checks.as_vector(np.zeros(4), "prior_mean", 3)
    with pytest.raises(ValueError, match="^prior_mean: expected shape"):
        checks.as_vector(np.zeros((3, 1)), "prior_mean", 3)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_is_rejected(bad):
    v = np.zeros(3)
    v[1] = bad
    with pytest.raises(ValueError, match="^xi: contains NaN or inf"):
        checks.as_batch(v, "xi", 3)
    with pytest.raises(ValueError, match="^t: contains NaN or inf"):
        checks.check_finite(torch.tensor(v), "t")


def test_as_batch_promotes_single_sample_and_copies():
    v = np.arange(3.0)
    out = checks.as_batch(v, "xi", 3)
    assert out.shape == (1, 3)
    out[0, 0] = 99.0
    assert v[0] == 0.0  # the caller's array is never modified


def test_covariance_accepts_tiny_diagonal_and_rejects_indefinite():
    tiny = np.diag([1.8e-10, 1e-20, 1e-20, 1e-20, 1e-20])  # the paper's vehicle prior K_M
    assert np.array_equal(checks.check_covariance(tiny, "prior_cov", 5), tiny)
    with pytest.raises(ValueError, match="^noise_cov: covariance is not positive semi-definite"):
        checks.check_covariance(np.array([[1.0, 2.0], [2.0, 1.0]]), "noise_cov", 2)
    with pytest.raises(ValueError, match="^noise_cov: covariance is not symmetric"):
        checks.check_covariance(np.array([[1.0, 0.5], [0.0, 1.0]]), "noise_cov", 2)
    with pytest.raises(ValueError, match=r"^noise_cov: expected shape \(2, 2\)"):
        checks.check_covariance(np.eye(3), "noise_cov", 2)


def test_unknown_keys_and_positive_int():
    with pytest.raises(ValueError, match=r"config: unknown key\(s\) \['lr_actr'\]"):
        checks.check_unknown_keys({"lr_actor": 1, "lr_actr": 2}, {"lr_actor"}, "config")
    assert checks.check_positive_int(3, "n") == 3
    for bad in (0, -1, 2.0, True):
        with pytest.raises(ValueError, match="^n: expected a positive integer"):
            checks.check_positive_int(bad, "n")


def test_check_int_bounds_and_messages():
    assert checks.check_nonnegative_int(0, "seed") == 0
    assert type(checks.check_int(np.int64(5), "k", minimum=5)) is int
    assert checks.check_int(-3, "offset") == -3
    for bad in (-1, 1.0, False, "1", None):
        with pytest.raises(ValueError, match="^seed: expected a non-negative integer"):
            checks.check_nonnegative_int(bad, "seed")
    with pytest.raises(ValueError, match="^k: expected an integer >= 5, got 4"):
        checks.check_int(4, "k", minimum=5)
    with pytest.raises(ValueError, match="^offset: expected an integer, got 0.5"):
        checks.check_int(0.5, "offset")


def test_check_fraction_and_allow_inf():
    assert checks.check_fraction(1, "tau") == 1.0
    assert checks.check_fraction(0.0, "p") == 0.0
    for bad, kwargs, interval in ((0.0, {"low_open": True}, r"\(0, 1\]"), (1.0, {"high_open": True}, r"\[0, 1\)"),
                                  (1.5, {}, r"\[0, 1\]"), (-0.1, {}, r"\[0, 1\]")):
        with pytest.raises(ValueError, match=rf"^tau: expected a number in {interval}"):
            checks.check_fraction(bad, "tau", **kwargs)
    assert checks.check_number(np.inf, "box", positive=True, allow_inf=True) == np.inf
    for bad in (np.inf, -np.inf, 0.0):
        with pytest.raises(ValueError, match="^box: expected a positive number"):
            checks.check_number(bad, "box", positive=True)
    with pytest.raises(ValueError, match="^box: expected a positive number"):
        checks.check_number(-np.inf, "box", positive=True, allow_inf=True)
