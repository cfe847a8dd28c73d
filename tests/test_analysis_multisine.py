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


# --- what mutation testing found untested (issue 16, docs/testing.md) ---------------------
import dataclasses  # noqa: E402

from fftune.analysis.multisine import (random_odd_multisine, synthesize_period,  # noqa: E402
                                       _reduce_crest_factor)


def test_band_and_period_limits():
    """N >= 4 and an integer; 1 <= k_min <= k_max < N/2 (one line is a band)."""
    np.testing.assert_array_equal(drive_lines(4, 1, 1, 0, 0).excited, [1])
    np.testing.assert_array_equal(drive_lines(64, 3, 3, 0, 0).excited, [3])
    np.testing.assert_array_equal(drive_lines(64, 31, 31, 0, 0).excited, [31])
    for n, lo, hi in ((3, 1, 1), (64.5, 1, 10), (64, 1, 32), (64, 4, 3), (64, 0, 3)):
        with pytest.raises(InputError, match="n_period must be an integer|band in bins"):
            drive_lines(n, lo, hi, 0, 0)


def test_group_size_limits():
    assert drive_lines(256, 1, 100, 16, 1).removed.size == 50 // 16
    assert drive_lines(256, 1, 100, 2, 1).removed.size == 25
    for g in (1, 17, -2):
        with pytest.raises(InputError, match="group must be 0 or 2..16"):
            drive_lines(256, 1, 100, g, 1)


def test_line_sets_cover_the_band_to_its_top_bin():
    odd = design_multisine(100.0, 256, k_min=2, k_max=60, kind="odd")
    np.testing.assert_array_equal(odd.even, np.arange(2, 61, 2))
    d = design_multisine(100.0, 256, k_min=3, k_max=61, kind="random_odd", group=4, seed=7)
    odd_bins = np.arange(3, 62, 2)
    np.testing.assert_array_equal(np.sort(np.concatenate([d.excited, d.detection_odd])), odd_bins)
    np.testing.assert_array_equal(d.even, np.arange(4, 61, 2))


def test_drive_multisine_input_checks_and_a_single_line():
    one = drive_multisine(64, 3, 3, 0, 1, 0, 0.5)               # one excited line
    assert np.sqrt(np.mean(one ** 2)) == pytest.approx(0.5)
    assert np.all(drive_multisine(64, 1, 20, 0, 1, 0, 0.0) == 0.0)   # rms 0: silence
    for rms in (-0.5, float("nan"), float("inf")):
        with pytest.raises(InputError, match="rms must be finite"):
            drive_multisine(64, 1, 20, 0, 1, 0, rms)
    with pytest.raises(InputError, match="no excited line"):
        drive_multisine(64, 2, 2, 0, 1, 0, 1.0)                  # no odd bin in [2, 2]


def test_odd_period_length_reaches_its_top_bin():
    d = design_multisine(100.0, 65, kind="full")                 # default band 1 .. (N-1)/2
    np.testing.assert_array_equal(d.excited, np.arange(1, 33))
    spectrum = np.abs(np.fft.rfft(d.period))
    assert spectrum[32] > 1e-3 * spectrum.max()
    top = design_multisine(100.0, 65, f_min=0.0, f_max=50.0, kind="full")
    np.testing.assert_array_equal(top.excited, np.arange(1, 33))
    np.testing.assert_array_equal(design_multisine(100.0, 64, kind="full").excited, np.arange(1, 32))
    x = synthesize_period(9, [4], [1.0], [0.3])
    np.testing.assert_allclose(x, np.sin(2 * np.pi * 4 * np.arange(9) / 9 + 0.3), atol=1e-12)


def test_design_defaults_and_keyword_only_parameters():
    d = design_multisine(fs=1000.0, n_period=256)
    ref = design_multisine(1000.0, 256, k_min=1, k_max=127, kind="random_odd", group=5, rms=1.0,
                           seed=0, realization=0, crest_factor_iterations=0)
    np.testing.assert_array_equal(d.period, ref.period)
    np.testing.assert_array_equal(d.removed, drive_lines(256, 1, 127, 5, 0).removed)
    assert d.rms == pytest.approx(1.0) and (d.seed, d.realization, d.kind) == (0, 0, "random_odd")
    np.testing.assert_array_equal(d.phases, drive_phases(d.excited.size, 0, 0))
    with pytest.raises(TypeError):
        design_multisine(1000.0, 256, 1.0)                      # the band only by keyword
    with pytest.raises(dataclasses.FrozenInstanceError):
        d.rms_target = 2.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        d.seed = 3


def test_design_input_checks():
    assert design_multisine(0.5, 64, kind="full").fs == 0.5            # below 1 Hz is a rate
    assert np.all(design_multisine(100.0, 64, rms=0.0).period == 0.0)
    for fs in (0.0, -0.5, float("nan")):
        with pytest.raises(InputError, match="fs must be"):
            design_multisine(fs, 64)
    for band in (dict(f_min=1.0, k_max=10), dict(f_max=10.0, k_min=2)):
        with pytest.raises(InputError, match="either in Hz"):
            design_multisine(100.0, 64, **band)
    for rms in (-0.5, float("nan")):
        with pytest.raises(InputError, match="rms must be finite"):
            design_multisine(100.0, 64, rms=rms)
    with pytest.raises(InputError, match="no excited line"):
        design_multisine(100.0, 64, k_min=2, k_max=2, kind="odd")
    one = design_multisine(100.0, 64, k_min=3, k_max=3, kind="odd", rms=0.5)
    np.testing.assert_array_equal(one.excited, [3])


