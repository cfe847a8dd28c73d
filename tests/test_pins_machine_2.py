"""A machine's stop, status and bus pacing on drive_sim (host/machine.py; issue 33's
hand-written bug audit, docs/testing.md): an axis thread stuck past the machine's join
after Ctrl-C is still stopped and disabled by the machine itself (the last axis too), an
axis whose search does not converge is 'unconverged' with exit status 1, and the bus'
SDO pacer shares the heartbeat's period among the machine's axes. The drive_sim of
tests/test_machine.py (two nodes, 5 and 7); seconds each.
"""
import _thread
import signal
import struct
import threading
import time

import pytest
import yaml

from fftune.host import drive as _drive
from fftune.host.cli import main
from fftune.host.drive import BusOptions, DriveClient
from host_fixtures import EDS, drive_sim_missing_reason
from test_machine import SMALL, _machine_file, machine_sim  # noqa: F401  (the module's drive_sim)

pytestmark = pytest.mark.skipif(drive_sim_missing_reason() is not None,
                                reason=drive_sim_missing_reason() or "")


def _enabled(sim, nid):
    with DriveClient(BusOptions(port=sim.port, node_id=nid, eds=EDS), heartbeat_ms=0) as c:
        status = struct.unpack("<H", c.node.sdo.upload(0x6041, 0))[0]
        return status & 0x6F == 0x27, int(c.get("run_state"))


def test_ctrl_c_with_the_last_axis_stuck_the_machine_disables_it(machine_sim, tmp_path, monkeypatch):
    """Ctrl-C while the last axis' thread is stuck (it sees no cancel for longer than the
    machine's 10 s join): the machine stops and disables that drive itself before it
    returns (exit 130), not the axis' thread later. A 16 s consumer: within the test only
    fftune's cleanup can disable the drive."""
    sim, d = machine_sim
    no_hb = dict(SMALL, drive={"heartbeat_ms": 4000, "fs_hz": 2560.0})
    (d / "small_stuck.yaml").write_text(yaml.safe_dump(no_hb))
    f = _machine_file(d, [{"name": "a", "node_id": 5}, {"name": "b", "node_id": 7}], "m_stuck.yaml",
                      config="small_stuck.yaml")
    original = DriveClient.run
    a_running, release, fired = threading.Event(), threading.Event(), []

    def run(self, *args, **kw):
        if self.opts.node_id == 7:
            assert a_running.wait(30), "axis a never started a run"
            if not fired:
                fired.append(True)
                _thread.interrupt_main()            # Ctrl-C, both drives enabled
                release.wait(40)                    # stuck: no SDO request, no cancel seen
        else:
            a_running.set()
        return original(self, *args, **kw)
    monkeypatch.setattr(_drive.DriveClient, "run", run)
    sigint = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        code = main(["tune", "--machine", f, "--port", str(sim.port), "--out", str(tmp_path / "o"),
                     "--no-progress", "--no-figures"])
        # main() has returned, axis b's thread still waits in its run: only the machine's own
        # cleanup can have left node 7 disabled by now
        assert any(t.name == "fftune-axis-b" and t.is_alive() for t in threading.enumerate())
        state = {nid: _enabled(sim, nid) for nid in (5, 7)}
    finally:
        signal.signal(signal.SIGINT, sigint)
        release.set()
        deadline = time.monotonic() + 30
        while any(t.name.startswith("fftune-axis-") and t.is_alive() for t in threading.enumerate()) \
                and time.monotonic() < deadline:
            time.sleep(0.05)
    assert fired and code == 130
    for nid, (enabled, run_state) in state.items():
        assert not enabled, f"node {nid} still OPERATION ENABLED after the machine returned"
        assert run_state not in (1, 2), (nid, run_state)


def test_an_unconverged_axis_is_reported_and_exits_1(machine_sim, tmp_path, capsys):
    """Axis a's search may take 3 experiments (too few to converge), axis b the small
    configuration's 8: a is 'unconverged' (its stop reason the error), b 'ok', exit 1."""
    sim, d = machine_sim
    f = _machine_file(d, [{"name": "a", "node_id": 5,
                           "overrides": {"tune": {"search": {"max_experiments": 3}}}},
                          {"name": "b", "node_id": 7}], "m_unconv.yaml")
    out = tmp_path / "o"
    code = main(["tune", "--machine", f, "--port", str(sim.port), "--out", str(out), "--no-progress",
                 "--no-figures"])
    text = capsys.readouterr()
    summary = yaml.safe_load((out / "results.yaml").read_text())
    by = {a["name"]: a for a in summary["axes"]}
    own = yaml.safe_load((out / "a" / "results.yaml").read_text())["tune"]["search"]
    assert own["converged"] is False and own["stop_reason"]
    assert (by["a"]["status"], by["a"]["converged"], by["a"]["error"]) == \
        ("unconverged", False, f"not converged: {own['stop_reason']}")
    assert (by["b"]["status"], by["b"]["converged"], by["b"]["error"]) == ("ok", True, None)
    assert code == 1, text.out + text.err
    line = [ln for ln in text.out.splitlines() if ln.startswith("  a ")]
    assert len(line) == 1 and " unconverged " in line[0], text.out


def test_the_sdo_pacer_shares_the_heartbeat_period_among_the_axes(machine_sim, tmp_path, monkeypatch):
    """At 20 kbit/s with a 100 ms heartbeat and three axes, the bus' pacer lets
    floor(1.5 x 100 ms / (3 x one 8-byte frame)) SDO frames go back to back; the frame
    (CAN 2.0A, 8 data bytes, worst-case stuffing, interframe space) is 135 bit times. The
    axes' nodes are absent (each fails at its probe): the pacer is made before them."""
    from fftune.host import machine as mc

    sim, d = machine_sim
    bursts = []
    pacer_init = _drive._SdoPacer.__init__

    def spy(self, network, bitrate, burst):
        bursts.append((bitrate, burst))
        pacer_init(self, network, bitrate, burst)
    monkeypatch.setattr(_drive._SdoPacer, "__init__", spy)
    fast = {"drive": {"sdo_timeout_s": 0.3, "sdo_retries": 1}}
    f = _machine_file(d, [{"name": n, "node_id": nid, "overrides": fast}
                          for n, nid in (("p", 21), ("q", 22), ("r", 23))], "m_pace.yaml")
    machine = mc.load_machine(f)
    opts = BusOptions(interface="socketcand", channel="can0", host=sim.host, port=sim.port, node_id=21,
                      eds=EDS, model_bitrate=20000)
    summary = mc.run_machine(machine, opts, str(tmp_path / "o"), figures=False, log=lambda s: None,
                             log_error=lambda s: None)
    assert [a["status"] for a in summary["axes"]] == ["failed"] * 3
    # SOF, id, RTR, IDE, r0, DLC, data, CRC, delimiters, ACK, EOF, IFS; 24 stuff bits at most
    frame_s = (1 + 11 + 1 + 1 + 1 + 4 + 64 + 15 + 1 + 1 + 1 + 7 + 3 + 24) / 20000.0  # 135 bits
    want = int(1.5 * 0.100 / (3 * frame_s))          # 150 ms / 20.25 ms: 7 (one axis alone: 22)
    assert want == 7
    assert bursts == [(20000, want)]
