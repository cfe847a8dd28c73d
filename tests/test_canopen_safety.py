"""Safety net of drive_sim (issue 10), checked through python-canopen as the peer: no
non-finite value reaches the plant input, inputs that would overflow are refused, a write
to the producer heartbeat time leaves the host watchdog armed, and a failed table download
keeps the previous table."""
import struct

import numpy as np
import pytest
from canopen.sdo import SdoAbortedError

from canopen_helpers import HostHeartbeat, collect, enable_402, wait_for

FLT_MAX = float(np.finfo(np.float32).max)


def _abort_of(fn):
    with pytest.raises(SdoAbortedError) as info:
        fn()
    return info.value.code


def _table(values):
    return np.asarray(values, dtype="<f4").tobytes()


def _table_run(node, n, amplitude, kp=None):
    ex = node.sdo["Excitation"]
    ex["Kind"].raw = 2
    ex["Injection point"].raw = 0
    ex["Amplitude"].raw = amplitude
    ex["Offset"].raw = 0.0
    ex["Period length N"].raw = n
    ex["Settle periods"].raw = 0
    ex["Record periods"].raw = 4
    node.sdo["Recorder"]["Signal selection"].raw = 0x03       # reference, plant input
    if kp is not None:
        node.sdo["Controller"]["Kp"].raw = kp


@pytest.mark.parametrize("values", [
    [3e38, 0.0, -3e38, 0.0],            # the review's case: t[2] - t[0] overflows
    [FLT_MAX, FLT_MAX, -FLT_MAX, -FLT_MAX],
])
def test_table_whose_derivative_overflows_is_refused_and_the_old_one_kept(co_node, values):
    net, node = co_node
    good = _table([0.1, 0.2, 0.3, 0.4])
    node.sdo[0x2002].raw = good
    assert _abort_of(lambda: node.sdo.download(0x2002, 0, _table(values))) == 0x06090030
    assert node.sdo[0x2003].raw == 4                            # finding 14: old table kept
    assert node.sdo.upload(0x2002, 0) == good


def test_failed_downloads_keep_the_previous_table(co_node):
    net, node = co_node
    good = _table(np.sin(2 * np.pi * np.arange(64) / 64))
    node.sdo[0x2002].raw = good
    bad = bytearray(_table(np.arange(64)))
    bad[40:44] = struct.pack("<f", float("nan"))
    assert _abort_of(lambda: node.sdo.download(0x2002, 0, bytes(bad))) == 0x06090030
    assert _abort_of(lambda: node.sdo.download(0x2002, 0, b"\0" * 6)) == 0x06070010  # not whole floats
    # a segmented download abandoned half-way by a client abort (raw frames)
    answers = collect(net, 0x580 + node.id)
    net.send_message(0x600 + node.id, bytes([0x21, 0x02, 0x20, 0, 0, 1, 0, 0]))   # 256 bytes
    assert wait_for(lambda: len(answers) == 1, 2.0) and answers[0][0] == 0x60
    net.send_message(0x600 + node.id, bytes([0x00, 1, 2, 3, 4, 5, 6, 7]))
    assert wait_for(lambda: len(answers) == 2, 2.0) and answers[1][0] == 0x20
    net.send_message(0x600 + node.id, bytes([0x80, 0x02, 0x20, 0, 0, 0, 0x04, 0x05]))
    assert node.sdo[0x2003].raw == 64
    assert node.sdo.upload(0x2002, 0) == good


@pytest.mark.parametrize("values, amplitude", [
    ([3e38, 3e38, 3e38, 3e38], 2.0),     # amplitude x table overflows
    ([1e36, 1e36, -1e36, 1e36], 1.0),    # velocity gain x difference overflows
])
def test_run_whose_excitation_overflows_is_refused(co_node, values, amplitude):
    net, node = co_node
    node.nmt.state = "OPERATIONAL"
    node.sdo[0x6060].raw = -1
    enable_402(node)
    node.sdo[0x2002].raw = _table(values)
    _table_run(node, 4, amplitude)
    assert _abort_of(lambda: setattr(node.sdo["Run control"]["Command"], "raw", 1)) == 0x06040043
    assert node.sdo["Run control"]["Last stop reason"].raw == 5
    assert node.sdo["Run control"]["State"].raw == 0


def test_non_finite_controller_output_is_a_fault_with_output_zero(co_node):
    """Accepted inputs whose controller sum still overflows (Kp 1e5 x 3e38 rad): the drive
    faults on the first such step (EMCY 0xFF00, reason 8, statusword fault, output 0)
    instead of feeding inf / NaN to the plant."""
    net, node = co_node
    emcy = collect(net, 0x80 + node.id)
    node.nmt.state = "OPERATIONAL"
    node.sdo[0x6060].raw = -1
    assert enable_402(node) & 0x6F == 0x27
    node.sdo[0x2002].raw = _table([3e38, 3e38, 3e38, 3e38])
    _table_run(node, 4, 1.0, kp=1.0e5)
    node.sdo["Run control"]["Command"].raw = 1
    assert wait_for(lambda: node.sdo["Run control"]["State"].raw == 5, 5.0)
    assert node.sdo["Run control"]["Last stop reason"].raw == 8
    assert node.sdo[0x6041].raw & 0x4F == 0x08                  # FAULT
    u = node.sdo["Measurements"]["Plant input"].raw
    assert u == 0.0
    assert wait_for(lambda: any(d[:2] == b"\x00\xff" and d[3] == 8 for d in emcy), 2.0), emcy
    # the recorded plant input is finite throughout
    data = np.frombuffer(node.sdo.upload(0x2021, 0), "<f4")
    assert np.all(np.isfinite(data))
    # fault reset + enable: running again
    node.sdo[0x6040].raw = 0x80
    assert enable_402(node) & 0x6F == 0x27
    assert np.isfinite(node.sdo["Measurements"]["Plant input"].raw)


@pytest.mark.drive_sim_args("--realtime")
def test_producer_heartbeat_write_leaves_the_host_watchdog_armed(co_node):
    """Finding 2: a 0x1017 write used to reset the consumers, so the host's loss went
    unnoticed and the run went on."""
    net, node = co_node
    emcy = collect(net, 0x80 + node.id)
    host_id = 0x7F
    # 1 s consumer, fed by a heartbeat thread while the run is set up (hand-sent heartbeats
    # between the SDO writes were more than 1 s apart in the qemu guest at load 15: the
    # drive then disabled itself, 0x6007 = 2, and refused the run)
    node.sdo[0x1016][1].raw = (host_id << 16) | 1000
    hb = HostHeartbeat(net, host_id)
    try:
        node.nmt.state = "OPERATIONAL"
        node.sdo[0x6060].raw = -1
        enable_402(node)
        ex = node.sdo["Excitation"]
        ex["Kind"].raw = 1
        ex["Amplitude"].raw = 0.01
        ex["Period length N"].raw = 8192
        ex["Sine cycles per period"].raw = 1
        ex["Settle periods"].raw = 1000
        ex["Record periods"].raw = 1
        node.sdo["Recorder"]["Signal selection"].raw = 0x01
        node.sdo["Run control"]["Command"].raw = 1
    finally:
        hb.stop()
    node.sdo[0x1017].raw = 100                                  # the write under test
    # no more host heartbeats: within 1 s (+ scheduling slack) the run must stop
    assert wait_for(lambda: node.sdo["Run control"]["State"].raw == 4, 5.0)
    assert node.sdo["Run control"]["Last stop reason"].raw == 2
    assert any(d[:2] == b"\x30\x81" for d in emcy), emcy