def test_band_in_hz_on_a_bin_is_that_bin():
    """A band edge on a bin (within rounding) includes that bin."""
    f0 = 100.0 / 64
    d = design_multisine(100.0, 64, f_min=3 * f0 * (1 + 1e-12), f_max=9 * f0 * (1 - 1e-12), kind="full")
    np.testing.assert_array_equal(d.excited, np.arange(3, 10))
    d = design_multisine(100.0, 64, f_min=3 * f0, f_max=9 * f0, kind="full")
    np.testing.assert_array_equal(d.excited, np.arange(3, 10))
    d = design_multisine(100.0, 64, f_min=3.2 * f0, f_max=8.8 * f0, kind="full")
    np.testing.assert_array_equal(d.excited, np.arange(4, 9))


def test_amplitude_spectrum_in_hz_or_per_line_and_its_checks():
    f0 = 100.0 / 256
    step = design_multisine(100.0, 256, k_min=1, k_max=60, kind="odd",
                            amplitude_spectrum=lambda f: np.where(f < 10.0, 2.0, 1.0))
    expected = np.where(step.excited * f0 < 10.0, 2.0, 1.0)
    np.testing.assert_allclose(step.amplitudes / step.amplitudes[-1], expected, rtol=1e-12)
    n = step.excited.size
    rel = np.linspace(1.0, 3.0, n)
    rel[4] = 0.0                                                  # a line may be off
    arr = design_multisine(100.0, 256, k_min=1, k_max=60, kind="odd", amplitude_spectrum=rel, rms=0.7)
    np.testing.assert_allclose(arr.amplitudes / arr.amplitudes[-1], rel / 3.0, rtol=1e-12)
    assert arr.rms == pytest.approx(0.7)
    for bad in (np.ones(n - 1), np.r_[np.ones(n - 1), -0.5], np.r_[np.ones(n - 1), np.nan],
                np.zeros(n)):
        with pytest.raises(InputError, match="amplitude_spectrum"):
            design_multisine(100.0, 256, k_min=1, k_max=60, kind="odd", amplitude_spectrum=bad)


def test_crest_factor_of_known_signals():
    t = np.arange(1000) / 1000
    assert crest_factor(np.sin(2 * np.pi * 5 * t)) == pytest.approx(np.sqrt(2), rel=1e-9)
    assert crest_factor(3.0 * np.sign(np.sin(2 * np.pi * 5 * t + 0.1))) == pytest.approx(1.0)


def test_crest_factor_reduction_clip_schedule_and_phase_convention(monkeypatch):
    """Each iteration clips at max(1.2 rms, peak (0.9 - 0.4 it / iterations)) and takes the
    clipped signal's phases in the sin convention, wrapped to [-pi, pi): one iteration
    keeps the signal close to the original (not shifted or negated)."""
    plain = design_multisine(1000.0, 2048, k_min=1, k_max=400, seed=3, kind="full", rms=0.5)
    levels, clip = [], np.clip

    def recording_clip(x, lo, hi, *a, **k):
        levels.append((np.max(np.abs(x)), np.sqrt(np.mean(x ** 2)), hi))
        return clip(x, lo, hi, *a, **k)

    monkeypatch.setattr(np, "clip", recording_clip)
    iterations = 40
    phases = _reduce_crest_factor(2048, plain.excited, plain.amplitudes, plain.phases, iterations)
    monkeypatch.setattr(np, "clip", clip)
    assert len(levels) == iterations
    for it, (peak, rms, level) in enumerate(levels):
        assert level == pytest.approx(max(1.2 * rms, peak * (0.9 - 0.4 * it / iterations)), rel=1e-12)
    # both bounds act: the peak fraction first, 1.2 rms once the crest factor is low
    assert levels[0][2] > 1.2 * levels[0][1] and levels[-1][2] == pytest.approx(1.2 * levels[-1][1])
    assert np.all((phases >= -np.pi) & (phases < np.pi))
    one = design_multisine(1000.0, 2048, k_min=1, k_max=400, seed=3, kind="full", rms=0.5,
                           crest_factor_iterations=1)
    assert np.corrcoef(one.period, plain.period)[0, 1] > 0.9
    assert crest_factor(one.period) < crest_factor(plain.period)
    np.testing.assert_allclose(one.period, synthesize_period(2048, one.excited, one.amplitudes,
                                                             one.phases), atol=1e-12)


def test_random_odd_multisine_defaults_and_realizations():
    u, d = random_odd_multisine(1000.0, 256, k_min=3, k_max=60)
    assert u.shape == (1, 256)
    np.testing.assert_array_equal(u[0], design_multisine(1000.0, 256, k_min=3, k_max=60).period)
    u, d = random_odd_multisine(fs=1000.0, n_period=256, n_realizations=3, k_min=3, k_max=60)
    assert u.shape == (3, 256) and d.realization == 0
    np.testing.assert_array_equal(u[0], d.period)
    for m in range(3):
        np.testing.assert_allclose(u[m], drive_multisine(256, 3, 60, 5, 0, m, 1.0), rtol=0, atol=1e-12)
    with pytest.raises(TypeError):
        random_odd_multisine(1000.0, 256, 1, 1.0)                # the band only by keyword
    with pytest.raises(InputError, match="n_realizations"):
        random_odd_multisine(1000.0, 256, 0)
