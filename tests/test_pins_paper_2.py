"""Pins of `make paper`'s numbers, second set (issue 33's hand-written bug audit,
docs/testing.md): an unsorted sweep, a NaN in the rms errors, a phase that wraps, the
simulation's own K_fc*, the accepted ranges' texts. Expected values written out here."""
import math

import numpy as np
import pytest

from fftune.analysis.reproduction import _range_text, min_rms_kfc, phase_turn_deg, reproduction_numbers


def _H(phases3, n):
    H = np.zeros((n, 7), dtype=complex)
    H[:, 0] = 1.0
    H[:, 2] = 0.05 * np.exp(1j * np.asarray(phases3))
    H[:, 1] = 0.02
    H[:, 4] = 0.01 * np.exp(1j * np.asarray(phases3) * 1.3)
    H[:, 6] = 0.004
    return H


def test_phase_turn_of_an_unsorted_sweep_across_the_wrap():
    # sorted by K_fc the H_3 phase walks 170, 175, 178 deg, then -176, -172 (i.e. 184, 188):
    # across K_fc* = 0.115 (between 0.11 and 0.12) it turns 6 deg, not 354
    k = np.array([0.12, 0.09, 0.13, 0.10, 0.11])
    deg = np.array([-176.0, 170.0, -172.0, 175.0, 178.0])
    turn = phase_turn_deg(k, _H(np.radians(deg), 5), 0.115, harmonic=3)
    assert turn == pytest.approx(6.0, abs=1e-9)


def test_min_rms_with_a_failed_point_and_an_unsorted_sweep():
    k = np.array([0.14, 0.10, 0.16, 0.12, 0.18])
    e = np.array([0.0210, 0.0300, np.nan, 0.0240, 0.0280])
    # sorted: 0.10 0.0300, 0.12 0.0240, 0.14 0.0210, 0.16 NaN, 0.18 0.0280: the minimum at
    # 0.14 with a NaN neighbour: no parabola through NaN, the grid point
    k_min, at_end = min_rms_kfc(k, e)
    assert at_end is False and k_min == pytest.approx(0.14)
    e2 = np.array([0.0210, 0.0300, 0.0226, 0.0240, 0.0280])
    # the parabola through (0.12, 0.0240), (0.14, 0.0210), (0.16, 0.0226)
    x, y = np.array([0.12, 0.14, 0.16]), np.array([0.0240, 0.0210, 0.0226])
    a, b, _ = np.polyfit(x, y, 2)
    assert min_rms_kfc(k, e2) == (pytest.approx(-b / (2 * a), rel=1e-9), False)


def test_simulation_turns_are_read_at_the_simulations_own_k_fc_star():
    k = np.array([0.0, 0.05, 0.10, 0.15, 0.20])
    # the set-up's sweep: H_3 turns between 0.10 and 0.15 (K_fc* 0.12)
    setup = _H(np.radians([10.0, 12.0, 14.0, 190.0, 192.0]), 5)
    # the simulation's: between 0.05 and 0.10 (its K_fc* 0.07): 150 deg there, 2 deg at 0.12
    sim = _H(np.radians([20.0, 22.0, 172.0, 174.0, 176.0]), 5)
    out = reproduction_numbers(k_star=0.12, k_true=0.118, k_sweep=k, H_sweep=setup,
                               rms_sweep=np.array([0.05, 0.04, 0.03, 0.02, 0.03]),
                               H_at_0=setup[0], H_at_star=setup[3],
                               sim_k_star=0.07, sim_k_sweep=k, sim_H_sweep=sim)
    assert out["h3_phase_turn_deg"] == pytest.approx(150.0)
    assert out["h3_phase_turn_deg_setup"] == pytest.approx(176.0)


def test_range_texts():
    assert _range_text([None, 0.015], "pct") == "<= 1.5 %"
    assert _range_text([10.0, None], "x") == ">= 10x"
    assert _range_text([-15.0, -5.0], "db") == "-15 .. -5 dB"
    assert _range_text([0.15, 0.35], "pct_signed") == "+15 % .. +35 %"
