#!/usr/bin/env python3
"""Write the seed corpora of the libFuzzer targets (fuzz_co_node.c, fuzz_scd.c).

The seeds are the frame sequences a CANopen master exchanges with the node in the
conformance tests, in the record format of ``fuzz_co_node.c``: NMT transitions, an
expedited / segmented read of every object of the EDS, writes of valid and invalid values
(NaN, inf, beyond the limits), segmented and block (CRC) download of a waveform table, a
complete excitation run followed by a block upload (with retransmission and back-pressure)
and a segmented upload of the recorder, heartbeat producer / consumer with host loss during
a run, PDO mapping and RPDO reception, SDO timeouts and protocol errors. For ``fuzz_scd``:
python-can's socketcand handshake and ``send`` lines, split across TCP reads and clients.

Usage: gen_seeds.py EDS OUTDIR   (writes OUTDIR/co_node/*.bin and OUTDIR/scd/*.bin)
"""
import configparser
import math
import os
import struct
import sys

NODE = 1

# ---- fuzz_co_node record encoders -------------------------------------------------------


def sdo(*data):
    """SDO request (8 bytes) to 0x600 + node."""
    b = bytes(data) + bytes(8 - len(data))
    return bytes([0]) + b[:8]


def frame(cob_id, data):
    return bytes([1, cob_id & 0xFF, cob_id >> 8, len(data)]) + bytes(data) + bytes(8 - len(data))


def nmt(cmd, node=NODE):
    return bytes([2, cmd, node])


def heartbeat(node, state=5):
    return bytes([3, node, state])


def wait_us(us):
    """Time passes (co_node_process); split into records of at most 0xFFFF * 16 us."""
    out = b""
    ticks = max(1, int(round(us / 16)))
    while ticks > 0:
        t = min(ticks, 0xFFFF)
        out += bytes([4, t & 0xFF, t >> 8])
        ticks -= t
    return out


def steps(n):
    out = b""
    while n > 0:
        t = min(n, 0xFFFF)
        out += bytes([5, t & 0xFF, t >> 8])
        n -= t
    return out


def backpressure(on, background=0):
    """Op 6: transmit back-pressure on / off and the background schedule B (0: never, else
    drv_background after every B-th controller step and once per time record)."""
    return bytes([6, (1 if on else 0) | (background << 1)])


def rpdo(which, data):
    return bytes([7, which, len(data)]) + bytes(data) + bytes(8 - len(data))


def mux(index, sub):
    return [index & 0xFF, index >> 8, sub]


def upload(index, sub):
    return sdo(0x40, *mux(index, sub))


def write_u(index, sub, value, size):
    n = 4 - size
    return sdo(0x23 | (n << 2), *mux(index, sub), *value.to_bytes(size, "little"))


def write_f32(index, sub, value):
    return sdo(0x23, *mux(index, sub), *struct.pack("<f", value))


def crc16(data):
    """CRC-16 CCITT (XMODEM), the SDO block transfer CRC."""
    crc = 0
    for b in data:
        crc ^= b << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


def segmented_upload(index, sub, nseg):
    out = upload(index, sub) + wait_us(1000)
    for k in range(nseg):
        out += sdo(0x60 | (0x10 if k % 2 else 0)) + wait_us(1000)
    return out


