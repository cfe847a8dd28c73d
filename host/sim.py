"""``fftune sim``: the simulated drive (firmware_sim's ``drive_sim``) as a child process.

:func:`start_drive_sim` starts it on a loopback socketcand port (0 = a free one, read
back from its 'listening' line) and returns a :class:`SimulatedDrive` that stops it again
(terminate, then kill) however the caller ends, including on an exception or Ctrl-C.
"""
import math
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
_LISTEN = re.compile(r"listening on (?:socketcand [\d.]+:(\d+)|socketcan (\S+?)),", re.IGNORECASE)
SIM_INTERFACES = ("socketcand", "socketcan")


class SimulatedDrive:
    """A running ``drive_sim``: on socketcand, ``host``/``port`` is its server; on
    SocketCAN, ``channel`` is the interface (``port`` None)."""

    def __init__(self, proc, host, port, log_path, interface="socketcand", channel=None, bitrate=None):
        self.proc, self.host, self.port, self.log_path = proc, host, port, log_path
        self.interface, self.channel = interface, channel
        self.bitrate = bitrate      # the bus model's bit rate (None: frames pass at once)

    def describe(self):
        if self.interface == "socketcan":
            return f"SocketCAN {self.channel}"
        return f"socketcand {self.host}:{self.port}"

    def bus_options(self, node_id, eds=None):
        """The host's :class:`~fftune.host.drive.BusOptions` to reach this drive's node
        ``node_id`` (``eds`` None: the packaged EDS)."""
        from fftune.host.drive import BusOptions
        from fftune.host.odmap import DEFAULT_EDS

        if self.interface == "socketcan":
            return BusOptions(interface="socketcan", channel=self.channel, node_id=node_id,
                              eds=eds or DEFAULT_EDS)
        return BusOptions(interface="socketcand", channel="can0", host=self.host, port=self.port,
                          node_id=node_id, eds=eds or DEFAULT_EDS, model_bitrate=self.bitrate)

    def reported_error(self):
        """drive_sim's last 'drive_sim: error: ...' message in its log (e.g. an FMU plant's
        step that failed mid-run, docs/fmu.md), or None (also without a log file)."""
        if not self.log_path:
            return None
        try:
            with open(self.log_path, "r", encoding="utf-8", errors="replace") as fh:
                return _drive_sim_error(fh.read())
        except OSError:
            return None

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


def check_bus(interface, channel=None, bitrate=None):
    """A one-line FftuneError for bus options the simulated drive cannot serve."""
    if interface not in SIM_INTERFACES:
        raise FftuneError(f"the simulated drive speaks socketcand or SocketCAN (-i socketcand | "
                          f"-i socketcan -c IFNAME), not -i {interface}")
    if interface == "socketcan" and not channel:
        raise FftuneError("the simulated drive on SocketCAN needs its interface: -c vcan0 "
                          "(set up with: modprobe vcan; ip link add dev vcan0 type vcan; ip link set up vcan0)")
    if bitrate is not None:
        if interface != "socketcand":
            raise FftuneError(f"--bitrate {bitrate}: the bus model is part of drive_sim's socketcand "
                              f"server; a SocketCAN interface ({channel}) has its own bit rate")
        if isinstance(bitrate, bool) or not isinstance(bitrate, int) or not 10_000 <= bitrate <= 1_000_000:
            raise FftuneError(f"--bitrate {bitrate}: a classic CAN bus runs at 10000 .. 1000000 bit/s")


def _bus_spec(interface, host, port, channel):
    return f"socketcand:{host}:{port}" if interface == "socketcand" else f"socketcan:{channel}"


def drive_sim_command(plant_config=DEFAULT_PLANT, host="127.0.0.1", port=0, node_id=1, extra=(),
                      interface="socketcand", channel=None, bitrate=None, realtime=False):
    """drive_sim's command line (see firmware_sim/port/main.c). A plant file naming an FMU
    (``--config`` or an ``--axis ID:FILE`` in ``extra``) is checked and replaced by drive_sim's
    view of it (:func:`fftune.host.fmu.drive_sim_plant`)."""
    from fftune.host.fmu import drive_sim_plant

    check_bus(interface, channel, bitrate)
    if interface == "socketcand":
        import ipaddress
        try:
            ipaddress.IPv4Address(str(host))
        except ValueError:
            raise FftuneError(f"--host {str(host)[:60]!r}: the simulated drive binds its socketcand "
                              f"server to an IPv4 address (127.0.0.1, 0.0.0.0 ...)") from None
    extra = list(extra)
    for i in range(len(extra) - 1):
        if extra[i] == "--axis" and ":" in extra[i + 1]:
            nid, path = extra[i + 1].split(":", 1)
            extra[i + 1] = f"{nid}:{drive_sim_plant(path)}"
    cmd = [drive_sim_path(), "--can", _bus_spec(interface, host, port, channel), "--config",
           drive_sim_plant(plant_config), "--node-id", str(node_id)]
    if bitrate is not None:
        cmd += ["--bitrate", str(bitrate)]
    if realtime:
        cmd.append("--realtime")
    return cmd + list(extra)


