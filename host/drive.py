"""The drive client: one CANopen drive reached through any python-can interface.

:class:`DriveClient` connects with python-can's own option names (``interface``,
``channel``, ``bitrate``; ``host``/``port`` for socketcand), imports the drive's EDS into a
python-canopen :class:`canopen.BaseNode402`, brings the drive to OPERATION ENABLED, sets
parameters by name, starts excitation runs, waits for them with a progress bar, uploads the
recording by SDO block transfer and checks its sample count. Heartbeats run both ways: the
drive watches the host's (object 0x1016), the client watches the drive's and its boot-up.

Every failure a user can cause or meet (unreachable bus, wrong node id, SDO abort, timeout,
run stopped by the drive) is raised as one :class:`fftune.analysis.errors.FftuneError` line.
"""
import argparse
import contextlib
import logging
import os
import signal
import socket
import struct
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from fftune.analysis.errors import FftuneError
from fftune.analysis.stats import STAT_K_MAX, STAT_SIG_MAX
from fftune.host.config import CAPTURE_MODES
from fftune.host.odmap import (DEFAULT_EDS, PARAMS, RUN_STATES, SIGNAL_BITS, STOP_REASONS,
                                check_drive_profile)

DEFAULT_SOCKETCAND_HOST = "127.0.0.1"
DEFAULT_SOCKETCAND_PORT = 29536
DEFAULT_SOCKETCAND_CHANNEL = "can0"
CONNECT_DEADLINE_S = 4.5
# CiA 402 abort connection option code: what the drive does when the host is lost
# (0 nothing, 1 fault, 2 disable voltage, 3 quick stop); the host never leaves it at 0.
ABORT_CONNECTION_INDEX = 0x6007
ABORT_CONNECTION_DEFAULT = 2

logger = logging.getLogger(__name__)


def quiet_can_loggers():
    """python-can's socketcand client logs every partial TCP read and every refused
    connection attempt as a warning; keep the user's terminal readable."""
    logging.getLogger("can.interfaces.socketcand").setLevel(logging.ERROR)
    # (CRITICAL: a receive error on a lost connection is logged with a traceback; the next
    # SDO request reports it as one line)
    logging.getLogger("can.interfaces.socketcand.socketcand").setLevel(logging.CRITICAL)
    # a heartbeat send failing on a lost connection: reported by the next SDO request
    logging.getLogger("can.bcm").setLevel(logging.CRITICAL)
    # python-canopen logs SDO retries and aborts itself; we report them as errors.
    logging.getLogger("canopen").setLevel(logging.CRITICAL)


def int_in_range(name, low, high, unit=""):
    """An argparse ``type``: an integer ``low .. high`` (``0x`` hex allowed), else an error
    naming the option and the range (one ``fftune: error:`` line, exit 2)."""
    def parse(text):
        try:
            value = int(str(text).strip(), 0)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer {low} .. {high}{unit}, got {text!r}") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"{value}: expected {low} .. {high}{unit}")
        return value
    parse.__name__ = name
    return parse


def add_bus_arguments(parser, drive_side=False, port_default=DEFAULT_SOCKETCAND_PORT):
    """python-can's option names (as in ``python -m can.logger``) plus the drive's.

    ``drive_side``: for ``fftune sim`` (the drive itself): ``--bitrate`` is the simulated
    bus's bit rate, ``--host``/``--port`` the server's address, no ``--eds``.
    """
    g = parser.add_argument_group("CAN bus (python-can options)")
    g.add_argument("-i", "--interface", default=None,
                   help="socketcand or socketcan (default: socketcand; `fftune sim`: python-can's "
                        "configuration when it names one of these)" if drive_side else
                   "python-can interface: socketcand, socketcan, pcan, kvaser, virtual, ... "
                   "(default: python-can's configuration, as its own tools read it: "
                   "CAN_INTERFACE / CAN_CHANNEL / CAN_BITRATE, ~/.canrc, can.ini ...; "
                   "else socketcand, the simulated drive)")
    g.add_argument("-c", "--channel", default=None,
                   help="channel (socketcand: the bus name served, default can0; socketcan: vcan0 ...)")
    g.add_argument("-b", "--bitrate", type=int_in_range("bit rate", 10_000, 1_000_000, " bit/s"), default=None,
                   help="simulate a classic CAN bus of this bit rate (socketcand only; default: "
                        "frames pass at once)" if drive_side else "bit rate in bit/s")
    g.add_argument("--host", default=DEFAULT_SOCKETCAND_HOST,
                   help=f"socketcand address to bind (default {DEFAULT_SOCKETCAND_HOST})" if drive_side else
                   f"socketcand server (default {DEFAULT_SOCKETCAND_HOST}, the simulated drive)")
    g.add_argument("--port", type=int_in_range("port", 0 if drive_side else 1, 65535),  # (0: a free one)
                   default=port_default,
                   help=f"socketcand TCP port (default {port_default if port_default else 'a free one'})")
    g.add_argument("--node-id", type=int_in_range("node id", 1, 127), default=None,
                   help="drive node id 1 .. 127 (default: config, else 1)")
    if not drive_side:
        g.add_argument("--eds", default=None,
                       help="the drive's EDS (default: config, else the firmware_sim build's)")


def python_can_config():
    """python-can's own bus configuration, read as its tools read it
    (:func:`can.util.load_config`: ``can.rc``, the environment variables CAN_INTERFACE,
    CAN_CHANNEL, CAN_BITRATE and CAN_CONFIG, the files /etc/can.conf, ~/.can, ~/.canrc,
    ~/can.conf); ``{}`` when it names no interface. A broken one is one error line."""
    import can

    try:
        sources = (can.rc, can.util.load_environment_config(), can.util.load_file_config())
        if not any(src.get("interface") or src.get("bustype") for src in sources):
            return {}           # nothing configured: load_config would refuse interface None
        conf = can.util.load_config()
    except (can.CanError, ValueError, TypeError, KeyError, OSError) as exc:
        raise FftuneError(f"python-can configuration (CAN_INTERFACE / CAN_CHANNEL / CAN_BITRATE "
                          f"/ CAN_CONFIG, ~/.canrc ...): {exc}") from None
    return dict(conf) if conf.get("interface") else {}


