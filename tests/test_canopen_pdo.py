"""drive_sim's PDOs with python-canopen: TPDO reception (status, run progress), RPDOs, and a
mapping changed by PdoMap.save()."""
import statistics
import struct
import time

import pytest

from canopen_helpers import collect, configure_sine_run, enable_402, wait_for


def test_tpdos_report_status_and_run_progress(co_node):
    net, node = co_node
    node.tpdo.read()
    assert node.tpdo[1].enabled and node.tpdo[1].cob_id == 0x180 + node.id
    assert [v.index for v in node.tpdo[2]] == [0x2010, 0x2010]
    states, progress = [], []

    def on_run(pdo):
        states.append(pdo["Run control.State"].raw)
        progress.append(pdo["Run control.Progress"].raw)
    node.tpdo[2].add_callback(on_run)
    node.nmt.state = "OPERATIONAL"                      # every TPDO once on entering
    assert node.tpdo[1].wait_for_reception(1.0) is not None
    assert node.tpdo[1]["Statusword"].raw & 0x4F == 0x40
    # event timer 100 ms: the median of 6 intervals (one stall of a loaded machine moves it not)
    stamps = []
    for _ in range(7):
        assert node.tpdo[1].wait_for_reception(1.0) is not None
        stamps.append(time.monotonic())
    assert 0.05 < statistics.median(b - a for a, b in zip(stamps, stamps[1:])) < 0.2
    enable_402(node)
    assert wait_for(lambda: node.tpdo[1]["Statusword"].raw & 0x6F == 0x27, 5.0)
    total = 20 * 8192
    configure_sine_run(node, period=8192, settle=10, record=10, signals=0x01)
    node.sdo["Run control"]["Command"].raw = 1
    assert wait_for(lambda: 3 in states, 20.0)
    assert states[-1] == 3 and progress[-1] == total
    assert progress == sorted(progress)                      # monotonic run progress
    assert node.sdo["Run control"]["Progress"].raw == total


def test_rpdo_controlword_and_mode(co_node):
    net, node = co_node
    node.rpdo.read()
    node.tpdo.read()
    node.nmt.state = "OPERATIONAL"
    node.rpdo[1]["Controlword"].raw = 0x06
    node.rpdo[1].transmit()
    assert wait_for(lambda: node.tpdo[1]["Statusword"].raw & 0x6F == 0x21, 5.0)
    node.rpdo[2]["Modes of operation"].raw = -1
    node.rpdo[2].transmit()
    assert wait_for(lambda: node.tpdo[1]["Modes of operation display"].raw == -1, 5.0)
    node.rpdo[2]["Modes of operation"].raw = 5          # not supported: dropped
    node.rpdo[2].transmit()
    # the SDO read goes after the RPDO on the same connection: the drive has handled the
    # RPDO (frames are processed in their bus order) when it answers
    assert node.sdo[0x6060].raw == -1


def test_short_rpdo_gives_emcy(co_node):
    net, node = co_node
    node.nmt.state = "OPERATIONAL"
    emcys = []
    node.emcy.add_callback(emcys.append)
    net.send_message(0x200 + node.id, b"\x06")          # RPDO1 maps 2 bytes
    assert wait_for(lambda: any(e.code == 0x8210 for e in emcys), 5.0)


def test_remapped_tpdo_with_pdo_save(co_node):
    net, node = co_node
    node.tpdo.read()
    tpdo = node.tpdo[4]
    tpdo.clear()
    tpdo.add_variable(0x6064)
    tpdo.add_variable(0x606C)
    tpdo.trans_type = 255
    tpdo.event_timer = 50
    tpdo.inhibit_time = 0
    tpdo.enabled = True
    tpdo.cob_id = 0x480 + node.id
    tpdo.save()
    node.tpdo.read()                                    # what the node now holds
    assert node.tpdo[4].enabled and [v.index for v in node.tpdo[4]] == [0x6064, 0x606C]
    node.nmt.state = "OPERATIONAL"
    assert node.tpdo[4].wait_for_reception(1.0) is not None
    assert len(node.tpdo[4].data) == 8
    assert node.tpdo[4]["Position actual value"].raw == node.sdo[0x6064].raw
