"""The enable rule and the heartbeat timing of DriveClient (host/drive.py; issue 33's
hand-written bug audit, docs/testing.md): the power stage goes on only when the drive's
heartbeat consumer (0x1016:1, read back) watches exactly this host's heartbeat (its node
id AND 4 x its period) and that heartbeat is running with the client's id and period (each
condition broken alone on drive_sim, the refusal named, the drive left disabled; then the
rule met and the drive enabled); the drive's heartbeat is lost after 10 of its periods (at
least 1 s) of silence; the SDO bursts share 1.5 heartbeat periods among the bus' drives.
"""
import math
import os
import struct
import time

import canopen
import pytest

from fftune.analysis.errors import FftuneError
from fftune.host.drive import BusOptions, DriveClient, HostHeartbeat, _open_bus, sdo_burst_frames
from fftune.host.sim import start_drive_sim
from host_fixtures import EDS, REPO, drive_sim_missing_reason

needs_drive_sim = pytest.mark.skipif(drive_sim_missing_reason() is not None,
                                     reason=drive_sim_missing_reason() or "")


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    d = tmp_path_factory.mktemp("enable_rule")
    s = start_drive_sim(os.path.join(REPO, "configs", "plant_twomass.yaml"), log_path=str(d / "drive_sim.log"))
    yield s
    s.stop()


def _status(c):
    return struct.unpack("<H", c.node.sdo.upload(0x6041, 0))[0]


@needs_drive_sim
def test_enable_refused_unless_the_consumer_reads_back_this_hosts_id_and_4x_its_period(sim):
    with DriveClient(BusOptions(port=sim.port, eds=EDS), heartbeat_ms=110, host_node_id=0x7D,
                     progress=False) as c:
        assert int(c.read(0x1016, 1)) == (0x7D << 16) | 440            # armed by connect()
        # the right host, another time (as another tool or a drive that kept its own
        # value would leave it): 0x07D03E8 (1000 ms), not 0x07D01B8 (4 x 110 ms)
        c.write(0x1016, 1, (0x7D << 16) | 1000)
        with pytest.raises(FftuneError) as exc:
            c.enable()
        assert str(exc.value) == ("node 1 not enabled: its heartbeat consumer 0x1016:1 reads 0x007D03E8, "
                                  "not 0x007D01B8 (host node 125 every 110 ms, 4 x the period)")
        assert _status(c) & 0x6F != 0x27
        # the period right, another host id
        c.write(0x1016, 1, (0x7C << 16) | 440)
        with pytest.raises(FftuneError, match="reads 0x007C01B8, not 0x007D01B8"):
            c.enable()
        assert _status(c) & 0x6F != 0x27
        # the period x1 (the consumer would time out between two heartbeats)
        c.write(0x1016, 1, (0x7D << 16) | 110)
        with pytest.raises(FftuneError, match="reads 0x007D006E, not 0x007D01B8"):
            c.enable()
        # armed for this host: enabled
        c.write(0x1016, 1, (0x7D << 16) | 440)
        c.enable()
        assert _status(c) & 0x6F == 0x27
    with DriveClient(BusOptions(port=sim.port, eds=EDS), heartbeat_ms=0, progress=False) as c:
        assert _status(c) & 0x6F != 0x27                             # close() disabled it


@needs_drive_sim
def test_enable_on_a_shared_bus_needs_the_owners_heartbeat_running_with_this_id_and_period(sim):
    net = canopen.Network(_open_bus(BusOptions(port=sim.port, eds=EDS)))
    net.connect()
    try:
        hb = HostHeartbeat(net, 0x7F, 120)          # made, not started
        c = DriveClient(BusOptions(port=sim.port, eds=EDS), heartbeat_ms=120, network=net, host_heartbeat=hb,
                        progress=False)
        c.connect()
        try:
            assert int(c.read(0x1016, 1)) == (0x7F << 16) | 480
            with pytest.raises(FftuneError) as exc:
                c.enable()
            assert str(exc.value) == "node 1 not enabled: this host sends no heartbeat on its bus"
            assert _status(c) & 0x6F != 0x27
        finally:
            c.close()
        other = HostHeartbeat(net, 0x7F, 250).start()   # the bus' heartbeat: another period
        try:
            c = DriveClient(BusOptions(port=sim.port, eds=EDS), heartbeat_ms=120, network=net,
                            host_heartbeat=other, progress=False)
            c.connect()
            try:
                with pytest.raises(FftuneError) as exc:
                    c.enable()
                assert str(exc.value) == ("node 1 not enabled: its consumer would watch host node 127 every "
                                          "120 ms, this host sends host node 127 every 250 ms")
                assert _status(c) & 0x6F != 0x27
            finally:
                c.close()
        finally:
            other.stop()
    finally:
        net.disconnect()


@pytest.mark.parametrize("heartbeat_ms, limit_s", [(150, 1.5), (40, 1.0), (230, 2.3)])
def test_drive_heartbeat_lost_after_ten_periods_at_least_one_second(heartbeat_ms, limit_s):
    """No bus: the client's record of the drive's last heartbeat set by hand."""
    c = DriveClient(BusOptions(node_id=3, eds=EDS), heartbeat_ms=heartbeat_ms, progress=False)
    c._last_hb = time.monotonic() - (limit_s - 0.05)
    c._check_heartbeat()                                     # silent less than the limit: fine
    c._last_hb = time.monotonic() - (limit_s + 0.05)
    with pytest.raises(FftuneError, match=r"^heartbeat of node 3 lost \(\d+\.\d s silent\)"):
        c._check_heartbeat()


