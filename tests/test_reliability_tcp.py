"""Security of the simulated drive's socketcand TCP server and of its parameter writes.

Against the running drive_sim (the ASan + UBSan build when `make test` built it; every
test ends by stopping the drive and checking that it exited cleanly with no sanitizer
report): loopback bind by default, a bounded number of clients, a bounded line buffer,
random bytes, over-long lines, half a line then a stall, a client that never reads; NaN /
inf / out-of-range parameter writes rejected with the CiA 301 abort codes; the controller
output saturated at u_max over a whole recording.
"""
import math
import random
import re
import socket
import struct
import time

import numpy as np
import pytest

from test_reliability_support import EDS, RawClient, needs_drive, start_drive

pytestmark = needs_drive

SCD_MAX_CLIENTS = 8  # firmware_sim/port/scd.h
SCD_LINE_MAX = 128


@pytest.fixture
def drive(tmp_path):
    d = start_drive(tmp_path)
    yield d
    d.stop(check=True)


def _device_type_ok(cli, timeout=2.0):
    resp = cli.sdo_upload_expedited(0x1000, 0, timeout=timeout)
    return resp is not None and resp[0] == 0x43 and int.from_bytes(resp[4:8], "little") == 0x00020192


def _listening_address(pid, port):
    """Local address of the LISTEN socket on `port` (from /proc/<pid>/net/tcp)."""
    with open(f"/proc/{pid}/net/tcp") as fh:
        for line in fh.readlines()[1:]:
            f = line.split()
            addr, p = f[1].split(":")
            if int(p, 16) == port and f[3] == "0A":
                return socket.inet_ntoa(struct.pack("<I", int(addr, 16)))
    return None


def test_binds_loopback_unless_told(tmp_path):
    d = start_drive(tmp_path)  # no host given: the default
    try:
        assert d.bound_host == "127.0.0.1"
        assert _listening_address(d.proc.pid, d.port) == "127.0.0.1"
    finally:
        d.stop()
    d = start_drive(tmp_path, "--can", "socketcand:0.0.0.0:0")  # told otherwise
    try:
        assert _listening_address(d.proc.pid, d.port) == "0.0.0.0"
    finally:
        d.stop()


def test_client_beyond_the_bound_is_closed_others_keep_working(drive):
    clients = [RawClient(drive.port) for _ in range(SCD_MAX_CLIENTS)]
    extra = socket.create_connection(("127.0.0.1", drive.port), timeout=3)
    extra.settimeout(3)
    # the server closes the extra connection without a greeting
    assert extra.recv(100) == b""
    extra.close()
    for cli in clients:
        assert _device_type_ok(cli)
    # a slot that frees up is usable again
    clients.pop().close()
    # the server notices the close in its next pass: retry until a connection gets the
    # freed slot (closed without a greeting until then), with a generous deadline
    deadline = time.monotonic() + 10.0
    while True:
        try:
            again = RawClient(drive.port)
            break
        except (AssertionError, OSError):
            assert time.monotonic() < deadline, "no client slot within 10 s of a close"
            time.sleep(0.01)
    assert _device_type_ok(again)
    for cli in clients + [again]:
        cli.close()


def test_random_bytes_overlong_lines_and_stalled_half_lines(drive):
    rng = random.Random(7)
    good = RawClient(drive.port)
    stalled = RawClient(drive.port)
    stalled.sock.sendall(b"< send 601 8 40 00 10")  # half a line, then nothing
    noisy = RawClient(drive.port)
    raw = socket.create_connection(("127.0.0.1", drive.port), timeout=3)  # never handshakes

    def raw_send(data):  # the server closes it SCD_HANDSHAKE_US after connecting (3 s)
        try:
            raw.sendall(data)
            return len(data)
        except (BrokenPipeError, ConnectionResetError):
            return 0
    sent = 0
    for k in range(40):
        blob = bytes(rng.getrandbits(8) for _ in range(8192))
        noisy.sock.sendall(blob)
        sent += len(blob) + raw_send(blob)
        if k % 10 == 0:
            # over-long commands: 100x the line buffer, with and without the closing '>'
            noisy.sock.sendall(b"< send 601 8 " + b"ff " * (SCD_LINE_MAX * 30) + b">")
            raw_send(b"<" + b"x" * (SCD_LINE_MAX * 100))
            assert _device_type_ok(good), "a well-behaved client got no answer"
    assert sent > 330_000
    assert _device_type_ok(good)
    # after the garbage, a complete command on the noisy connection is understood again
    noisy.sock.sendall(b">")
    noisy.buf = b""
    assert _device_type_ok(noisy, timeout=3.0)
    # the stalled client finishes its line: its request is served
    stalled.sock.sendall(b" 00 00 00 00 00 >")
    got = [d for cid, d in stalled.frames(1.0) if cid == 0x581 and d[:4] == bytes([0x43, 0x00, 0x10, 0x00])]
    assert got, "the completed half line was not served"
    for c in (good, stalled, noisy):
        c.close()
    raw.close()


