"""One safety envelope for every entry point (issue 30).

The probes of the issue, each one a test:

- every file a user gives (configuration, machine file, axis configuration, track
  configuration, plant, capture) goes through one loader: an alias bomb, deep nesting, a
  non-UTF-8 byte, NUL bytes, a wrong type, a directory, an oversized file: one ``fftune:
  error:`` line naming the file and key, exit 2, nothing written, no traceback; ``1e-3`` is a
  number through every entry point; a machine's name never leaves the output folder;
- every command that moves an axis has the same preflight (``limits:``, the drive's limits,
  the heartbeat) before the first motion, track's task and check included;
- no drive is enabled without an armed consumer for the heartbeat this host sends: one host
  id and period per bus, a host id in use by another producer refused, the SDO bursts
  bounded by the heartbeat at low bit rates; after SIGKILL of the host in each accepted
  configuration every axis leaves OPERATION ENABLED within its consumer time.

The drive's timestamps are the bus server's (drive_sim's socketcand), not this process'.
"""
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import yaml

from canopen_helpers import HOST_LOST_BOUND_S, HOST_LOST_CONSUMER_S
from fftune.analysis.errors import FftuneError, InputError
from fftune.host.cli import main
from host_fixtures import EDS, REPO, drive_sim_missing_reason

needs_drive = pytest.mark.skipif(drive_sim_missing_reason() is not None,
                                 reason=drive_sim_missing_reason() or "")

OPERATION_ENABLED = 0x0027
STATUS_POWER_MASK = 0x006F
TWOMASS = os.path.join(REPO, "configs", "plant_twomass.yaml")
# a small tune step (as tests/test_machine.py): in real time each run lasts 6.4 s
SMALL = {
    "output": "out/unused",
    "drive": {"heartbeat_ms": 100, "fs_hz": 2560.0},
    "detect": {"enabled": False, "encoder_step_rad": 0.0031415926535897933}, "quantify": {"enabled": False},
    "tune": {"frequency_hz": 0.625, "amplitude_rad": 0.5, "period_samples": 4096, "periods": 2,
             "settle_periods": 2, "harmonics": 7, "capture": "stats",
             "sweep": {"k_fc_max": 0.3, "points": 0}, "search": {"method": "root", "max_experiments": 8},
             "viscous": {"enabled": False}},
}


def _one_error_line(capsys, *needles):
    """stderr holds exactly one ``fftune: error:`` line, no traceback; it names every needle."""
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("fftune: error: "), err
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


def _write(path, text):
    path.write_text(text) if isinstance(text, str) else path.write_bytes(text)
    return str(path)


# ---------------------------------------------------------------------------------------
# one loader for every file a user gives
# ---------------------------------------------------------------------------------------
ALIAS_BOMB = ("a: &a [x, x, x, x, x, x, x, x, x]\n"
              + "".join(f"{c}: &{c} [*{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}]\n"
                        for p, c in zip("abcdefgh", "bcdefghi")))


def _machine(tmp_path, body, name="m.yaml"):
    (tmp_path / "small.yaml").write_text(yaml.safe_dump(SMALL))
    return _write(tmp_path / name, body)


