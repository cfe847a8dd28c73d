"""The passive SDO decoder against python-canopen as the peer (client and server).

A RemoteNode (client) talks to a LocalNode (server) on python-can's virtual bus; a third
virtual-bus listener feeds every frame to the sniffer, which must reassemble the same bytes
the client wrote and read. Block transfers are checked against drive_sim in
tests/test_host_canlog.py (python-canopen's LocalNode has no block transfer).
"""
import struct
import time

import can
import canopen
import pytest

from fftune.host.sdo_sniffer import SdoSniffer


def _od():
    od = canopen.ObjectDictionary()
    dom = canopen.objectdictionary.ODVariable("Blob", 0x2021, 0)
    dom.data_type = canopen.objectdictionary.DOMAIN
    dom.access_type = "rw"
    od.add_object(dom)
    rec = canopen.objectdictionary.ODRecord("Controller", 0x2000)
    kfc = canopen.objectdictionary.ODVariable("K_fc", 0x2000, 4)
    kfc.data_type = canopen.objectdictionary.REAL32
    kfc.access_type = "rw"
    rec.add_member(kfc)
    od.add_object(rec)
    return od


@pytest.fixture
def bus_pair():
    channel = f"sniff-{time.monotonic_ns()}"
    net_c, net_s = canopen.Network(), canopen.Network()
    net_c.connect(interface="virtual", channel=channel, receive_own_messages=False)
    net_s.connect(interface="virtual", channel=channel, receive_own_messages=False)
    spy = can.Bus(interface="virtual", channel=channel)
    sniffer = SdoSniffer([5])
    notifier = can.Notifier(spy, [lambda m: sniffer.feed(m.arbitration_id, m.data, m.timestamp)])
    server = canopen.LocalNode(5, _od())
    net_s.add_node(server)
    client = canopen.RemoteNode(5, _od())
    net_c.add_node(client)
    yield client, server, sniffer
    notifier.stop()
    spy.shutdown()
    net_c.disconnect()
    net_s.disconnect()


def _wait(sniffer, n, timeout=2.0):
    t = time.monotonic() + timeout
    while len(sniffer.transfers) < n and time.monotonic() < t:
        time.sleep(0.01)


def test_expedited_download_and_upload_are_reassembled(bus_pair):
    client, server, sniffer = bus_pair
    client.sdo[0x2000][4].raw = 0.125
    assert client.sdo[0x2000][4].raw == pytest.approx(0.125)
    _wait(sniffer, 2)
    dl, ul = sniffer.transfers[:2]
    assert (dl.direction, dl.mode, dl.index, dl.subindex) == ("download", "expedited", 0x2000, 4)
    assert struct.unpack("<f", dl.data)[0] == 0.125
    assert (ul.direction, ul.mode) == ("upload", "expedited")
    assert ul.data == dl.data


def test_segmented_transfers_are_reassembled(bus_pair):
    client, server, sniffer = bus_pair
    payload = bytes(range(256)) * 3 + b"tail!"       # not a multiple of 7: short last segment
    client.sdo[0x2021].raw = payload
    got = client.sdo[0x2021].raw
    assert got == payload
    _wait(sniffer, 2)
    dl, ul = sniffer.transfers[:2]
    assert (dl.direction, dl.mode, dl.data) == ("download", "segmented", payload)
    assert (ul.direction, ul.mode, ul.data) == ("upload", "segmented", payload)


def test_abort_is_reported_with_its_code(bus_pair):
    client, server, sniffer = bus_pair
    with pytest.raises(canopen.SdoAbortedError):
        client.sdo.upload(0x2000, 9)                 # no such sub-index on the server
    _wait(sniffer, 1)
    tr = sniffer.transfers[0]
    assert tr.abort_code in (0x06090011, 0x06020000)
    assert (tr.index, tr.subindex) == (0x2000, 9)


