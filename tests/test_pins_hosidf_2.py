"""Pins of the HOSIDF's checks and its drift removal, second set (issue 33's hand-written
bug audit, docs/testing.md): expected HOSIDFs from the closed form of sines (unequal
amplitudes and phases), the one-sine rule at its two limits."""
import numpy as np
import pytest

from fftune.analysis.errors import InputError
from fftune.analysis.hosidf import hosidf

FS, N, P, C = 1000.0, 200, 6, 2          # 2 sine periods per block of 200 samples


def _t():
    return np.arange(P * N) / FS


def test_drifting_output_gives_the_hosidf_of_the_periodic_part():
    # u = A sin(w t); y = B sin(w t + phi) + C3 sin(3 w t + psi) + a slow ramp: H_1 = B/A e^{j phi},
    # H_3 = -C3/A e^{j psi} (the input's phase -90 deg, three times), H_2 = 0
    w = 2 * np.pi * C * FS / N
    A, B, phi, C3, psi = 0.8, 0.55, -0.4, 0.031, 0.9
    t = _t()
    rng = np.random.default_rng(2)
    u = A * np.sin(w * t)
    y = B * np.sin(w * t + phi) + C3 * np.sin(3 * w * t + psi) + 0.9 * t + 1e-4 * rng.standard_normal(t.size)
    res = hosidf(u.reshape(1, P, N), y.reshape(1, P, N), fs=FS, n_harmonics=3, f0=C * FS / N)
    assert any("drift" in note and "removed" in note for note in res.notes), res.notes
    assert res.H[0] == pytest.approx(B / A * np.exp(1j * phi), abs=2e-3)
    assert res.H[2] == pytest.approx(-C3 / A * np.exp(1j * psi), abs=2e-3)
    assert abs(res.H[1]) < 2e-3
    assert res.amplitude == pytest.approx(A, rel=1e-9)


def _one_sine_check(extra_bin, extra_rel):
    t = _t()
    w = 2 * np.pi * C * FS / N
    u = np.sin(w * t) + extra_rel * np.sin(2 * np.pi * extra_bin * FS / N * t + 0.3)
    y = 0.5 * u
    return hosidf(u.reshape(1, P, N), y.reshape(1, P, N), fs=FS, n_harmonics=3, f0=C * FS / N)


def test_one_sine_rule_harmonics_to_half_other_lines_to_a_tenth():
    # a harmonic of the sine (bin 2 C) up to half of it: a distorted sine, accepted
    assert _one_sine_check(2 * C, 0.3).H[0] == pytest.approx(0.5, rel=1e-9)
    with pytest.raises(InputError, match="not one sine"):
        _one_sine_check(2 * C, 0.6)
    # another line (bin 3: no harmonic of bin 2) above a tenth: refused; below: accepted
    with pytest.raises(InputError, match="not one sine"):
        _one_sine_check(3, 0.3)
    assert _one_sine_check(3, 0.05).H[0] == pytest.approx(0.5, rel=1e-9)


def test_a_line_beside_the_sine_is_no_leakage():
    # the sine's own line found from the data (f0 not given): an off-grid sine raises both
    # neighbours, a small other input line at the next bin only one; accepted
    t = _t()
    u = np.sin(2 * np.pi * 5 * FS / N * t) + 0.05 * np.sin(2 * np.pi * 6 * FS / N * t)
    res = hosidf(u.reshape(1, P, N), (0.5 * u).reshape(1, P, N), fs=FS, n_harmonics=3)
    assert res.bin == 5 and res.H[0] == pytest.approx(0.5, rel=1e-9)
    off = np.sin(2 * np.pi * 5.3 * FS / N * t)
    with pytest.raises(InputError, match="off the DFT grid"):
        hosidf(off.reshape(1, P, N), off.reshape(1, P, N), fs=FS, n_harmonics=3)


def test_a_sine_that_falls_26_db_before_the_record_ends_is_named_a_burst():
    t = np.arange(P * N) / FS
    u = np.sin(2 * np.pi * 5 * FS / N * t)
    u[int(0.7 * u.size):] *= 0.05                     # -26 dB: under the envelope's 20 dB
    with pytest.raises(InputError, match="excitation stops at sample"):
        hosidf(u.reshape(1, 1, -1), u.reshape(1, 1, -1), fs=FS, n_harmonics=3)
