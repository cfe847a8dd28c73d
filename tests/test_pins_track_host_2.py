"""The drive side of ``fftune track`` (host/track.py; issue 33's hand-written bug audit,
docs/testing.md): the heartbeat's share of the bus stated for both producers (host and
drive), and a task run the drive ended in state idle named at once with its stop reason
(not waited on until the run timeout). Expected values computed here from the CAN frame
layout and the drive's objects.
"""
import os
import struct
import time

import pytest
import yaml

from fftune.analysis.errors import FftuneError
from fftune.host.cli import main
from fftune.host.track import TaskDrive, validate_track_config
from host_fixtures import drive_sim_missing_reason

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), os.pardir))


def _frame_bits(n):
    """A base-format data frame of n bytes: 44 bits of frame + 3 of interframe space, the
    data, and at most one stuff bit per 4 of the 34 + 8 n - 1 stuffed bits (REFERENCE.md 3)."""
    return 44 + 3 + 8 * n + (34 + 8 * n - 1) // 4


@pytest.mark.skipif(drive_sim_missing_reason() is not None, reason=drive_sim_missing_reason() or "")
def test_bus_loads_count_both_heartbeats_and_a_rows_whole_run(tmp_path):
    """Two producers (the host's and the drive's), one byte each, every 125 ms at
    500 kbit/s: 2 x 65 bits / 0.125 s / 500000 bit/s = 0.208 %. The task's own traffic per
    row over the row's run: 1 settle + 2 recorded repetitions of the task."""
    cfg = {"output": str(tmp_path / "out"), "sim": {"plant": os.path.join(REPO, "configs", "plant_twomass.yaml")},
           "drive": {"heartbeat_ms": 125},
           "track": {"tasks": 2, "settle_repetitions": 1, "record_repetitions": 2, "bus_bitrate": 500000,
                     "initial": {"k_fc": 0.1157, "k_v": 0.002, "k_a": 0.0}}}
    path = tmp_path / "track.yaml"
    path.write_text(yaml.safe_dump(cfg))
    assert main(["demo-track", "--config", str(path), "--no-progress", "--no-figures"]) == 0
    res = yaml.safe_load((tmp_path / "out" / "results.yaml").read_text())
    summary = res["track_summary"]
    bus = summary["bus"]
    # K_v held (track_k_v false): the task does not identify it, no K_v estimate is reported
    assert [(r["k_v"], r["k_v_estimate"], r["notes"]) for r in res["track"]] == \
        [(0.002, None, ["viscous_drift_folded_into_k_fc"])] * 2
    assert _frame_bits(1) == 65
    assert bus["heartbeat_load"] == pytest.approx(2 * 65 / 0.125 / 500000, rel=1e-5)
    assert bus["bitrate"] == 500000
    run_s = 3 * summary["task_samples"] / 2560.0
    assert bus["task_traffic_load"] == pytest.approx(bus["bits_per_task_max"] / (run_s * 500000), rel=1e-5)


class _Od(dict):
    pass


class _Opts:
    node_id = 6


class _Ran(Exception):
    """(the test drive's run: its parameters recorded, nothing measured)"""


class _IdleDrive:
    """A drive (the attributes TaskDrive uses of a DriveClient) whose task run goes back to
    idle after the start, its last stop reason 3 (it left OPERATION ENABLED)."""

    def __init__(self):
        self.node = type("N", (), {"object_dictionary": _Od()})()
        self.opts = _Opts()
        self.run_timeout_s = 3.0
        self._bootups = 0
        self._run_active = False
        self.values = {"fs": 2560.0, "task_period": 3072, "run_state": 0, "run_last_error": 3}
        self.writes = []
        self.runs = []

    def get(self, name):
        return self.values[name]

    def set(self, name, value):
        self.writes.append((name, value))

    def set_parameters(self, values):
        for k, v in values.items():
            self.set(k, v)

    def _check_heartbeat(self):
        pass

    def _block_upload(self, index, sub):
        return self.uploads[index]

    def run(self, parameters, signals=(), desc="run"):
        self.runs.append(dict(parameters))
        raise _Ran()

    def read(self, index, sub):
        return self.od_values[(index, sub)]

    def write(self, index, sub, value):
        self.od_values[(index, sub)] = value


def test_a_task_run_back_to_idle_is_named_at_once_with_its_reason():
    cfg = validate_track_config({"track": {"poll_s": 0.01}}, "t.yaml")
    cfg["_source"] = "t.yaml"
    client = _IdleDrive()
    drive = TaskDrive(client, cfg)
    drive.configure()
    assert drive.run_s == pytest.approx(2 * 3072 / 2560.0)    # 1 settle + 1 recorded repetition
    t0 = time.monotonic()
    with pytest.raises(FftuneError) as exc:
        drive.run_task()
    assert str(exc.value) == "task run stopped by the drive: state idle, reason 3 (drive left OPERATION ENABLED)"
    assert time.monotonic() - t0 < client.run_timeout_s     # (not the run timeout's abort)
    assert ("run_command", 1) in client.writes and ("run_command", 2) not in client.writes
    assert client._run_active is False


def _stream(reps, samples, sums_per_block):
    """A task statistics upload: u32 repetitions, u32 samples, 8 blocks of float32 sums."""
    sums = [0.5 + 0.01 * i for i in range(8 * sums_per_block)]
    return struct.pack("<II", reps, samples) + struct.pack(f"<{len(sums)}f", *sums)