def test_block_upload_with_retransmission_keeps_only_acknowledged_segments():
    # Synthetic frames, CiA 301 block upload: blksize 4, the client acknowledges only 2
    # segments of the first block; the server resends 3 and 4.
    import binascii
    data = bytes(range(40))                            # 6 segments, the last with 5 bytes
    segs = [data[i:i + 7] for i in range(0, len(data), 7)]
    sn = SdoSniffer([1])
    c, s = 0x601, 0x581
    feed = lambda cid, b: sn.feed(cid, bytes(b) + bytes(8 - len(b)), 0.0)
    feed(c, [0xA4, 0x21, 0x20, 0x00, 4, 0])                        # initiate, crc
    feed(s, [0xC6, 0x21, 0x20, 0x00] + list(struct.pack("<L", 40)))
    feed(c, [0xA3])
    for i in range(4):
        feed(s, [i + 1] + list(segs[i].ljust(7, b"\0")))
    feed(c, [0xA2, 2, 4])                                          # only 1..2 accepted
    for i in range(2, 6):
        last = 0x80 if i == 5 else 0
        feed(s, [(i - 1) | last] + list(segs[i].ljust(7, b"\0")))
    feed(c, [0xA2, 4, 4])
    crc = binascii.crc_hqx(data, 0)
    feed(s, [0xC1 | (2 << 2)] + list(struct.pack("<H", crc)))     # 2 unused bytes
    feed(c, [0xA1])
    assert not sn.problems
    assert len(sn.transfers) == 1
    assert sn.transfers[0].mode == "block"
    assert sn.transfers[0].data == data


def test_block_upload_crc_mismatch_is_a_problem():
    sn = SdoSniffer([1])
    feed = lambda cid, b: sn.feed(cid, bytes(b) + bytes(8 - len(b)), 0.0)
    feed(0x601, [0xA4, 0x21, 0x20, 0x00, 4, 0])
    feed(0x581, [0xC6, 0x21, 0x20, 0x00, 3, 0, 0, 0])
    feed(0x601, [0xA3])
    feed(0x581, [0x81, 1, 2, 3, 0, 0, 0, 0])
    feed(0x601, [0xA2, 1, 4])
    feed(0x581, [0xC1 | (4 << 2), 0x12, 0x34])
    assert sn.problems and "CRC" in sn.problems[0]


def _block_upload_frames(data, blksize=4):
    """A clean CiA 301 block upload of ``data`` as (can_id, bytes) in bus order."""
    import binascii
    segs = [data[i:i + 7] for i in range(0, len(data), 7)]
    frames = [(0x601, [0xA4, 0x21, 0x20, 0x00, blksize, 0]),
              (0x581, [0xC6, 0x21, 0x20, 0x00] + list(struct.pack("<L", len(data)))),
              (0x601, [0xA3])]
    for b in range(0, len(segs), blksize):
        block = segs[b:b + blksize]
        for i, seg in enumerate(block):
            last = 0x80 if b + i == len(segs) - 1 else 0
            frames.append((0x581, [(i + 1) | last] + list(seg.ljust(7, b"\0"))))
        frames.append((0x601, [0xA2, len(block), blksize]))
    unused = 7 * len(segs) - len(data)
    frames.append((0x581, [0xC1 | (unused << 2)] + list(struct.pack("<H", binascii.crc_hqx(data, 0)))))
    frames.append((0x601, [0xA1]))
    return frames


def _responses_first(frames):
    """Gateway order: every server frame moved before the client frame that caused it."""
    out, pending_client = [], None
    for cid, d in frames:
        if cid == 0x601:
            if pending_client is not None:
                out.append(pending_client)
            pending_client = (cid, d)
        else:
            out.append((cid, d))
    out.append(pending_client)
    return out


@pytest.mark.parametrize("order", ["bus", "responses first"])
def test_block_upload_over_several_sub_blocks_in_either_frame_order(order):
    data = bytes((7 * i) & 0xFF for i in range(100))       # 15 segments, 4 sub-blocks
    frames = _block_upload_frames(data)
    if order != "bus":
        frames = _responses_first(frames)
    # plus an expedited upload, answered before it was asked in the gateway order
    exp = [(0x601, [0x40, 0x00, 0x10, 0x00]), (0x581, [0x43, 0x00, 0x10, 0x00, 0x92, 0x01, 0x02, 0x00])]
    frames += exp if order == "bus" else exp[::-1]
    sn = SdoSniffer([1])
    for cid, d in frames:
        sn.feed(cid, bytes(d) + bytes(8 - len(d)), 0.0)
    assert not sn.problems
    assert [t.mode for t in sn.transfers] == ["block", "expedited"]
    assert sn.transfers[0].data == data
    assert sn.transfers[1].data == struct.pack("<L", 0x00020192)