def start_drive_sim(plant_config=DEFAULT_PLANT, host="127.0.0.1", port=0, node_id=1,
                    extra=(), startup_timeout_s=10.0, log_path=None, interface="socketcand",
                    channel=None, bitrate=None, realtime=False):
    """Start ``drive_sim`` and wait for its 'listening' line (the bound port)."""
    from fftune.host.config import read_plant

    drive_sim_path()  # a one-line error when it is missing
    if not os.path.exists(plant_config):
        raise FftuneError(f"plant configuration not found: {plant_config}")
    read_plant(plant_config)    # the one plant loader: a directory, FIFO, bomb or wrong shape refused
    cmd = drive_sim_command(plant_config, host, port, node_id, extra, interface=interface,
                            channel=channel, bitrate=bitrate, realtime=realtime)
    log = open(log_path, "w") if log_path else subprocess.DEVNULL
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE if not log_path else log,
                            text=True, bufsize=1)
    if log_path:
        log.close()
    deadline = time.monotonic() + startup_timeout_s
    seen = []
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            seen.append(proc.stdout.read())
            if proc.stderr:
                seen.append(proc.stderr.read())
            elif log_path:
                with open(log_path, encoding="utf-8", errors="replace") as fh:
                    seen.append(fh.read())
            said = _drive_sim_error("".join(seen))
            if said:  # drive_sim's own one-line reason (a plant file, an FMU): that line alone
                raise FftuneError(f"drive_sim: {said}")
            raise FftuneError(f"drive_sim exited with code {proc.returncode} before listening: "
                              f"{' '.join(cmd)}: {' '.join(''.join(seen).split())[-300:]}")
        ready, _, _ = select.select([proc.stdout], [], [], 0.1)
        if not ready:
            continue
        line = proc.stdout.readline()
        seen.append(line)
        m = _LISTEN.search(line)
        if m:
            # Keep draining stdout (and stderr) so that drive_sim never blocks on a full pipe.
            _drain(proc)
            if m.group(1):
                return SimulatedDrive(proc, host, int(m.group(1)), log_path, bitrate=bitrate)
            return SimulatedDrive(proc, None, None, log_path, interface="socketcan", channel=m.group(2))
    proc.kill()
    proc.wait()
    raise FftuneError(f"drive_sim printed no 'listening' line within {startup_timeout_s:g} s: "
                      f"{' '.join(cmd)}")


# The first line of a plant file fftune derived (base file + overrides): drive_sim's errors
# about it name the user's file and the overrides instead (the derived text's own path is a
# run's plant.yaml or, for `fftune sim`, a memory file /proc/self/fd/N nobody can open).
_DERIVED_MARK = "# fftune: derived plant: "


def _drive_sim_error(text):
    """The message of drive_sim's last 'drive_sim: error: ...' line in ``text`` (or None),
    a derived plant named by its origin (:func:`named_plant_error`)."""
    found = None
    for line in text.splitlines():
        if line.startswith("drive_sim: error: "):
            found = line[len("drive_sim: error: "):].strip()
    return None if found is None else named_plant_error(found)


def named_plant_error(message):
    """drive_sim's error ``message`` with a derived plant file's path (and its line number,
    which counts lines of the derived text) replaced by the origin its first line records:
    ``base.yaml (with <config>: key 'sim.overrides' applied): plant.j1 = ...: out of range``.
    Other messages are returned unchanged."""
    m = re.match(r"(?P<path>[^:]+?)(?::\d+)?: (?P<rest>.*)\Z", message, re.S)
    if not m:
        return message
    try:
        with open(m["path"], "r", encoding="utf-8", errors="replace") as fh:
            first = fh.readline(4096)
    except OSError:
        return message
    if not first.startswith(_DERIVED_MARK):
        return message
    return f"{first[len(_DERIVED_MARK):].strip()}: {m['rest']}"