@pytest.mark.parametrize("reps, samples", [(2, 3072), (1, 3071), (3, 6144)])
def test_task_statistics_of_another_count_or_length_are_refused(reps, samples):
    """The run recorded 1 repetition of 3072 samples; statistics of 2 repetitions, or of
    3071 samples, or both wrong, are another run's: refused, each number named."""
    cfg = validate_track_config({"track": {"poll_s": 0.01, "settle_repetitions": 0}}, "t.yaml")
    cfg["_source"] = "t.yaml"
    client = _IdleDrive()
    client.values["run_state"] = 3
    client.uploads = {0x2062: _stream(reps, samples, 9), 0x2061: _stream(reps, samples, 6)}
    drive = TaskDrive(client, cfg)
    drive.configure()
    with pytest.raises(FftuneError) as exc:
        drive.run_task()
    assert str(exc.value) == (f"task statistics from node 6: {reps} repetitions of {samples} samples, the run "
                              f"recorded 1 of 3072")
    # the statistics of this run are taken
    client.uploads = {0x2062: _stream(1, 3072, 9), 0x2061: _stream(1, 3072, 6)}
    drive.design_raw = None
    stats = drive.run_task()
    assert (stats.repetitions, stats.samples, stats.design.shape, stats.data.shape) == (1, 3072, (8, 9), (8, 6))


def test_the_progress_tpdo_is_switched_off_for_tracking_and_restored_as_it_was():
    from fftune.host.track import PROGRESS_TPDO, _progress_pdo_off

    client = _IdleDrive()
    client.node.object_dictionary[0x1801] = object()
    client.od_values = {PROGRESS_TPDO: 0x40000286}      # (bit 30 set: kept as it was)
    saved = _progress_pdo_off(client)
    assert client.od_values[PROGRESS_TPDO] == 0xC0000286    # bit 31: not valid while tracking
    assert saved == 0x40000286                              # what the session writes back
    # already off: nothing to restore
    assert _progress_pdo_off(client) is None and client.od_values[PROGRESS_TPDO] == 0xC0000286
    # no such PDO: nothing read or written
    other = _IdleDrive()
    other.od_values = {}
    assert _progress_pdo_off(other) is None and other.od_values == {}


@pytest.mark.parametrize("frequency_hz, cycles", [(0.99, 2), (2.2, 4), (0.625, 1), (1.3, 2)])
def test_the_odd_ratio_check_plays_the_nearest_whole_number_of_cycles(frequency_hz, cycles):
    """A period of 4096 samples at 2560 Hz holds 0.99 Hz x 1.6 s = 1.58 cycles: 2 are
    played (the nearest), 2.2 Hz: 3.52 -> 4; 0.625 Hz: exactly 1; 1.3 Hz: 2.08 -> 2."""
    from fftune.host.track import _odd_check

    cfg = validate_track_config({"track": {"check": {"frequency_hz": frequency_hz, "period_samples": 4096,
                                                     "amplitude_rad": 0.3, "periods": 3,
                                                     "settle_periods": 1}}}, "t.yaml")
    client = _IdleDrive()
    with pytest.raises(_Ran):
        _odd_check(client, cfg, 0.21, 0.004, 2560.0)
    assert client.writes == [("task_mode", 0)]
    p = client.runs[0]
    assert round(frequency_hz * 4096 / 2560.0) == cycles
    assert (p["exc_kind"], p["exc_period"], p["exc_sine_cycles"], p["exc_amplitude"]) == (1, 4096, cycles, 0.3)
    assert (p["exc_settle_periods"], p["exc_record_periods"], p["kfc"], p["kv"]) == (1, 3, 0.21, 0.004)


def test_summary_lines_count_the_rollbacks_and_state_each_figure():
    from fftune.host.track import summary_lines

    actions = ["update", "rollback", "update", "hold", "rollback", "update", "update"]
    rows = [{"task": i, "action": a} for i, a in enumerate(actions)]
    s = {"tasks": 7, "task_s": 1.2, "k_fc_final": 0.1523, "k_fc_true_final": 0.1504,
         "stop": {"task": 6, "cause": "rollbacks", "reason": "3 updates in a row raised the tracking error"},
         "bus": {"bits_per_task_max": 2675, "task_traffic_load": 0.0022292, "bitrate": 1000000,
                 "heartbeat_load": 0.00052, "measured_load": 0.0071},
         "check": {"odd_ratio": 0.0123, "k_fc": 0.1523}}
    lines = summary_lines({"track": rows, "track_summary": s}, "out/t")
    assert lines == [
        "fftune track: 7 tasks of 1.2 s; final K_fc 0.1523 V (truth 0.1504 V)",
        "  stopped at task 6: rollbacks: 3 updates in a row raised the tracking error",
        "  bus: at most 2675 bits per task = 0.22 % of 1000000 bit/s (+ heartbeats 0.05 %)",
        "  bus measured in real time (all frames, PDOs and heartbeats included): 0.71 %",
        "  rollbacks: 2",
        "  odd-ratio check: 0.0123 at K_fc 0.1523 V",
        "  results: out/t/results.yaml, figure out/t/track_kfc.png"]