@dataclass
class BusOptions:
    """Where the drive is: python-can interface options plus node id and EDS."""

    interface: str = "socketcand"
    channel: str = None
    bitrate: int = None
    host: str = DEFAULT_SOCKETCAND_HOST
    port: int = DEFAULT_SOCKETCAND_PORT
    node_id: int = 1
    eds: str = None
    # the bit rate of a simulated bus (drive_sim --bitrate): not a python-can option; the host
    # shortens its SDO bursts to it (sdo_burst_frames)
    model_bitrate: int = None

    @classmethod
    def from_args(cls, args, cfg_drive=None):
        """The options of the command line; without ``-i``, python-can's own configuration
        (:func:`python_can_config`) where it names an interface, else socketcand."""
        cfg_drive = cfg_drive or {}
        interface, channel, bitrate = args.interface, args.channel, args.bitrate
        host, port = args.host, args.port
        if interface is None:
            conf = python_can_config()
            interface = conf.get("interface") or "socketcand"
            if conf.get("interface"):
                channel = channel if channel is not None else conf.get("channel")
                bitrate = bitrate if bitrate is not None else conf.get("bitrate")
                if interface == "socketcand":
                    # (python-can's socketcand keys; the command line's when given)
                    host = conf.get("host", host) if host == DEFAULT_SOCKETCAND_HOST else host
                    port = conf.get("port", port) if port == DEFAULT_SOCKETCAND_PORT else port
        # python-can's configuration is text (CAN_BITRATE=abc, a port of 70000): the command
        # line's ranges, one error line naming where it came from
        for name, value, low, high in (("bitrate", bitrate, 10_000, 1_000_000), ("port", port, 1, 65535)):
            if value is None or (isinstance(value, int) and not isinstance(value, bool) and low <= value <= high):
                continue
            try:
                number = int(str(value).strip(), 0)
            except ValueError:
                number = None
            if number is None or not low <= number <= high:
                raise FftuneError(f"python-can configuration (CAN_BITRATE, CAN_CONFIG, ~/.canrc ...): "
                                  f"{name} {str(value)[:40]!r}: expected an integer {low} .. {high}")
            if name == "bitrate":
                bitrate = number
            else:
                port = number
        return cls(interface=interface, channel=channel, bitrate=bitrate, host=host, port=port,
                   node_id=args.node_id if args.node_id is not None else cfg_drive.get("node_id", 1),
                   eds=args.eds or cfg_drive.get("eds") or DEFAULT_EDS)

    def bus_kwargs(self):
        kw = {"interface": self.interface}
        if self.interface == "socketcand":
            kw.update(channel=self.channel or DEFAULT_SOCKETCAND_CHANNEL, host=self.host, port=self.port)
        elif self.channel is not None:
            kw["channel"] = self.channel
        if self.bitrate is not None:
            kw["bitrate"] = self.bitrate
        return kw

    def describe(self):
        if self.interface == "socketcand":
            return (f"interface socketcand, channel {self.channel or DEFAULT_SOCKETCAND_CHANNEL} "
                    f"at {self.host}:{self.port}")
        return f"interface {self.interface}, channel {self.channel}"


def stats_parameters(stats):
    """Drive parameters (``stat_harmonics``, ``stat_signals``, ``stat_power``) for a
    statistics request ``{"harmonics": K, "signals": [names], "power": [names]}``."""
    def bits(names, key):
        m = 0
        for name in names or ():
            if name not in SIGNAL_BITS:
                raise FftuneError(f"statistics: key '{key}': unknown signal {name!r} (expected one of "
                                  f"{', '.join(SIGNAL_BITS)})")
            m |= 1 << SIGNAL_BITS[name]
        return m
    return {"stat_harmonics": int(stats.get("harmonics", 0)),
            "stat_signals": bits(stats.get("signals"), "signals"),
            "stat_power": bits(stats.get("power"), "power")}


@dataclass
class RunRecord:
    """One completed run: the recorded signals and what the drive was set to."""

    signals: dict                 # name -> float64 array, length record_periods * N
    parameters: dict              # alias -> value read back from the drive after the run
    fs_hz: float
    period_samples: int
    settle_periods: int
    record_periods: int
    run_counter: int
    t_start: float                # POSIX time
    t_end: float
    meta: dict = field(default_factory=dict)
    # on-drive line statistics (fftune.analysis.stats.HarmonicStats) when captured
    stats: object = None
    # on-drive multisine line statistics (fftune.analysis.stats.LineStats) when captured
    line_stats: object = None


def sdo_abort_text(exc):
    """``0x06090031 (Value of parameter written too high)`` from an SdoAbortedError."""
    from canopen.sdo.exceptions import SdoAbortedError
    code = exc.code
    meaning = SdoAbortedError.CODES.get(code, "unknown abort code")
    return f"SDO abort 0x{code:08X} ({meaning})"


def _open_bus(opts, deadline_s=CONNECT_DEADLINE_S):
    """A python-can bus, or an FftuneError naming interface and channel within the deadline."""
    import can

    quiet_can_loggers()
    t0 = time.monotonic()
    if opts.interface == "socketcan":
        from fftune.host.socketcan_check import socketcan_problem
        problem = socketcan_problem(opts.channel)
        if problem:
            raise FftuneError(f"cannot open CAN bus: {opts.describe()}: {problem}")
    if opts.interface == "socketcand":
        # python-can's client retries a refused connection for 10 s; find out first.
        try:
            with socket.create_connection((opts.host, opts.port), timeout=min(2.0, deadline_s)):
                pass
        except OSError as exc:
            reason = exc.strerror or type(exc).__name__
            raise FftuneError(f"drive not reachable: {opts.describe()}: {reason}"
                              " (is the drive running? `fftune sim` starts the simulated one)") from None
    result = {}

    def worker():
        try:
            result["bus"] = can.Bus(**opts.bus_kwargs())
        except Exception as exc:  # any interface's own error type
            result["error"] = exc

    th = threading.Thread(target=worker, daemon=True, name="fftune-bus-open")
    th.start()
    th.join(max(0.1, deadline_s - (time.monotonic() - t0)))
    if th.is_alive():
        raise FftuneError(f"drive not reachable: {opts.describe()}: no answer within {deadline_s:.0f} s")
    if "error" in result:
        exc = result["error"]
        raise FftuneError(f"cannot open CAN bus: {opts.describe()}: {type(exc).__name__}: {exc}") from None
    return result["bus"]


def frame_bits(n_bytes):
    """Bit times of a classic base-format data frame with ``n_bytes`` data bytes, worst-case
    bit stuffing, plus the interframe space (docs/track.md; REFERENCE.md section 3)."""
    return 47 + 8 * n_bytes + (34 + 8 * n_bytes - 1) // 4


# The host's heartbeat may wait behind at most this share of its period of SDO frames (an SDO
# sub-block of the drive wins arbitration against it; one of the host's own waits ahead of it
# in its transmit queue). The consumer watches with 4 periods: a heartbeat delayed by 1.5
# periods leaves 1.5 periods for the host's own jitter.
SDO_BURST_SHARE = 1.5
SDO_BLKSIZE_MAX = 127


def sdo_burst_frames(bitrate, heartbeat_ms, nodes=1):
    """How many SDO frames may go back to back on a bus of ``bitrate`` bit/s so that the
    host's heartbeat (period ``heartbeat_ms``) keeps its consumer fed while ``nodes`` drives
    may transfer at once: the sub-block size of block uploads, the burst of block downloads.

    Returns ``SDO_BLKSIZE_MAX`` for an unknown bit rate or no heartbeat; raises
    FftuneError (the reason named) when not even one frame per node fits."""
    if not bitrate or not heartbeat_ms:
        return SDO_BLKSIZE_MAX
    frame_s = frame_bits(8) / float(bitrate)
    n = int(SDO_BURST_SHARE * heartbeat_ms / 1000.0 / (frame_s * max(1, nodes)))
    if n < 1:
        raise FftuneError(
            f"bit rate {bitrate} bit/s with drive.heartbeat_ms {heartbeat_ms}: one SDO frame of "
            f"each of {nodes} node(s) takes {1000 * frame_s * max(1, nodes):.1f} ms on the bus, more than "
            f"{SDO_BURST_SHARE:g} heartbeat periods ({SDO_BURST_SHARE * heartbeat_ms:g} ms): the host's "
            f"heartbeat (the lowest priority on the bus) could not keep the drives' consumer "
            f"fed; raise drive.heartbeat_ms or the bit rate")
    return min(SDO_BLKSIZE_MAX, n)


