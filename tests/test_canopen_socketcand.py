"""drive_sim's socketcand server: the handshake exactly as python-can reads it, several
clients on one bus, bounded clients, garbage survived."""
import socket
import time

import can
import pytest

from canopen_helpers import collect, wait_for
from conftest import can_transport

pytestmark = pytest.mark.skipif(
    can_transport()[0] != "socketcand",
    reason="FFTUNE_TEST_CAN selects SocketCAN: drive_sim's socketcand server is not running")


def _raw_client(sim, handshake=True):
    s = socket.create_connection((sim.host, sim.port), timeout=2.0)
    assert s.recv(256) == b"< hi >"
    if handshake:
        s.sendall(b"< open can0 >")
        assert s.recv(256) == b"< ok >"
        s.sendall(b"< rawmode >")
        assert s.recv(256) == b"< ok >"
    return s


def _until(pred, what, timeout_s=10.0):
    """Poll pred() until it returns something true (returned); fail naming ``what`` after a
    generous deadline (synchronisation on a condition, not on a sleep)."""
    end = time.monotonic() + timeout_s
    while True:
        got = pred()
        if got:
            return got
        assert time.monotonic() < end, f"{what}: not within {timeout_s:g} s"
        time.sleep(0.01)


def _try_raw_client(sim):
    """A handshaken raw client, or None if the server closed the connection (no slot)."""
    s = socket.create_connection((sim.host, sim.port), timeout=2.0)
    hello = s.recv(256)
    if hello == b"":
        s.close()
        return None
    assert hello == b"< hi >"
    for line in (b"< open can0 >", b"< rawmode >"):
        s.sendall(line)
        assert s.recv(256) == b"< ok >"
    return s


def _recv_until(s, needle, timeout_s=2.0):
    s.settimeout(0.2)
    buf = b""
    end = time.monotonic() + timeout_s
    while needle not in buf and time.monotonic() < end:
        try:
            chunk = s.recv(4096)
        except socket.timeout:
            continue
        if not chunk:
            break
        buf += chunk
    return buf


def test_handshake_replies_arrive_alone_even_while_the_node_talks(drive_sim):
    a = can.Bus(interface="socketcand", channel="can0", host=drive_sim.host, port=drive_sim.port)
    try:
        a.send(can.Message(arbitration_id=0x605 - 4, is_extended_id=False,   # 0x601: SDO
                           data=[0x2B, 0x17, 0x10, 0, 10, 0, 0, 0]))        # 0x1017 = 10 ms
        # heartbeats every 10 ms once the drive has answered the write
        _until(lambda: (lambda m: m is not None and m.arbitration_id == 0x581)(a.recv(0.05)),
               "the answer to the 0x1017 write")
        for _ in range(5):
            s = _raw_client(drive_sim)       # each recv(256) is exactly the reply
            buf = _recv_until(s, b"< frame 701 ")
            assert b"< frame 701 " in buf and buf.rstrip().endswith(b">")
            s.close()
    finally:
        a.shutdown()


def test_frame_format_and_node_frames_to_every_client(drive_sim):
    s1 = _raw_client(drive_sim)
    s2 = _raw_client(drive_sim)
    s1.sendall(b"< send 601 8 40 0 10 0 0 0 0 0 >")          # read 0x1000
    for s in (s2,):
        buf = _recv_until(s, b"< frame 581 ")
        assert b"< frame 601 " in buf                          # the other client's request
    for s in (s1, s2):
        buf = _recv_until(s, b"< frame 581 ") if s is s1 else buf
        line = buf[buf.index(b"< frame 581 "):]
        line = line[:line.index(b">") + 1].decode()
        _, _, ident, stamp, data, _ = line.split(" ")
        assert ident == "581" and data == "4300100092010200"
        assert abs(float(stamp) - time.time()) < 5.0
    s1.close()
    s2.close()


