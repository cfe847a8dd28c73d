"""drive_sim --axis: several nodes in one process behind ONE bus model (firmware_sim/port).

At 125 kbit/s a data frame of 8 bytes occupies the bus for about 1 ms. Two SDO requests,
to node 5 and to node 7, sent back to back: on one bus the answers follow each other (and
the second request) in bus order, each a frame time apart; a bus model per node would
deliver both answers one frame time after their requests, overlapping. Each node answers
with its own object dictionary and plant (unequal Coulomb levels in 0x2100).
"""
import os
import struct

import can
import pytest

from fftune.host.sim import derived_plant, start_drive_sim
from host_fixtures import REPO, drive_sim_missing_reason

pytestmark = pytest.mark.skipif(drive_sim_missing_reason() is not None,
                                reason=drive_sim_missing_reason() or "")
TWOMASS = os.path.join(REPO, "configs", "plant_twomass.yaml")
BITRATE = 125_000


def _frame_s(n_data):
    """The shortest duration of a classic 11-bit data frame on the bus (no stuff bits)."""
    return (44 + 8 * n_data + 3) / BITRATE


def test_two_nodes_answer_in_bus_order_on_one_bus_model(tmp_path):
    p5 = derived_plant(TWOMASS, {"plant": {"coulomb": 5.0e-3, "static": 5.0e-3}}, str(tmp_path / "p5.yaml"))
    p7 = derived_plant(TWOMASS, {"plant": {"coulomb": 9.0e-3, "static": 9.0e-3}}, str(tmp_path / "p7.yaml"))
    sim = start_drive_sim(TWOMASS, bitrate=BITRATE, log_path=str(tmp_path / "drive_sim.log"),
                          extra=["--axis", f"5:{p5}", "--axis", f"7:{p7}"])
    try:
        with can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port) as bus:
            got = {}
            # 0x2100:1 (simulated Coulomb level, float32) of both nodes, back to back
            for nid in (5, 7):
                bus.send(can.Message(arbitration_id=0x600 + nid, is_extended_id=False,
                                     data=[0x40, 0x00, 0x21, 0x01, 0, 0, 0, 0]))
            while len(got) < 2:
                msg = bus.recv(5.0)
                assert msg is not None, f"answers seen: {sorted(got)}"
                if msg.arbitration_id in (0x585, 0x587):
                    got[msg.arbitration_id - 0x580] = msg
    finally:
        sim.stop()
    km = 0.05   # plant_twomass.yaml: N m per V
    for nid, fc in ((5, 5.0e-3), (7, 9.0e-3)):
        assert got[nid].data[0] == 0x43
        assert struct.unpack("<f", bytes(got[nid].data[4:8]))[0] == pytest.approx(fc / km, rel=1e-5)
    # bus order: answer 5 (0x585 wins arbitration over request 0x607), request 7, answer 7
    gap = got[7].timestamp - got[5].timestamp
    assert gap >= 2 * _frame_s(8) * 0.999, gap
    with open(tmp_path / "drive_sim.log") as fh:
        log = fh.read()
    assert f"at {BITRATE} bit/s" in log and "0 dropped at full queues" in log


def test_fftune_sim_serves_a_machine_file(tmp_path):
    """`fftune sim --machine FILE`: drive_sim with one node per axis (plants with overrides
    handed over in memory, nothing written); the readiness line names the nodes, each node
    answers with its own plant."""
    import subprocess
    import sys

    import yaml

    f = tmp_path / "m.yaml"
    f.write_text(yaml.safe_dump({"machine": "s", "output": str(tmp_path / "out"), "axes": [
        {"name": "a", "node_id": 12, "plant": TWOMASS},
        {"name": "b", "node_id": 3, "plant": TWOMASS,
         "plant_overrides": {"plant": {"coulomb": 8.0e-3, "static": 8.0e-3}}}]}))
    fftune = os.path.join(os.path.dirname(sys.executable), "fftune")
    proc = subprocess.Popen([fftune, "sim", "--machine", str(f), "--port", "0", "-i", "socketcand"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert "listening on socketcand 127.0.0.1:" in line and line.rstrip().endswith(", nodes 12,3"), line
        port = int(line.split("127.0.0.1:")[1].split(",")[0])
        fc = {}
        with can.Bus(interface="socketcand", channel="can0", host="127.0.0.1", port=port) as bus:
            for nid in (12, 3):      # 0x2100:1, the simulated Coulomb level (V)
                bus.send(can.Message(arbitration_id=0x600 + nid, is_extended_id=False,
                                     data=[0x40, 0x00, 0x21, 0x01, 0, 0, 0, 0]))
            while len(fc) < 2:
                msg = bus.recv(5.0)
                assert msg is not None, f"answers seen: {sorted(fc)}"
                if msg.arbitration_id in (0x580 + 12, 0x580 + 3):
                    fc[msg.arbitration_id - 0x580] = struct.unpack("<f", bytes(msg.data[4:8]))[0]
    finally:
        proc.terminate()
        proc.wait(10)
    assert fc[12] == pytest.approx(5.785e-3 / 0.05, rel=1e-5)     # plant_twomass.yaml as it is
    assert fc[3] == pytest.approx(8.0e-3 / 0.05, rel=1e-5)        # with its plant_overrides
    assert not (tmp_path / "out").exists()                        # nothing written
