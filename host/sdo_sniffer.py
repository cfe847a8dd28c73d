"""Passive decoding of CANopen SDO traffic (CiA 301) from recorded CAN frames.

A listener on a bus (or a log replayed through :class:`can.LogReader`) sees both sides of
every SDO transfer; :class:`SdoSniffer` reassembles them into whole transfers: expedited,
segmented and block, uploads and downloads, with aborts. Block transfers honour the
client's acknowledged sequence number (segments after it are dropped and retransmitted)
and the server's CRC is checked (CRC-16-CCITT/XMODEM as in CiA 301).
"""
import binascii
import struct
from dataclasses import dataclass


@dataclass
class SdoTransfer:
    """One finished (or aborted) SDO transfer."""

    timestamp: float       # of its last frame
    node_id: int
    direction: str         # 'download' (client -> drive) or 'upload' (drive -> client)
    index: int
    subindex: int
    data: bytes
    mode: str              # 'expedited', 'segmented', 'block'
    abort_code: int = None


class _Channel:
    def __init__(self, node_id):
        self.node_id = node_id
        self.reset()

    def reset(self):
        self.state = None      # None, 'dl', 'ul', 'bdl', 'bul_init', 'bul_data', 'bul_end'
        self.index = self.sub = 0
        self.buf = bytearray()
        self.block = []        # segments of the present sub-block: (seqno, 7 bytes, last)
        self.last_seen = False
        self.size = None
        self.crc_on = False


