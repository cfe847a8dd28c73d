"""CiA 301 conformance findings of issue 10 (8-13), each against drive_sim with
python-canopen as the peer (raw SDO requests where the client library would not make the
request in question)."""
import struct

import pytest
from canopen.sdo import SdoAbortedError

from canopen_helpers import collect, configure_sine_run, enable_402, start_long_run, wait_for


def _abort_of(fn):
    with pytest.raises(SdoAbortedError) as info:
        fn()
    return info.value.code


def _raw(node, req):
    """One raw SDO request; the response bytes (aborts included: python-canopen's
    read_response would raise without the multiplexer)."""
    node.sdo.send_request(bytes(req))
    return bytes(node.sdo.responses.get(timeout=node.sdo.RESPONSE_TIMEOUT))


def _abort(resp):
    assert resp[0] == 0x80, resp.hex()
    return struct.unpack_from("<HBI", resp, 1)


@pytest.mark.drive_sim_args("--realtime")
def test_repeated_run_start_after_a_lost_response_is_answered_not_executed(co_node):
    """Finding 8: the decided behaviour (docs/reliability.md): an exact repeat of a completed
    download within the SDO timeout gets the same confirmation and is not executed again."""
    net, node = co_node
    node.nmt.state = "OPERATIONAL"
    enable_402(node)
    configure_sine_run(node, period=8192, settle=1000, record=1, signals=0x01)
    start = [0x2F, 0x10, 0x20, 1, 1, 0, 0, 0]
    assert _raw(node, start)[0] == 0x60
    assert _raw(node, start)[0] == 0x60                 # the retry: confirmed, no 0x08000022
    assert node.sdo["Run control"]["Run counter"].raw == 1
    assert node.sdo["Run control"]["State"].raw in (1, 2)
    node.sdo["Run control"]["Command"].raw = 2


def test_repeated_final_download_segment_is_answered_not_aborted(co_node):
    net, node = co_node
    assert _raw(node, [0x21, 0x00, 0x20, 2, 4, 0, 0, 0])[0] == 0x60     # Kd, segmented
    final = [(3 << 1) | 1, *struct.pack("<f", 0.75), 0, 0, 0]
    assert _raw(node, final)[0] == 0x20
    assert _raw(node, final)[0] == 0x20                 # was abort 0x05040001
    assert node.sdo["Controller"]["Kd"].raw == 0.75


def test_upload_toggle_not_alternated_aborts(co_node):
    """Finding 9."""
    net, node = co_node
    assert _raw(node, [0x40, 0x08, 0x10, 0, 0, 0, 0, 0])[0] == 0x41     # device name, 16 bytes
    assert _raw(node, [0x60, 0, 0, 0, 0, 0, 0, 0])[0] & 0xE1 == 0x00
    index, sub, code = _abort(_raw(node, [0x60, 0, 0, 0, 0, 0, 0, 0]))  # toggle 0 again
    assert (index, sub, code) == (0x1008, 0, 0x05030000)


def test_tpdo_inhibit_time_cannot_change_while_the_pdo_is_valid(co_node):
    """Finding 10."""
    net, node = co_node
    comm = node.sdo[0x1801]
    assert _abort_of(lambda: setattr(comm[3], "raw", 100)) == 0x06090030
    assert comm[3].raw == 500
    comm[1].raw = 0x80000280 + node.id
    comm[3].raw = 100
    comm[1].raw = 0x280 + node.id
    assert comm[3].raw == 100


def test_rpdo_length_error_is_reset_by_the_next_correct_rpdo(co_node):
    """Finding 11: EMCY 0x8210 once, then EMCY 0x0000 and error register 0 after a correct
    RPDO."""
    net, node = co_node
    emcy = collect(net, 0x80 + node.id)
    node.nmt.state = "OPERATIONAL"
    net.send_message(0x200 + node.id, b"\x06")             # RPDO1 maps 16 bits
    assert wait_for(lambda: len(emcy) == 1, 5.0)
    assert emcy[0][:3] == b"\x10\x82\x11"
    assert node.sdo[0x1001].raw == 0x11
    net.send_message(0x200 + node.id, b"\x06\x00")
    assert wait_for(lambda: len(emcy) == 2, 5.0), emcy
    assert emcy[1][:3] == b"\x00\x00\x00"
    assert node.sdo[0x1001].raw == 0
    assert node.sdo[0x6041].raw & 0x6F == 0x21             # the correct RPDO was applied


