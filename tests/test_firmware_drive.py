"""The drive core (firmware_sim/core, C via ctypes) in closed loop with the simulated plant:
the effect the project rests on (Coulomb feed-forward linearises the loop), and the on-drive
multisine against the shared vectors and the analysis package's design."""
import json
import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "firmware_sim", "tests"))
from fwsim import FwError, FwSim, sine_response  # noqa: E402

ROOT = os.path.join(os.path.dirname(__file__), "..")
TWOMASS = os.path.join(ROOT, "configs", "plant_twomass.yaml")
STAGE = os.path.join(ROOT, "configs", "plant_stage.yaml")
VECTORS = os.path.join(ROOT, "tests", "vectors", "multisine_vectors.json")

# sine reference: 0.5 rad at f0 = fs / N = 1 Hz, 3 settle + 4 recorded periods
AMPLITUDE, N_PERIOD, SETTLE, RECORD = 0.5, 2560, 3, 4


def harmonics(y, k_orders, record=RECORD):
    """Complex spectrum lines at k f0 (integer number of periods: leakage free)."""
    Y = np.fft.rfft(np.asarray(y, dtype=np.float64))
    return np.array([Y[k * record] for k in k_orders])


def odd_ratio(y):
    """rms of |Y(3 f0)|, |Y(5 f0)|, |Y(7 f0)| over |Y(f0)|."""
    h = np.abs(harmonics(y, (1, 3, 5, 7)))
    return np.sqrt(np.sum(h[1:] ** 2)) / h[0]


def hosidf3_phase_deg(y, r):
    """angle Y(3 f0) - 3 angle R(f0), wrapped to (-180, 180]."""
    y1, y3 = harmonics(y, (1, 3))
    r1 = harmonics(r, (1,))[0]
    ph = np.angle(y3) - 3 * np.angle(r1)
    return np.degrees(np.angle(np.exp(1j * ph)))


@pytest.fixture(scope="module")
def fc_volt():
    with FwSim(TWOMASS) as sim:
        return sim.truth("SIM_FC_VOLT")


@pytest.fixture(scope="module")
def responses(fc_volt):
    return {factor: sine_response(TWOMASS, factor * fc_volt, AMPLITUDE, N_PERIOD, 1, SETTLE, RECORD)
            for factor in (0.0, 0.5, 1.0, 1.5)}


def test_coulomb_feedforward_linearises_the_loop(responses):
    r0 = odd_ratio(responses[0.0]["motor_angle"])
    r1 = odd_ratio(responses[1.0]["motor_angle"])
    print(f"odd harmonic ratio: K_fc = 0: {r0:.4f}; K_fc = Fc: {r1:.5f}; drop {r0 / r1:.0f}x")
    assert 0.05 <= r0 <= 0.20  # the paper's order of magnitude (15 %)
    assert r1 <= r0 / 10.0     # the paper: 15 % -> under 1.5 %
    # under- and over-compensation both leave more odd distortion than the optimum
    assert odd_ratio(responses[0.5]["motor_angle"]) > 3 * r1
    assert odd_ratio(responses[1.5]["motor_angle"]) > 3 * r1


def test_third_harmonic_phase_turns_at_the_optimum(responses):
    # the paper: the phases of the odd HOSIDFs turn 180 deg at the optimal setting
    under = hosidf3_phase_deg(responses[0.5]["motor_angle"], responses[0.5]["reference"])
    over = hosidf3_phase_deg(responses[1.5]["motor_angle"], responses[1.5]["reference"])
    turn = abs(np.degrees(np.angle(np.exp(1j * np.radians(under - over)))))
    assert 150.0 <= turn <= 180.0, (under, over)


def test_recorded_run_is_periodic_in_steady_state(responses):
    # the settle periods suffice: consecutive recorded periods agree to one encoder count
    count = 2 * np.pi / 2000  # configs/plant_twomass.yaml sensor.counts_per_rev
    y = responses[1.0]["motor_angle"].reshape(RECORD, N_PERIOD)
    assert np.abs(y[-1] - y[-2]).max() <= 1.01 * count
    assert np.mean(y[-1] != y[-2]) < 0.01
    err = responses[1.0]["error"]
    ref = responses[1.0]["reference"]
    np.testing.assert_allclose(err, ref - responses[1.0]["motor_angle"], atol=1e-6)


def test_stage_relative_nonlinearity_falls_with_amplitude():
    # set-up I, the paper's HOSIDF experiment: a 20 Hz sine voltage at the plant input
    # (loop closed); bearing friction matters less at larger motion
    ratios = []
    for amplitude in (0.3, 0.6, 2.0):
        with FwSim(STAGE) as sim:
            sim.enable()
            sim.configure(exc_kind=1, exc_inject=1, exc_amplitude=amplitude, exc_period=2048,
                          exc_sine_cycles=16, exc_settle_periods=4, exc_record_periods=4, rec_signals=0x04)
            sim.start()
            sim.run_until_idle()
            data, _ = sim.record()
        h = np.abs(harmonics(data[:, 0], (16, 48, 80), record=4))
        ratios.append(np.sqrt(h[1] ** 2 + h[2] ** 2) / h[0])
    print("stage odd ratios vs amplitude:", ratios)
    assert ratios[0] > 2 * ratios[1] > 4 * ratios[2]
    assert ratios[0] > 0.01