MACHINE_PROBES = {
    "alias bomb": (ALIAS_BOMB, ("more than 100000 YAML nodes",)),
    "deep nesting": ("axes: " + "[" * 200 + "]" * 200 + "\n", ("nested deeper than 32",)),
    "non-UTF-8 byte": (b"machine: t\naxes: []\n# \xff\n", ("not UTF-8 text (byte 22)",)),
    "NUL bytes": (b"\0" * 64, ("a NUL byte at offset 0",)),
    "output: 5": ("output: 5\nconfig: small.yaml\naxes: [{name: x, node_id: 3}]\n", ("key 'output'", "got 5")),
    "config: [a, b]": ("config: [a, b]\naxes: [{name: x, node_id: 3}]\n", ("key 'config'", "got ['a', 'b']")),
    "axes[0].plant: 5": ("config: small.yaml\naxes: [{name: x, node_id: 3, plant: 5}]\n",
                         ("axes[0]: key 'plant': expected a file name, got 5",)),
    "axes[0].overrides: 5": ("config: small.yaml\naxes: [{name: x, node_id: 3, overrides: 5}]\n",
                             ("axes[0].overrides", "got 5")),
    "plant_overrides not numbers": ("config: small.yaml\naxes: [{name: x, node_id: 3, "
                                    "plant_overrides: {plant: 5}}]\n",
                                    ("axes[0].plant_overrides", "got 5")),
    "machine: ../../escaped": ("machine: ../../escaped\nconfig: small.yaml\naxes: [{name: x, node_id: 3}]\n",
                               ("key 'machine'", "'../../escaped'")),
    "axis name with a slash": ("config: small.yaml\naxes: [{name: ../x, node_id: 3}]\n", ("axes[0].name",)),
    "node id of 23 digits": ("config: small.yaml\naxes: [{name: x, node_id: 12345678901234567890123}]\n",
                             ("axes[0].node_id", "1 .. 127")),
    "config a directory": ("config: sub\naxes: [{name: x, node_id: 3}]\n", ("key 'config'", "is a directory")),
    "axis heartbeat differs": ("config: small.yaml\naxes: [{name: x, node_id: 3},\n"
                               "  {name: y, node_id: 4, overrides: {drive: {heartbeat_ms: 1000}}}]\n",
                               ("axes[1] 'y': key 'drive.heartbeat_ms': 1000 differs from 100 of axes[0] 'x'",)),
    "axis host id differs": ("config: small.yaml\naxes: [{name: x, node_id: 3},\n"
                             "  {name: y, node_id: 4, overrides: {drive: {host_node_id: 100}}}]\n",
                             ("axes[1] 'y': key 'drive.host_node_id': 100 differs from 127",)),
    "host id of an axis": ("config: small.yaml\noverrides: {drive: {host_node_id: 4}}\n"
                           "axes: [{name: x, node_id: 3}, {name: y, node_id: 4}]\n",
                           ("axes[1]", "key 'drive.host_node_id': must differ from drive.node_id")),
    "heartbeat 0": ("config: small.yaml\noverrides: {drive: {heartbeat_ms: 0}}\naxes: [{name: x, node_id: 3}]\n",
                    ("axis 'x'", "key 'drive.heartbeat_ms': 0 (no host heartbeat)")),
}


@pytest.mark.parametrize("probe", sorted(MACHINE_PROBES))
def test_machine_file_probe_is_one_line_and_nothing_written(tmp_path, capsys, monkeypatch, probe):
    body, needles = MACHINE_PROBES[probe]
    (tmp_path / "sub").mkdir()
    f = _machine(tmp_path, body)
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "out"
    assert main(["tune", "--machine", f, "--out", str(out), "--port", "1", "--no-progress"]) == 2
    _one_error_line(capsys, *needles)
    assert not out.exists() and not (tmp_path.parent / "escaped").exists()


def test_an_oversized_axis_configuration_is_refused_unparsed(tmp_path, capsys):
    big = tmp_path / "big.yaml"
    big.write_text("# padding\n" * 200_000)     # 2 MB of comments: valid YAML, too large
    f = _machine(tmp_path, "axes: [{name: x, node_id: 3, config: big.yaml}]\n")
    assert main(["tune", "--machine", f, "--out", str(tmp_path / "o"), "--port", "1"]) == 2
    _one_error_line(capsys, "axes[0].config", "2000000 bytes", "at most 1048576")


