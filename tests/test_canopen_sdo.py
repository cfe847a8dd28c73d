"""drive_sim's SDO server (CiA 301) against python-canopen's SDO client: every transfer
mode, and every abort code the server gives, each through a real request."""
import struct
import time

import numpy as np
import pytest
from canopen.sdo import SdoAbortedError
from canopen.sdo.client import BlockUploadStream

from canopen_helpers import collect, configure_sine_run, enable_402, run_to_done, start_long_run, wait_for

# ---- transfers --------------------------------------------------------------------------


def test_expedited_upload_and_download_of_each_type(co_node):
    net, node = co_node
    assert node.sdo[0x1000].raw == 0x00020192                           # UNSIGNED32
    assert node.sdo[0x1018][1].raw == 0x0FF7
    assert node.sdo[0x1014].raw == 0x80 + node.id                       # $NODEID relative
    node.sdo[0x1017].raw = 1234                                          # UNSIGNED16
    assert node.sdo[0x1017].raw == 1234
    node.sdo[0x6060].raw = -1                                            # INTEGER8
    assert node.sdo[0x6061].raw == -1
    node.sdo["Controller"]["Coulomb feed-forward K_fc"].raw = 0.125      # REAL32
    assert node.sdo["Controller"]["Coulomb feed-forward K_fc"].raw == 0.125
    node.sdo["Excitation"]["Kind"].raw = 2                               # UNSIGNED8 -> drive
    assert node.sdo["Excitation"]["Kind"].raw == 2
    node.sdo[0x607A].raw = -123456                                       # INTEGER32
    assert node.sdo[0x607A].raw == -123456


def test_segmented_upload_of_strings(co_node):
    net, node = co_node
    assert node.sdo[0x1008].raw == "fftune drive_sim"
    assert node.sdo[0x100A].raw == "0.1.0"


def test_segmented_download_forced_for_a_value(co_node):
    net, node = co_node
    node.sdo.download(0x2000, 2, struct.pack("<f", 0.75), force_segment=True)
    assert node.sdo["Controller"]["Kd"].raw == 0.75


def test_segmented_download_and_upload_of_the_waveform_table(co_node):
    net, node = co_node
    table = np.sin(2 * np.pi * np.arange(100) / 100).astype("<f4")
    node.sdo[0x2002].raw = table.tobytes()              # DOMAIN: python-canopen segments it
    assert node.sdo[0x2003].raw == 100
    back = np.frombuffer(node.sdo.upload(0x2002, 0), "<f4")
    np.testing.assert_array_equal(back, table)


def test_block_download_of_a_full_table_and_block_upload_back(co_node):
    net, node = co_node
    rng = np.random.default_rng(1)
    table = rng.standard_normal(8192).astype("<f4")      # 32768 bytes, the largest table
    with node.sdo[0x2002].open("wb", size=table.nbytes, block_transfer=True) as f:
        f.write(table.tobytes())
    assert node.sdo[0x2003].raw == 8192
    with node.sdo[0x2002].open("rb", block_transfer=True) as f:
        assert f.raw.crc_supported
        back = f.read()
    np.testing.assert_array_equal(np.frombuffer(back, "<f4"), table)


def test_block_upload_of_more_than_a_mebibyte_of_recorder_data_with_crc(co_node):
    net, node = co_node
    node.nmt.state = "OPERATIONAL"
    enable_402(node)
    n, cycles, periods, amp = 2048, 3, 129, 0.5        # 129 * 2048 samples * 4 B > 1 MiB
    configure_sine_run(node, period=n, settle=0, record=periods, amplitude=amp, cycles=cycles,
                       signals=0x01)
    assert run_to_done(node) == 3
    size = node.sdo["Recorder"]["Data size"].raw
    assert size == periods * n * 4 >= 1 << 20
    with node.sdo[0x2021].open("rb", block_transfer=True) as f:
        assert f.raw.crc_supported and f.raw.size == size   # client checks the CRC at the end
        data = f.read()
    ref = np.frombuffer(data, "<f4")
    assert ref.size == periods * n
    # the recorded reference is the drive's exactly periodic sine about the held set-point
    k = np.arange(ref.size)
    expected = ref[0] + amp * np.sin(2 * np.pi * cycles * k / n)
    np.testing.assert_allclose(ref, expected, atol=2e-6)
    np.testing.assert_array_equal(ref[:n], ref[-n:])


