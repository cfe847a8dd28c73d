"""SocketCAN on vcan0 inside the qemu guest: the link, can-utils, python-can's socketcan.

Its sections run in the one guest boot all VM test modules share (tests/vmguest.py
SharedGuestSession, fixture vm_session); each test checks one section. Skipped, with the reason, where qemu or the Debian kernel with
vcan are not installed.
"""
import json

import pytest

from vmguest import SH_WAIT_CAN_RECEIVERS, VENV_PYTHON

pytestmark = pytest.mark.vm

PYTHON_CAN_CHECK = r'''
import json, os, subprocess, sys, time
import can
import_s = time.time() - float(os.environ["T0"])

result = {"import_s": import_s}
rx = can.Bus(interface="socketcan", channel="vcan0")
tx = can.Bus(interface="socketcan", channel="vcan0")
try:
    # python-can -> python-can (two raw sockets on the same interface)
    sent = can.Message(arbitration_id=0x1ABCDE, is_extended_id=True,
                       data=bytes([1, 2, 3, 4, 5, 6, 7, 8]))
    tx.send(sent)
    got = rx.recv(timeout=20)
    result["py_to_py"] = None if got is None else [got.arbitration_id, got.is_extended_id,
                                                   got.data.hex()]
    # can-utils -> python-can
    subprocess.run(["cansend", "vcan0", "7FF#0102"], check=True)
    got = rx.recv(timeout=20)
    result["cansend_to_py"] = None if got is None else [got.arbitration_id, got.is_extended_id,
                                                        got.data.hex()]
finally:
    rx.shutdown()
    tx.shutdown()
with open(os.path.join(os.environ["SECTION_OUT"], "result.json"), "w") as f:
    json.dump(result, f)
'''

VM_SECTIONS = {
    "link": "ip -details link show vcan0",
    "candump": SH_WAIT_CAN_RECEIVERS + r'''
candump -L -n 1 vcan0 > "$SECTION_OUT/dump.log" &
pid=$!
wait_can_receivers vcan0 1 || exit 3
cansend vcan0 123#DEADBEEF01
wait $pid
''',
    "python_can": f'T0=$(date +%s.%N) {VENV_PYTHON} "$FFTUNE_VM_JOB/python_can_check.py"',
}


VM_SECTION_TIMEOUT_S = 150
VM_FILES = {"python_can_check.py": PYTHON_CAN_CHECK}


@pytest.fixture(scope="module")
def session(vm_session, request):
    return vm_session.results(request.module)


def test_guest_boots_with_vcan0_up(session):
    sections, whole = session
    link = sections["link"]
    assert link.returncode == 0, link.output + whole.describe()
    first, *rest = link.output.splitlines()
    assert "vcan0:" in first and ",UP," in first.replace("<", ",").replace(">", ","), link.output
    assert "link/can" in link.output
    # `-details` names the link kind on its own line: "    vcan numtxqueues 1 ..."
    assert any(line.split()[:1] == ["vcan"] for line in rest), link.output


def test_candump_receives_exactly_the_cansend_frame(session):
    sections, whole = session
    dump = sections["candump"]
    assert dump.returncode == 0, dump.output + whole.describe()
    lines = dump.files["dump.log"].splitlines()
    assert len(lines) == 1, dump.files
    # candump -L: "(1700000000.123456) vcan0 123#DEADBEEF01"
    assert lines[0].split()[1:] == ["vcan0", "123#DEADBEEF01"], lines


def test_python_can_socketcan_sends_and_receives_on_vcan0(session):
    sections, whole = session
    check = sections["python_can"]
    assert check.returncode == 0, check.output + whole.describe()
    result = json.loads(check.files["result.json"])
    assert result["py_to_py"] == [0x1ABCDE, True, "0102030405060708"]
    assert result["cansend_to_py"] == [0x7FF, False, "0102"]
    print(f"guest: boot-run-poweroff {whole.duration_s:.1f} s, python start + import can "
          f"{result['import_s']:.1f} s")
