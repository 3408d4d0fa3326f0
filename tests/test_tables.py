"""Tests of mixedrl.tables: mean and sample std, the bootstrap interval, CSV of dict rows."""

from __future__ import annotations

import csv
import io

import numpy as np
import pytest

from mixedrl.tables import bootstrap_interval, csv_text, mean_std, paired_interval


def test_mean_std_is_the_mean_and_sample_std() -> None:
    mean, std = mean_std([1.0, 2.0, 6.0])
    assert mean == 3.0 and std == pytest.approx(np.sqrt(((1 - 3) ** 2 + (2 - 3) ** 2 + (6 - 3) ** 2) / 2))
    assert mean_std([4.0]) == (4.0, 0.0) and mean_std([4.0], one=None) == (4.0, None)
    assert mean_std([]) == (None, None)


def test_bootstrap_interval_covers_the_mean_of_normal_samples() -> None:
    # coverage of the true mean over many seeded samples: a percentile bootstrap with n = 20 covers a 95%
    # interval about 93% of the time; 200 trials give a binomial standard error of ~1.8%
    rng = np.random.default_rng(7)
    trials = 200
    hits = 0
    for t in range(trials):
        low, high = bootstrap_interval(rng.normal(1.0, 2.0, size=20), n_resamples=999, seed=t)
        assert low < high
        hits += low <= 1.0 <= high
    assert 0.86 <= hits / trials <= 0.99


def test_bootstrap_interval_edge_cases() -> None:
    assert bootstrap_interval([3.0]) == (None, None) and bootstrap_interval([]) == (None, None)
    assert bootstrap_interval([2.0, 2.0, 2.0]) == (2.0, 2.0)
    values = [1.0, 4.0, 2.0, 8.0]
    assert bootstrap_interval(values) == bootstrap_interval(values)  # seeded
    low, high = bootstrap_interval(values)
    assert 1.0 <= low < np.mean(values) < high <= 8.0
    with pytest.raises(ValueError, match="^confidence"):
        bootstrap_interval(values, confidence=1.0)


def test_paired_interval_resamples_seeds_with_both_values() -> None:
    # a shared per-seed effect (the seed's difficulty) far larger than the difference: unpaired intervals
    # of the two means overlap, the paired interval of the difference excludes 0
    rng = np.random.default_rng(3)
    seed_effect = rng.normal(0.0, 1.0, size=20)
    a = 5.0 + seed_effect + rng.normal(0.0, 0.05, size=20)
    b = a + 0.2 + rng.normal(0.0, 0.05, size=20)
    diff, low, high = paired_interval(a, b)
    assert diff == pytest.approx(np.mean(a - b)) and low < diff < high < 0.0
    la, ha = bootstrap_interval(a)
    lb, hb = bootstrap_interval(b)
    assert lb < ha  # the unpaired intervals overlap
    ratio, rl, rh = paired_interval(b, a, statistic="ratio")
    assert ratio == pytest.approx(np.mean(b) / np.mean(a)) and 1.0 < rl < ratio < rh
    assert paired_interval(a, b) == paired_interval(a, b)  # seeded
    # breaking the pairing (b's seeds shuffled) loses it
    _, low_u, high_u = paired_interval(a, rng.permutation(b))
    assert low_u < 0.0 < high_u
    assert paired_interval([1.0], [2.0]) == (-1.0, None, None)
    assert paired_interval([1.0, 2.0], [0.0, 1.0]) == (1.0, 1.0, 1.0)
    with pytest.raises(ValueError, match="^b: expected as many"):
        paired_interval([1.0, 2.0], [1.0])
    with pytest.raises(ValueError, match="non-finite"):
        paired_interval([1.0, np.nan], [1.0, 2.0])
    with pytest.raises(ValueError, match="^statistic"):
        paired_interval([1.0, 2.0], [1.0, 2.0], statistic="median")


def test_csv_text_unions_the_keys_and_round_trips_floats() -> None:
    text = csv_text([{"a": 0.1 + 0.2, "b": None}, {"c": "x", "a": 1}], columns=("z", "a"))
    rows = list(csv.reader(io.StringIO(text)))
    assert rows == [["z", "a", "b", "c"], ["", repr(0.1 + 0.2), "", ""], ["", "1", "", "x"]]
    assert float(rows[1][1]) == 0.1 + 0.2 and "\r" not in text