def _frame_s(bitrate):
    # a CAN 2.0A frame of 8 data bytes: 111 bit times with the interframe space, plus at
    # most one stuff bit per 4 of the 97 stuffed bits (24): 135
    return (111 + (34 + 64 - 1) // 4) / bitrate


@pytest.mark.parametrize("bitrate, heartbeat_ms, nodes", [
    (20000, 100, 1), (20000, 100, 3), (125000, 50, 2), (50000, 250, 5), (1000000, 10, 4)])
def test_sdo_burst_shares_one_and_a_half_heartbeat_periods_among_the_drives(bitrate, heartbeat_ms, nodes):
    want = min(127, math.floor(1.5 * heartbeat_ms / 1000.0 / (nodes * _frame_s(bitrate))))
    assert sdo_burst_frames(bitrate, heartbeat_ms, nodes) == want
    # (written out: 20 kbit/s, 100 ms: 22 frames for one drive, 7 for three)
    assert sdo_burst_frames(20000, 100, 1) == 22 and sdo_burst_frames(20000, 100, 3) == 7


def test_sdo_burst_refused_when_not_one_frame_per_drive_fits():
    # 10 kbit/s: 13.5 ms a frame; 1.5 x 20 ms = 30 ms holds 2 frames, not 3
    assert sdo_burst_frames(10000, 20, 2) == 1
    with pytest.raises(FftuneError, match="one SDO frame of each of 3 node"):
        sdo_burst_frames(10000, 20, 3)
    assert sdo_burst_frames(None, 20, 3) == 127 and sdo_burst_frames(10000, 0, 3) == 127


class _Net:
    """The one attribute _SdoPacer wraps: send_message (records what reaches the bus)."""

    def __init__(self):
        self.sent = []

    def send_message(self, can_id, data, remote=False):
        self.sent.append(can_id)


def test_the_sdo_pacer_takes_a_token_for_each_sdo_request_and_for_nothing_else():
    """At 10 bit/s a token comes back every 135 / 10 / 0.7 = 19 s: the bucket's count is the
    requests sent (no refill within the test). SDO requests are 0x601 .. 0x67F (0x600 +
    node 1 .. 127); the host's heartbeat, NMT, an SDO response COB-ID and 0x600, 0x680 are
    not paced."""
    from fftune.host.drive import _SdoPacer

    net = _Net()
    pacer = _SdoPacer(net, 10, 5)
    assert pacer.interval_s == pytest.approx(135 / 10 / 0.7)
    for can_id in (0x605, 0x67F, 0x601):
        net.send_message(can_id, b"\x40\x00\x10\x00\x00\x00\x00\x00")
    assert pacer.tokens == pytest.approx(2.0, abs=0.01)
    for can_id in (0x77F, 0x000, 0x585, 0x600, 0x680, 0x705):
        net.send_message(can_id, b"\x05")
    assert pacer.tokens == pytest.approx(2.0, abs=0.01)
    assert net.sent == [0x605, 0x67F, 0x601, 0x77F, 0x000, 0x585, 0x600, 0x680, 0x705]


@needs_drive_sim
@pytest.mark.parametrize("before, after", [(0, 2), (3, 3), (1, 1), (2, 2)])
def test_enable_arms_the_lost_host_reaction_unless_the_integrator_chose_one(sim, before, after):
    """0x6007 = 0 (no action: the drive would stay enabled after the host died) is set to
    2 (disable voltage) before the power stage goes on; 1 (fault) and 3 (quick stop) are
    kept."""
    with DriveClient(BusOptions(port=sim.port, eds=EDS), heartbeat_ms=100, progress=False) as c:
        c.write(0x6007, 0, before)
        c.enable()
        assert int(c.read(0x6007, 0)) == after
        assert _status(c) & 0x6F == 0x27
        c.write(0x6040, 0, 0x0006)                   # (disabled before the next case)
        c.write(0x6007, 0, 2)


@needs_drive_sim
def test_an_enabled_drive_is_not_enabled_again_before_a_run(sim, caplog):
    import logging

    with DriveClient(BusOptions(port=sim.port, eds=EDS), heartbeat_ms=100, progress=False) as c:
        c.enable()
        with caplog.at_level(logging.WARNING, logger="fftune"):
            c._ensure_enabled()
        assert not [r for r in caplog.records if "left OPERATION ENABLED" in r.getMessage()]
        # the power stage off behind the client's back: enabled again, saying so
        c.write(0x6040, 0, 0x0006)
        with caplog.at_level(logging.WARNING):
            c._ensure_enabled()
        assert [r for r in caplog.records if "left OPERATION ENABLED" in r.getMessage()]
        assert _status(c) & 0x6F == 0x27


@needs_drive_sim
def test_one_heartbeat_frame_of_another_producer_refuses_the_host_id(sim):
    """Another node sends ONE heartbeat on the host's COB-ID while the host listens (2 s
    for a 1 s period): refused, naming the COB-ID and the frame count."""
    import threading

    import can

    net = canopen.Network(_open_bus(BusOptions(port=sim.port, eds=EDS)))
    net.connect()
    other = can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port)
    try:
        timer = threading.Timer(0.4, lambda: other.send(can.Message(arbitration_id=0x77B, data=[0x05],
                                                                    is_extended_id=False)))
        timer.start()
        hb = HostHeartbeat(net, 0x7B, 1000)
        with pytest.raises(FftuneError) as exc:
            hb.start()
        timer.join()
        assert str(exc.value).startswith("another node sends heartbeats on COB-ID 0x77B (host node id 123): "
                                         "1 frame(s) in 2000 ms, state OPERATIONAL")
        assert not hb.running
    finally:
        other.shutdown()
        net.disconnect()
