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
    duration_s: float | None = None   # wall time of the section in the guest


def run_sections(sections: dict, env: dict | None = None, cwd=None,
                 section_timeout: float | dict = 120.0, timeout: float = 300.0,
                 files: dict | None = None, cpus: int = 2):
    """Run several shell snippets one after the other in ONE guest boot.

    Each snippet runs under ``/bin/sh -c`` with its own time limit (coreutils ``timeout``,
    status 124 on expiry; ``section_timeout`` is one limit for all or ``{name: seconds}``),
    its stdout+stderr captured, and ``$SECTION_OUT`` set to a fresh directory whose files
    come back in :attr:`SectionResult.files`. A failing section does not stop the next one.

    Returns
    -------
    (sections, result) : ({name: SectionResult}, GuestResult of the whole session)
    """
    limits = (section_timeout if isinstance(section_timeout, dict)
              else dict.fromkeys(sections, section_timeout))
    lines = ["out=\"$FFTUNE_VM_OUT\""]
    for name, snippet in sections.items():
        if not name.replace("_", "").isalnum():
            raise ValueError(f"section name {name!r}: letters, digits and '_' only")
        lines += [
            f"date +%s.%N > \"$out/{name}.t0\"",
            f"mkdir -p \"$out/{name}.files\"",
            f"SECTION_OUT=\"$out/{name}.files\" timeout -k 5 {int(limits[name])} "
            f"/bin/sh -c {shlex.quote(snippet)} > \"$out/{name}.log\" 2>&1 < /dev/null",
            f"echo $? > \"$out/{name}.rc\"",
            f"date +%s.%N > \"$out/{name}.t1\"",
        ]
    result = run_in_guest("\n".join(lines) + "\n", env=env, cwd=cwd, timeout=timeout,
                          files=files, cpus=cpus)
    found = {}
    for name in sections:
        rc_text = result.outputs.get(f"{name}.rc", "").strip()
        try:
            duration = (float(result.outputs[f"{name}.t1"]) - float(result.outputs[f"{name}.t0"]))
        except (KeyError, ValueError):
            duration = None
        prefix = f"{name}.files/"
        found[name] = SectionResult(
            name=name,
            returncode=int(rc_text) if rc_text.lstrip("-").isdigit() else None,
            output=result.outputs.get(f"{name}.log", ""),
            files={k[len(prefix):]: v for k, v in result.outputs.items() if k.startswith(prefix)},
            duration_s=duration)
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


# --------------------------------------------------------------------------- one boot
# A VM test module declares what it runs in the guest at module level:
#
#     VM_SECTIONS = {"link": "ip -details link show vcan0", ...}   # name -> shell snippet
#     VM_SECTION_TIMEOUT_S = 150          # optional: one limit, or {name: seconds}
#     VM_FILES = {"check.py": "..."}      # optional: files at $FFTUNE_VM_JOB/name
#     def vm_skip_reason(): ...           # optional: None, or why this module cannot run
#
# and gets its results through the session fixture ``vm_session`` (tests/conftest.py):
# ``sections, whole = vm_session.results(request.module)``. The first request boots ONE
# guest that runs the sections of every VM module of this pytest run, one after the other
# (docs/vm-testing.md: a boot costs 7-25 s and Python's start-up in the guest 5-40 s, and
# several boots were most of `make test`'s time).
DEFAULT_SECTION_TIMEOUT_S = 150.0


def _module_sections(module):
    timeouts = getattr(module, "VM_SECTION_TIMEOUT_S", DEFAULT_SECTION_TIMEOUT_S)
    for name, snippet in module.VM_SECTIONS.items():
        limit = timeouts.get(name, DEFAULT_SECTION_TIMEOUT_S) if isinstance(timeouts, dict) \
            else timeouts
        yield name, snippet, float(limit)


class SharedGuestSession:
    """The guest sections of every VM test module of a pytest session, run in one boot.

    Parameters
    ----------
    modules : iterable of module
        Test modules with a ``VM_SECTIONS`` attribute (others are ignored), in the order
        their sections should run.
    """

    def __init__(self, modules):
        seen, self.modules = set(), []
        for module in modules:
            if hasattr(module, "VM_SECTIONS") and module.__name__ not in seen:
                seen.add(module.__name__)
                self.modules.append(module)
        self._results = None
        self._skips = {}

    @staticmethod
    def _key(module, name):
        return f"{module.__name__.rsplit('.', 1)[-1]}__{name}"

    def _run(self):
        ok, reason = guest_available()
        if not ok:
            self._results = f"SocketCAN qemu guest unavailable: {reason}"
            return
        sections, timeouts, files = {}, {}, {}
        for module in self.modules:
            why = getattr(module, "vm_skip_reason", lambda: None)()
            if why:
                self._skips[module.__name__] = why
                continue
            for name, snippet, limit in _module_sections(module):
                key = self._key(module, name)
                sections[key], timeouts[key] = snippet, limit
            for fname, content in getattr(module, "VM_FILES", {}).items():
                if fname in files and files[fname] != content:
                    raise ValueError(f"{module.__name__}: VM_FILES name {fname!r} used twice")
                files[fname] = content
        if not sections:
            self._results = {}
            return
        total = sum(timeouts.values()) + 30.0
        found, whole = run_sections(sections, section_timeout=timeouts, timeout=total,
                                    files=files)
        self._results = (found, whole)
        # where the time went, for a look after the run (build/ is ignored by git)
        summary = [f"shared guest session: {whole.duration_s:.1f} s boot-run-poweroff, "
                   f"returncode {whole.returncode}"]
        summary += [f"  {name}: rc {r.returncode}, "
                    + (f"{r.duration_s:.1f} s" if r.duration_s is not None else "no time")
                    for name, r in found.items()]
        try:
            log = _guest.CACHE_DIR / "last-session.txt"
            log.parent.mkdir(parents=True, exist_ok=True)
            log.write_text("\n".join(summary) + "\n\n" + whole.init_log)
        except OSError:
            pass

    def results(self, module):
        """(``{section name: SectionResult}``, ``GuestResult`` of the shared boot) of
        ``module``; ``pytest.skip`` with the reason when the guest or the module's own
        prerequisites are missing."""
        import pytest

        if self._results is None:
            self._run()
        if isinstance(self._results, str):
            pytest.skip(self._results)
        if module.__name__ in self._skips:
            pytest.skip(self._skips[module.__name__])
        if module not in self.modules:
            raise LookupError(f"{module.__name__} has no VM_SECTIONS")
        found, whole = self._results
        prefix = self._key(module, "")
        return {k[len(prefix):]: v for k, v in found.items() if k.startswith(prefix)}, whole

    def timeout_s(self):
        """Upper bound of the shared session's wall time (for pytest-timeout)."""
        total = sum(limit for m in self.modules for _, _, limit in _module_sections(m))
        return total + 30.0 + _guest.BOOT_ALLOWANCE_S
