"""The CANopen conformance suite (tests/test_canopen_*.py) over SocketCAN vcan0 in the guest.

The suite's ``drive_sim`` fixture (tests/conftest.py) puts drive_sim and python-canopen on
the interface named by FFTUNE_TEST_CAN; here that is ``socketcan:vcan0`` inside the qemu
guest, so the same tests that run over socketcand on the host run over a kernel SocketCAN
interface. Only the tests that use the bus run in the guest (tests/vm/pytest_bus_only.py):
Python is 20-40x slower under TCG, and two block-transfer tests cannot finish at that speed
(the plugin lists them with the measured reason). FFTUNE_VM_CONFORMANCE_ALL=1 runs the whole
suite.
"""
import os
import re
import shlex

import pytest

from vmguest import REPO_ROOT, VENV_PYTHON

pytestmark = pytest.mark.vm

VM_DIR = REPO_ROOT / "tests" / "vm"
SUITE = sorted(REPO_ROOT.glob("tests/test_canopen_*.py"))
GUEST_PYTEST_TIMEOUT_S = 480
_COUNT = re.compile(r"(\d+) (passed|failed|errors?|skipped|deselected|xfailed|xpassed)\b")


def pytest_summary_counts(output):
    """{outcome: count} from the last pytest summary line in ``output`` (empty if none).

    >>> pytest_summary_counts("4 failed, 38 passed, 5 skipped in 374.69s (0:06:14)")
    {'failed': 4, 'passed': 38, 'skipped': 5}
    """
    for line in reversed(output.splitlines()):
        if re.search(r"\bin [\d.]+s\b", line) and _COUNT.search(line):
            counts = {}
            for number, outcome in _COUNT.findall(line):
                counts["errors" if outcome == "error" else outcome] = int(number)
            return counts
    return {}


def test_summary_parser_reads_pytest_summary_lines():
    assert pytest_summary_counts("x\n= 1 failed, 2 passed, 1 error, 3 deselected in 5.00s =\n") \
        == {"failed": 1, "passed": 2, "errors": 1, "deselected": 3}
    assert pytest_summary_counts("47 passed in 34.81s") == {"passed": 47}
    assert pytest_summary_counts("no summary here") == {}


def _guest_pytest_command():
    args = [str(VENV_PYTHON), "-m", "pytest", "-q", "-p", "no:cacheprovider", "-rfEs",
            "--durations=10", *[str(p.relative_to(REPO_ROOT)) for p in SUITE]]
    if os.environ.get("FFTUNE_VM_CONFORMANCE_ALL") != "1":
        args[3:3] = ["-p", "pytest_bus_only"]
    return (f"cd {shlex.quote(str(REPO_ROOT))} && FFTUNE_TEST_CAN=socketcan:vcan0 "
            f"PYTHONPATH={shlex.quote(str(VM_DIR))} " + " ".join(map(shlex.quote, args)))


# One section of the guest boot all VM test modules share (tests/vmguest.py).
VM_SECTIONS = {"conformance": _guest_pytest_command()}
VM_SECTION_TIMEOUT_S = GUEST_PYTEST_TIMEOUT_S


def vm_skip_reason():
    if not SUITE:
        return "no tests/test_canopen_*.py (the CANopen conformance suite) yet"
    if not VENV_PYTHON.exists():
        return f"{VENV_PYTHON} missing (make setup)"
    return None


def test_canopen_conformance_suite_passes_over_vcan0_in_the_guest(vm_session, request):
    sections, whole = vm_session.results(request.module)
    run = sections["conformance"]
    # The whole guest output, kept for a look after the run (build/ is ignored by git).
    log = REPO_ROOT / "build" / "vm" / "last-conformance.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    log.write_text(run.output + "\n" + whole.describe())
    counts = pytest_summary_counts(run.output)
    # shown with -s / -rA: the guest's slowest tests and what it deselected, with reasons
    print(f"guest conformance run: {counts}, shared boot {whole.duration_s:.0f} s\n"
          + "\n".join(run.output.splitlines()[-40:]))
    assert counts, "no pytest summary line from the guest: " + run.output + whole.describe()
    assert counts.get("failed", 0) == 0 and counts.get("errors", 0) == 0, run.output
    assert counts.get("passed", 0) > 0, run.output
    assert run.returncode == 0, run.output + whole.describe()
