"""The drive on a Cortex-M4F (firmware_sim/port/mcu) under qemu-system-arm, reached by the
unchanged host over python-can's slcan interface (processor-in-the-loop):

- `fftune tune -i slcan -c socket://...` with configs/pil.yaml finds K_fc* within 2 % of the
  plant's Coulomb level (the plant's truth read from the drive, 0x2100);
- determinism: the same tune against drive_sim (x86-64, same plant file, same seed) gives the
  same line statistics (tune.capture: stats) bit for bit in every run, so the same K_fc*;
  a sine run records the same samples bit for bit;
- a multisine run agrees within a stated tolerance (the excitation table is built with the
  C library's sinf/cosf: glibc on x86, newlib on the M4);
- bad input on the link (garbage, overlong lines, a connection closed mid-line and during
  a block upload) leaves the MCU serving.
Skipped with the reason when qemu-system-arm or arm-none-eabi-gcc is missing.
"""
import json
import math
import os
import re
import socket
import struct
import time

import numpy as np
import pytest
import yaml

from fftune.analysis.stats import HarmonicStats
from fftune.host.cli import main
from fftune.host.config import load_config
from fftune.host.drive import BusOptions, DriveClient
from fftune.host.odmap import DEFAULT_EDS
from fftune.host.plan import read_drive_limits
from fftune.host.sim import start_drive_sim
from mcu_helpers import PIL_CONFIG, PIL_PLANT, build_pil, pil_missing_reason, pil_run_module, symbol_address

pytestmark = [pytest.mark.skipif(pil_missing_reason() is not None, reason=pil_missing_reason() or ""),
              pytest.mark.timeout(900)]


@pytest.fixture(scope="module")
def pil():
    """The pil_run module with the ELF built for configs/pil.yaml."""
    build_pil()
    return pil_run_module()


@pytest.fixture(scope="module")
def tuned_m4(pil, tmp_path_factory):
    """`fftune tune -i slcan -c socket://127.0.0.1:PORT --config configs/pil.yaml` on the M4."""
    out = tmp_path_factory.mktemp("pil_tune")
    with pil.start() as target:
        code = main(["tune", "-i", "slcan", "-c", target.channel, "--config", PIL_CONFIG,
                     "--out", str(out), "--no-progress", "--no-figures"])
        assert target.alive()
    assert code == 0
    return yaml.safe_load(open(out / "results.yaml")), out


@pytest.fixture(scope="module")
def tuned_x86(pil, tmp_path_factory):
    """The same tune against drive_sim with the plant file the ELF has compiled in."""
    out = tmp_path_factory.mktemp("sim_tune")
    with start_drive_sim(PIL_PLANT) as sim:
        code = main(["tune", "--config", PIL_CONFIG, "--port", str(sim.port), "--out", str(out),
                     "--no-progress", "--no-figures"])
    assert code == 0
    return yaml.safe_load(open(out / "results.yaml")), out


def test_tune_on_the_m4_finds_the_coulomb_level(tuned_m4):
    r, _ = tuned_m4
    t = r["tune"]
    assert "slcan" in r["drive"]["identity"]["bus"]
    truth = r["drive"]["plant_truth"]["sim_fc_volt"]
    assert truth == pytest.approx(0.1157, rel=1e-6)  # the plant of configs/pil.yaml
    assert abs(t["k_fc_star"] / truth - 1) <= 0.02 or abs(t["k_fc_star"] - truth) <= t["search"]["uncertainty"]
    assert t["ratio_at_zero"] >= 10 * t["ratio_at_k_fc_star"]


def _stats_runs(out):
    """{run key: HarmonicStats} of the .stats.json captures (float32 values stored exactly)."""
    return {p.name[:-len(".stats.json")]: HarmonicStats.from_dict(json.loads(p.read_text())["stats"])
            for p in (out / "captures").glob("*.stats.json")}


def _f32_bits(values):
    a = np.asarray(values, dtype=np.float32)
    return a.view(np.uint32)