def _load_vectors():
    with open(VECTORS, encoding="utf-8") as f:
        return json.load(f)["designs"]


def _drive_multisine(design, rms, record_periods=1):
    with FwSim(TWOMASS) as sim:
        sim.enable()
        sim.configure(exc_kind=3, exc_inject=0, exc_period=design["N"], ms_k_min=design["k_min"],
                      ms_k_max=design["k_max"], ms_group=design["G"], ms_seed=design["seed"],
                      ms_realization=design["m"], exc_amplitude=rms, exc_settle_periods=0,
                      exc_record_periods=record_periods, rec_signals=0x01, kp=0.0, kd=0.0)
        sim.start()
        table = sim.table()
        sim.run_until_idle()
        rec, _ = sim.record()
    return table, rec[:, 0]


@pytest.mark.parametrize("design", _load_vectors(), ids=lambda d: f"N{d['N']}_G{d['G']}_m{d['m']}")
def test_on_drive_multisine_equals_vectors(design):
    table, rec = _drive_multisine(design, design["rms"], record_periods=2)
    period = np.array(design["period"])
    peak = np.abs(period).max()
    # the drive's table is the unit-rms period; played at amplitude = rms
    assert np.abs(table * design["rms"] - period).max() <= 1e-5 * peak
    np.testing.assert_array_equal(rec, np.tile(np.float32(design["rms"]) * table, 2))


def test_on_drive_multisine_equals_analysis_design():
    multisine = pytest.importorskip("fftune.analysis.multisine", reason="fftune.analysis.multisine not present")
    designs = _load_vectors() + [
        {"N": 8192, "k_min": 1, "k_max": 2000, "G": 4, "seed": 2024, "m": 7, "rms": 0.3},
        {"N": 2048, "k_min": 5, "k_max": 1023, "G": 0, "seed": 0xFFFFFFFF, "m": 4294967295, "rms": 1.0},
    ]
    for d in designs:
        want = multisine.drive_multisine(d["N"], d["k_min"], d["k_max"], d["G"], d["seed"], d["m"], d["rms"])
        table, rec = _drive_multisine(d, d["rms"])
        peak = np.abs(want).max()
        err = np.abs(rec - want).max()
        assert err <= 1e-5 * peak, (d, err / peak)
        lines = multisine.drive_lines(d["N"], d["k_min"], d["k_max"], d["G"], d["seed"])
        spec = np.abs(np.fft.rfft(table.astype(np.float64)))
        excited = np.zeros(spec.size, dtype=bool)
        excited[lines.excited] = True
        # energy only on the excited lines, float32 floor elsewhere
        assert spec[~excited].max() < 1e-4 * spec[excited].min()


def test_multisine_start_refused_for_inconsistent_design():
    with FwSim(TWOMASS) as sim:
        sim.enable()
        sim.configure(exc_kind=3, exc_period=1000, ms_k_max=99)  # N not a power of two
        with pytest.raises(FwError, match="INCOMPATIBLE"):
            sim.start()
        assert sim.get("RUN_LAST_ERROR") == 5
        assert sim.get("RUN_STATE") == 0


def test_stage_detection_lines_show_odd_over_even_distortion():
    # the paper's detection experiment on set-up I: random odd multisine at the plant input;
    # friction (odd) puts power on the non-excited odd lines, its direction asymmetry a weaker
    # part on the even lines; both well under the excited lines
    n = 2048
    with FwSim(STAGE) as sim:
        sim.enable()
        sim.configure(exc_kind=3, exc_inject=1, exc_period=n, ms_k_min=1, ms_k_max=250, ms_group=4,
                      ms_seed=3, ms_realization=0, exc_amplitude=1.0, exc_settle_periods=3,
                      exc_record_periods=2, rec_signals=0x04)
        sim.start()
        table = sim.table()
        sim.run_until_idle()
        data, _ = sim.record()
    u_spec = np.abs(np.fft.rfft(table.astype(np.float64)))
    bins = np.arange(1, 251)
    excited = bins[u_spec[bins] > 1e-3 * u_spec.max()]
    detection = np.array([k for k in bins if k % 2 == 1 and k not in set(excited)])
    even = bins[bins % 2 == 0]
    y = np.abs(np.fft.rfft(data[:, 0].astype(np.float64).reshape(2, n).mean(axis=0)))
    p_exc, p_odd, p_even = (np.mean(y[k] ** 2) for k in (excited, detection, even))
    odd_db, even_db = 10 * np.log10(p_odd / p_exc), 10 * np.log10(p_even / p_exc)
    print(f"stage at 1 V rms: odd detection lines {odd_db:.1f} dB, even lines {even_db:.1f} dB")
    assert -40.0 < odd_db < -10.0
    assert odd_db - 30.0 < even_db < odd_db - 8.0
