"""The host leaves the drive safe on every exit path (issue 10, item 3).

A real ``fftune run`` against ``drive_sim --realtime`` (so a run lasts seconds, as on a
real drive) is interrupted while the drive is exciting:

- SIGINT (Ctrl-C) and SIGTERM: fftune exits 130 / 143 with one line; afterwards the run is
  not active (stopped by the host's abort command or the disable) and the drive is
  disabled (CiA 402 power stage off), read with python-canopen as the peer; the heartbeat
  consumer 0x1016 is still armed.
- SIGKILL (no cleanup at all): the armed consumer stops the run within its time.
- An exception inside the client's ``with`` block during a run: the same safe state.

The observer watches the run state in the drive's TPDO (0x280 + node: run state, progress)
while the host runs, so that it never competes with the host for the one SDO channel; it
reads by SDO only after the host is gone.
"""
import os
import signal
import struct
import subprocess
import sys
import time

import pytest
import yaml

from fftune.host.drive import BusOptions, DriveClient, quiet_can_loggers
from test_reliability_support import EDS, REPO, needs_drive, start_drive

pytestmark = needs_drive

RUN_ACTIVE = (1, 2)        # settling, recording
STATUS_POWER_MASK = 0x006F
READY_TO_SWITCH_ON = 0x0021
SWITCH_ON_DISABLED = 0x0040
OPERATION_ENABLED = 0x0027


class Observer:
    """A python-canopen peer: the run state from TPDO 0x280+1 and, later, SDO reads."""

    def __init__(self, port):
        import canopen
        quiet_can_loggers()
        self.net = canopen.Network()
        self.net.connect(interface="socketcand", channel="can0", host="127.0.0.1", port=port)
        self.node = canopen.RemoteNode(1, EDS)
        self.net.add_node(self.node)
        self.node.sdo.RESPONSE_TIMEOUT = 1.0
        self.states = []
        self.net.subscribe(0x281, lambda cob, data, ts: self.states.append(data[0]))

    def wait_for_active_run(self, proc, timeout_s=60.0):
        deadline = time.monotonic() + timeout_s
        while not (self.states and self.states[-1] in RUN_ACTIVE):
            assert proc.poll() is None, f"fftune ended before a run started: {proc.stderr.read()}"
            assert time.monotonic() < deadline, "no active run seen within the timeout"
            time.sleep(0.01)

    def u(self, index, sub):
        return int.from_bytes(self.node.sdo.upload(index, sub), "little")

    def close(self):
        self.net.disconnect()


def _config(tmp_path):
    cfg = yaml.safe_load(open(os.path.join(REPO, "configs", "demo.yaml")))
    cfg["detect"].update(rms_levels=[0.3], realizations=2, settle_periods=20)  # runs of ~9 s
    path = tmp_path / "cleanup.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return str(path)


def _fftune_run(tmp_path, port):
    return subprocess.Popen(
        [sys.executable, "-m", "fftune.host.cli", "run", "--config", _config(tmp_path),
         "--out", str(tmp_path / "out"), "--port", str(port), "--no-progress", "--no-figures"],
        cwd=REPO, env=dict(os.environ, PYTHONPATH=REPO), stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True)


def _tpdo_shows_stop(obs, within_s=0.15):
    deadline = time.monotonic() + within_s
    while time.monotonic() < deadline:
        if obs.states and obs.states[-1] not in RUN_ACTIVE:
            return True
        time.sleep(0.005)
    return False


def _assert_stopped_and_disabled(obs):
    state = obs.u(0x2010, 2)
    assert state not in RUN_ACTIVE, f"the run goes on after the host left (state {state})"
    # stop reason 1 (abort command) or 3 (disabled): the host's doing, not the watchdog's
    assert obs.u(0x2010, 5) in (1, 3), f"stop reason {obs.u(0x2010, 5)}"
    status = obs.u(0x6041, 0) & STATUS_POWER_MASK
    assert status in (READY_TO_SWITCH_ON, SWITCH_ON_DISABLED), f"statusword 0x{status:04X}: not disabled"
    consumer = obs.u(0x1016, 1)
    assert consumer >> 16 == 0x7F and consumer & 0xFFFF == 400, \
        f"heartbeat consumer 0x{consumer:08X}: no longer armed for the host"


