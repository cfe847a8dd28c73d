"""Shared pytest fixtures: the simulated drive (firmware_sim's ``drive_sim``) as a CANopen node.

``drive_sim`` starts ``firmware_sim/build/drive_sim`` as a subprocess (a fresh node per
test) and yields a :class:`DriveSim` with the connection facts. The transport is chosen
by the environment variable ``FFTUNE_TEST_CAN``:

- ``socketcand`` (default): drive_sim serves socketcand on a free loopback port; clients
  connect with python-can's ``socketcand`` interface;
- ``socketcan:IFNAME`` (e.g. ``socketcan:vcan0`` inside the qemu guest): drive_sim and the
  clients use that SocketCAN interface.
"""
import logging
import os
import re
import select
import subprocess
import time
from dataclasses import dataclass, field

import pytest

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), os.pardir))
DRIVE_SIM_BIN = os.environ.get("FFTUNE_DRIVE_SIM") or os.path.join(REPO, "firmware_sim", "build", "drive_sim")  # e.g. build/asan/drive_sim
DRIVE_SIM_EDS = os.path.join(REPO, "firmware_sim", "build", "gen", "fftune_drive.eds")
PLANT_TWOMASS = os.path.join(REPO, "configs", "plant_twomass.yaml")

# python-can's socketcand client logs a warning on every partial TCP read.
logging.getLogger("can.interfaces.socketcand").setLevel(logging.ERROR)

_LISTEN = re.compile(r"drive_sim: listening on (socketcand (\S+):(\d+)|socketcan (\S+)), node (\d+)")


def can_transport():
    """('socketcand', None) or ('socketcan', IFNAME) from FFTUNE_TEST_CAN."""
    spec = os.environ.get("FFTUNE_TEST_CAN", "socketcand").strip()
    if spec == "socketcand":
        return "socketcand", None
    if spec.startswith("socketcan:") and len(spec) > len("socketcan:"):
        return "socketcan", spec.split(":", 1)[1]
    raise pytest.UsageError(f"FFTUNE_TEST_CAN={spec!r}: expected 'socketcand' or 'socketcan:IFNAME'")


@dataclass
class DriveSim:
    """A running drive_sim and how to reach its bus."""
    proc: subprocess.Popen
    transport: str            # 'socketcand' or 'socketcan'
    node_id: int
    eds: str
    host: str = None
    port: int = None
    channel: str = "can0"
    stderr_path: str = None
    extra: dict = field(default_factory=dict)

    def bus_kwargs(self):
        """Keyword arguments for ``can.Bus(...)`` / ``canopen.Network.connect(...)``."""
        if self.transport == "socketcand":
            return dict(interface="socketcand", channel="can0", host=self.host, port=self.port)
        return dict(interface="socketcan", channel=self.channel)

    def network(self):
        """A connected ``canopen.Network`` (disconnect it when done)."""
        import canopen
        net = canopen.Network()
        # the notifier thread blocks this long in recv(): it bounds disconnect()'s wait
        net.NOTIFIER_CYCLE = 0.1
        net.connect(**self.bus_kwargs())
        if self.transport == "socketcan":
            enlarge_receive_buffer(net.bus)
        return net

    def stderr_text(self):
        with open(self.stderr_path, encoding="utf-8", errors="replace") as f:
            return f.read()


def enlarge_receive_buffer(bus, size=4 << 20):
    """A SocketCAN client on vcan: the bus has no bit rate, an SDO block of 127 frames
    arrives at once; the default socket buffer can overflow while Python is descheduled."""
    import socket
    try:
        bus.socket.setsockopt(socket.SOL_SOCKET, 33, size)       # SO_RCVBUFFORCE (root)
    except OSError:
        bus.socket.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size)


def drive_sim_missing_reason():
    if not os.path.exists(DRIVE_SIM_BIN):
        return f"{DRIVE_SIM_BIN} not built (run `make setup`; needs firmware_sim core + plant)"
    if not os.path.exists(DRIVE_SIM_EDS):
        return f"{DRIVE_SIM_EDS} not generated (run `make setup`)"
    return None


def start_drive_sim(tmp_path, node_id=1, extra_args=(), timeout_s=10.0):
    """Start drive_sim on the selected transport and wait for its 'listening' line."""
    reason = drive_sim_missing_reason()
    if reason:
        pytest.skip(reason)
    transport, ifname = can_transport()
    bus = f"socketcand:127.0.0.1:0" if transport == "socketcand" else f"socketcan:{ifname}"
    cmd = [DRIVE_SIM_BIN, "--can", bus, "--node-id", str(node_id), "--config", PLANT_TWOMASS,
           *extra_args]
    err_path = os.path.join(str(tmp_path), f"drive_sim_{node_id}.stderr")
    err = open(err_path, "w")
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, text=True, bufsize=1)
    err.close()
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"drive_sim exited ({proc.returncode}) before listening: "
                               f"{open(err_path).read().strip()}")
        ready, _, _ = select.select([proc.stdout], [], [], 0.1)
        if not ready:
            continue
        m = _LISTEN.search(proc.stdout.readline())
        if m:
            if transport == "socketcand":
                return DriveSim(proc, transport, int(m.group(5)), DRIVE_SIM_EDS, host=m.group(2),
                                port=int(m.group(3)), stderr_path=err_path)
            return DriveSim(proc, transport, int(m.group(5)), DRIVE_SIM_EDS, channel=m.group(4),
                            stderr_path=err_path)
    proc.kill()
    proc.wait()
    raise RuntimeError("drive_sim printed no 'listening' line within %g s" % timeout_s)


