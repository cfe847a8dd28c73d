"""Multisine: the on-drive algorithm against the shared vectors, and the designer's line sets."""
import json
from pathlib import Path

import numpy as np
import pytest

from fftune.analysis.errors import InputError
from fftune.analysis.multisine import (crest_factor, design_multisine, drive_lines, drive_multisine,
                                drive_phases, fmix32, multisine_realizations, stream_init,
                                xorshift32)

VECTORS = json.loads((Path(__file__).resolve().parent / "vectors" /
                      "multisine_vectors.json").read_text())


@pytest.mark.parametrize("z,expected", VECTORS["fmix_samples"])
def test_fmix32_matches_vectors(z, expected):
    assert fmix32(z) == expected


@pytest.mark.parametrize("case", VECTORS["prng"], ids=lambda c: f"seed{c['seed']}-s{c['stream']}")
def test_prng_streams_match_vectors(case):
    x = stream_init(case["seed"], case["stream"])
    assert x == case["init"]
    out = []
    for _ in case["outputs"]:
        x = xorshift32(x)
        out.append(x)
    assert out == case["outputs"]


@pytest.mark.parametrize("case", VECTORS["designs"], ids=lambda c: f"N{c['N']}-m{c['m']}")
def test_drive_multisine_matches_vectors(case):
    args = (case["N"], case["k_min"], case["k_max"], case["G"], case["seed"])
    lines = drive_lines(*args)
    assert lines.excited.tolist() == case["excited"]
    assert lines.removed.tolist() == case["removed"]
    phases = drive_phases(len(case["excited"]), case["seed"], case["m"])
    np.testing.assert_array_equal(phases, case["phases"])
    period = drive_multisine(*args, case["m"], case["rms"])
    assert period.dtype == np.float64 and period.shape == (case["N"],)
    np.testing.assert_allclose(period, case["period"], rtol=0, atol=1e-9)
    # the designer gives the same signal for the same parameters
    d = design_multisine(1000.0, case["N"], k_min=case["k_min"], k_max=case["k_max"],
                         group=case["G"], seed=case["seed"], realization=case["m"],
                         rms=case["rms"], kind="random_odd")
    np.testing.assert_allclose(d.period, case["period"], rtol=0, atol=1e-9)


def test_random_odd_line_set_properties():
    n, g = 4096, 5
    designs = multisine_realizations(4, 1000.0, n, f_min=1.0, f_max=300.0, group=g,
                                     seed=99, rms=0.7)
    d0 = designs[0]
    k_min, k_max = int(np.ceil(1.0 / (1000 / n))), int(300.0 / (1000 / n))
    assert np.all(d0.excited % 2 == 1)
    assert np.all((d0.excited >= k_min) & (d0.excited <= k_max))
    candidates = np.arange(k_min | 1, k_max + 1, 2)
    # exactly one removed per full group of G candidates
    for grp in range(candidates.size // g):
        chunk = candidates[grp * g:(grp + 1) * g]
        assert np.isin(chunk, d0.removed).sum() == 1
    assert set(d0.detection_odd) >= set(d0.removed)
    assert np.all(d0.even % 2 == 0)
    for d in designs:
        np.testing.assert_array_equal(d.excited, d0.excited)   # same lines every realization
        assert d.rms == pytest.approx(0.7, rel=1e-12)            # rms as asked
        spectrum = np.abs(np.fft.rfft(d.period))
        assert np.all(spectrum[d.excited] > 1e-3 * spectrum.max())
        off = np.setdiff1d(np.arange(1, n // 2), d.excited)
        assert np.max(spectrum[off]) < 1e-9 * spectrum.max()    # nothing elsewhere
    assert not np.allclose(designs[0].phases, designs[1].phases)  # new phases
    again = multisine_realizations(4, 1000.0, n, f_min=1.0, f_max=300.0, group=g, seed=99,
                                   rms=0.7)
    for a, b in zip(designs, again):
        np.testing.assert_array_equal(a.period, b.period)      # reproducible by seed
    other = design_multisine(1000.0, n, f_min=1.0, f_max=300.0, group=g, seed=100)
    assert not np.array_equal(other.excited, d0.excited)


def test_odd_and_full_kinds_and_user_spectrum():
    odd = design_multisine(100.0, 256, k_min=2, k_max=60, kind="odd", rms=2.0)
    np.testing.assert_array_equal(odd.excited, np.arange(3, 60, 2))
    assert odd.detection_odd.size == 0
    full = design_multisine(100.0, 256, k_min=2, k_max=60, kind="full", rms=2.0)
    np.testing.assert_array_equal(full.excited, np.arange(2, 61))
    assert full.even.size == 0 and full.rms == pytest.approx(2.0)
    shaped = design_multisine(100.0, 256, k_min=1, k_max=100, kind="odd",
                              amplitude_spectrum=lambda f: 1.0 / f, rms=1.0)
    amp = 2 * np.abs(np.fft.rfft(shaped.period))[shaped.excited] / 256
    np.testing.assert_allclose(amp * shaped.excited, amp[0] * shaped.excited[0], rtol=1e-9)
    assert shaped.rms == pytest.approx(1.0)


def test_band_in_hz_is_clipped_to_usable_bins():
    d = design_multisine(100.0, 64, f_min=0.0, f_max=50.0, kind="full")
    np.testing.assert_array_equal(d.excited, np.arange(1, 32))
    np.testing.assert_allclose(d.freq_excited, np.arange(1, 32) * 100.0 / 64)


def test_crest_factor_reduction_keeps_lines_and_amplitudes():
    plain = design_multisine(1000.0, 2048, k_min=1, k_max=400, seed=3, kind="full")
    reduced = design_multisine(1000.0, 2048, k_min=1, k_max=400, seed=3, kind="full",
                               crest_factor_iterations=40)
    assert crest_factor(reduced.period) < crest_factor(plain.period) - 0.3
    np.testing.assert_allclose(np.abs(np.fft.rfft(reduced.period)),
                               np.abs(np.fft.rfft(plain.period)), atol=1e-9)


@pytest.mark.parametrize("kwargs", [dict(k_min=0, k_max=10), dict(k_min=5, k_max=64),
                                    dict(k_min=1, k_max=10, group=1),
                                    dict(k_min=1, k_max=10, kind="pink"),
                                    dict(k_min=1, k_max=10, rms=float("nan"))])
def test_bad_design_parameters_raise_input_error(kwargs):
    with pytest.raises(InputError):
        design_multisine(100.0, 128, **kwargs)