class _SdoPacer:
    """Paces the host's SDO requests (COB-IDs 0x600 + node) on ``network`` so that a block
    download never queues more than ``burst`` frames ahead of the host's heartbeat in its
    transmit queue: a token bucket of ``burst`` frames refilled at 70 % of the bus' frame
    rate (one CAN controller queue per host, as drive_sim's bus model and a SocketCAN
    queue have). The heartbeat itself (send_periodic) is not paced."""

    RATE_SHARE = 0.7

    def __init__(self, network, bitrate, burst):
        self.interval_s = frame_bits(8) / float(bitrate) / self.RATE_SHARE
        self.burst = float(burst)
        self.tokens = float(burst)
        self.t = time.monotonic()
        self.lock = threading.Lock()
        self.network = network
        self._send = network.send_message

        def send(can_id, data, remote=False):
            if 0x600 < can_id <= 0x67F:
                self.wait()
            return self._send(can_id, data, remote)
        network.send_message = send

    def wait(self):
        with self.lock:
            now = time.monotonic()
            self.tokens = min(self.burst, self.tokens + (now - self.t) / self.interval_s)
            self.t = now
            if self.tokens < 1.0:
                time.sleep((1.0 - self.tokens) * self.interval_s)
                self.t = time.monotonic()
                self.tokens = 1.0
            self.tokens -= 1.0


class HostHeartbeat:
    """The host's heartbeat on one bus: one node id, one period (CANopen heartbeat producer,
    state 0x05 OPERATIONAL on COB-ID 0x700 + ``node_id``). Every drive the host enables has
    its consumer (0x1016) armed for exactly this producer (:meth:`DriveClient.enable`).

    :meth:`start` first listens for ``listen_periods`` periods (at least 0.1 s, at most
    ``LISTEN_MAX_S``): a frame on the COB-ID means another producer (another fftune session
    with the same host id, a node with that id) and is refused, naming it: its heartbeat
    would feed the drives after this host died. (A producer slower than one frame in
    ``LISTEN_MAX_S`` may pass unseen.)
    """

    LISTEN_MAX_S = 2.0

    def __init__(self, network, node_id, period_ms, listen_periods=2.0):
        self.network = network
        self.node_id = int(node_id)
        self.period_ms = int(period_ms)
        self.listen_s = min(self.LISTEN_MAX_S, max(0.1, listen_periods * self.period_ms / 1000.0))
        self._task = None

    @property
    def cob_id(self):
        return 0x700 + self.node_id

    @property
    def running(self):
        return self._task is not None

    def start(self):
        if not 1 <= self.node_id <= 127:
            raise FftuneError(f"drive.host_node_id {self.node_id}: expected 1 .. 127")
        if not 1 <= self.period_ms <= 0xFFFF // 4:
            raise FftuneError(f"drive.heartbeat_ms {self.period_ms}: the host needs a heartbeat "
                              f"(1 .. {0xFFFF // 4} ms) for a drive it enables")
        seen = []

        def heard(can_id, data, timestamp):
            seen.append(bytes(data))
        self.network.subscribe(self.cob_id, heard)
        try:
            time.sleep(self.listen_s)
        finally:
            self.network.unsubscribe(self.cob_id, heard)
        if seen:
            state = seen[-1][0] if seen[-1] else None
            names = {0x00: "boot-up", 0x04: "STOPPED", 0x05: "OPERATIONAL", 0x7F: "PRE-OPERATIONAL"}
            raise FftuneError(
                f"another node sends heartbeats on COB-ID 0x{self.cob_id:03X} (host node id "
                f"{self.node_id}): {len(seen)} frame(s) in {1000 * self.listen_s:.0f} ms, "
                f"state {names.get(state, state)} (another fftune session or a node with id "
                f"{self.node_id} on this bus?); its heartbeat would keep the drives enabled after "
                f"this host died: set drive.host_node_id to an id free on this bus")
        self._task = self.network.send_periodic(self.cob_id, [0x05], self.period_ms / 1000.0)
        # A send error (the bus went away) ends the heartbeat thread quietly; the next SDO
        # request reports the lost connection as one error line instead of a thread traceback.
        task = getattr(self._task, "_task", None)
        if task is not None and hasattr(task, "on_error"):
            task.on_error = lambda exc: False
        return self

    def stop(self):
        if self._task is not None:
            try:
                self._task.stop()
            finally:
                self._task = None

    def describe(self):
        return f"host node {self.node_id} every {self.period_ms} ms"


class _BusErrorListener:
    """Marks receive errors of the bus (e.g. the socketcand server went away) as handled,
    so that python-can's receive thread does not die with a traceback on the terminal; it
    retries every 50 ms until the client closes, and the next SDO request reports the lost
    connection as one error line."""

    def __call__(self, msg):
        pass

    def on_message_received(self, msg):
        pass

    def on_error(self, exc):
        time.sleep(0.05)

    def stop(self):
        pass