def test_stray_segment_abort_names_the_last_object_not_the_data(co_node):
    """Finding 12: the data bytes of a segment are not a multiplexer."""
    net, node = co_node
    assert node.sdo[0x1018][1].raw == 0x0FF7
    index, sub, code = _abort(_raw(node, [0x60, 0x40, 0x00, 0x07, 1, 2, 3, 4]))
    assert code == 0x05040001
    assert (index, sub) == (0x1018, 1)                     # was 0x0040:7


def test_inconsistent_excitation_gives_parameter_incompatibility(co_node):
    """Finding 13: sine at / above Nyquist, bad multisine band -> 0x06040043 (not the
    device-state code 0x08000022, which stays for "not enabled" / "running")."""
    net, node = co_node
    node.nmt.state = "OPERATIONAL"
    enable_402(node)
    configure_sine_run(node, period=64, cycles=32)
    cmd = node.sdo["Run control"]["Command"]
    assert _abort_of(lambda: setattr(cmd, "raw", 1)) == 0x06040043
    node.sdo["Excitation"]["Sine cycles per period"].raw = 40
    assert _abort_of(lambda: setattr(cmd, "raw", 1)) == 0x06040043
    ex = node.sdo["Excitation"]
    ex["Kind"].raw = 3
    ex["Period length N"].raw = 256
    ex["Multisine k_min"].raw = 50
    ex["Multisine k_max"].raw = 40                          # empty band
    assert _abort_of(lambda: setattr(cmd, "raw", 1)) == 0x06040043
    ex["Multisine k_max"].raw = 128                         # at Nyquist
    assert _abort_of(lambda: setattr(cmd, "raw", 1)) == 0x06040043
    assert node.sdo["Run control"]["Last stop reason"].raw == 5


def test_empty_domain_download_is_data_too_short(co_node):
    net, node = co_node
    node.sdo[0x2002].raw = struct.pack("<4f", 1, 2, 3, 4)
    index, sub, code = _abort(_raw(node, [0x21, 0x02, 0x20, 0, 0, 0, 0, 0]))  # size 0
    assert (index, code) == (0x2002, 0x06070013)
    assert _abort_of(lambda: node.sdo.download(0x2002, 0, b"\0" * 4)) == 0x06070013  # 1 sample
    assert node.sdo[0x2003].raw == 4


@pytest.mark.drive_sim_args("--realtime")
def test_modes_of_operation_matter(co_node):
    """Finding 13: mode 8 follows 0x607A and starts no run; -1 runs; the mode stays put
    while a run is active."""
    net, node = co_node
    node.nmt.state = "OPERATIONAL"
    enable_402(node)
    configure_sine_run(node)                                # sets mode -1
    node.sdo[0x6060].raw = 8
    assert node.sdo[0x6061].raw == 8
    cmd = node.sdo["Run control"]["Command"]
    assert _abort_of(lambda: setattr(cmd, "raw", 1)) == 0x08000022
    assert node.sdo["Run control"]["Run counter"].raw == 0
    node.sdo[0x607A].raw = 100000
    assert wait_for(lambda: abs(node.sdo[0x6064].raw - 100000) < 20000, 5.0)
    start_long_run(node)
    assert node.sdo["Run control"]["State"].raw in (1, 2)
    assert _abort_of(lambda: setattr(node.sdo[0x6060], "raw", 8)) == 0x08000022
    assert node.sdo[0x6061].raw == -1
    cmd.raw = 2
    node.sdo[0x6060].raw = 8
