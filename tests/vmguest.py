"""Tests' door to the SocketCAN qemu guest (tests/vm/guest.py; docs/vm-testing.md).

The guest boots Debian's kernel under qemu (TCG), has ``vcan0`` up, and sees the host's
``/`` (read-only on the host side, writable in the guest through a tmpfs overlay). A boot
costs 7-25 s on a shared 2-core machine and Python in the guest runs 10-40x slower than on
the host, so a test module should boot once and run all its checks in that session:
:func:`run_sections` does that and hands back each check's output and status.

Example::

    ok, reason = guest_available()
    if not ok:
        pytest.skip(f"SocketCAN guest unavailable: {reason}")
    result = run_in_guest("ip -details link show vcan0", timeout=60)
    assert result.returncode == 0, result.describe()
"""
from __future__ import annotations

import dataclasses
import importlib.util
import shlex
import sys
from pathlib import Path

_GUEST_PY = Path(__file__).resolve().parent / "vm" / "guest.py"
_spec = importlib.util.spec_from_file_location("fftune_vm_guest", _GUEST_PY)
_guest = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = _guest  # dataclasses needs the module registered
_spec.loader.exec_module(_guest)

GuestResult = _guest.GuestResult
GuestUnavailable = _guest.GuestUnavailable
REPO_ROOT = _guest.REPO_ROOT
VENV_PYTHON = REPO_ROOT / ".venv" / "bin" / "python"


def guest_available() -> tuple[bool, str]:
    """(True, description) when qemu, a kernel with vcan, busybox-static and cpio are
    installed and we are not inside the guest already; else (False, what is missing)."""
    return _guest.guest_available()


def run_in_guest(command, env: dict | None = None, cwd=None, timeout: float = 300.0,
                 files: dict | None = None, cpus: int = 2) -> GuestResult:
    """Boot the guest, run ``command`` there, power off; a CompletedProcess-like result.

    Parameters
    ----------
    command : str (run by /bin/sh -c) or sequence of str (executed as is).
    env : extra environment on top of tests/vm/guest.py DEFAULT_GUEST_ENV (PATH, HOME=/root,
        TMPDIR=/tmp, LANG, PYTHONDONTWRITEBYTECODE=1, MPLBACKEND=Agg, FFTUNE_IN_VM_GUEST=1,
        FFTUNE_VM_JOB, FFTUNE_VM_OUT). The host environment is not passed on.
    cwd : working directory in the guest; default the repo root.
    timeout : seconds the command may run in the guest; qemu itself is killed
        ``guest.BOOT_ALLOWANCE_S`` later at the latest.
    files : {name: str/bytes} placed at $FFTUNE_VM_JOB/name in the guest.
    cpus : virtual CPUs of the guest.

    Returns
    -------
    GuestResult with returncode, stdout, stderr, timed_out, outputs (files the command
    wrote under $FFTUNE_VM_OUT), init_log, console, duration_s and ``describe()``.
    """
    return _guest.run_in_guest(command, env=env, cwd=cwd, timeout_s=timeout, files=files,
                               cpus=cpus)


@dataclasses.dataclass
class SectionResult:
    """One check of a :func:`run_sections` session."""
    name: str
    returncode: int | None  # None: the section never finished (session killed)
    output: str             # stdout and stderr, interleaved
    files: dict             # {name: text} the section wrote into its $SECTION_OUT directory


def run_sections(sections: dict, env: dict | None = None, cwd=None,
                 section_timeout: float = 120.0, timeout: float = 300.0,
                 files: dict | None = None, cpus: int = 2):
    """Run several shell snippets one after the other in ONE guest boot.

    Each snippet runs under ``/bin/sh -c`` with its own time limit (coreutils ``timeout``,
    status 124 on expiry), its stdout+stderr captured, and ``$SECTION_OUT`` set to a fresh
    directory whose files come back in :attr:`SectionResult.files`. A failing section does
    not stop the next one.

    Returns
    -------
    (sections, result) : ({name: SectionResult}, GuestResult of the whole session)
    """
    lines = ["out=\"$FFTUNE_VM_OUT\""]
    for name, snippet in sections.items():
        if not name.replace("_", "").isalnum():
            raise ValueError(f"section name {name!r}: letters, digits and '_' only")
        lines += [
            f"mkdir -p \"$out/{name}.files\"",
            f"SECTION_OUT=\"$out/{name}.files\" timeout -k 5 {int(section_timeout)} "
            f"/bin/sh -c {shlex.quote(snippet)} > \"$out/{name}.log\" 2>&1 < /dev/null",
            f"echo $? > \"$out/{name}.rc\"",
        ]
    result = run_in_guest("\n".join(lines) + "\n", env=env, cwd=cwd, timeout=timeout,
                          files=files, cpus=cpus)
    found = {}
    for name in sections:
        rc_text = result.outputs.get(f"{name}.rc", "").strip()
        prefix = f"{name}.files/"
        found[name] = SectionResult(
            name=name,
            returncode=int(rc_text) if rc_text.lstrip("-").isdigit() else None,
            output=result.outputs.get(f"{name}.log", ""),
            files={k[len(prefix):]: v for k, v in result.outputs.items() if k.startswith(prefix)})
    return found, result


# Shell function for sections: `wait_can_receivers IFNAME N [TENTHS]` waits until at least N
# CAN_RAW receivers are registered on IFNAME (/proc/net/can/rcvlist_all), i.e. until a
# candump started in the background really listens; default limit 600 tenths of a second.
SH_WAIT_CAN_RECEIVERS = r'''
wait_can_receivers() {
    _i=0
    while [ "$(grep -cE "^ +$1 +[0-9A-Fa-f]+ +[0-9A-Fa-f]+ " /proc/net/can/rcvlist_all)" -lt "$2" ]; do
        _i=$((_i + 1))
        if [ "$_i" -gt "${3:-600}" ]; then
            echo "wait_can_receivers: fewer than $2 receivers on $1" >&2
            return 1
        fi
        sleep 0.1
    done
}
'''