def _stop_line(drive):
    drive.stop(check=True)
    line = [ln for ln in drive.log().splitlines() if ln.startswith("drive_sim: stopped:")]
    assert line, drive.log()
    return line[-1]


def test_silent_connections_do_not_lock_out_new_clients(drive):
    """Eight TCP connections that never say a word fill every slot; a new client still
    gets in (the longest-silent unhandshaken one is evicted), and a silent connection is
    closed once its handshake time (3 s) is over."""
    silent = [socket.create_connection(("127.0.0.1", drive.port), timeout=5)
              for _ in range(SCD_MAX_CLIENTS)]
    for s in silent:
        assert s.recv(6) == b"< hi >"
    time.sleep(0.3)  # > SCD_EVICT_IDLE_US: all eight are idle in their handshake
    newcomer = RawClient(drive.port)
    assert _device_type_ok(newcomer), "a new client is locked out by silent connections"
    # the one evicted sees its connection closed at once; the others within the 3 s timeout
    t0 = time.monotonic()
    closed = 0
    for s in silent:
        s.settimeout(max(0.1, 5.0 - (time.monotonic() - t0)))
        try:
            closed += s.recv(100) == b""
        except (socket.timeout, ConnectionResetError):
            closed += 0
        s.close()
    assert closed == SCD_MAX_CLIENTS, f"{closed} of {SCD_MAX_CLIENTS} silent connections closed"
    assert _device_type_ok(newcomer), "the handshaken client was dropped with the silent ones"
    newcomer.close()
    line = _stop_line(drive)
    assert "1 evicted in their handshake, 7 handshake timeouts" in line, line


def test_handshaken_clients_are_never_evicted(drive):
    """Eviction takes only connections still in their handshake: with eight clients in
    rawmode (silent, but handshaken) the ninth is refused, the eight keep working."""
    clients = [RawClient(drive.port) for _ in range(SCD_MAX_CLIENTS)]
    time.sleep(0.3)
    extra = socket.create_connection(("127.0.0.1", drive.port), timeout=3)
    assert extra.recv(100) == b""
    extra.close()
    for cli in clients:
        assert _device_type_ok(cli)
        cli.close()


def test_silent_clients_in_their_grace_cause_no_busy_loop(drive):
    """Frames queued for clients in their 200 ms handshake grace cannot be written; the
    server must not ask poll for POLLOUT then (it returned at once, again and again: a
    busy loop of ~100 000 passes a second). Idle, drive_sim wakes about once a millisecond
    (CANopen timers) plus once per frame or connection."""
    cfg = RawClient(drive.port)
    cfg.send_frame(0x601, [0x2B, 0x17, 0x10, 0x00, 5, 0, 0, 0])  # heartbeat every 5 ms
    assert cfg.expect_message(2.0) is not None
    cfg.close()
    t0 = time.monotonic()
    socks = []
    while time.monotonic() - t0 < 1.5:
        if len(socks) >= 6:
            socks.pop(0).close()
        s = socket.create_connection(("127.0.0.1", drive.port), timeout=3)
        assert s.recv(6) == b"< hi >"
        s.sendall(b"< open can0 >")
        assert s.recv(6) == b"< ok >"
        s.sendall(b"< rawmode >")
        assert s.recv(6) == b"< ok >"
        socks.append(s)  # silent from here on: in its grace, heartbeats queue up for it
        time.sleep(0.1)
    for s in socks:
        s.close()
    elapsed_ms = (time.monotonic() - t0) * 1000.0 + 1000.0  # + start-up and stop
    line = _stop_line(drive)
    passes = int(re.search(r"(\d+) bus passes", line).group(1))
    # once per ms, plus frames (heartbeats 1 per 5 ms) and connection events: far below
    # a busy loop's count
    assert passes < 3 * elapsed_ms, f"{passes} bus passes in about {elapsed_ms:.0f} ms: {line}"
    print(f"{passes} bus passes in about {elapsed_ms:.0f} ms with silent clients in their grace")


def test_client_that_never_reads_does_not_block_the_bus(drive):
    sleeper = RawClient(drive.port)  # in rawmode, never reads: its output buffer fills up
    talker = RawClient(drive.port)
    frame = b"< send 77f 1 5 >"
    t0 = time.monotonic()
    for _ in range(60):
        talker.sock.sendall(frame * 1000)  # 60 000 frames broadcast to the sleeper
        talker.buf = b""
    while True:  # drain the talker's own copies of the node's answers (none expected)
        if talker.expect_message(0.2) is None:
            break
    assert _device_type_ok(talker)
    assert time.monotonic() - t0 < 30
    sleeper.close()
    talker.close()


# ---- parameter writes ----------------------------------------------------------------

@pytest.fixture
def node(drive):
    import canopen

    net = canopen.Network()
    net.connect(interface="socketcand", channel="can0", host="127.0.0.1", port=drive.port)
    n = canopen.RemoteNode(1, EDS)
    net.add_node(n)
    n.sdo.RESPONSE_TIMEOUT = 2.0
    yield n
    net.disconnect()