def test_two_python_can_clients_and_two_canopen_networks_share_the_bus(drive_sim):
    a = can.Bus(interface="socketcand", channel="can0", host=drive_sim.host, port=drive_sim.port)
    b = can.Bus(interface="socketcand", channel="can0", host=drive_sim.host, port=drive_sim.port)
    try:
        a.send(can.Message(arbitration_id=0x123, is_extended_id=False, data=b"\x01\x02"))
        a.send(can.Message(arbitration_id=0x1ABCDEF, is_extended_id=True, data=b""))
        got = []
        end = time.monotonic() + 2.0
        while len(got) < 2 and time.monotonic() < end:
            m = b.recv(0.2)
            if m is not None:
                got.append(m)
        assert (got[0].arbitration_id, bytes(got[0].data), got[0].is_extended_id) == (0x123, b"\x01\x02", False)
        assert (got[1].arbitration_id, bytes(got[1].data), got[1].is_extended_id) == (0x1ABCDEF, b"", True)
        assert a.recv(0.2) is None                              # no echo to the sender
    finally:
        a.shutdown()
        b.shutdown()
    import canopen
    n1, n2 = drive_sim.network(), drive_sim.network()
    try:
        r1 = canopen.RemoteNode(1, drive_sim.eds)
        r2 = canopen.RemoteNode(1, drive_sim.eds)
        r1.sdo.RESPONSE_TIMEOUT = r2.sdo.RESPONSE_TIMEOUT = 0.8
        n1.add_node(r1)
        n2.add_node(r2)
        # both clients use the one SDO channel of node 1 (CiA 301 allows one client at a
        # time): each answer reaches both receive queues. python-canopen empties a queue
        # before its request, so an answer still on its way to the other client would be
        # taken for that client's own: each waits until it has seen the other's answer
        # (counted by a callback subscribed after the SDO client's, so it runs after the
        # answer is queued), with a generous deadline instead of a fixed sleep.
        seen = {1: 0, 2: 0}
        n1.subscribe(0x581, lambda *a: seen.__setitem__(1, seen[1] + 1))
        n2.subscribe(0x581, lambda *a: seen.__setitem__(2, seen[2] + 1))
        r1.sdo["Controller"]["Kp"].raw = 7.0
        _until(lambda: seen[2] >= 1, "r1's answer in r2's queue")
        assert r2.sdo["Controller"]["Kp"].raw == 7.0
        _until(lambda: seen[1] >= 2, "r2's answer in r1's queue")
        r1.sdo[0x1017].raw = 20
        assert r2.nmt.wait_for_heartbeat(1.0) == "PRE-OPERATIONAL"
        assert r1.nmt.wait_for_heartbeat(1.0) == "PRE-OPERATIONAL"
    finally:
        n1.disconnect()
        n2.disconnect()


def test_client_count_is_bounded(drive_sim):
    clients = [_raw_client(drive_sim) for _ in range(8)]
    extra = socket.create_connection((drive_sim.host, drive_sim.port), timeout=2.0)
    assert extra.recv(256) == b""                                 # closed: 8 is the limit
    extra.close()
    clients.pop().close()
    clients.append(_until(lambda: _try_raw_client(drive_sim),       # a slot is free again
                          "a client slot after one closed"))
    for c in clients:
        c.close()


def test_garbage_and_stalled_half_lines_do_not_disturb_the_bus(drive_sim):
    bad = _raw_client(drive_sim)
    bad.sendall(b"no brackets at all\n< send 1ZZ 1 00 >< send 123 9 00 >< send 123 2 00 >"
                b"< " + b"x" * 5000 + b" >< unknown command ><<<>>>\x00\xff")
    stalled = _raw_client(drive_sim)
    stalled.sendall(b"< send 60")                                  # half a line, then nothing
    half_hs = socket.create_connection((drive_sim.host, drive_sim.port), timeout=2.0)
    assert half_hs.recv(256) == b"< hi >"                          # never opens a bus
    import canopen
    net = drive_sim.network()
    try:
        node = canopen.RemoteNode(1, drive_sim.eds)
        node.sdo.RESPONSE_TIMEOUT = 2.0                # TCP loses nothing: a stall only
        net.add_node(node)
        assert node.sdo[0x1000].raw == 0x00020192
        # the garbage client is still connected and still sees and sends frames
        listener = collect(net, 0x77F)
        bad.sendall(b"< send 77F 1 5 >")
        assert wait_for(lambda: listener == [b"\x05"], 5.0)
        node.sdo[0x1017].raw = 10
        assert b"< frame 701 " in _recv_until(bad, b"< frame 701 ")
    finally:
        net.disconnect()
        for s in (bad, stalled, half_hs):
            s.close()
    assert drive_sim.proc.poll() is None