class SdoSniffer:
    """Feed frames with :meth:`feed`; finished transfers collect in :attr:`transfers`.

    Parameters
    ----------
    node_ids : iterable of int, optional
        Servers to follow (default all 1..127) on the default SDO COB-IDs
        (0x600 + id requests, 0x580 + id responses).
    """

    def __init__(self, node_ids=None):
        ids = range(1, 128) if node_ids is None else node_ids
        self.channels = {nid: _Channel(nid) for nid in ids}
        self.transfers = []
        self.problems = []

    def feed(self, can_id, data, timestamp):
        data = bytes(data)
        if len(data) != 8:
            return
        if 0x600 < can_id < 0x680 and (can_id - 0x600) in self.channels:
            self._client(self.channels[can_id - 0x600], data, timestamp)
        elif 0x580 < can_id < 0x600 and (can_id - 0x580) in self.channels:
            self._server(self.channels[can_id - 0x580], data, timestamp)

    def _done(self, ch, direction, data, mode, ts, abort=None):
        self.transfers.append(SdoTransfer(ts, ch.node_id, direction, ch.index, ch.sub,
                                          bytes(data), mode, abort))
        ch.reset()

    # ---- client -> server -------------------------------------------------------------
    def _client(self, ch, d, ts):
        cmd = d[0]
        if ch.state == "bdl" and cmd != 0x80:
            # Block download sub-block: raw segments.
            ch.block.append((cmd & 0x7F, d[1:8], bool(cmd & 0x80)))
            return
        if ch.state == "bdl_end":
            if cmd >> 5 == 6 and cmd & 0x01:
                n = (cmd >> 2) & 0x07
                data = bytes(ch.buf[:len(ch.buf) - n]) if n else bytes(ch.buf)
                ch.buf = bytearray(data)
                ch.pending_crc = struct.unpack_from("<H", d, 1)[0] if ch.crc_on else None
                ch.state = "bdl_end_ack"
            return
        ccs = cmd >> 5
        if cmd == 0x80:
            if ch.state is not None:
                code = struct.unpack_from("<L", d, 4)[0]
                self._done(ch, "upload" if ch.state.startswith(("ul", "bul")) else "download",
                           ch.buf, "aborted", ts, abort=code)
            return
        if ccs == 1:                                   # initiate download
            ch.reset()
            ch.index, ch.sub = struct.unpack_from("<HB", d, 1)
            if cmd & 0x02:                             # expedited
                n = (cmd >> 2) & 0x03 if cmd & 0x01 else 0
                ch.buf = bytearray(d[4:8 - n])
                ch.state = "dl_exp"
            else:
                ch.size = struct.unpack_from("<L", d, 4)[0] if cmd & 0x01 else None
                ch.state = "dl"
        elif ccs == 0 and ch.state == "dl":            # download segment
            n = (cmd >> 1) & 0x07
            ch.buf += d[1:8 - n]
            ch.last_seen = bool(cmd & 0x01)
        elif ccs == 2:                                 # initiate upload
            ch.reset()
            ch.index, ch.sub = struct.unpack_from("<HB", d, 1)
            ch.state = "ul_init"
        elif ccs == 3:                                 # upload segment request
            pass
        elif ccs == 5:                                 # block upload
            cs = cmd & 0x03
            if cs == 0:
                ch.reset()
                ch.index, ch.sub = struct.unpack_from("<HB", d, 1)
                ch.state = "bul_init"
            elif cs == 3 and ch.state == "bul_init":
                ch.state = "bul_data"
                ch.block = []
            elif cs == 2 and ch.state == "bul_data":   # block ack
                ackseq = d[1]
                accepted = [s for s in ch.block if s[0] <= ackseq]
                for seq, payload, last in sorted(accepted):
                    ch.buf += payload
                    if last:
                        ch.last_seen = True
                ch.block = []
                if ch.last_seen:
                    ch.state = "bul_end"
            elif cs == 1 and ch.state == "bul_end_ok":
                self._done(ch, "upload", ch.buf, "block", ts)
        elif ccs == 6:                                 # block download initiate
            if not cmd & 0x01:
                ch.reset()
                ch.index, ch.sub = struct.unpack_from("<HB", d, 1)
                ch.crc_on = bool(cmd & 0x04)
                ch.size = struct.unpack_from("<L", d, 4)[0] if cmd & 0x02 else None
                ch.state = "bdl_init"

    # ---- server -> client -------------------------------------------------------------
    def _server(self, ch, d, ts):
        cmd = d[0]
        if ch.state == "bul_data":
            if cmd == 0x80 and struct.unpack_from("<L", d, 4)[0] != 0:
                code = struct.unpack_from("<L", d, 4)[0]
                self._done(ch, "upload", ch.buf, "aborted", ts, abort=code)
                return
            ch.block.append((cmd & 0x7F, d[1:8], bool(cmd & 0x80)))
            return
        if cmd == 0x80:
            if ch.state is not None:
                code = struct.unpack_from("<L", d, 4)[0]
                direction = "upload" if ch.state.startswith(("ul", "bul")) else "download"
                self._done(ch, direction, ch.buf, "aborted", ts, abort=code)
            return
        scs = cmd >> 5
        if ch.state == "dl_exp" and scs == 3:
            self._done(ch, "download", ch.buf, "expedited", ts)
        elif ch.state == "dl" and scs == 1 and ch.last_seen:
            self._done(ch, "download", ch.buf, "segmented", ts)
        elif ch.state == "ul_init" and scs == 2:
            if cmd & 0x02:                             # expedited
                n = (cmd >> 2) & 0x03 if cmd & 0x01 else 0
                self._done(ch, "upload", d[4:8 - n], "expedited", ts)
            else:
                ch.size = struct.unpack_from("<L", d, 4)[0] if cmd & 0x01 else None
                ch.state = "ul"
        elif ch.state == "ul" and scs == 0:
            n = (cmd >> 1) & 0x07
            ch.buf += d[1:8 - n]
            if cmd & 0x01:
                self._done(ch, "upload", ch.buf, "segmented", ts)
        elif ch.state == "bul_init":
            if scs == 6 and (cmd & 0x01) == 0:
                ch.crc_on = bool(cmd & 0x04)
                ch.size = struct.unpack_from("<L", d, 4)[0] if cmd & 0x02 else None
            elif scs == 2:
                # Server fell back to a normal upload (protocol switch threshold).
                ch.state = "ul_init"
                self._server(ch, d, ts)
        elif ch.state == "bul_end" and scs == 6 and (cmd & 0x01) == 1:
            n = (cmd >> 2) & 0x07
            if n:
                del ch.buf[len(ch.buf) - n:]
            if ch.crc_on:
                crc = struct.unpack_from("<H", d, 1)[0]
                calc = binascii.crc_hqx(bytes(ch.buf), 0)
                if crc != calc:
                    self.problems.append(f"node {ch.node_id} block upload 0x{ch.index:04X}:"
                                         f"{ch.sub:02X}: CRC 0x{crc:04X} != 0x{calc:04X}")
            ch.state = "bul_end_ok"
        elif ch.state == "bdl_init" and scs == 5 and (cmd & 0x03) == 0:
            ch.state = "bdl"
            ch.block = []
        elif ch.state == "bdl" and scs == 5 and (cmd & 0x03) == 2:
            ackseq = d[1]
            for seq, payload, last in sorted(s for s in ch.block if s[0] <= ackseq):
                ch.buf += payload
                if last:
                    ch.last_seen = True
            ch.block = []
            if ch.last_seen:
                ch.state = "bdl_end"
        elif ch.state == "bdl_end_ack" and scs == 5 and (cmd & 0x03) == 1:
            self._done(ch, "download", ch.buf, "block", ts)