def check_drive_sim_command(cmd):
    """Run drive_sim's ``cmd`` with ``--check`` (every plant file and FMU loaded and
    range-checked, no bus opened): one FftuneError line naming the file (its origin, for a
    derived plant) and the key, or None. For ``fftune sim``, whose drive_sim replaces the
    process: its refusals then read as every other command's."""
    fds = [int(m) for m in re.findall(r"/proc/self/fd/(\d+)", " ".join(cmd))]
    for fd in fds:
        os.lseek(fd, 0, os.SEEK_SET)
    try:
        done = subprocess.run([*cmd, "--check"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True, errors="replace", pass_fds=fds, timeout=60)
    except subprocess.TimeoutExpired:
        raise FftuneError(f"drive_sim --check did not finish within 60 s: {' '.join(cmd)}") from None
    finally:
        for fd in fds:
            os.lseek(fd, 0, os.SEEK_SET)    # (drive_sim reads the memory file again after exec)
    if done.returncode != 0:
        said = _drive_sim_error(done.stderr)
        raise FftuneError(f"drive_sim: {said}" if said else
                          f"drive_sim --check exited with code {done.returncode}: "
                          f"{' '.join(done.stderr.split())[-300:]}")


def _drain(proc):
    import threading

    def pump(stream):
        try:
            for _ in stream:
                pass
        except (ValueError, OSError):
            pass
    for stream in (proc.stdout, proc.stderr):
        if stream is not None:
            threading.Thread(target=pump, args=(stream,), daemon=True, name="drive_sim-output").start()


def add_parser(sub):
    from fftune.host.drive import add_bus_arguments
    from fftune.host.resources import config_path

    p = sub.add_parser("sim", help="start the simulated drive (drive_sim) in the foreground",
                       description="Run firmware_sim's drive_sim as a CANopen node on a "
                                   "socketcand server (default 127.0.0.1:29536) or on a SocketCAN "
                                   "interface (-i socketcan -c vcan0); stop it with Ctrl-C. The "
                                   "host then connects with the same bus options. The plant is "
                                   "the one `fftune demo` simulates for the same configuration: "
                                   "its sim.plant with sim.overrides applied (and its "
                                   "sim.bitrate, drive.node_id unless given here).")
    p.add_argument("--config", default=config_path("demo.yaml"),
                   help="configuration whose sim: section (plant, overrides, bitrate) is "
                        "simulated (default: configs/demo.yaml, as fftune demo)")
    p.add_argument("--plant", default=None,
                   help="plant configuration (default: the configuration's sim.plant, else "
                        "configs/plant_twomass.yaml); the configuration's sim.overrides apply to it")
    p.add_argument("--realtime", action="store_true", help="step at the controller rate")
    p.add_argument("--machine", default=None, metavar="FILE",
                   help="serve every axis of a machine file, one node each on the one bus "
                        "(docs/machine.md)")
    add_bus_arguments(p, drive_side=True)
    p.set_defaults(func=_run)


def _bus_from_python_can(args):
    """Without ``-i``: the bus python-can's configuration names (as ``fftune run`` reads it,
    so that both meet) when the simulated drive can serve it, else socketcand (said so)."""
    from fftune.host.drive import (DEFAULT_SOCKETCAND_HOST, DEFAULT_SOCKETCAND_PORT,
                                   python_can_config)

    if args.interface is not None:
        return
    conf = python_can_config()
    name = conf.get("interface")
    if name in SIM_INTERFACES:
        args.interface = name
        if args.channel is None:
            args.channel = conf.get("channel")
        if name == "socketcand":
            if args.host == DEFAULT_SOCKETCAND_HOST:
                args.host = conf.get("host", args.host)
            if args.port == DEFAULT_SOCKETCAND_PORT:
                args.port = conf.get("port", args.port)
        return
    if name:
        print(f"fftune sim: python-can's configuration names interface {name}, which the "
              f"simulated drive cannot serve: socketcand (-i socketcand | -i socketcan -c IFNAME "
              f"to choose)", file=sys.stderr)
    args.interface = "socketcand"


def _plant_path(text):
    """A path drive_sim can open holding ``text`` and surviving exec: an anonymous memory
    file (Linux memfd, inherited by drive_sim; nothing left on disk), else a temporary file."""
    data = text.encode("utf-8")
    if hasattr(os, "memfd_create"):
        fd = os.memfd_create("fftune-plant", 0)
        os.write(fd, data)
        os.lseek(fd, 0, os.SEEK_SET)
        os.set_inheritable(fd, True)
        return f"/proc/self/fd/{fd}"
    import tempfile
    fd, path = tempfile.mkstemp(prefix="fftune-plant-", suffix=".yaml")
    os.write(fd, data)
    os.close(fd)
    return path


def _run(args):
    from fftune.host.config import load_config
    from fftune.host.demo import resolve_plant

    exe = drive_sim_path()
    if args.machine:
        from fftune.host.machine import sim_axis_args
        _bus_from_python_can(args)
        extra = sim_axis_args(args.machine, plant_path=_plant_path)
        cmd = drive_sim_command(DEFAULT_PLANT, args.host, args.port, 1, extra=extra,
                                interface=args.interface, channel=args.channel, bitrate=args.bitrate,
                                realtime=args.realtime)
        check_drive_sim_command(cmd)
        sys.stdout.flush()
        sys.stderr.flush()
        os.execv(exe, cmd)
    cfg = load_config(args.config)
    plant = resolve_plant(cfg, args.plant)
    if not os.path.exists(plant):
        raise FftuneError(f"plant configuration not found: {plant}")
    from fftune.host.config import read_plant
    read_plant(plant)           # (before drive_sim replaces this process: one fftune error line)
    bitrate = args.bitrate if args.bitrate is not None else cfg["sim"]["bitrate"]
    node_id = args.node_id if args.node_id is not None else cfg["drive"]["node_id"]
    _bus_from_python_can(args)
    check_bus(args.interface, args.channel, bitrate)
    if cfg["sim"]["overrides"]:
        from fftune.host.fmu import is_fmu_plant, overrides_note
        where = f"{args.config}: key 'sim.overrides'"
        if is_fmu_plant(plant):
            print(f"fftune sim: {overrides_note(plant, where)}", file=sys.stderr)
        else:
            plant = _plant_path(derived_plant_text(plant, cfg["sim"]["overrides"], where=where))
    cmd = drive_sim_command(plant, args.host, args.port, node_id,
                            interface=args.interface, channel=args.channel, bitrate=bitrate,
                            realtime=args.realtime)
    check_drive_sim_command(cmd)
    sys.stdout.flush()
    sys.stderr.flush()
    # Become drive_sim: signals (Ctrl-C, kill) reach the simulator itself, no orphan.
    os.execv(exe, cmd)


def derived_plant(base_path, overrides, out_path, where="sim.overrides"):
    """Write ``base_path`` with ``overrides`` ({section: {key: number}}) to ``out_path``
    in drive_sim's two-level YAML subset; returns ``out_path``."""
    from fftune.host.atomic import write_atomic

    write_atomic(out_path, derived_plant_text(base_path, overrides, where))
    return out_path


def derived_plant_text(base_path, overrides, where="sim.overrides"):
    """``base_path`` with ``overrides`` applied, as drive_sim's two-level YAML subset."""

    from fftune.host.config import read_yaml, show
    from fftune.host.fmu import is_fmu_plant

    if overrides and is_fmu_plant(base_path):
        raise FftuneError(f"{where}: the plant {base_path} is an FMU: overrides of the built-in plant do not "
                          f"apply to it (set its values in fmu.parameters; docs/fmu.md)")

    plant = read_yaml(base_path, "plant configuration")
    if not isinstance(plant, dict) or not all(isinstance(v, dict) for v in plant.values()):
        raise FftuneError(f"plant configuration {base_path}: expected sections of key: value")
    if not isinstance(overrides, dict):
        raise FftuneError(f"{where}: expected {{section: {{key: number}}}}, got {show(overrides)}")
    for section, values in overrides.items():
        if section not in plant:
            raise FftuneError(f"{where}.{str(section)[:40]}: no section '{str(section)[:40]}' in {base_path}")
        if not isinstance(values, dict):
            raise FftuneError(f"{where}.{section}: expected {{key: number}}, got {show(values)}")
        for key, value in values.items():
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise FftuneError(f"{where}.{section}.{str(key)[:40]}: expected a finite number, got {show(value)}")
            if key not in plant[section]:
                raise FftuneError(f"{where}.{section}.{key}: no key '{key}' in section "
                                  f"'{section}' of {base_path}")
            plant[section][key] = value
    lines = [f"{_DERIVED_MARK}{base_path} (with {where} applied)"]
    for section, values in plant.items():
        lines.append(f"{section}:")
        for key, value in values.items():
            lines.append(f"  {key}: {value!r}")
    return "\n".join(lines) + "\n"
