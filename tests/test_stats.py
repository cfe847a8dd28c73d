"""On-drive line statistics (firmware_sim/core/stat.h, object 0x2040/0x2041) against the
same numbers from the raw samples of the same run in float64 (numpy's FFT), and the
analysis on statistics (fftune.analysis.stats) against the analysis on samples.

Accuracy as stated in docs/analysis.md: line means and H_k within 1e-5 of the largest
line (|X_1|, |H_1|); the period-to-period spread (standard deviation) within 1e-5 of |X_1|
(a variance far below the float32 resolution of the line, (1e-6 |X_1|)^2, cannot be
relative-accurate from float32 sums: those cases are checked on this scale); the mean
square within 1e-5 relative.
"""
import os
import sys

import numpy as np
import pytest

from fftune.analysis.errors import InputError
from fftune.analysis.hosidf import hosidf
from fftune.analysis.stats import (HarmonicStats, harmonic_stats, hosidf_from_stats, parse_stats,
                                   relative_difference)

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), os.pardir))
sys.path.insert(0, os.path.join(REPO, "firmware_sim", "tests"))
from fwsim import FwSim  # noqa: E402

TWOMASS = os.path.join(REPO, "configs", "plant_twomass.yaml")
STAGE = os.path.join(REPO, "configs", "plant_stage.yaml")
FS = 2560.0
SIG = {"reference": 0x01, "plant_input": 0x02, "motor_angle": 0x04, "load_angle": 0x08, "error": 0x10}


def _run(plant, *, n, cycles, amplitude, periods, settle, inject=0, kfc=0.0, harmonics=7,
         target=0.0, hsig=("reference", "motor_angle"), power=("error",)):
    """One sine run recording reference, plant input, motor angle and error AND accumulating
    statistics: (signals dict float64, HarmonicStats from the drive's bytes)."""
    with FwSim(plant) as sim:
        sim.enable()
        if target:
            sim.lib.drv_set_target(sim.drv, target)
        sim.configure(kfc=kfc, exc_kind=1, exc_inject=inject, exc_amplitude=amplitude, exc_period=n,
                      exc_sine_cycles=cycles, exc_settle_periods=settle, exc_record_periods=periods,
                      rec_signals=0x17, stat_harmonics=harmonics,
                      stat_signals=sum(SIG[s] for s in hsig), stat_power=sum(SIG[s] for s in power))
        sim.start()
        sim.run_until_idle()
        data, names = sim.record()
        assert sim.get("STAT_PERIODS") == periods
        raw = sim.stats_bytes()
        assert len(raw) == sim.get("STAT_BYTES")
    return {nm: data[:, i].astype(np.float64) for i, nm in enumerate(names)}, parse_stats(raw)


CASES = {
    # the demo's tune experiment (0.625 Hz, one cycle per period of 4096), with and without K_fc
    "tune_kfc0": dict(plant=TWOMASS, n=4096, cycles=1, amplitude=0.5, periods=2, settle=2),
    "tune_kfc0.1_p4": dict(plant=TWOMASS, n=4096, cycles=1, amplitude=0.5, periods=4, settle=2, kfc=0.1),
    # 20 Hz around a set-point of 3 rad (the offset must not cost float32 accuracy), K = 8
    "offset_20hz_k8": dict(plant=TWOMASS, n=2048, cycles=16, amplitude=0.2, periods=4, settle=2,
                           kfc=0.1, target=3.0, harmonics=8),
    # set-up I: sine voltage at the plant input of the stage, 3 signals, K = 8
    "stage_input_3sig": dict(plant=STAGE, n=2048, cycles=16, amplitude=0.6, periods=4, settle=4,
                             inject=1, harmonics=8, hsig=("plant_input", "motor_angle", "error")),
}


