"""drive_sim as a CANopen node on vcan0 inside the qemu guest, talked to with can-utils.

In the guest boot all VM test modules share (tests/vmguest.py): candump records the bus, drive_sim starts with ``--can socketcan:vcan0``,
cansend issues raw CiA 301 requests. The expected bytes come from CiA 301 (frame layouts,
abort codes) and from the node's EDS read by python-canopen, not from our own code.
"""
import struct
from pathlib import Path

import pytest

from vmguest import REPO_ROOT, SH_WAIT_CAN_RECEIVERS

pytestmark = pytest.mark.vm

DRIVE_SIM = REPO_ROOT / "firmware_sim" / "build" / "drive_sim"
EDS = REPO_ROOT / "firmware_sim" / "build" / "gen" / "fftune_drive.eds"

# Each step waits for its answer in the candump log before the next request goes out.
EXCHANGE = SH_WAIT_CAN_RECEIVERS + r'''
dump="$SECTION_OUT/dump.log"
wait_dump() {  # wait_dump COUNT PATTERN: until COUNT lines of the dump match PATTERN
    _i=0
    while [ "$(grep -cE "$2" "$dump")" -lt "$1" ]; do
        _i=$((_i + 1))
        if [ "$_i" -gt 600 ]; then echo "timeout waiting for $1 x '$2'"; return 1; fi
        sleep 0.1
    done
}
candump -L vcan0 > "$dump" &
dump_pid=$!
wait_can_receivers vcan0 1 || exit 3
DRIVE_SIM --can socketcan:vcan0 --node-id 1 > "$SECTION_OUT/drive_sim.out" \
    2> "$SECTION_OUT/drive_sim.err" &
sim_pid=$!
status=0
# boot-up, then SDO upload of 0x1000:00, SDO upload of a missing object, NMT reset node.
wait_dump 1 ' 701#00$' \
 && cansend vcan0 601#4000100000000000 && wait_dump 1 ' 581#' \
 && cansend vcan0 601#40FF5F0000000000 && wait_dump 2 ' 581#' \
 && cansend vcan0 000#8101 && wait_dump 2 ' 701#00$' \
 || status=4
kill "$sim_pid" 2>/dev/null
wait "$sim_pid"
echo "drive_sim exit status $?"
kill "$dump_pid"
exit $status
'''.replace("DRIVE_SIM", str(DRIVE_SIM))


VM_SECTIONS = {"exchange": EXCHANGE}
VM_SECTION_TIMEOUT_S = 150


def vm_skip_reason():
    return None if DRIVE_SIM.exists() else f"{DRIVE_SIM} not built (make setup)"


@pytest.fixture(scope="module")
def session(vm_session, request):
    sections, whole = vm_session.results(request.module)
    exchange = sections["exchange"]
    assert exchange.returncode == 0, (exchange.output + str(exchange.files)
                                      + whole.describe())
    return frames_in_time_order(exchange.files["dump.log"])


def frames_in_time_order(candump_log):
    """Frames of a ``candump -L`` log, ordered by their receive timestamps.

    Why not file order: with 2 vCPUs the node can receive a request, answer, and have its
    answer queued to candump's socket before the kernel reaches candump in the receiver list
    for the request itself (seen here). The timestamps are taken when each frame enters the
    stack, so they keep cause before effect.
    """
    stamped = []
    for line in candump_log.splitlines():
        # "(1700000000.123456) vcan0 581#4300100092010200"
        stamp, _ifname, frame = line.split()
        seconds, micros = stamp.strip("()").split(".")
        stamped.append(((int(seconds), int(micros)), frame))
    return [frame for _, frame in sorted(stamped, key=lambda item: item[0])]


def test_drive_sim_sends_boot_up_before_anything_else(session):
    assert session[0] == "701#00", session


def test_sdo_upload_of_device_type_matches_the_eds(session):
    canopen = pytest.importorskip("canopen")
    if not EDS.exists():
        pytest.skip(f"{EDS} not generated (make setup)")
    device_type = canopen.import_od(str(EDS), 1)[0x1000].default
    request = session.index("601#4000100000000000")
    responses = [f for f in session[request:] if f.startswith("581#")]
    # expedited upload response, 4 bytes (0x43), index 0x1000 little-endian, sub 0, value
    expected = "581#" + (bytes([0x43, 0x00, 0x10, 0x00]) + struct.pack("<I", device_type)).hex()
    assert responses[0].upper() == expected.upper(), session


def test_sdo_upload_of_missing_object_aborts_with_object_does_not_exist(session):
    request = session.index("601#40FF5F0000000000")
    responses = [f for f in session[request:] if f.startswith("581#")]
    # abort (0x80), index 0x5FFF, sub 0, code 0x06020000 little-endian
    assert responses[0].upper() == "581#80FF5F0000000206", session


def test_nmt_reset_node_sends_boot_up_again(session):
    reset = session.index("000#8101")
    assert "701#00" in session[reset + 1:], session
