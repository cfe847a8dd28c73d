"""Pins of the checks before averaging, second set (issue 33's hand-written bug audit,
docs/testing.md): a level step at the two sides of its floor, the count of blocks in
the non-finite message, the smallest period."""
import math

import numpy as np
import pytest

from fftune.analysis.checks import check_arguments, check_blocks, locate_nonfinite
from fftune.analysis.errors import InputError


def _multisine(n=256, seed=1):
    rng = np.random.default_rng(seed)
    X = np.zeros(n // 2 + 1, complex)
    X[3:60:2] = np.exp(2j * np.pi * rng.random(29))
    return np.fft.irfft(X, n)


def test_a_level_step_below_its_floor_is_kept_above_it_refused():
    one = _multisine()
    gains = np.ones(8)
    # a step of 0.1 dB between blocks 3 and 4 that stays, no scatter otherwise: under the
    # 0.2 dB floor (STEP_MIN_DB), not refused
    gains[4:] = 10 ** (0.1 / 20)
    x = (gains[:, None] * one[None, :])[None]
    assert not check_blocks(x).changed
    gains[4:] = 10 ** (0.5 / 20)
    x = (gains[:, None] * one[None, :])[None]
    with pytest.raises(InputError, match="level changes"):
        check_blocks(x)


def test_non_finite_message_counts_blocks_and_samples():
    x = np.ones((2, 3, 8))
    x[1, 2, [1, 4, 6]] = np.nan
    text = locate_nonfinite("input u", x)
    assert "3 sample(s) in 1 period(s)" in text
    assert "realization 1, period 2" in text and "sample 17" in text


def test_a_period_of_fewer_than_four_samples_is_refused():
    assert check_arguments(fs=10.0, n_period=4) == (10.0, None)
    with pytest.raises(InputError, match="too small"):
        check_arguments(fs=10.0, n_period=3)


def test_a_period_is_named_only_when_the_record_repeats_closely():
    # a record periodic in 1333 samples, read with N = 1024: refused; with little noise the
    # message names the period 1333, with noise of 40 % of its power (autocorrelation 0.7 at
    # the lag: under 0.9) it says no period was found
    rng = np.random.default_rng(6)
    m, n, blocks = 1333, 1024, 8
    k = np.arange(1, 400)
    t = np.arange(n * blocks)
    x = np.sum(np.cos(2 * np.pi * np.outer(t, k) / m + 2 * np.pi * rng.random(k.size)), axis=1)
    x /= np.std(x)
    with pytest.raises(InputError, match="repeats every 1333 samples"):
        check_blocks((x + 0.01 * rng.standard_normal(x.size)).reshape(1, blocks, n))
    with pytest.raises(InputError, match="no period found"):
        check_blocks((x + math.sqrt(0.43) * rng.standard_normal(x.size)).reshape(1, blocks, n))
