"""CiA 402 basics: python-canopen's BaseNode402 brings drive_sim to OPERATION ENABLED over
its PDOs; the power state machine; runs only in OPERATION ENABLED."""
import struct
import time

import canopen
import pytest
from canopen.sdo import SdoAbortedError

from canopen_helpers import attach_node, collect, configure_sine_run, start_long_run, wait_for


@pytest.fixture
def node402(drive_sim):
    net, node = attach_node(drive_sim, canopen.BaseNode402)
    yield net, node
    net.disconnect()


def test_base_node_402_reaches_operation_enabled_over_pdos(node402):
    net, node = node402
    node.nmt.state = "OPERATIONAL"
    node.setup_402_state_machine()              # reads the PDO configuration by SDO
    assert 0x6040 in node.rpdo_pointers and 0x6060 in node.rpdo_pointers
    assert 0x6041 in node.tpdo_values and 0x6061 in node.tpdo_values
    sdo_requests = collect(net, 0x600 + node.id)
    node.state = "OPERATION ENABLED"
    assert node.state == "OPERATION ENABLED"
    assert sdo_requests == []                   # controlword and statusword went by PDO
    assert node.sdo[0x6041].raw & 0x6F == 0x27
    assert node.op_mode == "CYCLIC SYNCHRONOUS POSITION"
    node.state = "SWITCHED ON"
    assert node.sdo[0x6041].raw & 0x6F == 0x23
    node.state = "OPERATION ENABLED"
    node.state = "QUICK STOP ACTIVE"
    assert node.sdo[0x6041].raw & 0x6F == 0x07
    node.state = "SWITCH ON DISABLED"
    assert node.sdo[0x6041].raw & 0x4F == 0x40


def test_power_state_machine_by_sdo(co_node):
    net, node = co_node
    sw = lambda: node.sdo[0x6041].raw
    assert sw() & 0x4F == 0x40                          # switch on disabled after boot
    node.sdo[0x6040].raw = 0x0F                          # enable without the path: ignored
    assert sw() & 0x4F == 0x40
    for cw, mask, state in ((0x06, 0x6F, 0x21), (0x07, 0x6F, 0x23), (0x0F, 0x6F, 0x27),
                            (0x07, 0x6F, 0x23), (0x0F, 0x6F, 0x27), (0x02, 0x6F, 0x07),
                            (0x0F, 0x6F, 0x27), (0x06, 0x6F, 0x21), (0x00, 0x4F, 0x40)):
        node.sdo[0x6040].raw = cw
        assert sw() & mask == state, hex(cw)
    assert sw() & 0x0200                                   # remote


def test_target_position_moves_the_drive_in_csp(co_node):
    net, node = co_node
    node.nmt.state = "OPERATIONAL"
    for cw in (0x06, 0x07, 0x0F):
        node.sdo[0x6040].raw = cw
    # free-run holds simulated time while idle: a run advances it (the excitation is 0)
    node.sdo[0x607A].raw = 200000                          # 0.2 rad
    configure_sine_run(node, period=2048, record=5, amplitude=0.0)
    node.sdo["Run control"]["Command"].raw = 1
    assert wait_for(lambda: node.sdo["Run control"]["State"].raw == 3, 10.0)
    pos = node.sdo[0x6064].raw
    assert abs(pos - 200000) < 20000, pos
    assert abs(node.sdo[0x60F4].raw) < 20000


@pytest.mark.drive_sim_args("--realtime")
def test_a_run_starts_only_in_operation_enabled_and_disable_stops_it(co_node):
    net, node = co_node
    node.nmt.state = "OPERATIONAL"
    configure_sine_run(node)
    for cw in (0x06, 0x07):
        node.sdo[0x6040].raw = cw
        with pytest.raises(SdoAbortedError) as info:
            node.sdo["Run control"]["Command"].raw = 1
        assert info.value.code == 0x08000022
    node.sdo[0x6040].raw = 0x0F
    start_long_run(node)
    assert node.sdo["Run control"]["State"].raw in (1, 2)
    node.sdo[0x6040].raw = 0x07                               # disable operation
    assert node.sdo["Run control"]["State"].raw == 4
    assert node.sdo["Run control"]["Last stop reason"].raw == 3
