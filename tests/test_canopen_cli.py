"""drive_sim's command line: readiness line, bad input, realtime mode, SocketCAN errors."""
import os
import subprocess
import time

import canopen
import pytest

from canopen_helpers import configure_sine_run, enable_402, sdo_response_timeout_s, wait_for
from conftest import DRIVE_SIM_BIN, drive_sim_missing_reason, start_drive_sim, stop_drive_sim

pytestmark = pytest.mark.skipif(drive_sim_missing_reason() is not None,
                                reason=drive_sim_missing_reason() or "")


@pytest.mark.parametrize("args, message", [
    (["--node-id", "0"], "--node-id must be 1..127"),
    (["--node-id", "128"], "--node-id must be 1..127"),
    (["--can", "socketcand:127.0.0.1"], "--can socketcand:HOST:PORT expected"),
    (["--can", "udp:1"], "unknown bus"),
    (["--can", "socketcand:not-an-ip:0"], "bad IPv4 address 'not-an-ip'"),
    (["--config", "/nonexistent/plant.yaml"], "/nonexistent/plant.yaml"),
    (["--frobnicate"], "unknown or incomplete option: --frobnicate"),
    (["--can", "socketcan:nosuchcan0"], "socketcan:"),
])
def test_bad_arguments_give_one_clear_line_and_exit_2(args, message):
    proc = subprocess.run([DRIVE_SIM_BIN, *args], capture_output=True, text=True, timeout=10)
    assert proc.returncode == 2
    first = proc.stderr.splitlines()[0]
    assert first.startswith("drive_sim: error: ") and message in first
    assert proc.stdout == ""


def test_bad_config_value_names_file_line_and_key(tmp_path):
    bad = tmp_path / "plant.yaml"
    bad.write_text("drive:\n  fs_hz: -5\n")
    proc = subprocess.run([DRIVE_SIM_BIN, "--config", str(bad), "--port", "0"],
                          capture_output=True, text=True, timeout=10)
    assert proc.returncode == 2
    assert str(bad) in proc.stderr and "fs_hz" in proc.stderr


def test_node_id_option_moves_every_cob_id(tmp_path):
    sim = start_drive_sim(tmp_path, node_id=42)
    try:
        net = sim.network()
        node = canopen.RemoteNode(42, sim.eds)
        net.add_node(node)
        assert node.sdo[0x1014].raw == 0x80 + 42
        assert node.sdo[0x1800][1].raw == 0x180 + 42
        net.disconnect()
    finally:
        stop_drive_sim(sim)


def test_realtime_mode_steps_at_the_controller_rate(tmp_path):
    """--realtime: a 1 s recording (2560 samples at 2560 Hz) takes at least ~1 s of wall
    time (free-run does it in milliseconds); the exit line reports the overrun count."""
    sim = start_drive_sim(tmp_path, extra_args=["--realtime"])
    try:
        net = sim.network()
        node = canopen.RemoteNode(1, sim.eds)
        node.sdo.RESPONSE_TIMEOUT = sdo_response_timeout_s(sim)
        net.add_node(node)
        node.nmt.state = "OPERATIONAL"
        enable_402(node)
        configure_sine_run(node, period=2560, record=1, signals=0x01)
        t0 = time.monotonic()
        node.sdo["Run control"]["Command"].raw = 1
        assert wait_for(lambda: node.sdo["Run control"]["State"].raw == 3, 10.0, 0.05)
        assert time.monotonic() - t0 > 0.9
        net.disconnect()
    finally:
        stop_drive_sim(sim)
    assert "overruns" in sim.stderr_text()
