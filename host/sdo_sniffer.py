"""Passive decoding of CANopen SDO traffic (CiA 301) from recorded CAN frames.

A listener on a bus (or a log replayed through :class:`can.LogReader`) sees both sides of
every SDO transfer; :class:`SdoSniffer` reassembles them into whole transfers: expedited,
segmented and block, uploads and downloads, with aborts. Block transfers honour the
client's acknowledged sequence number (segments after it are dropped; the server resends
them in a new sub-block numbered from 1) and the server's CRC (CRC-16-CCITT/XMODEM) is
checked.

Frame order: on a CAN bus a request precedes its response. A log taken from a gateway
(e.g. a second socketcand client) may show the server's answer before the client's frame
that caused it. The decoder therefore holds server frames that do not fit the present
state and replays them after the next client frame, and it separates block-transfer
sub-blocks by their sequence numbers rather than by the client's acknowledgements.
"""
import binascii
import struct
from dataclasses import dataclass

_HOLD_MAX = 512     # server frames kept while waiting for the client frame they answer


@dataclass
class SdoTransfer:
    """One finished (or aborted) SDO transfer."""

    timestamp: float       # of its last frame
    node_id: int
    direction: str         # 'download' (client -> drive) or 'upload' (drive -> client)
    index: int
    subindex: int
    data: bytes
    mode: str              # 'expedited', 'segmented', 'block', 'aborted'
    abort_code: int = None