def test_one_number_parsing_through_every_entry_point(tmp_path):
    """``1e-3`` (YAML 1.2's float, a string to PyYAML's 1.1) is a number through load_config,
    a machine file, an axis configuration and a track configuration alike."""
    from fftune.host.config import load_config
    from fftune.host.machine import load_machine
    from fftune.host.track import load_track_config

    cfg = dict(SMALL, tune=dict(SMALL["tune"], search={"method": "root", "xtol_v": "XTOL"}))
    text = yaml.safe_dump(cfg).replace("XTOL", "1e-3").replace("'1e-3'", "1e-3")
    (tmp_path / "c.yaml").write_text(text)
    assert load_config(str(tmp_path / "c.yaml"))["tune"]["search"]["xtol_v"] == 0.001
    f = _write(tmp_path / "m.yaml", "config: c.yaml\noverrides: {tune: {search: {k_fc_max: 2e-1}}}\n"
                                    "axes: [{name: x, node_id: 3}, {name: y, node_id: 4e0, config: c.yaml,\n"
                                    "        overrides: {tune: {search: {xtol_v: 5e-4}}}}]\n")
    m = load_machine(f)
    assert [a["cfg"]["tune"]["search"]["xtol_v"] for a in m["axes"]] == [0.001, 0.0005]
    assert [a["cfg"]["tune"]["search"]["k_fc_max"] for a in m["axes"]] == [0.2, 0.2]
    assert [a["node_id"] for a in m["axes"]] == [3, 4] and isinstance(m["axes"][1]["node_id"], int)
    t = _write(tmp_path / "t.yaml", "track: {write_deadband_rel: 1e-3, task: {v_max: 3e0}}\n")
    tc = load_track_config(t)
    assert tc["track"]["write_deadband_rel"] == 0.001 and tc["track"]["task"]["v_max"] == 3.0


@pytest.mark.parametrize("body, needles", [
    (ALIAS_BOMB, ("more than 100000 YAML nodes",)),
    (b"track: {tasks: 3}\n\xfe\n", ("not UTF-8 text",)),
    ("drive: {heartbeat_ms: 65535}\n", ("key 'drive.heartbeat_ms'", "<= 16383")),
    ("drive: {heartbeat_ms: 0}\n", ("key 'drive.heartbeat_ms': 0 (no host heartbeat)",)),
    ("drive: {host_node_id: 1}\n", ("key 'drive.host_node_id': must differ from drive.node_id",)),
    ("sim: {plant: 5}\n", ("key 'sim.plant': expected a file name, got 5",)),
    ("sim: {overrides: {plant: 5}}\n", ("key 'sim.overrides.plant': expected a mapping {key: number}, got 5",)),
    ("sim: {overrides: {plant: {coulomb: [1]}}}\n", ("key 'sim.overrides.plant.coulomb': expected a finite number",)),
    ("track: {check: {enabled: true, amplitude_rad: 30}}\n",
     ("key 'track.check.amplitude_rad'", "30 rad peak is above 8 rad (limits.max_amplitude_rad)")),
    ("track: {check: {enabled: true, frequency_hz: 2.5, amplitude_rad: 1000}}\n",
     ("key 'track.check.amplitude_rad'",)),
    ("track: {check: {enabled: true, frequency_hz: 100, amplitude_rad: 2}}\n",
     ("key 'track.check.amplitude_rad'", "peak velocity", "limits.max_velocity_rad_s")),
    ("drive: {fs_hz: 2560}\ntrack: {check: {enabled: true, frequency_hz: 5000}}\n",
     ("key 'track.check.frequency_hz': 5000 Hz is at or above fs/2 = 1280 Hz",)),
    ("track: {task: {distance_rad: 1000}}\n", ("key 'track.task.distance_rad'", "limits.max_amplitude_rad")),
    ("limits: {max_velocity_rad_s: 3}\ntrack: {task: {v_max: 4}}\n",
     ("key 'track.task.v_max'", "4 rad/s", "above 3 rad/s")),
])
def test_track_probe_is_refused_before_the_drive_is_contacted(tmp_path, capsys, body, needles):
    f = _write(tmp_path / "t.yaml", body)
    out = tmp_path / "o"
    assert main(["track", "--config", f, "--port", "1", "--out", str(out), "--no-progress"]) == 2
    _one_error_line(capsys, *needles)
    assert not out.exists()


@pytest.mark.parametrize("what", ["directory", "nul", "heartbeat0"])
def test_run_config_probes(tmp_path, capsys, what):
    if what == "directory":
        f, needles = str(tmp_path), ("is a directory",)
    elif what == "nul":
        f, needles = _write(tmp_path / "c.yaml", b"output: x\n\0\n"), ("a NUL byte at offset 10",)
    else:
        f = _write(tmp_path / "c.yaml", yaml.safe_dump(dict(SMALL, drive={"heartbeat_ms": 0})))
        needles = ("key 'drive.heartbeat_ms': 0 (no host heartbeat)",)
    assert main(["tune", "--config", f, "--port", "1", "--out", str(tmp_path / "o")]) == 2
    _one_error_line(capsys, *needles)