@pytest.mark.parametrize("sig, code, line", [(signal.SIGINT, 130, "fftune: interrupted"),
                                             (signal.SIGTERM, 143, "fftune: terminated")])
def test_interrupted_run_leaves_the_drive_stopped_and_disabled(tmp_path, sig, code, line):
    drive = start_drive(tmp_path, "--realtime")
    obs = Observer(drive.port)
    host = _fftune_run(tmp_path, drive.port)
    try:
        obs.wait_for_active_run(host)
        time.sleep(0.3)
        host.send_signal(sig)
        t_sig = time.monotonic()
        _, err = host.communicate(timeout=20)
        t_exit = time.monotonic() - t_sig
        assert host.returncode == code, err
        assert err.strip().splitlines()[-1] == line, err
        assert "Traceback" not in err, err
        # the host stopped it itself before it exited (not the 400 ms watchdog after it
        # left): the stop shows in the TPDO within its 50 ms inhibit time
        assert _tpdo_shows_stop(obs), f"TPDO run states {obs.states[-5:]}"
        _assert_stopped_and_disabled(obs)
        print(f"{signal.Signals(sig).name}: fftune exited {t_exit * 1000:.0f} ms after the signal")
    finally:
        if host.poll() is None:
            host.kill()
        obs.close()
        drive.stop()


def test_killed_host_is_stopped_by_the_armed_consumer(tmp_path):
    drive = start_drive(tmp_path, "--realtime")
    obs = Observer(drive.port)
    host = _fftune_run(tmp_path, drive.port)
    try:
        obs.wait_for_active_run(host)
        host.send_signal(signal.SIGKILL)
        t_kill = time.monotonic()
        host.wait(5)
        while obs.states[-1] in RUN_ACTIVE:
            assert time.monotonic() - t_kill < 3.0, "the run went on without the host"
            time.sleep(0.005)
        t_stop = time.monotonic() - t_kill
        assert obs.u(0x2010, 2) == 4  # aborted
        assert obs.u(0x2010, 5) == 2  # host heartbeat lost
        assert t_stop <= 0.4 + 0.15, f"stopped {t_stop * 1000:.0f} ms after the kill"
        print(f"SIGKILL: run stopped {t_stop * 1000:.0f} ms after the kill (consumer 400 ms)")
    finally:
        if host.poll() is None:
            host.kill()
        obs.close()
        drive.stop()


def test_exception_during_a_run_leaves_the_drive_safe(tmp_path, monkeypatch):
    drive = start_drive(tmp_path, "--realtime")
    obs = Observer(drive.port)
    quiet_can_loggers()
    client = DriveClient(BusOptions(port=drive.port, eds=EDS), heartbeat_ms=100, progress=False)
    calls = []

    def failing_check():  # the host's own failure in the middle of waiting for a run
        calls.append(1)
        if len(calls) > 5:
            raise RuntimeError("host bug")
    monkeypatch.setattr(client, "_check_heartbeat", failing_check)
    try:
        with pytest.raises(RuntimeError, match="host bug"):
            with client:
                client.enable()
                client.run(dict(exc_kind=1, exc_inject=0, exc_amplitude=0.3, exc_period=2048,
                                exc_sine_cycles=2, exc_settle_periods=20, exc_record_periods=1))
        assert _tpdo_shows_stop(obs), obs.states[-5:]
        _assert_stopped_and_disabled(obs)
    finally:
        client.close()
        obs.close()
        drive.stop()


def test_close_without_enable_touches_nothing(tmp_path):
    """A session that only read (no enable, no run) does not disable a drive that someone
    else enabled."""
    drive = start_drive(tmp_path)
    obs = Observer(drive.port)
    try:
        from canopen_helpers import enable_402
        obs.net.nmt.state = "OPERATIONAL"
        enable_402(obs.node)
        assert obs.u(0x6041, 0) & STATUS_POWER_MASK == OPERATION_ENABLED
        with DriveClient(BusOptions(port=drive.port, eds=EDS), heartbeat_ms=0, progress=False) as c:
            c.get("fs")
        assert obs.u(0x6041, 0) & STATUS_POWER_MASK == OPERATION_ENABLED
    finally:
        obs.close()
        drive.stop()