def test_block_upload_with_protocol_switch_threshold_falls_back_for_small_data(co_node):
    net, node = co_node
    # 0x1008 holds 16 bytes: with pst = 16 in the initiate request the server switches to
    # a normal (segmented) upload, with pst = 15 it answers with a block upload
    node.sdo.send_request(bytes([0xA4, 0x08, 0x10, 0x00, 127, 16, 0, 0]))
    resp = node.sdo.read_response()
    assert resp[0] == 0x41 and struct.unpack_from("<I", resp, 4)[0] == 16
    node.sdo.send_request(bytes([0xA4, 0x08, 0x10, 0x00, 127, 15, 0, 0]))
    resp = node.sdo.read_response()
    assert resp[0] == 0xC6 and struct.unpack_from("<I", resp, 4)[0] == 16


# ---- abort codes ------------------------------------------------------------------------


def _abort_of(fn):
    with pytest.raises(SdoAbortedError) as info:
        fn()
    return info.value.code


def test_abort_object_does_not_exist(co_node):
    net, node = co_node
    assert _abort_of(lambda: node.sdo.upload(0x3000, 0)) == 0x06020000


def test_abort_sub_index_does_not_exist(co_node):
    net, node = co_node
    assert _abort_of(lambda: node.sdo.upload(0x1018, 9)) == 0x06090011


def test_abort_write_to_read_only(co_node):
    net, node = co_node
    assert _abort_of(lambda: node.sdo.download(0x1000, 0, b"\0\0\0\0")) == 0x06010002


def test_abort_read_of_write_only(co_node):
    net, node = co_node
    assert _abort_of(lambda: node.sdo.upload(0x2010, 1)) == 0x06010001


def test_abort_length_too_high(co_node):
    net, node = co_node
    assert _abort_of(lambda: node.sdo.download(0x1017, 0, b"\1\0\0\0")) == 0x06070012


def test_abort_length_too_low(co_node):
    net, node = co_node
    assert _abort_of(lambda: node.sdo.download(0x2000, 1, b"\1\0")) == 0x06070013


def test_abort_length_does_not_match_for_a_table_of_partial_samples(co_node):
    net, node = co_node
    assert _abort_of(lambda: node.sdo.download(0x2002, 0, b"\0" * 6)) == 0x06070010


def test_abort_value_too_high(co_node):
    net, node = co_node
    assert _abort_of(lambda: setattr(node.sdo["Controller"]["Kp"], "raw", 2e5)) == 0x06090031


def test_abort_value_too_low(co_node):
    net, node = co_node
    assert _abort_of(lambda: setattr(node.sdo["Controller"]["Kp"], "raw", -1.0)) == 0x06090032


def test_abort_invalid_value_nan_and_unsupported_mode(co_node):
    net, node = co_node
    assert _abort_of(lambda: setattr(node.sdo["Controller"]["Kp"], "raw", float("nan"))) == 0x06090030
    assert _abort_of(lambda: setattr(node.sdo[0x6060], "raw", 3)) == 0x06090030
    assert node.sdo["Controller"]["Kp"].raw == 2.0       # old value kept


def test_abort_toggle_bit_not_alternated(co_node):
    net, node = co_node
    node.sdo.send_request(bytes([0x21, 0x00, 0x20, 0x02, 4, 0, 0, 0]))   # segmented, 4 bytes
    assert node.sdo.read_response()[0] == 0x60
    node.sdo.send_request(bytes([0x10 | (3 << 1) | 1, 0, 0, 0, 0x3F, 0, 0, 0]))  # toggle 1
    assert _abort_of(node.sdo.read_response) == 0x05030000


def test_abort_sdo_protocol_timed_out(co_node):
    net, node = co_node
    node.sdo.send_request(bytes([0x21, 0x00, 0x20, 0x02, 4, 0, 0, 0]))
    assert node.sdo.read_response()[0] == 0x60
    time.sleep(1.3)                                  # server timeout: 1 s without a segment
    assert _abort_of(node.sdo.read_response) == 0x05040000


def test_abort_unknown_command_specifier(co_node):
    net, node = co_node
    node.sdo.send_request(bytes([0xE0, 0x00, 0x10, 0, 0, 0, 0, 0]))
    assert _abort_of(node.sdo.read_response) == 0x05040001


def test_abort_invalid_block_size(co_node, monkeypatch):
    net, node = co_node
    monkeypatch.setattr(BlockUploadStream, "blksize", 0)
    assert _abort_of(lambda: node.sdo[0x1008].open("rb", block_transfer=True)) == 0x05040002