class _Channel:
    def __init__(self, node_id):
        self.node_id = node_id
        self.held = []         # server frames waiting for their client frame: (data, ts)
        self.reset()

    def reset(self):
        self.state = None
        self.index = self.sub = 0
        self.buf = bytearray()
        self.blocks = []       # sub-blocks not yet acknowledged: lists of (seq, payload, last)
        self.last_seen = False
        self.pending_end = None
        self.size = None
        self.crc_on = False
        self.crc = None


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
            ch = self.channels[can_id - 0x600]
            self._client(ch, data, timestamp)
            held, ch.held = ch.held, []
            for d, ts in held:
                # Replayed once: a held frame still unmatched now answers nothing we saw.
                self._server(ch, d, ts, replay=True)
        elif 0x580 < can_id < 0x600 and (can_id - 0x580) in self.channels:
            self._server(self.channels[can_id - 0x580], data, timestamp)

    def _done(self, ch, direction, data, mode, ts, abort=None):
        self.transfers.append(SdoTransfer(ts, ch.node_id, direction, ch.index, ch.sub,
                                          bytes(data), mode, abort))
        ch.reset()

    def _hold(self, ch, d, ts, replay=False):
        if replay:
            return
        ch.held.append((d, ts))
        if len(ch.held) > _HOLD_MAX:
            del ch.held[0]

    def _abort(self, ch, d, ts):
        code = struct.unpack_from("<L", d, 4)[0]
        direction = "upload" if (ch.state or "").startswith(("ul", "bul")) else "download"
        self._done(ch, direction, ch.buf, "aborted", ts, abort=code)

    @staticmethod
    def _add_segment(ch, d):
        seq, last = d[0] & 0x7F, bool(d[0] & 0x80)
        if not ch.blocks or seq <= ch.blocks[-1][-1][0]:
            ch.blocks.append([])
        ch.blocks[-1].append((seq, d[1:8], last))

    @staticmethod
    def _ack_block(ch, ackseq):
        """The client acknowledged ``ackseq`` segments of the oldest open sub-block."""
        if not ch.blocks:
            return False
        block = ch.blocks.pop(0)
        for seq, payload, last in block:
            if seq <= ackseq:
                ch.buf += payload
                ch.last_seen = ch.last_seen or last
        return True

    def _finish_block_data(self, ch, n_unused, crc):
        if n_unused:
            del ch.buf[len(ch.buf) - n_unused:]
        if ch.crc_on and crc is not None:
            calc = binascii.crc_hqx(bytes(ch.buf), 0)
            if crc != calc:
                self.problems.append(f"node {ch.node_id} block transfer 0x{ch.index:04X}:"
                                     f"{ch.sub:02X}: CRC 0x{crc:04X} != 0x{calc:04X}")

    # ---- client -> server -------------------------------------------------------------
    def _client(self, ch, d, ts):
        cmd = d[0]
        if cmd == 0x80:
            if ch.state is not None:
                self._abort(ch, d, ts)
            return
        if ch.state == "bdl":
            self._add_segment(ch, d)               # block download: raw segments
            return
        ccs = cmd >> 5
        if ch.state == "bdl_end" and ccs == 6 and cmd & 0x01:
            n = (cmd >> 2) & 0x07
            self._finish_block_data(ch, n, struct.unpack_from("<H", d, 1)[0])
            ch.state = "bdl_end_sent"
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
        elif ccs == 5:                                 # block upload
            cs = cmd & 0x03
            if cs == 0:
                ch.reset()
                ch.index, ch.sub = struct.unpack_from("<HB", d, 1)
                ch.state = "bul_init"
            elif cs == 3 and ch.state == "bul_init":
                ch.state = "bul_data"
            elif cs == 2 and ch.state == "bul_data":   # block ack
                self._ack_block(ch, d[1])
                if ch.last_seen:
                    ch.state = "bul_end"
                    if ch.pending_end is not None:
                        n, crc = ch.pending_end
                        self._finish_block_data(ch, n, crc)
                        ch.state = "bul_end_ok"
            elif cs == 1 and ch.state == "bul_end_ok":
                self._done(ch, "upload", ch.buf, "block", ts)
        elif ccs == 6 and not cmd & 0x01:              # block download initiate
            ch.reset()
            ch.index, ch.sub = struct.unpack_from("<HB", d, 1)
            ch.crc_on = bool(cmd & 0x04)
            ch.size = struct.unpack_from("<L", d, 4)[0] if cmd & 0x02 else None
            ch.state = "bdl_init"

    # ---- server -> client -------------------------------------------------------------
    def _server(self, ch, d, ts, replay=False):
        cmd = d[0]
        if ch.state == "bul_data":
            if cmd == 0x80 and struct.unpack_from("<L", d, 4)[0] != 0:
                self._abort(ch, d, ts)
            elif ch.blocks and ch.blocks[-1][-1][2]:
                # After the last segment only the end-of-block response can follow.
                if cmd >> 5 == 6 and cmd & 0x01:
                    ch.pending_end = ((cmd >> 2) & 0x07, struct.unpack_from("<H", d, 1)[0])
            else:
                self._add_segment(ch, d)
            return
        if cmd == 0x80:
            if ch.state is not None:
                self._abort(ch, d, ts)
            else:
                self._hold(ch, d, ts, replay)
            return
        scs = cmd >> 5
        if ch.state == "dl_exp" and scs == 3:
            self._done(ch, "download", ch.buf, "expedited", ts)
        elif ch.state == "dl" and scs == 1:
            if ch.last_seen:
                self._done(ch, "download", ch.buf, "segmented", ts)
            else:
                self._hold(ch, d, ts, replay)           # may answer a segment still to come
        elif ch.state == "dl" and scs == 3:
            pass                                       # initiate response of a segmented download
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
        elif ch.state == "bul_init" and scs == 6 and not cmd & 0x01:
            ch.crc_on = bool(cmd & 0x04)
            ch.size = struct.unpack_from("<L", d, 4)[0] if cmd & 0x02 else None
        elif ch.state == "bul_init" and scs == 2 and not ch.crc_on and ch.size is None:
            # Server fell back to a normal upload (protocol switch threshold).
            ch.state = "ul_init"
            self._server(ch, d, ts, replay)
        elif ch.state == "bul_end" and scs == 6 and cmd & 0x01:
            self._finish_block_data(ch, (cmd >> 2) & 0x07, struct.unpack_from("<H", d, 1)[0])
            ch.state = "bul_end_ok"
        elif ch.state == "bdl_init" and scs == 5 and (cmd & 0x03) == 0:
            ch.state = "bdl"
        elif ch.state == "bdl" and scs == 5 and (cmd & 0x03) == 2:
            if not ch.blocks or not any(s[0] >= d[1] or s[2] for s in ch.blocks[0]):
                self._hold(ch, d, ts, replay)          # its segments are still to come
                return
            self._ack_block(ch, d[1])
            if ch.last_seen:
                ch.state = "bdl_end"
        elif ch.state == "bdl_end_sent" and scs == 5 and (cmd & 0x03) == 1:
            self._done(ch, "download", ch.buf, "block", ts)
        else:
            self._hold(ch, d, ts, replay)