def test_plant_file_probes(tmp_path):
    from fftune.host.sim import derived_plant_text, start_drive_sim

    with pytest.raises(FftuneError, match="is a directory, expected a file"):
        derived_plant_text(str(tmp_path), {})
    with pytest.raises(FftuneError, match="more than 100000 YAML nodes"):
        derived_plant_text(_write(tmp_path / "p.yaml", ALIAS_BOMB), {})
    with pytest.raises(FftuneError, match=r"sim.overrides.plant.coulomb: expected a finite number, got \[1, 2\]"):
        derived_plant_text(TWOMASS, {"plant": {"coulomb": [1, 2]}})
    with pytest.raises(FftuneError, match="is a directory, expected a file"):
        start_drive_sim(str(tmp_path))


@needs_drive
@pytest.mark.parametrize("option", ["--config", "--axis"])
def test_drive_sim_refuses_a_directory_for_a_plant(tmp_path, option):
    from fftune.host.resources import drive_sim_path

    arg = str(tmp_path) if option == "--config" else f"1:{tmp_path}"
    p = subprocess.run([drive_sim_path(), option, arg, "--port", "0"], capture_output=True, text=True,
                       timeout=20)
    assert p.returncode == 2
    assert p.stderr.splitlines() == [f"drive_sim: error: {tmp_path}: not a regular file (a directory)"]
    assert p.stdout == ""


# ---------------------------------------------------------------------------------------
# captures: shape, dtype and declared size before reading
# ---------------------------------------------------------------------------------------
def _forged_capture(path, n_period, record_periods, dtype="<f4", write=None):
    import h5py

    with h5py.File(path, "w") as f:
        f.attrs["format"] = "fftune-capture"
        f.attrs["format_version"] = 1
        f.attrs["fs_hz"] = 2560.0
        f.attrs["n_period"] = n_period
        f.attrs["settle_periods"] = 0
        f.attrs["record_periods"] = record_periods
        f.attrs["experiment"] = "detect"
        ds = f.create_dataset("plant_input", shape=(n_period * record_periods,), dtype=dtype)
        if write is not None:
            ds[...] = write
    return path


@pytest.mark.parametrize("periods, dtype, needle", [
    (18311, "<f4", "declares 150003712 samples a signal"),      # 600 MB declared in a few kB
    (500, "<f4", "declares 16384000 bytes, the file stores 0"),   # within the limit, not stored
    (1, "<i4", "has dtype int32, expected float32"),
])
def test_a_forged_capture_is_refused_before_its_data_is_read(tmp_path, monkeypatch, periods, dtype, needle):
    import h5py

    from fftune.analysis.capture import read_run

    path = _forged_capture(str(tmp_path / "c.h5"), 8192, periods, dtype)
    assert os.path.getsize(path) < 10_000
    read = []
    original = h5py.Dataset.__getitem__
    monkeypatch.setattr(h5py.Dataset, "__getitem__", lambda self, key: read.append(key) or original(self, key))
    with pytest.raises(InputError, match=needle):
        read_run(path)
    assert read == []                   # refused before any dataset was read


def test_a_true_capture_still_reads(tmp_path):
    from fftune.analysis.capture import read_run

    x = np.linspace(-1.0, 2.0, 64, dtype=np.float32)
    path = _forged_capture(str(tmp_path / "c.h5"), 32, 2, write=x)
    np.testing.assert_array_equal(read_run(path).signals["plant_input"], x)


# ---------------------------------------------------------------------------------------
# the host heartbeat at low bit rates
# ---------------------------------------------------------------------------------------
def test_sdo_bursts_are_bounded_by_the_heartbeat():
    from fftune.host.drive import frame_bits, sdo_burst_frames

    # 135 bits a frame (8 data bytes, worst-case stuffing): 1.5 periods of the heartbeat
    assert frame_bits(8) == 47 + 64 + 24
    assert sdo_burst_frames(20_000, 100) == int(0.15 / (135 / 20_000)) == 22
    assert sdo_burst_frames(20_000, 100, nodes=4) == int(0.15 / (4 * 135 / 20_000)) == 5
    assert sdo_burst_frames(1_000_000, 100) == 127 and sdo_burst_frames(None, 100) == 127
    with pytest.raises(FftuneError, match="bit rate 10000 bit/s with drive.heartbeat_ms 10: one SDO frame"):
        sdo_burst_frames(10_000, 10, nodes=2)


