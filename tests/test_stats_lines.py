"""On-drive line statistics of multisine runs (firmware_sim/core/lstat.h, objects 0x2042 line
list / 0x2043 data) against the same numbers from the raw samples of the same run in float64
(numpy's FFT): through the C core (ctypes) and through drive_sim's CANopen node with
python-canopen as the peer (SDO downloads of the line list, its CiA 301 aborts for bad lists,
the upload of 0x2043 beside the recording 0x2021).

Accuracy (docs/firmware.md "Line statistics"): means of U, Y, R within 1e-5 of the largest
line of that signal (float32 FFT of N points, relative_difference's scale) and within 1e-5 of
their own magnitude on the lines above 1 % of the largest; the variances of U and Y and the
covariance within 1e-5 relative, line by line, also for a quiet plant whose period-to-period
spread is far below the float32 resolution of the lines (the drive transforms period p minus
period 0, sample by sample: shifted data, core/lstat.h).
"""
import os
import sys

import numpy as np
import pytest

from fftune.analysis.errors import InputError
from fftune.analysis.stats import LineStats, line_stats, parse_line_stats, relative_difference

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), os.pardir))
sys.path.insert(0, os.path.join(REPO, "firmware_sim", "tests"))
from fwsim import FwSim  # noqa: E402

TWOMASS = os.path.join(REPO, "configs", "plant_twomass.yaml")


@pytest.fixture(scope="module")
def noisy_plant(tmp_path_factory):
    """The two-mass plant with 2e-3 rad measurement noise and an ideal encoder (every line
    gets a period-to-period spread)."""
    from fftune.host.sim import derived_plant
    path = tmp_path_factory.mktemp("noisy") / "plant.yaml"
    return derived_plant(TWOMASS, {"sensor": {"noise_std": 2e-3, "counts_per_rev": 0}}, str(path))


def _check(st, ref, tol=1e-5):
    assert st.periods == ref.periods
    np.testing.assert_array_equal(st.bins, ref.bins)
    for name in ("U", "Y", "R"):
        a, b = getattr(st, name), getattr(ref, name)
        assert relative_difference(a, b) <= tol, name
    for name, scale in (("var_u", np.max(np.abs(ref.U))), ("var_y", np.max(np.abs(ref.Y)))):
        sd, sd_ref = np.sqrt(np.maximum(getattr(st, name), 0)), np.sqrt(getattr(ref, name))
        assert np.max(np.abs(sd - sd_ref)) <= tol * scale, name
    scale = np.sqrt(np.max(np.abs(ref.U)) * np.max(np.abs(ref.Y)))
    assert np.max(np.abs(np.sqrt(np.abs(st.cov_yu)) - np.sqrt(np.abs(ref.cov_yu)))) <= tol * scale
    _check_relative(st, ref, tol)


def _rel(a, b):
    return float(np.max(np.abs(a - b) / np.abs(b)))


def _check_relative(st, ref, tol=1e-5):
    """Line by line: variances and covariance relative to themselves, means relative to their
    own magnitude where the line is above 1 % of the largest of its signal."""
    assert _rel(st.var_u, ref.var_u) <= tol, _rel(st.var_u, ref.var_u)
    assert _rel(st.var_y, ref.var_y) <= tol, _rel(st.var_y, ref.var_y)
    assert _rel(st.cov_yu, ref.cov_yu) <= tol, _rel(st.cov_yu, ref.cov_yu)
    for name in ("U", "Y", "R"):
        a, b = getattr(st, name), getattr(ref, name)
        big = np.abs(b) >= 1e-2 * np.max(np.abs(b))
        if np.max(np.abs(b)) > 0:          # (r = 0 in an input-injection run)
            assert _rel(a[big], b[big]) <= tol, name


def _fwsim_run(plant, *, n, periods, bins, k_max, inject=0, rms=0.3, settle=1):
    with FwSim(plant) as sim:
        sim.enable()
        sim.configure(kfc=0.05, exc_kind=3, exc_inject=inject, exc_amplitude=rms, exc_period=n,
                      ms_k_min=1, ms_k_max=k_max, ms_group=5, ms_seed=3, exc_settle_periods=settle,
                      exc_record_periods=periods, rec_signals=0x07)
        sim.set_lines(bins)
        sim.configure(stat_line_mode=1)
        sim.start()
        sim.run_until_idle()
        data, names = sim.record()
        assert names[:3] == ["reference", "plant_input", "motor_angle"]
        assert sim.get("STAT_LINE_PERIODS") == periods
        raw = sim.line_stats_bytes()
    return data.astype(np.float64), parse_line_stats(raw)