@pytest.mark.parametrize("case", list(CASES), ids=list(CASES))
def test_drive_statistics_equal_float64_of_the_samples(case):
    kw = dict(CASES[case])
    sig, st = _run(**kw)
    hsig = kw.get("hsig", ("reference", "motor_angle"))
    k = kw.get("harmonics", 7)
    ref = harmonic_stats({s: sig[s] for s in hsig}, n=kw["n"], cycles=kw["cycles"], harmonics=k,
                         power=())
    ref_p = harmonic_stats({"error": sig["error"]}, n=kw["n"], cycles=kw["cycles"], harmonics=k,
                           power=["error"])
    assert st.periods == kw["periods"] and st.harmonics == k
    assert sorted(st.mean) == sorted(hsig) and list(st.power_msq) == ["error"]
    for s in hsig:
        scale = abs(ref.mean[s][0])
        assert relative_difference(st.mean[s], ref.mean[s], scale) <= 1e-5, s
        np.testing.assert_allclose(np.sqrt(st.var[s]), np.sqrt(ref.var[s]), rtol=0, atol=1e-5 * scale)
    assert abs(st.power_msq["error"] / ref_p.power_msq["error"] - 1) <= 1e-5
    assert abs(st.power_mean["error"] - ref_p.power_mean["error"]) <= 1e-5 * np.sqrt(ref_p.power_msq["error"])
    # the HOSIDFs from the statistics = hosidf() on the samples
    u = "plant_input" if kw.get("inject") else "reference"
    n, p = kw["n"], kw["periods"]
    h_raw = hosidf(sig[u].reshape(1, p, n), sig["motor_angle"].reshape(1, p, n), fs=FS,
                   n_harmonics=k, f0=kw["cycles"] * FS / n)
    h_st = hosidf_from_stats(st, st, u_name=u, y_name="motor_angle", fs=FS, n=n, cycles=kw["cycles"])
    assert relative_difference(h_st.H, h_raw.H, abs(h_raw.H[0])) <= 1e-5
    assert abs(h_st.amplitude / h_raw.amplitude - 1) <= 1e-5
    assert h_st.f0 == h_raw.f0 and h_st.H.shape == h_raw.H.shape


@pytest.fixture(scope="module")
def noisy_plant(tmp_path_factory):
    """The two-mass plant with 2e-3 rad measurement noise and an ideal encoder."""
    from fftune.host.sim import derived_plant
    path = tmp_path_factory.mktemp("noisy") / "plant.yaml"
    return derived_plant(TWOMASS, {"sensor": {"noise_std": 2e-3, "counts_per_rev": 0}}, str(path))


def test_variances_relative_when_the_spread_is_resolvable(noisy_plant):
    # measurement noise gives every line a period-to-period spread well above the float32
    # resolution of the line: then the variances agree relatively too
    kw = dict(plant=noisy_plant, n=4096, cycles=1, amplitude=0.5, periods=8, settle=2, kfc=0.1)
    sig, st = _run(**kw)
    ref = harmonic_stats({"motor_angle": sig["motor_angle"], "reference": sig["reference"]},
                         n=4096, cycles=1, harmonics=7)
    v, vr = st.var["motor_angle"], ref.var["motor_angle"]
    assert np.all(vr > (3e-5 * abs(ref.mean["motor_angle"][0])) ** 2)   # resolvable spread
    rel = np.abs(v / vr - 1)
    print("variance relative differences:", rel)
    assert np.all(rel <= 1e-2)


def test_harmonic_statistics_refused_above_nyquist_and_beyond_capacity():
    with FwSim(TWOMASS) as sim:
        sim.enable()
        sim.configure(exc_kind=1, exc_amplitude=0.1, exc_period=64, exc_sine_cycles=4,
                      exc_settle_periods=0, exc_record_periods=1, rec_signals=0)
        assert sim.try_set("STAT_HARMONICS", 9) == 4          # RANGE_HIGH: holds 8
        assert sim.try_set("STAT_SIGNALS", 0x0F) == 4         # 4 signals: holds 3
        assert sim.get("STAT_SIGNALS") == 0                   # old value kept
        sim.configure(stat_harmonics=8, stat_signals=0x05)    # line 8 x 4 = 32 = N/2
        assert sim.lib.drv_run_start(sim.drv) == 10           # DRV_E_INCOMPATIBLE
        assert sim.get("RUN_LAST_ERROR") == 9 and sim.get("RUN_STATE") == 0
        sim.configure(stat_harmonics=7)                       # line 28 < 32: accepted
        sim.start()
        sim.run_until_idle()
        assert sim.get("STAT_PERIODS") == 1
        assert sim.get("REC_BYTES") == 0                      # statistics only: nothing recorded
        sim.configure(exc_kind=0)                              # no sine: no harmonic bins
        assert sim.lib.drv_run_start(sim.drv) == 10
        assert sim.get("RUN_LAST_ERROR") == 10