def test_abort_crc_error_in_block_download(co_node, monkeypatch):
    net, node = co_node

    class WrongCrc:
        def __init__(self):
            self.v = 0

        def process(self, data):
            import binascii
            self.v = binascii.crc_hqx(data, self.v)

        def final(self):
            return self.v ^ 0x0001

    monkeypatch.setattr(node.sdo, "crc_cls", WrongCrc)
    table = np.ones(64, "<f4").tobytes()

    def download():
        with node.sdo[0x2002].open("wb", size=len(table), block_transfer=True) as f:
            f.write(table)
    assert _abort_of(download) == 0x05040004
    assert node.sdo[0x2003].raw == 0                  # nothing committed


@pytest.mark.drive_sim_args("--realtime")
def test_abort_data_cannot_be_stored_in_the_present_device_state(co_node):
    net, node = co_node
    configure_sine_run(node)
    # a run starts only in NMT OPERATIONAL and CiA 402 OPERATION ENABLED
    assert _abort_of(lambda: setattr(node.sdo["Run control"]["Command"], "raw", 1)) == 0x08000022
    node.nmt.state = "OPERATIONAL"
    assert _abort_of(lambda: setattr(node.sdo["Run control"]["Command"], "raw", 1)) == 0x08000022
    enable_402(node)
    start_long_run(node)
    # while it runs: no new table, no recorder data
    assert _abort_of(lambda: node.sdo.download(0x2002, 0, b"\0" * 8)) == 0x08000022
    assert _abort_of(lambda: node.sdo.upload(0x2021, 0)) == 0x08000022
    node.sdo["Run control"]["Command"].raw = 2
    assert node.sdo["Run control"]["State"].raw == 4


def test_abort_general_error_when_a_new_run_replaces_data_being_uploaded(co_node):
    net, node = co_node
    node.nmt.state = "OPERATIONAL"
    enable_402(node)
    configure_sine_run(node, period=256, record=1, signals=0x01)
    # TPDO2 (run state, progress) is change-driven with an inhibit time (0x1801:3, 100 us
    # units) and no event timer: it is sent only when its data differ from the last frame.
    tpdo2 = []                                    # (python's receipt time, data)
    net.subscribe(0x280 + node.id, lambda can_id, data, ts: tpdo2.append((time.monotonic(), bytes(data))))
    inhibit_s = node.sdo[0x1801][3].raw * 100e-6
    assert run_to_done(node) == 3
    assert wait_for(lambda: tpdo2 and tpdo2[-1][1][0] == 3, 10.0)   # (3, 256) sent
    # RPDO4 (disabled by default) mapped to the run command, as a host may configure it
    rpdo = node.rpdo[4]
    rpdo.read()
    rpdo.clear()
    rpdo.add_variable(0x2010, 1)
    rpdo.enabled = True
    rpdo.cob_id = 0x500 + node.id
    rpdo.trans_type = 255
    rpdo.save()
    # The new run must start after TPDO2's inhibit time has passed since that (3, 256)
    # frame: a 256-sample run in free-run ends within a millisecond, so inside the inhibit
    # window its states coalesce to (3, 256) again, equal to the last frame, and no TPDO2
    # is ever sent (seen in the qemu guest: RPDO 33 ms after the frame, inhibit 50 ms).
    # Receipt time >= send time, so waiting from receipt is long enough.
    assert wait_for(lambda: time.monotonic() - tpdo2[-1][0] > inhibit_s, inhibit_s + 1.0)
    node.sdo.send_request(bytes([0x40, 0x21, 0x20, 0, 0, 0, 0, 0]))     # segmented upload
    assert node.sdo.read_response()[0] == 0x41
    node.sdo.send_request(bytes([0x60, 0, 0, 0, 0, 0, 0, 0]))
    assert node.sdo.read_response()[0] & 0xE0 == 0x00                  # first segment
    counters = collect(net, 0x380 + node.id)      # TPDO3: run counter, last stop reason
    states = collect(net, 0x280 + node.id)        # TPDO2: run state, progress
    rpdo["Run control.Command"].raw = 1
    rpdo.transmit()                               # a new run, by PDO (no SDO in between)
    assert wait_for(lambda: any(struct.unpack_from("<I", d)[0] == 2 for d in counters), 10.0)
    assert wait_for(lambda: any(d[0] == 3 for d in states), 10.0)  # the new run is done
    node.sdo.send_request(bytes([0x70, 0, 0, 0, 0, 0, 0, 0]))
    assert _abort_of(node.sdo.read_response) == 0x08000000
    assert node.sdo["Run control"]["State"].raw == 3
