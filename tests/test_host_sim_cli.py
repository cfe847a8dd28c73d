"""`fftune sim` and `fftune demo` take the other commands' bus options (issue 15 item 7)
and the bus model's bit rate (issue 13 item 1): `-i socketcand --host --port`,
`-i socketcan -c IFNAME`, `-b/--bitrate`, `sim.bitrate` in a configuration. SocketCAN
itself is exercised in the qemu guest (tests/test_host_vm.py: `fftune sim -i socketcan -c
vcan0` + `fftune tune -i socketcan -c vcan0`); here the options, the errors and the
socketcand paths."""
import os
import re
import signal
import subprocess
import sys

import pytest
import yaml

from fftune.host.cli import main
from fftune.host.config import load_config
from fftune.host.drive import BusOptions, DriveClient, quiet_can_loggers
from fftune.host.sim import drive_sim_command, start_drive_sim
from host_fixtures import EDS, REPO, drive_sim_missing_reason, free_port

PLANT = os.path.join(REPO, "configs", "plant_twomass.yaml")
needs_drive = pytest.mark.skipif(drive_sim_missing_reason() is not None, reason=drive_sim_missing_reason() or "")


def test_drive_sim_command_maps_the_bus_options():
    cmd = drive_sim_command(PLANT, interface="socketcan", channel="vcan0", node_id=3, realtime=True)
    assert cmd[1:3] == ["--can", "socketcan:vcan0"]
    assert "--realtime" in cmd and cmd[cmd.index("--node-id") + 1] == "3" and "--bitrate" not in cmd
    cmd = drive_sim_command(PLANT, host="127.0.0.1", port=4000, bitrate=500_000)
    assert cmd[1:3] == ["--can", "socketcand:127.0.0.1:4000"]
    assert cmd[cmd.index("--bitrate") + 1] == "500000"


@pytest.mark.parametrize("argv, message", [
    (["sim", "-i", "pcan"], "the simulated drive speaks socketcand or SocketCAN (-i socketcand | "
                            "-i socketcan -c IFNAME), not -i pcan"),
    (["sim", "-i", "socketcan"], "the simulated drive on SocketCAN needs its interface: -c vcan0 "
                                 "(set up with: modprobe vcan; ip link add dev vcan0 type vcan; ip link set up vcan0)"),
    (["sim", "-b", "5000"], "sim: argument -b/--bitrate: 5000: expected 10000 .. 1000000 bit/s"),
    (["sim", "-i", "socketcan", "-c", "vcan0", "-b", "500000"],
     "--bitrate 500000: the bus model is part of drive_sim's socketcand server; a SocketCAN "
     "interface (vcan0) has its own bit rate"),
])
def test_sim_bad_bus_options_are_one_line(argv, message, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err == f"fftune: error: {message}\n"


def test_demo_bad_bus_option_touches_no_output(tmp_path, capsys):
    out = tmp_path / "demo"
    out.mkdir()
    (out / "results.yaml").write_text("earlier\n")
    assert main(["demo", "--out", str(out), "-i", "kvaser"]) == 2
    assert capsys.readouterr().err.startswith("fftune: error: the simulated drive speaks socketcand")
    assert (out / "results.yaml").read_text() == "earlier\n"  # not set aside as .previous
    assert not (tmp_path / "demo.previous").exists()


def test_config_sim_bitrate_is_checked(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("sim:\n  bitrate: 2000000\n")
    assert main(["demo", "--config", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fftune: error: ") and "sim.bitrate" in err and "1000000" in err
    good = tmp_path / "good.yaml"
    good.write_text("sim:\n  bitrate: 500000\n")
    assert load_config(str(good))["sim"]["bitrate"] == 500_000
    assert load_config(os.path.join(REPO, "configs", "demo.yaml"))["sim"]["bitrate"] is None


@needs_drive
def test_fftune_sim_serves_the_bus_model_on_the_given_port():
    """`fftune sim --port P -b 1000000` then a client with `--port P`: one command each."""
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "fftune.host.cli", "sim", "--port", str(port), "-b", "1000000",
                             "--plant", PLANT], cwd=REPO, env=dict(os.environ, PYTHONPATH=REPO),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert line.strip() == f"drive_sim: listening on socketcand 127.0.0.1:{port}, node 1, CAN bus model 1000000 bit/s"
        quiet_can_loggers()
        with DriveClient(BusOptions(port=port, eds=EDS), heartbeat_ms=0, progress=False) as c:
            assert c.get("fs") == 2560.0
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=10)
        assert proc.returncode == 0
        bits = int(re.search(r"CAN bus model: (\d+) frames, (\d+) bits", err).group(2))
        assert bits > 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


@needs_drive
def test_start_drive_sim_with_bitrate_and_node_id(tmp_path):
    sim = start_drive_sim(PLANT, node_id=5, bitrate=250_000, log_path=str(tmp_path / "d.log"))
    try:
        assert sim.interface == "socketcand" and sim.describe() == f"socketcand 127.0.0.1:{sim.port}"
        quiet_can_loggers()
        with DriveClient(BusOptions(port=sim.port, node_id=5, eds=EDS), heartbeat_ms=0, progress=False) as c:
            assert int(c.read(0x1000, 0)) == 0x00020192
    finally:
        sim.stop()
    assert "CAN bus model: " in open(tmp_path / "d.log").read()