def segmented_download(index, sub, payload):
    out = sdo(0x21, *mux(index, sub), *len(payload).to_bytes(4, "little")) + wait_us(1000)
    for k in range(0, len(payload), 7):
        chunk = payload[k:k + 7]
        last = k + 7 >= len(payload)
        toggle = 0x10 if (k // 7) % 2 else 0
        cmd = toggle | ((7 - len(chunk)) << 1) | (1 if last else 0)
        out += sdo(cmd, *chunk) + wait_us(500)
    return out


def block_download(index, sub, payload, blksize=127, crc=True):
    out = sdo(0xC2 | (0x04 if crc else 0), *mux(index, sub), *len(payload).to_bytes(4, "little"))
    out += wait_us(1000)
    segs = [payload[k:k + 7] for k in range(0, len(payload), 7)]
    seq = 0
    for i, s in enumerate(segs):
        seq += 1
        last = i == len(segs) - 1
        out += sdo((0x80 if last else 0) | seq, *s)
        if seq == blksize:
            seq = 0
            out += wait_us(200)
    unused = 7 - len(segs[-1])
    out += wait_us(1000)
    out += sdo(0xC1 | (unused << 2), *crc16(payload).to_bytes(2, "little"))
    return out + wait_us(1000)


def block_upload(index, sub, size, blksize=127, retransmit=False, pressure=False):
    """Client side of a block upload of `size` bytes: initiate, start, acks, end confirm."""
    out = sdo(0xA4, *mux(index, sub), blksize, 0) + wait_us(1000)
    out += sdo(0xA3)
    if pressure:
        out += backpressure(True) + wait_us(2000) + backpressure(False)
    out += wait_us(2000)
    nseg = (size + 6) // 7
    sent = 0
    first = True
    while sent < nseg:
        in_block = min(blksize, nseg - sent)
        if retransmit and first and in_block > 3:
            ack = in_block - 3  # lost the last three segments of the first block
            first = False
        else:
            ack = in_block
        out += sdo(0xA2, ack, blksize) + wait_us(2000)
        sent += ack
    out += sdo(0xA1) + wait_us(1000)
    return out


def operational_enabled():
    """NMT start, mode -1 (excitation runs) and CiA 402 to OPERATION ENABLED (shutdown,
    switch on, enable)."""
    out = nmt(0x01) + wait_us(1000) + write_u(0x6060, 0, 0xFF, 1)
    for cw in (0x06, 0x07, 0x0F):
        out += write_u(0x6040, 0, cw, 2) + wait_us(1000)
    return out


def setup_sine_run(period=32, record=2, settle=0, amplitude=0.2, signals=0x07):
    out = write_u(0x2001, 1, 1, 1)  # kind: sine
    out += write_f32(0x2001, 3, amplitude)
    out += write_u(0x2001, 5, period, 4)
    out += write_u(0x2001, 7, settle, 4)
    out += write_u(0x2001, 8, record, 4)
    out += write_u(0x2020, 1, signals, 4)
    return out


def start_run():
    return write_u(0x2010, 1, 1, 1)


def eds_objects(eds_path):
    """(index, sub, datatype, access) of every variable of the EDS."""
    cp = configparser.ConfigParser(strict=False, interpolation=None)
    cp.optionxform = str
    cp.read(eds_path)
    out = []
    for sec in cp.sections():
        name = sec.lower()
        try:
            if "sub" in name:
                idx, sub = name.split("sub")
                index, subi = int(idx, 16), int(sub, 16)
            else:
                index, subi = int(name, 16), 0
        except ValueError:
            continue
        dt = cp[sec].get("DataType")
        if dt is None:
            continue
        out.append((index, subi, int(dt, 0), cp[sec].get("AccessType", "ro").lower()))
    return sorted(out)


def write_objects(objs):
    """Expedited writes of valid and invalid values (NaN, inf, beyond the limits, wrong length)."""
    writes = b""
    for i, s, dt, acc in objs:
        if dt == 0x0008:  # REAL32: a plain value, NaN, +inf, -inf, far beyond the limits
            for v in (0.5, math.nan, math.inf, -math.inf, 1e30, -1e30, -0.0):
                writes += write_f32(i, s, v) + wait_us(200)
        elif dt in (0x0005, 0x0002, 0x0001):
            writes += write_u(i, s, 0xFF, 1) + write_u(i, s, 1, 1)
        elif dt in (0x0006, 0x0003):
            writes += write_u(i, s, 0xFFFF, 2) + write_u(i, s, 0, 2)
        elif dt in (0x0007, 0x0004):
            writes += write_u(i, s, 0xFFFFFFFF, 4) + write_u(i, s, 0x80000000, 4) + write_u(i, s, 4, 4)
        # wrong length on purpose
        writes += sdo(0x2F, *mux(i, s), 1) + sdo(0x27, *mux(i, s), 1, 2, 3)
    return writes


def co_node_seeds(eds_path):
    objs = eds_objects(eds_path)
    seeds = {}
    seeds["nmt_cycle"] = (nmt(0x01) + wait_us(2000) + nmt(0x02) + wait_us(2000) + nmt(0x80) + nmt(0x01, 0)
                          + nmt(0x82) + wait_us(1000) + nmt(0x81) + wait_us(1000) + nmt(0x01, 5) + nmt(0x99))
    # (long sequences are split into several seeds of at most ~1.5 kB: short inputs keep
    # the executions fast and libFuzzer's -max_len small)
    for k in range(0, len(objs), 100):
        seeds["read_objects_%03d" % k] = b"".join(upload(i, s) + wait_us(300) for i, s, _, _ in objs[k:k + 100])
    for k in range(0, len(objs), 40):
        seeds["read_objects_segmented_%03d" % k] = b"".join(segmented_upload(i, s, 3) for i, s, _, _ in objs[k:k + 40])
    for k in range(0, len(objs), 30):
        seeds["write_objects_%03d" % k] = write_objects(objs[k:k + 30])
    table = b"".join(struct.pack("<f", 0.1 * math.sin(2 * math.pi * k / 64)) for k in range(64))
    seeds["table_segmented_download"] = segmented_download(0x2002, 0, table) + upload(0x2003, 0)
    seeds["table_block_download"] = block_download(0x2002, 0, table) + segmented_upload(0x2002, 0, 40)
    # a full table of the fuzz build (256 samples)
    big = b"".join(struct.pack("<f", 0.05 * math.sin(2 * math.pi * 3 * k / 256)) for k in range(256))
    seeds["table_block_download_full"] = block_download(0x2002, 0, big, blksize=127)
    seeds["table_block_download_badcrc"] = block_download(0x2002, 0, table)[:-9] + sdo(0xC1, 0x12, 0x34)
    run = operational_enabled() + setup_sine_run() + start_run() + steps(500) + wait_us(1000)
    size = 32 * 2 * 3 * 4
    seeds["run_block_upload"] = run + upload(0x2010, 2) + block_upload(0x2021, 0, size)
    seeds["run_block_upload_retransmit"] = run + block_upload(0x2021, 0, size, blksize=40, retransmit=True,
                                                              pressure=True)
    seeds["run_segmented_upload"] = run + segmented_upload(0x2021, 0, 12) + sdo(0x80, *mux(0x2021, 0))
    seeds["run_table_kind"] = (operational_enabled() + block_download(0x2002, 0, table)
                               + write_u(0x2001, 1, 2, 1) + write_u(0x2001, 5, 64, 4) + write_u(0x2001, 7, 0, 4) + write_f32(0x2001, 3, 1.0)
                               + start_run() + steps(300) + write_u(0x2010, 1, 2, 1) + upload(0x2010, 5))
    # the same run with the table sent segmented (no CRC): the structure-aware mutator's
    # table values then reach the drive (a block download with a changed sample fails its CRC)
    seeds["run_table_kind_segmented"] = (operational_enabled() + segmented_download(0x2002, 0, table[:32])
                                         + write_u(0x2001, 1, 2, 1) + write_u(0x2001, 5, 8, 4)
                                         + write_u(0x2001, 7, 0, 4) + write_f32(0x2001, 3, 1.0)
                                         + start_run() + steps(64) + upload(0x2030, 4))
    seeds["run_multisine"] = (operational_enabled() + write_u(0x2001, 1, 3, 1) + write_u(0x2001, 5, 256, 4) + write_u(0x2001, 7, 0, 4)
                              + write_u(0x2001, 10, 40, 4) + write_f32(0x2001, 3, 0.5) + start_run()
                              + steps(1200) + upload(0x2020, 3))
    # line statistics of a multisine run (N = 32, 3 recorded periods) with the background
    # behind (every 40th step: the run ends with periods pending), then the next run's set-up
    # written before anything reads 0x2043: another period, list, recorder selection, u_max
    # (issue 21: the old core read the new list against the run's N, out of bounds)
    lines = (operational_enabled() + backpressure(False, background=40)
             + write_u(0x2001, 1, 3, 1) + write_u(0x2001, 5, 32, 4) + write_u(0x2001, 7, 0, 4)
             + write_u(0x2001, 8, 3, 4) + write_u(0x2001, 9, 1, 4) + write_u(0x2001, 10, 10, 4)
             + write_f32(0x2001, 3, 0.2) + write_u(0x2020, 1, 0x07, 4)
             + sdo(0x23, *mux(0x2042, 0), 3, 0, 5, 0) + write_u(0x2040, 7, 1, 1)
             + start_run() + steps(100) + upload(0x2010, 2)
             + write_u(0x2001, 5, 256, 4) + sdo(0x23, *mux(0x2042, 0), 3, 0, 9, 0)
             + write_u(0x2020, 1, 0x1F, 4) + write_f32(0x2000, 7, 2.0)
             + upload(0x2040, 10) + segmented_upload(0x2043, 0, 4) + upload(0x2040, 11))
    seeds["line_stats_background_behind"] = lines
    hb = (write_u(0x1017, 0, 100, 2) + write_u(0x1016, 1, (0x7F << 16) | 300, 4) + heartbeat(0x7F)
          + operational_enabled() + setup_sine_run(period=512, record=8, settle=2) + start_run()
          + heartbeat(0x7F) + steps(200) + wait_us(100000) + heartbeat(0x7F) + steps(200) + wait_us(400000)
          + steps(200) + upload(0x2010, 2) + upload(0x2010, 5) + heartbeat(0x7F) + wait_us(200000))
    seeds["heartbeat_loss_during_run"] = hb
    pdo = (write_u(0x1800, 1, 0x80000181, 4) + write_u(0x1A00, 0, 0, 1) + write_u(0x1A00, 1, 0x60410010, 4)
           + write_u(0x1A00, 2, 0x20100208, 4) + write_u(0x1A00, 0, 2, 1) + write_u(0x1800, 1, 0x181, 4)
           + write_u(0x1800, 3, 10, 2) + write_u(0x1800, 5, 50, 2)
           + write_u(0x1400, 1, 0x80000201, 4) + write_u(0x1600, 0, 0, 1) + write_u(0x1600, 1, 0x60400010, 4)
           + write_u(0x1600, 0, 1, 1) + write_u(0x1400, 1, 0x201, 4)
           + nmt(0x01) + wait_us(60000) + rpdo(0, [0x06, 0x00]) + rpdo(0, [0x07, 0x00]) + rpdo(0, [0x0F, 0x00])
           + rpdo(0, [0x0F]) + rpdo(1, [1, 2, 3, 4, 5, 6, 7, 8]) + wait_us(60000)
           + rpdo(0, [0x80, 0x00]) + frame(0x201, [0x06, 0x00, 0x00]) + wait_us(60000))
    seeds["pdo_mapping_and_rpdo"] = pdo
    seeds["sdo_timeout"] = (sdo(0x21, *mux(0x2002, 0), 64, 0, 0, 0) + wait_us(600000)
                            + sdo(0x00, 1, 2, 3, 4, 5, 6, 7) + upload(0x1008, 0) + wait_us(600000)
                            + sdo(0xA4, *mux(0x2021, 0), 10, 0) + wait_us(700000))
    seeds["sdo_protocol_errors"] = (upload(0x1008, 0) + sdo(0x70) + sdo(0xE0, 0, 0x10, 0)
                                    + segmented_download(0x2002, 0, table)[:30] + sdo(0x10, 1, 2)
                                    + sdo(0xA4, *mux(0x2021, 0), 0, 0) + sdo(0xA4, *mux(0x2021, 0), 200, 0)
                                    + sdo(0xC0, *mux(0x2002, 0)) + sdo(0x83) + sdo(0x80, 0, 0x20, 0)
                                    + upload(0x5FFF, 0) + upload(0x1018, 9) + frame(0x601, [0x40, 0, 0x10])
                                    + frame(0x000, [0x01]) + frame(0x701, [5, 5]) + frame(0x7FF, [0] * 8))
    seeds.update(task_seeds())
    return seeds


def task_params(mode=1, distance=0.05, v_max=2.0, a_max=200.0, jerk=20000.0, dwell=0.005):
    """The task objects (0x2060:1..6) and a task run's excitation kind 0."""
    out = write_u(0x2001, 1, 0, 1)          # excitation kind 0: a run plays the task
    for sub, value in ((2, distance), (3, v_max), (4, a_max), (5, jerk), (6, dwell)):
        out += write_f32(0x2060, sub, value)
    return out + write_u(0x2060, 1, mode, 1) + upload(0x2060, 8)


def task_seeds():
    """Issue 30: the task objects (0x2060 .. 0x2064), 0x2004 and 0x6007 written out of range,
    with the wrong size and at the wrong time (during a task run), around complete task runs
    with their statistics uploaded (continuous latches included)."""
    seeds = {}
    run = (operational_enabled() + task_params() + write_u(0x2001, 7, 0, 4) + write_u(0x2001, 8, 2, 4)
           + write_u(0x2020, 1, 0, 4) + start_run())
    seeds["task_run_and_statistics"] = (run + steps(1500) + upload(0x2010, 2) + upload(0x2060, 10)
                                        + segmented_upload(0x2062, 0, 6) + segmented_upload(0x2061, 0, 6)
                                        + block_upload(0x2061, 0, 8 + 8 * 24, blksize=10))
    seeds["task_forward_continuous_latches"] = (
        operational_enabled() + task_params(mode=2) + write_u(0x2001, 7, 1, 4) + write_u(0x2001, 8, 20, 4)
        + write_u(0x2020, 1, 0, 4) + start_run() + steps(700) + upload(0x2060, 10)
        + segmented_upload(0x2064, 0, 6) + steps(300) + segmented_upload(0x2063, 0, 6)
        + write_f32(0x2060, 7, 0.01) + steps(700) + block_upload(0x2063, 0, 8 + 8 * 24, blksize=4)
        + write_u(0x2010, 1, 2, 1) + upload(0x2010, 5))
    bad = b""
    for sub, value in ((2, 2000.0), (2, -1.0), (2, float("nan")), (3, 1e5), (3, float("inf")), (4, -0.0),
                       (5, 0.0), (6, 1e3), (7, 101.0), (7, float("-inf"))):
        bad += write_f32(0x2060, sub, value) + upload(0x2060, sub)
    bad += (write_u(0x2060, 1, 3, 1) + write_u(0x2060, 1, 1, 4) + write_u(0x2060, 8, 64, 4)
            + write_u(0x2060, 9, 1, 4) + write_u(0x2060, 10, 0, 4) + write_u(0x2060, 11, 0, 4)
            + sdo(0x2F, *mux(0x2060, 2), 1) + write_u(0x2004, 0, 16, 4)
            + write_u(0x6007, 0, 4, 2) + write_u(0x6007, 0, 0xFFFF, 2) + write_u(0x6007, 0, 0, 1)
            + upload(0x6007, 0) + upload(0x2004, 0))
    seeds["task_objects_out_of_range"] = operational_enabled() + bad
    # the same writes while a task run is active (refused, the run's values kept), then the
    # host lost (no heartbeat within the consumer time: 0x6007 acts)
    mid = (write_f32(0x2060, 2, 0.5) + write_u(0x2060, 1, 0, 1) + write_u(0x2001, 1, 1, 1)
           + write_f32(0x2060, 7, 0.5) + write_u(0x6007, 0, 0, 2) + write_u(0x6007, 0, 1, 2))
    seeds["task_writes_during_the_run_then_host_lost"] = (
        write_u(0x1017, 0, 100, 2) + write_u(0x1016, 1, (0x7F << 16) | 300, 4) + heartbeat(0x7F)
        + run + steps(200) + mid + steps(200) + heartbeat(0x7F) + wait_us(200000) + steps(100)
        + wait_us(400000) + steps(200) + upload(0x2010, 2) + upload(0x2010, 5) + upload(0x6041, 0))
    # degenerate tasks: fewer than 64 or more than 2^24 samples a repetition (no task: 0x2060:8 = 0)
    seeds["task_degenerate_then_start"] = (
        operational_enabled() + task_params(distance=1e-6, v_max=1e4, a_max=1e6, jerk=1e9, dwell=0.0)
        + start_run() + steps(50) + upload(0x2010, 5)
        + task_params(distance=1000.0, v_max=1e-3, a_max=1e-3, jerk=1e-3, dwell=100.0) + start_run()
        + steps(50) + upload(0x2010, 5))
    return seeds


# ---- fuzz_scd -------------------------------------------------------------------------


def scd_input(nclients, chunks):
    """chunks: [(client, bytes)], each written as records of at most 255 bytes."""
    out = bytes([nclients - 1])
    for ci, b in chunks:
        for k in range(0, len(b), 255):
            part = b[k:k + 255]
            out += bytes([ci, len(part)]) + part
    return out


def scd_seeds():
    hs = [b"< open can0 >", b"< rawmode >"]
    sends = [b"< send 601 8 40 0 10 0 0 0 0 0 >", b"< send 000 2 1 0 >", b"< send 77f 1 5 >",
             b"< send 12345678 3 a b c >", b"< send 201 0 >", b"< echo >"]
    seeds = {}
    seeds["python_can_session"] = scd_input(1, [(0, hs[0]), (0, hs[1])] + [(0, s) for s in sends])
    seeds["two_clients"] = scd_input(2, [(0, hs[0]), (1, hs[0]), (0, hs[1]), (1, hs[1]), (0, sends[0]),
                                         (1, sends[1]), (0, b"".join(sends))])
    split = b"".join(hs) + b"".join(sends)
    seeds["split_reads"] = scd_input(1, [(0, split[k:k + 3]) for k in range(0, len(split), 3)])
    seeds["garbage_and_long_line"] = scd_input(2, [(0, hs[0] + hs[1]), (1, b"\x00\xff<<<>>> hello"),
                                                   (0, b"< send 601 8 " + b"ff " * 60 + b">"),
                                                   (1, b"< " + b"x" * 300), (1, b" >"), (0, sends[0])])
    seeds["too_many_clients"] = scd_input(9, [(i, hs[0] + hs[1] + sends[0]) for i in range(9)])
    seeds["half_line_stall"] = scd_input(3, [(0, hs[0] + hs[1]), (1, hs[0] + hs[1]), (2, b"< send 601 8 40"),
                                             (0, sends[0]), (1, sends[1]), (0, sends[2])])
    return seeds


def main(argv):
    if len(argv) != 3:
        sys.stderr.write("usage: gen_seeds.py EDS OUTDIR\n")
        return 2
    eds, outdir = argv[1], argv[2]
    for target, seeds in (("co_node", co_node_seeds(eds)), ("scd", scd_seeds())):
        d = os.path.join(outdir, target)
        os.makedirs(d, exist_ok=True)
        for name, data in seeds.items():
            tmp = os.path.join(d, name + ".bin.tmp")
            with open(tmp, "wb") as f:
                f.write(data)
            os.replace(tmp, os.path.join(d, name + ".bin"))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
