"""``fftune sim``: the simulated drive (firmware_sim's ``drive_sim``) as a child process.

:func:`start_drive_sim` starts it on a loopback socketcand port (0 = a free one, read
back from its 'listening' line) and returns a :class:`SimulatedDrive` that stops it again
(terminate, then kill) however the caller ends, including on an exception or Ctrl-C.
"""
import os
import re
import select
import signal
import subprocess
import sys
import time

from fftune.analysis.errors import FftuneError
from fftune.host.resources import config_path, drive_sim_path

DEFAULT_PLANT = config_path("plant_twomass.yaml")
_LISTEN = re.compile(r"listening\D*?(?:[\d.]+:)?(\d{2,5})\b", re.IGNORECASE)


class SimulatedDrive:
    """A running ``drive_sim``; ``host``/``port`` is its socketcand server."""

    def __init__(self, proc, host, port, log_path):
        self.proc, self.host, self.port, self.log_path = proc, host, port, log_path

    def stop(self, timeout_s=3.0):
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout_s)
        for fh in (self.proc.stdout, self.proc.stderr):
            if fh:
                fh.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()


def drive_sim_command(plant_config=DEFAULT_PLANT, host="127.0.0.1", port=0, node_id=1, extra=()):
    return [drive_sim_path(), "--can", f"socketcand:{host}:{port}", "--config", plant_config,
            "--node-id", str(node_id), *extra]


def start_drive_sim(plant_config=DEFAULT_PLANT, host="127.0.0.1", port=0, node_id=1,
                    extra=(), startup_timeout_s=10.0, log_path=None):
    """Start ``drive_sim`` and wait for its 'listening' line (the bound port)."""
    drive_sim_path()  # a one-line error when it is missing
    if not os.path.exists(plant_config):
        raise FftuneError(f"plant configuration not found: {plant_config}")
    cmd = drive_sim_command(plant_config, host, port, node_id, extra)
    log = open(log_path, "w") if log_path else subprocess.DEVNULL
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=log, text=True, bufsize=1)
    if log_path:
        log.close()
    deadline = time.monotonic() + startup_timeout_s
    seen = []
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            rest = proc.stdout.read()
            seen.append(rest)
            raise FftuneError(f"drive_sim exited with code {proc.returncode} before listening: "
                              f"{' '.join(cmd)}: {''.join(seen).strip()[-300:]}")
        ready, _, _ = select.select([proc.stdout], [], [], 0.1)
        if not ready:
            continue
        line = proc.stdout.readline()
        seen.append(line)
        m = _LISTEN.search(line)
        if m:
            # Keep draining stdout so that drive_sim never blocks on a full pipe.
            _drain(proc)
            return SimulatedDrive(proc, host, int(m.group(1)), log_path)
    proc.kill()
    proc.wait()
    raise FftuneError(f"drive_sim printed no 'listening' line within {startup_timeout_s:g} s: "
                      f"{' '.join(cmd)}")


def _drain(proc):
    import threading

    def pump():
        try:
            for _ in proc.stdout:
                pass
        except (ValueError, OSError):
            pass
    threading.Thread(target=pump, daemon=True, name="drive_sim-stdout").start()


def add_parser(sub):
    p = sub.add_parser("sim", help="start the simulated drive (drive_sim) in the foreground",
                       description="Run firmware_sim's drive_sim as a CANopen node on a "
                                   "socketcand server; stop it with Ctrl-C.")
    p.add_argument("--plant", default=DEFAULT_PLANT, help="plant configuration (default %(default)s)")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default %(default)s)")
    p.add_argument("--port", type=int, default=29536, help="socketcand TCP port (default %(default)s)")
    p.add_argument("--node-id", type=int, default=1)
    p.add_argument("--realtime", action="store_true", help="step at the controller rate")
    p.set_defaults(func=_run)


def _run(args):
    exe = drive_sim_path()
    if not os.path.exists(args.plant):
        raise FftuneError(f"plant configuration not found: {args.plant}")
    extra = ["--realtime"] if args.realtime else []
    cmd = drive_sim_command(args.plant, args.host, args.port, args.node_id, extra)
    sys.stdout.flush()
    sys.stderr.flush()
    # Become drive_sim: signals (Ctrl-C, kill) reach the simulator itself, no orphan.
    os.execv(exe, cmd)


def derived_plant(base_path, overrides, out_path, where="sim.overrides"):
    """Write ``base_path`` with ``overrides`` ({section: {key: number}}) to ``out_path``
    in drive_sim's two-level YAML subset; returns ``out_path``."""
    import yaml

    from fftune.host.atomic import write_atomic

    try:
        with open(base_path, "r", encoding="utf-8") as fh:
            plant = yaml.safe_load(fh)
    except OSError as exc:
        raise FftuneError(f"plant configuration {base_path}: {exc.strerror}") from None
    for section, values in overrides.items():
        if section not in plant:
            raise FftuneError(f"{where}.{section}: no section '{section}' in {base_path}")
        for key, value in values.items():
            if key not in plant[section]:
                raise FftuneError(f"{where}.{section}.{key}: no key '{key}' in section "
                                  f"'{section}' of {base_path}")
            plant[section][key] = value
    lines = [f"# {os.path.basename(base_path)} with {where} applied (written by fftune demo)"]
    for section, values in plant.items():
        lines.append(f"{section}:")
        for key, value in values.items():
            lines.append(f"  {key}: {value!r}")
    write_atomic(out_path, "\n".join(lines) + "\n")
    return out_path