def _rw_real32_parameters(node):
    from canopen.objectdictionary import REAL32

    out = []
    for obj in node.object_dictionary.values():
        subs = obj.values() if hasattr(obj, "values") else [obj]
        for var in subs:
            if getattr(var, "data_type", None) == REAL32 and "w" in var.access_type and 0x2000 <= var.index < 0x6000:
                out.append(var)
    return out


def _eds_limits():
    """(index, sub) -> (LowLimit, HighLimit) of the REAL32 entries, read from the EDS text
    (python-canopen 2.4 leaves REAL32 limits unset)."""
    import configparser

    cp = configparser.ConfigParser(interpolation=None, strict=False)
    cp.optionxform = str
    cp.read(EDS)
    out = {}
    for sec in cp.sections():
        m = sec.lower().split("sub")
        try:
            key = (int(m[0], 16), int(m[1], 16) if len(m) > 1 else 0)
        except ValueError:
            continue
        lo, hi = cp[sec].get("LowLimit"), cp[sec].get("HighLimit")
        if cp[sec].get("DataType") == "0x0008" and lo is not None and hi is not None:
            out[key] = (float(lo), float(hi))
    return out


def test_nan_inf_and_out_of_range_writes_rejected_with_the_right_abort(node):
    from canopen.sdo.exceptions import SdoAbortedError

    params = _rw_real32_parameters(node)
    limits = _eds_limits()
    assert len(params) >= 8  # controller and excitation parameters
    tried = 0
    for var in params:
        before = node.sdo[var.index][var.subindex].raw if var.subindex else node.sdo[var.index].raw
        cases = [(math.nan, 0x06090030), (math.inf, 0x06090030), (-math.inf, 0x06090030)]
        lo, hi = limits[(var.index, var.subindex)]
        cases += [(hi * 2 + 1.0, 0x06090031), (lo - 1.0 - abs(lo), 0x06090032),
                  (3.0e38, 0x06090031), (-3.0e38, 0x06090032)]
        for value, code in cases:
            with pytest.raises(SdoAbortedError) as exc:
                node.sdo.download(var.index, var.subindex, struct.pack("<f", value))
            assert exc.value.code == code, f"0x{var.index:04X}:{var.subindex} = {value}: 0x{exc.value.code:08X}"
            tried += 1
        after = node.sdo[var.index][var.subindex].raw if var.subindex else node.sdo[var.index].raw
        assert after == before or (math.isnan(after) and math.isnan(before))
    assert tried == 7 * len(params)


@pytest.mark.parametrize("fc_smooth", [0.0, 1.0e-40])
def test_controller_output_saturated_over_a_whole_recording(node, fc_smooth):
    """A deliberately violent controller (Kp 1e5, Kd 1e4, big excitation): every recorded
    plant-input sample stays finite and within u_max. fc_smooth 1e-40 (a denormal sign
    smoothing width, accepted as >= 0) is the regression case of fuzz/regress/co_node/
    nan_output_denormal_fc_smooth.bin: 1/width overflowed and the output became NaN."""
    u_max = 0.75
    node.nmt.state = "OPERATIONAL"
    for cw in (0x06, 0x07, 0x0F):
        node.sdo.download(0x6040, 0, struct.pack("<H", cw))
    w = lambda i, s, fmt, v: node.sdo.download(i, s, struct.pack(fmt, v))  # noqa: E731
    w(0x2000, 1, "<f", 1.0e5)   # Kp
    w(0x2000, 2, "<f", 1.0e4)   # Kd
    w(0x2000, 4, "<f", 50.0)    # K_fc far above u_max
    w(0x2000, 7, "<f", u_max)
    w(0x2000, 6, "<f", fc_smooth)
    w(0x2001, 1, "<B", 1)       # sine
    w(0x2001, 3, "<f", 500.0)   # amplitude [rad]
    w(0x2001, 5, "<I", 1024)
    w(0x2001, 7, "<I", 0)
    w(0x2001, 8, "<I", 2)
    w(0x2020, 1, "<I", 0x02 | 0x04)  # plant input + motor angle
    w(0x6060, 0, "<b", -1)      # runs start in the excitation-run mode only
    w(0x2010, 1, "<B", 1)
    deadline = time.monotonic() + 30
    while node.sdo.upload(0x2010, 2)[0] not in (3, 4, 5):
        assert time.monotonic() < deadline
        time.sleep(0.02)
    assert node.sdo.upload(0x2010, 2)[0] == 3
    with node.sdo[0x2021].open("rb", block_transfer=True) as fh:
        data = fh.read()
    rec = np.frombuffer(data, dtype="<f4").reshape(-1, 2)
    assert rec.shape[0] == 2048
    u = rec[:, 0]
    assert np.all(np.isfinite(u))
    assert np.max(np.abs(u)) <= u_max * (1 + 1e-6)
    assert np.max(np.abs(u)) > 0.99 * u_max  # the limit was actually hit
    live = struct.unpack("<f", node.sdo.upload(0x2030, 4))[0]
    assert abs(live) <= u_max * (1 + 1e-6)