# ---------------------------------------------------------------------------------------
# SIGKILL of the host in every accepted configuration: every axis leaves OPERATION ENABLED
# within its consumer time
# ---------------------------------------------------------------------------------------
CONSUMER_S, BOUND_S = HOST_LOST_CONSUMER_S, HOST_LOST_BOUND_S   # (canopen_helpers: why)


class BusWatch:
    """A passive python-canopen peer: each node's statusword TPDO (0x180 + id) and the host's
    heartbeat (0x77F), with the bus server's time stamps."""

    def __init__(self, port, nodes):
        import canopen

        from fftune.host.drive import quiet_can_loggers
        quiet_can_loggers()
        self.net = canopen.Network()
        self.net.connect(interface="socketcand", channel="can0", host="127.0.0.1", port=port)
        self.status = {n: [] for n in nodes}
        self.host_hb = []
        for n in nodes:
            self.net.subscribe(0x180 + n, lambda cob, data, ts, n=n:
                               self.status[n].append((ts, data[0] | data[1] << 8)))
        self.net.subscribe(0x77F, lambda cob, data, ts: self.host_hb.append(ts))
        self.sdo_frames = []        # (time stamp, COB-ID) of every SDO frame (0x580/0x600 + id)
        for n in nodes:
            for cob in (0x580 + n, 0x600 + n):
                self.net.subscribe(cob, lambda cob, data, ts: self.sdo_frames.append((ts, cob)))

    def enabled(self, n):
        return bool(self.status[n]) and self.status[n][-1][1] & STATUS_POWER_MASK == OPERATION_ENABLED

    def ever_enabled(self, n):
        return any(sw & STATUS_POWER_MASK == OPERATION_ENABLED for _, sw in self.status[n])

    def wait(self, cond, timeout_s, what, proc=None):
        deadline = time.monotonic() + timeout_s
        while not cond():
            if proc is not None and proc.poll() is not None:
                pytest.fail(f"{what}: the host ended first: {proc.communicate()[1][-3000:]}")
            assert time.monotonic() < deadline, f"{what}: not within {timeout_s:g} s"
            time.sleep(0.01)

    def off_after_host_lost(self, n, timeout_s=10.0):
        """The delay from the host's last heartbeat to the first statusword TPDO of node n
        that shows it left OPERATION ENABLED."""
        self.wait(lambda: not self.enabled(n), timeout_s, f"node {n} leaving OPERATION ENABLED")
        log = list(self.status[n])
        last_on = max(i for i, (_, sw) in enumerate(log) if sw & STATUS_POWER_MASK == OPERATION_ENABLED)
        t_off = log[last_on + 1][0]
        return t_off - max(t for t in self.host_hb if t <= t_off)

    def close(self):
        self.net.disconnect()


@pytest.fixture(scope="module")
def two_axes(tmp_path_factory):
    """drive_sim in real time serving nodes 5 and 7 (each run lasts seconds, as on a drive)."""
    from fftune.host.sim import start_drive_sim

    d = tmp_path_factory.mktemp("envelope")
    (d / "small.yaml").write_text(yaml.safe_dump(SMALL))
    sim = start_drive_sim(TWOMASS, log_path=str(d / "drive_sim.log"), realtime=True,
                          extra=["--axis", f"5:{TWOMASS}", "--axis", f"7:{TWOMASS}"])
    watch = BusWatch(sim.port, (5, 7))
    yield sim, d, watch
    watch.close()
    sim.stop()


