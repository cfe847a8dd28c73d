"""The drive side of ``fftune track`` (host/track.py; issue 33's hand-written bug audit,
docs/testing.md): the heartbeat's share of the bus stated for both producers (host and
drive), and a task run the drive ended in state idle named at once with its stop reason
(not waited on until the run timeout). Expected values computed here from the CAN frame
layout and the drive's objects.
"""
import os
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
def test_heartbeat_load_counts_the_host_and_the_drive(tmp_path):
    """Two producers (the host's and the drive's), one byte each, every 125 ms at
    500 kbit/s: 2 x 65 bits / 0.125 s / 500000 bit/s = 0.208 %."""
    cfg = {"output": str(tmp_path / "out"), "sim": {"plant": os.path.join(REPO, "configs", "plant_twomass.yaml")},
           "drive": {"heartbeat_ms": 125},
           "track": {"tasks": 2, "settle_repetitions": 0, "bus_bitrate": 500000,
                     "initial": {"k_fc": 0.1157, "k_v": 0.002, "k_a": 0.0}}}
    path = tmp_path / "track.yaml"
    path.write_text(yaml.safe_dump(cfg))
    assert main(["demo-track", "--config", str(path), "--no-progress", "--no-figures"]) == 0
    bus = yaml.safe_load((tmp_path / "out" / "results.yaml").read_text())["track_summary"]["bus"]
    assert _frame_bits(1) == 65
    assert bus["heartbeat_load"] == pytest.approx(2 * 65 / 0.125 / 500000, rel=1e-5)
    assert bus["bitrate"] == 500000


class _Od(dict):
    pass


class _Opts:
    node_id = 6


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

    def get(self, name):
        return self.values[name]

    def set(self, name, value):
        self.writes.append((name, value))

    def set_parameters(self, values):
        for k, v in values.items():
            self.set(k, v)

    def _check_heartbeat(self):
        pass


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
