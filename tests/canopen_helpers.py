"""Helpers of the CANopen conformance tests (tests/test_canopen_*.py)."""
import threading
import time

# issue 21: a drive that loses its host (heartbeat consumer 4 x the host's 100 ms) shows
# SWITCH ON DISABLED in its statusword TPDO within the consumer time + one TPDO event
# period (100 ms), + 50 ms for drive_sim, a process of a loaded host that steps when it is
# scheduled (501 ms was measured once at load 15; an MCU has no such slack)
HOST_LOST_CONSUMER_S = 0.4
HOST_LOST_BOUND_S = HOST_LOST_CONSUMER_S + 0.1 + 0.05


def wait_for(pred, timeout_s, poll_s=0.02):
    """True as soon as pred() is true, False after timeout_s."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(poll_s)
    return bool(pred())


def collect(net, cob_id):
    """Subscribe to a COB-ID; returns the list the frames (data bytes) are appended to."""
    got = []
    net.subscribe(cob_id, lambda can_id, data, ts: got.append(bytes(data)))
    return got


def enable_402(node):
    """Shutdown, switch on, enable operation by SDO; returns the statusword."""
    for cw in (0x06, 0x07, 0x0F):
        node.sdo[0x6040].raw = cw
    return node.sdo[0x6041].raw


def configure_sine_run(node, period=2048, settle=0, record=1, amplitude=0.5, cycles=1,
                       signals=0x07):
    node.sdo[0x6060].raw = -1          # runs start only in the excitation-run mode
    ex = node.sdo["Excitation"]
    ex["Kind"].raw = 1
    ex["Amplitude"].raw = amplitude
    ex["Offset"].raw = 0.0
    ex["Period length N"].raw = period
    ex["Sine cycles per period"].raw = cycles
    ex["Settle periods"].raw = settle
    ex["Record periods"].raw = record
    node.sdo["Recorder"]["Signal selection"].raw = signals


def start_long_run(node):
    """A run that settles for 1000 periods of 8192 samples: 53 min with drive_sim --realtime
    (free-run may finish it in half a second), so mark the test drive_sim_args("--realtime")."""
    configure_sine_run(node, period=8192, settle=1000, record=1, signals=0x01)
    node.sdo["Run control"]["Command"].raw = 1


def run_to_done(node, timeout_s=30.0):
    node.sdo["Run control"]["Command"].raw = 1
    ok = wait_for(lambda: node.sdo["Run control"]["State"].raw not in (1, 2), timeout_s, 0.01)
    assert ok, "run did not finish"
    return node.sdo["Run control"]["State"].raw


_OD_CACHE = {}


def parsed_eds(path, node_id):
    """The EDS as a python-canopen ObjectDictionary, parsed once per (file, node id) and
    test process: parsing takes 0.1 s here and 1-2 s in the qemu guest, once per test.
    The clients only read the dictionary (types, names, defaults), so tests can share it."""
    import canopen
    import os
    key = (os.path.abspath(path), os.path.getmtime(path), int(node_id))
    if key not in _OD_CACHE:
        _OD_CACHE[key] = canopen.import_od(path, node_id)
    return _OD_CACHE[key]


def sdo_response_timeout_s(drive_sim):
    """The SDO answer wait of a test client on ``drive_sim``'s transport (see attach_node)."""
    return 0.8 if drive_sim.transport == "socketcan" else 2.0


def attach_node(drive_sim, node_class=None):
    """(network, node): a python-canopen node of ``node_class`` (default RemoteNode) for
    drive_sim with the generated EDS, on a fresh network. The caller disconnects it."""
    import canopen
    net = drive_sim.network()
    node = (node_class or canopen.RemoteNode)(drive_sim.node_id,
                                              parsed_eds(drive_sim.eds, drive_sim.node_id))
    # python-canopen waits 0.3 s for an SDO answer and does not retry: on a loaded 2-core CI
    # machine its own receive thread can miss that; the node itself answers in < 1 ms.
    # On SocketCAN (vcan in the guest, where a full socket buffer can drop a frame) below
    # drive_sim's 1 s SDO server timeout, so that a lost block segment is still recovered
    # by the client's retransmission request. socketcand is TCP and loses nothing: there
    # the host's own default (2 s), because 0.8 s was once missed at load 3 in CI.
    node.sdo.RESPONSE_TIMEOUT = sdo_response_timeout_s(drive_sim)
    net.add_node(node)
    return net, node


class HostHeartbeat:
    """A host's heartbeat (NMT state 5) every ``period_s`` from a thread, until stop()
    (python-can's send_periodic needs CAN_BCM, which the qemu guest's kernel lacks).
    A test that must keep a drive's consumer fed across slow SDO traffic uses this, not
    hand-sent heartbeats between requests: in the guest on a loaded machine a few SDO
    writes took more than a second."""

    def __init__(self, net, node_id, period_s=0.05):
        self.net, self.node_id, self.period_s = net, node_id, period_s
        self.stopped = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True, name="host-heartbeat")
        self.thread.start()

    def _run(self):
        self.net.send_message(0x700 + self.node_id, [5])
        while not self.stopped.wait(self.period_s):
            self.net.send_message(0x700 + self.node_id, [5])

    def stop(self):
        self.stopped.set()
        self.thread.join()