@pytest.mark.parametrize("n,periods,inject", [(1024, 4, 0), (4096, 3, 1)], ids=["N1024_ref", "N4096_input"])
def test_drive_line_statistics_equal_float64_of_the_samples(noisy_plant, n, periods, inject):
    k_max = min(n // 16, 60)                        # 2 k_max - 1 lines
    bins = np.arange(1, 2 * k_max)                  # excited lines and the detection lines between
    data, st = _fwsim_run(noisy_plant, n=n, periods=periods, bins=bins, k_max=k_max, inject=inject)
    r, u, y = data[:, 0], data[:, 1], data[:, 2]
    ref = line_stats(u, y, r, n=n, bins=bins)
    _check(st, ref)
    # the noise made the spreads resolvable (above the float32 resolution of the lines)
    assert np.median(np.sqrt(ref.var_y)) > 3e-5 * np.max(np.abs(ref.Y))


def test_drive_holds_1024_lines(noisy_plant):
    """drive_sim's capacity (0x2040:9 = LSTAT_LINES_MAX = 1024): every line from 1 to 1024 of
    N = 4096, the demo's excitation (bins 4 .. 160 at N = 4096) inside them."""
    n, periods = 4096, 3
    bins = np.arange(1, 1025)
    data, st = _fwsim_run(noisy_plant, n=n, periods=periods, bins=bins, k_max=160, settle=2)
    assert st.bins.size == 1024
    ref = line_stats(data[:, 1], data[:, 2], data[:, 0], n=n, bins=bins)
    _check(st, ref)


@pytest.fixture(scope="module", params=[1e-5, 0.0], ids=["noise1e-5", "noise0"])
def quiet_plant(request, tmp_path_factory):
    """The two-mass plant with 10 urad measurement noise or none, ideal encoder: the
    period-to-period spreads are 1e-5 .. 1e-9 of the largest line, at or below the float32
    resolution of the lines themselves."""
    from fftune.host.sim import derived_plant
    path = tmp_path_factory.mktemp("quiet") / "plant.yaml"
    return derived_plant(TWOMASS, {"sensor": {"noise_std": request.param, "counts_per_rev": 0}}, str(path))


@pytest.mark.parametrize("n,periods,inject,settle", [(2048, 4, 0, 3), (4096, 3, 1, 2)],
                         ids=["N2048_ref", "N4096_input"])
def test_quiet_plant_variances_relative_to_themselves(quiet_plant, n, periods, inject, settle):
    """Shifted data: the drive's variances and covariance of a quiet plant within 1e-5 of the
    float64 ones relative to themselves (a per-period float32 FFT of X_p gets them wrong by
    O(1): its rounding is relative to |X_p|). Settled: with a transient in the recorded
    periods, a line whose spread is far below the spread of the other lines' differences
    gets more (the FFT of x_p - x_0 rounds relative to all of its lines, docs/firmware.md)."""
    k_max = 50
    bins = np.arange(1, 2 * k_max + 20)
    data, st = _fwsim_run(quiet_plant, n=n, periods=periods, bins=bins, k_max=k_max, inject=inject,
                          settle=settle)
    r, u, y = data[:, 0], data[:, 1], data[:, 2]
    ref = line_stats(u, y, r, n=n, bins=bins)
    # the spreads are at or below the float32 resolution of the lines on the scale of the largest
    assert np.median(np.sqrt(ref.var_y)) < 2e-5 * np.max(np.abs(ref.Y))
    assert np.all(ref.var_u > 0) and np.all(ref.var_y > 0)
    assert relative_difference(st.U, ref.U) <= 1e-5 and relative_difference(st.Y, ref.Y) <= 1e-5
    if np.any(ref.R != 0):
        assert relative_difference(st.R, ref.R) <= 1e-5
    _check_relative(st, ref)


def test_line_list_refused_beyond_n_half_and_capacity_through_the_c_core():
    with FwSim(TWOMASS) as sim:
        sim.configure(exc_period=256)
        raw = np.arange(1, 1026, dtype="<u2").tobytes()  # 1025 lines: one more than the drive holds
        assert sim.lib.drv_lines_write(sim.drv, 0, raw, len(raw)) == 12   # DRV_E_TOO_LONG
        ok = np.array([5, 9], dtype="<u2").tobytes()
        assert sim.lib.drv_lines_write(sim.drv, 0, ok, 4) == 0
        assert sim.lib.drv_lines_commit(sim.drv, 4) == 0
        bad = np.array([5, 128], dtype="<u2").tobytes()   # N/2
        assert sim.lib.drv_lines_write(sim.drv, 0, bad, 4) == 0
        assert sim.lib.drv_lines_commit(sim.drv, 4) == 11  # DRV_E_VALUE
        assert sim.get("STAT_LINES") == 2 and sim.get("STAT_LINES_CAP") == 1024


def test_parse_line_stats_rejects_inconsistent_data_and_line_stats_its_input():
    with pytest.raises(InputError, match="8-byte header"):
        parse_line_stats(b"\x00")
    hdr = (3).to_bytes(4, "little") + (2).to_bytes(2, "little") + b"\x00\x00"
    with pytest.raises(InputError, match="need 96"):
        parse_line_stats(hdr + bytes(40))
    with pytest.raises(InputError, match="unknown status"):
        parse_line_stats(hdr[:6] + b"\x01\x00" + bytes(88))
    line = lambda b: int(b).to_bytes(4, "little") + np.arange(10, dtype="<f4").tobytes()  # noqa: E731
    with pytest.raises(InputError, match="ascending"):
        parse_line_stats(hdr + line(5) + line(5))
    st = parse_line_stats(hdr + line(5) + line(7))
    assert isinstance(st, LineStats) and list(st.bins) == [5, 7] and st.U[0] == 0 + 1j
    assert st.cov_yu[1] == 8 + 9j and st.var_y[0] == 7
    with pytest.raises(InputError, match="N/2"):
        line_stats(np.zeros(64), np.zeros(64), np.zeros(64), n=64, bins=[32])
    with pytest.raises(InputError, match="whole number of periods"):
        line_stats(np.zeros(60), np.zeros(64), np.zeros(64), n=64, bins=[3])
    # analytic: cos at bin 3 of N = 64 -> X[3] = 32 in every period, no spread
    t = np.arange(128)
    x = np.cos(2 * np.pi * 3 * t / 64)
    ref = line_stats(x, 2 * x, -x, n=64, bins=[3, 4])
    np.testing.assert_allclose(ref.U, [32, 0], atol=1e-12)
    np.testing.assert_allclose(ref.Y, [64, 0], atol=1e-12)
    np.testing.assert_allclose(ref.R, [-32, 0], atol=1e-12)
    np.testing.assert_allclose(ref.var_u, [0, 0], atol=1e-20)


# ---- through drive_sim's CANopen node, python-canopen as the peer ----------------------------

def _drive_sim_reason():
    from host_fixtures import drive_sim_missing_reason
    return drive_sim_missing_reason()


@pytest.fixture(scope="module")
def sim(tmp_path_factory, noisy_plant):
    reason = _drive_sim_reason()
    if reason is not None:
        pytest.skip(reason)
    from fftune.host.sim import start_drive_sim
    d = tmp_path_factory.mktemp("sim")
    drive = start_drive_sim(noisy_plant, log_path=str(d / "drive_sim.log"))
    yield drive
    drive.stop()


@pytest.fixture()
def drive(sim):
    from fftune.host.drive import BusOptions, DriveClient
    from host_fixtures import EDS
    with DriveClient(BusOptions(port=sim.port, host=sim.host, eds=EDS), progress=False) as d:
        d.enable()
        yield d


def _abort_code(fn):
    import canopen
    with pytest.raises(canopen.SdoAbortedError) as info:
        fn()
    return info.value.code


def test_line_list_aborts_over_canopen(drive):
    sdo = drive.node.sdo
    drive.set("exc_period", 1024)
    cap = int(drive.get("stat_lines_cap"))
    assert cap == 1024   # drive_sim's LSTAT_LINES_MAX (core/lstat.h), the EDS default of 0x2040:9
    sdo.download(0x2042, 0, np.array([3, 5, 7], dtype="<u2").tobytes())       # segmented
    assert int(drive.get("stat_lines")) == 3
    sdo.download(0x2042, 0, np.array([4, 6], dtype="<u2").tobytes())          # expedited
    assert int(drive.get("stat_lines")) == 2
    # a bin at N/2: value range of parameter exceeded; more lines than held: length too high
    assert _abort_code(lambda: sdo.download(0x2042, 0, np.array([3, 512], dtype="<u2").tobytes())) \
        == 0x06090030
    too_many = np.arange(1, cap + 2, dtype="<u2").tobytes()
    assert _abort_code(lambda: sdo.download(0x2042, 0, too_many)) == 0x06070012
    assert _abort_code(lambda: sdo.download(0x2042, 0, too_many, force_segment=True)) == 0x06070012
    assert bytes(sdo.upload(0x2042, 0)) == np.array([4, 6], dtype="<u2").tobytes()   # the list kept


def test_drive_sim_multisine_line_statistics_equal_float64_of_its_raw_samples(drive):
    n, periods, k_max = 2048, 4, 50
    bins = np.arange(1, 2 * k_max + 1)
    drive.set("exc_period", n)
    drive.node.sdo.download(0x2042, 0, bins.astype("<u2").tobytes())
    params = {"exc_kind": 3, "exc_inject": 0, "exc_amplitude": 0.3, "exc_offset": 0.0, "exc_period": n,
              "ms_k_min": 1, "ms_k_max": k_max, "ms_group": 5, "ms_seed": 11, "ms_realization": 0,
              "exc_settle_periods": 1, "exc_record_periods": periods, "kfc": 0.05, "stat_line_mode": 1}
    try:
        rec = drive.run(params, signals=("reference", "plant_input", "motor_angle"), capture="raw", desc="lines")
        raw = bytes(drive.node.sdo.upload(0x2043, 0))
    finally:
        drive.set("stat_line_mode", 0)
    st = parse_line_stats(raw)
    assert len(raw) == 8 + 44 * bins.size
    ref = line_stats(rec.signals["plant_input"], rec.signals["motor_angle"], rec.signals["reference"],
                     n=n, bins=bins)
    _check(st, ref)
    assert int(drive.get("stat_line_periods")) == periods
