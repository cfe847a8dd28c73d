"""Pins of the BLA's and the LPM's numbers, second set (issue 33's hand-written bug audit,
docs/testing.md): expected values computed here from the definitions (least squares by
hand, the F(2, 2q) tail), unequal and asymmetric inputs."""
import math

import numpy as np
import pytest

from fftune.analysis.bla import _drift_test


def _t_by_hand(row):
    p = row.size
    i = np.arange(p, dtype=float)
    X = np.column_stack([np.ones(p), i])
    coef, *_ = np.linalg.lstsq(X, row, rcond=None)
    rss = float(np.sum((row - X @ coef) ** 2))
    se = math.sqrt(rss / (p - 2) / np.sum((i - i.mean()) ** 2))
    return coef[1], coef[1] / se


def test_drift_test_slope_and_t_with_p_minus_2_degrees_of_freedom():
    dc = np.array([[0.10, 0.13, 0.11, 0.16, 0.15, 0.19],           # a trend in noise
                   [2.00, 1.97, 2.04, 1.99, 2.02, 1.98]])          # none
    slope, t = _t_by_hand(dc[0])
    assert 3.0 < t < 8.0
    m, s, tt = _drift_test(dc, t_limit=0.9 * t)
    assert m == 0 and s == pytest.approx(slope, rel=1e-12) and tt == pytest.approx(t, rel=1e-12)
    # just above the limit: no drift (with P instead of P - 2 the t would be sqrt(6 / 4) larger)
    assert _drift_test(dc, t_limit=1.05 * t) is None
    # the most significant realization is named, its sign kept
    dc2 = np.vstack([dc, -3 * dc[0][::-1] + 0.01 * np.array([1, -1, 2, 0, -2, 1])])
    slope2, t2 = _t_by_hand(dc2[2])
    m, s, tt = _drift_test(dc2, t_limit=1.0)
    assert m == (2 if abs(t2) > abs(t) else 0)
    assert _drift_test(dc[:, :3]) is None                             # P < 4: no test