def test_statistics_of_a_run_without_harmonics_hold_only_power():
    with FwSim(TWOMASS) as sim:
        sim.enable()
        sim.configure(exc_kind=1, exc_amplitude=0.1, exc_period=256, exc_sine_cycles=2,
                      exc_settle_periods=1, exc_record_periods=3, rec_signals=0x10,
                      stat_harmonics=0, stat_signals=0x05, stat_power=0x10)
        sim.start()
        sim.run_until_idle()
        st = parse_stats(sim.stats_bytes())
        data, _ = sim.record()
    assert st.harmonics == 0 and st.mean == {} and st.periods == 3
    e = data[:, 0].astype(np.float64)
    assert abs(st.power_msq["error"] / np.mean(e ** 2) - 1) <= 1e-5


def test_parse_stats_rejects_inconsistent_data():
    with pytest.raises(InputError, match="8-byte header"):
        parse_stats(b"\x01\x00")
    hdr = (2).to_bytes(4, "little") + bytes([7, 0x05, 0x10, 0])
    with pytest.raises(InputError, match="needs 184"):
        parse_stats(hdr + bytes(100))
    with pytest.raises(InputError, match="beyond what the drive holds"):
        parse_stats((2).to_bytes(4, "little") + bytes([9, 0x05, 0, 0]) + bytes(12 * 18))
    st = parse_stats(hdr + bytes(176))
    assert st.harmonics == 7 and list(st.mean) == ["reference", "motor_angle"]
    back = HarmonicStats.from_dict(st.to_dict())
    assert back.periods == 2 and np.array_equal(back.mean["reference"], st.mean["reference"])


def test_statistics_invalidated_by_a_background_overrun_are_rejected():
    """The drive's sums run in its background task (drv_background between control steps);
    if that falls behind, the run's statistics carry status bit 0 and P = 0, and the parser
    refuses them instead of returning numbers."""
    with FwSim(TWOMASS) as sim:
        sim.enable()
        sim.configure(exc_kind=1, exc_amplitude=0.3, exc_period=256, exc_sine_cycles=1, exc_settle_periods=0,
                      exc_record_periods=2, rec_signals=0, stat_harmonics=3, stat_signals=0x05, stat_power=0x10)
        sim.start()
        for _ in range(40):  # control steps with no background in between: 2 blocks of 16 fill
            sim.lib.sim_step(sim.sim)
        sim.run_until_idle()
        assert sim.get("STAT_OVERRUNS") == 1 and sim.get("STAT_PERIODS") == 0
        raw = sim.stats_bytes()
        with pytest.raises(InputError, match="background task fell behind"):
            parse_stats(raw)
        sim.start()  # the next run, background keeping up: valid again
        sim.run_until_idle()
        st = parse_stats(sim.stats_bytes())
        assert st.periods == 2 and abs(st.mean["reference"][0]) > 0.3 * 256 / 2 * 0.9
    hdr = (2).to_bytes(4, "little") + bytes([0, 0, 0x10, 0x80])
    with pytest.raises(InputError, match="unknown status bits 0x80"):
        parse_stats(hdr + bytes(8))


def test_harmonic_stats_checks_its_input():
    with pytest.raises(InputError, match="N/2"):
        harmonic_stats({"x": np.zeros(64)}, n=64, cycles=4, harmonics=8)
    with pytest.raises(InputError, match="whole number of periods"):
        harmonic_stats({"x": np.zeros(100)}, n=64, cycles=1, harmonics=3)
    # analytic: x = cos(2 pi 3 n / 64) -> X[3] = 32, spread 0 over 2 periods
    n = np.arange(128)
    st = harmonic_stats({"x": np.cos(2 * np.pi * 3 * n / 64)}, n=64, cycles=3, harmonics=2, power=["x"])
    np.testing.assert_allclose(st.mean["x"], [32, 0], atol=1e-12)
    np.testing.assert_allclose(st.var["x"], [0, 0], atol=1e-20)
    assert abs(st.power_msq["x"] - 0.5) < 1e-12


def test_capture_key_is_checked_naming_the_key():
    from fftune.analysis.errors import FftuneError
    from fftune.host.config import validate
    assert validate({"tune": {"capture": "stats"}})["tune"]["capture"] == "stats"
    assert validate({})["quantify"]["capture"] is None          # auto
    with pytest.raises(FftuneError, match=r"c\.yaml: key 'tune\.capture': expected one of raw, stats, both"):
        validate({"tune": {"capture": "samples"}}, "c.yaml")
    with pytest.raises(FftuneError, match=r"key 'quantify\.capture'"):
        validate({"quantify": {"capture": 1}}, "c.yaml")