def stop_drive_sim(sim):
    if sim.proc.poll() is None:
        sim.proc.terminate()
        try:
            sim.proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            sim.proc.kill()
            sim.proc.wait()
    sim.proc.stdout.close()


@pytest.fixture
def drive_sim(tmp_path, request):
    """A fresh drive_sim (node 1, plant_twomass) on the transport FFTUNE_TEST_CAN selects.

    ``@pytest.mark.drive_sim_args("--realtime")`` adds command-line options: tests that
    need a run still active seconds later use real-time stepping, because in free-run a
    "long" run ends in well under a second on an idle machine.
    """
    marker = request.node.get_closest_marker("drive_sim_args")
    sim = start_drive_sim(tmp_path, extra_args=marker.args if marker else ())
    yield sim
    stop_drive_sim(sim)


@pytest.fixture
def co_node(drive_sim):
    """(network, node): python-canopen RemoteNode for drive_sim with the generated EDS."""
    from canopen_helpers import attach_node
    net, node = attach_node(drive_sim)
    yield net, node
    net.disconnect()


# --------------------------------------------------------------------------- test run layout
# `make test` runs pytest-xdist workers with --dist loadgroup (tests/README is the Makefile):
# tests that share something that is not per-test go into one xdist group, so one worker
# runs them in order:
# - "qemu_guest": every `vm`-marked test; their guest sections run in ONE boot
#   (vm_session below), and that worker starts them first: they are the longest pole.
# - "firmware_build": tests that run make in firmware_sim/ (core-cross, pil, pil-test:
#   fixed output files there, which two workers must not write at once).
# - "<module>:<fixtures>": tests sharing module-scoped fixtures of their module.
# Without xdist the markers do nothing and the order is the same.
_GROUP_OF_MODULE = dict.fromkeys(("test_firmware_cross", "test_mcu_build", "test_mcu_pil"),
                                 "firmware_build")


def _module_name(item):
    return item.module.__name__.rsplit(".", 1)[-1] if getattr(item, "module", None) else ""


def _module_fixture_group(item):
    """Tests that use the same module-scoped fixtures of their own module (a drive_sim
    session, a tuned pipeline, a built wheel: seconds to minutes each) form one group, so
    the fixture is made once, not once per worker; other tests are scheduled one by one."""
    info = getattr(item, "_fixtureinfo", None)
    if info is None:
        return None
    path = item.nodeid.split("::", 1)[0]
    names = sorted(name for name, defs in info.name2fixturedefs.items()
                   if defs and defs[-1].scope in ("module", "package")
                   and defs[-1].baseid == path)
    return f"{path}:{'+'.join(names)}" if names else None


# --------------------------------------------------------------------------- fresh binaries
def pytest_configure(config):
    """No test runs a stale binary (tests/fw_fresh.py): the firmware_sim products the tests
    run are rebuilt here when older than their sources, once per session (in the xdist
    controller, before any worker starts)."""
    if hasattr(config, "workerinput") or os.environ.get("FFTUNE_TEST_NO_REBUILD") == "1":
        return          # (the C mutation harness: it links the binaries it tests itself)
    from fw_fresh import rebuild_stale
    try:
        config._fftune_rebuilt = rebuild_stale()
    except RuntimeError as exc:
        pytest.exit(f"conftest: {exc}", returncode=2)


def pytest_report_header(config):
    rebuilt = getattr(config, "_fftune_rebuilt", None)
    if rebuilt:
        return [f"firmware_sim: rebuilt {', '.join(rebuilt)} (older than their sources)"]
    return None


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    vm_items = [item for item in items if item.get_closest_marker("vm")]
    if vm_items:
        from vmguest import SharedGuestSession
        limit = SharedGuestSession(item.module for item in vm_items).timeout_s()
    for item in vm_items:
        item.add_marker(pytest.mark.xdist_group("qemu_guest"))
        if item.get_closest_marker("timeout") is None:
            # the first vm test's set-up runs the whole shared guest session
            item.add_marker(pytest.mark.timeout(limit))
    for item in items:
        if item.get_closest_marker("vm"):
            continue
        group = _GROUP_OF_MODULE.get(_module_name(item)) or _module_fixture_group(item)
        if group:
            item.add_marker(pytest.mark.xdist_group(group))
    # the guest session first (stable sort keeps the collection order otherwise)
    items.sort(key=lambda item: 0 if item.get_closest_marker("vm") else 1)


@pytest.fixture(scope="session")
def vm_session(request):
    """ONE qemu guest boot for the sections (``VM_SECTIONS``) of every VM test module
    of this run (tests/vmguest.py SharedGuestSession; docs/vm-testing.md)."""
    from vmguest import SharedGuestSession
    modules = []
    for item in request.session.items:
        if item.get_closest_marker("vm") and getattr(item, "module", None) is not None:
            modules.append(item.module)
    return SharedGuestSession(modules)
