"""The drive client against python-canopen's LocalNode as the peer (SDO server from the EDS
that firmware_sim/tools/odgen.py generates from configs/od.yaml), on python-can's virtual bus;
and the unreachable-drive error over socketcand. Runs against drive_sim itself are in
tests/test_host_drive_sim.py."""
import os
import socket
import subprocess
import sys
import time

import can
import canopen
import pytest

from fftune.analysis.errors import FftuneError
from fftune.host.cli import main
from fftune.host.drive import BusOptions, DriveClient
from fftune.host.odmap import PARAMS

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), os.pardir))


@pytest.fixture(scope="module")
def eds(tmp_path_factory):
    out = tmp_path_factory.mktemp("gen")
    subprocess.run([sys.executable, os.path.join(REPO, "firmware_sim", "tools", "odgen.py"),
                    os.path.join(REPO, "configs", "od.yaml"), str(out)], check=True,
                   capture_output=True)
    return str(out / "fftune_drive.eds")


@pytest.fixture
def peer(eds):
    """A LocalNode with the drive's EDS as node 1 on a fresh virtual channel."""
    channel = f"host-{time.monotonic_ns()}"
    net = canopen.Network()
    net.connect(interface="virtual", channel=channel, receive_own_messages=False)
    node = canopen.LocalNode(1, eds)
    net.add_node(node)
    yield channel, node
    net.disconnect()


def _client(channel, eds, node_id=1, **kw):
    kw.setdefault("heartbeat_ms", 0)
    return DriveClient(BusOptions(interface="virtual", channel=channel, node_id=node_id, eds=eds),
                       sdo_timeout_s=0.5, sdo_retries=1, progress=False, **kw)


def test_parameters_by_alias_and_by_eds_name_reach_the_node(peer, eds):
    channel, node = peer
    with _client(channel, eds) as drive:
        drive.set("kfc", 0.25)
        assert node.sdo[0x2000][4].raw == pytest.approx(0.25)
        drive.set("Controller.Viscous feed-forward K_v", 0.125)
        assert node.sdo[0x2000][5].raw == pytest.approx(0.125)
        assert drive.get("kv") == pytest.approx(0.125)
        ident = drive.identity()
        assert ident["vendor_id"] == 0xFF7 and ident["firmware_version"] == "0.1.0"
        params = drive.read_parameters()
        assert all(PARAMS[a].access != "wo" for a in params)   # write-only ones not read
        assert params["kfc"] == pytest.approx(0.25)


def test_sdo_abort_is_shown_with_its_meaning(peer, eds):
    channel, _ = peer
    with _client(channel, eds) as drive:
        with pytest.raises(FftuneError) as exc:
            drive.set("fs", 1000.0)                        # Controller rate is read-only
    msg = str(exc.value)
    assert "0x2000:08 'Controller.Controller rate'" in msg
    assert "SDO abort 0x06010002 (Attempt to write a read only object)" in msg


def test_unknown_parameter_name_is_named(peer, eds):
    channel, _ = peer
    with _client(channel, eds) as drive:
        with pytest.raises(FftuneError, match="no object named 'Controller.Kx' in the EDS"):
            drive.set("Controller.Kx", 1.0)


def test_wrong_node_id_names_the_nodes_that_answer(peer, eds):
    channel, _ = peer
    t = time.monotonic()
    with pytest.raises(FftuneError) as exc:
        _client(channel, eds, node_id=5).connect()
    assert time.monotonic() - t < 5
    msg = str(exc.value)
    assert "no SDO answer from node 5" in msg and f"channel {channel}" in msg
    assert "nodes answering on this bus: 1" in msg


def test_heartbeats_are_configured_both_ways(peer, eds):
    channel, node = peer
    spy = can.Bus(interface="virtual", channel=channel)
    try:
        with _client(channel, eds, heartbeat_ms=50, host_node_id=0x7E):
            assert node.sdo[0x1017].raw == 50
            assert node.sdo[0x1016][1].raw == (0x7E << 16) | 200
            t_end = time.monotonic() + 1.0
            beats = 0
            while time.monotonic() < t_end and beats < 3:
                msg = spy.recv(0.2)
                if msg is not None and msg.arbitration_id == 0x77E and bytes(msg.data) == b"\x05":
                    beats += 1
            assert beats >= 3
        # the consumer stays armed after close (issue 10 item 3): a host that dies without
        # closing must still be noticed by the drive
        assert node.sdo[0x1016][1].raw == (0x7E << 16) | 200
    finally:
        spy.shutdown()


def _closed_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_unreachable_drive_is_reported_within_5_s(eds, tmp_path, capsys):
    port = _closed_port()
    t = time.monotonic()
    code = main(["tune", "--port", str(port), "--eds", eds, "--out", str(tmp_path / "o"),
                 "--no-progress"])
    assert time.monotonic() - t < 5
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("fftune: error: drive not reachable: interface socketcand, channel can0 "
                          f"at 127.0.0.1:{port}")
    assert "Traceback" not in err


def test_config_error_is_one_line_with_exit_2(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("tune:\n  sweep: {points: 1}\n")
    code = main(["run", "--config", str(bad), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2
    assert err.strip() == (f"fftune: error: {bad}: key 'tune.sweep.points': expected 0 (no sweep) "
                           "or >= 3, got 1")


def test_unwritable_output_directory_is_refused_before_any_experiment(tmp_path, capsys, eds):
    blocker = tmp_path / "f"
    blocker.write_text("")
    port = _closed_port()                           # no drive: must not even be tried
    code = main(["run", "--out", str(blocker / "out"), "--port", str(port), "--eds", eds])
    err = capsys.readouterr().err
    assert code == 2
    assert "output directory" in err and "cannot create it" in err
    assert "drive not reachable" not in err
