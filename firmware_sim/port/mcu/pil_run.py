"""Start the processor-in-the-loop drive (build/mcu/pil.elf) in qemu-system-arm.

The MCU's USART1 is a TCP server on a free loopback port (chosen by qemu, read back over
QMP, so there is no race with other programs); python-can's ``slcan`` interface reaches it
as ``socket://127.0.0.1:PORT``:

    python firmware_sim/port/mcu/pil_run.py            # prints the channel, runs until Ctrl-C
    fftune tune -i slcan -c socket://127.0.0.1:PORT --config configs/pil.yaml

Time: with ``-icount`` virtual time comes from the instruction count. The default
``shift=auto`` lets qemu adjust the rate so that virtual time keeps up with the host clock:
the 2560 Hz control interrupt and the CANopen timers then run at about real time, as the
host's heartbeat and SDO timeouts need. A fixed ``--shift N`` (2^N ns per instruction)
makes virtual time lag the wall clock while the UART model sends (each byte a blocking
write), which on a loaded machine silenced the drive's heartbeat for seconds. The recorded
samples do not depend on the shift. ``--align`` adds ``align=on``: qemu also sleeps when
the guest runs ahead of the wall clock.

Functions for programs and tests: :func:`start` returns a :class:`PilTarget` (``port``,
``channel``, ``stop()``, context manager).
"""
import argparse
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_ELF = os.path.normpath(os.path.join(HERE, "..", "..", "build", "mcu", "pil.elf"))
MACHINE = "netduinoplus2"
QEMU = "qemu-system-arm"


class PilError(Exception):
    """The target could not be started (one line, for ``pil_run: error: ...``)."""


class PilTarget:
    """A running qemu with the drive; ``channel`` is python-can's slcan channel."""

    def __init__(self, proc, port, cmd):
        self.proc, self.port, self.cmd = proc, port, cmd

    @property
    def channel(self):
        return f"socket://127.0.0.1:{self.port}"

    def monitor(self, command):
        """One human-monitor command over QMP (e.g. ``xp /4wx 0x20000000``); its text output."""
        self.proc.stdin.write(json.dumps({"execute": "human-monitor-command",
                                          "arguments": {"command-line": command}}) + "\n")
        self.proc.stdin.flush()
        while True:
            line = self.proc.stdout.readline()
            if not line:
                raise PilError("qemu exited")
            msg = json.loads(line)
            if "return" in msg:
                return msg["return"]
            if "error" in msg:
                raise PilError(f"qemu monitor {command!r}: {msg['error'].get('desc')}")

    def read_words(self, address, count):
        """``count`` 32-bit words of guest memory from ``address`` (physical)."""
        text = self.monitor(f"xp /{int(count)}wx {int(address):#x}")
        return [int(w, 16) for line in text.splitlines() for w in line.split(":", 1)[1].split()]

    def alive(self):
        return self.proc.poll() is None

    def stop(self, timeout_s=3.0):
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout_s)
        for fh in (self.proc.stdin, self.proc.stdout):
            if fh:
                try:
                    fh.close()
                except OSError:
                    pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()


def qemu_command(elf, shift="auto", align=False, extra=()):
    """The qemu-system-arm command line (UART on an ephemeral loopback port, QMP on stdio)."""
    icount = f"shift={shift if shift == 'auto' else int(shift)}" + (",align=on" if align else "")
    return [QEMU, "-M", MACHINE, "-display", "none", "-nodefaults", "-kernel", elf,
            "-icount", icount,
            "-chardev", "socket,id=link,host=127.0.0.1,port=0,server=on,wait=off,nodelay=on",
            "-serial", "chardev:link", "-qmp", "stdio", *extra]


def _qmp(proc, command, deadline):
    """Send one QMP command and return its 'return' value (events are skipped)."""
    proc.stdin.write(json.dumps({"execute": command}) + "\n")
    proc.stdin.flush()
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            raise PilError(f"qemu exited (code {proc.poll()}) while starting")
        msg = json.loads(line)
        if "return" in msg:
            return msg["return"]
        if "error" in msg:
            raise PilError(f"qemu QMP {command}: {msg['error'].get('desc')}")
    raise PilError(f"qemu did not answer QMP {command}")


def start(elf=DEFAULT_ELF, shift="auto", align=False, extra=(), startup_timeout_s=10.0):
    """Start qemu with the drive; returns a :class:`PilTarget` once the port is known."""
    if shutil.which(QEMU) is None:
        raise PilError(f"{QEMU} not found (install: sudo make system-deps, package qemu-system-arm)")
    if not os.path.isfile(elf):
        raise PilError(f"{elf} not built: run `make pil`")
    cmd = qemu_command(elf, shift, align, extra)
    proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True, bufsize=1)
    deadline = time.monotonic() + startup_timeout_s
    try:
        greeting = proc.stdout.readline()
        if not greeting:
            raise PilError(f"qemu exited (code {proc.wait()}) before QMP: {' '.join(cmd)}")
        _qmp(proc, "qmp_capabilities", deadline)
        for dev in _qmp(proc, "query-chardev", deadline):
            if dev.get("label") == "link":
                m = re.search(r"tcp:[\d.]+:(\d+)", dev.get("filename", ""))
                if m:
                    return PilTarget(proc, int(m.group(1)), cmd)
        raise PilError("qemu did not report the UART's TCP port")
    except BaseException:
        proc.kill()
        proc.wait()
        raise


def main(argv=None):
    ap = argparse.ArgumentParser(description="Run the processor-in-the-loop drive in qemu-system-arm.")
    ap.add_argument("--elf", default=DEFAULT_ELF, help="firmware (default: build/mcu/pil.elf)")
    ap.add_argument("--shift", default="auto",
                    help="-icount shift: 2^N ns per instruction, or auto (default: qemu keeps virtual time "
                         "with the host clock, as a host talking to the drive needs)")
    ap.add_argument("--align", action="store_true", help="icount align=on: never run ahead of the wall clock")
    args = ap.parse_args(argv)

    def on_term(signum, frame):
        raise KeyboardInterrupt  # SIGTERM ends qemu as Ctrl-C does

    signal.signal(signal.SIGTERM, on_term)
    try:
        target = start(args.elf, args.shift, args.align)
    except PilError as exc:
        print(f"pil_run: error: {exc}", file=sys.stderr)
        return 2
    print(f"pil_run: {MACHINE} running {os.path.relpath(args.elf)}; SLCAN on "
          f"{target.channel} (fftune ... -i slcan -c {target.channel})", flush=True)
    try:
        target.proc.wait()
    except KeyboardInterrupt:
        pass
    finally:
        target.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