def test_m4_and_drive_sim_accumulate_the_same_statistics_bit_for_bit(tuned_m4, tuned_x86):
    """configs/pil.yaml's tune captures the drive's line statistics (tune.capture: stats):
    the float32 sums of the M4 and of drive_sim (x86-64) are the same bits, so the same
    K_fc*. (The recorded samples of a sine run: test_sine_and_multisine_runs_... below.)"""
    (r4, out4), (r86, out86) = tuned_m4, tuned_x86
    assert not list((out4 / "captures").glob("*.h5"))
    runs4, runs86 = _stats_runs(out4), _stats_runs(out86)
    assert len(runs4) >= 4 and set(runs4) == set(runs86)  # the sweep points and the search's runs
    for key, run in runs4.items():
        a, b = run, runs86[key]
        assert a.periods == b.periods >= 2 and a.harmonics == b.harmonics == 7
        for name in a.mean:
            for x, y in ((a.mean[name].real, b.mean[name].real), (a.mean[name].imag, b.mean[name].imag),
                         (a.var[name], b.var[name])):
                differ = int(np.count_nonzero(_f32_bits(x) != _f32_bits(y)))
                assert differ == 0, f"{key}: {name}: {differ} values differ"
        assert a.power_msq == b.power_msq and a.power_mean == b.power_mean
    assert r4["tune"]["k_fc_star"] == r86["tune"]["k_fc_star"]


MULTISINE = {"exc_kind": 3, "exc_period": 512, "ms_k_min": 1, "ms_k_max": 20, "ms_group": 5, "ms_seed": 7,
             "ms_realization": 1, "exc_amplitude": 1.0, "exc_settle_periods": 2, "exc_record_periods": 1,
             "exc_inject": 1, "kfc": 0.0}


def _session(opts, requests, limits=None):
    """The runs' signals; with ``limits`` (a list) the preflight's :class:`DriveLimits` read
    from the drive are appended to it."""
    with DriveClient(opts, heartbeat_ms=500, progress=False) as c:
        if limits is not None:
            limits.append(read_drive_limits(c, load_config(PIL_CONFIG)))
        c.enable()
        return [c.run(r).signals for r in requests]


SINE = {"exc_kind": 1, "exc_period": 1024, "exc_sine_cycles": 1, "exc_amplitude": 0.5,
        "exc_settle_periods": 1, "exc_record_periods": 2, "exc_inject": 0, "kfc": 0.05}


def test_sine_and_multisine_runs_record_the_same_samples(pil):
    """A sine run (the tune's kind) records the same bits on the M4 and on drive_sim; a
    multisine run agrees within the libm tolerance."""
    limits = []
    with pil.start() as target:
        m4, sine4 = _session(BusOptions(interface="slcan", channel=target.channel, eds=DEFAULT_EDS),
                             [MULTISINE, SINE], limits)
    # the M4's table holds 4096 samples (pil.mk MCU_TABLE_MAX), half the EDS's period limit:
    # the preflight reads it from 0x2004, and its recorder capacity from 0x2020:2
    plant = yaml.safe_load(open(PIL_PLANT))
    assert limits[0].table_capacity == plant["drive"]["table_capacity"] == 4096
    assert limits[0].rec_capacity == plant["drive"]["rec_capacity"]
    with start_drive_sim(PIL_PLANT) as sim:
        x86, sine86 = _session(BusOptions(host=sim.host, port=sim.port, eds=DEFAULT_EDS), [MULTISINE, SINE])
    for name, values in sine4.items():
        a, b = _f32_bits(values), _f32_bits(sine86[name])
        assert a.shape == b.shape and a.size == 2048
        differ = int(np.count_nonzero(a != b))
        assert differ == 0, f"sine run: {name}: {differ} of {a.size} samples differ"
    u4, u86 = np.float32(m4["plant_input"]), np.float32(x86["plant_input"])
    # The period is built by an inverse FFT whose twiddles come from sinf/cosf (glibc on
    # x86, newlib's fdlibm on the M4; both within 1 ulp, not always the same): the plant
    # input may differ by a few float32 ulps of its peak (the period is scaled as a whole),
    # nothing more.
    ulp_at_peak = np.spacing(np.max(np.abs(u86)))
    assert 0 < np.max(np.abs(u4 - u86)) <= 4 * ulp_at_peak
    # ... which stays below the encoder resolution here: the measured angles agree
    count = 2 * math.pi / 2000
    assert np.max(np.abs(np.float32(m4["motor_angle"]) - np.float32(x86["motor_angle"]))) <= count
    assert np.array_equal(np.float32(m4["reference"]), np.float32(x86["reference"]))


def _raw(port):
    s = socket.create_connection(("127.0.0.1", port), timeout=5)
    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return s