def test_capture_mode_follows_the_bus():
    from fftune.host.experiments import Session

    class S:  # only what capture_mode reads
        capture_mode = Session.capture_mode
    s = S()
    s.cfg, s.truth = {"tune": {"capture": None}, "sim": {"bitrate": None}}, {"sim_fc_volt": 0.1}
    assert s.capture_mode("tune") == "raw"            # simulated drive, no bus model
    s.cfg["sim"]["bitrate"] = 1_000_000
    assert s.capture_mode("tune") == "stats"          # behind a bus model
    s.cfg["sim"]["bitrate"], s.truth = None, None
    assert s.capture_mode("tune") == "stats"          # a real drive
    s.cfg["tune"]["capture"] = "both"
    assert s.capture_mode("tune") == "both"           # the configuration decides


def test_period_hosidf_moments_equal_the_per_period_hosidfs_of_the_samples(noisy_plant):
    """The tune search's input from statistics (mean H and one period's variance) against
    the per-period HOSIDFs from the samples of the same run; the noise per sample from the
    line variances against the spread of the samples over the periods."""
    from fftune.analysis.stats import period_hosidf_moments, period_noise_rms
    n, p = 4096, 8
    sig, st = _run(plant=noisy_plant, n=n, cycles=1, amplitude=0.5, periods=p, settle=2, kfc=0.05)
    H, H_var, P = period_hosidf_moments(st, u_name="reference", y_name="motor_angle")
    h = hosidf(sig["reference"].reshape(p, 1, n), sig["motor_angle"].reshape(p, 1, n), fs=FS,
               n_harmonics=7, f0=FS / n)
    Hp = np.asarray(h.H_repeats).reshape(p, 7)          # (P experiments of one period, K)
    assert P == p
    assert relative_difference(H, Hp.mean(axis=0), abs(Hp[0, 0])) <= 1e-5
    d = Hp - Hp.mean(axis=0)
    var_raw = np.sum(d.real ** 2 + d.imag ** 2, axis=0) / (p - 1)
    np.testing.assert_allclose(H_var, var_raw, rtol=1e-2)
    y = sig["motor_angle"].reshape(p, n)
    noise_raw = np.sqrt(np.sum((y - y.mean(axis=0)) ** 2) / (y.size - n))
    # 7 lines x 7 degrees of freedom: the estimate scatters by about 1 / sqrt(2 x 49)
    assert abs(period_noise_rms(st, "motor_angle", n) / noise_raw - 1) <= 0.35
    assert abs(noise_raw / 2e-3 - 1) <= 0.1


def test_period_hosidf_moments_refuse_what_they_cannot_stand_for():
    from fftune.analysis.stats import period_hosidf_moments, period_noise_rms
    st = HarmonicStats(periods=4, harmonics=3,
                       mean={"reference": np.array([100 + 0j, 0, 0]), "motor_angle": np.array([90j, 1, 2])},
                       var={"reference": np.zeros(3), "motor_angle": np.array([4.0, 1, 1])})
    H, H_var, P = period_hosidf_moments(st, u_name="reference", y_name="motor_angle")
    np.testing.assert_allclose(H, [0.9j, 0.01, 0.02])
    np.testing.assert_allclose(H_var, [4e-4, 1e-4, 1e-4])
    assert period_noise_rms(st, "motor_angle", n=2) == pytest.approx(1.0)
    with pytest.raises(InputError, match="changes from period to period"):
        period_hosidf_moments(HarmonicStats(periods=4, harmonics=3, mean=st.mean,
                                            var={"reference": np.array([1.0, 0, 0]),
                                                 "motor_angle": st.var["motor_angle"]}),
                              u_name="reference", y_name="motor_angle")
    with pytest.raises(InputError, match="needs >= 2"):
        period_hosidf_moments(HarmonicStats(periods=1, harmonics=3, mean=st.mean, var=st.var),
                              u_name="reference", y_name="motor_angle")
    with pytest.raises(InputError, match="no harmonic statistics of 'load_angle'"):
        period_hosidf_moments(st, u_name="reference", y_name="load_angle")
    with pytest.raises(InputError, match="4 asked for"):
        period_hosidf_moments(st, u_name="reference", y_name="motor_angle", n_harmonics=4)