def _fftune(*args):
    return subprocess.Popen([sys.executable, "-m", "fftune.host.cli", *args, "--no-progress"],
                            cwd=REPO, env=dict(os.environ, PYTHONPATH=REPO),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _kill(proc):
    proc.send_signal(signal.SIGKILL)
    proc.wait(10)


@needs_drive
def test_two_sessions_with_one_host_id_the_second_is_refused_the_first_killed_disables(two_axes, tmp_path):
    sim, d, watch = two_axes
    cfg = str(d / "small.yaml")
    first = _fftune("tune", "--config", cfg, "--node-id", "5", "--port", str(sim.port),
                    "--out", str(tmp_path / "a"), "--no-figures")
    try:
        watch.wait(lambda: watch.enabled(5), 60, "node 5 enabled by the first session", first)
        second = _fftune("tune", "--config", cfg, "--node-id", "7", "--port", str(sim.port),
                         "--out", str(tmp_path / "b"), "--no-figures")
        out, err = second.communicate(timeout=60)
        assert second.returncode == 2, out + err
        assert "Traceback" not in err
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("fftune: error: another node sends heartbeats "
                                                       "on COB-ID 0x77F (host node id 127)"), err
        assert not watch.ever_enabled(7)            # the second session enabled nothing
        assert not (tmp_path / "b").exists()
        assert watch.enabled(5)
        _kill(first)
        delay = watch.off_after_host_lost(5)
        assert delay <= BOUND_S, f"node 5 left OPERATION ENABLED {delay * 1000:.0f} ms after the last heartbeat"
        print(f"two sessions: the first killed, node 5 off {delay * 1000:.0f} ms after its last heartbeat")
    finally:
        if first.poll() is None:
            _kill(first)


@needs_drive
def test_sigkill_of_a_track_session_disables_its_axis(two_axes, tmp_path):
    sim, d, watch = two_axes
    t = _write(tmp_path / "t.yaml", yaml.safe_dump({
        "drive": {"heartbeat_ms": 100, "node_id": 7},
        "track": {"tasks": 1000, "settle_repetitions": 1, "initial": {"k_fc": 0.1, "k_v": 0.002}}}))
    proc = _fftune("track", "--config", t, "--port", str(sim.port), "--out", str(tmp_path / "o"),
                   "--no-figures")
    try:
        watch.wait(lambda: watch.enabled(7), 60, "node 7 enabled by fftune track", proc)
        time.sleep(0.3)                             # (into its first task)
        _kill(proc)
        delay = watch.off_after_host_lost(7)
        assert delay <= BOUND_S, f"node 7 left OPERATION ENABLED {delay * 1000:.0f} ms after the last heartbeat"
        print(f"track killed: node 7 off {delay * 1000:.0f} ms after the last heartbeat")
    finally:
        if proc.poll() is None:
            _kill(proc)


@needs_drive
def test_sigkill_of_a_machine_session_disables_every_axis(two_axes, tmp_path):
    """The accepted machine: one heartbeat for the bus (set in the machine's overrides: an
    axis of its own is refused above); every axis' consumer watches it."""
    sim, d, watch = two_axes
    f = _write(d / "m_kill.yaml", yaml.safe_dump({
        "machine": "k", "config": "small.yaml", "overrides": {"drive": {"heartbeat_ms": 100}},
        "axes": [{"name": "a", "node_id": 5}, {"name": "b", "node_id": 7}]}))
    proc = _fftune("tune", "--machine", f, "--port", str(sim.port), "--out", str(tmp_path / "o"),
                   "--no-figures")
    try:
        watch.wait(lambda: watch.enabled(5) and watch.enabled(7), 60, "both axes enabled", proc)
        _kill(proc)
        for n in (5, 7):
            delay = watch.off_after_host_lost(n)
            assert delay <= BOUND_S, f"node {n} left OPERATION ENABLED {delay * 1000:.0f} ms after the last heartbeat"
            print(f"machine killed: node {n} off {delay * 1000:.0f} ms after the last heartbeat")
    finally:
        if proc.poll() is None:
            _kill(proc)


@needs_drive
def test_at_20_kbit_s_the_host_heartbeat_keeps_its_period_under_block_transfers(tmp_path):
    """A block download (waveform, 1 kB: 147 frames of the host) and a block upload (the
    recording, 1 kB: 147 frames of the drive) on a 20 kbit/s bus: 6.75 ms a frame, a sub-block
    of 127 would hold the host's 200 ms heartbeat 0.86 s, more than the consumer time (4
    periods, 0.8 s). The host's bursts are bounded (44 frames, 300 ms of bus time): between
    two of its heartbeats at most a period's frames and one burst (counted, independent of
    how the test machine schedules the host), no gap reaches the consumer time and the drive stays
    enabled throughout. (200 ms, not 100: the gap also holds the host's scheduling delay; on
    a 2-core machine at load 10 a 100 ms heartbeat's largest gap reached 514 ms, over its
    0.4 s consumer time, where 200 ms periods' gaps stay under 0.5 s of 0.8 s.)"""
    from fftune.host.drive import BusOptions, DriveClient
    from fftune.host.sim import start_drive_sim

    sim = start_drive_sim(TWOMASS, log_path=str(tmp_path / "drive_sim.log"), realtime=True, bitrate=20_000)
    watch = BusWatch(sim.port, (1,))
    try:
        opts = BusOptions(port=sim.port, eds=EDS, model_bitrate=20_000)
        with DriveClient(opts, heartbeat_ms=200, progress=False) as c:
            assert c.sdo_burst == 44           # int(1.5 x 200 ms / 6.75 ms)
            c.enable()
            x = np.sin(np.linspace(0.0, 2 * np.pi, 256, endpoint=False)).astype(np.float32)
            assert c.load_waveform(x) == 256
            rec = c.run(dict(exc_kind=1, exc_inject=0, exc_amplitude=0.05, exc_period=256, exc_sine_cycles=3,
                             exc_settle_periods=1, exc_record_periods=1), signals=("plant_input",))
            assert rec.signals["plant_input"].size == 256
            assert watch.enabled(1)
        hb = np.array(watch.host_hb)        # the whole session: enable, download, run, upload
        gaps = np.diff(hb)
        # the rule itself, counted: between two host heartbeats the bus carries at most a
        # period's worth of SDO frames plus the burst the heartbeat may wait behind, (200 +
        # 300) ms / 6.75 ms = 74 (unbounded sub-blocks: 127 + 30)
        sdo_t = np.array([t for t, _ in watch.sdo_frames])
        between = np.diff(np.searchsorted(sdo_t, hb))
        assert sdo_t.size > 2 * 147 and between.max() <= 74 + 2, \
            f"{between.max()} SDO frames between two host heartbeats"
        assert hb.size > 5 and gaps.max() < 4 * 0.2, f"largest gap {gaps.max() * 1000:.0f} ms"
        print(f"20 kbit/s: {hb.size} host heartbeats, largest gap {gaps.max() * 1000:.0f} ms, "
              f"at most {between.max()} SDO frames between two")
        assert watch.ever_enabled(1)
        # the drive never left OPERATION ENABLED while the host was in charge (its own
        # disable at close is READY TO SWITCH ON, after the last run)
        sws = [sw & STATUS_POWER_MASK for _, sw in watch.status[1]]
        first_on = sws.index(OPERATION_ENABLED)
        assert 0x0040 not in sws[first_on:], "SWITCH ON DISABLED: the consumer fired"
    finally:
        watch.close()
        sim.stop()


@needs_drive
def test_enable_refuses_a_consumer_not_armed_for_this_hosts_heartbeat(two_axes):
    """The rule at the one place a drive is enabled: a consumer armed for another host id, a
    shared bus without the owner's heartbeat, or a heartbeat of another period: refused, one
    line, the drive not enabled."""
    import canopen

    from fftune.host.drive import BusOptions, DriveClient, HostHeartbeat

    sim, d, watch = two_axes
    with DriveClient(BusOptions(port=sim.port, node_id=7, eds=EDS), heartbeat_ms=100, progress=False) as c:
        c.write(0x1016, 1, (0x7E << 16) | 400)       # armed for host 126, not this host (127)
        with pytest.raises(FftuneError, match=r"^node 7 not enabled: its heartbeat consumer 0x1016:1 reads "
                                              r"0x007E0190, not 0x007F0190 \(host node 127 every 100 ms"):
            c.enable()
    net = canopen.Network()
    net.connect(interface="socketcand", channel="can0", host="127.0.0.1", port=sim.port)
    try:
        c = DriveClient(BusOptions(port=sim.port, node_id=7, eds=EDS), heartbeat_ms=100, network=net,
                        progress=False).connect()
        with pytest.raises(FftuneError, match="^node 7 not enabled: this host sends no heartbeat on its bus$"):
            c.enable()
        c.close()
        hb = HostHeartbeat(net, 0x7F, 200).start()
        c = DriveClient(BusOptions(port=sim.port, node_id=7, eds=EDS), heartbeat_ms=100, network=net,
                        host_heartbeat=hb, progress=False).connect()
        with pytest.raises(FftuneError, match="its consumer would watch host node 127 every 100 ms, this host "
                                              "sends host node 127 every 200 ms"):
            c.enable()
        c.close()
        hb.stop()
    finally:
        net.disconnect()
    assert not watch.enabled(7)
    assert int.from_bytes(_sdo_read(sim.port, 7, 0x6041, 0), "little") & STATUS_POWER_MASK != OPERATION_ENABLED


def _sdo_read(port, node, index, sub):
    from fftune.host.drive import BusOptions, DriveClient

    with DriveClient(BusOptions(port=port, node_id=node, eds=EDS), heartbeat_ms=0, progress=False) as c:
        return c.node.sdo.upload(index, sub)


@needs_drive
def test_track_check_frequency_against_the_drives_fs_is_refused_before_enabling(two_axes, tmp_path, capsys):
    """Without drive.fs_hz the check's frequency is checked against the fs read from the
    drive, after connecting and before enabling (it failed as an SDO abort after every task,
    results.yaml not written)."""
    sim, d, watch = two_axes
    t = _write(tmp_path / "t.yaml", yaml.safe_dump({
        "drive": {"heartbeat_ms": 100, "node_id": 7},
        "track": {"tasks": 3, "check": {"enabled": True, "frequency_hz": 5000, "amplitude_rad": 0.01}}}))
    n_status = len(watch.status[7])
    out = tmp_path / "o"
    assert main(["track", "--config", t, "--port", str(sim.port), "--out", str(out), "--no-progress"]) == 2
    _one_error_line(capsys, "key 'track.check.frequency_hz': 5000 Hz is at or above fs/2 = 1280 Hz of the drive")
    assert not any(sw & STATUS_POWER_MASK == OPERATION_ENABLED for _, sw in watch.status[7][n_status:])
    assert not (out / "results.yaml").exists()


@pytest.mark.parametrize("command", [["export"], ["analyze", "bla"], ["analyze", "hosidf"]])
def test_a_forged_capture_is_one_line_through_analyze_and_export(tmp_path, capsys, command):
    path = _forged_capture(str(tmp_path / "c.h5"), 8192, 18311)
    args = command + [path] + (["--to", str(tmp_path / "o")] if command == ["export"] else [])
    assert main(args) == 2
    _one_error_line(capsys, "declares 150003712 samples a signal", "at most 16777216")
    assert not (tmp_path / "o").exists()


@needs_drive
def test_sigkill_at_20_kbit_s_disables_the_axis(tmp_path):
    """The lowest bit rate the tools accept for this heartbeat (20 kbit/s, 100 ms: 22-frame
    bursts): `fftune tune -b 20000` killed while it measures; the drive leaves OPERATION
    ENABLED within its consumer time. (The statusword TPDO waits in the drive's queue behind
    at most one SDO burst of 22 frames, 150 ms, which the bound allows for.)"""
    from fftune.host.sim import start_drive_sim

    (tmp_path / "small.yaml").write_text(yaml.safe_dump(SMALL))
    sim = start_drive_sim(TWOMASS, log_path=str(tmp_path / "drive_sim.log"), realtime=True, bitrate=20_000)
    watch = BusWatch(sim.port, (1,))
    proc = _fftune("tune", "--config", str(tmp_path / "small.yaml"), "--port", str(sim.port), "-b", "20000",
                   "--out", str(tmp_path / "o"), "--no-figures")
    try:
        watch.wait(lambda: watch.enabled(1), 90, "node 1 enabled at 20 kbit/s", proc)
        time.sleep(0.5)
        _kill(proc)
        delay = watch.off_after_host_lost(1)
        assert delay <= BOUND_S + 22 * 135 / 20_000, \
            f"node 1 left OPERATION ENABLED {delay * 1000:.0f} ms after the last heartbeat"
        print(f"20 kbit/s, tune killed: node 1 off {delay * 1000:.0f} ms after the last heartbeat")
    finally:
        if proc.poll() is None:
            _kill(proc)
        watch.close()
        sim.stop()