def _read_until(s, pattern, timeout_s=5.0):
    """Bytes from the socket until the regular expression ``pattern`` matches (or the timeout)."""
    s.settimeout(0.2)
    data = b""
    deadline = time.monotonic() + timeout_s
    while re.search(pattern, data) is None and time.monotonic() < deadline:
        try:
            chunk = s.recv(4096)
        except socket.timeout:
            continue
        if not chunk:
            break
        data += chunk
    return data


def test_bad_input_on_the_link_leaves_the_mcu_serving(pil):
    slcan_addr = symbol_address("g_slcan")
    fault_addr = symbol_address("mcu_fault_count")
    sine = {"exc_kind": 1, "exc_period": 512, "exc_sine_cycles": 1, "exc_amplitude": 0.3,
            "exc_settle_periods": 1, "exc_record_periods": 1, "exc_inject": 0}
    with pil.start() as target:
        opts = BusOptions(interface="slcan", channel=target.channel, eds=DEFAULT_EDS)
        # a recording to upload later
        _session(opts, [sine])
        # 1. garbage bytes, an overlong line, malformed frames, then a good SDO request
        s = _raw(target.port)
        s.sendall(bytes(range(256)) * 4 + b"\r" + b"t" * 3000 + b"\r" + b"t60190000\rT123\rS9\r")
        s.sendall(b"O\rt60184000100000000000\r")  # SDO upload 0x1000:0 (device type)
        reply = _read_until(s, rb"t5818[0-9A-F]{16}\r")
        # the device type 0x1000 (CiA 402 drive: 0x00020192)
        assert re.search(rb"t581843001000920102..\r", reply[-40:]), reply[-200:]
        assert b"\a" in reply
        # 2. closed in the middle of a line
        s.sendall(b"t6018400")
        s.close()
        # 3. closed during a block upload of the recording (the MCU keeps sending into the
        #    void): initiate 0x2021 with 127 segments per block, start, close at once
        s = _raw(target.port)
        s.sendall(b"O\rt6018A42120007F000000\r")
        assert re.search(rb"t5818C[0-9A-F]{15}\r", _read_until(s, rb"t5818C[0-9A-F]{15}\r"))
        s.sendall(b"t6018A300000000000000\r")
        time.sleep(0.05)
        s.close()
        time.sleep(0.5)
        # still serving: the host's client connects, reaches OPERATION ENABLED, runs, uploads
        with DriveClient(opts, heartbeat_ms=500, progress=False) as c:
            c.enable()
            assert int(c.read(0x6041, 0)) & 0x6F == 0x27  # CiA 402 OPERATION ENABLED
            rec = c.run(sine)
            assert rec.signals["reference"].size == 512
        # the parser saw and refused the bad lines; no fault handler ran
        words = target.read_words(slcan_addr + 32, 5)  # slcan_t statistics (offset asserted in slcan.c)
        frames_in, commands, bad_lines, overlong_lines, partial_dropped = words[:5]
        assert bad_lines >= 4 and overlong_lines >= 1 and frames_in > 100
        assert target.read_words(fault_addr, 1) == [0]
        assert target.alive()


def test_launcher_prints_the_channel_and_stops_qemu_on_sigterm(pil):
    import signal
    import subprocess
    import sys
    proc = subprocess.Popen([sys.executable, pil.__file__], stdout=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        m = re.search(r"socket://127\.0\.0\.1:(\d+)", line)
        assert m, line
        s = _raw(int(m.group(1)))
        # bytes that arrive before the firmware has enabled its UART are lost (as on the
        # hardware); on a loaded machine qemu may not have run that far yet: ask again
        reply = b""
        for _ in range(20):
            s.sendall(b"\rV\rN\r")
            reply += _read_until(s, rb"NPIL1\r", timeout_s=0.5)
            if b"NPIL1" in reply:
                break
        assert b"V1013\rNPIL1\r" in reply
        s.close()
        qemu = subprocess.run(["pgrep", "-P", str(proc.pid), "qemu-system-arm"], capture_output=True, text=True)
        qemu_pids = [int(p) for p in qemu.stdout.split()]
        assert len(qemu_pids) == 1, "qemu is not the launcher's child"
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
        assert not os.path.exists(f"/proc/{qemu_pids[0]}"), "qemu outlived its launcher"
        with pytest.raises(OSError):
            _raw(int(m.group(1))).close()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