@contextlib.contextmanager
def _signals_deferred(signums=(signal.SIGINT, signal.SIGTERM)):
    """Hold SIGINT / SIGTERM while the block runs (main thread only: elsewhere Python
    delivers no signals anyway), then act on the first one that came, as it would have."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending = []
    saved = {}
    for signum in signums:
        try:
            saved[signum] = signal.signal(signum, lambda sig, frame: pending.append(sig))
        except (ValueError, OSError):
            pass
    try:
        yield
    finally:
        for signum, handler in saved.items():
            signal.signal(signum, handler)
        if pending:
            handler = saved.get(pending[0])
            if callable(handler):
                handler(pending[0], None)
            elif handler == signal.SIG_DFL:
                signal.raise_signal(pending[0])


class Cancelled(BaseException):
    """The session was cancelled from another thread (``DriveClient.cancel`` set: a
    machine's Ctrl-C / SIGTERM): raised at the axis' next SDO request, past every
    ``except FftuneError``, so that its thread ends and the machine leaves every drive safe."""


# python-canopen takes the block upload's sub-block size from a class attribute: the
# retries with smaller sub-blocks change it for every client of the process (several axes).
_BLKSIZE_LOCK = threading.Lock()
_BLKSIZE_DEFAULT = 127


class DriveClient:
    """A connected drive. Use as a context manager, or call :meth:`close`.

    Parameters
    ----------
    opts : BusOptions
        Interface, channel, node id and EDS.
    sdo_timeout_s : float
        Response timeout of one SDO request.
    sdo_retries : int
        Attempts per SDO request (python-canopen's ``MAX_RETRIES``), >= 1: 1 sends each
        request once.
    heartbeat_ms : int
        Producer time of the drive's heartbeat and of the host's; the drive's consumer
        watches the host with 4x this time. 0 switches both off.
    host_node_id : int
        Node id under which the host produces its heartbeat.
    network : canopen.Network, optional
        A network (bus) shared with other drive clients (the axes of a machine): the node
        is added to it; its owner connects it, produces the host heartbeat and
        disconnects it. Default: the client opens its own bus.
    host_heartbeat : HostHeartbeat, optional
        With ``network``: the owner's heartbeat producer (one per bus); the drive is
        enabled only when its consumer is armed for it (same id and period).
    bus_nodes : int
        Drives that may transfer at once on this bus (a machine's axes): the SDO bursts
        are shortened so that the host's heartbeat keeps its period (:func:`sdo_burst_frames`).

    Attributes
    ----------
    time_account : dict
        Accumulated over the session: ``runs`` completed, ``excitation_s`` (their settle +
        recorded periods at fs: the physical minimum), ``run_wait_s`` (wall time from the
        start command to the end of each run), ``transfer_s`` (wall time of every other
        SDO transfer: parameters, read-back, uploads).
    """

    def __init__(self, opts, *, sdo_timeout_s=2.0, sdo_retries=2, heartbeat_ms=100,
                 host_node_id=0x7F, run_timeout_s=120.0, progress=True, network=None,
                 host_heartbeat=None, bus_nodes=1):
        import canopen

        if isinstance(sdo_retries, bool) or not isinstance(sdo_retries, int) or sdo_retries < 1:
            raise ValueError(f"sdo_retries: attempts per SDO request must be an integer >= 1, "
                             f"got {sdo_retries!r}")
        # the one place every command's client passes (--node-id overrides the configuration's
        # node id after its checks): a drive whose node id is the host's heartbeat id would
        # watch a COB-ID its own heartbeat uses (0x700 + id), fed after the host died
        for name, value in (("node id", opts.node_id), ("host node id", host_node_id)):
            if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 127:
                raise FftuneError(f"{name} {value!r}: expected 1 .. 127")
        if opts.node_id == host_node_id:
            raise FftuneError(f"node id {opts.node_id} is the host's heartbeat id (drive.host_node_id "
                              f"= {host_node_id}): the drive's consumer would watch its own "
                              f"heartbeat's COB-ID 0x{0x700 + host_node_id:03X}; give the host "
                              f"another id")
        if isinstance(heartbeat_ms, bool) or not isinstance(heartbeat_ms, int) \
                or not 0 <= heartbeat_ms <= 0xFFFF // 4:
            raise FftuneError(f"heartbeat_ms {heartbeat_ms!r}: expected 0 .. {0xFFFF // 4} ms (the "
                              f"consumer time, 4 x the period, is a 16-bit ms field)")
        self.opts = opts
        self.sdo_timeout_s = sdo_timeout_s
        self.sdo_retries = sdo_retries
        self.heartbeat_ms = heartbeat_ms
        self.host_node_id = host_node_id
        self.run_timeout_s = run_timeout_s
        self.progress = progress
        self._hb_task = None
        self._bootups = 0
        self._last_hb = None
        self._run_active = False      # a run may be going on the drive (started by us)
        self._enabled = False         # we enabled the drive (CiA 402)
        self._transfer_open = False   # an SDO transfer may be half done (interrupted)
        self._waiting_for_run = False
        # Where the session's time goes (fftune.host.pipeline's time budget): see time_account.
        self.time_account = {"runs": 0, "excitation_s": 0.0, "run_wait_s": 0.0, "transfer_s": 0.0}
        self.network = None
        self._shared_network = network
        self._host_hb = host_heartbeat if network is not None else None
        # the bit rate the SDO bursts are measured against: python-can's, else a simulated
        # bus' (drive_sim --bitrate); unknown: not limited
        self.bus_bitrate = opts.bitrate or getattr(opts, "model_bitrate", None)
        self.bus_nodes = bus_nodes
        self.sdo_burst = sdo_burst_frames(self.bus_bitrate, heartbeat_ms, bus_nodes)
        self.cancel = None            # a threading.Event: set, the next SDO request raises Cancelled
        if opts.eds and os.path.exists(opts.eds):     # (a directory, FIFO, device: one line)
            from fftune.host.config import MAX_EDS_BYTES, regular_file
            regular_file(opts.eds, "EDS", MAX_EDS_BYTES)
        try:
            self.node = canopen.BaseNode402(opts.node_id, opts.eds)
        except FileNotFoundError:
            raise FftuneError(f"EDS not found: {opts.eds} (build it with `make firmware`, or pass --eds)") from None
        except Exception as exc:
            raise FftuneError(f"EDS {opts.eds}: cannot import: {exc}") from None
        check_drive_profile(self.node.object_dictionary, opts.eds)

    # ---- connection -------------------------------------------------------------------
    def connect(self):
        import canopen

        if self._shared_network is not None:
            self.network = self._shared_network
            self.network.add_node(self.node)
        else:
            bus = _open_bus(self.opts)
            self.network = canopen.Network(bus)
            self.network.add_node(self.node)
            self.network.connect()
            self.network.notifier.add_listener(_BusErrorListener())
            if self.sdo_burst < SDO_BLKSIZE_MAX:
                _SdoPacer(self.network, self.bus_bitrate, self.sdo_burst)
        self.node.sdo.RESPONSE_TIMEOUT = self.sdo_timeout_s
        self.node.sdo.MAX_RETRIES = self.sdo_retries
        self.node.nmt.add_heartbeat_callback(self._on_heartbeat)
        self._probe()
        self._start_heartbeats()
        return self

    def _on_heartbeat(self, state):
        self._last_hb = time.monotonic()
        if state == 0:
            self._bootups += 1

    def _probe(self):
        """First contact: one short SDO read of the device type, a named error if silent."""
        from canopen.sdo.exceptions import SdoCommunicationError

        sdo = self.node.sdo
        saved = sdo.RESPONSE_TIMEOUT, sdo.MAX_RETRIES
        sdo.RESPONSE_TIMEOUT, sdo.MAX_RETRIES = min(0.5, self.sdo_timeout_s), 2
        try:
            sdo.upload(0x1000, 0)
        except SdoCommunicationError:
            seen = self._scan_nodes()
            hint = (f"; nodes answering on this bus: {', '.join(map(str, seen))}" if seen
                    else "; no node answered on this bus")
            self.close()
            raise FftuneError(f"no SDO answer from node {self.opts.node_id} on {self.opts.describe()}"
                              f" (wrong node id?){hint}") from None
        finally:
            sdo.RESPONSE_TIMEOUT, sdo.MAX_RETRIES = saved

    def _scan_nodes(self, wait_s=0.3):
        """Node ids that answer an SDO read of 0x1000 (python-canopen's NodeScanner)."""
        try:
            scanner = self.network.scanner
            scanner.reset()
            scanner.search(limit=127)
            time.sleep(wait_s)
            return sorted(set(scanner.nodes))
        except Exception:
            return []

    def _consumer_value(self):
        """0x1016:1 for this host's heartbeat: host id << 16 | 4 x the period in ms."""
        return (self.host_node_id << 16) | min(0xFFFF, 4 * self.heartbeat_ms)

    def _start_heartbeats(self):
        if not self.heartbeat_ms:
            return
        # Host heartbeat (state 0x05 operational) on 0x700 + host id, after listening for
        # another producer on it (on a shared network: its owner's, one for all nodes).
        if self._shared_network is None:
            try:
                self._host_hb = HostHeartbeat(self.network, self.host_node_id, self.heartbeat_ms).start()
            except FftuneError:
                self.close()
                raise
            self._hb_task = self._host_hb
        self.write(0x1017, 0, self.heartbeat_ms)
        self.write(0x1016, 1, self._consumer_value())

    def _check_watchdog(self):
        """The rule before the power stage goes on: the drive's consumer (0x1016:1, read
        back) is armed for the heartbeat this host sends (same node id, 4 x its period), and
        that heartbeat is running. Else one FftuneError line; nothing is enabled."""
        where = f"node {self.opts.node_id} not enabled"
        if not self.heartbeat_ms:
            raise FftuneError(f"{where}: drive.heartbeat_ms is 0 (no host heartbeat): a drive that "
                              f"moves needs its consumer (0x1016) armed for the host's heartbeat, "
                              f"1 .. {0xFFFF // 4} ms")
        hb = self._host_hb
        if hb is None or not hb.running:
            raise FftuneError(f"{where}: this host sends no heartbeat on its bus")
        if (hb.node_id, hb.period_ms) != (self.host_node_id, self.heartbeat_ms):
            raise FftuneError(f"{where}: its consumer would watch host node {self.host_node_id} every "
                              f"{self.heartbeat_ms} ms, this host sends {hb.describe()}")
        armed = int(self.read(0x1016, 1))
        if armed != self._consumer_value():
            raise FftuneError(f"{where}: its heartbeat consumer 0x1016:1 reads 0x{armed:08X}, "
                              f"not 0x{self._consumer_value():08X} ({hb.describe()}, 4 x the period)")

    def close(self):
        """Leave the drive safe, then disconnect: abort a transfer the host may have left
        half done, stop a run, disable the drive (CiA 402 shutdown: power stage off), stop
        the host heartbeat. The drive's heartbeat consumer (0x1016) stays armed, so a host
        that dies without reaching this point still stops the drive within the consumer
        time. Ctrl-C / SIGTERM arriving meanwhile are held until the cleanup is done (it is
        bounded: at most three short SDO requests)."""
        if self.network is None:
            return
        with _signals_deferred():
            try:
                self._leave_safe()
            except Exception:
                pass  # the bus is gone: the armed consumer stops the drive
            try:
                if self._hb_task is not None:
                    self._hb_task.stop()
                    self._hb_task = None
                if self._shared_network is None:
                    self.network.disconnect()
            except Exception:
                pass
            self.network = None

    def _leave_safe(self):
        """Stop a run and disable the drive, each step tried even if another fails."""
        if not (self._run_active or self._enabled):
            return
        sdo = self.node.sdo
        sdo.RESPONSE_TIMEOUT = min(0.3, self.sdo_timeout_s)
        sdo.MAX_RETRIES = 1
        steps = []
        if self._transfer_open:
            steps.append(lambda: sdo.abort(0x08000000))  # general error: reset the server's transfer
        cmd = PARAMS["run_command"]
        steps.append(lambda: sdo.download(cmd.index, cmd.subindex, struct.pack("<B", 2)))  # stop
        if self._enabled and 0x6040 in self.node.object_dictionary:
            steps.append(lambda: sdo.download(0x6040, 0, struct.pack("<H", 0x0006)))  # shutdown
        for step in steps:
            try:
                step()
            except Exception as exc:
                logger.debug("cleanup step failed: %s", exc)
        self._run_active = self._enabled = self._transfer_open = False

    def __enter__(self):
        if self.network is None:
            self.connect()
        return self

    def __exit__(self, *exc):
        self.close()

    # ---- SDO access -------------------------------------------------------------------
    def _describe_obj(self, index, sub):
        try:
            obj = self.node.object_dictionary[index]
            name = obj.name
            if sub or hasattr(obj, "subindices"):
                name = f"{name}.{obj[sub].name}"
        except KeyError:
            name = "?"
        return f"0x{index:04X}:{sub:02X} '{name}'"

    def _sdo_call(self, what, index, sub, fn):
        import can
        from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

        if self.cancel is not None and self.cancel.is_set():
            raise Cancelled()
        self._transfer_open = True
        t0 = time.monotonic()
        try:
            result = fn()
            self._transfer_open = False
            return result
        except SdoAbortedError as exc:
            raise FftuneError(f"{what} {self._describe_obj(index, sub)} on node {self.opts.node_id}: "
                              f"{sdo_abort_text(exc)}") from None
        except SdoCommunicationError as exc:
            raise FftuneError(f"{what} {self._describe_obj(index, sub)} on node {self.opts.node_id}: "
                              f"{exc} after {self.node.sdo.MAX_RETRIES} attempt(s) of "
                              f"{self.node.sdo.RESPONSE_TIMEOUT:g} s ({self.opts.describe()})") from None
        except (ValueError, TypeError, KeyError) as exc:
            raise FftuneError(f"{what} {self._describe_obj(index, sub)}: {exc}") from None
        except (OSError, can.CanError) as exc:
            # the bus itself failed (e.g. the socketcand server, the drive, went away)
            raise FftuneError(f"{what} {self._describe_obj(index, sub)} on node {self.opts.node_id}: "
                              f"connection lost ({type(exc).__name__}: {exc}) on {self.opts.describe()}") from None
        finally:
            if not self._waiting_for_run:  # (polls during a run overlap the excitation)
                self.time_account["transfer_s"] += time.monotonic() - t0

    def _var(self, index, sub):
        obj = self.node.sdo[index]
        return obj[sub] if hasattr(obj, "__getitem__") and sub is not None and \
            not hasattr(obj, "raw") else obj

    def resolve(self, name):
        """(index, sub-index) for an alias (``kfc``), an EDS name
        (``Controller.Coulomb feed-forward K_fc``) or ``0x2000:4``."""
        if name in PARAMS:
            e = PARAMS[name]
            return e.index, e.subindex
        if isinstance(name, str) and name.lower().startswith("0x"):
            idx, _, sub = name.partition(":")
            return int(idx, 16), int(sub, 0) if sub else 0
        od = self.node.object_dictionary
        rec, _, sub = name.partition(".")
        try:
            obj = od[rec]
            if sub:
                var = obj[sub]
                return obj.index, var.subindex
            return obj.index, 0
        except KeyError:
            raise FftuneError(f"no object named '{name}' in the EDS {self.opts.eds}") from None

    def read(self, index, sub=0):
        var = self._var(index, sub)
        return self._sdo_call("reading", index, sub, lambda: var.raw)

    def write(self, index, sub, value):
        var = self._var(index, sub)

        def do():
            var.raw = value
        self._sdo_call(f"writing {value!r} to", index, sub, do)

    def get(self, name):
        """A parameter's value by alias or EDS name."""
        return self.read(*self.resolve(name))

    def set(self, name, value):
        """Write a parameter by alias or EDS name (SDO; the drive range-checks it)."""
        index, sub = self.resolve(name)
        self.write(index, sub, value)

    def set_parameters(self, values):
        for name, value in values.items():
            self.set(name, value)

    def read_parameters(self):
        """Every manufacturer parameter the EDS has, by alias (the run's metadata)."""
        out = {}
        for alias, e in PARAMS.items():
            if alias.startswith(("sim_", "meas_")) or e.access == "wo":
                continue
            try:
                self.node.object_dictionary[e.index][e.subindex] if e.subindex else \
                    self.node.object_dictionary[e.index]
            except KeyError:
                continue
            out[alias] = self.read(e.index, e.subindex)
        return out

    def identity(self):
        """Identity object 0x1018, firmware 0x100A and device name 0x1008."""
        ident = {}
        for key, (index, sub) in {"vendor_id": (0x1018, 1), "product_code": (0x1018, 2),
                                  "revision": (0x1018, 3), "serial": (0x1018, 4)}.items():
            ident[key] = int(self.read(index, sub))
        ident["firmware_version"] = str(self.read(0x100A, 0))
        ident["device_name"] = str(self.read(0x1008, 0))
        ident["node_id"] = self.opts.node_id
        ident["bus"] = self.opts.describe()
        return ident

    def plant_truth(self):
        """The simulated plant's true friction (0x2100, simulation build only), or None."""
        if 0x2100 not in self.node.object_dictionary:
            return None
        out = {}
        for alias in ("sim_fc_volt", "sim_fv_volt", "sim_fs_volt", "sim_noise_std", "sim_fc_torque"):
            if alias in PARAMS:
                out[alias] = float(self.get(alias))
        return out

    # ---- state machines ---------------------------------------------------------------
    def enable(self):
        """NMT OPERATIONAL and CiA 402 OPERATION ENABLED in the excitation-run mode."""
        node = self.node
        self._check_watchdog()
        self._enabled = True  # from the first attempt on: close() disables again
        self._arm_abort_connection()
        # python-canopen waits 0.2 .. 0.8 s for each statusword TPDO of the state machine; a
        # loaded host machine or a slow bus misses that now and then (issue 21 item 7). A
        # drive that answers in time costs nothing more; the longer bound only waits longer.
        for name, at_least_s in (("TIMEOUT_SWITCH_STATE_FINAL", 8.0), ("TIMEOUT_SWITCH_STATE_SINGLE", 4.0),
                                 ("TIMEOUT_CHECK_TPDO", 2.0), ("TIMEOUT_SWITCH_OP_MODE", 5.0),
                                 ("TIMEOUT_RESET_FAULT", 4.0)):
            if hasattr(node, name):
                setattr(node, name, max(float(getattr(node, name)), at_least_s))
        try:
            node.nmt.state = "PRE-OPERATIONAL"
            node.setup_402_state_machine(read_pdos=True)
            node.nmt.state = "OPERATIONAL"
            time.sleep(0.05)
            if 0x6060 in node.object_dictionary:
                self.write(0x6060, 0, -1)
            if node.state != "OPERATION ENABLED":
                node.state = "OPERATION ENABLED"
        except FftuneError:
            raise
        except Exception as exc:
            from canopen.sdo.exceptions import SdoAbortedError
            if isinstance(exc, SdoAbortedError):
                raise FftuneError(f"enabling node {self.opts.node_id}: {sdo_abort_text(exc)}") from None
            raise FftuneError(f"enabling node {self.opts.node_id} (CiA 402 OPERATION ENABLED): "
                              f"{type(exc).__name__}: {exc}") from None

    def _arm_abort_connection(self):
        """Before the power stage goes on: the drive's reaction to a lost host (CiA 402
        0x6007, acted on when the host heartbeat in 0x1016 is missing or NMT ends the
        connection). A drive set to 0 (no action) would stay enabled after the host died: it
        is set to 2 (disable voltage); 1 (fault) and 3 (quick stop) are the integrator's
        choice for the axis and are kept. Drives without 0x6007 are left as they are."""
        if ABORT_CONNECTION_INDEX not in self.node.object_dictionary:
            return
        code = int(self.read(ABORT_CONNECTION_INDEX, 0))
        if code not in (1, 2, 3):
            logger.info("node %d: abort connection option code 0x6007 was %d; set to %d (disable "
                        "voltage when the host is lost)", self.opts.node_id, code,
                        ABORT_CONNECTION_DEFAULT)
            self.write(ABORT_CONNECTION_INDEX, 0, ABORT_CONNECTION_DEFAULT)

    def _ensure_enabled(self):
        """Before a run: the drive may have left OPERATION ENABLED since :meth:`enable`
        by its own reaction to a lost host (0x6007): its heartbeat consumer missed the host
        for longer than the consumer time (this process stalled, e.g. on a loaded machine).
        The host is alive and in charge: enable again, saying so, instead of a run start
        refused for the device state."""
        if not self._enabled or 0x6041 not in self.node.object_dictionary:
            return
        status = int(self.read(0x6041, 0))
        if status & 0x006F == 0x0027:  # OPERATION ENABLED
            return
        logger.warning("node %d left OPERATION ENABLED (statusword 0x%04X: its reaction to a missed "
                       "host heartbeat, 0x6007); enabling it again", self.opts.node_id, status)
        self.enable()

    # ---- runs -------------------------------------------------------------------------
    def run(self, parameters, signals=("reference", "plant_input", "motor_angle", "error"),
            desc="run", capture="raw", stats=None, lines=None):
        """Set ``parameters``, start a run, wait for it, upload and check the recording
        and/or the drive's line statistics.

        Parameters
        ----------
        parameters : dict
            Alias (or EDS name) -> value, written before the start in this order.
        signals : sequence of str
            Recorder signals (``fftune.host.odmap.SIGNAL_BITS``).
        desc : str
            Progress bar label.
        capture : {'raw', 'stats', 'both'}
            Upload the recording, the statistics (object 0x2041, one small upload; nothing
            is recorded), or both.
        stats : dict, optional
            With ``capture`` 'stats' or 'both': ``{"harmonics": K, "signals": [names],
            "power": [names]}`` (:func:`stats_parameters`).
        lines : array_like of int, optional
            With ``capture`` 'stats' or 'both' (multisine runs): the DFT bins of the
            drive's line statistics (object 0x2042; read back as 0x2043). The drive
            computes them from its recorder, which then holds r, u and y; only the
            statistics cross the bus with 'stats'.

        Returns
        -------
        RunRecord
            ``signals`` empty with ``capture='stats'``; ``stats`` (harmonic statistics)
            or ``line_stats`` (with ``lines``) set unless 'raw'.
        """
        from tqdm import tqdm

        if capture not in CAPTURE_MODES:
            raise FftuneError(f"capture mode {capture!r}: expected one of {', '.join(CAPTURE_MODES)}")
        want_lines = lines is not None and capture != "raw"
        mask = 0
        if capture != "stats":
            for name in signals:
                mask |= 1 << SIGNAL_BITS[name]
        wanted = {n for n, b in SIGNAL_BITS.items() if mask >> b & 1}
        if want_lines:
            # the drive transforms the recorded periods of r, u and y in its background
            mask |= sum(1 << SIGNAL_BITS[s] for s in ("reference", "plant_input", "motor_angle"))
        # what the recorder holds, in bit order (with 'both' and lines perhaps more than asked)
        order = [n for n, b in sorted(SIGNAL_BITS.items(), key=lambda kv: kv[1]) if mask >> b & 1]
        self.set_parameters(dict(parameters, rec_signals=mask))
        self._set_stats(stats if capture != "raw" else None)
        self._set_lines(lines if want_lines else None, parameters)
        counter0 = int(self.get("run_counter"))
        boots0 = self._bootups
        t_start = time.time()
        self._ensure_enabled()
        self._run_active = True  # (also if the start's answer is lost): close() stops it
        self._start_run(stats if capture != "raw" and not want_lines else None,
                        lines if want_lines else None, parameters)
        t_wait = time.monotonic()
        self._waiting_for_run = True
        total = int(self.get("run_total"))
        deadline = time.monotonic() + self.run_timeout_s
        bar = tqdm(total=total, desc=desc, unit="sample", unit_scale=True, leave=False,
                   disable=None if self.progress else True, dynamic_ncols=True)  # None: off when not a terminal
        try:
            while True:
                state = int(self.get("run_state"))
                progress = int(self.get("run_progress"))
                bar.update(max(0, min(progress, total) - bar.n))
                if self._bootups != boots0:
                    raise FftuneError(f"node {self.opts.node_id} rebooted during the run (boot-up seen)")
                if state == 3 and int(self.get("run_counter")) != counter0:
                    self._run_active = False
                    break
                if state in (4, 5):
                    self._run_active = False
                    reason = int(self.get("run_last_error"))
                    raise FftuneError(f"run stopped by the drive: state {RUN_STATES[state]}, reason "
                                      f"{reason} ({STOP_REASONS.get(reason, 'unknown')})")
                if time.monotonic() > deadline:
                    self.set("run_command", 2)
                    raise FftuneError(f"run did not finish within {self.run_timeout_s:g} s "
                                      f"(progress {progress}/{total} samples); aborted it")
                self._check_heartbeat()
                time.sleep(0.02)
        finally:
            bar.close()
            self._waiting_for_run = False
            self.time_account["run_wait_s"] += time.monotonic() - t_wait
        t_end = time.time()
        params = self.read_parameters()
        if self._bootups != boots0:
            raise FftuneError(f"node {self.opts.node_id} rebooted during the run (boot-up seen); "
                              "its recording is lost")
        n = int(params["exc_period"])
        rec_periods = int(params["exc_record_periods"])
        run_stats = self.upload_stats() if capture != "raw" and not want_lines else None
        run_lines = self.upload_line_stats() if want_lines else None
        if run_lines is not None and "stat_line_saturated" in PARAMS:
            run_lines.saturated_samples = int(self.get("stat_line_saturated"))
        data = self.upload_recording() if capture != "stats" else b""
        if self._bootups != boots0:
            raise FftuneError(f"node {self.opts.node_id} rebooted during the run (boot-up seen); "
                              "its recording is lost")
        expected_samples = rec_periods * n
        nsig = len(order)
        if capture != "stats" and len(data) != expected_samples * nsig * 4:
            raise FftuneError(f"recording from node {self.opts.node_id}: {len(data)} bytes, expected "
                              f"{expected_samples} samples x {nsig} signals x 4 bytes = "
                              f"{expected_samples * nsig * 4}")
        self.time_account["runs"] += 1
        self.time_account["excitation_s"] += (int(params["exc_settle_periods"]) + rec_periods) * n / float(params["fs"])
        sig = {}
        if capture != "stats":
            arr = np.frombuffer(data, dtype="<f4").reshape(expected_samples, nsig)
            sig = {name: arr[:, i].astype(np.float64) for i, name in enumerate(order) if name in wanted}
        for what, got in (("statistics", run_stats), ("line statistics", run_lines)):
            if got is not None and got.periods != rec_periods:
                raise FftuneError(f"{what} from node {self.opts.node_id}: {got.periods} periods "
                                  f"accumulated, the run recorded {rec_periods}")
        if run_lines is not None and not np.array_equal(run_lines.bins, np.asarray(lines, dtype=np.int64)):
            raise FftuneError(f"line statistics from node {self.opts.node_id}: {run_lines.bins.size} "
                              f"lines, not the {len(lines)} lines written to 0x2042")
        return RunRecord(signals=sig, parameters=params, fs_hz=float(params["fs"]),
                         period_samples=n, settle_periods=int(params["exc_settle_periods"]),
                         record_periods=rec_periods, run_counter=int(self.get("run_counter")),
                         t_start=t_start, t_end=t_end, stats=run_stats, line_stats=run_lines)

    # ---- on-drive statistics (object 0x2040 / 0x2041, firmware_sim/core/stat.h) ----------
    def _set_stats(self, stats):
        """Write the statistics configuration (all off for None); a value beyond what the
        drive holds comes back as its SDO abort, with the limit named."""
        if "stat_harmonics" not in PARAMS or 0x2040 not in self.node.object_dictionary:
            if stats is None:
                return
            raise FftuneError(f"node {self.opts.node_id}: its EDS has no statistics object 0x2040 "
                              f"(capture: stats needs firmware with on-drive statistics)")
        values = stats_parameters(stats) if stats is not None else \
            {"stat_harmonics": 0, "stat_signals": 0, "stat_power": 0}
        limits = {"stat_harmonics": f"the drive holds at most {STAT_K_MAX} harmonics",
                  "stat_signals": f"the drive holds harmonic statistics of at most {STAT_SIG_MAX} signals",
                  "stat_power": "signal bits 0 .. 4"}
        for name, value in values.items():
            try:
                self.set(name, value)
            except FftuneError as exc:
                raise FftuneError(f"statistics: {exc} ({limits[name]})") from None

    def _set_lines(self, lines, parameters):
        """Write the line list 0x2042 and turn the line statistics on (off for None). The
        drive checks the list against its period and capacity; its SDO abort comes back
        as one error line naming the limit."""
        from canopen.sdo.exceptions import SdoAbortedError

        if "stat_line_mode" not in PARAMS or 0x2042 not in self.node.object_dictionary:
            if lines is None:
                return
            raise FftuneError(f"node {self.opts.node_id}: its EDS has no line statistics objects "
                              f"0x2042/0x2043 (capture: stats of a multisine run needs firmware "
                              f"with on-drive line statistics)")
        if lines is None:
            if "stat_line_mode" not in parameters:   # (a caller's own setting stays)
                self.set("stat_line_mode", 0)
            return
        bins = np.asarray(lines, dtype=np.int64).reshape(-1)
        if bins.size == 0 or bins.min() < 0 or bins.max() > 0xFFFF:
            raise FftuneError(f"line statistics: {bins.size} lines, bins must be 1 .. 65535")
        raw = bins.astype("<u2").tobytes()
        n = int(parameters.get("exc_period", 0)) or int(self.get("exc_period"))

        aborted = []

        def do():
            try:
                if len(raw) <= 4:       # expedited: one frame
                    self.node.sdo.download(0x2042, 0, raw)
                    return
                # block download: the frames of a sub-block go without an answer each
                with self.node.sdo[0x2042].open("wb", size=len(raw), block_transfer=True) as fh:
                    fh.write(raw)
            except SdoAbortedError as exc:
                aborted.append(exc)
                raise
        try:
            self._sdo_call("download of", 0x2042, 0, do)
        except FftuneError:
            if not aborted:
                raise
            exc = aborted[0]
            text = sdo_abort_text(exc)
            if exc.code == 0x06070012:
                cap = int(self.get("stat_lines_cap"))
                raise FftuneError(f"line statistics: {bins.size} lines (bins {bins[0]} .. {bins[-1]}), "
                                  f"the drive holds at most {cap} (object 0x2040:9 Lines capacity): "
                                  f"{text}; use capture: raw for this step, or fewer lines (a "
                                  f"narrower band or a shorter period)") from None
            if exc.code == 0x06090030:
                bad = bins[(bins < 1) | (2 * bins >= n)]
                where = f"line {bad[0]} is at or above" if bad.size else "a line is not below"
                raise FftuneError(f"line statistics: {where} N/2 = {n // 2} (fs/2) of the period "
                                  f"N = {n}, or the bins are not strictly ascending from 1: "
                                  f"{text}") from None
            raise
        self.set("stat_line_mode", 1)

    def upload_line_stats(self):
        """The drive's line statistics of the last run (0x2043) as
        :class:`fftune.analysis.stats.LineStats`."""
        from fftune.analysis.stats import parse_line_stats

        # 8 + 44 bytes a line: kilobytes, a block upload (one answer per sub-block instead
        # of one per 7 bytes; 12 x 7 kB took 15 s of a real-time 1 Mbit/s bus segmented)
        data = self._block_upload(0x2043, 0)
        try:
            return parse_line_stats(data)
        except FftuneError as exc:
            raise FftuneError(f"line statistics from node {self.opts.node_id}: {exc}") from None

    def _start_run(self, stats, lines, parameters):
        """Run command 1; a refusal for the statistics names the limit (last stop reason)."""
        try:
            self.set("run_command", 1)
        except FftuneError as exc:
            if (stats is None and lines is None) or "stat_harmonics" not in PARAMS:
                raise
            reason = int(self.get("run_last_error"))
            n = int(parameters.get("exc_period", 0))
            if reason == 9 and stats is not None:
                k, c = int(stats["harmonics"]), int(parameters.get("exc_sine_cycles", 0))
                raise FftuneError(f"statistics: harmonic K = {k} of the sine at bin {c} is line {k * c}, "
                                  f"at or above N/2 = {n / 2:g} (fs/2), the highest line the drive "
                                  f"can accumulate: {exc}") from None
            if reason == 10 and stats is not None:
                raise FftuneError(f"statistics: harmonic statistics need a sine run (exc_kind 1): "
                                  f"{exc}") from None
            if reason == 11 and lines is not None:
                raise FftuneError(f"line statistics: the drive refused the run (stop reason 11: "
                                  f"{STOP_REASONS[11]}): each line below N/2 = {n // 2}, N a power "
                                  f"of two >= 8 within the table capacity, the recorder holding r, "
                                  f"u, y: {exc}") from None
            raise

    def upload_stats(self):
        """The drive's statistics of the last run (0x2041, a few hundred bytes at most) as
        :class:`fftune.analysis.stats.HarmonicStats`."""
        from fftune.analysis.stats import parse_stats

        index, sub = 0x2041, 0

        def do():
            return self.node.sdo.upload(index, sub)
        data = self._sdo_call("upload of", index, sub, do)
        try:
            return parse_stats(data)
        except FftuneError as exc:
            raise FftuneError(f"statistics from node {self.opts.node_id}: {exc}") from None

    def _check_heartbeat(self):
        if not self.heartbeat_ms or self._last_hb is None:
            return
        silent = time.monotonic() - self._last_hb
        if silent > max(1.0, 10 * self.heartbeat_ms / 1000.0):
            raise FftuneError(f"heartbeat of node {self.opts.node_id} lost ({silent:.1f} s silent) on "
                              f"{self.opts.describe()}")

    def load_waveform(self, samples):
        """Download one period (float32 little-endian, at most 8192 samples) into the
        waveform table 0x2002 by SDO block download; returns the drive's table length.

        Runs with ``exc_kind = 2`` play it cyclically, scaled by ``exc_amplitude``.
        """
        data = np.asarray(samples, dtype="<f4")
        if data.ndim != 1 or not 4 <= data.size <= 8192 or not np.isfinite(data).all():
            raise FftuneError(f"waveform table: need 4 .. 8192 finite samples, got shape {data.shape}")
        raw = data.tobytes()

        def do():
            with self.node.sdo[0x2002].open("wb", size=len(raw), block_transfer=True) as fh:
                fh.write(raw)
        self._sdo_call("block download of", 0x2002, 0, do)
        length = int(self.get("table_length"))
        if length != data.size:
            raise FftuneError(f"waveform table: the drive reports {length} samples after writing {data.size}")
        return length

    def upload_recording(self, block_sizes=(127, 32, 8)):
        """The recorder data (0x2021) by SDO block upload (CRC checked by python-canopen).

        A failed transfer (timeout, lost segments: a slow receiver on a bus without flow
        control drops frames of a long sub-block) is repeated with smaller sub-blocks; the
        recording stays on the drive until the next run starts.
        """
        return self._block_upload(0x2021, 0, block_sizes)

    def _block_upload(self, index, sub, block_sizes=(127, 32, 8)):
        """A DOMAIN by SDO block upload (:meth:`upload_recording`): 7 bytes a frame with one
        acknowledgement per sub-block, where a segmented upload waits for the drive's
        answer to every 7 bytes."""
        from canopen.sdo.client import BlockUploadStream

        def do():
            from canopen.sdo.exceptions import SdoCommunicationError
            try:
                with self.node.sdo[index].open("rb", block_transfer=True) as fh:
                    return fh.read()
            except AttributeError as exc:
                # python-canopen 2.x: a lost end-of-upload frame makes
                # BlockUploadStream._end_upload call self.abort, which does not exist; do
                # what it meant (abort the transfer, report the timeout)
                if "abort" not in str(exc):
                    raise
                self.node.sdo.abort(0x05040000)
                raise SdoCommunicationError("No SDO response received (end of the block upload)") from None

        # sub-blocks short enough that the host's heartbeat keeps its period (sdo_burst_frames)
        block_sizes = sorted({min(int(b), self.sdo_burst) for b in block_sizes}, reverse=True)
        for i, size in enumerate(block_sizes):
            # python-canopen takes the sub-block size from a class attribute: changed only
            # under the lock (other axes of the process upload meanwhile), then restored
            lock = _BLKSIZE_LOCK if size != _BLKSIZE_DEFAULT else contextlib.nullcontext()
            with lock:
                if size != _BLKSIZE_DEFAULT:
                    BlockUploadStream.blksize = size
                try:
                    return self._sdo_call(f"block upload (sub-blocks of {size}) of", index, sub, do)
                except FftuneError:
                    if i == len(block_sizes) - 1:
                        raise
                finally:
                    BlockUploadStream.blksize = _BLKSIZE_DEFAULT
            time.sleep(0.2)
