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


# --------------------------------------------------------------------------- plant refusals
# drive_sim checks each plant value's range (firmware_sim/plant/plant_config.c, the one
# table); every command that starts it says which file and key, as the user wrote them:
# a plant fftune derived (a base file + sim.overrides / an axis' plant_overrides) is named
# by that origin, never by the derived text's path (a run's plant.yaml, or /proc/self/fd/N
# for `fftune sim`, which nobody can open).

@pytest.fixture
def no_exec(monkeypatch):
    """`fftune sim` replaces its process with drive_sim once the plant passes: here that
    would replace pytest, so it fails the test instead."""
    def refuse(*args):
        raise AssertionError(f"the plant passed drive_sim --check: would exec {args}")
    monkeypatch.setattr(os, "execv", refuse)


def _plant_with(tmp_path, old, new, name="plant.yaml"):
    text = open(PLANT, encoding="utf-8").read()
    assert old in text
    path = tmp_path / name
    path.write_text(text.replace(old, new, 1))
    return str(path)


def _config_with_overrides(tmp_path, overrides):
    cfg = yaml.safe_load(open(os.path.join(REPO, "configs", "demo.yaml"), encoding="utf-8"))
    cfg["sim"]["overrides"] = overrides
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return str(path)


@needs_drive
def test_sim_out_of_range_plant_names_the_users_file_and_line(tmp_path, capsys, no_exec):
    plant = _plant_with(tmp_path, "  j2: 2.0e-4 ", "  j2: -3.0e-4 ")
    line = 1 + open(plant).read().splitlines().index(next(
        ln for ln in open(plant).read().splitlines() if ln.startswith("  j2:")))
    cfg = _config_with_overrides(tmp_path, {})
    assert main(["sim", "--plant", plant, "--config", cfg]) == 2
    assert capsys.readouterr().err == (f"fftune: error: drive_sim: {plant}:{line}: plant.j2 = -3.0e-4: "
                                       f"out of range [1e-12, 1e+06]\n")


@needs_drive
@pytest.mark.parametrize("bad_in", ["base", "overrides"])
def test_sim_with_overrides_names_the_base_file_and_the_overrides(tmp_path, capsys, no_exec, bad_in):
    """The value out of range in the base file or in sim.overrides: either way the error names
    both, with the value drive_sim read (not /proc/self/fd/N and a line of the derived text)."""
    plant = _plant_with(tmp_path, "  j2: 2.0e-4 ", "  j2: -3.0e-4 ") if bad_in == "base" else PLANT
    overrides = {"plant": {"viscous": 3.0e-4}} if bad_in == "base" else {"plant": {"k": -2.0e7}}
    cfg = _config_with_overrides(tmp_path, overrides)
    assert main(["sim", "--plant", plant, "--config", cfg]) == 2
    err = capsys.readouterr().err
    key = "plant.j2 = -0.0003" if bad_in == "base" else "plant.k = -20000000.0"
    assert err.startswith(f"fftune: error: drive_sim: {plant} (with {cfg}: key 'sim.overrides' "
                          f"applied): {key}: out of range [")
    assert err.count("\n") == 1 and "/proc/self/fd" not in err


@needs_drive
def test_sim_machine_names_the_axis_whose_plant_overrides_are_out_of_range(tmp_path, capsys, no_exec):
    text = open(os.path.join(REPO, "configs", "machine_demo.yaml"), encoding="utf-8").read()
    old = "j1: 0.8e-4, coulomb: 4.0e-3"
    assert old in text
    machine = tmp_path / "m.yaml"
    machine.write_text(text.replace(old, "j1: 0.8e-4, coulomb: -4.0e-3", 1))
    axes = yaml.safe_load(machine.read_text())["axes"]
    name = next(a["name"] for a in axes if (a.get("plant_overrides") or {}).get("plant", {}).get("coulomb", 0) < 0)
    assert main(["sim", "--machine", str(machine)]) == 2
    err = capsys.readouterr().err
    assert f"(with {machine}: axis '{name}' plant_overrides applied): plant.coulomb = -0.004: out of range" in err
    assert err.startswith("fftune: error: drive_sim: ") and err.count("\n") == 1


@needs_drive
def test_demo_with_a_derived_plant_out_of_range_names_its_origin_and_writes_nothing(tmp_path, capsys):
    cfg = _config_with_overrides(tmp_path, {"plant": {"c": -2.0e-4}})
    out = tmp_path / "demo"
    assert main(["demo", "--config", cfg, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    # (the plant as the configuration's sim.plant names it: configs/plant_twomass.yaml)
    assert err.startswith("fftune: error: drive_sim: ") and err.count("\n") == 1
    assert f"plant_twomass.yaml (with {cfg}: key 'sim.overrides' applied): plant.c = -0.0002: out of range [" in err
    assert not out.exists()


def test_named_plant_error_rewrites_only_a_derived_plants_path(tmp_path):
    from fftune.host.sim import derived_plant, named_plant_error
    derived = derived_plant(PLANT, {"plant": {"k": 0.7}}, str(tmp_path / "plant.yaml"), where="X: key 'y'")
    assert named_plant_error(f"{derived}:19: plant.k = 0.7: out of range [1, 2]") == \
        f"{PLANT} (with X: key 'y' applied): plant.k = 0.7: out of range [1, 2]"
    assert named_plant_error(f"{derived}: cannot open: gone") == f"{PLANT} (with X: key 'y' applied): cannot open: gone"
    # a user's own file, a file that is not there, a message with no path: unchanged
    for message in (f"{PLANT}:19: plant.k = 0.7: out of range [1, 2]",
                    f"{tmp_path / 'missing.yaml'}:3: plant.k = 1: out of range [1, 2]",
                    "out of memory (recorder of 4 floats)"):
        assert named_plant_error(message) == message


@needs_drive
def test_drive_sim_check_loads_every_axis_and_opens_no_bus(tmp_path):
    from fftune.host.resources import drive_sim_path
    good = subprocess.run([drive_sim_path(), "--check", "--axis", f"1:{PLANT}", "--axis", f"2:{PLANT}"],
                          capture_output=True, text=True, timeout=30)
    assert (good.returncode, good.stdout, good.stderr) == (0, "", "")
    bad = _plant_with(tmp_path, "  k: 0.5 ", "  k: -0.5 ")
    refused = subprocess.run([drive_sim_path(), "--check", "--axis", f"1:{PLANT}", "--axis", f"2:{bad}"],
                             capture_output=True, text=True, timeout=30)
    assert refused.returncode == 2 and refused.stdout == ""
    assert refused.stderr.startswith(f"drive_sim: error: {bad}:") and "plant.k = -0.5: out of range" in refused.stderr
